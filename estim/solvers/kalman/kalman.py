r"""The fused Kalman step shared by the EKF and the UKF: its symbols, flags and record scan.

Each filter writes its prediction and update as CasADi expressions of one step; this
module turns them into the Function of a step,
``(s, u, y, tuning) -> (s_new, innovation, flags, s_prior)``, with the filter state
:math:`s = [x; \operatorname{vec}(P)]` (column-major) and the tuning
:math:`[\operatorname{vec}(Q); \operatorname{vec}(R)]` as data, and scans that step over a
whole record (:func:`record_function`). The flags are

====  ==================================================================
0     the normalised innovation squared :math:`e^\top S^{-1} e`
1     the update is finite (and, for the UKF, its covariance definite)
2     the prediction is usable
3     the count of :math:`\pm\infty` in :math:`y` (refused by the estimator)
4     the outputs measured (not NaN)
5     the prediction's derivative is usable
6     suspect: NIS beyond the :data:`~estim.consistency.SUSPECT_TAIL` tail of
      :math:`\chi^2(\text{outputs measured})`
7     gated: NIS beyond the ``gate`` tail
8     the iterated update converged (1 for a filter that does not iterate)
====  ==================================================================

What a step does with them (keep the update, the prediction, or re-anchor) is the
estimator's: :class:`estim.estimators.kalman.fused.FusedKalman`.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca

from estim._scan import blocked_scan
from estim.consistency import SUSPECT_TAIL, chi2_limit
from estim.model import Model
from estim.solvers.kalman.triangular import tria

#: The flags of a fused step (see the module).
NFLAGS = 9

__all__ = ["NFLAGS", "ekf_checks", "finite", "fused_function", "matrix", "record_function",
           "step_symbols"]


def finite(v) -> ca.SX:
    """1 where every entry of ``v`` is finite (a NaN or inf makes the sum not finite)."""
    return ca.fabs(ca.sum1(ca.vec(v))) < ca.inf


def ekf_checks(s_new, nis, Ph, xb, Pb) -> tuple:
    """``(ok, ok_mean, ok_prior)`` of an extended Kalman update: the new state and the NIS
    finite with a covariance of positive diagonal (lost in overflowing updates), the
    prediction's mean finite, and its covariance too."""
    ok = ca.logic_and(ca.fabs(ca.sum1(s_new) + nis) < ca.inf, ca.mmin(ca.diag(Ph)) > 0)
    ok_mean = ca.fabs(ca.sum1(xb)) < ca.inf
    return ok, ok_mean, ca.logic_and(ok_mean, ca.fabs(ca.sum1(ca.vec(Pb))) < ca.inf)


def matrix(v, n: int, diagonal: bool):
    """The ``(n, n)`` matrix stored column-major in ``v`` (its diagonal only if asked)."""
    return ca.diag(v[[i * n + i for i in range(n)]]) if diagonal else ca.reshape(v, n, n)


def step_symbols(model: Model, diagonal: dict[str, bool], extra: int = 0) -> tuple:
    """The symbols of a step: ``s, x, P, u, y, tuning``, the ``Q, R`` read from the
    tuning (diagonal only where ``diagonal["Q"]``/``diagonal["R"]``), the parameters
    ``p``, the mask of measured outputs (0 for NaN and for ±inf) and the count of ±inf in
    ``y``. ``extra``: entries of the filter state after ``[x; vec P]`` (an adaptive
    filter's noise statistics, ``s[nx + nd^2:]``)."""
    m = model
    nx, ny, nd = m.nx, m.ny, m.ndx  # P, Q in the tangent space (nd = nx for vectors)
    s = ca.SX.sym("s", nx + nd * nd + extra)
    x, P = s[:nx], ca.reshape(s[nx:nx + nd * nd], nd, nd)
    u = ca.SX.sym("u", m.nw)
    y = ca.SX.sym("y", ny)
    tun = ca.SX.sym("tuning", nd * nd + ny * ny)  # the tuning is data (set_tuning)
    Q, R = (matrix(tun[:nd * nd], nd, diagonal["Q"]),
            matrix(tun[nd * nd:], ny, diagonal["R"]))
    mask = ca.fabs(y) < ca.inf
    y_inf = ca.sum1(ca.fabs(y) == ca.inf) if ny else ca.SX(0)
    return s, x, P, u, y, tun, Q, R, ca.DM(m.p), mask, y_inf


def fused_function(name: str, inputs: list, s_new, e, nis, ok, ok_prior, y_inf, ok_mean,
                   mask, s_prior, gate: float | None = None, converged=None) -> ca.Function:
    r"""The step's CasADi Function ``(s, u, y, tuning) -> (s_new, innovation, flags,
    s_prior)`` from the filter's expressions: the flags (see the module) with the
    suspect and gate tests, NIS beyond the :math:`\chi^2` tail of the number of
    outputs measured (``SUSPECT_TAIL``, and ``gate`` when set); ``converged``: whether an
    iterated update converged (None: a filter that does not iterate)."""
    ny = mask.numel()
    measured = ca.sum1(mask) if ny else ca.SX(0)
    onehot = ca.vertcat(*[measured == k for k in range(1, ny + 1)])

    def beyond(tail):  # NIS beyond the tail of chi2(outputs measured)
        if not ny or tail is None:
            return ca.SX(0)
        limits = ca.DM([chi2_limit(k, tail) for k in range(1, ny + 1)])
        return ca.logic_and(measured > 0, nis > ca.dot(limits, onehot))

    flags = ca.vertcat(nis, ok, ok_prior, y_inf, measured, ok_mean,
                       beyond(SUSPECT_TAIL), beyond(gate),
                       ca.SX(1) if converged is None else converged)
    return ca.Function(name, inputs, [s_new, e, flags, s_prior],
                       ["s", "u", "y", "tuning"], ["s_new", "innovation", "flags", "s_prior"])


def record_function(prefix: str, model: Model, build: Callable[[bool], ca.Function], T: int,
                    expand: bool = True, sqrt: bool = False, first: bool = True,
                    extra: int = 0) -> ca.Function:
    """``(s0, Y, W, tuning, P0) -> (S, E, flags)``: the fused step ``build(predict)`` over
    ``T`` samples (the first an update only; not ``first``: every one a prediction and
    an update, a record continued from the filter state ``s0``), the filter state,
    innovation and flags of every sample side by side; a gated step keeps the prediction
    with ``P0`` added.
    With ``sqrt``, the filter state holds the lower factor ``S`` of ``P`` and the input
    ``P0`` the Cholesky factor of ``P0``: a gated step keeps the factor
    ``tria([S_prior, chol(P0)])`` (:func:`estim.solvers.kalman.triangular.tria`).
    Scanned in blocks of about :math:`\\sqrt T` steps (:func:`estim._scan.blocked_scan`);
    not ``expand``: the step is called in loops instead of inlined (the form to compile
    to C). The Functions are named ``{prefix}_first``, ``{prefix}_step`` and
    ``{prefix}_{T}`` (not ``first``: ``{prefix}_then_{T}``). ``extra``: entries of the
    filter state after ``[x; vec P]`` (see :func:`step_symbols`), kept by a gated step."""
    m = model
    nx, ny, nw, nd = m.nx, m.ny, m.nw, m.ndx
    nP = nx + nd * nd

    def scanned(predict: bool) -> ca.Function:
        s, w = ca.SX.sym("s", nP + extra), ca.SX.sym("w", nw)
        y, tun = ca.SX.sym("y", ny), ca.SX.sym("tuning", nd * nd + ny * ny)
        P0 = ca.SX.sym("P0", nd * nd)
        s_new, e, flags, s_prior = build(predict)(s, w, y, tun)
        if sqrt:
            factor = tria(ca.horzcat(ca.reshape(s_prior[nx:nP], nd, nd),
                                     ca.reshape(P0, nd, nd)))
            gated = ca.vertcat(s_prior[:nx], ca.vec(factor), s_prior[nP:])
        else:
            gated = s_prior + ca.vertcat(ca.SX(nx, 1), P0, ca.SX(extra, 1))
        s_next = ca.if_else(flags[7], gated, s_new)
        return ca.Function(f"{prefix}_" + ("step" if predict else "first"),
                           [s, w, y, tun, P0], [s_next, s_next, e, flags],
                           ["s", "w", "y", "tuning", "P0"],
                           ["s_next", "s_out", "innovation", "flags"])

    s0 = ca.MX.sym("s0", nP + extra)
    Y, W = ca.MX.sym("Y", ny, T), ca.MX.sym("W", nw, T)
    tun, P0 = ca.MX.sym("tuning", nd * nd + ny * ny), ca.MX.sym("P0", nd * nd)
    name = f"{prefix}_{T}"
    if not first:
        _, S, E, F = blocked_scan(scanned(True), T, (1, 2), expand=expand)(s0, W, Y, tun, P0)
        name = f"{prefix}_then_{T}"
    else:
        s1, _, e0, f0 = scanned(False)(s0, W[:, 0], Y[:, 0], tun, P0)
        S, E, F = s1, e0, f0
        if T > 1:
            scan = blocked_scan(scanned(True), T - 1, (1, 2), expand=expand)
            _, S1, E1, F1 = scan(s1, W[:, 1:], Y[:, 1:], tun, P0)
            S, E, F = ca.horzcat(s1, S1), ca.horzcat(e0, E1), ca.horzcat(f0, F1)
    return ca.Function(name, [s0, Y, W, tun, P0], [S, E, F],
                       ["s0", "Y", "W", "tuning", "P0"], ["S", "innovation", "flags"])
