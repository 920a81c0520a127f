r"""The square-root form of the fused Kalman filters (``form="sqrt"``).

The filter state holds the lower-triangular factor :math:`S` of the covariance,
:math:`s = [x; \operatorname{vec}(S)]`, :math:`P = S S^\top`, and the tuning the
factors :math:`[\operatorname{vec}(L_Q); \operatorname{vec}(L_R)]`
(:math:`L_Q L_Q^\top = Q`, a semi-definite ``Q`` included; :math:`L_R` the Cholesky
factor of ``R``). Every covariance of a step is formed as a triangular factor by
orthogonal transformations (:func:`estim.solvers.kalman.triangular.tria`) or rank-one
downdates, so it stays symmetric and positive semi-definite by construction.

EKF (:func:`ekf_step`): the time update
:math:`\bar S = \operatorname{tria}([A S, L_Q])` and the measurement update by the
array form of Morf and Kailath,

.. math::
    \operatorname{tria}\begin{bmatrix} L_R & C \bar S \\ 0 & \bar S \end{bmatrix}
    = \begin{bmatrix} S_y & 0 \\ \bar K & S^+ \end{bmatrix}, \qquad
    \hat x = \bar x + \bar K S_y^{-1} e, \quad \text{NIS} = \|S_y^{-1} e\|^2,

with :math:`S_y S_y^\top = C \bar P C^\top + R` and :math:`\bar K = K S_y`.

UKF (:func:`ukf_step`, van der Merwe & Wan 2001): sigma points
:math:`x \pm \sqrt c\, S_{:,i}` from the factor itself; a covariance
:math:`\sum_i W^c_i d_i d_i^\top + L L^\top` is factored as
:math:`\operatorname{tria}([\sqrt{W^c_i} d_i]_{W^c_i \ge 0}, L)` followed by a rank-one
downdate by :math:`\sqrt{-W^c_0}\, d_0` where the centre weight is negative (Van der
Merwe's points); so are :math:`\bar S` (deviations of :math:`F`, :math:`L_Q`) and
:math:`S_y` (of :math:`h`, :math:`L_R`). The gain
:math:`K = P_{xy} S_y^{-\top} S_y^{-1}` comes from two triangular solves and the
posterior factor from the same construction over
:math:`\mathcal X_i - \bar x - K \delta\mathcal Z_i` and :math:`K L_R`,

.. math::
    P^+ = \sum_i W^c_i (\delta\mathcal X_i - K \delta\mathcal Z_i)
          (\delta\mathcal X_i - K \delta\mathcal Z_i)^\top + K R K^\top
        = \bar P - K S_y S_y^\top K^\top,

the QR equivalent of the rank-one downdates by the columns of :math:`K S_y`, without
their cancellation when a measurement is nearly exact.

Missing outputs (NaN) zero their rows of :math:`C` (of :math:`\mathcal Z`) and of
:math:`L_R` and add a unit diagonal entry, which decouples them from the rest exactly.

References
----------
M. Morf, T. Kailath, "Square-root algorithms for least-squares estimation",
IEEE TAC 20(4), 1975;
R. van der Merwe, E. A. Wan, "The square-root unscented Kalman filter for state and
parameter estimation", ICASSP 2001;
M. Grewal, A. Andrews, *Kalman Filtering: Theory and Practice*, 4th ed., 2015, ch. 7.
"""

from __future__ import annotations

from functools import cache
from typing import Any

import casadi as ca
import numpy as np

from estim.estimators.manifold_steps import (
    output_jacobian,
    retracted,
    sigma_offsets,
    transition_jacobian,
)
from estim.solvers.kalman.continuous import (
    drift_jacobian,
    interval,
    sqrt_moment_step,
    sqrt_sigma_moment_step,
)
from estim.solvers.kalman.kalman import finite
from estim.solvers.kalman.triangular import (
    cholesky_downdate,
    psd_factor,
    solve_lower,
    tria,
)

#: The forms of the fused filters: the covariance itself, or its triangular factor.
FORMS = ("covariance", "sqrt")

#: A fused filter (:class:`~estim.EKF` or :class:`~estim.UKF`): its model, symbols,
#: weights and flags Function are read.
Filter = Any


def check_form(form: object) -> tuple[str, bool]:
    """``(form, whether it is the square-root form)``; ValueError for another form."""
    if not isinstance(form, str) or form not in FORMS:
        raise ValueError(f"form must be one of {', '.join(map(repr, FORMS))}, got {form!r}")
    return form, form == "sqrt"


def noise_factors(Q: np.ndarray, R: np.ndarray, diagonal: dict[str, bool]
                  ) -> tuple[np.ndarray, np.ndarray]:
    r"""The tuning of the square-root form: lower factors :math:`L_Q, L_R` of ``Q``
    (semi-definite allowed, see :func:`~estim.solvers.kalman.triangular.psd_factor`) and
    ``R``; diagonal (the square roots of the diagonal) where the graphs read the
    diagonal only."""
    def factor(M: np.ndarray, name: str) -> np.ndarray:
        return np.diag(np.sqrt(np.diag(M))) if diagonal[name] else psd_factor(M)

    return factor(Q, "Q"), factor(R, "R")


def covariances(S: np.ndarray) -> np.ndarray:
    """:math:`S S^\\top` of one factor ``(n, n)`` or a stack ``(..., n, n)``."""
    return S @ np.swapaxes(S, -1, -2)


def covariance(v: np.ndarray, n: int, sqrt: bool) -> np.ndarray:
    """The covariance ``(n, n)`` of the filter state's part ``v = vec(P)`` (a copy), or
    ``S S^T`` of ``v = vec(S)`` with ``sqrt``."""
    P = v.reshape(n, n, order="F")
    return covariances(P) if sqrt else P.copy()


def P0_data(P0: np.ndarray, sqrt: bool) -> np.ndarray:
    """``vec(P0)``, or ``vec(chol(P0))`` with ``sqrt`` (column-major): the ``P0`` input
    of the record Functions and the covariance part of the filter state after a reset."""
    return (np.linalg.cholesky(P0) if sqrt else P0).ravel(order="F")


def with_P0(v: np.ndarray, p0: np.ndarray, sqrt: bool) -> np.ndarray:
    r"""The covariance part of the filter state ``v`` with ``P0`` added, given as
    ``p0 = P0_data(P0, sqrt)``: ``v + vec(P0)``,
    or with ``sqrt`` the factor of :math:`S S^\top + P_0`,
    :math:`\operatorname{vec}(\operatorname{tria}([S, \operatorname{chol}(P_0)]))`
    (the factor of ``P0`` alone where ``S`` is not finite), by the compiled
    :func:`~estim.solvers.kalman.triangular.tria` that the whole-record scan's gate uses, so
    that :meth:`~estim.EKF.step` and :meth:`~estim.EKF.filter` agree to the last bit."""
    if not sqrt:
        return v + p0
    if not np.isfinite(v).all():
        return p0.copy()
    return np.asarray(_added_factor(int(round(np.sqrt(p0.size))))(v, p0)).ravel()


@cache
def _added_factor(n: int) -> ca.Function:
    """``(vec(S), vec(L0)) -> vec(tria([S, L0]))`` for ``(n, n)`` factors."""
    S, L0 = ca.SX.sym("S", n * n), ca.SX.sym("L0", n * n)
    factor = tria(ca.horzcat(ca.reshape(S, n, n), ca.reshape(L0, n, n)))
    return ca.Function("added_factor", [S, L0], [ca.vec(factor)])


def _measurement_noise(LR: ca.SX, mask: ca.SX, diagonal: bool) -> ca.SX:
    """A factor of ``D R D + diag(1 - mask)`` (``D = diag(mask)``): ``D L_R + I - D`` for
    a diagonal ``R``, else the wider ``[D L_R, I - D]``."""
    D, E = ca.diag(mask), ca.diag(1 - mask)
    return D @ LR + E if diagonal else ca.horzcat(D @ LR, E)


def _positive_variances(S: ca.SX) -> ca.SX:
    """1 where every variance, the diagonal of :math:`S S^\\top`, is positive."""
    return ca.mmin(ca.sum2(S * S)) > 0


def ekf_step(est: Filter, predict: bool) -> ca.Function:
    """The square-root EKF's step Function (see the module), with the flags of the
    covariance form."""
    m = est.model
    M, nx, ny = m.manifold, m.ndx, m.ny  # (on a manifold: the tangent space's size)
    s, x, S, u, y, tun, LQ, LR, p, mask, y_inf = est._symbols()
    uy = m.measurement_input(u)
    # (on a manifold the multiplicative form: derivatives along the retraction)
    if predict and est.Qc is not None:  # the factor's moment equation over the interval
        u_of, h = interval(m, u)
        xb, Sb = sqrt_moment_step(m.f_c, drift_jacobian(m), x, S, u_of, p, LQ, h,
                                  est.substeps)
    else:
        xb = m.F(x, u, p) if predict else x
        Sb = tria(ca.horzcat(transition_jacobian(m, x, u, p, xb) @ S, LQ)) if predict else S
    C = ca.diag(mask) @ output_jacobian(m, xb, uy, p)
    e = ca.if_else(mask, M.output_difference(y, m.H(xb, uy, p)), 0)
    a_prior = a_new = s[est._nP:]
    diagonal = est._diagonal["R"]
    if getattr(est, "dof", None) is not None or est._n_adapt:  # Student-t or adaptive
        Pb = Sb @ Sb.T
        LR, a_prior, a_new = est._sqrt_noise(s, predict, xb, Pb @ C.T, C @ Pb @ C.T, Pb, e,
                                             LR, mask)
        diagonal = False
    LRm = _measurement_noise(LR, mask, diagonal)
    pre = ca.vertcat(ca.horzcat(LRm, C @ Sb), ca.horzcat(ca.SX(nx, LRm.shape[1]), Sb))
    post = tria(pre)
    Sy, Kb = post[:ny, :ny], post[ny:, :ny]
    z = solve_lower(Sy, e)
    # the posterior factor in Joseph's form, tria([(I - K C) Sb, K L_R]) with the gain
    # K = Kb Sy^-1: the block tria leaves beside Kb is the same in exact arithmetic, but
    # it loses K R K^T where R is far below P (R = 1e-300: a zero factor, a failed step)
    K = solve_lower(Sy, Kb.T, transpose=True).T
    Sh = tria(ca.horzcat((ca.SX.eye(nx) - K @ C) @ Sb, K @ LRm))
    if M.euclidean_states:
        xh = xb + Kb @ z
    else:  # the retraction, and the factor carried by the reset Jacobian
        xh, Sh = _reset(M, xb, Kb @ z, Sh)
    if est.clip:
        xh = ca.fmin(ca.fmax(xh, ca.DM(est.lower)), ca.DM(est.upper))
    nis = ca.sumsqr(z)
    s_new = ca.vertcat(xh, ca.vec(Sh), a_new)
    s_prior = ca.vertcat(xb, ca.vec(Sb), a_prior)
    ok = ca.logic_and(finite(ca.vertcat(s_new, nis)), _positive_variances(Sh))
    ok_mean = finite(xb)
    ok_prior = ca.logic_and(ok_mean, finite(Sb))
    name = "ekf_sqrt_predict_update" if predict else "ekf_sqrt_update"
    return est._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                               ok_mean, mask, s_prior)


def _reset(M: Any, xb: ca.SX, delta: ca.SX, Sh: ca.SX) -> tuple[ca.SX, ca.SX]:
    r"""The multiplicative update on a manifold: :math:`\hat x = \bar x \oplus \delta`
    and the factor :math:`\operatorname{tria}(J S)` of the covariance carried to it by
    the reset Jacobian (:func:`~estim.estimators.manifold_steps.retracted`)."""
    xh, J = retracted(M, xb, delta)
    return xh, tria(J @ Sh)


def _factor(deviations: list, weights: np.ndarray, L: ca.SX) -> ca.SX:
    r"""The factor of :math:`\sum_i W_i d_i d_i^\top + L L^\top`: a QR of the
    non-negatively weighted deviations with ``L``, then a downdate for each negative
    weight."""
    cols = [float(np.sqrt(w)) * d for w, d in zip(weights, deviations, strict=True) if w > 0]
    F = tria(ca.horzcat(*cols, L))
    for w, d in zip(weights, deviations, strict=True):
        if w < 0:
            F = cholesky_downdate(F, float(np.sqrt(-w)) * d)
    return F


def ukf_step(est: Filter, predict: bool) -> ca.Function:
    """The square-root UKF's step Function (see the module), with the flags of the
    covariance form."""
    m = est.model
    M = m.manifold
    Wm, Wc = est._Wm, est._Wc
    root = float(np.sqrt(est._scale))
    s, x, S, u, y, tun, LQ, LR, p, mask, y_inf = est._symbols()

    def offsets(S):  # the sigma points' offsets, from the factor itself
        return sigma_offsets(est, [root * S[:, k] for k in range(S.shape[1])])

    def sigma(x, offs):  # x (+) the offsets (x + the offsets on vector states)
        if M.euclidean_states:
            return [x + d for d in offs]
        return [M.retract(x, d) for d in offs]

    def mean(points):
        return sum((float(w) * v for w, v in zip(Wm, points, strict=True)),
                   ca.SX.zeros(points[0].numel()))

    if predict and est.Qc is not None:  # the factor's sigma-point moment equations
        u_of, h = interval(m, u)
        xb, Sb = sqrt_sigma_moment_step(m.f_c, offsets, Wm, Wc, x, S, u_of, p, LQ, h,
                                        est.substeps)
        ok_mean = finite(ca.vertcat(xb, ca.vec(Sb)))
    elif predict:
        FX = [m.F(v, u, p) for v in sigma(x, offsets(S))]
        if M.euclidean_states:
            xb = mean(FX)
            Sb = _factor([v - xb for v in FX], Wc, LQ)
        else:  # tangent vectors about F(x); their mean retracted
            ref = m.F(x, u, p)
            dF = [M.local(ref, v) for v in FX]
            dbar = mean(dF)
            xb = M.retract(ref, dbar)
            Sb = _factor([v - dbar for v in dF], Wc, LQ)
        ok_mean = finite(ca.vertcat(*FX))
    else:
        xb, Sb = x, S
        ok_mean = ca.SX(1)
    ok_prior = ca.logic_and(ok_mean, finite(ca.vertcat(xb, ca.vec(Sb))))
    offs = offsets(Sb)
    sig = sigma(xb, offs)
    uy = m.measurement_input(u)
    if M.trivial:
        Z = [ca.if_else(mask, m.H(v, uy, p), 0) for v in sig]
        zp = mean(Z)
        dZ = [v - zp for v in Z]
        dX = [v - xb for v in sig]
        e = ca.if_else(mask, y - zp, 0)
    else:  # output deviations from h(xb), wrapped; the offsets are the tangent deviations
        zr = m.H(xb, uy, p)
        Z = [ca.if_else(mask, M.output_difference(m.H(v, uy, p), zr), 0) for v in sig]
        zp = mean(Z)
        dZ = [v - zp for v in Z]
        dX = offs if not M.euclidean_states else [v - xb for v in sig]
        e = ca.if_else(mask, M.output_difference(y, zr + zp), 0)
    a_prior = a_new = s[est._nP:]
    diagonal = est._diagonal["R"]
    if getattr(est, "dof", None) is not None or est._n_adapt:  # Student-t or adaptive
        Pzz = sum((float(w) * (b @ b.T) for w, b in zip(Wc, dZ, strict=True)), 0)
        Pxz = sum((float(w) * (a @ b.T) for w, a, b in zip(Wc, dX, dZ, strict=True)), 0)
        LR, a_prior, a_new = est._sqrt_noise(s, predict, xb, Pxz, Pzz, Sb @ Sb.T, e, LR, mask)
        diagonal = False
    LRm = _measurement_noise(LR, mask, diagonal)
    Sy = _factor(dZ, Wc, LRm)
    Pxz = sum((float(w) * (a @ b.T) for w, a, b in zip(Wc, dX, dZ, strict=True)),
              ca.SX.zeros(m.ndx, m.ny))
    K = solve_lower(Sy, solve_lower(Sy, Pxz.T), transpose=True).T
    Sh = _factor([a - K @ b for a, b in zip(dX, dZ, strict=True)], Wc, K @ LRm)
    if M.euclidean_states:
        xh = xb + K @ e
    else:  # the retraction, and the factor carried by the reset Jacobian
        xh, Sh = _reset(M, xb, K @ e, Sh)
    if est.clip:
        xh = ca.fmin(ca.fmax(xh, ca.DM(est.lower)), ca.DM(est.upper))
    nis = ca.sumsqr(solve_lower(Sy, e))
    s_new = ca.vertcat(xh, ca.vec(Sh), a_new)
    s_prior = ca.vertcat(xb, ca.vec(Sb), a_prior)
    ok = ca.logic_and(finite(ca.vertcat(s_new, nis)), _positive_variances(Sh))
    name = "ukf_sqrt_predict_update" if predict else "ukf_sqrt_update"
    return est._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                               ok_mean, mask, s_prior)
