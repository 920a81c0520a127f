r"""The fused filters with a continuous-time process noise (``Qc=``): the continuous-discrete
EKF and UKF, whose prediction integrates the mean and the covariance over each interval
(:func:`~estim.solvers.kalman.continuous.moment_step`,
:func:`~estim.solvers.kalman.continuous.sigma_moment_step`), so that the noise a transition
receives is that of its interval, as long or as short as the time stamps make it.

The tuning's ``Q`` slot holds :math:`W = L Q_c L^\top` (``L`` the model's ``noise_input``),
the spectral density the moment equations add, so the fused step, its whole-record scan, the
batched seeds of :func:`~estim.compare` and ``jit=True`` carry it as they carry a
per-transition ``Q``.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_int
from estim.solvers.kalman.continuous import (
    drift_jacobian,
    interval,
    moment_step,
    noise_density,
    sigma_moment_step,
    van_loan,
)

__all__ = ["continuous_noise", "ekf_moments", "ekf_prediction", "sigma_moments",
           "smoother_prediction", "ukf_prediction", "unscented_smoother_prediction"]

#: Runge-Kutta sub-steps of the moment equations per interval, by default.
SUBSTEPS = 4
#: How the continuous-discrete EKF carries the covariance over an interval.
DISCRETISATIONS = ("moments", "van-loan")


def continuous_noise(model: Any, Q: ArrayLike | None, Qc: ArrayLike | None,
                     substeps: object) -> tuple[Any, np.ndarray | None, int]:
    """``(the Q the estimator stores, Qc, substeps)``: ``Q`` itself, or with ``Qc`` the
    density :math:`W = L Q_c L^\\top` it enters the states with; checked (exactly one of
    the two, ``Qc`` on a continuous vector model; see
    :func:`~estim.solvers.kalman.continuous.noise_density`)."""
    substeps = as_int(substeps, "substeps", minimum=1)
    Q, Qc = noise_density(model, Q, Qc)
    return Q, Qc, substeps


def ekf_prediction(est: Any, x: Any, P: Any, w: Any, p: Any, W: Any) -> tuple[Any, Any]:
    r"""The continuous-discrete EKF's prediction of ``(x, P)`` over the interval of ``w``:
    :math:`\dot m = f(m)`, :math:`\dot P = A P + P A^\top + W` by ``est.substeps`` Runge-Kutta
    steps; or with ``est.discretisation == "van-loan"`` the mean by the model's ``F`` and
    the covariance by the exact discretisation of the linearisation at ``x`` (the input at
    the interval's start), :math:`\bar P = \Phi P \Phi^\top + Q_d(\Delta t)`
    (:func:`~estim.solvers.kalman.continuous.van_loan`: exact on a linear model)."""
    m = est.model
    u_of, h = interval(m, w)
    jac = drift_jacobian(m)
    if getattr(est, "discretisation", "moments") == "van-loan":
        from estim._discretise import input_at

        Phi, Qd = van_loan(jac(x, input_at(u_of, 0.0), p), W, h)
        Pb = Phi @ P @ Phi.T + Qd
        return m.F(x, w, p), 0.5 * (Pb + Pb.T)
    return moment_step(m.f_c, jac, x, P, u_of, p, W, h, est.substeps)


def ukf_prediction(est: Any, x: Any, P: Any, w: Any, p: Any, W: Any) -> tuple[Any, Any, Any]:
    r"""The continuous-discrete UKF's prediction (Särkkä 2007): the sigma-point moment
    equations with ``est``'s rule, the points drawn at every Runge-Kutta stage; and whether
    every stage's covariance was positive definite."""
    m = est.model
    u_of, h = interval(m, w)
    return sigma_moment_step(m.f_c, est._sigma_points, est._Wm, est._Wc, x, P, u_of, p, W,
                             h, est.substeps)


def _mapped_moments(est: Any, prediction, jacobian: bool = True) -> Any:
    """``(X (k, n), P (k, n, n), Wt (k, nw)) -> (x_bar, P_bar, Phi)`` over ``k`` transitions
    at once: ``prediction(est, x, P, w, p, W)``'s mean and covariance (symmetrised) and, with
    ``jacobian``, the Jacobian of the mean by the state (else None), one mapped call."""
    m = est.model
    n = m.nx
    x, w = ca.SX.sym("x", n), ca.SX.sym("w", m.nw)
    Ps, Ws = ca.SX.sym("P", n, n), ca.SX.sym("W", n, n)
    xb, Pb = prediction(est, x, Ps, w, ca.DM(m.p), Ws)[:2]
    outs = [xb, ca.vec(Pb)] + ([ca.vec(ca.jacobian(xb, x))] if jacobian else [])
    fun = ca.Function("cd_predict", [x, ca.vec(Ps), w, ca.vec(Ws)], outs)
    Wq = est.Q.ravel(order="F")

    def moments(X, P, Wt):
        k = len(X)
        out = fun.map(k)(X.T, P.transpose(0, 2, 1).reshape(k, n * n).T, Wt.T,
                         np.repeat(Wq[:, None], k, axis=1))
        Pb, *Phi = (np.asarray(o).T.reshape(k, n, n).transpose(0, 2, 1) for o in out[1:])
        return (np.asarray(out[0]).T, 0.5 * (Pb + Pb.transpose(0, 2, 1)),
                Phi[0] if Phi else None)

    return moments


def smoother_prediction(est: Any):
    r"""The continuous-discrete extended smoother's predictions of every transition at once:
    ``(X, P, Wt) -> (x_bar, P_bar, D)``, :math:`(\bar x, \bar P)` from the moment equations
    and :math:`D = P_k \Phi_k^\top`, :math:`\Phi_k` the Jacobian of the mean's flow over the
    interval (Särkkä & Svensson 2023, sec. 10.6)."""
    moments = ekf_moments(est)

    def predict(X, P, Wt):
        xb, Pb, Phi = moments(X, P, Wt)
        return xb, Pb, P @ Phi.transpose(0, 2, 1)

    return predict


def ekf_moments(est: Any):
    """``(X, P, Wt) -> (x_bar, P_bar, Phi)``: the continuous-discrete EKF's predictions of
    every transition at once (:func:`ekf_prediction`) and the Jacobians of their means by
    the state, one mapped call."""
    return _mapped_moments(est, ekf_prediction)


def sigma_moments(est: Any):
    """``(X, P, Wt) -> (x_bar, P_bar, None)``: the sigma-point moment equations of every
    transition at once (:func:`ukf_prediction`, one mapped call)."""
    return _mapped_moments(est, ukf_prediction, jacobian=False)


def unscented_smoother_prediction(est: Any):
    r"""The continuous-discrete unscented smoother's predictions of every transition:
    ``(X, P, Wt) -> (x_bar, P_bar, D)``, :math:`(\bar x, \bar P)` from the sigma-point
    moment equations and the cross-covariance
    :math:`D = \sum_i W^c_i (\mathcal X_i - \hat x_k)(\varphi(\mathcal X_i) - \bar\varphi)^\top`
    of the filter's sigma points through the noise-free flow :math:`\varphi` (the model's
    ``F``: the noise over the interval is independent of :math:`x_k`; exact on a linear
    model, where the smoother is the RTS smoother of the exact discretisation)."""
    from estim.solvers.kalman.rts import transitions

    m = est.model
    moments = sigma_moments(est)

    def predict(X, P, Wt):
        k, ns, n = len(X), len(est._Wm), m.nx
        xb, Pb, _ = moments(X, P, Wt)
        sig = est.sigma_points(X, P)  # (k, ns, n)
        Fs = transitions(m, sig.reshape(k * ns, n), np.repeat(Wt, ns, axis=0)
                         ).reshape(k, ns, n)
        fbar = np.einsum("i,kij->kj", est._Wm, Fs)
        D = np.einsum("i,kia,kib->kab", est._Wc, sig - X[:, None, :], Fs - fbar[:, None, :])
        return xb, Pb, D

    return predict
