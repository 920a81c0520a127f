r"""The mapped mode of the structured Gauss-Newton solver: a long record in chunks of slots.

An unrolled iteration graph grows with the record; for long records
(:data:`~estim.solvers.least_squares.gauss_newton.AUTO_UNROLL_INSTRUCTIONS`) or with ``jit``, the
solver's functions are instead compiled for one chunk of slots and called on
consecutive slices of the solver's buffers in a Python loop (:class:`Chunked`):
memory proportional to the record, building independent of it, results equal to the
unrolled graph's up to rounding. :class:`ChunkedIteration`, :class:`ChunkedCost`,
:class:`ChunkedCovariance`, :class:`ChunkedCovariances` and :class:`ChunkedRoll` stand
for the unrolled iteration, cost, covariance and rollout functions with the same
``evaluate()``.
"""

from __future__ import annotations

import copy
import itertools
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim._fast import jitted

if TYPE_CHECKING:
    from estim.solvers.least_squares.gauss_newton import StructuredGaussNewton

__all__ = ["Chunked", "ChunkedCost", "ChunkedCovariance", "ChunkedCovariances",
           "ChunkedIteration", "ChunkedRoll", "PREBIND_BYTES"]

#: A chunk function whose work memory over all chunks stays below this many bytes
#: gets one buffer per chunk, its arguments bound once: a call is then about 1
#: microsecond instead of about 12 (binding some twenty arguments each time).
PREBIND_BYTES = 16 * 2**20


def bind(buffer: ca.FunctionBuffer, args: Sequence[np.ndarray], res: Sequence[np.ndarray]
         ) -> None:
    """Point a CasADi ``FunctionBuffer`` at the arrays ``args`` and ``res`` in place (no
    copies; they must stay alive and in place while the buffer is used). CasADi's stub
    asks for a size that its wrapper does not take: it reads it from the memoryview."""
    for i, a in enumerate(args):
        buffer.set_arg(i, a.data)  # type: ignore[call-arg]
    for i, r in enumerate(res):
        buffer.set_res(i, r.data)  # type: ignore[call-arg]


def split(lo: int, hi: int, chunk: int) -> list[tuple[int, int]]:
    """The slots ``lo..hi-1`` as ``(start, stop)`` chunks of ``chunk`` slots, the rest
    (fewer than ``chunk``) one slot each: functions of two lengths, one of them a single
    slot, instead of a third for the rest (which would cost up to a whole chunk to build,
    where a single-slot call costs a microsecond)."""
    full = lo + (hi - lo) // chunk * chunk
    return [(a, a + chunk) for a in range(lo, full, chunk)] + [(a, a + 1)
                                                                for a in range(full, hi)]


def offsets(sizes: Sequence[int]) -> list[int]:
    """Where the parts of ``sizes`` start in one vector packing them, and its length."""
    return [int(v) for v in np.cumsum([0, *sizes])]


def unpack(packed: ca.SX, sparsities: Sequence[ca.Sparsity]) -> list[ca.SX]:
    """The parts of the vector ``packed`` in the (dense) shapes of ``sparsities``,
    column-major, as :func:`offsets` lays them out."""
    parts = ca.vertsplit(packed, offsets([sp.numel() for sp in sparsities]))
    return [ca.reshape(p, sp.size1(), sp.size2()) for p, sp in zip(parts, sparsities,
                                                                    strict=True)]


class Chunked:
    """The iteration, cost, covariance and rollout functions of a long record, evaluated
    as a loop over chunks of slots.

    Each chunk length has one compiled SX function per task (a forward elimination
    chunk, a backward one, a cost one, a rollout one), applied to consecutive slices of
    the buffers: the slices are bound in place (no copies), so memory holds only the
    per-slot data, and building costs the same at any record length. A call is a
    Python loop over the chunks (``N / chunk`` function calls per scan). The results
    equal the unrolled graph's up to rounding.
    """

    def __init__(self, gn: StructuredGaussNewton, chunk_length: Callable[[int], int],
                 jit: bool):
        """``chunk_length(n)``: the chunk length for ``n`` alike slots."""
        self.gn, self.st = gn, gn._stages
        m, N = gn.model, gn.N
        self.nx, self.nu, self.ny, self.nw, self.N = m.nx, m.nu, m.ny, gn.u_width, N
        if gn.full and N > 2:
            # the first and last slots alone (the arrival term, the missing link): the
            # chunks between are alike, one function for all of them
            chunk = chunk_length(N - 2)
            self.chunks = [(0, 1)] + split(1, N - 1, chunk) + [(N - 1, N)]
        else:
            chunk = chunk_length(N)
            self.chunks = split(0, N, chunk)
        # transitions 0..N-2 in chunks, for the backward pass and the rollout
        self.tchunks = split(0, N - 1, chunk)
        self.jit = jit
        self._funs: dict[tuple, ca.Function] = {}
        self._bufs: dict[tuple, tuple] = {}
        self._held: list = []  # what the prebound buffers point at, and the buffers
        nx, ny, nu = self.nx, self.ny, self.nu
        self.xnext = np.zeros(N * nx)
        self.om = np.zeros(N)
        self.link = np.ones(N)
        self.link[-1] = 0.0
        self.a = np.zeros(N)
        # the inputs every slot shares, one vector: wq, xbar, w0 and a0 = W0^T W0
        self._shared_layout = offsets([nx * nx, nx, nx * nx, nx * nx])
        self.shared = np.zeros(self._shared_layout[-1])
        self._shared_parts = [self.shared[a:b]
                              for a, b in itertools.pairwise(self._shared_layout)]
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
        bind(b, (S, z), (dl,))
        self.last_buf = (S, z, dl, ev, b)
        self.parameters_written()

    # ---------------------------------------------------------------- building
    def _compiled(self, key, build):
        """``build()``'s function with dense outputs (the buffers are read as dense
        arrays), compiled with ``jit`` (through the per-machine cache)."""
        if key not in self._funs:
            t0 = time.perf_counter()
            fun = build()
            if not all(fun.sparsity_out(i).is_dense() for i in range(fun.n_out())):
                ins = fun.sx_in()
                fun = ca.Function(fun.name(), ins, [ca.densify(o) for o in fun.call(ins)])
            self._funs[key] = jitted(fun) if self.jit else fun
            self.gn.build_seconds += time.perf_counter() - t0
        return self._funs[key]

    def _buffer(self, fun):
        key = id(fun)
        if key not in self._bufs:
            self._bufs[key] = fun.buffer()
        return self._bufs[key]

    def _kind(self, lo, hi):
        """What distinguishes the chunk functions of slots ``lo:hi`` besides their length:
        for a full record whether the chunk holds the first slot and the last (its window
        bookkeeping is then constant, see :meth:`_sequences`); None for a window."""
        return (lo == 0, hi == self.N) if self.gn.full else None

    def _sequences(self, L, complete, kind):
        """The per-slot symbols of a chunk of ``L`` slots, ``{name: [column of each
        slot]}``, and the inputs among them.

        A full record's window bookkeeping (arrival weight ``a``, ``om``, ``link``) is
        constant, as in the unrolled graph: ``a`` is 1 at the first slot, ``link`` 0 at
        the last, ``om`` 1; they fold away and are no inputs. In a window they are
        data. With ``complete`` every slot has the same output weight ``wy``."""
        sym = ca.SX.sym
        seq = {k: sym(k, n, L) for k, n in self.sizes.items()}
        if complete:
            seq["wy"] = sym("wy", self.ny * self.ny)
        if kind is None:
            inputs = list(seq.values())
        else:
            inputs = [v for k, v in seq.items() if k not in ("a", "om", "link")]
            first, last = kind
            a, link = np.zeros(L), np.ones(L)
            a[0], link[-1] = float(first), float(not last)
            seq.update(a=ca.DM(a).T, om=ca.DM.ones(1, L), link=ca.DM(link).T)
        cols = {k: ca.horzsplit(v) for k, v in seq.items()}
        if complete:
            cols["wy"] = [seq["wy"]] * L
        return cols, inputs

    def _shared_symbols(self):
        """The inputs every slot shares, as one vector (:attr:`shared`): ``wq``,
        ``xbar``, ``w0``, ``a0``."""
        sh = ca.SX.sym("shared", self.shared.size)
        wq, xbar, w0, a0 = ca.vertsplit(sh, self._shared_layout)
        return sh, wq, xbar, w0, a0

    def _forward_chunk(self, step, L, n_carry, complete, damped, kind=None):
        """``L`` slots of the fused forward step
        (:meth:`~estim.solvers.least_squares.stages.StageFunctions.fused`), ``kind`` as
        :meth:`_kind`. The carry in and out is one vector (:func:`offsets`), the
        shared inputs another (:meth:`_shared_symbols`), so that binding a chunk's
        buffer takes few calls."""
        def build():
            sparsities = [step.sparsity_in(i) for i in range(n_carry)]
            packed = ca.SX.sym("carry", sum(sp.numel() for sp in sparsities))
            c = unpack(packed, sparsities)
            seq, inputs = self._sequences(L, complete, kind)
            sh, wq, *rest = self._shared_symbols()
            lam = [ca.SX.sym("lam")] if damped else []
            slots = []
            for x, xn, y, wy, up, a, u, om, link in zip(*seq.values(), strict=True):
                res = step(*c, x, xn, y, wy, up, a, u, om, wq, link, *rest, *lam)
                c, slots = res[:n_carry], slots + [res[n_carry:]]
            outs = [ca.vertcat(*[ca.vec(ca.densify(o)) for o in c])] + \
                [ca.horzcat(*col) for col in zip(*slots, strict=True)]
            return ca.Function(f"fwd_chunk_{L}", [packed] + inputs + [sh] + lam,
                               [ca.densify(o) for o in outs])  # (dense: built once)
        return self._compiled(("fwd", id(step), L, complete, kind), build)

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
        """``L`` steps of the covariance recursion
        (:attr:`~estim.solvers.least_squares.stages.StageFunctions.cov_bwd`), the last slot
        first."""
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

    def _cost_chunk(self, L, complete, kind=None):
        """The cost of ``L`` slots, ``kind`` as :meth:`_kind`."""
        def build():
            seq, inputs = self._sequences(L, complete, kind)
            sh, wq, xbar, w0, a0 = self._shared_symbols()
            total = ca.SX(0)
            for x, xn, y, wy, up, a, u, om, link in zip(*seq.values(), strict=True):
                total += self.st.meas_cost(x, y, wy, up, a, xbar, w0, a0)
                total += link * self.st.trans_cost(x, xn, u, om, wq)
            return ca.Function(f"cost_chunk_{L}", inputs + [sh], [total])
        return self._compiled(("cost", L, complete, kind), build)

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
        bind(b, args, res)
        ev()

    def calls(self, jobs) -> list:
        """One callable per ``(fun, args, res)`` of ``jobs`` (a chunk loop, in order).

        The arrays must stay in place (they are views of the solver's buffers): each
        chunk gets a buffer with its arguments bound once, unless the buffers' work
        memory would exceed :data:`PREBIND_BYTES`; then one buffer per function is
        rebound at every call. The buffers and arrays a call reads are kept alive by
        :attr:`_held` (one list, not some objects per chunk: fewer objects for Python's
        garbage collector to track)."""
        jobs = list(jobs)
        work = sum(8 * fun.sz_w() for fun, _, _ in jobs)
        out: list[Callable[[], None]] = []
        for fun, args, res in jobs:
            if work <= PREBIND_BYTES:
                b, ev = fun.buffer()
                bind(b, args, res)
                out.append(ev)
                self._held.append(b)
                self._held.extend(args)
                self._held.extend(res)
            else:
                out.append(partial(self._call, self._buffer(fun), args, res))
        return out

    def parameters_written(self) -> None:
        """The data derived from the solver's parameters (window bookkeeping, the shared
        vector with the arrival weight's Gram matrix): at construction and whenever the
        solver writes them (:meth:`StructuredGaussNewton._set_parameters
        <estim.solvers.least_squares.gauss_newton.StructuredGaussNewton._set_parameters>`)."""
        gn, nx, v = self.gn, self.nx, self.views
        if not gn.full:  # (a full record's bookkeeping is constant, no input)
            p, sl = gn._pbuf, gn._slices
            self.om[:-1] = p[sl["omega"]]
            self.a[:] = p[sl["a"]]
        W0 = v["w0"].reshape(nx, nx, order="F")
        wq, xbar, w0, a0 = self._shared_parts
        wq[:], xbar[:], w0[:] = v["wq"], v["xbar"], v["w0"]
        a0[:] = (W0.T @ W0).ravel(order="F")

    def prepare(self):
        """The per-call data derived from the point: the shifted states."""
        nx, x = self.nx, self.gn._xbuf
        self.xnext[:-nx] = x[nx:]
        self.xnext[-nx:] = x[-nx:]

    def _slot_args(self, lo, hi, complete):
        """The per-slot inputs of the chunk of slots ``lo:hi`` (see :meth:`_sequences`)."""
        nx, ny, nu = self.nx, self.ny, self.nu
        v = self.views
        wy = v["wr"] if complete else v["wy"][lo * ny * ny:hi * ny * ny]
        x, xn, y, up, u = (self.gn._xbuf[lo * nx:hi * nx], self.xnext[lo * nx:hi * nx],
                           v["y"][lo * ny:hi * ny], v["up"][lo * nu:hi * nu],
                           v["u"][lo * self.nw:hi * self.nw])
        if self.gn.full:  # the bookkeeping is constant
            return [x, xn, y, wy, up, u]
        return [x, xn, y, wy, up, self.a[lo:hi], u, self.om[lo:hi], self.link[lo:hi]]


class ChunkedIteration:
    """An iteration function of the mapped mode: ``evaluate()`` returns ``[cost, g,
    directions...]`` like the compiled graph of :meth:`StructuredGaussNewton._build`."""

    def __init__(self, ch: Chunked, newton, damped, bounds, complete, solve=True,
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
        # one vector each (see Chunked._forward_chunk), and views of the last one's parts
        layout = offsets([a.size for a in init])
        self.carries = [np.concatenate(init)] + [np.zeros(layout[-1]) for _ in range(M)]
        self._last = [self.carries[-1][a:b] for a, b in itertools.pairwise(layout)]
        # per-slot outputs: per chain Vs, vs, L; then g, cost; with bounds free, diag
        shapes = [nx * nx, nx, nx * nx] * self.chains + [nx, 1] + ([nx, nx] if self.bounded
                                                                  else []) + \
            ([nx] * self.chains if covariance else [])  # (the reciprocals of D last)
        self.slot_out = [np.zeros(n * N) for n in shapes]
        self.d = [np.zeros(N * nx) for _ in range(self.chains)]  # (scratch)
        self.out = [np.zeros(1), np.zeros(N * nx)] + [np.zeros(N * nx)
                                                      for _ in range(self.chains)]
        self.lam = np.zeros(1)
        self._shared = self.shared()
        # the chunk loops, "fwd" and "bwd", bound on first use (see Chunked.calls) and
        # shared with the twins, as the scratch they work on is
        self._loops: dict[str, list] = {}

    def twin(self) -> ChunkedIteration:
        """The same function with its own output buffers (the scratch, and with it the
        chunk loops, is shared)."""
        other = copy.copy(self)
        other.out = [np.zeros_like(a) for a in self.out]
        return other

    def shared(self):
        return [self.ch.shared] + ([self.lam] if self.damped else [])

    def forward(self):
        ch = self.ch
        if "fwd" not in self._loops:
            shapes = [len(a) // ch.N for a in self.slot_out]
            self._loops["fwd"] = ch.calls(
                (ch._forward_chunk(self.step, hi - lo, self.n_carry, self.complete,
                                   self.damped, ch._kind(lo, hi)),
                 [self.carries[c]] + ch._slot_args(lo, hi, self.complete) + self._shared,
                 [self.carries[c + 1]] + [a[lo * n:hi * n] for a, n in
                                          zip(self.slot_out, shapes, strict=True)])
                for c, (lo, hi) in enumerate(ch.chunks))
        ch.prepare()
        for call in self._loops["fwd"]:
            call()
        return self._last

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
        if "bwd" not in self._loops:
            self._loops["bwd"] = self._backward_calls()
        for c in range(self.chains):
            S, z = last[4 * c], last[4 * c + 1]
            d = self.d[c]
            ch.last_buf[0][:] = S
            ch.last_buf[1][:] = z
            ch.last_buf[3]()
            d[-nx:] = ch.last_buf[2]
            for call in self._loops["bwd"][c]:
                call()
            if self.bounded:  # fixed variables: a step scaled by the Gauss-Newton diagonal
                free, diag = self.slot_out[-2], self.slot_out[-1]
                d = np.where(free > 0, d, -g / (diag + 1e-300))
            self.out[2 + self.chains - 1 - c][:] = d  # Newton's first, Gauss-Newton's last
        return self.out


class ChunkedCost:
    def __init__(self, ch: Chunked, complete):
        self.ch, self.complete = ch, complete
        self.parts = np.zeros(len(ch.chunks))
        self.out = [np.zeros(1)]
        self._calls: list | None = None

    def evaluate(self):
        ch = self.ch
        if self._calls is None:
            self._calls = ch.calls(
                (ch._cost_chunk(hi - lo, self.complete, ch._kind(lo, hi)),
                 ch._slot_args(lo, hi, self.complete) + [ch.shared], [self.parts[c:c + 1]])
                for c, (lo, hi) in enumerate(ch.chunks))
        ch.prepare()
        for call in self._calls:
            call()
        self.out[0][0] = self.parts.sum()
        return self.out


class ChunkedCovariance:
    def __init__(self, ch: Chunked, complete):
        self.it = ChunkedIteration(ch, False, False, None, complete, solve=False)
        self.out = [np.zeros(ch.nx * ch.nx)]

    def evaluate(self):
        nx = self.it.ch.nx
        S = self.it.forward()[0]
        self.out[0][:] = np.asarray(self.it.ch.st.inverse(S.reshape(nx, nx, order="F"))
                                    ).ravel(order="F")
        return self.out


class ChunkedCovariances:
    """The mapped mode's :meth:`StructuredGaussNewton.covariances`: the forward chunks,
    then the backward recursion in chunks, the last slot first."""

    def __init__(self, ch: Chunked, complete):
        self.it = ChunkedIteration(ch, False, False, None, complete, solve=False,
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
        for call in self._calls:
            call()
        return self.out


class ChunkedRoll:
    def __init__(self, ch: Chunked):
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
        for call in self._calls:
            call()
        return self.out
