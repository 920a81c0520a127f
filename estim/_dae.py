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
    Radau IIA collocation of the DAE (:func:`radau_tableau`, 3 stages, order 5) on
    ``substeps`` finite elements: the collocation equations are written into the
    expression graph, solved there exactly when they are linear in the stages, else by
    one Newton solve per sample (:func:`_collocation`); the same discretisation as
    CasADi's ``collocation`` integrator and do-mpc's Radau collocation;
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
import numpy as np
from numpy.polynomial import Polynomial

from estim._discretise import as_column, equation, euler_step, input_at, rk4_step

__all__ = ["DAE_INTEGRATORS", "LINEAR_SOLVE_MAX", "RADAU_DEGREE", "RESIDUAL_TOL", "dae_functions",
           "radau_tableau"]

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
#: Stages of the Radau IIA collocation (order ``2 * RADAU_DEGREE - 1``).
RADAU_DEGREE = 3


def dae_functions(model: Any) -> tuple[ca.Function, ca.Function, ca.Function, ca.Function,
                                       ca.Function, ca.Function]:
    """``(f_c, F, F_x, H, H_x, Z)`` of a model with algebraic states (see the module)."""
    nx, nz, nu = model.nx, model.nz, model.nu
    x, z, u = ca.SX.sym("x", nx), ca.SX.sym("z", nz), ca.SX.sym("u", nu)
    psym = [ca.SX.sym(n) for n in model.param_names]
    p = ca.vertcat(*psym) if psym else ca.SX(0, 1)
    pdict = dict(zip(model.param_names, psym, strict=True))
    g = as_column(equation(model, "alg", model._alg, x, z, u, pdict), nz, "alg")
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
    ode = as_column(equation(model, "ode", model._ode, x, z, u, pdict), nx, "ode")
    y = as_column(equation(model, "output", model._output, x, z, u, pdict), model.ny, "output")
    linear = not ca.depends_on(gz, z) and nz <= LINEAR_SOLVE_MAX
    Z, f_c, H, H_x = (_solved(x, z, u, p, g, gz, ode, y) if linear else
                      _newton(model, x, z, u, p, g, ode, y))
    F, F_x = _transition(model, f_c, Z, (x, z, u, p, g, ode), linear)
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
    Z = ca.Function("Z", args, [zs], names, ["z"],
                    {**_CALLED, "custom_jacobian": _implicit_jacobian(x, z, u, p, g),
                     "jac_penalty": 0})
    f_xz = ca.Function("f_xz", [x, z, u, p], [ode])
    h_xz = ca.Function("h_xz", [x, z, u, p], [y])
    yh = h_xz(xm, Z(xm, um, pm), um, pm)
    return (Z, ca.Function("f_c", args, [f_xz(xm, Z(xm, um, pm), um, pm)], names, ["xdot"],
                           _CALLED),
            ca.Function("h", args, [yh], names, ["y"], _CALLED),
            ca.Function("H_x", args, [ca.jacobian(yh, xm)], names, ["C"], _CALLED))


def _implicit_jacobian(x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX) -> ca.Function:
    r"""The Jacobians of :math:`Z(x, u; p)` by the implicit function theorem, written out:
    :math:`\partial Z/\partial v = -g_z^{-1} g_v` at the solution, for ``v`` each of
    ``x, u, p`` (CasADi's ``custom_jacobian`` form: the inputs, then the nominal output).
    CasADi's own derivative of the Newton solve fails where :math:`g_z` is singular, and
    called inside another graph such a failure reads as zeros; written out it gives
    NaN there, which every estimator sees as a failed step."""
    gz = ca.jacobian(g, z)
    jacs = [-ca.solve(gz, ca.jacobian(g, v)) for v in (x, u, p)]
    D = ca.Function("dZ", [x, u, p, z], jacs)
    xm, um, pm = (ca.MX.sym(n, v.numel()) for n, v in (("x", x), ("u", u), ("p", p)))
    zm = ca.MX.sym("out_z", z.numel())
    return ca.Function("jac_Z", [xm, um, pm, zm], list(D(xm, um, pm, zm)),
                       ["x", "u", "p", "out_z"], ["jac_z_x", "jac_z_u", "jac_z_p"])


def _transition(model: Any, f_c: ca.Function, Z: ca.Function,
                parts: tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX, ca.SX], linear: bool
                ) -> tuple[ca.Function, ca.Function]:
    """``(F, F_x)`` over one sample: the explicit integrator on ``f_c``, Radau IIA
    collocation (:func:`_collocation`) or IDAS on the DAE ``parts = (x, z, u, p, g, ode)``;
    an SX graph where everything in it is one (``linear`` algebraic equations), else a
    function the estimators' graphs call."""
    if model.integrator == "collocation":
        xn, xs, ws, ps, sx = _collocation(model, f_c, Z, parts, linear)
    else:
        sx = linear and model.integrator in ("rk4", "euler")
        sym: Any = ca.SX if sx else ca.MX
        xs, ws, ps = sym.sym("x", model.nx), sym.sym("w", model.nw), sym.sym("p", parts[3].numel())
        u_of, h = _input_and_interval(model, ws)
        if model.integrator == "idas":
            xn = _idas(model, *parts, Z, xs, ws, ps, u_of)
        else:
            step = rk4_step if model.integrator == "rk4" else euler_step
            xn = step(f_c, xs, u_of, ps, h, model.substeps)
    names, opts = ["x", "u", "p"], {} if sx else _CALLED
    return (ca.Function("F", [xs, ws, ps], [xn], names, ["x_next"], opts),
            ca.Function("F_x", [xs, ws, ps], [ca.jacobian(xn, xs)], names, ["A"], opts))


def _input_and_interval(model: Any, w: Any) -> tuple[Any, Any]:
    """The input over the sample (held or a path in the fraction ``s``) and the sample's
    length (``model.dt``, or the last entry of ``w`` for a ``variable_dt`` model)."""
    nw = w.numel()
    if model.variable_dt:
        return model.input_path(w[:nw - 1]), w[nw - 1]
    return model.input_path(w), model.dt


def radau_tableau(degree: int = RADAU_DEGREE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""The Butcher tableau ``(A, b, c)`` of the ``degree``-stage Radau IIA method:
    collocation at the Radau points :math:`c_i` (:math:`c_s = 1`) with
    :math:`A_{ij} = \int_0^{c_i} \ell_j(\tau)\,d\tau`, :math:`\ell_j` the Lagrange
    polynomials on the :math:`c_i`, and :math:`b = A_{s,:}` (stiffly accurate); order
    :math:`2s - 1`."""
    c = np.array(ca.collocation_points(degree, "radau"))
    A = np.empty((degree, degree))
    for j in range(degree):
        ell = Polynomial.fromroots(np.delete(c, j))
        ell = ell / ell(c[j])
        A[:, j] = ell.integ()(c)
    return A, A[-1].copy(), c


def _collocation(model: Any, f_c: ca.Function, Z: ca.Function,
                 parts: tuple[ca.SX, ca.SX, ca.SX, ca.SX, ca.SX, ca.SX], linear: bool
                 ) -> tuple[Any, Any, Any, Any, bool]:
    r"""One sample of Radau IIA collocation: ``substeps`` elements of length
    :math:`h_e`, each with stage derivatives :math:`K_i` (and, unless the algebraic
    equations are solved in the graph, stage algebraic states :math:`z_i`) solving

    .. math::
        K_i = f(x_i, z_i, u(t_i)), \quad 0 = g(x_i, z_i, u(t_i)), \quad
        x_i = x_e + h_e \textstyle\sum_j A_{ij} K_j, \qquad
        x_{e+1} = x_e + h_e \textstyle\sum_j b_j K_j

    (the same discretisation as CasADi's ``collocation`` integrator and do-mpc's
    orthogonal collocation with Radau points). Equations affine in the stages (a linear
    model) are solved in the expression graph, element by element; otherwise by one Newton
    solve over all elements (:func:`_newton_stages`). Returns ``(x_next, x, w, p,
    is_sx)``."""
    x, z, u, p, g, ode = parts
    nx, nz, n_el = model.nx, model.nz, model.substeps
    A, b, c = radau_tableau()
    ns = len(c)
    nv = ns * (nx if linear else nx + nz)  # unknowns per element
    # one element from x_e at the fraction s_e of the sample: residual and x_{e+1}
    ve, xe, se = ca.SX.sym("V", nv), ca.SX.sym("x_e", nx), ca.SX.sym("s_e")
    ws, ps = ca.SX.sym("w", model.nw), ca.SX.sym("p", p.numel())
    u_of, h = _input_and_interval(model, ws)
    he, K = h / n_el, ca.reshape(ve[:ns * nx], nx, ns)
    dae = ca.Function("dae_at", [x, z, u, p], [ode, g])
    r = []
    for i in range(ns):
        xi, ui = xe + he * ca.mtimes(K, ca.DM(A[i])), input_at(u_of, se + c[i] / n_el)
        if linear:
            r.append(K[:, i] - f_c(xi, ui, ps))
        else:
            fi, gi = dae(xi, ve[ns * nx + i * nz:ns * nx + (i + 1) * nz], ui, ps)
            r += [K[:, i] - fi, gi]
    re, x_next = ca.vertcat(*r), xe + he * ca.mtimes(K, ca.DM(b))
    jac = ca.jacobian(re, ve)
    xs = ca.SX.sym("x", nx)
    if not ca.depends_on(jac, ve):  # affine in the stages: solved in the graph
        sol = -ca.solve(jac, ca.substitute(re, ve, ca.DM.zeros(nv)))
        element = ca.Function("radau_element", [xe, se, ws, ps],
                              [ca.substitute(x_next, ve, sol)])
        xn = xs
        for e in range(n_el):
            xn = element(xn, e / n_el, ws, ps)
        return xn, xs, ws, ps, True
    element = ca.Function("radau_element", [ve, xe, se, ws, ps], [re, x_next])
    V = ca.SX.sym("V", nv * n_el)
    res, xn = [], xs
    for e in range(n_el):
        re_e, xn = element(V[e * nv:(e + 1) * nv], xn, e / n_el, ws, ps)
        res.append(re_e)
    return (*_newton_stages(model, f_c, Z, ca.vertcat(*res), V, xn, (xs, ws, ps), nv), False)


def _newton_stages(model: Any, f_c: ca.Function, Z: ca.Function, r: ca.SX, V: ca.SX,
                   xn: ca.SX, args: tuple[ca.SX, ca.SX, ca.SX], nv: int
                   ) -> tuple[ca.MX, ca.MX, ca.MX, ca.MX]:
    """The collocation equations ``r(V; x, w, p) = 0`` solved by Newton's method (a
    CasADi ``rootfinder``, derivatives by the implicit function theorem) and the state
    ``xn(V, x, w, p)`` at their solution; ``(x_next, x, w, p)`` as MX."""
    xs, ws, ps = args
    R = ca.Function("radau_r", [V, ca.vertcat(*args)], [r])
    solve = ca.rootfinder("radau_stages", "newton", R, _NEWTON)
    xm, wm, pm = (ca.MX.sym(n, s.numel()) for n, s in zip("xwp", args, strict=True))
    u_of, _ = _input_and_interval(model, wm)
    u0 = input_at(u_of, 0.0)
    k0 = ca.repmat(f_c(xm, u0, pm), len(radau_tableau()[2]), 1)
    guess = k0 if nv == k0.numel() else ca.vertcat(k0, ca.repmat(Z(xm, u0, pm),
                                                                 (nv - k0.numel()) // model.nz, 1))
    par = ca.vertcat(xm, wm, pm)
    Vs = solve(ca.repmat(guess, V.numel() // nv, 1), par)
    scale = 1 + ca.mmax(ca.fabs(ca.vertcat(xm, Vs)))
    ok = ca.mmax(ca.fabs(R(Vs, par))) <= RESIDUAL_TOL * scale
    xn_of = ca.Function("radau_x", [V, xs, ws, ps], [xn])
    return ca.if_else(ok, xn_of(Vs, xm, wm, pm), ca.DM.nan(model.nx)), xm, wm, pm


def _idas(model: Any, x: ca.SX, z: ca.SX, u: ca.SX, p: ca.SX, g: ca.SX, ode: ca.SX,
          Z: ca.Function, xm: ca.MX, wm: ca.MX, pm: ca.MX, u_of: Any) -> ca.MX:
    """The state after one sample by SUNDIALS' IDAS on the DAE, in the fraction ``s`` of
    the sample (``dx/ds = h f``, ``0 = g``), from the consistent algebraic state."""
    s = ca.SX.sym("s")
    w = ca.SX.sym("w", wm.numel())
    path, hs = _input_and_interval(model, w)
    f_s, g_s = ca.Function("dae_at", [x, z, u, p], [ode, g])(x, z, input_at(path, s), p)
    dae = {"x": x, "z": z, "t": s, "p": ca.vertcat(w, p), "ode": hs * f_s, "alg": g_s}
    integ = ca.integrator("F_idas", "idas", dae, 0.0, 1.0, _IDAS)
    z0 = Z(xm, input_at(u_of, 0.0), pm)
    return integ(x0=xm, z0=z0, p=ca.vertcat(wm, pm))["xf"]
