r"""Projected Gauss-Newton for the windowed least-squares problem, exploiting its structure.

The cost :math:`f(X) = \|r(X)\|^2` of :mod:`estim.estimators.nlp` couples
only neighbouring states, so the Gauss-Newton matrix :math:`H = J^\top J` is
block tridiagonal: diagonal blocks :math:`D_j` and off-diagonal blocks
:math:`E_j = \partial r^\top/\partial x_j\,\partial r/\partial x_{j+1}`. A
step solves :math:`H d = -J^\top r` by block elimination (a Riccati
recursion, :math:`O(N n_x^3)`):

.. math::
    S_0 = D_0,\quad S_j = D_j - E_{j-1}^\top S_{j-1}^{-1} E_{j-1}, \qquad
    d_{N-1} = S_{N-1}^{-1} z_{N-1},\quad d_j = S_j^{-1}(z_j - E_j d_{j+1}).

State bounds are handled by the projected Newton method of Bertsekas
(1982): variables at a bound whose gradient points outward are fixed
(their rows and columns of :math:`H` replaced by the identity) and take a
scaled gradient step; the step is followed along the projection arc
:math:`X(\alpha) = \Pi[X + \alpha d]` with an Armijo test. The result is a
KKT point of the bound-constrained problem: zero gradient on the free
variables, outward gradient on the active ones.

Everything in one iteration (residuals, Jacobian blocks, active set,
elimination) is one compiled CasADi Function; the cost for the line search
another. For a linear model one iteration is exact, and
:math:`S_{N-1}^{-1}` is then the covariance of the last state.

References
----------
D. P. Bertsekas, "Projected Newton methods for optimization problems with
simple constraints", SIAM J. Control Optim. 20(2), 1982;
J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., ch. 10.
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim.model import Model


def _sym_solve(S, B):
    r"""Solve :math:`S X = B` for a symmetric SX block by :math:`LDL^\top` without pivoting.

    About :math:`n^3/6 + n^2 m` operations, far fewer nodes than a symbolic QR;
    works for indefinite nonsingular blocks (no square roots).
    """
    n = S.shape[0]
    L = [[None] * n for _ in range(n)]
    Dg = [None] * n
    for k in range(n):
        Dg[k] = S[k, k] - sum((L[k][m] ** 2 * Dg[m] for m in range(k)), ca.SX(0))
        for i in range(k + 1, n):
            L[i][k] = (S[i, k] - sum((L[i][m] * L[k][m] * Dg[m] for m in range(k)),
                                     ca.SX(0))) / Dg[k]
    cols = []
    for c in range(B.shape[1]):
        z = [None] * n
        for i in range(n):  # L z = b
            z[i] = B[i, c] - sum((L[i][m] * z[m] for m in range(i)), ca.SX(0))
        xs = [None] * n
        for i in range(n - 1, -1, -1):  # D L^T x = z
            xs[i] = z[i] / Dg[i] - sum((L[m][i] * xs[m] for m in range(i + 1, n)), ca.SX(0))
        cols.append(ca.vertcat(*xs))
    return ca.horzcat(*cols)


def _eliminate(D, E, g, free, lam, nx):
    """Solve the masked, damped block-tridiagonal system ``H d = -g`` by block elimination.

    Rows and columns of fixed variables are replaced by the identity; the
    diagonal blocks get Marquardt damping ``lam * diag(D_j)`` and a ridge of
    1e-12 of their largest entry (which leaves stationary points unchanged).
    """
    N = len(D)
    eye = ca.DM.eye(nx)
    Dm, Em, z = [], [], []
    for j in range(N):
        Fj = ca.diag(free[j * nx:(j + 1) * nx])
        dj = ca.diag(D[j])
        ridge = 1e-12 * ca.fmax(ca.mmax(ca.fabs(dj)), 1e-300)
        Dj = D[j] + lam * ca.diag(ca.fabs(dj)) + ridge * eye
        Dm.append(Fj @ Dj @ Fj + (eye - Fj))
        z.append(-(Fj @ g[j]))
        if j < N - 1:
            Em.append(Fj @ E[j] @ ca.diag(free[(j + 1) * nx:(j + 2) * nx]))
    S, zs = [Dm[0]], [z[0]]
    for j in range(1, N):
        K = _sym_solve(S[j - 1], ca.horzcat(Em[j - 1], zs[j - 1]))
        S.append(Dm[j] - Em[j - 1].T @ K[:, :nx])
        zs.append(z[j] - Em[j - 1].T @ K[:, nx])
    d = [None] * N
    d[N - 1] = _sym_solve(S[N - 1], zs[N - 1])
    for j in range(N - 2, -1, -1):
        d[j] = _sym_solve(S[j], zs[j] - Em[j] @ d[j + 1])
    return ca.vertcat(*d)


class StructuredGaussNewton:
    """Compiled Gauss-Newton iteration for the windowed problem.

    Parameters
    ----------
    model : Model
    N : int
        Number of slots.
    WQ : (nx, nx) array
        Process-noise weight factor.
    lower, upper : (N * nx,) arrays
        Bounds of ``vec(X)`` (slot-major).
    slices : dict
        Parameter layout of :class:`~estim.estimators.nlp.LeastSquaresNLP`.
    n_params : int
        Length of the parameter vector.
    max_iter : int
        Gauss-Newton iterations at most.
    xtol : float
        Stop when the step is below ``xtol * (1 + max|X|)``.
    """

    def __init__(self, model: Model, N: int, WQ: np.ndarray, lower: np.ndarray,
                 upper: np.ndarray, slices: dict, n_params: int, max_iter: int = 50,
                 xtol: float = 1e-10, newton: bool = False, jit: bool = False):
        self.model, self.N = model, N
        self.lower, self.upper = lower, upper
        self.max_iter, self.xtol = int(max_iter), float(xtol)
        self.newton, self.jit = bool(newton), bool(jit)
        nx, nu, ny = model.nx, model.nu, model.ny
        p = ca.SX.sym("p", n_params)
        part = {k: p[s] for k, s in slices.items()}
        Y = ca.reshape(part["y"], ny, N)
        U = ca.reshape(part["u"], nu, N)
        Up = ca.reshape(part["up"], nu, N)
        a, xbar = part["a"], part["xbar"]
        W0 = ca.reshape(part["w0"], nx, nx)
        WQd, pm, eye = ca.DM(WQ), ca.DM(model.p), ca.DM.eye(nx)
        X = ca.SX.sym("X", nx, N)
        lam = ca.SX.sym("lam")

        D = [ca.SX.zeros(nx, nx) for _ in range(N)]   # Gauss-Newton blocks of J^T J
        E = [ca.SX.zeros(nx, nx) for _ in range(N - 1)]
        Dh = [ca.SX.zeros(nx, nx) for _ in range(N)]  # exact Hessian blocks of f/2
        Eh = [ca.SX.zeros(nx, nx) for _ in range(N - 1)]
        g = [ca.SX.zeros(nx, 1) for _ in range(N)]
        r0 = W0 @ (X @ a - xbar)
        cost = ca.sumsqr(r0)
        for j in range(N):
            xj = X[:, j]
            D[j] += a[j] * (W0.T @ W0)
            Dh[j] += a[j] * (W0.T @ W0)
            g[j] += a[j] * (W0.T @ r0)
            Wy = ca.reshape(part["wy"][j * ny * ny:(j + 1) * ny * ny], ny, ny)
            ry = Wy @ (Y[:, j] - model.H(xj, Up[:, j], pm))
            Jy = -Wy @ model.H_x(xj, Up[:, j], pm)
            cost += ca.sumsqr(ry)
            D[j] += Jy.T @ Jy
            Dh[j] += ca.hessian(0.5 * ca.sumsqr(ry), xj)[0]
            g[j] += Jy.T @ ry
        for j in range(N - 1):
            xj, xk = X[:, j], X[:, j + 1]
            om = part["omega"][j]
            M = om * WQd + (1 - om) * eye
            A = om * model.F_x(xj, U[:, j], pm) + (1 - om) * eye
            G = om * model.F(xj, U[:, j], pm) + (1 - om) * xj
            rw = M @ (xk - G)
            Ja, Jb = -M @ A, M
            cost += ca.sumsqr(rw)
            D[j] += Ja.T @ Ja
            D[j + 1] += Jb.T @ Jb
            E[j] += Ja.T @ Jb
            Hw = ca.hessian(0.5 * ca.sumsqr(rw), ca.vertcat(xj, xk))[0]
            Dh[j] += Hw[:nx, :nx]
            Dh[j + 1] += Hw[nx:, nx:]
            Eh[j] += Hw[:nx, nx:]
            g[j] += Ja.T @ rw
            g[j + 1] += Jb.T @ rw
        gvec = ca.vertcat(*g)
        xv = ca.vec(X)
        lo, hi = ca.DM(lower), ca.DM(upper)
        # fixed: at a bound with the gradient (of f/2) pushing outward
        fixed = ca.logic_or(ca.logic_and(xv <= lo, gvec > 0), ca.logic_and(xv >= hi, gvec < 0))
        free = 1 - fixed
        scaled = -gvec / ca.vertcat(*[ca.diag(D[j]) + 1e-300 for j in range(N)])
        d_gn = ca.if_else(fixed, scaled, _eliminate(D, E, g, free, lam, nx))
        d_newton = ca.if_else(fixed, scaled, _eliminate(Dh, Eh, g, free, lam, nx))
        opts = {"jit": True, "compiler": "shell",
                "jit_options": {"flags": ["-O1"], "verbose": False}} if self.jit else {}
        self._iter_gn = FastFunction(ca.Function("gn_iter", [xv, p, lam], [cost, gvec, d_gn],
                                                 opts))
        self._iter_newton = FastFunction(ca.Function(
            "newton_iter", [xv, p, lam], [cost, gvec, d_newton, d_gn], opts))
        self._cost = FastFunction(ca.Function("gn_cost", [xv, p], [cost], opts))
        # covariance of the last state: inverse of the last Schur complement of J^T J
        S_last = D[0]
        for j in range(1, N):
            S_last = D[j] - E[j - 1].T @ _sym_solve(S_last, E[j - 1])
        cov = _sym_solve(S_last, ca.SX.eye(nx))
        self._cov = FastFunction(ca.Function("gn_cov", [xv, p], [0.5 * (cov + cov.T)]))

    def solve(self, X0: np.ndarray, p: np.ndarray):
        r"""Minimise from ``X0`` (N, nx).

        Gauss-Newton iterations first (cheap: no second derivatives). When
        they contract slowly (a step more than a quarter of the previous one,
        as on large-residual problems) or stop descending, the iterations
        switch to Newton steps with the exact Hessian blocks, falling back to
        the Gauss-Newton direction where the Newton one does not descend. If
        no direction decreases the cost, Levenberg-Marquardt damping
        :math:`\lambda\,\mathrm{diag}(H)` is raised until one does (and
        relaxed after full steps). Converged when the next projected step
        would move no variable by more than ``xtol * (1 + max|x|)``, or when
        the decrease it predicts is below 1e-13 of the cost (rounding level).

        Returns ``(x, success, status, iterations, cost, seconds)``, ``x`` flat.
        """
        t0 = time.perf_counter()
        lo, hi = self.lower, self.upper
        x = np.clip(np.asarray(X0, float).ravel(), lo, hi)
        lam, newton, last_step = 0.0, self.newton, np.inf
        f, g, dirs = self._evaluate(x, p, lam, newton)
        if not np.isfinite(f):
            return x, False, "non-finite cost at the initial guess", 0, f, time.perf_counter() - t0
        status, steps = "max_iter", 0
        while steps < self.max_iter:
            scale = 1.0 + np.max(np.abs(x))
            # judged on the Gauss-Newton direction, a descent direction (J^T J is positive
            # semi-definite) where the Newton one may not be: converged when the next
            # step is negligible or the decrease it predicts is at rounding level
            # (an ascending one means the near-singular solve lost accuracy: not converged;
            # the line search rejects it and the damping below regularises the system)
            move = np.clip(x + dirs[-1], lo, hi) - x
            decrease = -float(g @ move)
            if np.max(np.abs(move)) <= self.xtol * scale or \
                    0.0 <= decrease <= 1e-13 * max(abs(f), 1e-300):
                status = "ok"
                break
            new = None
            for d in dirs:
                new = self._line_search(x, f, g, d, p, lam, newton)
                if new is not None:
                    break
            if new is None:
                if not newton:
                    newton = True
                else:  # no decrease along either direction: damp
                    lam = max(1e-3, 10.0 * lam)
                    if lam > 1e10:
                        status = "line search failed"
                        break
                f, g, dirs = self._evaluate(x, p, lam, newton)
                continue
            xn, alpha, evaluated = new
            step = np.max(np.abs(xn - x))
            switch = not newton and step > 0.25 * last_step
            x, steps, last_step = xn, steps + 1, step
            if alpha == 1.0 and lam:
                lam = lam / 10.0 if lam > 1e-8 else 0.0
                evaluated = None
            if switch:
                newton, evaluated = True, None
            f, g, dirs = evaluated if evaluated is not None else \
                self._evaluate(x, p, lam, newton)
        ok = status == "ok" and bool(np.isfinite(x).all()) and np.isfinite(f)
        return x, ok, status, steps, f, time.perf_counter() - t0

    def _line_search(self, x, f, g, d, p, lam, newton):
        """Armijo backtracking along the projection arc.

        The full step is tried with a whole iteration evaluation (reused by
        the next iteration when accepted), shorter ones with the cost only.
        Returns ``(x_new, alpha, evaluation or None)``, or None on failure.
        """
        lo, hi = self.lower, self.upper
        if float(g @ (np.clip(x + 1e-8 * d, lo, hi) - x)) >= 0.0:
            return None  # not a descent direction
        xn = np.clip(x + d, lo, hi)
        ev = self._evaluate(xn, p, lam, newton)
        # Armijo test; the gradient of f is 2 g
        if np.isfinite(ev[0]) and ev[0] <= f + 2e-4 * float(g @ (xn - x)):
            return xn, 1.0, ev
        alpha = 0.5
        while alpha > 1e-8:
            xn = np.clip(x + alpha * d, lo, hi)
            fn = float(self._cost(xn, p)[0][0])
            if np.isfinite(fn) and fn <= f + 2e-4 * float(g @ (xn - x)):
                return xn, alpha, None
            alpha *= 0.5
        return None

    def _evaluate(self, x, p, lam, newton):
        if newton:
            f, g, d_newton, d_gn = self._iter_newton(x, p, lam)
            return float(f[0]), g.copy(), (d_newton.copy(), d_gn.copy())
        f, g, d_gn = self._iter_gn(x, p, lam)
        return float(f[0]), g.copy(), (d_gn.copy(),)

    def covariance(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``(J^T J)^{-1}`` block of the last state at ``x`` (the posterior covariance)."""
        nx = self.model.nx
        return self._cov(x, p)[0].reshape(nx, nx, order="F").copy()
