r"""The windowed least-squares problem as a CasADi NLP, for Ipopt, SQP and fatrop.

:class:`~estim.solvers.least_squares.nlp.LeastSquaresNLP` solves its problem with the structured
Gauss-Newton solver, or hands it to a general NLP solver built here once per problem:

- :func:`build_eliminated`: the states of the ``N`` slots as the only variables and the
  cost :math:`\|r(X)\|^2` of :mod:`estim.solvers.least_squares.nlp` (Ipopt with its exact Hessian;
  CasADi's ``sqpmethod`` with the Gauss-Newton Hessian :math:`2 J^\top J`, slightly
  damped);
- :func:`build_singular`: the constrained form of a singular process noise (see
  :class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`), for Ipopt or fatrop;
- :func:`build_fatrop`: the multiple-shooting form with the process noise as controls
  and the dynamics as gap constraints, whose stage structure fatrop exploits
  (Vanroye et al., "FATROP: A fast constrained optimal control problem solver for
  robot trajectory optimization and control", IROS 2023).

Every data, weight and bookkeeping value is a parameter ``p``: the NLP is built once
and serves every window.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from estim.model import Model
from estim.solvers.least_squares.gauss_newton import full_record_constants
from estim.solvers.least_squares.options import (
    _FATROP_DEFAULTS,
    _IPOPT_DEFAULTS,
    _SQP_DEFAULTS,
    merge,
    nlpsol,
)

__all__ = ["FatropLayout", "build_eliminated", "build_fatrop", "build_singular", "charted",
           "solve_fatrop"]


@dataclass(frozen=True)
class FatropLayout:
    """Bounds of the multiple-shooting form: of the gap constraints ``lbg, ubg`` (zero),
    of the stage variables ``(x_k, w_k)`` ``lbz, ubz``, and ``xsel``, the indices of the
    states among the variables."""

    lbg: np.ndarray
    ubg: np.ndarray
    lbz: np.ndarray
    ubz: np.ndarray
    xsel: np.ndarray


def charted(model: Model, Z, ref) -> list:
    r"""The states of the slots from the variables ``Z (nx, N)``: ``Z`` itself on vector
    states; on a manifold each slot's chart centre (the columns of ``ref``, parameters)
    moved by its variables, a padded tangent step (:meth:`Manifold.padded
    <estim._manifold.Manifold.padded>`): :math:`x_j = c_j \oplus z_j`. The NLP then moves
    in the tangent space, and its optimum is the intrinsic one (a chart is a local
    diffeomorphism)."""
    M = model.manifold
    if M.euclidean_states:
        return [Z[:, j] for j in range(Z.shape[1])]
    return [M.retract(ref[:, j], Z[M.slots, j]) for j in range(Z.shape[1])]


def _difference(model: Model, x, x_to):
    r"""``x_to - x``: on a manifold the padded tangent vector :math:`x_{to} \ominus x`."""
    M = model.manifold
    return x_to - x if M.euclidean_states else M.padded(M.local(x, x_to))


def build_eliminated(model: Model, N: int, solver: str, options: dict, p, Y, U, Up, part, a,
                     xbar, W0, weight, pm) -> ca.Function:
    """The NLP solver (``"ipopt"`` or ``"sqp"``) of the eliminated form over the states of
    ``N`` slots (on a manifold, their tangent steps from the chart centres
    ``part["ref"]``: :func:`charted`), the user's ``options`` merged over the defaults;
    ``p`` is the parameter symbol and the others its parts (see
    :class:`~estim.solvers.least_squares.nlp.LeastSquaresNLP`), ``weight(j)`` the process
    term's weight of transition ``j``."""
    nx, ny = model.nx, model.ny
    Z = ca.SX.sym("X", nx, N)
    X = charted(model, Z, ca.reshape(part["ref"], nx, N) if "ref" in part else None)
    out = model.manifold.output_difference
    # arrival on the first active slot, one residual block per slot (a_j in {0, 1}):
    # a single W0 (X a - xbar) would couple every slot and make the Hessian dense
    res = [a[j] * (W0 @ _difference(model, xbar, X[j])) for j in range(N)]
    for j in range(N - 1):
        om = part["omega"][j]
        xn = model.F(X[j], U[:, j], pm)
        res.append(om * (weight(j) @ _difference(model, xn, X[j + 1]))
                   + (1 - om) * _difference(model, X[j], X[j + 1]))
    for j in range(N):
        Wy = ca.reshape(part["wy"][j * ny * ny:(j + 1) * ny * ny], ny, ny)
        res.append(Wy @ out(Y[:, j], model.H(X[j], Up[:, j], pm)))
    r = ca.vertcat(*res)
    x = ca.vec(Z)
    f = ca.dot(r, r)
    nlp = {"x": x, "p": p, "f": f}
    if solver == "ipopt":
        return nlpsol("mhe_ipopt", "ipopt", nlp, merge(_IPOPT_DEFAULTS, options), options)
    J = ca.jacobian(r, x)
    lam_f, lam_g = ca.SX.sym("lam_f"), ca.SX.sym("lam_g", 0)
    # Gauss-Newton Hessian with a tiny damping: the stationary points are unchanged,
    # the QP stays well posed when the window alone does not determine every state
    H = lam_f * (2 * (J.T @ J) + 1e-10 * ca.DM.eye(x.numel()))
    hess = ca.Function("nlp_hess_l", [x, p, lam_f, lam_g], [H],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    opts = merge(_SQP_DEFAULTS, options)
    opts["hess_lag"] = hess
    return nlpsol("mhe_sqp", "sqp", nlp, opts, options)


def build_fatrop(model: Model, N: int, lbx: np.ndarray, ubx: np.ndarray, options: dict, p, Y, U,
                 Up, part, a, xbar, W0, weight, pm) -> tuple[ca.Function, FatropLayout]:
    """Multiple-shooting form with process noise as controls, for fatrop.

    Stage k has variables ``(x_k, w_k)``; the gap constraint is
    ``x_{k+1} = omega_k F(x_k, u_k) + (1 - omega_k) x_k + w_k`` and the
    stage cost ``omega_k ||W_Q w_k||^2 + (1 - omega_k) ||w_k||^2``: the same
    optimum as the eliminated form.
    """
    m = model
    nx, ny = m.nx, m.ny
    M = m.manifold
    zs = [ca.SX.sym(f"x{k}", nx) for k in range(N)]
    ws = [ca.SX.sym(f"w{k}", nx) for k in range(N - 1)]
    ref = ca.reshape(part["ref"], nx, N) if "ref" in part else None
    xs = charted(m, ca.horzcat(*zs), ref)
    variables, g, lbg, ubg = [], [], [], []
    cost = sum(a[k] * ca.sumsqr(W0 @ _difference(m, xbar, xs[k])) for k in range(N))
    for k in range(N):
        variables.append(zs[k])
        Wy = ca.reshape(part["wy"][k * ny * ny:(k + 1) * ny * ny], ny, ny)
        cost += ca.sumsqr(Wy @ M.output_difference(Y[:, k], m.H(xs[k], Up[:, k], pm)))
        if k < N - 1:
            variables.append(ws[k])
            om = part["omega"][k]
            cost += om * ca.sumsqr(weight(k) @ ws[k]) + (1 - om) * ca.sumsqr(ws[k])
            G = om * m.F(xs[k], U[:, k], pm) + (1 - om) * xs[k]
            if M.euclidean_states:
                g.append(xs[k + 1] - (G + ws[k]))
            else:  # x_{k+1} = G (+) w_k, in the chart of slot k + 1
                assert ref is not None
                g.append(zs[k + 1] - M.padded(M.local(ref[:, k + 1],
                                                       M.retract(G, ws[k][M.slots]))))
            lbg.append(np.zeros(nx))
            ubg.append(np.zeros(nx))
    x = ca.vertcat(*variables)
    nlp = {"x": x, "p": p, "f": cost, "g": ca.vertcat(*g)}
    opts = merge(_FATROP_DEFAULTS, options)
    opts.setdefault("equality", [True] * (nx * (N - 1)))
    solver = nlpsol("mhe_fatrop", "fatrop", nlp, opts, options)
    lbg_all = np.concatenate(lbg) if lbg else np.zeros(0)
    ubg_all = np.concatenate(ubg) if ubg else np.zeros(0)
    inf = np.full(nx, np.inf)
    lb, ub = [], []
    for k in range(N):
        lb.append(lbx[k * nx:(k + 1) * nx])
        ub.append(ubx[k * nx:(k + 1) * nx])
        if k < N - 1:
            lb.append(-inf)
            ub.append(inf)
    xsel = np.concatenate([np.arange(k * 2 * nx, k * 2 * nx + nx) for k in range(N)])
    return solver, FatropLayout(lbg_all, ubg_all, np.concatenate(lb), np.concatenate(ub), xsel)


def solve_fatrop(solver: ca.Function, layout: FatropLayout, X0: np.ndarray, p: np.ndarray,
                 lbx: np.ndarray, ubx: np.ndarray, N: int, nx: int) -> dict:
    """One fatrop solve from the states ``X0 (N, nx)`` (on a manifold, the steps from the
    chart centres), projected on the bounds ``lbx``, ``ubx`` ``(N * nx,)``; the process
    noise starts at zero."""
    z0 = np.zeros(layout.lbz.size)
    X0 = np.clip(np.asarray(X0, float), lbx.reshape(N, nx), ubx.reshape(N, nx))
    z0[layout.xsel] = X0.ravel()
    lbz, ubz = layout.lbz.copy(), layout.ubz.copy()
    lbz[layout.xsel], ubz[layout.xsel] = lbx, ubx  # (on a manifold: the steps' bounds)
    return solver(x0=z0, p=p, lbx=lbz, ubx=ubz, lbg=layout.lbg, ubg=layout.ubg)


def build_singular(model: Model, N: int, solver: str, options: dict, slices: dict, n_p: int,
           r: int, full: bool) -> tuple[ca.Function, dict]:
    """The NLP solver of the constrained form (stage variables ``(x_j, w_j)``, the
    dynamics as equality constraints: fatrop's stage structure) and its layout: the
    variables' bounds ``lbz``, ``ubz``, the states' indices ``xsel`` and the noises'
    ``wsel``. Parameters:
    those of :class:`LeastSquaresNLP` (``n_p``) and then ``G`` (``nx * r``)."""
    nx, ny = model.nx, model.ny
    p = ca.SX.sym("p", n_p + nx * r)
    part = {k: p[sl] for k, sl in slices.items()}
    Y = ca.reshape(part["y"], ny, N)
    U = ca.reshape(part["u"], model.nw, N)
    Up = ca.reshape(part["up"], model.nu, N)
    a, omega = (full_record_constants(N) if full else (part["a"], part["omega"]))
    W0 = ca.reshape(part["w0"], nx, nx)
    G = ca.reshape(p[n_p:], nx, r)
    pm = ca.DM(model.p)
    out = model.manifold.output_difference
    xs = [ca.SX.sym(f"x{k}", nx) for k in range(N)]
    ws = [ca.SX.sym(f"w{k}", r) for k in range(N - 1)]
    variables, gaps = [], []
    cost: ca.SX | int = 0
    for k in range(N):
        variables.append(xs[k])
        Wy = ca.reshape(part["wy"][k * ny * ny:(k + 1) * ny * ny], ny, ny)
        cost += a[k] * ca.sumsqr(W0 @ (xs[k] - part["xbar"]))
        cost += ca.sumsqr(Wy @ out(Y[:, k], model.H(xs[k], Up[:, k], pm)))
        if k < N - 1:
            variables.append(ws[k])
            cost += ca.sumsqr(ws[k])
            om = omega[k]
            gaps.append(xs[k + 1] - (om * (model.F(xs[k], U[:, k], pm) + G @ ws[k])
                                     + (1 - om) * xs[k]))
    nlp = {"x": ca.vertcat(*variables), "p": p, "f": cost, "g": ca.vertcat(*gaps)}
    if solver == "fatrop":
        opts = merge(_FATROP_DEFAULTS, options)
        opts.setdefault("equality", [True] * (nx * (N - 1)))
    else:
        opts = merge({k: v for k, v in _IPOPT_DEFAULTS.items() if "warm_start" not in k},
                     options)
    fun = nlpsol(f"mhe_{solver}_singular", solver, nlp, opts, options)
    stage = nx + r
    xsel = np.concatenate([np.arange(k * stage, k * stage + nx) for k in range(N)])
    wsel = np.concatenate([np.arange(k * stage + nx, (k + 1) * stage, dtype=int)
                           for k in range(N - 1)] + [np.zeros(0, dtype=int)])
    nz = N * nx + (N - 1) * r
    return fun, {"lbz": np.full(nz, -np.inf), "ubz": np.full(nz, np.inf), "xsel": xsel,
                 "wsel": wsel}
