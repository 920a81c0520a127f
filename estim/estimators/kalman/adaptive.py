r"""Measurement noise learnt online: the variational Bayes adaptive filter
(``EKF/UKF(..., adapt="R", forgetting=rho)``), and the update the heavy-tailed and adaptive
filters share.

The measurement noise covariance :math:`R_k` is unknown and drifts. Its posterior is kept
as an inverse Wishart :math:`\mathrm{IW}(\nu_k, V_k)` (mean :math:`V_k / (\nu_k - d - 1)`,
:math:`d` outputs) beside the state's Gaussian, in the filter state after
:math:`[x; \operatorname{vec} P]`, and the joint posterior is approximated by the
variational Bayes product of the two (Särkkä & Hartikainen 2013, generalising the
diagonal form of Särkkä & Nummenmaa 2009):

* **prediction**, a forgetting factor :math:`\rho \in (0, 1]` that lets :math:`R` drift:
  :math:`\nu^-_k = \rho(\nu_{k-1} - d - 1) + d + 1`, :math:`V^-_k = \rho V_{k-1}` (the
  mean unchanged, its weight shrinking to an effective window of about
  :math:`1/(1-\rho)` samples);
* **update**, :math:`\nu_k = \nu^-_k + 1`, then :data:`ITERATIONS` fixed-point
  iterations of the Kalman update with :math:`\hat R = V_k / (\nu_k - d - 1)` and

  .. math::
      V_k = V^-_k + r r^\top + H \hat P H^\top + \Omega,

  :math:`r = e - H(\hat x - \bar x)` the posterior's residual, :math:`H` the output's
  Jacobian (EKF) or the sigma points' statistical linear regression (UKF, with its error
  covariance :math:`\Omega`).

A sample with an output missing updates the state with :math:`\hat R^-` on the measured
rows and leaves the statistics at their prediction (an inverse Wishart takes whole
vectors); over a long gap :math:`\hat R` stays where it was while its weight fades, so
the first measurements after the gap move it quickly. The statistics start at
:math:`\hat R = R` (the filter's ``R``) with the weight of the forgetting's window
(:math:`\nu_0 - d - 1 = 1/(1-\rho)`, at most :data:`PRIOR_WEIGHT` without forgetting).

References
----------
S. Särkkä, A. Nummenmaa, "Recursive noise adaptive Kalman filtering by variational Bayesian
approximations", IEEE TAC 54(3), 2009; S. Särkkä, J. Hartikainen, "Non-linear noise
adaptive Kalman filtering via variational Bayes", IEEE MLSP 2013.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from estim._validate import as_choice, as_float
from estim.estimators.kalman.heavy_tails import ITERATIONS, student_t_update

__all__ = ["ADAPTS", "PRIOR_WEIGHT", "adapted", "check_adapt", "noise_update",
           "predicted_statistics", "start_statistics"]

#: What the filters adapt: the measurement noise covariance.
ADAPTS = ("R",)
#: The weight (:math:`\nu_0 - d - 1`, in samples) of the start :math:`\hat R = R` without
#: forgetting (``forgetting=1``).
PRIOR_WEIGHT = 20.0


def check_adapt(adapt: object, forgetting: object, est: Any) -> tuple[str | None, float, int]:
    """``(adapt, forgetting, size of the statistics in the filter state)`` of the filter
    ``est`` checked: ``forgetting`` in (0, 1]; the adaptive filter in the covariance form
    on vector states, without the iterated update or a Student-t noise."""
    rho = as_float(forgetting, "forgetting")
    if not 0 < rho <= 1:
        raise ValueError(f"forgetting must be in (0, 1] (1: no forgetting, R constant), got "
                         f"{forgetting!r}")
    if adapt is None:
        return None, rho, 0
    adapt = as_choice(adapt, ADAPTS, "adapt")
    if est._sqrt or not est.model.manifold.trivial or est.iterations > 1 \
            or est.dof is not None:
        raise ValueError(f"adapt={adapt!r} is built in the {est.name.upper()}'s covariance "
                         f"form on vector states, with iterations=1 and a Gaussian noise")
    ny = est.model.ny
    return adapt, rho, 1 + ny * ny


def start_statistics(est: Any) -> np.ndarray:
    r"""``[nu_0; vec V_0]``: :math:`\hat R = R` with the weight of the forgetting's window
    (nothing for a filter that does not adapt)."""
    if not est._n_adapt:
        return np.zeros(0)
    d = est.model.ny
    weight = 1.0 / (1.0 - est.forgetting) if est.forgetting < 1 else PRIOR_WEIGHT
    return np.concatenate([[weight + d + 1.0], (weight * est.R).ravel(order="F")])


def predicted_statistics(est: Any, a: Any) -> Any:
    """The statistics ``[nu; vec V]`` after the forgetting's prediction."""
    d, rho = est.model.ny, est.forgetting
    return ca.vertcat(rho * (a[0] - d - 1) + d + 1, rho * a[1:])


def noise_update(est: Any, xb: Any, Pb: Any, e: Any, Pxz: Any, Pzz: Any, R: Any, mask: Any,
                 a: Any) -> tuple[Any, Any, Any, Any]:
    r"""The update of a Student-t or adaptive filter ``est`` from the prediction ``(xb,
    Pb)``, the innovation ``e``, the linearisation's ``Pxz``, ``Pzz`` and the predicted
    statistics ``a`` (empty without adaptation): ``(x_hat, P_hat, S, a_new)``."""
    if est.dof is not None:
        xh, Ph, S, _ = student_t_update(xb, Pb, e, Pxz, Pzz, R, mask, est.dof)
        return xh, Ph, S, a
    d = est.model.ny
    D, E = ca.diag(mask), ca.diag(1 - mask)
    every = ca.sum1(mask) == d  # an inverse Wishart takes whole vectors
    nu = ca.if_else(every, a[0] + 1, a[0])
    V0 = ca.reshape(a[1:], d, d)
    H = ca.solve(Pb, Pxz).T  # P_xz^T Pb^-1 (the EKF's C)
    Omega = Pzz - H @ Pb @ H.T
    V = V0
    xh, Ph, S = xb, Pb, Pzz + E
    for _ in range(ITERATIONS):
        Rh = V / (nu - d - 1)
        S = Pzz + D @ Rh @ D + E
        S = 0.5 * (S + S.T)
        K = ca.solve(S, Pxz.T).T
        xh = xb + K @ e
        Ph = Pb - K @ S @ K.T
        Ph = 0.5 * (Ph + Ph.T)
        r = e - H @ (xh - xb)
        Vn = V0 + r @ r.T + H @ Ph @ H.T + Omega
        V = ca.if_else(every, 0.5 * (Vn + Vn.T), V0)
    return xh, Ph, S, ca.vertcat(nu, ca.vec(V))


def adapted(est: Any, a: np.ndarray) -> dict[str, np.ndarray]:
    r"""``{"R": R_hat}`` of the statistics ``a = [nu; vec V]`` (a stack ``(T, n)``: a stack of
    covariances): :math:`\hat R = V / (\nu - d - 1)`; nothing without adaptation."""
    if not est._n_adapt:
        return {}
    d = est.model.ny
    a = np.asarray(a, dtype=float)
    V = a[..., 1:].reshape(a.shape[:-1] + (d, d)).swapaxes(-1, -2)
    return {"R": V / (a[..., :1, None] - d - 1)}
