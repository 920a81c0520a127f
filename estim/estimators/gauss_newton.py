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
    """Solve the masked, damped block-tridiagonal system ``H d = -g`` (unrolled SX).

    Rows and columns of fixed variables are replaced by the identity; the
    diagonal blocks get Marquardt damping ``lam * |diag(D_j)|`` and a ridge of
    1e-12 of their largest entry (which leaves stationary points unchanged).
    """
    N = len(D)
    rows = [_mask_row(D[j], E[j] if j < N - 1 else ca.SX.zeros(nx, nx), g[j],
                      free[j * nx:(j + 1) * nx],
                      free[(j + 1) * nx:(j + 2) * nx] if j < N - 1 else ca.SX.zeros(nx, 1),
                      lam, nx) for j in range(N)]
    Dm, Em, z = [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows]
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


#: Gauss-Newton steps that shrink by less than this factor switch to Newton steps.
SWITCH_RATIO = 0.8


class _StageFunctions:
    """Per-slot pieces of the Gauss-Newton/Newton system as SX Functions.

    ``meas``: arrival (weight ``a``) and measurement terms of one slot;
    ``trans``: the process term linking two slots; ``mask``: the active-set
    masking and damping of one block row; ``fwd``/``bwd``: one step of the
    block elimination. Inlined into one graph for short windows, mapped and
    scanned for long records.
    """

    def __init__(self, model: Model, WQ: np.ndarray, diagonal_R: bool = False):
        nx, nu, ny = model.nx, model.nu, model.ny
        pm, eye = ca.DM(model.p), ca.DM.eye(nx)
        x, xb = ca.SX.sym("x", nx), ca.SX.sym("xb", nx)
        y, wy = ca.SX.sym("y", ny), ca.SX.sym("wy", ny * ny)
        u, up = ca.SX.sym("u", nu), ca.SX.sym("up", nu)
        a, om = ca.SX.sym("a"), ca.SX.sym("omega")
        xbar, w0, a0 = ca.SX.sym("xbar", nx), ca.SX.sym("w0", nx * nx), ca.SX.sym("A0", nx * nx)
        W0, A0 = ca.reshape(w0, nx, nx), ca.reshape(a0, nx, nx)  # A0 = W0^T W0, hoisted
        # arrival and measurement terms of one slot; a diagonal R gives diagonal
        # weights (also with missing rows), applied as row scalings
        r0 = W0 @ (x - xbar)
        e = y - model.H(x, up, pm)
        C = model.H_x(x, up, pm)
        if diagonal_R:
            wd = wy[[i * ny + i for i in range(ny)]]
            ry, Jy = wd * e, -(wd @ ca.DM.ones(1, nx)) * C
        else:
            Wy = ca.reshape(wy, ny, ny)
            ry, Jy = Wy @ e, -Wy @ C
        c = a * ca.sumsqr(r0) + ca.sumsqr(ry)
        A0a = a * A0
        margs = [x, y, wy, up, a, xbar, w0, a0]
        self.meas = ca.Function("meas", margs, [
            A0a + Jy.T @ Jy, A0a + ca.hessian(0.5 * ca.sumsqr(ry), x)[0],
            A0a @ (x - xbar) + Jy.T @ ry, c])
        self.meas_cost = ca.Function("meas_cost", margs, [c])
        # process term between slots (a diagonal weight is a row scaling)
        A = om * model.F_x(x, u, pm) + (1 - om) * eye
        G = om * model.F(x, u, pm) + (1 - om) * x
        if np.allclose(WQ, np.diag(np.diag(WQ))):
            mv = om * ca.DM(np.diag(WQ)) + (1 - om)
            rw = mv * (xb - G)
            Ja, Jb = -(mv @ ca.DM.ones(1, nx)) * A, ca.diag(mv)
        else:
            M = om * ca.DM(WQ) + (1 - om) * eye
            rw = M @ (xb - G)
            Ja, Jb = -M @ A, M
        Hw = ca.hessian(0.5 * ca.sumsqr(rw), ca.vertcat(x, xb))[0]
        targs = [x, xb, u, om]
        self.trans = ca.Function("trans", targs, [
            Ja.T @ Ja, Jb.T @ Jb, Ja.T @ Jb, Hw[:nx, :nx], Hw[nx:, nx:], Hw[:nx, nx:],
            Ja.T @ rw, Jb.T @ rw, ca.sumsqr(rw)])
        self.trans_cost = ca.Function("trans_cost", targs, [ca.sumsqr(rw)])
        # masking/damping of one block row, and one elimination step
        Dj, Ej = ca.SX.sym("D", nx, nx), ca.SX.sym("E", nx, nx)
        gj, lam = ca.SX.sym("g", nx), ca.SX.sym("lam")
        fj, fn = ca.SX.sym("free", nx), ca.SX.sym("free_next", nx)
        Dm, Em, z = _mask_row(Dj, Ej, gj, fj, fn, lam, nx)
        self.mask = ca.Function("mask", [Dj, Ej, gj, fj, fn, lam], [Dm, Em, z])
        self.diag = ca.Function("diag", [Dj], [ca.diag(Dj)])
        Sp, zp = ca.SX.sym("S_prev", nx, nx), ca.SX.sym("z_prev", nx)
        Ep = ca.SX.sym("E_prev", nx, nx)
        zj = ca.SX.sym("z", nx)
        K = _sym_solve(Sp, ca.horzcat(Ep, zp))
        self.fwd = ca.Function("fwd", [Sp, zp, Dj, Ep, zj],
                               [Dj - Ep.T @ K[:, :nx], zj - Ep.T @ K[:, nx]])
        dn = ca.SX.sym("d_next", nx)
        self.bwd = ca.Function("bwd", [dn, Dj, zj, Ej], [_sym_solve(Dj, zj - Ej @ dn)])


def _mask_row(D, E, g, free, free_next, lam, nx):
    """Masked, damped block row: fixed rows/columns become the identity.

    Elementwise: ``Dm = (f f^T) * (D + lam |diag D| + ridge I) + diag(1 - f)``,
    ``Em = (f f_next^T) * E``, ``z = -f * g``.
    """
    dj = ca.diag(D)
    ridge = 1e-12 * ca.fmax(ca.mmax(ca.fabs(dj)), 1e-300)
    Dd = D + ca.diag(lam * ca.fabs(dj) + ridge)
    return (free @ free.T) * Dd + ca.diag(1 - free), (free @ free_next.T) * E, -free * g


def _reverse_cols(M, N, width):
    """Reverse the order of the ``N`` column blocks (each ``width`` wide) of an MX."""
    idx = [b * width + c for b in range(N - 1, -1, -1) for c in range(width)]
    return M[:, idx]


def _scan_solve(st, Dm, Em, z, N, nx):
    """Block-tridiagonal solve by a forward and a backward ``mapaccum`` scan."""
    Ep = ca.horzcat(ca.MX.zeros(nx, nx), Em[:, :(N - 1) * nx])
    S, zz = st.fwd.mapaccum("fwd_scan", N, 2)(ca.MX.eye(nx), ca.MX.zeros(nx, 1), Dm, Ep, z)
    d_rev = st.bwd.mapaccum("bwd_scan", N, 1)(
        ca.MX.zeros(nx, 1), _reverse_cols(S, N, nx), _reverse_cols(zz, N, 1),
        _reverse_cols(Em, N, nx))
    return _reverse_cols(d_rev, N, 1)


def _scan_last_inverse(st, D, E, N, nx):
    """Inverse of the last Schur complement of ``J^T J`` (covariance of the last state)."""
    Ep = ca.horzcat(ca.MX.zeros(nx, nx), E[:, :(N - 1) * nx])
    S, _ = st.fwd.mapaccum("cov_scan", N, 2)(ca.MX.eye(nx), ca.MX.zeros(nx, 1), D, Ep,
                                             ca.MX.zeros(nx, N))
    S_last = S[:, (N - 1) * nx:]
    Sl = ca.SX.sym("S", nx, nx)
    cov = ca.Function("inv_last", [Sl], [_sym_solve(Sl, ca.SX.eye(nx))])(S_last)
    return 0.5 * (cov + cov.T)


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
                 xtol: float = 1e-10, newton: bool = False, jit: bool = False,
                 mode: str = "auto", diagonal_R: bool = False, full: bool = False):
        if mode not in ("auto", "unrolled", "mapped"):
            raise ValueError(f"mode must be 'auto', 'unrolled' or 'mapped', got {mode!r}")
        self.model, self.N = model, N
        self.lower, self.upper = lower, upper
        bounded = bool(np.isfinite(lower).any() or np.isfinite(upper).any())
        self._bounded = bounded
        self._project = (lambda z: np.clip(z, lower, upper)) if bounded else (lambda z: z)
        self.max_iter, self.xtol = int(max_iter), float(xtol)
        self.newton, self.jit = bool(newton), bool(jit)
        self.full = bool(full)
        self.mode = ("unrolled" if N <= 128 else "mapped") if mode == "auto" else mode
        if self.mode == "mapped" and N < 2:
            self.mode = "unrolled"
        self._stages = _StageFunctions(model, WQ, diagonal_R)
        opts = {"jit": True, "compiler": "shell",
                "jit_options": {"flags": ["-O1"], "verbose": False}} if self.jit else {}
        build = self._build_unrolled if self.mode == "unrolled" else self._build_mapped
        it_gn, it_newton, cost, cov = build(N, slices, n_params)
        self._iter_gn = FastFunction(ca.Function("gn_iter", *it_gn, opts))
        self._iter_newton = FastFunction(ca.Function("newton_iter", *it_newton, opts))
        self._cost = FastFunction(ca.Function("gn_cost", *cost, opts))
        self._cov = FastFunction(ca.Function("gn_cov", *cov))

    def _parts(self, p, slices, N):
        m = self.model
        nx, nu, ny = m.nx, m.nu, m.ny
        part = {k: p[s] for k, s in slices.items()}
        return {
            "Y": ca.reshape(part["y"], ny, N), "WY": ca.reshape(part["wy"], ny * ny, N),
            "U": ca.reshape(part["u"], nu, N), "Up": ca.reshape(part["up"], nu, N),
            "a": ca.reshape(part["a"], 1, N), "omega": ca.reshape(part["omega"], 1, N - 1),
            "xbar": part["xbar"], "W0": part["w0"],
            "A0": ca.vec(ca.reshape(part["w0"], nx, nx).T @ ca.reshape(part["w0"], nx, nx)),
        } if not self.full else {
            # every slot active, arrival on the first: constants fold away in the graph
            "Y": ca.reshape(part["y"], ny, N), "WY": ca.reshape(part["wy"], ny * ny, N),
            "U": ca.reshape(part["u"], nu, N), "Up": ca.reshape(part["up"], nu, N),
            "a": ca.DM([[1.0] + [0.0] * (N - 1)]), "omega": ca.DM.ones(1, N - 1),
            "xbar": part["xbar"], "W0": part["w0"],
            "A0": ca.vec(ca.reshape(part["w0"], nx, nx).T @ ca.reshape(part["w0"], nx, nx)),
        }

    @staticmethod
    def _direction(gvec, Dd, free, eliminate):
        """Fixed variables take a scaled gradient step, free ones the eliminated step."""
        scaled = -gvec / (Dd + 1e-300)
        return ca.if_else(1 - free, scaled, eliminate)

    def _build_unrolled(self, N, slices, n_params):
        """One SX expression graph over all slots (fastest for short windows)."""
        st, nx = self._stages, self.model.nx
        p = ca.SX.sym("p", n_params)
        X = ca.SX.sym("X", nx, N)
        lam = ca.SX.sym("lam")
        q = self._parts(p, slices, N)
        D, Dh, g, cost = [], [], [], 0
        for j in range(N):
            Dg, Dhj, gj, cj = st.meas(X[:, j], q["Y"][:, j], q["WY"][:, j], q["Up"][:, j],
                                      q["a"][j], q["xbar"], q["W0"], q["A0"])
            D.append(Dg)
            Dh.append(Dhj)
            g.append(gj)
            cost += cj
        E, Eh = [], []
        for j in range(N - 1):
            Daa, Dbb, Eab, Haa, Hbb, Hab, ga, gb, cj = st.trans(
                X[:, j], X[:, j + 1], q["U"][:, j], q["omega"][j])
            D[j] += Daa
            D[j + 1] += Dbb
            Dh[j] += Haa
            Dh[j + 1] += Hbb
            E.append(Eab)
            Eh.append(Hab)
            g[j] += ga
            g[j + 1] += gb
            cost += cj
        gvec, xv = ca.vertcat(*g), ca.vec(X)
        free = self._free(xv, gvec)
        Dd = ca.vertcat(*[ca.diag(Dj) for Dj in D])
        d_gn = self._direction(gvec, Dd, free, _eliminate(D, E, g, free, lam, nx))
        d_nt = self._direction(gvec, Dd, free, _eliminate(Dh, Eh, g, free, lam, nx))
        S_last = D[0]
        for j in range(1, N):
            S_last = D[j] - E[j - 1].T @ _sym_solve(S_last, E[j - 1])
        cov = _sym_solve(S_last, ca.SX.eye(nx))
        return (([xv, p, lam], [cost, gvec, d_gn]), ([xv, p, lam], [cost, gvec, d_nt, d_gn]),
                ([xv, p], [cost]), ([xv, p], [0.5 * (cov + cov.T)]))

    def _build_mapped(self, N, slices, n_params):
        """Stage functions mapped over the slots and the elimination as two scans
        (``mapaccum``): the graph does not grow with ``N``, the work is linear in it."""
        st, nx = self._stages, self.model.nx
        p = ca.MX.sym("p", n_params)
        X = ca.MX.sym("X", nx, N)
        lam = ca.MX.sym("lam")
        q = self._parts(p, slices, N)
        Z = ca.MX.zeros(nx, nx)
        Dg, Dhm, gm, cm = st.meas.map(N)(X, q["Y"], q["WY"], q["Up"], q["a"], q["xbar"],
                                         q["W0"], q["A0"])
        Daa, Dbb, Eab, Haa, Hbb, Hab, ga, gb, ct = st.trans.map(N - 1)(
            X[:, :N - 1], X[:, 1:], q["U"][:, :N - 1], q["omega"])
        D = Dg + ca.horzcat(Daa, Z) + ca.horzcat(Z, Dbb)
        Dh = Dhm + ca.horzcat(Haa, Z) + ca.horzcat(Z, Hbb)
        E = ca.horzcat(Eab, Z)
        Eh = ca.horzcat(Hab, Z)
        zc = ca.MX.zeros(nx, 1)
        g = gm + ca.horzcat(ga, zc) + ca.horzcat(zc, gb)
        cost = ca.sum2(cm) + ca.sum2(ct)
        gvec, xv = ca.vec(g), ca.vec(X)
        free = self._free(xv, gvec)
        Fm = ca.reshape(free, nx, N)
        Fnext = ca.horzcat(Fm[:, 1:], ca.MX.zeros(nx, 1))
        Dd = ca.vec(st.diag.map(N)(D))

        def solve(Db, Eb):
            Dm, Em, z = st.mask.map(N)(Db, Eb, g, Fm, Fnext, lam)
            return _scan_solve(st, Dm, Em, z, N, nx)

        d_gn = self._direction(gvec, Dd, free, ca.vec(solve(D, E)))
        d_nt = self._direction(gvec, Dd, free, ca.vec(solve(Dh, Eh)))
        cov = _scan_last_inverse(st, D, E, N, nx)
        cm_only = st.meas_cost.map(N)(X, q["Y"], q["WY"], q["Up"], q["a"], q["xbar"], q["W0"],
                                      q["A0"])
        ct_only = st.trans_cost.map(N - 1)(X[:, :N - 1], X[:, 1:], q["U"][:, :N - 1],
                                          q["omega"])
        c_only = ca.sum2(cm_only) + ca.sum2(ct_only)
        return (([xv, p, lam], [cost, gvec, d_gn]), ([xv, p, lam], [cost, gvec, d_nt, d_gn]),
                ([xv, p], [c_only]), ([xv, p], [cov]))

    def _free(self, xv, gvec):
        """1 for free variables, 0 at a bound with the gradient (of f/2) pushing outward."""
        if not (np.isfinite(self.lower).any() or np.isfinite(self.upper).any()):
            return ca.DM.ones(xv.shape[0])  # no bounds: constant, folded away by CasADi
        lo, hi = ca.DM(self.lower), ca.DM(self.upper)
        fixed = ca.logic_or(ca.logic_and(xv <= lo, gvec > 0), ca.logic_and(xv >= hi, gvec < 0))
        return 1 - fixed

    def solve(self, X0: np.ndarray, p: np.ndarray):
        r"""Minimise from ``X0`` (N, nx).

        Gauss-Newton iterations first (cheap: no second derivatives). When
        they contract slowly (a step more than ``SWITCH_RATIO`` = 0.8 of the
        previous one, as on large-residual problems) or stop descending, the iterations
        switch to Newton steps with the exact Hessian blocks, falling back to
        the Gauss-Newton direction where the Newton one does not descend. If
        no direction decreases the cost, Levenberg-Marquardt damping
        :math:`\lambda\,\mathrm{diag}(H)` is raised until one does (and
        relaxed after full steps). Converged when the next projected step
        would move no variable by more than ``xtol * (1 + max|x|)``, or when
        the decrease it predicts is below 1e-13 of the cost (rounding level;
        on Lorenz FIE this stops within 3e-8 of the optimum Ipopt finds at 1e-12).

        Returns ``(x, success, status, iterations, cost, seconds)``, ``x`` flat.
        """
        t0 = time.perf_counter()
        proj = self._project
        x = proj(np.asarray(X0, float).ravel())
        for fun in (self._iter_gn, self._iter_newton, self._cost):
            fun.args[1][:] = p  # fixed for the whole solve: written once
        lam, newton, last_step = 0.0, self.newton, np.inf
        f, g, dirs = self._evaluate(x, p, lam, newton)
        if not np.isfinite(f):
            return x, False, "non-finite cost at the initial guess", 0, f, time.perf_counter() - t0
        status, steps = "max_iter", 0
        while steps < self.max_iter:
            scale = 1.0 + np.abs(x).max()
            # judged on the Gauss-Newton direction, a descent direction (J^T J is positive
            # semi-definite) where the Newton one may not be: converged when the next
            # step is negligible or the decrease it predicts is at rounding level
            # (an ascending one means the near-singular solve lost accuracy: not converged;
            # the line search rejects it and the damping below regularises the system)
            move = proj(x + dirs[-1]) - x if self._bounded else dirs[-1]
            decrease = -float(g @ move)
            if np.abs(move).max() <= self.xtol * scale or \
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
            step = np.abs(xn - x).max()
            switch = not newton and step > SWITCH_RATIO * last_step
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
        proj = self._project
        slope = float(g @ (proj(x + 1e-8 * d) - x)) if self._bounded else float(g @ d)
        if slope >= 0.0:
            return None  # not a descent direction
        xn = proj(x + d)
        ev = self._evaluate(xn, p, lam, newton)
        # Armijo test; the gradient of f is 2 g
        gd = float(g @ (xn - x)) if self._bounded else float(g @ d)
        if np.isfinite(ev[0]) and ev[0] <= f + 2e-4 * gd:
            return xn, 1.0, ev
        alpha = 0.5
        while alpha > 1e-8:
            xn = proj(x + alpha * d)
            self._cost.args[0][:] = xn
            fn = float(self._cost.evaluate()[0][0])
            if np.isfinite(fn) and fn <= f + 2e-4 * float(g @ (xn - x)):
                return xn, alpha, None
            alpha *= 0.5
        return None

    def _evaluate(self, x, p, lam, newton):
        """Cost, gradient and direction(s) at ``x`` (``p`` already in the buffers)."""
        fun = self._iter_newton if newton else self._iter_gn
        fun.args[0][:] = x
        fun.args[2][0] = lam
        out = fun.evaluate()
        if newton:
            return float(out[0][0]), out[1].copy(), (out[2].copy(), out[3].copy())
        return float(out[0][0]), out[1].copy(), (out[2].copy(),)

    def covariance(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        """``(J^T J)^{-1}`` block of the last state at ``x`` (the posterior covariance)."""
        nx = self.model.nx
        return self._cov(x, p)[0].reshape(nx, nx, order="F").copy()
