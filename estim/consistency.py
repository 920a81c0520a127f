"""The chi-square consistency test every estimator reports in its status.

A Kalman filter's normalised innovation squared, and the weighted least-squares cost of
a moving horizon or full-information estimate, follow a chi-square distribution with
as many degrees of freedom as measured components when the model and the tuning are
right (Bar-Shalom, Li, Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, Wiley, 2001, sec. 5.4). A value beyond the :data:`SUSPECT_TAIL` tail of
that distribution makes the step ``"suspect"``.
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["SUSPECT_TAIL", "chi2_limit", "consistency_status"]


#: A step whose normalised innovation squared (filters) or weighted least-squares cost
#: (MHE, full information) lies beyond this tail probability of its chi-square
#: distribution is reported ``"suspect"``. At 1e-9 a consistent estimator raises a false
#: alarm about once in a billion steps; a 100-sigma outlier or a diverged estimate is far
#: beyond it.
SUSPECT_TAIL = 1e-9


@lru_cache(maxsize=4096)
def chi2_limit(dof: int, tail: float = SUSPECT_TAIL) -> float:
    """The value that a chi-square variable with ``dof`` degrees of freedom exceeds
    with probability ``tail`` (inf without any degree of freedom). Kept for the last
    4096 ``(dof, tail)`` asked: every step of an optimisation-based estimator asks."""
    from scipy.special import chdtri  # imported on first use, not with estim

    return float(chdtri(dof, tail)) if dof > 0 else float("inf")


def consistency_status(statistic: float, dof: int, what: str = "NIS") -> str:
    """``"ok"``, or ``"suspect: ..."`` when ``statistic`` is beyond :func:`chi2_limit`."""
    if statistic > chi2_limit(dof):
        return f"suspect: {what} {statistic:.3g} beyond the {SUSPECT_TAIL:g} tail of chi2({dof})"
    return "ok"
