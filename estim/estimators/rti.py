r"""The real-time iteration of moving horizon estimation (:class:`~estim.MHE` with
``rti=True``), split into a preparation and a feedback phase.

One Gauss-Newton step per sample on the window's least-squares problem

.. math::
    \min_{x_0..x_{N-1}} \|W_0 (x_0 - \bar x)\|^2
    + \sum_{k=0}^{N-2} \|W_Q (x_{k+1} - F(x_k, u_k))\|^2
    + \sum_{k=0}^{N-1} \|W_{y,k} (y_k - h(x_k))\|^2 ,

linearised at the shifted previous window (the newest slot predicted by :math:`F`).
The Gauss-Newton matrix is block tridiagonal, with diagonal blocks
:math:`H_k = C_k^\top W_{y,k}^\top W_{y,k} C_k + [k = 0]\, W_0^\top W_0 + [k \ge 1]\,
W_Q^\top W_Q + [k \le N-2]\, A_k^\top W_Q^\top W_Q A_k` and off-diagonal blocks
:math:`H_{k,k+1} = -A_k^\top W_Q^\top W_Q` (:math:`A_k = \partial F/\partial x`,
:math:`C_k = \partial h/\partial x`). Forward block elimination,

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
    S = \tilde S_{N-1}^0 + C^\top W_y^\top W_y C, \quad
    \Delta_{N-1} = -S^{-1} \big(\tilde g^0_{N-1} - C^\top W_y^\top W_y (y - h)\big),
    \quad \Delta_k = v_k - M_k \Delta_{k+1},

an :math:`O(N n_x^2)` computation, and :math:`S^{-1}` is the covariance of the new
estimate (the Laplace covariance of the last state, as for the converged MHE). A ridge
of :math:`10^{-10}` on the diagonal keeps the elimination defined when the window alone
does not determine a state.

References
----------
M. Diehl, H. G. Bock, J. P. Schlöder, "A real-time iteration scheme for nonlinear
optimization in optimal feedback control", SIAM J. Control Optim. 43(5), 2005;
P. Kühl, M. Diehl, T. Kraus, J. P. Schlöder, H. G. Bock, "A real-time algorithm for
moving horizon state and parameter estimation", Comput. Chem. Eng. 35(1), 2011.
"""

from __future__ import annotations

import casadi as ca

from estim.model import Model

#: Diagonal ridge of the Gauss-Newton matrix's blocks.
RIDGE = 1e-10


def build(model: Model, N: int) -> tuple[ca.Function, ca.Function]:
    """The preparation and feedback Functions of a window of ``N`` slots.

    ``prepare(X, Y, Wy, U, Up, xbar, W0, WQ) -> (S0, g0, C, h, v, M)``: ``X (nx, N)`` the
    window to linearise at, ``Y (ny, N-1)`` the measurements of all slots but the newest
    (0 where missing), ``Wy (ny*ny, N-1)`` their weight factors (column-major, zero rows
    where missing), ``U (nw, N-1)`` the transitions' inputs, ``Up (nu, N)`` the inputs
    ``h`` sees, ``xbar, W0`` the arrival cost (``W0 = 0`` without one), ``WQ``.

    ``feedback(S0, g0, C, h, y, Wy, v, M) -> (dX, P)``: the step ``dX (nx, N)`` and the
    newest state's covariance ``P (nx, nx)`` for the measurement ``y`` (0 where missing)
    with its weight factor ``Wy (ny, ny)``.
    """
    nx, ny, nu, nw = model.nx, model.ny, model.nu, model.nw
    p = ca.DM(model.p)
    X = ca.SX.sym("X", nx, N)
    Y = ca.SX.sym("Y", ny, N - 1)
    Wy = ca.SX.sym("Wy", ny * ny, N - 1)
    U = ca.SX.sym("U", nw, N - 1)
    Up = ca.SX.sym("Up", nu, N)
    xbar, W0, WQ = ca.SX.sym("xbar", nx), ca.SX.sym("W0", nx, nx), ca.SX.sym("WQ", nx, nx)
    Qw = WQ.T @ WQ
    ridge = RIDGE * ca.DM.eye(nx)
    Hd, g, Hoff = [], [], []
    for k in range(N):
        x = X[:, k]
        Hk = W0.T @ W0 + ridge if k == 0 else Qw + ridge
        gk = W0.T @ (W0 @ (x - xbar)) if k == 0 else WQ.T @ (WQ @ (x - _f(model, X, U, k - 1, p)))
        if k < N - 1:
            A = model.F_x(x, U[:, k], p)
            rq = WQ @ (X[:, k + 1] - _f(model, X, U, k, p))
            Hk += A.T @ Qw @ A
            gk -= A.T @ (WQ.T @ rq)
            Hoff.append(-A.T @ Qw)
            W = ca.reshape(Wy[:, k], ny, ny)
            C = model.H_x(x, Up[:, k], p)
            ry = W @ (Y[:, k] - model.H(x, Up[:, k], p))
            Hk += C.T @ (W.T @ W) @ C
            gk -= C.T @ (W.T @ ry)
        Hd.append(Hk)
        g.append(gk)
    S, gt = Hd[0], g[0]
    v, M = [], []
    for k in range(1, N):
        Z = ca.solve(S, ca.horzcat(Hoff[k - 1], gt))  # S~_{k-1}^{-1} [H_{k-1,k}, g~_{k-1}]
        v.append(-Z[:, nx])
        M.append(ca.vec(Z[:, :nx]))
        S = Hd[k] - Hoff[k - 1].T @ Z[:, :nx]
        gt = g[k] - Hoff[k - 1].T @ Z[:, nx]
    S0, g0 = 0.5 * (S + S.T), gt
    xN, upN = X[:, N - 1], Up[:, N - 1]
    C, h = model.H_x(xN, upN, p), model.H(xN, upN, p)
    V = ca.horzcat(*v) if v else ca.SX(nx, 0)
    Mm = ca.horzcat(*M) if M else ca.SX(nx * nx, 0)
    prepare = ca.Function("mhe_rti_prepare", [X, Y, Wy, U, Up, xbar, W0, WQ],
                          [S0, g0, C, h, V, Mm],
                          ["X", "Y", "Wy", "U", "Up", "xbar", "W0", "WQ"],
                          ["S0", "g0", "C", "h", "v", "M"])
    # feedback
    S0s, g0s = ca.SX.sym("S0", nx, nx), ca.SX.sym("g0", nx)
    Cs, hs = ca.SX.sym("C", ny, nx), ca.SX.sym("h", ny)
    y, W = ca.SX.sym("y", ny), ca.SX.sym("Wy", ny, ny)
    vs, Ms = ca.SX.sym("v", nx, N - 1), ca.SX.sym("M", nx * nx, N - 1)
    S = S0s + Cs.T @ (W.T @ W) @ Cs
    S = 0.5 * (S + S.T)
    gN = g0s - Cs.T @ (W.T @ (W @ (y - hs)))
    d = [None] * N
    d[N - 1] = -ca.solve(S, gN)
    for k in range(N - 2, -1, -1):
        d[k] = vs[:, k] - ca.reshape(Ms[:, k], nx, nx) @ d[k + 1]
    P = ca.solve(S, ca.DM.eye(nx))
    feedback = ca.Function("mhe_rti_feedback", [S0s, g0s, Cs, hs, y, W, vs, Ms],
                           [ca.horzcat(*d), 0.5 * (P + P.T)],
                           ["S0", "g0", "C", "h", "y", "Wy", "v", "M"], ["dX", "P"])
    return prepare, feedback


def _f(model: Model, X, U, k: int, p):
    """``F(x_k, u_k)`` of the window."""
    return model.F(X[:, k], U[:, k], p)
