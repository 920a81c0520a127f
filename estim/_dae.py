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

from typing import Any

import casadi as ca

from estim._discretise import as_column, euler_step, input_at, rk4_step

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


def dae_functions(model: Any) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function,
                                       ca.Function, ca.Function]:
    """``(f_c, F, F_x, H, H_x, Z)`` of a model with algebraic states (see the module)."""
    nx, nz, nu = model.nx, model.nz, model.nu
    x, z, u = ca.SX.sym("x", nx), ca.SX.sym("z", nz), ca.SX.sym("u", nu)
    psym = [ca.SX.sym(n) for n in model.param_names]
    p = ca.vertcat(*psym) if psym else ca.SX(0, 1)
    pdict = dict(zip(model.param_names, psym, strict=True))
    g = as_column(model._alg(x, z, u, pdict), nz, "alg")
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
    ode = as_column(model._ode(x, z, u, pdict), nx, "ode")
    y = as_column(model._output(x, z, u, pdict), model.ny, "output")
    linear = not ca.depends_on(gz, z) and nz <= LINEAR_SOLVE_MAX
    Z, f_c, H, H_x = (_solved(x, z, u, p, g, gz, ode, y) if linear else
                      _newton(model, x, z, u, p, g, ode, y))
    # the transition is an SX graph too when everything in it is (an explicit integrator
    # of equations solved in the graph); else a function the estimators' graphs call
    sx = linear and model.integrator in ("rk4", "euler")
    F, F_x = _transition(model, f_c, Z, (x, z, u, p, g, ode), sx)
    return f_c, F, F_x, H, H_x, Z


def _solved(x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX, gz: ca.SX, ode: ca.SX,
            y: ca.SX) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function]:
    """``(Z, f_c, H, H_x)`` for algebraic equations linear in ``z``: ``g = g_z z + g(0)``
    with ``g_z`` free of ``z``, so ``z = -g_z^{-1} g(0)`` exactly, written into the
    expression graph (one symbolic solve): SX graphs, evaluated without a call per solve,
    whose derivative is the implicit function theorem's. A ``g_z`` singular at some ``x``
    gives non-finite values there, as a failed solve."""
    zsol = -ca.solve(gz, ca.substitute(g, z, ca.DM.zeros(z.numel())))
    args, names = [x, u, p], ["x", "u", "p"]
    yh = ca.substitute(y, z, zsol)
    return (ca.Function("Z", args, [zsol], names, ["z"]),
            ca.Function("f_c", args, [ca.substitute(ode, z, zsol)], names, ["xdot"]),
            ca.Function("h", args, [yh], names, ["y"]),
            ca.Function("H_x", args, [ca.jacobian(yh, x)], names, ["C"]))


def _newton(model: Any, x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX, ode: ca.SX,
            y: ca.SX) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function]:
    """``(Z, f_c, H, H_x)`` with ``Z(x, u, p)`` a Newton solve from ``z0`` (NaN unless
    its residual is small), functions the estimators' graphs call."""
    G = ca.Function("g", [z, ca.vertcat(x, u, p)], [g])
    solve = ca.rootfinder("z_solve", "newton", G, _NEWTON)
    xm, um, pm = ca.MX.sym("x", x.numel()), ca.MX.sym("u", u.numel()), ca.MX.sym("p", p.numel())
    zs = solve(ca.DM(model.z0), ca.vertcat(xm, um, pm))
    r = G(zs, ca.vertcat(xm, um, pm))
    scale = 1 + ca.mmax(ca.fabs(ca.vertcat(xm, zs)))
    zs = ca.if_else(ca.mmax(ca.fabs(r)) <= RESIDUAL_TOL * scale, zs, ca.DM.nan(z.numel()))
    args, names = [xm, um, pm], ["x", "u", "p"]
    Z = ca.Function("Z", args, [zs], names, ["z"], _CALLED)
    f_xz = ca.Function("f_xz", [x, z, u, p], [ode])
    h_xz = ca.Function("h_xz", [x, z, u, p], [y])
    yh = h_xz(xm, Z(xm, um, pm), um, pm)
    return (Z, ca.Function("f_c", args, [f_xz(xm, Z(xm, um, pm), um, pm)], names, ["xdot"],
                           _CALLED),
            ca.Function("h", args, [yh], names, ["y"], _CALLED),
            ca.Function("H_x", args, [ca.jacobian(yh, xm)], names, ["C"], _CALLED))


def _transition(model: Any, f_c: ca.Function, Z: ca.Function,
                parts: tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX, ca.SX], sx: bool
                ) -> tuple[ca.Function, ca.Function]:
    """``(F, F_x)`` over one sample: the explicit integrator on ``f_c``, or CasADi's
    collocation or IDAS integrator on the DAE ``parts = (x, z, u, p, g, ode)``; an SX
    graph (``sx``) or a function the estimators' graphs call."""
    sym: Any = ca.SX if sx else ca.MX
    opts = {} if sx else _CALLED
    nw = model.nw
    xs, ws, ps = sym.sym("x", model.nx), sym.sym("w", nw), sym.sym("p", parts[3].numel())
    u_of = model.input_path(ws[:nw - 1] if model.variable_dt else ws)
    h = ws[nw - 1] if model.variable_dt else model.dt
    if model.integrator in ("rk4", "euler"):
        step = rk4_step if model.integrator == "rk4" else euler_step
        xn = step(f_c, xs, u_of, ps, h, model.substeps)
    else:
        xn = _integrated(model, *parts, Z, xs, ws, ps, u_of, h)
    names = ["x", "u", "p"]
    return (ca.Function("F", [xs, ws, ps], [xn], names, ["x_next"], opts),
            ca.Function("F_x", [xs, ws, ps], [ca.jacobian(xn, xs)], names, ["A"], opts))


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
