r"""Semi-explicit index-1 differential-algebraic models: ``Model(algebraic=..., alg=...)``.

.. math::
    \dot x = f(x, z, u; p), \qquad 0 = g(x, z, u; p), \qquad y = h(x, z, u; p),

with :math:`\partial g / \partial z` nonsingular, so that the algebraic states are
an implicit function :math:`z = Z(x, u; p)` of the differential ones. That function
is a Newton solve (CasADi's ``rootfinder``) from the model's guess ``z0``; its
derivatives come from the implicit function theorem,
:math:`\partial Z / \partial x = -g_z^{-1} g_x`, exact, through CasADi's algorithmic
differentiation. Every estimator then sees what it sees of an ODE model: the
transition :math:`F(x, w; p)`, the output :math:`H(x, u; p) = h(x, Z(x, u), u)` and
their Jacobians (Functions that call the solve; the particle filters evaluate them
with CasADi's ``map``).

Integrators of a transition:

``"rk4"``, ``"euler"``
    the reduced ODE :math:`\dot x = f(x, Z(x, u), u)`, the algebraic equations solved
    at every stage;
``"collocation"``
    CasADi's collocation integrator on the DAE (Radau IIA points, order
    ``2 * 3 - 1 = 5`` at the default ``substeps`` finite elements of degree 3),
    started from the consistent :math:`z`;
``"idas"``
    SUNDIALS' IDAS (variable order BDF, tolerances 1e-10), started from the
    consistent :math:`z`.

A Newton solve that does not converge (the residual above :data:`RESIDUAL_TOL`)
gives NaN, not a wrong :math:`z`: an estimator's step then fails and re-anchors, as
on any non-finite prediction, and :meth:`Model.z` raises a ``ValueError``.

References
----------
K. E. Brenan, S. L. Campbell, L. R. Petzold, *Numerical Solution of Initial-Value
Problems in Differential-Algebraic Equations*, SIAM 1996; E. Hairer, G. Wanner,
*Solving Ordinary Differential Equations II*, Springer 1996, ch. VI (Radau IIA).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca

from estim._discretise import euler_step, input_at, rk4_step

__all__ = ["DAE_INTEGRATORS", "LINEAR_SOLVE_MAX", "RESIDUAL_TOL", "dae_functions"]

#: Algebraic equations linear in ``z`` with at most this many algebraic states are solved
#: in the expression graph (see :func:`_linear`); others by a Newton solve.
LINEAR_SOLVE_MAX = 12
#: Integrators of a model with algebraic states.
DAE_INTEGRATORS = ("rk4", "euler", "collocation", "idas")
#: A Newton solve of the algebraic equations whose residual stays above this (infinity
#: norm, relative to 1 + the largest term) gives NaN.
RESIDUAL_TOL = 1e-9
_NEWTON = {"abstol": 1e-13, "max_iter": 50, "error_on_fail": False}
#: the model's Functions are called, not inlined, from the estimators' SX graphs (the
#: Newton solve and its derivatives have no SX form)
_CALLED = {"never_inline": True}
_IDAS = {"abstol": 1e-10, "reltol": 1e-10, "calc_ic": True}
_COLLOCATION = {"interpolation_order": 3, "collocation_scheme": "radau",
                "rootfinder": "newton", "rootfinder_options": {"abstol": 1e-13,
                                                               "error_on_fail": False}}


def dae_functions(model: Any, column: Callable[[Any, int, str], ca.SX]
                  ) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function, ca.Function,
                             ca.Function]:
    """``(f_c, F, F_x, H, H_x, Z)`` of a model with algebraic states (see the module);
    ``column(expr, n, what)`` turns a user's equation result into an ``(n, 1)``
    expression with a clear error."""
    nx, nz, nu, nw = model.nx, model.nz, model.nu, model.nw
    x, z, u = ca.SX.sym("x", nx), ca.SX.sym("z", nz), ca.SX.sym("u", nu)
    psym = [ca.SX.sym(n) for n in model.param_names]
    p = ca.vertcat(*psym) if psym else ca.SX(0, 1)
    pdict = dict(zip(model.param_names, psym, strict=True))
    g = column(model._alg(x, z, u, pdict), nz, "alg")
    gz = ca.jacobian(g, z)
    if ca.sprank(gz.sparsity()) < nz:
        free = [model.algebraic_names[j] for j in range(nz) if not ca.depends_on(g, z[j])]
        raise ValueError(
            "alg: the Jacobian dg/dz of the algebraic equations is structurally singular "
            f"(rank {ca.sprank(gz.sparsity())} < {nz}"
            + (f"; no equation contains {free}" if free else "")
            + "): the model is not index 1 (an index-2 or higher system, e.g. a pendulum "
            "whose constraint holds only the positions); differentiate the constraints "
            "until they determine every algebraic state")
    ode = column(model._ode(x, z, u, pdict), nx, "ode")
    y = column(model._output(x, z, u, pdict), model.ny, "output")
    if not ca.depends_on(gz, z) and nz <= LINEAR_SOLVE_MAX:
        return _linear(model, x, z, u, p, g, gz, ode, y)
    G = ca.Function("g", [z, ca.vertcat(x, u, p)], [g])
    solve = ca.rootfinder("z_solve", "newton", G, _NEWTON)
    # Z(x, u, p): Newton from z0, NaN unless the residual is small
    xm, um, pm = ca.MX.sym("x", nx), ca.MX.sym("u", nu), ca.MX.sym("p", p.numel())
    zs = solve(ca.DM(model.z0), ca.vertcat(xm, um, pm))
    r = G(zs, ca.vertcat(xm, um, pm))
    scale = 1 + ca.mmax(ca.fabs(ca.vertcat(xm, zs)))
    zs = ca.if_else(ca.mmax(ca.fabs(r)) <= RESIDUAL_TOL * scale, zs, ca.DM.nan(nz))
    Z = ca.Function("Z", [xm, um, pm], [zs], ["x", "u", "p"], ["z"], _CALLED)
    f_xz = ca.Function("f_xz", [x, z, u, p], [ode])
    h_xz = ca.Function("h_xz", [x, z, u, p], [y])
    f_c = ca.Function("f_c", [xm, um, pm], [f_xz(xm, Z(xm, um, pm), um, pm)],
                      ["x", "u", "p"], ["xdot"], _CALLED)
    yh = h_xz(xm, Z(xm, um, pm), um, pm)
    H = ca.Function("h", [xm, um, pm], [yh], ["x", "u", "p"], ["y"], _CALLED)
    H_x = ca.Function("H_x", [xm, um, pm], [ca.jacobian(yh, xm)], ["x", "u", "p"], ["C"],
                      _CALLED)
    wm = ca.MX.sym("w", nw)
    u_of = model.input_path(wm[:nw - 1] if model.variable_dt else wm)
    h = wm[nw - 1] if model.variable_dt else model.dt
    if model.integrator in ("rk4", "euler"):
        step = rk4_step if model.integrator == "rk4" else euler_step
        xn = step(f_c, xm, u_of, pm, h, model.substeps)
    else:
        xn = _integrated(model, x, z, u, p, g, ode, Z, xm, wm, pm, u_of, h)
    F = ca.Function("F", [xm, wm, pm], [xn], ["x", "u", "p"], ["x_next"], _CALLED)
    F_x = ca.Function("F_x", [xm, wm, pm], [ca.jacobian(xn, xm)], ["x", "u", "p"], ["A"],
                      _CALLED)
    return f_c, F, F_x, H, H_x, Z


def _linear(model: Any, x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX, gz: ca.SX,
            ode: ca.SX, y: ca.SX) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function,
                                           ca.Function, ca.Function]:
    """:func:`dae_functions` for algebraic equations linear in ``z``: ``g = g_z z + g(0)``
    with ``g_z`` free of ``z``, so ``z = -g_z^{-1} g(0)`` exactly, written into the
    expression graph (one symbolic solve): every Function is then an SX graph, evaluated
    without a call per solve, and its derivative is the implicit function theorem's. A
    ``g_z`` singular at some ``x`` gives non-finite values there, as a failed solve."""
    zsol = -ca.solve(gz, ca.substitute(g, z, ca.DM.zeros(z.numel())))
    args, names = [x, u, p], ["x", "u", "p"]
    Z = ca.Function("Z", args, [zsol], names, ["z"])
    xdot = ca.substitute(ode, z, zsol)
    yh = ca.substitute(y, z, zsol)
    f_c = ca.Function("f_c", args, [xdot], names, ["xdot"])
    H = ca.Function("h", args, [yh], names, ["y"])
    H_x = ca.Function("H_x", args, [ca.jacobian(yh, x)], names, ["C"])
    nw = model.nw
    if model.integrator in ("rk4", "euler"):
        w = ca.SX.sym("w", nw)
        u_of = model.input_path(w[:nw - 1] if model.variable_dt else w)
        h = w[nw - 1] if model.variable_dt else model.dt
        step = rk4_step if model.integrator == "rk4" else euler_step
        xn = step(f_c, x, u_of, p, h, model.substeps)
        return (f_c, ca.Function("F", [x, w, p], [xn], names, ["x_next"]),
                ca.Function("F_x", [x, w, p], [ca.jacobian(xn, x)], names, ["A"]), H, H_x, Z)
    xm, wm, pm = ca.MX.sym("x", x.numel()), ca.MX.sym("w", nw), ca.MX.sym("p", p.numel())
    u_of = model.input_path(wm[:nw - 1] if model.variable_dt else wm)
    h = wm[nw - 1] if model.variable_dt else model.dt
    xn = _integrated(model, x, z, u, p, g, ode, Z, xm, wm, pm, u_of, h)
    F = ca.Function("F", [xm, wm, pm], [xn], names, ["x_next"], _CALLED)
    F_x = ca.Function("F_x", [xm, wm, pm], [ca.jacobian(xn, xm)], names, ["A"], _CALLED)
    return f_c, F, F_x, H, H_x, Z


def _integrated(model: Any, x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX, ode: ca.SX,
                Z: ca.Function, xm: ca.MX, wm: ca.MX, pm: ca.MX, u_of: Any, h: Any) -> ca.MX:
    """The state after one sample by CasADi's ``"collocation"`` or ``"idas"`` integrator
    on the DAE, in the fraction ``s`` of the sample (``dx/ds = h f``, ``0 = g``), from
    the consistent algebraic state."""
    s = ca.SX.sym("s")
    w = ca.SX.sym("w", wm.numel())
    path = model.input_path(w[:w.numel() - 1] if model.variable_dt else w)
    us = input_at(path, s)
    hs = w[w.numel() - 1] if model.variable_dt else model.dt
    sub = ca.Function("dae_at", [x, z, u, p], [ode, g])
    f_s, g_s = sub(x, z, us, p)
    dae = {"x": x, "z": z, "t": s, "p": ca.vertcat(w, p), "ode": hs * f_s, "alg": g_s}
    if model.integrator == "idas":
        integ = ca.integrator("F_idas", "idas", dae, 0.0, 1.0, _IDAS)
    else:
        opts = dict(_COLLOCATION, number_of_finite_elements=model.substeps)
        integ = ca.integrator("F_collocation", "collocation", dae, 0.0, 1.0, opts)
    z0 = Z(xm, input_at(u_of, 0.0), pm)
    return integ(x0=xm, z0=z0, p=ca.vertcat(wm, pm))["xf"]
