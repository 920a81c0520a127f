r"""The per-slot Functions of the windowed least-squares problem, and the scans over slots.

The cost of :mod:`estim.solvers.least_squares.nlp` is a sum of per-slot terms: the arrival and
measurement terms of slot :math:`j` and the process term linking slots :math:`j` and
:math:`j+1`. :class:`StageFunctions` builds them once per model as SX Functions, with
their Gauss-Newton blocks (and the exact Hessian blocks for Newton steps), one step
of the block elimination and of the backward recursions; :func:`forward_scan` strings
them over ``N`` slots with CasADi's ``mapaccum`` (:class:`Slots`) into the graph of one
iteration of :class:`~estim.solvers.least_squares.gauss_newton.StructuredGaussNewton`. What a slot
computes from the weights and the window's bookkeeping alone (the products of the
weights with the constant entries of the model's Jacobians) is the same at every
slot of a kind: the scan computes it once per kind of slot (:func:`hoisted`), which
saves about a tenth of the instructions of an iteration on a full record.
"""

from __future__ import annotations

from functools import cached_property

import casadi as ca
import numpy as np

from estim.model import Model
from estim.solvers.least_squares.blocks import (
    damp,
    gram,
    ldl,
    lower_solve,
    lower_transposed_solve,
    sym_product,
    sym_solve,
)

__all__ = ["Slots", "StageFunctions", "forward_scan", "reverse_cols"]


class StageFunctions:
    """Per-slot pieces of the Gauss-Newton/Newton system as SX Functions.

    ``meas``: arrival (weight ``a``) and measurement terms of one slot;
    ``trans``: the process term linking two slots (``*_newton``: with the
    exact Hessian blocks as well, ``*_cost``: the cost alone);
    ``fwd``/``last``/``bwd``: one step of the block elimination; ``inverse``:
    a symmetric block inverse; ``cov_bwd``: one step of the backward recursion for
    the diagonal blocks of :math:`H^{-1}`; :meth:`fused`: one slot of the forward pass.
    """

    def __init__(self, model: Model, diagonal_Q: bool = False, diagonal_R: bool = False,
                 interval_weights: bool = False):
        nx, nu, ny = model.nx, model.nu, model.ny
        pm, eye = ca.DM(model.p), ca.DM.eye(nx)
        x, xb = ca.SX.sym("x", nx), ca.SX.sym("xb", nx)
        y, wy = ca.SX.sym("y", ny), ca.SX.sym("wy", ny * ny)
        # the transition's parameters: its input, and with interval_weights its own
        # weight factor after it (column-major), in place of the shared wq
        width = model.nw + (nx * nx if interval_weights else 0)
        u, up = ca.SX.sym("u", width), ca.SX.sym("up", nu)  # transition, measurement
        uF = u[:model.nw]
        a, om, wq = ca.SX.sym("a"), ca.SX.sym("omega"), ca.SX.sym("wq", nx * nx)
        xbar, w0, a0 = ca.SX.sym("xbar", nx), ca.SX.sym("w0", nx * nx), ca.SX.sym("A0", nx * nx)
        W0, A0 = ca.reshape(w0, nx, nx), ca.reshape(a0, nx, nx)  # A0 = W0^T W0, hoisted
        self.nx, self.nu, self.ny, self.nw = nx, nu, ny, width
        self._fused: dict[tuple, ca.Function] = {}
        self._elimination()
        #: the states move on a manifold: steps in the padded tangent space
        self.tangent = not model.manifold.euclidean_states
        if self.tangent:
            self._tangent_terms(model, [x, y, wy, up, a, xbar, w0, a0], [x, xb, u, om, wq])
            return
        # arrival and measurement terms of one slot; a diagonal R gives diagonal
        # weights (also with missing rows), applied as row scalings
        r0 = W0 @ (x - xbar)
        e = model.manifold.output_difference(y, model.H(x, up, pm))
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
        self.meas = ca.Function("meas", margs, [A0a + gram(Jy), gy, c])
        # the exact Hessian blocks are built on first use (Newton steps, hard problems),
        # from these Functions (picklable, where expressions are not)
        self._meas_parts = ca.Function("meas_parts", margs, [A0a + gram(Jy), A0a, gy, c, ry])
        self.meas_cost = ca.Function("meas_cost", margs, [c])
        # process term between slots, weighted by W_Q (a parameter: tuning is data; a
        # diagonal weight is a row scaling)
        A = om * model.F_x(x, uF, pm) + (1 - om) * eye
        G = om * model.F(x, uF, pm) + (1 - om) * x
        if interval_weights:  # each transition's own weight (a continuous noise)
            M = om * ca.reshape(u[model.nw:], nx, nx) + (1 - om) * eye
            rw = M @ (xb - G)
            Ja, Jb = -M @ A, M
        elif diagonal_Q:
            mv = om * wq[[i * nx + i for i in range(nx)]] + (1 - om)
            rw = mv * (xb - G)
            Ja, Jb = -(mv @ ca.DM.ones(1, nx)) * A, ca.diag(mv)
        else:
            M = om * ca.reshape(wq, nx, nx) + (1 - om) * eye
            rw = M @ (xb - G)
            Ja, Jb = -M @ A, M
        targs = [x, xb, u, om, wq]
        gn_blocks = [gram(Ja), gram(Jb), Ja.T @ Jb]
        rest = [Ja.T @ rw, Jb.T @ rw, ca.sumsqr(rw)]
        self.trans = ca.Function("trans", targs, gn_blocks + rest)
        self._trans_parts = ca.Function("trans_parts", targs, gn_blocks + rest + [rw])
        self.trans_cost = ca.Function("trans_cost", targs, [ca.sumsqr(rw)])
        # a step taken through the dynamics: from the moved state xp of slot k, the next
        # slot is G(xp) plus the defect the linearised step predicts,
        # x_{k+1} + alpha d_{k+1} - G(x_k) - alpha A d_k (see StructuredGaussNewton.solve)
        xp, d, dn, alpha = (ca.SX.sym("xp", nx), ca.SX.sym("d", nx), ca.SX.sym("dn", nx),
                            ca.SX.sym("alpha"))
        Gp = om * model.F(xp, uF, pm) + (1 - om) * xp
        self.roll = ca.Function("roll", [xp, x, d, xb, dn, u, om, alpha],
                                [Gp + (xb + alpha * dn - G - alpha * ca.jtimes(G, x, d))])
    def _elimination(self) -> None:
        """The block elimination's steps: ``fwd``, ``last`` and ``bwd``."""
        nx = self.nx
        Dj = ca.SX.sym("D", nx, nx)
        # one elimination step: with S_{j-1} = L D L^T factored once,
        # V = L^{-1} [E_{j-1}, z~_{j-1}] and Vs = D^{-1} V give
        # E^T S^{-1} E = V_E^T Vs_E and E^T S^{-1} z~ = V_E^T Vs_z; the backward pass
        # needs d_{j-1} = L^{-T} (Vs_z - Vs_E d_j): Vs and L are passed on
        Sp, Ep = ca.SX.sym("S_prev", nx, nx), ca.SX.sym("E_prev", nx, nx)
        zp, zj = ca.SX.sym("z_prev", nx), ca.SX.sym("z", nx)
        L, inv_D = ldl(Sp)
        V = lower_solve(L, ca.horzcat(Ep, zp))
        Vs = ca.diag(ca.vertcat(*inv_D)) @ V
        Lm = ca.SX.zeros(nx, nx)
        for i in range(nx):
            for k in range(i):
                Lm[i, k] = L[i][k]
        self.fwd = ca.Function("fwd", [Sp, zp, Dj, Ep, zj], [
            Dj - sym_product(V[:, :nx], Vs[:, :nx]), zj - V[:, :nx].T @ Vs[:, nx],
            Vs[:, :nx], Vs[:, nx], Lm, ca.vertcat(*inv_D)])
        self.last = ca.Function("last", [Dj, zj], [sym_solve(Dj, zj)])
        dn, Vj, vj = ca.SX.sym("d_next", nx), ca.SX.sym("Vs", nx, nx), ca.SX.sym("vs", nx)
        Lj = ca.SX.sym("L", nx, nx)
        self.bwd = ca.Function("bwd", [dn, Vj, vj, Lj], [lower_transposed_solve(Lj, vj - Vj @ dn)])


    def _tangent_terms(self, model: Model, margs: list, targs: list) -> None:
        r"""The slot terms of a model whose states move on a manifold
        (:mod:`estim._manifold`): the residuals are tangent vectors, :math:`x \ominus
        \bar x`, :math:`y \ominus h(x)` and :math:`x_{k+1} \ominus F(x_k)`, and the
        blocks are their derivatives along :math:`x \oplus \delta` at
        :math:`\delta = 0` (padded to ``nx``: each pad has a unit diagonal and no
        residual, so its step is 0). The Gauss-Newton iteration then moves in the
        tangent space and retracts (:meth:`StructuredGaussNewton._step_to
        <estim.solvers.least_squares.gauss_newton.StructuredGaussNewton._step_to>`)."""
        M, nx, ny = model.manifold, self.nx, self.ny
        pm = ca.DM(model.p)
        x, y, wy, up, a, xbar, w0, _ = margs
        xa, xb, u, om, wq = targs
        dx, db = ca.SX.sym("dx", nx), ca.SX.sym("db", nx)
        self._pad = ca.diag(ca.DM([float(i in M.pads) for i in range(nx)]))

        def moved(v, d):
            return M.retract(v, d[M.slots])

        xr = moved(x, dx)
        r0 = ca.reshape(w0, nx, nx) @ M.padded(M.local(xbar, xr))
        ry = ca.reshape(wy, ny, ny) @ M.output_difference(y, model.H(xr, up, pm))
        J0, Jy = ca.jacobian(r0, dx), ca.jacobian(ry, dx)
        c = a * ca.sumsqr(r0) + ca.sumsqr(ry)
        A0a = a * gram(J0) + self._pad
        gy = a * (J0.T @ r0) + Jy.T @ ry
        self._meas_parts = ca.Function("meas_parts", margs + [dx],
                                       [A0a + gram(Jy), A0a, gy, c, ry])
        at0 = [ca.DM.zeros(nx)]
        self.meas, self.meas_cost = (
            ca.Function(name, margs, ca.substitute(outs, [dx], at0))
            for name, outs in (("meas", [A0a + gram(Jy), gy, c]), ("meas_cost", [c])))
        # the process term: om = 0 chains an unused slot to the next at no cost
        ar, br = moved(xa, dx), moved(xb, db)
        G = om * model.F(ar, u, pm) + (1 - om) * ar
        W = om * ca.reshape(wq, nx, nx) + (1 - om) * ca.DM.eye(nx)
        rw = W @ M.padded(M.local(G, br))
        Ja, Jb = ca.jacobian(rw, dx), ca.jacobian(rw, db)
        outs = [gram(Ja), gram(Jb), Ja.T @ Jb, Ja.T @ rw, Jb.T @ rw, ca.sumsqr(rw)]
        self._trans_parts = ca.Function("trans_parts", targs + [dx, db], outs + [rw])
        at0 = at0 * 2
        self.trans = ca.Function("trans", targs, ca.substitute(outs, [dx, db], at0))
        self.trans_cost = ca.Function("trans_cost", targs,
                                      ca.substitute([outs[-1]], [dx, db], at0))
        # (no roll: a step through the dynamics is taken on vector states only)

    @cached_property
    def meas_newton(self) -> ca.Function:
        """:attr:`meas` with the exact Hessian of the measurement term as well (built on
        first use)."""
        args = self._meas_parts.sx_in()
        gn, A0a, gy, c, ry = self._meas_parts.call(args)
        if self.tangent:  # the Hessian along the retraction, at delta = 0
            H = ca.hessian(0.5 * c, args[-1])[0] + self._pad
            outs = ca.substitute([gn, H, gy, c], [args[-1]], [ca.DM.zeros(self.nx)])
            return ca.Function("meas_newton", args[:-1], outs)
        H = ca.hessian(0.5 * ca.sumsqr(ry), args[0])[0]
        return ca.Function("meas_newton", args, [gn, A0a + H, gy, c])

    @cached_property
    def trans_newton(self) -> ca.Function:
        """:attr:`trans` with the exact Hessian blocks of the process term as well (built
        on first use)."""
        nx, args = self.nx, self._trans_parts.sx_in()
        *blocks, rw = self._trans_parts.call(args)
        at = args[-2:] if self.tangent else args[:2]  # along the retraction, or x itself
        Hw = ca.hessian(0.5 * ca.sumsqr(rw), ca.vertcat(*at))[0]
        outs = blocks[:3] + [Hw[:nx, :nx], Hw[nx:, nx:], Hw[:nx, nx:]] + blocks[3:]
        if self.tangent:
            outs = ca.substitute(outs, at, [ca.DM.zeros(nx)] * 2)
            args = args[:-2]
        return ca.Function("trans_newton", args, outs)

    @cached_property
    def inverse(self) -> ca.Function:
        """A symmetric block's inverse (built on first use: for covariances only)."""
        Dj = ca.SX.sym("D", self.nx, self.nx)
        inv = sym_solve(Dj, ca.SX.eye(self.nx))
        return ca.Function("inverse", [Dj], [0.5 * (inv + inv.T)])

    @cached_property
    def cov_bwd(self) -> ca.Function:
        r"""One step of the covariance recursion (the diagonal blocks of :math:`H^{-1}`;
        built on first use): with :math:`S_j = L D L^\top` and :math:`V_s = D^{-1}
        L^{-1} E_j` from the elimination, :math:`\Sigma_j = S_j^{-1} + G \Sigma_{j+1}
        G^\top`, :math:`G = S_j^{-1} E_j = L^{-\top} V_s`, is :math:`L^{-\top} (D^{-1} +
        V_s \Sigma_{j+1} V_s^\top) L^{-1}`."""
        nx = self.nx
        Vj, Lj = ca.SX.sym("Vs", nx, nx), ca.SX.sym("L", nx, nx)
        Sn, iD = ca.SX.sym("Sigma_next", nx, nx), ca.SX.sym("inv_D", nx)
        K = ca.diag(iD) + Vj @ Sn @ Vj.T
        X = ca.horzcat(*[lower_transposed_solve(Lj, K[:, c]) for c in range(nx)])  # L^{-T} K
        Sig = ca.horzcat(*[lower_transposed_solve(Lj, X[c, :].T) for c in range(nx)])  # L^{-T} X^T
        return ca.Function("cov_bwd", [Sn, Vj, Lj, iD], [0.5 * (Sig + Sig.T)])

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
                D = damp(D, lam)
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
            assert D_gn is not None  # there is at least one chain
            extra = [free, ca.diag(D_gn)]
        ins = carry + [x, xn, y, wy, up, a, u, om, wq, link, xbar, w0, a0] + \
            ([lam] if damped else [])
        if covariance:
            extra += inv_D
        fun = ca.Function("slot", ins, out_carry + per_chain + [g, cost] + extra)
        self._fused[key] = fun
        return fun


def hoisted(f: ca.Function, inputs: list[int]) -> tuple[ca.Function, ca.Function] | None:
    """``f`` split into ``pre``, what depends on the inputs ``inputs`` alone, and ``core``,
    the rest: ``core(*args, pre(*(args[i] for i in inputs)))`` is ``f(*args)``, the same
    operations on the same values (bit-identical).

    A scan over slots whose weights are shared (or whose bookkeeping is constant) then
    computes ``pre`` once per kind of slot instead of once per slot. ``pre``'s output is
    the vector of the values ``core`` reads. None when ``f`` calls other Functions or
    nothing is left to hoist.
    """
    sx = f.sx_in()
    hoist = set(inputs)
    # per work slot: (depends on another input, value in pre, value in core)
    work: dict[int, tuple[bool, ca.SX, ca.SX | None]] = {}
    pre_out: list[ca.SX] = []
    core_in: list[ca.SX] = []
    outs = [[ca.SX(0)] * f.nnz_out(i) for i in range(f.n_out())]

    def read(w: int) -> ca.SX:
        dep, pv, cv = work[w]
        if cv is None:  # a hoisted value read by the core: one of pre's outputs
            cv = ca.SX.sym(f"h{len(core_in)}")
            pre_out.append(pv)
            core_in.append(cv)
            work[w] = (dep, pv, cv)
        return cv

    for k in range(f.n_instructions()):
        op, a, o = f.instruction_id(k), f.instruction_input(k), f.instruction_output(k)
        if op == ca.OP_INPUT:
            v = sx[a[0]].nz[a[1]]
            work[o[0]] = (a[0] not in hoist, v, v)
        elif op == ca.OP_CONST:
            c = ca.SX(f.instruction_constant(k))
            work[o[0]] = (False, c, c)
        elif op == ca.OP_OUTPUT:
            outs[o[0]][o[1]] = read(a[0])
        elif len(a) not in (1, 2) or min(a) < 0 or op == ca.OP_CALL:
            return None  # not a plain unary or binary operation
        elif any(work[w][0] for w in a):  # the core's
            args = [read(w) for w in a]
            v = ca.SX.unary(op, args[0]) if len(a) == 1 else ca.SX.binary(op, *args)
            work[o[0]] = (True, v, v)
        else:  # pre's
            args = [work[w][1] for w in a]
            v = ca.SX.unary(op, args[0]) if len(a) == 1 else ca.SX.binary(op, *args)
            work[o[0]] = (False, v, None)
    if not pre_out:
        return None
    res = [ca.SX(f.sparsity_out(i), ca.vertcat(*nz)) if nz else ca.SX(f.sparsity_out(i))
           for i, nz in enumerate(outs)]
    pre = ca.Function(f"{f.name()}_pre", [sx[i] for i in inputs], [ca.vertcat(*pre_out)])
    core = ca.Function(f"{f.name()}_core", sx + [ca.vertcat(*core_in)], res)
    return pre, core


def _hoisted_scan(step: ca.Function, n_carry: int, N: int, args: list):
    """The scan of ``step`` over ``N`` slots with what depends only on arguments that
    are the same at every slot (the weights) or constant (a full record's bookkeeping,
    DM) computed once per kind of slot instead of once per slot (see :func:`hoisted`):
    ``(function, arguments)`` for :meth:`Slots.scan`, or None when nothing is hoisted."""
    if N < 3:
        return None
    shared, constant = [], []  # indices of the arguments
    for i in range(n_carry, len(args)):
        a, width = args[i], step.size2_in(i)
        if isinstance(a, ca.DM) and width == 1 and a.size2() == N:
            constant.append(i)
        elif a.size2() == width:
            shared.append(i)
    inputs = sorted(shared + constant)
    split = hoisted(step, inputs) if inputs else None
    if split is None:
        return None
    pre, core = split
    values = {i: np.asarray(args[i]) for i in constant}
    kinds: dict[bytes, ca.MX] = {}
    cols = []
    for j in range(N):
        key = b"".join(values[i][:, j].tobytes() for i in constant)
        if key not in kinds:
            kinds[key] = pre(*[ca.DM(values[i][:, j]) if i in values else args[i]
                               for i in inputs])
        cols.append(kinds[key])
    return core, list(args) + [ca.horzcat(*cols)]


def reverse_cols(M, N, width):
    """Reverse the order of the ``N`` column blocks (each ``width`` wide) of an MX."""
    idx = [b * width + c for b in range(N - 1, -1, -1) for c in range(width)]
    return M[:, idx]


class Slots:
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


def forward_scan(st: StageFunctions, slots: Slots, X, q, N, lam, newton, damped, bounds,
                 solve=False, covariance=False):
    """The fused forward scan over the slots (see :meth:`StageFunctions.fused`).

    Returns ``(chains, g, cost, free, diag)``: per chain (Gauss-Newton, then
    Newton's) the last Schur complement and reduced right-hand side, or with
    ``solve`` the direction ``vec(d)`` from the backward scan; the gradient
    ``vec(g)``, the total cost, and with bounds ``vec(free)`` and the
    Gauss-Newton diagonal. With ``covariance`` (Gauss-Newton, no bounds):
    ``vec`` of the diagonal blocks of :math:`H^{-1}`, ``(nx, nx N)``, from the
    backward recursion (see
    :meth:`StructuredGaussNewton.covariances
    <estim.solvers.least_squares.gauss_newton.StructuredGaussNewton.covariances>`).
    """
    nx = st.nx
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
    scan = _hoisted_scan(step, n_carry, N, args)
    if scan is not None:
        step, args = scan
    outs = slots.scan(step, N, n_carry, *args, last_only=True)
    carries, rest = outs[:n_carry], outs[n_carry:]
    if covariance:  # the factors of S_{j-1} in slot j's outputs: the blocks of slot j-1
        Vs, L, inv_D = rest[0], rest[2], rest[-1]
        last = st.inverse(carries[0])
        if N == 1:
            return last
        rev = slots.scan(st.cov_bwd, N - 1, 1, last, reverse_cols(Vs[:, nx:], N - 1, nx),
                         reverse_cols(L[:, nx:], N - 1, nx),
                         reverse_cols(inv_D[:, 1:], N - 1, 1))[0]
        return ca.horzcat(reverse_cols(rev, N - 1, nx), last)
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
        d_rev = slots.scan(st.bwd, N - 1, 1, d_last, reverse_cols(Vs[:, nx:], N - 1, nx),
                           reverse_cols(vs[:, 1:], N - 1, 1),
                           reverse_cols(L[:, nx:], N - 1, nx))[0]
        results.append(ca.vec(ca.horzcat(reverse_cols(d_rev, N - 1, 1), d_last)))
    return results, ca.vec(g), cost, free, diag
