"""What a step of the Kalman family says when it did not do its work, or did it on data
or a covariance that cannot be trusted: the statuses
:class:`~estim.estimators.kalman.fused.FusedKalman` reports beyond the chi-square test
(docs/failures.md, "What estim promises when data go wrong")."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from estim.estimators.kalman.fused import FusedKalman

__all__ = ["BLOWN_UP", "HUGE_MEASUREMENT", "blown_up", "overflowing", "record_statuses", "reported",
           "state_trace", "unconverged"]

#: a covariance whose trace exceeds this many times the larger of the traces of ``P0`` and
#: ``Q`` makes a step ``"suspect"``: the filter has lost the state (an absorbed outlier
#: that threw the estimate where the model's Jacobians explode), even when its NIS, on
#: that huge covariance, looks fine
BLOWN_UP = 1e8
#: a measurement beyond this magnitude overflows the update's squares (a failed update
#: then says so, rather than blaming the output function)
HUGE_MEASUREMENT = 1e150


def blown_up(trace: float) -> str:
    """The status of a step whose covariance blew up (see :data:`BLOWN_UP`)."""
    return (f"suspect: the covariance blew up (trace {trace:.3g}, over {BLOWN_UP:g} times "
            f"the larger of P0's and Q's): the filter has lost the state")


def unconverged(est: Any) -> str:
    """The status of a step whose damped iterated update did not converge."""
    return (f"suspect: the damped iterated update ({est.damping}) did not converge in "
            f"{est.iterations} iterations (its next step is beyond {est.tol:g} posterior sd); "
            f"kept the last iterate")


def overflowing(model: Any, y: np.ndarray) -> str:
    """What a failed update says when the measurement itself is absurd (beyond
    :data:`HUGE_MEASUREMENT`: its squares overflow), else empty."""
    huge = np.flatnonzero(np.abs(np.nan_to_num(y)) > HUGE_MEASUREMENT)
    if not huge.size:
        return ""
    return ("non-finite update: the measurement " + ", ".join(
        f"{model.output_names[i]} = {y[i]:.3g}" for i in huge) +
        " overflows the update (an absurd value: check the data)")


def record_statuses(est: FusedKalman, F: np.ndarray, P: np.ndarray
                    ) -> tuple[dict[int, str], np.ndarray]:
    """The statuses that are not ``"ok"`` of a record's steps, ``{sample: status}``, as
    :meth:`~estim.estimators.kalman.fused.FusedKalman.step` reports them, from the flags
    ``F (T, NFLAGS)`` and covariances ``P (T, n, n)`` of the compiled scan, and which steps
    leave the filter untrusted ``(T,)``."""
    suspect = (F[:, 6] + F[:, 7]) > 0
    if est.damping is not None:  # a damped iterated update that did not converge
        suspect |= F[:, 8] == 0
    with np.errstate(invalid="ignore"):  # (inf - inf in a blown-up covariance)
        traces = np.trace(P, axis1=1, axis2=2)
    blown = ~suspect & (traces > est._blown)
    out = {int(k): est._consistency(float(F[k, 0]), int(F[k, 4]), bool(F[k, 7]),
                                    bool(F[k, 8]))
           for k in np.flatnonzero(suspect)}
    out.update({int(k): blown_up(float(traces[k])) for k in np.flatnonzero(blown)})
    return out, suspect | blown


def state_trace(s: np.ndarray, nx: int, stride: int, sqrt: bool) -> float:
    r"""The trace of the covariance in a filter state ``s = [x; vec(P)]``: the sum of its
    diagonal (every ``stride``-th entry after ``nx``), or with ``sqrt`` of the squares
    of its factor's entries (:math:`\operatorname{tr} S S^\top = \|S\|_F^2`), inf
    rather than an overflow warning for a factor beyond 1e154."""
    if sqrt:
        part = s[nx:]
        with np.errstate(over="ignore", invalid="ignore"):
            return float(part @ part)
    return sum(s[nx::stride].tolist())  # (a handful of numbers: faster than numpy's sum)


def reported(P: np.ndarray, sqrt: bool) -> np.ndarray:
    """The covariance(s) a filter reports from its stored ``P`` (a copy), or ``S S^T`` of
    its factor(s) ``(..., n, n)`` with ``sqrt``: inf rather than an overflow warning for
    a factor that blew up."""
    if not sqrt:
        return P.copy()
    with np.errstate(over="ignore", invalid="ignore"):
        return P @ np.swapaxes(P, -1, -2)
