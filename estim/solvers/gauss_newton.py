r"""Projected Gauss-Newton for the windowed least-squares problem, exploiting its structure.

The cost :math:`f(X) = \|r(X)\|^2` of :mod:`estim.solvers.nlp` couples
only neighbouring states, so the Gauss-Newton matrix :math:`H = J^\top J` is
block tridiagonal: diagonal blocks :math:`D_j` and off-diagonal blocks
:math:`E_j = \partial r^\top/\partial x_j\,\partial r/\partial x_{j+1}`. A
step solves :math:`H d = z` (:math:`z = -J^\top r`) by block elimination, a
Riccati recursion of :math:`O(N n_x^3)` operations:

.. math::
    S_0 = D_0,\quad \tilde z_0 = z_0,\quad
    S_j = D_j - E_{j-1}^\top S_{j-1}^{-1} E_{j-1},\quad
    \tilde z_j = z_j - E_{j-1}^\top S_{j-1}^{-1} \tilde z_{j-1},

    d_{N-1} = S_{N-1}^{-1} \tilde z_{N-1},\qquad
    d_j = S_j^{-1} (\tilde z_j - E_j d_{j+1}).

Each :math:`S_j = L_j D_j L_j^\top` is factored once (no square roots); with
:math:`V = L_j^{-1} [E_j, \tilde z_j]` the products are
:math:`V^\top D_j^{-1} V` (lower triangles only) and the backward step is
:math:`d_j = L_j^{-\top}(D_j^{-1} V_z - D_j^{-1} V_E d_{j+1})`.

State bounds are handled by the projected Newton method of Bertsekas
(1982): variables at a bound whose gradient points outward are fixed
(their rows and columns of :math:`H` replaced by the identity) and take a
scaled gradient step; the step is followed along the projection arc
:math:`X(\alpha) = \Pi[X + \alpha d]` with an Armijo test. The result is a
KKT point of the bound-constrained problem: zero gradient on the free
variables, outward gradient on the active ones.

Everything in one iteration (residuals, Jacobian blocks, active set,
elimination) is one compiled CasADi Function, the cost for the line search
another. An iteration is two scans (``mapaccum``) over the slots: a forward
one whose step does all the work of one slot (its residuals and blocks, the
process term to the next slot, masking, damping and one elimination step)
and a backward one for the direction. The graph is either expanded into one
flat SX graph (``mode="unrolled"``: building takes milliseconds per hundred
slots, the work per slot does not depend on ``N``), or compiled for one chunk
of slots and called on consecutive slices of the buffers in a loop
(``mode="mapped"``, :class:`_Chunked`: memory proportional to the record,
building independent of it). For a linear model one iteration is exact, and
:math:`S_{N-1}^{-1}` is then the covariance of the last state.

A full step that the line search rejects is tried again through the dynamics
(:meth:`StructuredGaussNewton._rolled`): at small process noise the defects
:math:`x_{k+1} - F(x_k)` are weighted so heavily that the linear step raises
the cost (the Maratos effect of a penalty formulation), while the same step
propagated through the model keeps each defect at its linearised prediction.
This is the nonlinear rollout of differential dynamic programming; it makes an
identification at tiny ``Q`` converge like single shooting, and a well-weighted
problem like multiple shooting.

References
----------
D. P. Bertsekas, "Projected Newton methods for optimization problems with
simple constraints", SIAM J. Control Optim. 20(2), 1982;
J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., ch. 10;
P. Deuflhard, *Newton Methods for Nonlinear Problems*, Springer, 2004, ch. 2 and 4;
G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., sec. 4.1 (LDLᵀ).
"""

from __future__ import annotations

import copy
import time

import casadi as ca
import numpy as np

from estim._fast import FastFunction, jitted
from estim.model import Model

#: Gauss-Newton steps that shrink by less than this factor switch to Newton steps.
SWITCH_RATIO = 0.8
#: iteration function by (Newton, damped or with the ridge)
_ITERATIONS = {(False, False): "gn", (False, True): "gn_lam", (True, False): "newton",
               (True, True): "newton_lam"}
#: ``mode="auto"`` expands the graph while it has at most this many instructions (the
#: slots times the instructions of one slot's forward step: about 4200 slots of the
#: Lorenz model, 850 of the seven-state Silverbox one), and maps beyond. Building takes about 0.25
#: microseconds per instruction (1 s at the limit), the mapped mode's a fixed 0.05-0.2 s;
#: per evaluation the mapped mode pays about a microsecond per chunk call, which matters
#: for small models only (Lorenz: 1.3x the unrolled time at 4000 slots, 0.7x at 10 000;
#: a 7-state model at 4000: 0.7x).
AUTO_UNROLL_INSTRUCTIONS = 2_200_000
#: ``mode="mapped"`` evaluates chunks of at least this many slots in a loop (with
#: ``jit``: fewer, compiled in about two seconds instead of ten, and as fast), and at
#: most :data:`MAX_CHUNKS` of them (longer chunks for longer records). The build time
#: grows with the chunk, the loop's overhead (a few microseconds per call) with their
#: number: on the Silverbox (7 states) at 40 000 samples, 625 chunks of 64 build in
#: 0.12 s and solve as fast as 128 chunks of 313, which take 1.0 s to build.
CHUNK_SLOTS = 64
JIT_CHUNK_SLOTS = 16
MAX_CHUNKS = 1024
#: The covariances of every slot (read once per fit) are one expanded graph up to this
#: many slots, and a loop over chunks beyond, whatever the mode: the chunks build in
#: 0.05 s at any length where the expanded graph takes 0.3 s at 1000 slots of the
#: Lorenz model, and evaluate about as fast (1.1 ms against 0.7 ms there).
COVARIANCE_UNROLL_SLOTS = 256
#: A chunk function whose work memory over all chunks stays below this many bytes
#: gets one buffer per chunk, its arguments bound once: a call is then about 1
#: microsecond instead of about 12 (binding some twenty arguments each time).
PREBIND_BYTES = 16 * 2**20


def full_record_constants(N: int) -> tuple[ca.DM, ca.DM]:
    """Window bookkeeping of a problem whose ``N`` slots all hold data: the arrival
    weights ``a`` (on the first slot) and the process-term switches ``omega`` (all
    on), as ``(1, N)`` and ``(1, N - 1)`` constants."""
    return ca.DM([[1.0] + [0.0] * (N - 1)]), ca.DM.ones(1, max(N - 1, 0))


def _total(terms) -> ca.SX:
    """Sum of SX terms, ``SX(0)`` when there are none (adding to zero folds away)."""
    out = ca.SX(0)
    for t in terms:
        out = out + t
    return out


def _ldl(S):
    r"""Factors of a symmetric SX block, :math:`S = L\,\mathrm{diag}(D)\,L^\top`, no pivoting.

    Reads the lower triangle only. Returns ``(L, inv_D)`` as nested lists
    (unit lower triangular ``L``, reciprocals of ``D``): about :math:`n^3/6`
    operations and no square roots, so indefinite nonsingular blocks (exact
    Hessians) work too. The products :math:`L_{ik} D_k` are kept from the
    elimination rather than recomputed (Golub and Van Loan, alg. 4.1.2).
    """
    n = S.shape[0]
    L = [[None] * n for _ in range(n)]
    LD = [[None] * n for _ in range(n)]  # L[i][k] * D[k]
    inv_D = [None] * n
    for k in range(n):
        Dk = S[k, k] - _total(L[k][m] * LD[k][m] for m in range(k))
        inv_D[k] = 1 / Dk
        for i in range(k + 1, n):
            LD[i][k] = S[i, k] - _total(L[i][m] * LD[k][m] for m in range(k))
            L[i][k] = LD[i][k] * inv_D[k]
    return L, inv_D


def _forward(L, B) -> ca.SX:
    """:math:`L^{-1} B` for unit lower triangular ``L`` (nested list)."""
    n = len(L)
    cols = []
    for c in range(B.shape[1]):
        z = [None] * n
        for i in range(n):
            z[i] = B[i, c] - _total(L[i][m] * z[m] for m in range(i))
        cols.append(ca.vertcat(*z))
    return ca.horzcat(*cols)


def _backward(L, b) -> ca.SX:
    r""":math:`L^{-\top} b` for unit lower triangular ``L`` (nested list or SX) and a vector."""
    n = len(L) if isinstance(L, list) else L.shape[0]
    x = [None] * n
    for i in range(n - 1, -1, -1):
        x[i] = b[i] - _total(L[m][i] * x[m] if isinstance(L, list) else L[m, i] * x[m]
                             for m in range(i + 1, n))
    return ca.vertcat(*x)


def _ldl_solve(L, inv_D, B) -> ca.SX:
    r"""Solve :math:`L D L^\top X = B` column by column (``B`` an SX matrix)."""
    Z = ca.diag(ca.vertcat(*inv_D)) @ _forward(L, B)
    return ca.horzcat(*[_backward(L, Z[:, c]) for c in range(B.shape[1])])


def _sym_solve(S, B) -> ca.SX:
    """Solve :math:`S X = B` for a symmetric SX block (see :func:`_ldl`)."""
    return _ldl_solve(*_ldl(S), B)


def _sym_product(A, B) -> ca.SX:
    """:math:`A^\\top B` for a product known to be symmetric: the lower triangle is
    computed, the upper one mirrors it (same SX nodes)."""
    n = A.shape[1]
    out = ca.SX(n, n)
    for i in range(n):
        for j in range(i + 1):
            out[i, j] = ca.dot(A[:, i], B[:, j])
            out[j, i] = out[i, j]
    return out


def _gram(A) -> ca.SX:
    """:math:`A^\\top A`, lower triangle computed and mirrored."""
    return _sym_product(A, A)


def _damp(D, lam) -> ca.SX:
    """Ridge of 1e-12 of the largest diagonal entry (leaves stationary points
    unchanged, keeps singular blocks factorable) plus Marquardt damping
    ``lam |diag D|``.

    The undamped iterations go without (fewer operations); a solve switches
    to this form, with ``lam = 0`` for the ridge alone, once a direction comes
    out non-finite.
    """
    dj = ca.fabs(ca.diag(D))
    return D + ca.diag(1e-12 * ca.fmax(ca.mmax(dj), 1e-300) + lam * dj)


class _StageFunctions:
    """Per-slot pieces of the Gauss-Newton/Newton system as SX Functions.

    ``meas``: arrival (weight ``a``) and measurement terms of one slot;
    ``trans``: the process term linking two slots (``*_newton``: with the
    exact Hessian blocks as well, ``*_cost``: the cost alone);
    ``fwd``/``last``/``bwd``: one step of the block elimination; ``inverse``:
    a symmetric block inverse; ``cov_bwd``: one step of the backward recursion for
    the diagonal blocks of :math:`H^{-1}`; :meth:`fused`: one slot of the forward pass.
    """

    def __init__(self, model: Model, diagonal_Q: bool = False, diagonal_R: bool = False):
        nx, nu, ny = model.nx, model.nu, model.ny
        pm, eye = ca.DM(model.p), ca.DM.eye(nx)
        x, xb = ca.SX.sym("x", nx), ca.SX.sym("xb", nx)
        y, wy = ca.SX.sym("y", ny), ca.SX.sym("wy", ny * ny)
        u, up = ca.SX.sym("u", model.nw), ca.SX.sym("up", nu)  # transition, measurement
        a, om, wq = ca.SX.sym("a"), ca.SX.sym("omega"), ca.SX.sym("wq", nx * nx)
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
        gy = A0a @ (x - xbar) + Jy.T @ ry
        self.meas = ca.Function("meas", margs, [A0a + _gram(Jy), gy, c])
        self.meas_newton = ca.Function("meas_newton", margs, [
            A0a + _gram(Jy), A0a + ca.hessian(0.5 * ca.sumsqr(ry), x)[0], gy, c])
        self.meas_cost = ca.Function("meas_cost", margs, [c])
        # process term between slots, weighted by W_Q (a parameter: tuning is data; a
        # diagonal weight is a row scaling)
        A = om * model.F_x(x, u, pm) + (1 - om) * eye
        G = om * model.F(x, u, pm) + (1 - om) * x
        if diagonal_Q:
            mv = om * wq[[i * nx + i for i in range(nx)]] + (1 - om)
            rw = mv * (xb - G)
            Ja, Jb = -(mv @ ca.DM.ones(1, nx)) * A, ca.diag(mv)
        else:
            M = om * ca.reshape(wq, nx, nx) + (1 - om) * eye
            rw = M @ (xb - G)
            Ja, Jb = -M @ A, M
        Hw = ca.hessian(0.5 * ca.sumsqr(rw), ca.vertcat(x, xb))[0]
        targs = [x, xb, u, om, wq]
        gn_blocks = [_gram(Ja), _gram(Jb), Ja.T @ Jb]
        rest = [Ja.T @ rw, Jb.T @ rw, ca.sumsqr(rw)]
        self.trans = ca.Function("trans", targs, gn_blocks + rest)
        self.trans_newton = ca.Function("trans_newton", targs, gn_blocks + [
            Hw[:nx, :nx], Hw[nx:, nx:], Hw[:nx, nx:]] + rest)
        self.trans_cost = ca.Function("trans_cost", targs, [ca.sumsqr(rw)])
        # a step taken through the dynamics: from the moved state xp of slot k, the next
        # slot is G(xp) plus the defect the linearised step predicts,
        # x_{k+1} + alpha d_{k+1} - G(x_k) - alpha A d_k (see StructuredGaussNewton.solve)
        xp, d, dn, alpha = (ca.SX.sym("xp", nx), ca.SX.sym("d", nx), ca.SX.sym("dn", nx),
                            ca.SX.sym("alpha"))
        Gp = om * model.F(xp, u, pm) + (1 - om) * xp
        self.roll = ca.Function("roll", [xp, x, d, xb, dn, u, om, alpha],
                                [Gp + (xb + alpha * dn - G - alpha * ca.jtimes(G, x, d))])
        Dj = ca.SX.sym("D", nx, nx)
        # one elimination step: with S_{j-1} = L D L^T factored once,
        # V = L^{-1} [E_{j-1}, z~_{j-1}] and Vs = D^{-1} V give
        # E^T S^{-1} E = V_E^T Vs_E and E^T S^{-1} z~ = V_E^T Vs_z; the backward pass
        # needs d_{j-1} = L^{-T} (Vs_z - Vs_E d_j): Vs and L are passed on
        Sp, Ep = ca.SX.sym("S_prev", nx, nx), ca.SX.sym("E_prev", nx, nx)
        zp, zj = ca.SX.sym("z_prev", nx), ca.SX.sym("z", nx)
        L, inv_D = _ldl(Sp)
        V = _forward(L, ca.horzcat(Ep, zp))
        Vs = ca.diag(ca.vertcat(*inv_D)) @ V
        Lm = ca.SX.zeros(nx, nx)
        for i in range(nx):
            for k in range(i):
                Lm[i, k] = L[i][k]
        self.fwd = ca.Function("fwd", [Sp, zp, Dj, Ep, zj], [
            Dj - _sym_product(V[:, :nx], Vs[:, :nx]), zj - V[:, :nx].T @ Vs[:, nx],
            Vs[:, :nx], Vs[:, nx], Lm, ca.vertcat(*inv_D)])
        self.last = ca.Function("last", [Dj, zj], [_sym_solve(Dj, zj)])
        dn, Vj, vj = ca.SX.sym("d_next", nx), ca.SX.sym("Vs", nx, nx), ca.SX.sym("vs", nx)
        Lj = ca.SX.sym("L", nx, nx)
        self.bwd = ca.Function("bwd", [dn, Vj, vj, Lj], [_backward(Lj, vj - Vj @ dn)])
        inv = _sym_solve(Dj, ca.SX.eye(nx))
        self.inverse = ca.Function("inverse", [Dj], [0.5 * (inv + inv.T)])
        # one step of the covariance recursion (the diagonal blocks of H^{-1}): with
        # S_j = L D L^T and Vs = D^{-1} L^{-1} E_j from the elimination,
        # Sigma_j = S_j^{-1} + G Sigma_{j+1} G^T, G = S_j^{-1} E_j = L^{-T} Vs, is
        # L^{-T} (D^{-1} + Vs Sigma_{j+1} Vs^T) L^{-1}
        Sn, iD = ca.SX.sym("Sigma_next", nx, nx), ca.SX.sym("inv_D", nx)
        K = ca.diag(iD) + Vj @ Sn @ Vj.T
        X = ca.horzcat(*[_backward(Lj, K[:, c]) for c in range(nx)])  # L^{-T} K
        Sig = ca.horzcat(*[_backward(Lj, X[c, :].T) for c in range(nx)])  # L^{-T} X^T
        self.cov_bwd = ca.Function("cov_bwd", [Sn, Vj, Lj, iD], [0.5 * (Sig + Sig.T)])
        self.nx, self.nu, self.ny, self.nw = nx, nu, ny, model.nw
        self._fused: dict[tuple, ca.Function] = {}

    def fused(self, newton: bool, damped: bool, bounds=None,
              covariance: bool = False) -> ca.Function:
        r"""One slot of the forward pass, all in one SX function.

        The slot's arrival and measurement terms, the process term to the next
        slot (times ``link``, 0 for the last slot), the blocks
        :math:`D_j = D^m_j + D^{aa}_j + D^{bb}_{j-1}` and gradient, the
        active-set mask (``bounds = (lo, hi)`` per state), Marquardt damping,
        and one elimination step, for the Gauss-Newton blocks (and the exact
        Hessian ones with ``newton``). What the next slot needs is carried:
        per chain ``S_j, z~_j`` and the process term's ``D^{bb}_j, E_j``, then
        its gradient ``g^b_j`` and (with bounds) the free mask. Outputs: the
        carries, then per chain the elimination's ``D^{-1} V_E, D^{-1} V_z, L``,
        then the gradient, the cost and (with bounds) the free mask and
        :math:`\mathrm{diag}\,D_j`, and with ``covariance`` last, per chain, the
        reciprocals of the elimination's :math:`D` (for :attr:`cov_bwd`).
        """
        key = (newton, damped, None if bounds is None else
               tuple(np.concatenate(bounds).tolist()), covariance)
        if key in self._fused:
            return self._fused[key]
        nx, nu, ny = self.nx, self.nu, self.ny
        sym = ca.SX.sym
        chains = 2 if newton else 1
        carry = []
        for c in range(chains):
            carry += [sym(f"S{c}", nx, nx), sym(f"z{c}", nx), sym(f"Dbb{c}", nx, nx),
                      sym(f"E{c}", nx, nx)]
        gb_prev = sym("gb", nx)
        carry.append(gb_prev)
        if bounds is not None:
            f_prev = sym("free_prev", nx)
            carry.append(f_prev)
        x, xn, y, wy = sym("x", nx), sym("x_next", nx), sym("y", ny), sym("wy", ny * ny)
        up, a, u, om = sym("up", nu), sym("a"), sym("u", self.nw), sym("omega")
        wq = sym("wq", nx * nx)
        link, xbar, w0, a0 = sym("link"), sym("xbar", nx), sym("w0", nx * nx), sym("A0", nx * nx)
        lam = sym("lam")
        margs = [x, y, wy, up, a, xbar, w0, a0]
        if newton:
            Dm, Dmh, gm, cm = self.meas_newton(*margs)
            Daa, Dbb, Eab, Haa, Hbb, Hab, ga, gb, ct = self.trans_newton(x, xn, u, om, wq)
            blocks = [(Dm, Daa, Dbb, Eab), (Dmh, Haa, Hbb, Hab)]
        else:
            Dm, gm, cm = self.meas(*margs)
            Daa, Dbb, Eab, ga, gb, ct = self.trans(x, xn, u, om, wq)
            blocks = [(Dm, Daa, Dbb, Eab)]
        g = gm + link * ga + gb_prev
        cost = cm + link * ct
        out_carry, per_chain, D_gn, inv_D = [], [], None, []
        if bounds is not None:
            lo, hi = ca.DM(bounds[0]), ca.DM(bounds[1])
            free = 1 - ca.logic_or(ca.logic_and(x <= lo, g > 0), ca.logic_and(x >= hi, g < 0))
        for c, (Dmc, Daac, Dbbc, Eabc) in enumerate(blocks):
            S_prev, z_prev, Dbb_prev, E_prev = carry[4 * c:4 * c + 4]
            D = Dmc + link * Daac + Dbb_prev
            D_gn = D if D_gn is None else D_gn  # scales the steps of fixed variables
            if damped:
                D = _damp(D, lam)
            z, Ep = -g, E_prev
            if bounds is not None:
                D, Ep, z = (free @ free.T) * D + ca.diag(1 - free), (f_prev @ free.T) * E_prev, \
                    -free * g
            S, zt, Vs, vs, L, iD = self.fwd(S_prev, z_prev, D, Ep, z)
            out_carry += [S, zt, link * Dbbc, link * Eabc]
            per_chain += [Vs, vs, L]
            inv_D.append(iD)
        out_carry.append(link * gb)
        extra = []
        if bounds is not None:
            out_carry.append(free)
            extra = [free, ca.diag(D_gn)]
        ins = carry + [x, xn, y, wy, up, a, u, om, wq, link, xbar, w0, a0] + \
            ([lam] if damped else [])
        if covariance:
            extra += inv_D
        fun = ca.Function("slot", ins, out_carry + per_chain + [g, cost] + extra)
        self._fused[key] = fun
        return fun


def _reverse_cols(M, N, width):
    """Reverse the order of the ``N`` column blocks (each ``width`` wide) of an MX."""
    idx = [b * width + c for b in range(N - 1, -1, -1) for c in range(width)]
    return M[:, idx]


class _Slots:
    """Maps and scans of per-slot functions over ``N`` slots, as CasADi ``map`` and
    ``mapaccum`` (the unrolled mode expands the whole graph afterwards)."""

    @staticmethod
    def _outs(res, f):
        return list(res) if f.n_out() > 1 else [res]

    def map(self, f, N, *args):
        """``f.map(N)(*args)``, always a list of outputs."""
        return self._outs(f.map(N)(*args), f)

    def scan(self, f, N, n_acc, *args, last_only=False):
        """``f.mapaccum(N, n_acc)(*args)``, always a list of outputs; with ``last_only``
        the state outputs are the last states only."""
        out = self._outs(f.mapaccum(f"{f.name()}_scan", N, n_acc)(*args), f)
        if last_only:
            out = [o[:, -f.size2_out(i):] if i < n_acc else o for i, o in enumerate(out)]
        return out


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
        Bounds of ``vec(X)`` (slot-major), the same state bounds in every slot.
    slices : dict
        Parameter layout of :class:`~estim.solvers.nlp.LeastSquaresNLP`.
    n_params : int
        Length of the parameter vector.
    max_iter : int
        Gauss-Newton iterations at most.
    xtol : float
        Step tolerance relative to ``1 + max|X|`` (see :meth:`solve`; the
        default is that of ``scipy.optimize.least_squares``).
    newton : bool
        Start with Newton steps (exact Hessian blocks) instead of Gauss-Newton.
    jit : bool
        Compile the functions to C (needs a C compiler; about two seconds per
        chunk function in the mapped mode, far longer for an unrolled graph).
    mode : {"auto", "unrolled", "mapped"}
        One flat expanded graph, a loop over compiled chunks of slots, or
        ``"auto"``: unrolled up to :data:`AUTO_UNROLL_INSTRUCTIONS` instructions
        (mapped with ``jit``).
    diagonal_Q, diagonal_R : bool
        The process and measurement weights are diagonal (their graphs use the
        diagonals only). The weights themselves are parameters: changing the
        tuning never rebuilds a graph.
    full : bool
        Every slot holds data and the arrival term is on the first: the window
        bookkeeping parameters are constants in the graph.

    Notes
    -----
    The compiled functions are built on first use (the damped and Newton
    variants are needed only on hard problems, the covariance only when read),
    and all read the same input buffers.
    """

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 slices: dict, n_params: int, max_iter: int = 50, xtol: float = 1e-8,
                 newton: bool = False, jit: bool = False, mode: str = "auto",
                 diagonal_Q: bool = False, diagonal_R: bool = False, full: bool = False):
        if mode not in ("auto", "unrolled", "mapped"):
            raise ValueError(f"mode must be 'auto', 'unrolled' or 'mapped', got {mode!r}")
        self.model, self.N = model, N
        self.lower, self.upper = lower, upper
        bounded = bool(np.isfinite(lower).any() or np.isfinite(upper).any())
        nx = model.nx
        if not (np.array_equal(lower, np.tile(lower[:nx], N)) and
                np.array_equal(upper, np.tile(upper[:nx], N))):
            raise ValueError("lower and upper must repeat the same state bounds in every slot")
        self._bounded = bounded
        self._project = (lambda z: np.clip(z, lower, upper)) if bounded else (lambda z: z)
        self.max_iter, self.xtol = int(max_iter), float(xtol)
        self.newton, self.jit = bool(newton), bool(jit)
        self.full = bool(full)
        self._stages = _StageFunctions(model, diagonal_Q, diagonal_R)
        if mode == "auto":  # compiled code: small chunks compile fast and run as fast
            per_slot = self._stages.fused(False, False).n_instructions()
            mode = "mapped" if self.jit or N * per_slot > AUTO_UNROLL_INSTRUCTIONS \
                else "unrolled"
        self.mode = mode
        self._slots = _Slots()
        self._slices, self._n_params = slices, n_params
        # input buffers shared by every compiled function
        self._xbuf, self._pbuf, self._lbuf = np.zeros(N * model.nx), np.zeros(n_params), np.zeros(1)
        self._dbuf, self._abuf = np.zeros(N * model.nx), np.zeros(1)  # for the rollout
        self._funs: dict[tuple[str, bool], object] = {}  # FastFunction or a pair
        self._chunked: _Chunked | None = None  # the mapped mode's chunk functions
        #: seconds spent building compiled functions (all of them are built on first
        #: use); :meth:`solve` leaves them out of its time and reports them apart
        self.build_seconds = 0.0
        self.last_build = 0.0
        self._ridge = False  # set for good once a block was singular without it
        self._complete = False  # graphs of the current solve

    # ------------------------------------------------------------------ graphs
    def _function(self, key: str, complete: bool | None = None):
        """The compiled function ``key`` ("gn", "gn_lam", "newton", "newton_lam",
        "cost" or "cov") for complete data or not (default: as the current
        solve), built on first use. The iterations come as a pair of
        FastFunctions with separate output buffers."""
        complete = self._complete if complete is None else complete
        fun = self._funs.get((key, complete))
        if fun is None:
            t0 = time.perf_counter()
            fun = self._funs[key, complete] = self._build(key, complete)
            self.build_seconds += time.perf_counter() - t0
        return fun

    def _build(self, key: str, complete: bool):
        if self.mode == "mapped" or (key == "covs" and self.N > COVARIANCE_UNROLL_SLOTS
                                     and not self.jit):
            return self._build_chunked(key, complete)
        st, nx, N = self._stages, self.model.nx, self.N
        p = ca.MX.sym("p", self._n_params)
        X = ca.MX.sym("X", nx, N)
        lam = ca.MX.sym("lam")
        xv = ca.vec(X)
        q = self._parts(p, N, complete)
        damped, newton = key.endswith("_lam"), key.startswith("newton")
        if key == "cost":
            ins, outs = [xv, p], [self._cost_graph(X, q, N)]
        elif key == "cov":
            S_last = self._forward(X, q, N, lam, False, False, None)[0][0][0]
            ins, outs = [xv, p], [st.inverse(S_last)]
        elif key == "covs":
            ins, outs = [xv, p], [self._forward(X, q, N, lam, False, False, None,
                                                covariance=True)]
        elif key == "roll":
            D, alpha = ca.MX.sym("D", nx, N), ca.MX.sym("alpha")
            cols = [X[:, 0] + alpha * D[:, 0]]
            if N > 1:
                cols.append(self._slots.scan(
                    st.roll, N - 1, 1, cols[0], X[:, :N - 1], D[:, :N - 1], X[:, 1:],
                    D[:, 1:], q["U"][:, :N - 1], q["omega"], alpha)[0])
            ins, outs = [xv, p, ca.vec(D), alpha], [ca.vec(ca.horzcat(*cols))]
        else:
            ins = [xv, p] + ([lam] if damped else [])
            bounds = (self.lower[:nx], self.upper[:nx]) if self._bounded else None
            directions, g, cost, free, diag = self._forward(X, q, N, lam, newton, damped,
                                                            bounds, solve=True)
            if bounds is not None:  # fixed variables: a step scaled by the GN diagonal
                scaled = -g / (diag + 1e-300)
                directions = [ca.if_else(1 - free, scaled, d) for d in directions]
            outs = [cost, g] + directions[::-1]  # Newton's first, Gauss-Newton's last
        name = f"gn_{key}" + ("_complete" if complete else "")
        fun = ca.Function(name, ins, outs).expand(name)
        if self.jit and key not in ("cov", "covs"):
            fun = jitted(fun)
        bufs = [self._xbuf, self._pbuf] + ([self._lbuf] if len(ins) == 3 else [])
        if key == "roll":
            return FastFunction(fun, [self._xbuf, self._pbuf, self._dbuf, self._abuf])
        if key in ("cost", "cov", "covs"):
            return FastFunction(fun, bufs)
        return FastFunction(fun, bufs), FastFunction(fun, bufs)  # two output buffers

    def _build_chunked(self, key: str, complete: bool):
        """The mapped mode's function ``key``: loops over chunks (see :class:`_Chunked`)."""
        if self._chunked is None:
            chunk = JIT_CHUNK_SLOTS if self.jit else \
                max(CHUNK_SLOTS, -(-self.N // MAX_CHUNKS))
            self._chunked = _Chunked(self, chunk, self.jit)
        ch, nx = self._chunked, self.model.nx
        if key == "cost":
            return _ChunkedCost(ch, complete)
        if key == "cov":
            return _ChunkedCovariance(ch, complete)
        if key == "covs":
            return _ChunkedCovariances(ch, complete)
        if key == "roll":
            return _ChunkedRoll(ch)
        bounds = (self.lower[:nx], self.upper[:nx]) if self._bounded else None
        it = _ChunkedIteration(ch, key.startswith("newton"), key.endswith("_lam"), bounds,
                               complete)
        return it, it.twin()

    def _forward(self, X, q, N, lam, newton, damped, bounds, solve=False,
                 covariance=False):
        """The fused forward scan over the slots (see :meth:`_StageFunctions.fused`).

        Returns ``(chains, g, cost, free, diag)``: per chain (Gauss-Newton, then
        Newton's) the last Schur complement and reduced right-hand side, or with
        ``solve`` the direction ``vec(d)`` from the backward scan; the gradient
        ``vec(g)``, the total cost, and with bounds ``vec(free)`` and the
        Gauss-Newton diagonal. With ``covariance`` (Gauss-Newton, no bounds):
        ``vec`` of the diagonal blocks of :math:`H^{-1}`, ``(nx, nx N)``, from the
        backward recursion (see :meth:`covariances`).
        """
        st, nx, slots = self._stages, self.model.nx, self._slots
        step = st.fused(newton, damped, bounds, covariance)
        chains = 2 if newton else 1
        init = []
        for _ in range(chains):
            init += [ca.MX.eye(nx), ca.MX.zeros(nx, 1), ca.MX.zeros(nx, nx), ca.MX.zeros(nx, nx)]
        init.append(ca.MX.zeros(nx, 1))
        if bounds is not None:
            init.append(ca.MX.ones(nx, 1))
        n_carry = len(init)
        om = q["omega"]
        om = ca.horzcat(om, ca.DM.zeros(1, 1) if isinstance(om, ca.DM) else ca.MX.zeros(1, 1))
        link = ca.DM([[1.0] * (N - 1) + [0.0]])  # the last slot has no process term
        x_next = ca.horzcat(X[:, 1:], X[:, N - 1:])
        args = init + [X, x_next, q["Y"], q["WY"], q["Up"], q["a"], q["U"], om, q["WQ"], link,
                       q["xbar"], q["W0"], q["A0"]] + ([lam] if damped else [])
        outs = slots.scan(step, N, n_carry, *args, last_only=True)
        carries, rest = outs[:n_carry], outs[n_carry:]
        if covariance:  # the factors of S_{j-1} in slot j's outputs: the blocks of slot j-1
            Vs, L, inv_D = rest[0], rest[2], rest[-1]
            last = st.inverse(carries[0])
            if N == 1:
                return last
            rev = slots.scan(st.cov_bwd, N - 1, 1, last, _reverse_cols(Vs[:, nx:], N - 1, nx),
                             _reverse_cols(L[:, nx:], N - 1, nx),
                             _reverse_cols(inv_D[:, 1:], N - 1, 1))[0]
            return ca.horzcat(_reverse_cols(rev, N - 1, nx), last)
        g, cost = rest[3 * chains], ca.sum2(rest[3 * chains + 1])
        free, diag = (ca.vec(rest[3 * chains + 2]), ca.vec(rest[3 * chains + 3])) \
            if bounds is not None else (None, None)
        results = []
        for c in range(chains):
            S_last, z_last = carries[4 * c], carries[4 * c + 1]
            if not solve:
                results.append((S_last, z_last))
                continue
            Vs, vs, L = rest[3 * c:3 * c + 3]
            d_last = st.last(S_last, z_last)
            if N == 1:
                results.append(ca.vec(d_last))
                continue
            # what step j returns for the backward pass belongs to slot j - 1
            d_rev = slots.scan(st.bwd, N - 1, 1, d_last, _reverse_cols(Vs[:, nx:], N - 1, nx),
                               _reverse_cols(vs[:, 1:], N - 1, 1),
                               _reverse_cols(L[:, nx:], N - 1, nx))[0]
            results.append(ca.vec(ca.horzcat(_reverse_cols(d_rev, N - 1, 1), d_last)))
        return results, ca.vec(g), cost, free, diag

    def _parts(self, p, N, complete):
        m = self.model
        nx, nu, ny = m.nx, m.nu, m.ny
        part = {k: p[s] for k, s in self._slices.items()}
        W0 = ca.reshape(part["w0"], nx, nx)
        # complete data: one measurement weight for every slot (passed once, shared)
        WY = part["wr"] if complete else ca.reshape(part["wy"], ny * ny, N)
        q = {"Y": ca.reshape(part["y"], ny, N), "WY": WY, "WQ": part["wq"],
             "U": ca.reshape(part["u"], m.nw, N), "Up": ca.reshape(part["up"], nu, N),
             "xbar": part["xbar"], "W0": part["w0"], "A0": ca.vec(W0.T @ W0)}
        if self.full:  # constants that fold away
            q["a"], q["omega"] = full_record_constants(N)
        else:
            q["a"] = ca.reshape(part["a"], 1, N)
            q["omega"] = ca.reshape(part["omega"], 1, N - 1)
        return q

    def _meas_args(self, X, q):
        return (X, q["Y"], q["WY"], q["Up"], q["a"], q["xbar"], q["W0"], q["A0"])

    def _trans_args(self, X, q, N):
        return (X[:, :N - 1], X[:, 1:], q["U"][:, :N - 1], q["omega"], q["WQ"])

    def _cost_graph(self, X, q, N):
        st = self._stages
        cost = ca.sum2(self._slots.map(st.meas_cost, N, *self._meas_args(X, q))[0])
        if N > 1:
            cost = cost + ca.sum2(self._slots.map(st.trans_cost, N - 1,
                                                  *self._trans_args(X, q, N))[0])
        return cost

    # ------------------------------------------------------------------ solve
    def solve(self, X0: np.ndarray, p: np.ndarray, complete: bool = False, reweight=None):
        r"""Minimise from ``X0`` (N, nx).

        Gauss-Newton iterations first (cheap: no second derivatives). When
        they contract slowly (a step more than ``SWITCH_RATIO`` = 0.8 of the
        previous one, as on large-residual problems) or stop descending, the iterations
        switch to Newton steps with the exact Hessian blocks, falling back to
        the Gauss-Newton direction where the Newton one does not descend. If
        no direction decreases the cost, Levenberg-Marquardt damping
        :math:`\lambda\,\mathrm{diag}(H)` is raised until one does (and
        relaxed after full steps).

        Converged when what is left after the next projected Gauss-Newton
        step :math:`d_k` is negligible: the step itself moves no variable by
        more than :math:`\epsilon = ` ``xtol * (1 + max|x|)``, or (without
        bounds) the steps contract, :math:`\rho = \|d_k\|_\infty /
        \|d_{k-1}\|_\infty < 1` after a full step, and the geometric bound on
        the rest, :math:`\rho/(1-\rho)\,\|d_k\|_\infty`, is below
        :math:`\epsilon` (Deuflhard's contraction estimate), or the decrease
        it predicts is at rounding level (1e-13 of the cost).
        That last step is taken when the cost, evaluated alone without
        derivatives, confirms it (MINPACK likewise returns the last accepted
        step without a new Jacobian). On the Lorenz FIE of seed 000 this stops
        within 3e-8 of the optimum Ipopt finds at tolerance 1e-12.

        ``complete``: every slot holds every output with the weights given at
        construction (``p`` carries the same values); constant-weight graphs
        are used.

        ``reweight(x)``: called at the start and at every accepted point; it may
        change the measurement weights in :attr:`_pbuf` (a robust loss's
        iteratively reweighted least squares, see :mod:`estim.solvers.robust`).
        Each step then decreases the cost of the weights of its starting point,
        and a negligible step is a stationary point of the robust cost (only the
        step test then stops the iterations).

        Returns ``(x, success, status, iterations, cost, seconds)``, ``x`` flat.
        """
        # far from the data the iterates may overflow: the line search rejects such
        # points (inf and NaN fail its test) without a numpy warning
        with np.errstate(over="ignore", invalid="ignore"):
            return self._minimise(X0, p, complete, reweight)

    def _minimise(self, X0, p, complete, reweight):
        """:meth:`solve`'s iterations."""
        t0, b0 = time.perf_counter(), self.build_seconds
        proj, bounded, xtol = self._project, self._bounded, self.xtol
        x = proj(np.array(X0, dtype=float).ravel())
        self._complete = bool(complete)
        self._pbuf[:] = p  # fixed for the whole solve (but for reweight): written once
        if reweight is not None:
            reweight(x)
        lam, newton, last_step, last_full, last_alpha = 0.0, self.newton, np.inf, np.inf, 0.0
        self._prefer_roll = False
        # two output buffers: the current point's, and the one a trial point writes
        slot, pair = 0, self._iteration(newton, lam)
        f, g, dirs = self._evaluate(pair[slot], x, lam)
        if not np.isfinite(f):
            return x, False, "non-finite cost at the initial guess", 0, f, self._elapsed(t0, b0)
        status, steps = "max_iter", 0
        xmax = np.abs(x).max()  # an upper bound of max|x|, made exact when it matters
        while steps < self.max_iter:
            # judged on the Gauss-Newton direction, a descent direction (J^T J is positive
            # semi-definite) where the Newton one may not be: converged when the rest
            # after the next step is negligible or the decrease it predicts is at rounding
            # level (an ascending one means the near-singular solve lost accuracy: not
            # converged; the line search rejects it and the damping below regularises)
            d_gn = dirs[-1]
            move = proj(x + d_gn) - x if bounded else d_gn
            decrease = -float(g @ move)
            if decrease != decrease and not (lam or self._ridge):
                # a singular block: from now on with the ridge (see _damp)
                self._ridge = True
                slot, pair = 1 - slot, self._iteration(newton, lam)
                f, g, dirs = self._evaluate(pair[slot], x, lam)
                continue
            size = np.abs(move).max()
            # contraction rate of unbounded iterations (with bounds, a tiny step can
            # precede a change of the active set and a large one)
            rho = size / last_full if last_full < np.inf and not bounded else np.inf
            rest = min(size, rho * size / (1.0 - rho) if rho < 1.0 else np.inf)
            if rest <= xtol * (1.0 + xmax):
                xmax = np.abs(x).max()
            # (reweighted: a small decrease of this iteration's weighted cost is no
            # proof, IRLS converges linearly in directions the weights flatten)
            if rest <= xtol * (1.0 + xmax) or (
                    0.0 <= decrease <= 1e-13 * abs(f) and reweight is None):
                status = "ok"
                xn = x + move
                self._xbuf[:] = xn
                fn = float(self._function("cost").evaluate()[0][0])
                if fn <= f - 1e-4 * max(decrease, 0.0):  # the last step, confirmed by the cost
                    x, f, steps = xn, fn, steps + 1
                break
            new = None
            for d in dirs:
                slope = -decrease if d is d_gn and not bounded else None
                new = self._line_search(x, f, g, d, pair[1 - slot], lam, slope)
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
                slot, pair = 1 - slot, self._iteration(newton, lam)
                f, g, dirs = self._evaluate(pair[slot], x, lam)
                last_full = np.inf
                continue
            xn, alpha, evaluated, fn = new
            step = np.abs(xn - x).max()
            # Gauss-Newton's linear rate near a large-residual optimum: full steps that
            # shrink slowly and gain little (not the steps far from it, which halve the
            # cost or are damped)
            switch = not newton and alpha == 1.0 == last_alpha and \
                step > SWITCH_RATIO * last_step and fn > 0.5 * f
            x, steps, last_step, xmax, last_alpha = xn, steps + 1, step, xmax + step, alpha
            last_full = step if alpha == 1.0 and not lam else np.inf  # for the rate rho
            if alpha == 1.0 and lam:
                lam = lam / 10.0 if lam > 1e-8 else 0.0
                evaluated, pair = None, self._iteration(newton, lam)
            if switch:
                newton, evaluated, pair = True, None, self._iteration(True, lam)
            if reweight is not None:  # new weights at the new point: evaluated afresh
                reweight(x)
                evaluated = None
            slot = 1 - slot  # the trial's buffer, or a new evaluation there
            f, g, dirs = evaluated if evaluated is not None else \
                self._evaluate(pair[slot], x, lam)
        ok = status == "ok" and bool(np.isfinite(x).all()) and np.isfinite(f)
        return x, ok, status, steps, f, self._elapsed(t0, b0)

    def _elapsed(self, t0: float, b0: float) -> float:
        """Seconds since ``t0`` without the building since then (kept in
        :attr:`last_build`)."""
        self.last_build = self.build_seconds - b0
        return time.perf_counter() - t0 - self.last_build

    def _line_search(self, x, f, g, d, fun, lam, slope=None):
        """Armijo backtracking along one of two paths: the step ``x + alpha d``
        (projected on the bounds), or the same step taken through the dynamics
        (:meth:`_rolled`).

        The path that gave the last accepted step is tried first, its full step
        evaluated by the iteration function ``fun`` (reused by the next iteration
        when accepted); then the other path's full step, by the cost alone; then
        shorter steps along the path whose full step was cheaper, by the cost alone.
        ``slope``: ``g @ d`` if known. Returns ``(x_new, alpha, evaluation or None,
        cost at x_new)``, or None on failure.
        """
        proj, bounded = self._project, self._bounded
        if slope is None:
            slope = float(g @ (proj(x + 1e-8 * d) - x)) if bounded else float(g @ d)
        if not slope < 0.0:
            return None  # not a descent direction (or not finite)
        paths = ("line",) if self.N == 1 else ("roll", "line") if self._prefer_roll \
            else ("line", "roll")
        cost = self._function("cost")
        full = {}
        for path in paths:
            xn = self._point(path, x, d, 1.0)
            if path == paths[0]:
                ev = self._evaluate(fun, xn, lam)
                fn = ev[0]
            else:
                ev, self._xbuf[:] = None, xn
                fn = float(cost.evaluate()[0][0])
            # Armijo test (False for NaN); the gradient of f is 2 g
            if fn <= f + 2e-4 * float(g @ (xn - x)):
                self._prefer_roll = path == "roll"
                return xn, 1.0, ev, fn
            full[path] = fn if fn == fn else np.inf
        path = min(full, key=full.get)
        alpha = 0.5
        while alpha > 1e-8:
            xn = self._point(path, x, d, alpha)
            self._xbuf[:] = xn
            fn = float(cost.evaluate()[0][0])
            if fn <= f + 2e-4 * float(g @ (xn - x)):
                self._prefer_roll = path == "roll"
                return xn, alpha, None, fn
            alpha *= 0.5
        return None

    def _point(self, path: str, x, d, alpha: float) -> np.ndarray:
        """The point ``alpha`` along ``path`` (see :meth:`_line_search`)."""
        if path == "roll":
            return self._rolled(x, d, alpha)
        return self._project(x + alpha * d) if self._bounded else x + alpha * d

    def _rolled(self, x, d, alpha: float) -> np.ndarray:
        """The step ``alpha d`` from ``x`` taken through the dynamics (projected)."""
        self._xbuf[:] = x
        self._dbuf[:] = d
        self._abuf[0] = alpha
        out = self._function("roll").evaluate()[0]
        return self._project(out.copy()) if self._bounded else out.copy()

    def _iteration(self, newton, lam):
        """The pair of iteration functions (two output buffers) for the current state."""
        return self._function(_ITERATIONS[newton, bool(lam) or self._ridge])

    def _evaluate(self, fun, x, lam):
        """Cost, gradient and direction(s) at ``x`` by the iteration function ``fun``
        (the parameters already in place), as views of its output buffers."""
        self._xbuf[:] = x
        self._lbuf[0] = lam
        out = fun.evaluate()
        return float(out[0][0]), out[1], tuple(out[2:])

    def cost(self, x: np.ndarray, p: np.ndarray, complete: bool = False) -> float:
        """The cost ``||r(x)||^2`` at ``x`` (flat) for the parameters ``p``."""
        self._xbuf[:] = x
        self._pbuf[:] = p
        fun = self._function("cost", bool(complete))
        return float(fun.evaluate()[0][0])

    def reset(self) -> None:
        """Back to the state after construction (the ridge is added again only when
        a block turns out singular)."""
        self._ridge = False
        self._complete = False

    def covariances(self, x: np.ndarray, p: np.ndarray, complete: bool = False) -> np.ndarray:
        r"""The diagonal blocks of :math:`H^{-1} = (J^\top J)^{-1}` at ``x`` (flat) for the
        parameters ``p``, ``(N, nx, nx)``: the Laplace covariance of every slot.

        The Gauss-Newton matrix without damping or active set (the unconstrained
        approximation at ``x``, as :meth:`covariance`). From the Schur complements
        :math:`S_j` and off-diagonal blocks :math:`E_j` of the forward elimination
        (see the module docstring), the backward recursion

        .. math::
            \Sigma_{N-1} = S_{N-1}^{-1}, \qquad
            \Sigma_j = S_j^{-1} + G_j \Sigma_{j+1} G_j^\top, \quad G_j = S_j^{-1} E_j,

        costs :math:`O(N n_x^3)` operations and :math:`O(N n_x^2)` memory: no
        dense inverse is formed. On a linear-Gaussian problem :math:`-G_j` is the
        Rauch-Tung-Striebel smoother gain and :math:`\Sigma_j` its covariance.
        """
        nx = self.model.nx
        self._xbuf[:] = x
        self._pbuf[:] = p
        fun = self._function("covs", bool(complete))
        out = fun.evaluate()[0]
        return out.reshape(self.N, nx, nx).transpose(0, 2, 1).copy()

    def covariance(self, x: np.ndarray, p: np.ndarray, complete: bool = False) -> np.ndarray:
        """``(J^T J)^{-1}`` block of the last state at ``x`` (the posterior covariance)
        for the parameters ``p`` (``complete`` as in :meth:`solve`)."""
        nx = self.model.nx
        self._xbuf[:] = x
        self._pbuf[:] = p
        fun = self._function("cov", bool(complete))
        return fun.evaluate()[0].reshape(nx, nx, order="F").copy()


def _key(const) -> tuple | None:
    """A hashable form of :meth:`_Chunked._constants`."""
    return None if const is None else tuple(tuple(v.tolist()) for v in const.values())


class _Chunked:
    """The iteration, cost, covariance and rollout functions of a long record, evaluated
    as a loop over chunks of slots.

    Each chunk length has one compiled SX function per task (a forward elimination
    chunk, a backward one, a cost one, a rollout one), applied to consecutive slices of
    the buffers: the slices are bound in place (no copies), so memory holds only the
    per-slot data, and building costs the same at any record length. A call is a
    Python loop over the chunks (``N / chunk`` function calls per scan). The results
    equal the unrolled graph's up to rounding.
    """

    def __init__(self, gn: StructuredGaussNewton, chunk: int, jit: bool):
        self.gn, self.st = gn, gn._stages
        m, N = gn.model, gn.N
        self.nx, self.nu, self.ny, self.nw, self.N = m.nx, m.nu, m.ny, m.nw, N
        if gn.full and N > 2:
            # the first and last slots alone (the arrival term, the missing link): the
            # chunks between are alike, one function for all of them
            self.chunks = [(0, 1)] + [(lo, min(lo + chunk, N - 1))
                                      for lo in range(1, N - 1, chunk)] + [(N - 1, N)]
        else:
            self.chunks = [(lo, min(lo + chunk, N)) for lo in range(0, N, chunk)]
        # transitions 0..N-2 in chunks, for the backward pass and the rollout
        self.tchunks = [(lo, min(lo + chunk, N - 1)) for lo in range(0, N - 1, chunk)]
        self.jit = jit
        self._funs: dict[tuple, ca.Function] = {}
        self._bufs: dict[tuple, tuple] = {}
        nx, ny, nu = self.nx, self.ny, self.nu
        self.xnext = np.zeros(N * nx)
        self.om = np.zeros(N)
        self.link = np.ones(N)
        self.link[-1] = 0.0
        self.a = np.zeros(N)
        self.a0 = np.zeros(nx * nx)
        self.full_a, self.full_om = gn.full, gn.full
        sl = gn._slices
        p = gn._pbuf
        self.views = {"y": p[sl["y"]], "wy": p[sl["wy"]], "u": p[sl["u"]], "up": p[sl["up"]],
                      "xbar": p[sl["xbar"]], "w0": p[sl["w0"]], "wq": p[sl["wq"]],
                      "wr": p[sl["wr"]]}
        self.sizes = {"x": nx, "xn": nx, "y": ny, "wy": ny * ny, "up": nu, "a": 1,
                      "u": self.nw,
                      "om": 1, "link": 1}
        # the last slot's solve S^{-1} z, bound once: (S, z, out, call)
        S, z, dl = np.zeros(nx * nx), np.zeros(nx), np.zeros(nx)
        b, ev = self.st.last.buffer()
        for i, a in enumerate((S, z)):
            b.set_arg(i, memoryview(a))
        b.set_res(0, memoryview(dl))
        self.last_buf = (S, z, dl, ev, b)

    # ---------------------------------------------------------------- building
    def _compiled(self, key, build):
        """``build()``'s function with dense outputs (the buffers are read as dense
        arrays), compiled with ``jit`` (through the per-machine cache)."""
        if key not in self._funs:
            t0 = time.perf_counter()
            fun = build()
            ins = fun.sx_in()
            dense = ca.Function(fun.name(), ins, [ca.densify(o) for o in fun.call(ins)])
            self._funs[key] = jitted(dense) if self.jit else dense
            self.gn.build_seconds += time.perf_counter() - t0
        return self._funs[key]

    def _buffer(self, fun):
        key = id(fun)
        if key not in self._bufs:
            self._bufs[key] = fun.buffer()
        return self._bufs[key]

    def _constants(self, lo, hi):
        """A full record's window bookkeeping of slots ``lo:hi`` (arrival weight ``a``,
        ``om``, ``link``), constants of its chunk functions as in the unrolled graph
        (they fold away); None for a window, where they are data."""
        if not self.gn.full:
            return None
        a = np.zeros(hi - lo)
        if lo == 0:
            a[0] = 1.0
        link = np.ones(hi - lo)
        if hi == self.N:
            link[-1] = 0.0
        return {"a": a, "om": np.ones(hi - lo), "link": link}

    def _fold(self, seq, const):
        """``seq`` with the bookkeeping symbols replaced by ``const`` (if any); the
        function keeps them as (unused) inputs, so every chunk is called alike."""
        if const is None:
            return seq
        out = dict(seq)
        for k, v in const.items():
            out[k] = ca.DM(v).T
        return out

    def _forward_chunk(self, step, L, n_carry, complete, damped, const=None):
        """``L`` slots of the fused forward step (:meth:`_StageFunctions.fused`)."""
        def build():
            nx, sym = self.nx, ca.SX.sym
            carry = [sym(f"c{i}", step.sparsity_in(i)) for i in range(n_carry)]
            seq = {k: sym(k, n, L) for k, n in self.sizes.items()}
            if complete:
                seq["wy"] = sym("wy", self.ny * self.ny)
            inputs = list(seq.values())
            seq = self._fold(seq, const)
            shared = [sym("wq", nx * nx), sym("xbar", nx), sym("w0", nx * nx),
                      sym("a0", nx * nx)] + ([sym("lam")] if damped else [])
            c, slots = carry, []
            for j in range(L):
                wy = seq["wy"] if complete else seq["wy"][:, j]
                res = step(*c, seq["x"][:, j], seq["xn"][:, j], seq["y"][:, j], wy,
                           seq["up"][:, j], seq["a"][j], seq["u"][:, j], seq["om"][j],
                           shared[0], seq["link"][j], *shared[1:])
                c, slots = res[:n_carry], slots + [res[n_carry:]]
            outs = list(c) + [ca.horzcat(*col) for col in zip(*slots, strict=True)]
            return ca.Function(f"fwd_chunk_{L}", carry + inputs + shared, outs)
        return self._compiled(("fwd", id(step), L, complete, _key(const)), build)

    def _backward_chunk(self, L):
        """``L`` steps of the backward substitution, the last slot first."""
        def build():
            nx, sym = self.nx, ca.SX.sym
            dn, Vs, vs, Lm = (sym("d_next", nx), sym("Vs", nx, nx * L), sym("vs", nx, L),
                              sym("L", nx, nx * L))
            d, out = dn, [None] * L
            for j in range(L - 1, -1, -1):
                d = self.st.bwd(d, Vs[:, j * nx:(j + 1) * nx], vs[:, j], Lm[:, j * nx:(j + 1) * nx])
                out[j] = d
            return ca.Function(f"bwd_chunk_{L}", [dn, Vs, vs, Lm], [ca.horzcat(*out)])
        return self._compiled(("bwd", L), build)

    def _cov_backward_chunk(self, L):
        """``L`` steps of the covariance recursion (:attr:`_StageFunctions.cov_bwd`),
        the last slot first."""
        def build():
            nx, sym = self.nx, ca.SX.sym
            Sn, Vs, Lm, iD = (sym("Sigma_next", nx, nx), sym("Vs", nx, nx * L),
                              sym("L", nx, nx * L), sym("inv_D", nx, L))
            Sig, out = Sn, [None] * L
            for j in range(L - 1, -1, -1):
                cols = slice(j * nx, (j + 1) * nx)
                Sig = self.st.cov_bwd(Sig, Vs[:, cols], Lm[:, cols], iD[:, j])
                out[j] = Sig
            return ca.Function(f"cov_bwd_chunk_{L}", [Sn, Vs, Lm, iD], [ca.horzcat(*out)])
        return self._compiled(("cov_bwd", L), build)

    def _cost_chunk(self, L, complete, const=None):
        def build():
            nx, sym = self.nx, ca.SX.sym
            seq = {k: sym(k, n, L) for k, n in self.sizes.items()}
            if complete:
                seq["wy"] = sym("wy", self.ny * self.ny)
            inputs = list(seq.values())
            seq = self._fold(seq, const)
            wq, xbar, w0, a0 = (sym("wq", nx * nx), sym("xbar", nx), sym("w0", nx * nx),
                                sym("a0", nx * nx))
            total = ca.SX(0)
            for j in range(L):
                wy = seq["wy"] if complete else seq["wy"][:, j]
                total += self.st.meas_cost(seq["x"][:, j], seq["y"][:, j], wy, seq["up"][:, j],
                                           seq["a"][j], xbar, w0, a0)
                total += seq["link"][j] * self.st.trans_cost(
                    seq["x"][:, j], seq["xn"][:, j], seq["u"][:, j], seq["om"][j], wq)
            return ca.Function(f"cost_chunk_{L}", inputs + [wq, xbar, w0, a0], [total])
        return self._compiled(("cost", L, complete, _key(const)), build)

    def _roll_chunk(self, L):
        def build():
            nx, sym = self.nx, ca.SX.sym
            xp0 = sym("xp0", nx)
            xp = xp0
            x, d, xn, dn = (sym(k, nx, L) for k in ("x", "d", "xn", "dn"))
            u, om, alpha = sym("u", self.nw, L), sym("om", 1, L), sym("alpha")
            oms = ca.DM.ones(1, L) if self.gn.full else om  # a full record: every link
            cols = []
            for j in range(L):
                xp = self.st.roll(xp, x[:, j], d[:, j], xn[:, j], dn[:, j], u[:, j], oms[j],
                                  alpha)
                cols.append(xp)
            return ca.Function(f"roll_chunk_{L}", [xp0, x, d, xn, dn, u, om, alpha],
                               [ca.horzcat(*cols)])
        return self._compiled(("roll", L, self.gn.full), build)

    # ---------------------------------------------------------------- calling
    @staticmethod
    def _call(buf, args, res) -> None:
        b, ev = buf
        for i, a in enumerate(args):
            b.set_arg(i, memoryview(a))
        for i, r in enumerate(res):
            b.set_res(i, memoryview(r))
        ev()

    def calls(self, jobs) -> list:
        """One callable per ``(fun, args, res)`` of ``jobs`` (a chunk loop, in order).

        The arrays must stay in place (they are views of the solver's buffers): each
        chunk gets a buffer with its arguments bound once, unless the buffers' work
        memory would exceed :data:`PREBIND_BYTES`; then one buffer per function is
        rebound at every call."""
        jobs = list(jobs)
        work = sum(8 * fun.sz_w() for fun, _, _ in jobs)
        out = []
        for fun, args, res in jobs:
            if work <= PREBIND_BYTES:
                b, ev = fun.buffer()
                for i, a in enumerate(args):
                    b.set_arg(i, memoryview(a))
                for i, r in enumerate(res):
                    b.set_res(i, memoryview(r))
                out.append((ev, (b, args, res)))  # the buffer and arrays kept alive
            else:
                buf = self._buffer(fun)
                out.append((lambda buf=buf, args=args, res=res: self._call(buf, args, res),
                            None))
        return out

    def prepare(self):
        """The per-call data derived from the buffers (shifted states, window
        bookkeeping, the arrival weight's Gram matrix)."""
        gn, nx = self.gn, self.nx
        x = gn._xbuf
        self.xnext[:-nx] = x[nx:]
        self.xnext[-nx:] = x[-nx:]
        p, sl = gn._pbuf, gn._slices
        if gn.full:
            self.om[:-1] = 1.0
            self.a[:] = 0.0
            self.a[0] = 1.0
        else:
            self.om[:-1] = p[sl["omega"]]
            self.a[:] = p[sl["a"]]
        W0 = self.views["w0"].reshape(nx, nx, order="F")
        self.a0[:] = (W0.T @ W0).ravel(order="F")

    def _slot_args(self, lo, hi, complete):
        nx, ny, nu = self.nx, self.ny, self.nu
        v = self.views
        wy = v["wr"] if complete else v["wy"][lo * ny * ny:hi * ny * ny]
        return [self.gn._xbuf[lo * nx:hi * nx], self.xnext[lo * nx:hi * nx],
                v["y"][lo * ny:hi * ny], wy, v["up"][lo * nu:hi * nu], self.a[lo:hi],
                v["u"][lo * self.nw:hi * self.nw], self.om[lo:hi], self.link[lo:hi]]


class _ChunkedIteration:
    """An iteration function of the mapped mode: ``evaluate()`` returns ``[cost, g,
    directions...]`` like the compiled graph of :meth:`StructuredGaussNewton._build`."""

    def __init__(self, ch: _Chunked, newton, damped, bounds, complete, solve=True,
                 covariance=False):
        self.ch, self.complete, self.solve = ch, complete, solve
        st, nx, N = ch.st, ch.nx, ch.N
        self.step = st.fused(newton, damped, bounds, covariance)
        self.chains, self.bounded, self.damped = 2 if newton else 1, bounds is not None, damped
        self.n_carry = 4 * self.chains + 1 + (1 if self.bounded else 0)
        M = len(ch.chunks)
        # carries at the chunk boundaries: the initial ones, then each chunk's last
        init = []
        for _ in range(self.chains):
            init += [np.eye(nx).ravel(), np.zeros(nx), np.zeros(nx * nx), np.zeros(nx * nx)]
        init.append(np.zeros(nx))
        if self.bounded:
            init.append(np.ones(nx))
        self.carries = [init] + [[np.zeros_like(a) for a in init] for _ in range(M)]
        # per-slot outputs: per chain Vs, vs, L; then g, cost; with bounds free, diag
        shapes = [nx * nx, nx, nx * nx] * self.chains + [nx, 1] + ([nx, nx] if self.bounded
                                                                  else []) + \
            ([nx] * self.chains if covariance else [])  # (the reciprocals of D last)
        self.slot_out = [np.zeros(n * N) for n in shapes]
        self.d = [np.zeros(N * nx) for _ in range(self.chains)]
        self.out = [np.zeros(1), np.zeros(N * nx)] + [np.zeros(N * nx)
                                                      for _ in range(self.chains)]
        self.lam = np.zeros(1)
        self._shared = self.shared()
        self._fwd_calls: list | None = None  # built on first use (see _Chunked.calls)
        self._bwd_calls: list | None = None

    def twin(self) -> _ChunkedIteration:
        """The same function with its own output buffers (the scratch, and with it the
        forward calls, is shared)."""
        other = copy.copy(self)
        other.out = [np.zeros_like(a) for a in self.out]
        other.d = [np.zeros_like(a) for a in self.d]
        other._bwd_calls = None
        return other

    def shared(self):
        v = self.ch.views
        return [v["wq"], v["xbar"], v["w0"], self.ch.a0] + ([self.lam] if self.damped else [])

    def forward(self):
        ch = self.ch
        if self._fwd_calls is None:
            shapes = [len(a) // ch.N for a in self.slot_out]
            self._fwd_calls = ch.calls(
                (ch._forward_chunk(self.step, hi - lo, self.n_carry, self.complete,
                                   self.damped, ch._constants(lo, hi)),
                 self.carries[c] + ch._slot_args(lo, hi, self.complete) + self._shared,
                 self.carries[c + 1] + [a[lo * n:hi * n] for a, n in
                                        zip(self.slot_out, shapes, strict=True)])
                for c, (lo, hi) in enumerate(ch.chunks))
        ch.prepare()
        for call, _ in self._fwd_calls:
            call()
        return self.carries[-1]

    def _backward_calls(self):
        """Per chain, the backward chunks from the last: ``d_j`` from ``d_{j+1}`` and
        slot ``j+1``'s factors."""
        ch, nx = self.ch, self.ch.nx
        calls = []
        for c in range(self.chains):
            Vs, vs, L = self.slot_out[3 * c:3 * c + 3]
            d = self.d[c]
            calls.append(ch.calls(
                (ch._backward_chunk(hi - lo),
                 [d[hi * nx:(hi + 1) * nx], Vs[(lo + 1) * nx * nx:(hi + 1) * nx * nx],
                  vs[(lo + 1) * nx:(hi + 1) * nx], L[(lo + 1) * nx * nx:(hi + 1) * nx * nx]],
                 [d[lo * nx:hi * nx]])
                for lo, hi in reversed(ch.tchunks)))
        return calls

    def evaluate(self):
        ch, nx = self.ch, self.ch.nx
        self.lam[0] = ch.gn._lbuf[0]
        last = self.forward()
        g, cost = self.slot_out[3 * self.chains], self.slot_out[3 * self.chains + 1]
        self.out[0][0] = cost.sum()
        self.out[1][:] = g
        if self._bwd_calls is None:
            self._bwd_calls = self._backward_calls()
        for c in range(self.chains):
            S, z = last[4 * c], last[4 * c + 1]
            d = self.d[c]
            ch.last_buf[0][:] = S
            ch.last_buf[1][:] = z
            ch.last_buf[3]()
            d[-nx:] = ch.last_buf[2]
            for call, _ in self._bwd_calls[c]:
                call()
            if self.bounded:  # fixed variables: a step scaled by the Gauss-Newton diagonal
                free, diag = self.slot_out[-2], self.slot_out[-1]
                d = np.where(free > 0, d, -g / (diag + 1e-300))
            self.out[2 + self.chains - 1 - c][:] = d  # Newton's first, Gauss-Newton's last
        return self.out


class _ChunkedCost:
    def __init__(self, ch: _Chunked, complete):
        self.ch, self.complete = ch, complete
        self.parts = np.zeros(len(ch.chunks))
        self.out = [np.zeros(1)]
        self._calls: list | None = None

    def evaluate(self):
        ch = self.ch
        if self._calls is None:
            v = ch.views
            shared = [v["wq"], v["xbar"], v["w0"], ch.a0]
            self._calls = ch.calls(
                (ch._cost_chunk(hi - lo, self.complete, ch._constants(lo, hi)),
                 ch._slot_args(lo, hi, self.complete) + shared, [self.parts[c:c + 1]])
                for c, (lo, hi) in enumerate(ch.chunks))
        ch.prepare()
        for call, _ in self._calls:
            call()
        self.out[0][0] = self.parts.sum()
        return self.out


class _ChunkedCovariance:
    def __init__(self, ch: _Chunked, complete):
        self.it = _ChunkedIteration(ch, False, False, None, complete, solve=False)
        self.out = [np.zeros(ch.nx * ch.nx)]

    def evaluate(self):
        nx = self.it.ch.nx
        S = self.it.forward()[0]
        self.out[0][:] = np.asarray(self.it.ch.st.inverse(S.reshape(nx, nx, order="F"))
                                    ).ravel(order="F")
        return self.out


class _ChunkedCovariances:
    """The mapped mode's :meth:`StructuredGaussNewton.covariances`: the forward chunks,
    then the backward recursion in chunks, the last slot first."""

    def __init__(self, ch: _Chunked, complete):
        self.it = _ChunkedIteration(ch, False, False, None, complete, solve=False,
                                    covariance=True)
        self.out = [np.zeros(ch.N * ch.nx * ch.nx)]
        self._calls: list | None = None

    def evaluate(self):
        it, ch = self.it, self.it.ch
        nx, n2 = ch.nx, ch.nx * ch.nx
        S = it.forward()[0]
        P = self.out[0]
        P[-n2:] = np.asarray(ch.st.inverse(S.reshape(nx, nx, order="F"))).ravel(order="F")
        if self._calls is None:
            Vs, L, inv_D = it.slot_out[0], it.slot_out[2], it.slot_out[-1]
            self._calls = ch.calls(
                (ch._cov_backward_chunk(hi - lo),
                 [P[hi * n2:(hi + 1) * n2], Vs[(lo + 1) * n2:(hi + 1) * n2],
                  L[(lo + 1) * n2:(hi + 1) * n2], inv_D[(lo + 1) * nx:(hi + 1) * nx]],
                 [P[lo * n2:hi * n2]])
                for lo, hi in reversed(ch.tchunks))
        for call, _ in self._calls:
            call()
        return self.out


class _ChunkedRoll:
    def __init__(self, ch: _Chunked):
        self.ch = ch
        self.out = [np.zeros(ch.N * ch.nx)]
        self._calls: list | None = None

    def evaluate(self):
        ch, nx, nu = self.ch, self.ch.nx, self.ch.nw
        gn = ch.gn
        x, d, alpha = gn._xbuf, gn._dbuf, gn._abuf
        out = self.out[0]
        if self._calls is None:
            u = ch.views["u"]
            self._calls = ch.calls(
                (ch._roll_chunk(hi - lo),
                 [out[lo * nx:(lo + 1) * nx], x[lo * nx:hi * nx], d[lo * nx:hi * nx],
                  x[(lo + 1) * nx:(hi + 1) * nx], d[(lo + 1) * nx:(hi + 1) * nx],
                  u[lo * nu:hi * nu], ch.om[lo:hi], alpha],
                 [out[(lo + 1) * nx:(hi + 1) * nx]])
                for lo, hi in ch.tchunks)
        ch.prepare()
        out[:nx] = x[:nx] + alpha[0] * d[:nx]
        for call, _ in self._calls:
            call()
        return self.out
