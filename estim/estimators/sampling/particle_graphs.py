"""The particle filter's per-particle Functions, from the model's CasADi graph.

:func:`graphs` builds, for one particle, the weighting by a measurement, the step from
a particle (the bootstrap proposal, or the transition updated by the measurement,
linearised or unscented: :func:`linearised`), the first step from the prior, and the
transition alone (for the smoother). :class:`~estim.ParticleFilter` evaluates them
over all particles at once (numpy, CasADi's ``map``, or compiled:
:mod:`estim.solvers.sampling.particle_kernel`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import casadi as ca
import numpy as np

from estim.estimators.manifold_steps import output_jacobian
from estim.model import Model
from estim.solvers.quadrature import cubature, cubature5, gauss_hermite

__all__ = ["Graphs", "definite", "graphs", "measured_tuning", "prior_tuning", "scalar"]


def definite(Q: np.ndarray) -> None:
    """Refuse a singular ``Q`` for the linearised proposal (its density ratio needs one)."""
    if np.linalg.eigvalsh(Q).min() <= 0.0:
        raise ValueError("Q must be positive definite with proposal='ekf' or 'ukf' (the "
                         "weights hold "
                         "the transition density); use the bootstrap proposal for a "
                         "singular Q")


def prior_tuning(P0: np.ndarray, tun: np.ndarray) -> np.ndarray:
    """The linearised proposal's tuning ``tun`` with ``P0`` in place of ``Q``."""
    nx, L0 = len(P0), np.linalg.cholesky(P0)
    return np.concatenate([P0.ravel(order="F"), np.linalg.inv(L0).ravel(order="F"),
                           tun[2 * nx * nx:-nx * nx], L0.ravel(order="F")])


def measured_tuning(Q: np.ndarray, R: np.ndarray, LQ: np.ndarray, proposal: str,
                    observed: np.ndarray
                    ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
    """For the measured outputs ``observed``: ``WR`` (flat), the inverse Cholesky factor
    of their block of ``R`` embedded in ``(ny, ny)``, the Gaussian's constant, that block
    ``Ro``, the proposal's tuning ``tun`` (:func:`graphs`: ``L_Q`` (flat, ``LQ``), or Q,
    ``L_Q^-1``, R with identity rows where missing, ``L_Q``) and the missing outputs'
    indicator ``miss``."""
    ny, idx = len(observed), np.flatnonzero(observed)
    WR, const, Ro = np.zeros((ny, ny)), 0.0, R[np.ix_(idx, idx)]
    if idx.size:
        L = np.linalg.cholesky(Ro)
        WR[np.ix_(idx, idx)] = np.linalg.inv(L)
        const = -0.5 * idx.size * np.log(2 * np.pi) - float(np.log(np.diag(L)).sum())
    tun = LQ
    if proposal != "bootstrap":
        Rm = np.eye(ny)
        Rm[np.ix_(idx, idx)] = Ro
        LQi = np.linalg.inv(LQ.reshape(len(Q), -1, order="F"))
        tun = np.concatenate([Q.ravel(order="F"), LQi.ravel(order="F"), Rm.ravel(order="F"),
                              LQ])
    return WR.ravel(order="F"), const, Ro, tun, (~observed).astype(float)


class Graphs(NamedTuple):
    """The per-particle Functions of :func:`graphs`."""

    weigh: ca.Function
    advance: ca.Function
    start: ca.Function | None
    transit: ca.Function
    first: ca.Function


def proposal_rule(proposal: str, points: object, order: object, n: int
                  ) -> tuple[np.ndarray, np.ndarray] | None:
    """The unscented proposal's rule ``(unit points (n, N), weights (N,))`` of
    ``ParticleFilter(points=, order=)`` (None: the default cubature), checked: a rule of
    positive weights, with ``proposal="ukf"`` only."""
    from estim._validate import as_int

    rules = ("cubature", "gauss-hermite", "cubature5")
    if not isinstance(points, str) or points not in rules:
        raise ValueError(f"points must be one of {', '.join(map(repr, rules))} (rules of "
                         f"positive weights), got {points!r}")
    order = as_int(order, "order", minimum=1)
    if points == "cubature":
        return None
    if proposal != "ukf":
        raise ValueError(f"points={points!r} chooses the unscented proposal's rule: give "
                         f"proposal='ukf' (got {proposal!r})")
    if points == "cubature5":
        if n > 4:
            raise ValueError(f"points='cubature5' has negative weights beyond four states "
                             f"(here {n}): the proposal's covariance could lose "
                             f"definiteness; use 'cubature' or 'gauss-hermite'")
        return cubature5(n)
    return gauss_hermite(n, order)


def graphs(model: Model, loglik: Callable | None, proposal: str,
           rule: tuple[np.ndarray, np.ndarray] | None = None) -> Graphs:
    """``weigh(x, w, y0, WR, miss) -> (yhat, l)``, ``advance(x, v, w, tun, y0, WR, miss)
    -> (x_next, yhat, l)``, the linearised proposal's first step ``start`` (from the
    prior; None for the bootstrap filter), ``transit(x, w) -> F(x, w)`` and ``first(x0,
    v, w, tun0, y0, WR, miss) -> (x, yhat, l)``, the first step from the prior in one
    Function (``start``, or ``x0 + L_0 v`` weighed, ``tun0`` then ``L_0``), for one
    particle (see :class:`~estim.ParticleFilter`): ``w`` the transition input followed by
    the model's parameters (``nw + np``: a chain over the parameters changes data, not
    the Functions), ``y0`` the measurement with 0 where
    missing (``miss`` 1 there), ``WR`` the inverse Cholesky factor of the measured rows
    of ``R`` embedded in ``(ny, ny)`` (the Gaussian term without its constant), ``tun``
    what the ``proposal`` reads of the tuning (see ``ParticleFilter._measured``); with
    the linearised proposal ``l`` includes the ratio of the transition density to the
    proposal's."""
    nx, ny, nw, nd = model.nx, model.ny, model.nw, model.ndx
    M = model.manifold
    # the transition input and then the parameters: one input, so that a chain over the
    # parameters changes data, not the compiled kernels
    wp = ca.SX.sym("w", nw + model.p.size)
    w, p = wp[:nw], wp[nw:]
    x, v = ca.SX.sym("x", nx), ca.SX.sym("v", nd)
    y0 = ca.SX.sym("y0", ny)
    WR, miss = ca.SX.sym("WR", ny * ny), ca.SX.sym("miss", ny)

    def measure(xk):
        yhat = model.H(xk, model.measurement_input(w), p)
        if loglik is None:  # (output angles wrapped)
            e = (1 - miss) * M.output_difference(y0, yhat)
            return yhat, -0.5 * ca.sumsqr(ca.reshape(WR, ny, ny) @ e)
        y = (1 - miss) * y0 + miss * yhat
        params = {n: p[i] for i, n in enumerate(model.param_names)}
        try:
            value = loglik(y, yhat, params)
        except Exception as exc:  # noqa: BLE001 - re-raised naming the argument
            raise TypeError(f"loglik: calling loglik(y, yhat, p) on symbols (y, yhat: "
                            f"({ny}, 1) CasADi columns, p: dict of the parameters) failed: "
                            f"{type(exc).__name__}: {exc}" + (
                                " (write it with ca.* or numpy functions, not math.*)"
                                if "real number" in str(exc) else "")) from exc
        ell = scalar(value)
        if ell.is_constant():
            raise ValueError(f"loglik must depend on y or yhat, got the constant {ell} (a "
                             f"math.* function evaluates once to a number: use ca.* or "
                             f"numpy functions)")
        return yhat, ell

    yhat, ell = measure(x)
    weigh = ca.Function("pf_weigh", [x, wp, y0, WR, miss], [yhat, ell])
    xb = model.F(x, w, p)
    if proposal == "bootstrap":  # tun: L_Q; on a manifold the noise in its tangent space
        tun = ca.SX.sym("tun", nd * nd)
        noise = ca.reshape(tun, nd, nd) @ v
        xn = xb + noise if M.euclidean_states else M.retract(xb, noise)
        advance = ca.Function("pf_advance", [x, v, wp, tun, y0, WR, miss],
                              [xn, *measure(xn)])
        start = None
        L0 = ca.SX.sym("L0", nd * nd)
        x_0 = x + ca.reshape(L0, nd, nd) @ v if M.euclidean_states else \
            M.retract(x, ca.reshape(L0, nd, nd) @ v)
        first = ca.Function("pf_first", [x, v, wp, L0, y0, WR, miss], [x_0, *measure(x_0)])
    else:  # "ekf", "ukf", tun: Q, L_Q^-1, R (identity rows where missing), L_Q
        tun = ca.SX.sym("tun", 3 * nd * nd + ny * ny)
        advance = ca.Function("pf_advance", [x, v, wp, tun, y0, WR, miss], list(
            linearised(model, measure, xb, v, w, p, tun, y0, miss, proposal, rule)))
        # the first step: the same from the prior N(x0, P0) (tun with P0 for Q)
        start = ca.Function("pf_start", [x, v, wp, tun, y0, WR, miss], list(
            linearised(model, measure, x, v, w, p, tun, y0, miss, proposal, rule)))
        first = start
    transit = ca.Function("pf_transit", [x, wp], [xb])
    return Graphs(weigh, advance, start, transit, first)


def linearised(model: Model, measure: Callable, xb: ca.SX, v: ca.SX, w: ca.SX, p: ca.SX,
               tun: ca.SX, y0: ca.SX, miss: ca.SX, kind: str = "ekf",
               rule: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[ca.SX, ca.SX, ca.SX]:
    r"""A particle drawn from :math:`N(\bar x,\, Q)` updated by the measurement
    (see :class:`ParticleFilter`'s ``proposal``): with the output linearised at
    :math:`\bar x` (``kind="ekf"``), or through the unscented transform of
    :math:`N(\bar x, Q)` by the spherical-cubature rule (``"ukf"``: the :math:`2n`
    points :math:`\bar x \pm \sqrt{n}\, L_Q e_j` of weight :math:`1/(2n)`, or the
    ``rule``'s unit points :math:`\xi_j` and weights :math:`W_j`, the points
    :math:`\bar x + L_Q \xi_j`: with positive weights the joint covariance of state and
    output is positive semi-definite, so that the updated covariance
    :math:`Q - K P_{yy} K^\top`, its Schur complement, is too). The
    particle, its predicted output and its log-weight factor (measurement density
    times :math:`N(x; \bar x, Q) / q(x)`; the :math:`2\pi` terms cancel).

    On a manifold the Gaussian is that of the tangent step :math:`\delta` at
    :math:`\bar x`, the particle :math:`\bar x \oplus \delta` (the transition's noise
    is :math:`x \ominus \bar x = \delta`), the output's derivative taken along the
    retraction and its deviations wrapped."""
    M = model.manifold
    nx, ny = model.ndx, model.ny  # (on a manifold: the tangent space)
    n2 = nx * nx
    Qm, LQi = ca.reshape(tun[:n2], nx, nx), ca.reshape(tun[n2:2 * n2], nx, nx)
    Rm = ca.reshape(tun[2 * n2:2 * n2 + ny * ny], ny, ny)
    uy = model.measurement_input(w)

    def moved(d):
        return xb + d if M.trivial else M.retract(xb, d)

    h0 = model.H(xb, uy, p)
    e = (1 - miss) * M.output_difference(y0, h0)
    if kind == "ekf":
        Cm = ca.diag(1 - miss) @ output_jacobian(model, xb, uy, p)
        K = ca.solve(Cm @ Qm @ Cm.T + Rm, Cm @ Qm).T  # Q C^T S^-1
        IKC = ca.DM.eye(nx) - K @ Cm
        Sig = IKC @ Qm @ IKC.T + K @ Rm @ K.T  # Joseph form
    else:
        LQ = ca.reshape(tun[2 * n2 + ny * ny:], nx, nx)
        unit, W = cubature(nx) if rule is None else rule
        offsets = [LQ @ ca.DM(xi) for xi in unit.T]
        # the outputs' deviations from h(x_bar) (wrapped); missing rows: 0
        Ys = [(1 - miss) * M.output_difference(model.H(moved(d), uy, p), h0)
              for d in offsets]
        yb = sum((float(wt) * Yj for wt, Yj in zip(W, Ys, strict=True)), ca.SX.zeros(ny))
        db = sum((float(wt) * d for wt, d in zip(W, offsets, strict=True)), ca.SX.zeros(nx))
        Pyy, Pxy = Rm, ca.SX.zeros(nx, ny)
        for wt, d, Yj in zip(W, offsets, Ys, strict=True):
            dy = Yj - yb
            Pyy = Pyy + float(wt) * (dy @ dy.T)
            Pxy = Pxy + float(wt) * ((d - db) @ dy.T)
        e = e - (1 - miss) * yb
        K = ca.solve(Pyy, Pxy.T).T  # P_xy P_yy^-1 (Pyy symmetric)
        Sig = Qm - K @ Pyy @ K.T
    LS = ca.chol(0.5 * (Sig + Sig.T)).T
    step = K @ e + LS @ v
    xn = moved(step)
    yhat, ell = measure(xn)
    d = LQi @ step
    ell += -0.5 * ca.sumsqr(d) + ca.sum1(ca.log(ca.diag(LQi))) + 0.5 * ca.sumsqr(v) + \
        ca.sum1(ca.log(ca.diag(LS)))
    return xn, yhat, ell


def scalar(value) -> ca.SX:
    """The user's log-density as a scalar SX expression (a clear error otherwise)."""
    try:
        out = ca.SX(value)
    except (NotImplementedError, RuntimeError, TypeError):
        raise TypeError(f"loglik must return a scalar CasADi expression of y, yhat and p, "
                        f"got {type(value).__name__}") from None
    if out.numel() != 1:
        raise ValueError(f"loglik must return a scalar expression, got shape {out.shape}")
    return out


