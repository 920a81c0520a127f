r"""The real-time iteration of moving horizon estimation (:class:`~estim.MHE` with
``rti=True``), split into a preparation and a feedback phase.

One Gauss-Newton step per sample on the window's least-squares problem

.. math::
    \min_{x_0..x_{N-1}} \|x_0 - \bar x\|^2_{\bar P^{-1}}
    + \sum_{k=0}^{N-2} \|x_{k+1} - F(x_k, u_k)\|^2_{Q^{-1}}
    + \sum_{k=0}^{N-1} \|y_k - h(x_k)\|^2_{R_k^{-1}} ,

linearised at the shifted previous window (the newest slot predicted by :math:`F`).
The Gauss-Newton matrix is block tridiagonal, with diagonal blocks
:math:`H_k = C_k^\top R_k^{-1} C_k + [k = 0]\, \bar P^{-1} + [k \ge 1]\, Q^{-1}
+ [k \le N-2]\, A_k^\top Q^{-1} A_k` and off-diagonal blocks
:math:`H_{k,k+1} = -A_k^\top Q^{-1}` (:math:`A_k = \partial F/\partial x`,
:math:`C_k = \partial h/\partial x`; :math:`R_k^{-1}` the inverse of the marginal of
:math:`R` over the measured outputs, zero elsewhere). Forward block elimination,

.. math::
    \tilde S_0 = H_0, \quad
    \tilde S_k = H_k - H_{k-1,k}^\top \tilde S_{k-1}^{-1} H_{k-1,k}, \quad
    \tilde g_k = g_k - H_{k-1,k}^\top \tilde S_{k-1}^{-1} \tilde g_{k-1},

reaches the newest slot without its measurement: that is the **preparation**
(:meth:`MHE.prepare <estim.MHE.prepare>`, before :math:`y_{N-1}` arrives), which also
keeps :math:`v_k = -\tilde S_k^{-1} \tilde g_k` and :math:`M_k = \tilde S_k^{-1}
H_{k,k+1}` for the back-substitution. The **feedback** (:meth:`MHE.step
<estim.MHE.step>`) adds the measurement,

.. math::
    S = \tilde S_{N-1}^0 + C^\top R^{-1} C, \quad
    \Delta_{N-1} = -S^{-1} \big(\tilde g^0_{N-1} - C^\top R^{-1} (y - h)\big),
    \quad \Delta_k = v_k - M_k \Delta_{k+1},

an :math:`O(N n_x^2)` computation, and :math:`S^{-1}` is the covariance of the new
estimate (the Laplace covariance of the last state, as for the converged MHE). A ridge
of :math:`10^{-10}` on the diagonal keeps the elimination defined when the window alone
does not determine a state. While the window fills (its first slots unused, chained to
the first used one at no cost) each sample's window is solved to convergence by projected
Gauss-Newton steps with the same Functions: variables at a bound whose gradient points out
of the box are held, and the step is halved until the projected point does not raise the
window's cost (:meth:`MHE._startup <estim.MHE._startup>`). Every weight is computed inside
the Functions from :math:`\bar P`, :math:`Q^{-1}` and :math:`R`, so that code generated
from them computes exactly what they compute.

References
----------
M. Diehl, H. G. Bock, J. P. Schlöder, "A real-time iteration scheme for nonlinear
optimization in optimal feedback control", SIAM J. Control Optim. 43(5), 2005;
P. Kühl, M. Diehl, T. Kraus, J. P. Schlöder, H. G. Bock, "A real-time algorithm for
moving horizon state and parameter estimation", Comput. Chem. Eng. 35(1), 2011.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca

from estim.model import Model

#: Diagonal ridge of the Gauss-Newton matrix's blocks.
RIDGE = 1e-10


def _weighed(model: Model, N: int, core: ca.Function, process_weight: Callable
             ) -> ca.Function:
    r"""``core`` (whose ``Qinv`` input holds the transitions' weights :math:`Q_d(\Delta
    t_k)^{-1}`, one column each) with the density :math:`L Q_c L^\top` in that input
    instead: the weights made by one Function of a transition mapped over the window
    (``process_weight(model, W, x, w) -> M``, :math:`M^\top M = Q_d^{-1}`:
    :func:`~estim.solvers.kalman.continuous.interval_weight` at the window's
    :math:`x_k`), which generated code then holds once, not once per transition."""
    nx = model.nx
    x, w, D = ca.SX.sym("x", nx), ca.SX.sym("w", model.nw), ca.SX.sym("D", nx, nx)
    M = process_weight(model, D, x, w)
    weight = ca.Function("mhe_rti_interval_weight", [x, w, D], [ca.vec(M.T @ M)])
    args = [ca.MX.sym(core.name_in(i), core.sparsity_in(i)) for i in range(core.n_in())]
    names = [core.name_in(i) for i in range(core.n_in())]
    i_q, i_x, i_u = names.index("Qinv"), names.index("X"), names.index("U")
    args[i_q] = ca.MX.sym("Qinv", nx, nx)
    inner = list(args)
    inner[i_q] = weight.map(N - 1)(args[i_x][:, :N - 1], args[i_u], ca.repmat(args[i_q], 1,
                                                                             N - 1))
    return ca.Function(core.name(), args, core.call(inner), names,
                       [core.name_out(i) for i in range(core.n_out())])


def build(model: Model, N: int, process_weight: Callable | None = None
          ) -> tuple[ca.Function, ca.Function, ca.Function]:
    r"""The preparation, feedback and cost Functions of a window of ``N`` slots.

    ``prepare(X, Y, mask, U, Up, a, om, xbar, Pbar, arrival, Qinv, R, free) -> (S0, g0,
    C, h, v, M, grad)``: ``X (nx, N)`` the window to linearise at; ``Y (ny, N-1)`` the
    measurements of all slots but the newest (0 where missing) with ``mask`` (1 where
    measured); ``U (nw, N-1)`` the transitions' inputs; ``Up (nu, N)`` the inputs ``h``
    sees; ``a (N)`` the arrival cost's slot (1 on the first used slot) and ``om (N-1)``
    the links that carry the model (1; 0 chains an unused slot to the next at no cost, as
    the converged MHE's growing window does); the arrival cost
    :math:`\|x - \bar x\|^2_{\bar P^{-1}}` (``arrival`` 0 without one); ``Qinv``
    :math:`Q^{-1}`; ``R``; ``free (nx, N)`` 1 for the variables that may move (a held
    variable's row and column of the Gauss-Newton matrix become the identity's and its
    gradient 0). ``grad (nx, N)`` is the cost's gradient without the newest measurement.

    ``feedback(S0, g0, C, h, y, mask, R, v, M, free) -> (dX, P, grad_y)``: the step
    ``dX (nx, N)`` and the newest state's covariance ``P (nx, nx)`` for the measurement
    ``y`` (0 where missing, ``mask`` 1 where measured; ``free (nx)`` the newest slot's),
    and the newest measurement's term of the gradient.

    ``cost(X, Y, mask, U, Up, a, om, xbar, Pbar, arrival, Qinv, R, y, mask_y) -> cost``:
    half the window's weighted sum of squares, the newest measurement ``y`` included.

    ``process_weight`` (a continuous noise): ``Qinv`` is the density :math:`L Q_c
    L^\top`, and transition ``k`` is weighed by :math:`M^\top M` from
    ``process_weight(model, Qinv, x_k, u_k)``, :math:`Q_d(\Delta t_k)^{-1}` of the drift
    linearised at the window's :math:`x_k`
    (:func:`~estim.solvers.kalman.continuous.interval_weight`), held constant in the
    Gauss-Newton step (the weights of the converged windows, re-linearised at each
    preparation).
    """
    nx, ny, nu, nw = model.nx, model.ny, model.nu, model.nw
    p = ca.DM(model.p)
    X = ca.SX.sym("X", nx, N)
    Y, mask = ca.SX.sym("Y", ny, N - 1), ca.SX.sym("mask", ny, N - 1)
    U = ca.SX.sym("U", nw, N - 1)
    Up = ca.SX.sym("Up", nu, N)
    a, om = ca.SX.sym("a", N), ca.SX.sym("om", N - 1)
    xbar, Pbar = ca.SX.sym("xbar", nx), ca.SX.sym("Pbar", nx, nx)
    arrival = ca.SX.sym("arrival")
    Qinv, R = ca.SX.sym("Qinv", nx, nx), ca.SX.sym("R", ny, ny)
    eye = ca.DM.eye(nx)
    P0inv = arrival * ca.solve(Pbar, eye)
    # with a continuous noise the transitions' weights are inputs of the core Functions
    # here, made from the density by one Function mapped over the window (below)
    Wk = ca.SX.sym("Wk", nx * nx, N - 1) if process_weight is not None else None
    weights = [om[k] * (ca.reshape(Wk[:, k], nx, nx) if Wk is not None else Qinv)
               + (1 - om[k]) * eye for k in range(N - 1)]
    tangent = _TangentTerms(model) if not model.manifold.euclidean_states else None
    if tangent is None:
        Hd = [a[k] * P0inv + RIDGE * eye for k in range(N)]
        g = [a[k] * (P0inv @ (X[:, k] - xbar)) for k in range(N)]
    else:  # the arrival residual x - xbar on the manifold; a unit diagonal on the pads
        Hd, g = [], []
        for k in range(N):
            e0, J0 = tangent.arrival(X[:, k], xbar)
            Hd.append(a[k] * (J0.T @ P0inv @ J0) + RIDGE * eye + tangent.pads)
            g.append(a[k] * (J0.T @ (P0inv @ e0)))
    Hoff = []
    for k in range(N - 1):
        x, xn = X[:, k], X[:, k + 1]
        W = weights[k]
        if tangent is None:
            A = model.F_x(x, U[:, k], p)
            e = om[k] * (xn - model.F(x, U[:, k], p)) + (1 - om[k]) * (xn - x)
            B = om[k] * A + (1 - om[k]) * eye  # -de/dx_k
            Hd[k] += B.T @ W @ B
            Hd[k + 1] += W
            Hoff.append(-B.T @ W)
            g[k] -= B.T @ (W @ e)
            g[k + 1] += W @ e
        else:  # e = x_{k+1} - F(x_k) on the manifold, derivatives along the retraction
            e, Ja, Jb = tangent.transition(x, xn, U[:, k], om[k])
            Hd[k] += Ja.T @ W @ Ja
            Hd[k + 1] += Jb.T @ W @ Jb
            Hoff.append(Ja.T @ W @ Jb)
            g[k] += Ja.T @ (W @ e)
            g[k + 1] += Jb.T @ (W @ e)
        Rinv = _masked_inverse(R, mask[:, k])
        h, C = _measurement(model, tangent, x, Up[:, k], p)
        Hd[k] += C.T @ Rinv @ C
        g[k] -= C.T @ (Rinv @ model.manifold.output_difference(Y[:, k], h))
    # the free set: a variable held at its bound has its row and column of the
    # Gauss-Newton matrix replaced by the identity's and its gradient by 0 (step 0)
    free = ca.SX.sym("free", nx, N)
    Fd = [ca.diag(free[:, k]) for k in range(N)]
    grad = ca.horzcat(*g)
    Hd = [Fd[k] @ Hd[k] @ Fd[k] + eye - Fd[k] for k in range(N)]
    Hoff = [Fd[k] @ Hoff[k] @ Fd[k + 1] for k in range(N - 1)]
    g = [Fd[k] @ g[k] for k in range(N)]
    S, gt = Hd[0], g[0]
    v, M = [], []
    for k in range(1, N):
        Z = ca.solve(S, ca.horzcat(Hoff[k - 1], gt))  # S~_{k-1}^{-1} [H_{k-1,k}, g~_{k-1}]
        v.append(-Z[:, nx])
        M.append(ca.vec(Z[:, :nx]))
        S = Hd[k] - Hoff[k - 1].T @ Z[:, :nx]
        gt = g[k] - Hoff[k - 1].T @ Z[:, nx]
    xN, upN = X[:, N - 1], Up[:, N - 1]
    hN, CN = _measurement(model, tangent, xN, upN, p)
    names = ["X", "Y", "mask", "U", "Up", "a", "om", "xbar", "Pbar", "arrival", "Qinv", "R"]
    inputs = [X, Y, mask, U, Up, a, om, xbar, Pbar, arrival, Qinv if Wk is None else Wk, R]
    prepare = ca.Function(
        "mhe_rti_prepare", inputs + [free],
        [0.5 * (S + S.T), gt, CN, hN,
         ca.horzcat(*v) if v else ca.SX(nx, 0), ca.horzcat(*M) if M else ca.SX(nx * nx, 0),
         grad],
        names + ["free"], ["S0", "g0", "C", "h", "v", "M", "grad"])
    # the cost of the window with the newest slot's measurement (the start-up's line search)
    yN, mN = ca.SX.sym("yN", ny), ca.SX.sym("maskN", ny)
    man = model.manifold
    terms = []
    for k in range(N):
        e0 = X[:, k] - xbar if tangent is None else tangent.arrival(X[:, k], xbar)[0]
        terms.append(a[k] * ca.dot(e0, P0inv @ e0))
    for k in range(N):
        yk, mk = (Y[:, k], mask[:, k]) if k < N - 1 else (yN, mN)
        r = man.output_difference(yk, model.H(X[:, k], Up[:, k], p))
        terms.append(ca.dot(r, _masked_inverse(R, mk) @ r))
        if k < N - 1:
            x, xn = X[:, k], X[:, k + 1]
            e = om[k] * (xn - model.F(x, U[:, k], p)) + (1 - om[k]) * (xn - x) \
                if tangent is None else tangent.transition(x, xn, U[:, k], om[k])[0]
            terms.append(ca.dot(e, weights[k] @ e))
    cost = ca.Function("mhe_rti_cost", inputs + [yN, mN],
                       [0.5 * ca.sum1(ca.vertcat(*terms))], names + ["y", "mask_y"], ["cost"])
    if process_weight is not None:
        prepare, cost = (_weighed(model, N, prepare, process_weight),
                         _weighed(model, N, cost, process_weight))
    # feedback
    S0s, g0s = ca.SX.sym("S0", nx, nx), ca.SX.sym("g0", nx)
    Cs, hs = ca.SX.sym("C", ny, nx), ca.SX.sym("h", ny)
    y, ym = ca.SX.sym("y", ny), ca.SX.sym("mask", ny)
    Rs = ca.SX.sym("R", ny, ny)
    vs, Ms = ca.SX.sym("v", nx, N - 1), ca.SX.sym("M", nx * nx, N - 1)
    fN = ca.SX.sym("free", nx)
    FN = ca.diag(fN)
    Rinv = _masked_inverse(Rs, ym)
    g_meas = -Cs.T @ (Rinv @ man.output_difference(y, hs))  # the newest measurement's gradient
    S = S0s + FN @ (Cs.T @ Rinv @ Cs) @ FN
    S = 0.5 * (S + S.T)
    d: list[Any] = [None] * N
    d[N - 1] = -ca.solve(S, g0s + FN @ g_meas)
    for k in range(N - 2, -1, -1):
        d[k] = vs[:, k] - ca.reshape(Ms[:, k], nx, nx) @ d[k + 1]
    P = ca.solve(S, eye)
    feedback = ca.Function("mhe_rti_feedback", [S0s, g0s, Cs, hs, y, ym, Rs, vs, Ms, fN],
                           [ca.horzcat(*d), 0.5 * (P + P.T), g_meas],
                           ["S0", "g0", "C", "h", "y", "mask", "R", "v", "M", "free"],
                           ["dX", "P", "grad_y"])
    return prepare, feedback, cost


def _measurement(model: Model, tangent: _TangentTerms | None, x, up, p) -> tuple:
    """``(h(x), dh/dx)``; on a manifold the derivative along the retraction."""
    if tangent is None:
        return model.H(x, up, p), model.H_x(x, up, p)
    return tangent.measurement(x, up)


class _TangentTerms:
    """The window's residuals on a manifold as Functions of the stored states, with their
    derivatives along the retraction at zero, padded to ``nx`` (see
    :class:`~estim.solvers.least_squares.stages.StageFunctions`): the arrival ``x - xbar``, the
    transition ``x_{k+1} - (om F(x_k) + (1 - om) x_k)`` and the output map."""

    def __init__(self, model: Model):
        M, nx = model.manifold, model.nx
        p = ca.DM(model.p)
        x, xn, xbar = ca.SX.sym("x", nx), ca.SX.sym("xn", nx), ca.SX.sym("xbar", nx)
        u, up, om = ca.SX.sym("u", model.nw), ca.SX.sym("up", model.nu), ca.SX.sym("om")
        d, dn = ca.SX.sym("d", nx), ca.SX.sym("dn", nx)
        zero = [ca.DM.zeros(nx)] * 2
        xr, xnr = M.retract(x, d[M.slots]), M.retract(xn, dn[M.slots])

        def at_zero(name, ins, outs, ds):
            return ca.Function(name, ins, ca.substitute(outs, ds, zero[:len(ds)]))

        e0 = M.padded(M.local(xbar, xr))
        self.arrival = at_zero("arrival", [x, xbar], [e0, ca.jacobian(e0, d)], [d])
        G = om * model.F(xr, u, p) + (1 - om) * xr
        e = M.padded(M.local(G, xnr))
        self.transition = at_zero("transition", [x, xn, u, om],
                                  [e, ca.jacobian(e, d), ca.jacobian(e, dn)], [d, dn])
        h = model.H(xr, up, p)
        self.measurement = at_zero("measurement", [x, up], [h, ca.jacobian(h, d)], [d])
        self.pads = ca.diag(ca.DM([float(i in M.pads) for i in range(nx)]))


def _masked_inverse(R, mask):
    """The inverse of ``R``'s marginal over the measured rows (``mask`` 1), embedded with
    zeros elsewhere: :math:`D (D R D + I - D)^{-1} D`, ``D = diag(mask)``."""
    D = ca.diag(mask)
    n = R.shape[0]
    return D @ ca.solve(D @ R @ D + ca.DM.eye(n) - D, D) if n else ca.SX(0, 0)
