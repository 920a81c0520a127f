r"""The EKF's and the UKF's steps on a state with quaternions and angles.

The error of an estimate lives in the tangent space of the state's manifold
(:mod:`estim._manifold`): :math:`x = \hat x \oplus \delta`, :math:`\delta \sim
N(0, P)`, ``P`` of size ``ndx``. The multiplicative EKF (Markley's MEKF for a
quaternion, :math:`q = \hat q \otimes \exp(\delta\theta/2)`) predicts

.. math::
    \bar x = F(\hat x, u), \qquad \bar P = A P A^\top + Q, \quad
    A = \frac{\partial}{\partial \delta}\Big[F(\hat x \oplus \delta, u) \ominus \bar x
    \Big]_{\delta = 0},

and updates with :math:`C = \partial h(\bar x \oplus \delta) / \partial\delta` at 0 and
the innovation :math:`e = y \ominus h(\bar x)` (output angles wrapped),

.. math::
    K = \bar P C^\top S^{-1}, \quad \hat\delta = K e, \quad
    \hat x = \bar x \oplus \hat\delta, \quad
    P = J \big[(I - KC)\bar P(I - KC)^\top + K R K^\top\big] J^\top,

where the reset Jacobian :math:`J = \partial [(\bar x \oplus (\hat\delta + \epsilon))
\ominus \hat x] / \partial \epsilon` at 0 carries the error covariance from the prior
to the updated estimate (for a quaternion the right Jacobian of SO(3) at
:math:`\hat\delta\theta`, :math:`I - \tfrac12[\hat\delta\theta\times] + \dots`;
the identity on vector and angle states). Every Jacobian is CasADi's algorithmic
derivative. The UKF (USQUE-style, Crassidis & Markley 2003) draws its sigma points in
the tangent space, :math:`\mathcal X_i = \bar x \oplus \sigma_i`, takes means as
tangent vectors about the propagated centre and covariances of those vectors, and
resets its covariance as the EKF does.

References
----------
F. L. Markley, J. L. Crassidis, *Fundamentals of Spacecraft Attitude Determination and
Control*, Springer 2014, sec. 6.2; J. L. Crassidis, F. L. Markley, "Unscented
filtering for spacecraft attitude estimation", J. Guid. Control Dyn. 26(4), 2003;
M. Brossard, S. Bonnabel, A. Barrau, "Unscented Kalman filter on Lie groups", 2020.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from estim.solvers.kalman.kalman import ekf_checks

__all__ = ["check_manifold_options", "mekf_step", "output_jacobian", "refuse_manifold",
           "retracted", "sigma_offsets", "tangent_jacobian", "tangent_offsets",
           "tangent_transition_jacobian",
           "transition_jacobian", "unit_bounds", "unscented_innovation", "usque_step"]


def check_manifold_options(model: Any, form: str, clip: bool, lower: Any, upper: Any
                           ) -> None:
    """Refuse clipping with bounds on a quaternion component or an angle
    (:func:`unit_bounds`; the other states are clipped as on vector states)."""
    if model.manifold.trivial:
        return
    if clip:
        unit_bounds(model, lower, upper)


def unit_bounds(model: Any, lower: Any, upper: Any) -> None:
    """A ``ValueError`` for bounds on a quaternion component (a unit quaternion is
    bounded by its norm; its steps are rotations) or on an angle (it wraps)."""
    M = model.manifold
    at = [i for g in M.quaternions for i in g] + list(M.angles)
    bounded = [model.state_names[i] for i in at
               if np.isfinite(lower[i]) or np.isfinite(upper[i])]
    if bounded:
        raise ValueError(f"lower/upper: {bounded} are quaternion components or angles of "
                         f"{model.name}, which cannot be bounded; bound the other states")


def refuse_manifold(model: Any, what: str) -> None:
    """A ``ValueError`` when ``model`` declares quaternions or angles, which ``what``
    does not handle yet."""
    if not model.manifold.trivial:
        raise ValueError(f"{what} does not handle the quaternions and angles of "
                         f"{model.name} yet")


def tangent_jacobian(fun: Any, n: int) -> Any:
    """``d fun(d) / d d`` at ``d = 0`` for an expression builder ``fun`` of a tangent
    vector of size ``n``."""
    d = ca.SX.sym("d", n)
    return ca.substitute(ca.jacobian(fun(d), d), d, ca.DM.zeros(n))


def transition_jacobian(model: Any, x: Any, u: Any, p: Any, xn: Any = None) -> Any:
    r"""The transition's Jacobian: :math:`\partial F / \partial x`, on a manifold
    :math:`\partial [F(x \oplus \delta) \ominus F(x)] / \partial \delta` at 0
    (ndx x ndx); ``xn`` is :math:`F(x)` if already built."""
    M = model.manifold
    if M.euclidean_states:
        return model.F_x(x, u, p)
    xn = model.F(x, u, p) if xn is None else xn
    return tangent_jacobian(lambda d: M.local(xn, model.F(M.retract(x, d), u, p)),
                            model.ndx)


def output_jacobian(model: Any, x: Any, uy: Any, p: Any) -> Any:
    r"""The output's Jacobian: :math:`\partial h / \partial x`, on a manifold
    :math:`\partial h(x \oplus \delta) / \partial \delta` at 0 (ny x ndx)."""
    M = model.manifold
    if M.euclidean_states:
        return model.H_x(x, uy, p)
    return tangent_jacobian(lambda d: model.H(M.retract(x, d), uy, p), model.ndx)


def retracted(M: Any, xb: Any, delta: Any) -> tuple[Any, Any]:
    r"""The update :math:`\hat x = \bar x \oplus \delta` and its reset Jacobian
    :math:`J = \partial [(\bar x \oplus (\delta + \epsilon)) \ominus \hat x] /
    \partial \epsilon` at 0, which carries a covariance of the prediction's tangent
    space to the estimate's (see the module)."""
    xh = M.retract(xb, delta)
    return xh, tangent_jacobian(lambda d: M.local(xh, M.retract(xb, delta + d)),
                                delta.numel())


def tangent_transition_jacobian(model: Any) -> ca.Function:
    """``A(x, w, p)``: :func:`transition_jacobian` as a Function (ndx x ndx)."""
    x, w = ca.SX.sym("x", model.nx), ca.SX.sym("w", model.nw)
    p = ca.SX.sym("p", model.F.size1_in(2))
    return ca.Function("A_tangent", [x, w, p], [transition_jacobian(model, x, w, p)])


def _updated(est: Any, xb: Any, Pb: Any, delta: Any, P_update: Any, e: Any, S: Any
             ) -> tuple[Any, Any, Any, Any]:
    """``(s_new, s_prior, nis, P)`` after an update by the tangent step ``delta`` of the
    prediction ``(xb, Pb)``: the retraction (clipped on the vector states' bounds with
    ``est.clip``), and the update's covariance ``P_update`` carried to the new estimate
    by the reset Jacobian (see the module)."""
    xh, J = retracted(est.model.manifold, xb, delta)
    Ph = J @ P_update @ J.T
    Ph = 0.5 * (Ph + Ph.T)
    if est.clip:  # (quaternions and angles have no bounds: unit_bounds)
        xh = ca.fmin(ca.fmax(xh, ca.DM(est.lower)), ca.DM(est.upper))
    return (ca.vertcat(xh, ca.vec(Ph)), ca.vertcat(xb, ca.vec(Pb)),
            ca.dot(e, ca.solve(S, e)), Ph)


def mekf_step(est: Any, predict: bool) -> ca.Function:
    """The multiplicative EKF's fused step (see the module), with the flags of
    :func:`estim.solvers.kalman.kalman.fused_function`."""
    m = est.model
    M, nd = m.manifold, m.ndx
    s, x, P, u, y, tun, Q, R, p, mask, y_inf = est._symbols()
    if predict:
        xb = m.F(x, u, p)
        A = transition_jacobian(m, x, u, p, xb)
        Pb = A @ P @ A.T + Q
    else:
        xb, Pb = x, P
    D = ca.diag(mask)
    uy = m.measurement_input(u)  # the input at this measurement
    C = D @ output_jacobian(m, xb, uy, p)
    e = ca.if_else(mask, M.output_difference(y, m.H(xb, uy, p)), 0)
    Rm = D @ R @ D + ca.diag(1 - mask)
    S = C @ Pb @ C.T + Rm
    S = 0.5 * (S + S.T)
    K = ca.solve(S, C @ Pb).T
    IKC = ca.DM.eye(nd) - K @ C
    s_new, s_prior, nis, Ph = _updated(est, xb, Pb, K @ e,
                                       IKC @ Pb @ IKC.T + K @ Rm @ K.T, e, S)
    ok, ok_mean, ok_prior = ekf_checks(s_new, nis, Ph, xb, Pb)
    name = "mekf_predict_update" if predict else "mekf_update"
    return est._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                               ok_mean, mask, s_prior)


def _weighted(weights: Any, vs: list) -> Any:
    """The weighted sum of the expressions ``vs``."""
    return sum((float(w) * v for w, v in zip(weights, vs, strict=True)),
               ca.SX.zeros(*vs[0].shape))


def sigma_offsets(est: Any, cols: list) -> list:
    """A UKF's sigma points' offsets about their centre from the columns ``cols`` of a
    factor of :math:`cP`: both signs, and 0 first for merwe points; :math:`L \\xi_i` for a
    rule given by its unit points :math:`\\xi_i` (Gauss-Hermite, fifth-degree cubature:
    ``est._unit``, :math:`c = 1`)."""
    if est._unit is not None:
        L = ca.horzcat(*cols)
        return [L @ ca.DM(xi) for xi in est._unit.T]
    centre = [] if est.points == "cubature" else [ca.SX.zeros(cols[0].numel())]
    return centre + cols + [-c for c in cols]


def tangent_offsets(est: Any, P: Any, cholesky: Any) -> tuple[list, Any]:
    """The tangent offsets of a UKF's sigma points (:func:`sigma_offsets` of the lower
    Cholesky factor of :math:`cP`) and whether ``P`` is positive definite."""
    L, definite = cholesky(est._scale * P)
    return sigma_offsets(est, [L[:, k] for k in range(P.shape[0])]), definite


def unscented_innovation(est: Any, xb: Any, Pb: Any, u: Any, y: Any, R: Any, p: Any,
                         mask: Any, cholesky: Any) -> tuple[list, list, Any, Any, Any]:
    """A UKF's update on a manifold from the prediction ``(xb, Pb)``: the sigma points'
    tangent offsets, the deviations of their outputs from their mean (from ``h(xb)``,
    wrapped), the innovation covariance ``S`` and the innovation ``e`` over the measured
    outputs (``mask``), and whether ``Pb`` is positive definite."""
    m = est.model
    M = m.manifold
    sig, definite = tangent_offsets(est, Pb, cholesky)
    uy = m.measurement_input(u)
    zr = m.H(xb, uy, p)  # the outputs' centre: deviations from it wrapped
    dz = [ca.if_else(mask, M.output_difference(m.H(M.retract(xb, d), uy, p), zr), 0)
          for d in sig]
    dzbar = _weighted(est._Wm, dz)
    dZ = [v - dzbar for v in dz]
    D = ca.diag(mask)
    S = _weighted(est._Wc, [v @ v.T for v in dZ]) + D @ R @ D + ca.diag(1 - mask)
    e = ca.if_else(mask, M.output_difference(y, zr + dzbar), 0)
    return sig, dZ, 0.5 * (S + S.T), e, definite


def usque_step(est: Any, predict: bool, cholesky: Any) -> ca.Function:
    """The UKF's fused step on a manifold (see the module): sigma points
    :math:`\\hat x \\oplus \\sigma_i` with the offsets :math:`\\sigma_i` the columns of
    the lower Cholesky factor (``cholesky``) of :math:`cP`, means and covariances of
    tangent vectors, output angles wrapped, the covariance reset as the EKF's."""
    m = est.model
    M = m.manifold
    Wm, Wc = est._Wm, est._Wc
    s, x, P, u, y, tun, Q, R, p, mask, y_inf = est._symbols()

    def mean(vs):
        return _weighted(Wm, vs)

    def cov(a, b):
        return _weighted(Wc, [da @ db.T for da, db in zip(a, b, strict=True)])

    if predict:
        sig, definite = tangent_offsets(est, P, cholesky)
        ref = m.F(x, u, p)  # the propagated estimate: the centre of the tangent vectors
        FX = [m.F(M.retract(x, d), u, p) for d in sig]
        dF = [M.local(ref, v) for v in FX]
        dbar = mean(dF)
        xb = M.retract(ref, dbar)
        dev = [v - dbar for v in dF]
        Pb = cov(dev, dev) + Q
        ok_mean = ca.logic_and(definite, ca.fabs(ca.sum1(ca.vertcat(*FX))) < ca.inf)
    else:
        xb, Pb = x, P
        ok_mean = ca.SX(1)
    # the update draws the sigma points of the prediction
    sig, dZ, S, e, definite = unscented_innovation(est, xb, Pb, u, y, R, p, mask, cholesky)
    ok_prior = ca.logic_and(ca.logic_and(ok_mean, definite),
                            ca.fabs(ca.sum1(ca.vertcat(xb, ca.vec(Pb)))) < ca.inf)
    Pxz = cov(sig, dZ)
    K = ca.solve(S, Pxz.T).T
    s_new, s_prior, nis, Ph = _updated(est, xb, Pb, K @ e, Pb - K @ S @ K.T, e, S)
    ok = ca.logic_and(ca.fabs(ca.sum1(ca.vertcat(s_new, nis))) < ca.inf, cholesky(Ph)[1])
    name = "usque_predict_update" if predict else "usque_update"
    return est._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                               ok_mean, mask, s_prior)
