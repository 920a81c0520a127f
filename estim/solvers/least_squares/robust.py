r"""Robust measurement costs for MHE and full-information estimation.

With a robust loss the measurement term of the cost,
:math:`\sum_k \|W_{y,k}(y_k - h(x_k))\|^2`, becomes
:math:`\sum_k \sum_i \rho(r_{k,i})` over the whitened residual components
:math:`r_{k,i} = [W_{y,k}(y_k - h(x_k))]_i` (units of their standard
deviation). Each :math:`\rho` equals :math:`r^2` for :math:`|r| \ll c`
(``f_scale``) and grows more slowly beyond:

========== ============================================= ==================================
loss       :math:`\rho(r)`                                weight :math:`w = \rho'(r) / 2r`
========== ============================================= ==================================
huber      :math:`r^2` if :math:`|r| \le c`, else         :math:`\min(1, c/|r|)`
           :math:`2c|r| - c^2`
soft_l1    :math:`2c^2(\sqrt{1 + (r/c)^2} - 1)`           :math:`1/\sqrt{1 + (r/c)^2}`
cauchy     :math:`c^2 \ln(1 + (r/c)^2)`                   :math:`1/(1 + (r/c)^2)`
student-t  :math:`(\nu + 1) \ln(1 + r^2/\nu)`             :math:`(\nu + 1)/(\nu + r^2)`
========== ============================================= ==================================

These are twice ``scipy.optimize.least_squares``'s ``loss`` functions with the
same ``f_scale`` (the factor of the sum-of-squares cost used throughout estim),
so both fit the same optimum. ``huber`` and ``soft_l1`` (a smooth L1) keep the
problem convex in the residuals; ``cauchy`` rejects gross outliers harder but
is not convex, so its optimum depends more on the start.

The cost is minimised by iteratively reweighted least squares (Holland &
Welsch 1977): at the current trajectory each component gets the weight
:math:`w(r)`, the weighted least-squares problem (rows of :math:`W_{y,k}`
scaled by :math:`\sqrt{w}`) is solved by the estimator's solver, and the
weights are recomputed at its solution until they settle. For these three
losses :math:`\rho(\sqrt s)` is concave in :math:`s`, so the weighted sum of
squares majorises the robust cost and touches it at the current trajectory:
each reweighted solve decreases the robust cost (a majorise-minimise method),
from the first one on. At a fixed point the gradient of the robust cost is
zero.

The default scales (``f_scale=None``) give 95 % efficiency on Gaussian
residuals: :math:`c = 1.345` (huber, soft_l1) and :math:`c = 2.385` (cauchy).

``student-t`` is not a tuned M-estimator but the noise model itself: twice the negative
log-density of Student's :math:`t` with :math:`\nu` degrees of freedom (``dof``) and scale
:math:`R`, so the robust fit is the MAP estimate under that noise (its IRLS weight, the
expectation-maximisation weight of the :math:`t` as a scale mixture, exceeds 1 near zero:
:math:`\rho \approx (\nu+1)/\nu\, r^2`); the measurement noise of the Student-t filters
(:mod:`estim.estimators.kalman.heavy_tails`).

References
----------
P. J. Huber (1981), *Robust Statistics*, Wiley;
P. W. Holland, R. E. Welsch (1977), "Robust regression using iteratively
reweighted least-squares", Commun. Stat. Theory Methods 6(9);
B. Triggs, P. F. McLauchlan, R. I. Hartley, A. W. Fitzgibbon (2000), "Bundle
adjustment: a modern synthesis", LNCS 1883 (section 3.3).
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from estim._validate import as_choice, as_float
from estim.consistency import SUSPECT_TAIL

#: A whitened measurement component beyond this many standard deviations is an
#: outlier for a robust loss: a Gaussian one goes beyond it with the probability
#: ``SUSPECT_TAIL`` of the consistency test (6.1 at 1e-9): the square root of the
#: chi-square(1) quantile, which is the normal one.
OUTLIER_SIGMA = -NormalDist().inv_cdf(SUSPECT_TAIL / 2)

#: The measurement losses: ``"squared"`` (least squares) and the robust ones.
LOSSES = ("squared", "huber", "soft_l1", "cauchy", "student-t")

#: ``f_scale`` for 95 % asymptotic efficiency on Gaussian residuals.
DEFAULT_SCALES = {"huber": 1.345, "soft_l1": 1.345, "cauchy": 2.385}


@dataclass(frozen=True)
class RobustLoss:
    """A robust loss :math:`\\rho` on whitened residuals, with its IRLS weight.

    Parameters
    ----------
    name : {"huber", "soft_l1", "cauchy", "student-t"}
    f_scale : float
        :math:`c`, where the loss leaves the quadratic, in standard deviations (for
        ``"student-t"``: the degrees of freedom :math:`\\nu`).
    """

    name: str
    f_scale: float

    def rho(self, r: np.ndarray) -> np.ndarray:
        """The cost of each residual component (equal to ``r**2`` near zero)."""
        c, a = self.f_scale, np.abs(r)
        if self.name == "student-t":
            return (c + 1) * np.log1p(a * a / c)
        if self.name == "huber":
            return np.where(a <= c, a * a, 2 * c * a - c * c)
        z = (a / c) ** 2
        if self.name == "soft_l1":
            return 2 * c * c * (np.sqrt(1 + z) - 1)
        return c * c * np.log1p(z)

    def weight(self, r: np.ndarray) -> np.ndarray:
        """The IRLS weight :math:`\\rho'(r) / 2r` of each component, in (0, 1] (to
        :math:`(\\nu+1)/\\nu` for ``"student-t"``)."""
        c, a = self.f_scale, np.abs(r)
        if self.name == "student-t":
            return (c + 1) / (c + a * a)
        if self.name == "huber":
            return np.minimum(1.0, c / np.maximum(a, c))
        z = (a / c) ** 2
        if self.name == "soft_l1":
            return 1 / np.sqrt(1 + z)
        return 1 / (1 + z)


def as_dof(dof: object) -> float:
    """Student's t degrees of freedom, checked: a finite number above 2 (a finite
    variance)."""
    nu = as_float(dof, "dof")
    if not nu > 2:
        raise ValueError(f"dof must be above 2 (Student's t has a finite variance only "
                         f"then), got {dof!r}")
    return nu


def as_loss(loss, f_scale, dof=None) -> RobustLoss | None:
    """Check ``loss``, ``f_scale`` and ``dof`` (the Student-t loss's degrees of freedom,
    above 2); None for least squares."""
    loss = as_choice(loss, LOSSES, "loss")
    f_scale = as_float(f_scale, "f_scale", positive=True, allow_none=True)
    if dof is None and loss == "student-t":
        raise TypeError("loss='student-t' needs dof= (its degrees of freedom, above 2)")
    if dof is not None and loss != "student-t":
        raise ValueError(f"dof is the Student-t loss's degrees of freedom; loss is {loss!r}: "
                         f"give loss='student-t' with it")
    if loss == "student-t":
        if f_scale is not None:
            raise ValueError("f_scale applies to 'huber', 'soft_l1' and 'cauchy'; the "
                             "Student-t loss's scale is R itself (give dof)")
        return RobustLoss(loss, as_dof(dof))
    if loss == "squared":
        if f_scale is not None:
            raise ValueError("f_scale applies to a robust loss ('huber', 'soft_l1', "
                             "'cauchy'); loss is 'squared'")
        return None
    return RobustLoss(loss, DEFAULT_SCALES[loss] if f_scale is None else f_scale)
