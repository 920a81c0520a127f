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

``adapt="sage-husa"`` is the classical baseline (Sage & Husa 1969), a fading-memory mean
of the innovations' outer products less their predicted part,

.. math::
    \hat R_k = (1 - d_k) \hat R_{k-1} + d_k (e_k e_k^\top - H \bar P_k H^\top), \qquad
    d_k = \frac{1 - b}{1 - b^{j+1}}

(:math:`b` the forgetting, :math:`j` the updates so far; :math:`d_k = 1/(j+1)` without
forgetting), after the Kalman update with :math:`\hat R_{k-1}`. Its known failure is the
loss of definiteness (the subtraction); guarded: a candidate that is not positive definite
is replaced by :math:`(1 - d_k)\hat R_{k-1} + d_k e_k e_k^\top`, and if that is not
either, :math:`\hat R_{k-1}` is kept. Its statistics ``[j; vec R]`` start at the filter's
``R`` (which the first update replaces: :math:`d_0 = 1`).

``adapt="QR"`` learns the process noise too (Huang, Zhang, Wu, Li & Chambers 2018): the
predicted covariance is itself uncertain, :math:`\bar P_k \sim \mathrm{IW}(n + \tau + 1,
\tau \tilde P_k)` about the nominal :math:`\tilde P_k = A P_{k-1} A^\top + Q` (:math:`\tau`
= :data:`TAU`), and each iteration updates both inverse Wisharts: :math:`T_k = \tau \tilde
P_k + P^{(i)} + (x^{(i)} - \bar x)(x^{(i)} - \bar x)^\top`, :math:`\bar P^{(i+1)} =
T_k / (\tau + 1)` (:math:`t_k = n + \tau + 2`), and :math:`U_k` as :math:`V_k` above; the Kalman
update then uses :math:`\bar P^{(i+1)}` and :math:`\hat R`. The process noise it implies,
:math:`\hat Q_k = Q + \bar P^{(N)} - \tilde P_k`, is reported beside :math:`\hat R`.

References
----------
Y. Huang, Y. Zhang, Z. Wu, N. Li, J. Chambers, "A novel adaptive Kalman filter with
inaccurate process and measurement noise covariance matrices", IEEE TAC 63(2), 2018;
A. P. Sage, G. W. Husa, "Adaptive filtering with unknown prior statistics", Proc. JACC
1969; S. Särkkä, A. Nummenmaa, "Recursive noise adaptive Kalman filtering by variational Bayesian
approximations", IEEE TAC 54(3), 2009; S. Särkkä, J. Hartikainen, "Non-linear noise
adaptive Kalman filtering via variational Bayes", IEEE MLSP 2013.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from estim._validate import as_choice, as_float
from estim.estimators.kalman.heavy_tails import (
    ITERATIONS,
    gain_update,
    roth_update,
    student_t_update,
)
from estim.solvers.kalman.triangular import checked_cholesky

__all__ = ["ADAPTS", "DEFINITE", "PRIOR_WEIGHT", "adapted", "check_adapt", "noise_update",
           "predicted_statistics", "sqrt_noise", "start_parts", "start_statistics"]

#: What the filters adapt: the measurement noise covariance, by variational Bayes or by
#: Sage and Husa's fading-memory estimate, or both noise covariances by variational Bayes.
ADAPTS = ("R", "sage-husa", "QR")
#: The prior weight :math:`\tau` of the predicted covariance in ``adapt="QR"`` (Huang et
#: al. 2018: 3).
TAU = 3.0
#: The smallest Cholesky pivot, relative to the largest variance, of a Sage-Husa estimate
#: taken as positive definite.
DEFINITE = 1e-10
#: The weight (:math:`\nu_0 - d - 1`, in samples) of the start :math:`\hat R = R` without
#: forgetting (``forgetting=1``).
PRIOR_WEIGHT = 20.0


def check_adapt(adapt: object, forgetting: object, est: Any) -> tuple[str | None, float, int]:
    """``(adapt, forgetting, size of the statistics in the filter state)`` of the filter
    ``est`` checked: ``forgetting`` in (0, 1]; the adaptive filter on vector states,
    without the iterated update or a Student-t noise (``"QR"`` in the covariance form)."""
    rho = as_float(forgetting, "forgetting")
    if not 0 < rho <= 1:
        raise ValueError(f"forgetting must be in (0, 1] (1: no forgetting, R constant), got "
                         f"{forgetting!r}")
    if adapt is None:
        return None, rho, 0
    adapt = as_choice(adapt, ADAPTS, "adapt")
    if not est.model.manifold.trivial or est.iterations > 1 or est.dof is not None \
            or (adapt == "QR" and est._sqrt):
        raise ValueError(f"adapt={adapt!r} is built in the {est.name.upper()} on vector "
                         f"states, with iterations=1 and a Gaussian noise"
                         + (" (and adapt='QR' in the covariance form)" if est._sqrt else ""))
    ny, nx = est.model.ny, est.model.nx
    return adapt, rho, 1 + ny * ny + (nx * nx if adapt == "QR" else 0)


def start_statistics(est: Any) -> np.ndarray:
    r"""``[nu_0; vec V_0]``: :math:`\hat R = R` with the weight of the forgetting's window
    (nothing for a filter that does not adapt)."""
    if not est._n_adapt:
        return np.zeros(0)
    first, scale = start_parts(est)
    Q = [est.Q.ravel(order="F")] if est.adapt == "QR" else []
    return np.concatenate([[first], (scale * est.R).ravel(order="F"), *Q])


def start_parts(est: Any) -> tuple[float, float]:
    """The statistics' start as ``(first entry, the factor of R)``: ``(nu_0, weight)``, or
    Sage-Husa's ``(0, 1)``."""
    if est.adapt == "sage-husa":
        return 0.0, 1.0
    weight = 1.0 / (1.0 - est.forgetting) if est.forgetting < 1 else PRIOR_WEIGHT
    return weight + est.model.ny + 1.0, weight


def predicted_statistics(est: Any, a: Any) -> Any:
    """The statistics ``[nu; vec V]`` after the forgetting's prediction (Sage-Husa's
    unchanged)."""
    if est.adapt == "sage-husa":
        return a
    d, rho = est.model.ny, est.forgetting
    return ca.vertcat(rho * (a[0] - d - 1) + d + 1, rho * a[1:1 + d * d], a[1 + d * d:])


def noise_update(est: Any, xb: Any, Pb: Any, e: Any, Pxz: Any, Pzz: Any, Q: Any, R: Any,
                 mask: Any, a: Any) -> tuple[Any, Any, Any, Any, Any]:
    r"""The update of a Student-t or adaptive filter ``est`` from the prediction ``(xb,
    Pb)``, the innovation ``e``, the linearisation's ``Pxz``, ``Pzz``, the nominal ``Q``
    and the predicted statistics ``a`` (empty without adaptation): ``(x_hat, P_hat, S,
    a_new, R_used)``, ``R_used`` the measurement noise covariance of the final update."""
    if est.noise == "student-t-roth":
        xh, Ph, S = roth_update(xb, Pb, e, Pxz, Pzz, R, mask, est.dof)
        return xh, Ph, S, a, R
    if est.dof is not None:
        xh, Ph, S, lam = student_t_update(xb, Pb, e, Pxz, Pzz, R, mask, est.dof)
        return xh, Ph, S, a, R / lam
    if est.adapt == "sage-husa":
        return _sage_husa(est, xb, Pb, e, Pxz, Pzz, mask, a)
    d = est.model.ny
    D, E = ca.diag(mask), ca.diag(1 - mask)
    every = ca.sum1(mask) == d  # an inverse Wishart takes whole vectors
    nu = ca.if_else(every, a[0] + 1, a[0])
    V0 = ca.reshape(a[1:1 + d * d], d, d)
    H = ca.solve(Pb, Pxz).T  # P_xz^T Pb^-1 (the EKF's C)
    Omega = Pzz - H @ Pb @ H.T
    V, Pbar = V0, Pb  # (with adapt="QR" the predicted covariance learnt too)
    xh, Ph, S = xb, Pb, Pzz + E
    qr = est.adapt == "QR"  # (Huang et al.: both noises from the current posterior first)
    for i in range(ITERATIONS):
        if qr or i:  # the statistics from the current posterior (x^(i), P^(i))
            r = e - H @ (xh - xb)
            Vn = V0 + r @ r.T + H @ Ph @ H.T + Omega
            V = ca.if_else(every, 0.5 * (Vn + Vn.T), V0)
        if qr:  # T_k / (t_k - n - 1), t_k - n - 1 = tau + 1
            dx = xh - xb
            Pn = (TAU * Pb + Ph + dx @ dx.T) / (TAU + 1)
            Pbar = ca.if_else(every, 0.5 * (Pn + Pn.T), Pb)
        Rh = V / (nu - d - 1)
        xh, Ph, S = gain_update(xb, Pbar, e, Pbar @ H.T, H @ Pbar @ H.T + Omega + D @ Rh @ D + E)
    if not qr:  # Sarkka & Hartikainen's statistics from the final posterior
        r = e - H @ (xh - xb)
        Vn = V0 + r @ r.T + H @ Ph @ H.T + Omega
        V = ca.if_else(every, 0.5 * (Vn + Vn.T), V0)
    Qh = [ca.vec(Q + Pbar - Pb)] if qr else []
    return xh, Ph, S, ca.vertcat(nu, ca.vec(V), *Qh), Rh


def sqrt_noise(est: Any, s: Any, predict: bool, xb: Any, Pxz: Any, Pzz: Any, Pb: Any,
               e: Any, LR: Any, mask: Any) -> tuple[Any, Any, Any]:
    r"""The square-root filters' Student-t or adaptive noise: ``(L, a_prior, a_new)``,
    ``L`` the lower factor of the measurement noise covariance of the final update (of
    :math:`R/\lambda`, or of the learnt :math:`\hat R`), which the filter's update then
    takes in place of :math:`L_R` (the scale and the statistics found from the
    covariances ``Pxz``, ``Pzz``, ``Pb`` of the factors; :func:`noise_update`), the
    statistics before and after (empty without adaptation)."""
    from estim.solvers.kalman.triangular import cholesky

    a_prior = s[est._nP:]
    if predict and est.adapt:
        a_prior = predicted_statistics(est, a_prior)
    R = LR @ LR.T
    _, _, _, a_new, R_used = noise_update(est, xb, Pb, e, Pxz, Pzz, ca.SX(0), R, mask,
                                          a_prior)
    return cholesky(0.5 * (R_used + R_used.T)), a_prior, a_new


def adapted(est: Any, a: np.ndarray) -> dict[str, np.ndarray]:
    r"""``{"R": R_hat}`` of the statistics ``a = [nu; vec V]`` (a stack ``(T, n)``: a stack of
    covariances): :math:`\hat R = V / (\nu - d - 1)`; nothing without adaptation."""
    if not est._n_adapt:
        return {}
    d, n = est.model.ny, est.model.nx
    a = np.asarray(a, dtype=float)
    V = a[..., 1:1 + d * d].reshape(a.shape[:-1] + (d, d)).swapaxes(-1, -2)
    out = {"R": V if est.adapt == "sage-husa" else V / (a[..., :1, None] - d - 1)}
    if est.adapt == "QR":
        out["Q"] = a[..., 1 + d * d:].reshape(a.shape[:-1] + (n, n)).swapaxes(-1, -2)
    return out


def _sage_husa(est: Any, xb: Any, Pb: Any, e: Any, Pxz: Any, Pzz: Any, mask: Any, a: Any
               ) -> tuple[Any, Any, Any, Any, Any]:
    """Sage and Husa's update (see the module): the Kalman update with the current
    estimate, then the estimate moved towards the innovation's, definiteness guarded."""
    d, b = est.model.ny, est.forgetting
    D, E = ca.diag(mask), ca.diag(1 - mask)
    j, Rh = a[0], ca.reshape(a[1:], d, d)
    xh, Ph, S = gain_update(xb, Pb, e, Pxz, Pzz + D @ Rh @ D + E)
    dk = 1 / (j + 1) if b == 1 else (1 - b) / (1 - b ** (j + 1))
    ee = e @ e.T
    first = (1 - dk) * Rh + dk * (ee - Pzz)
    second = (1 - dk) * Rh + dk * ee
    Rn = ca.if_else(checked_cholesky(first, DEFINITE)[1], first,
                    ca.if_else(checked_cholesky(second, DEFINITE)[1], second, Rh))
    every = ca.sum1(mask) == d  # (whole vectors only, as the variational filter)
    Rn = ca.if_else(every, 0.5 * (Rn + Rn.T), Rh)
    return xh, Ph, S, ca.vertcat(ca.if_else(every, j + 1, j), ca.vec(Rn)), Rh

