r"""Projected Gauss-Newton for the windowed least-squares problem, exploiting its structure.

The cost :math:`f(X) = \|r(X)\|^2` of :mod:`estim.solvers.least_squares.nlp` couples
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
(``mode="mapped"``, :class:`~estim.solvers.least_squares.chunked.Chunked`: memory
proportional to the record, building independent of it). For a linear model one
iteration is exact, and :math:`S_{N-1}^{-1}` is then the covariance of the last state.

A full step that the line search rejects is tried again through the dynamics
(:meth:`StructuredGaussNewton._rolled`): at small process noise the defects
:math:`x_{k+1} - F(x_k)` are weighted so heavily that the linear step raises
the cost (the Maratos effect of a penalty formulation), while the same step
propagated through the model keeps each defect at its linearised prediction.
This is the nonlinear rollout of differential dynamic programming; it makes an
identification at tiny ``Q`` converge like single shooting, and a well-weighted
problem like multiple shooting.

The pieces live in their own modules: the block factorisation and solves in
:mod:`estim.solvers.least_squares.blocks`, the per-slot Functions and scans in
:mod:`estim.solvers.least_squares.stages`, the iteration loop (line search, rollout, Newton switch,
damping, stopping test) in :mod:`estim.solvers.least_squares.globalisation`, the mapped mode in
:mod:`estim.solvers.least_squares.chunked`; :class:`StructuredGaussNewton` builds the graphs and
holds the buffers.

References
----------
D. P. Bertsekas, "Projected Newton methods for optimization problems with
simple constraints", SIAM J. Control Optim. 20(2), 1982;
J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., ch. 10;
P. Deuflhard, *Newton Methods for Nonlinear Problems*, Springer, 2004, ch. 2 and 4;
G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., sec. 4.1 (LDLᵀ).
"""

from __future__ import annotations

import time

import casadi as ca
import numpy as np

from estim._fast import FastFunction, jitted
from estim.model import Model
from estim.solvers.least_squares.chunked import (
    Chunked,
    ChunkedCost,
    ChunkedCovariance,
    ChunkedCovariances,
    ChunkedIteration,
    ChunkedRoll,
)
from estim.solvers.least_squares.globalisation import Globalised
from estim.solvers.least_squares.stages import Slots, StageFunctions, forward_scan

__all__ = ["StructuredGaussNewton", "chunk_slots", "full_record_constants"]

#: ``mode="auto"`` expands the graph while it has at most this many instructions (the
#: slots times the instructions of one slot's forward step: about 4200 slots of the
#: Lorenz model, 850 of the seven-state Silverbox one), and maps beyond. Building takes about 0.25
#: microseconds per instruction (1 s at the limit), the mapped mode's a fixed 0.05-0.2 s;
#: per evaluation the mapped mode pays about a microsecond per chunk call, which matters
#: for small models only (Lorenz: 1.3x the unrolled time at 4000 slots, 0.7x at 10 000;
#: a 7-state model at 4000: 0.7x).
AUTO_UNROLL_INSTRUCTIONS = 2_200_000
#: ``mode="mapped"`` evaluates chunks of :math:`\sqrt{N/5}` slots, at least
#: :data:`MIN_CHUNK_SLOTS` and at most :data:`CHUNK_SLOTS` (with ``jit``: 16, compiled
#: in about two seconds instead of ten, and as fast), in a loop of at most
#: :data:`MAX_CHUNKS` calls (longer chunks for longer records). Building grows with the
#: chunk (a function per task), binding the buffers of the loop (about 25 microseconds
#: a chunk and task) and its overhead per call (a microsecond) with their number, so
#: that their sum is least near :math:`\sqrt{N}`: on the Silverbox (7 states) at 2000
#: samples, chunks of 16-24 slots build and bind in 0.06 s, chunks of 48 in 0.09 s,
#: and all evaluate as fast; at 40 000 samples, 625 chunks of 64 build in 0.12 s and
#: solve as fast as 128 chunks of 313, which take 1.0 s to build.
CHUNK_SLOTS = 64
#: Default relative tolerance of the predicted decrease (``ftol``): stop once the next
#: Gauss-Newton step promises less than this fraction of the cost, rounding level, so
#: that by default the step tolerance ``xtol`` decides (every variable converged to it,
#: also in directions the data determine weakly). ``least_squares`` and MINPACK stop at
#: 1e-8 of the reductions; on a cost weighted by the noise covariances a cost change of
#: ``ftol * f`` is a move of at most ``sqrt(ftol * f)`` standard deviations (1e-3 at
#: ``ftol = 1e-10`` and ten thousand residuals), a looser ``ftol`` saving the last
#: iterations of large-residual problems, where Gauss-Newton converges linearly.
FTOL = 1e-13
MIN_CHUNK_SLOTS = 16
JIT_CHUNK_SLOTS = 16
MAX_CHUNKS = 1024
#: The covariances of every slot (read once per fit) are one expanded graph up to this
#: many slots, and a loop over chunks beyond, whatever the mode: the chunks build in
#: 0.05 s at any length where the expanded graph takes 0.3 s at 1000 slots of the
#: Lorenz model, and evaluate about as fast (1.1 ms against 0.7 ms there).
COVARIANCE_UNROLL_SLOTS = 256


def chunk_slots(n: int) -> int:
    """The mapped mode's chunk length for ``n`` alike slots: about :math:`\\sqrt{n/5}`
    (see :data:`CHUNK_SLOTS`), moved by up to a quarter to the length that leaves the
    fewest slots over (each of which is a call of its own, and the first of them a
    function to build), the nearest such."""
    base = max(min(CHUNK_SLOTS, max(MIN_CHUNK_SLOTS, round((n / 5) ** 0.5))),
               -(-n // MAX_CHUNKS))
    near = range(max(1, base - base // 4), base + base // 4 + 1)
    return min(near, key=lambda L: (n % L, abs(L - base)))


def full_record_constants(N: int) -> tuple[ca.DM, ca.DM]:
    """Window bookkeeping of a problem whose ``N`` slots all hold data: the arrival
    weights ``a`` (on the first slot) and the process-term switches ``omega`` (all
    on), as ``(1, N)`` and ``(1, N - 1)`` constants."""
    return ca.DM([[1.0] + [0.0] * (N - 1)]), ca.DM.ones(1, max(N - 1, 0))


class StructuredGaussNewton(Globalised):
    r"""Compiled Gauss-Newton iteration for the windowed problem.

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
        Parameter layout of :class:`~estim.solvers.least_squares.nlp.LeastSquaresNLP`.
    n_params : int
        Length of the parameter vector.
    max_iter : int
        Gauss-Newton iterations at most.
    xtol : float
        Step tolerance relative to ``1 + max|X|`` (see :meth:`solve`; the
        default is that of ``scipy.optimize.least_squares``).
    ftol : float
        Relative tolerance of the decrease the next Gauss-Newton step predicts
        (see :meth:`solve`; default :data:`FTOL`, rounding level).
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
    interval_weights : bool
        Each transition's parameters ``u`` carry its own process weight after its input
        (``nw + nx**2`` per slot, the weight column-major: a continuous noise's
        :math:`Q_d(\Delta t_j)^{-1/2}`) in place of the shared ``wq``.

    Notes
    -----
    The compiled functions are built on first use (the damped and Newton
    variants are needed only on hard problems, the covariance only when read),
    and all read the same input buffers.
    """

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 slices: dict, n_params: int, max_iter: int = 50, xtol: float = 1e-8,
                 ftol: float = FTOL,
                 newton: bool = False, jit: bool = False, mode: str = "auto",
                 diagonal_Q: bool = False, diagonal_R: bool = False, full: bool = False,
                 interval_weights: bool = False):
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
        self.max_iter, self.xtol, self.ftol = int(max_iter), float(xtol), float(ftol)
        self.newton, self.jit = bool(newton), bool(jit)
        self.full = bool(full)
        self._stages = StageFunctions(model, diagonal_Q, diagonal_R, interval_weights)
        #: the width of a transition's parameters in ``u``
        self.u_width = self._stages.nw
        self._tangent = self._stages.tangent
        if self._tangent:  # the line search's moves, built once
            self._retract, self._local = map(FastFunction, model.manifold.window_moves(N))
        if mode == "auto":  # compiled code: small chunks compile fast and run as fast
            per_slot = self._stages.fused(False, False).n_instructions()
            mode = "mapped" if self.jit or N * per_slot > AUTO_UNROLL_INSTRUCTIONS \
                else "unrolled"
        self.mode = mode
        self._slots = Slots()
        self._slices, self._n_params = slices, n_params
        # input buffers shared by every compiled function
        self._xbuf, self._pbuf, self._lbuf = np.zeros(N * model.nx), np.zeros(n_params), np.zeros(1)
        self._dbuf, self._abuf = np.zeros(N * model.nx), np.zeros(1)  # for the rollout
        self._funs: dict[tuple[str, bool], object] = {}  # FastFunction or a pair
        self._chunked: Chunked | None = None  # the mapped mode's chunk functions
        #: seconds spent building compiled functions (all of them are built on first
        #: use); :meth:`solve` leaves them out of its time and reports them apart
        self.build_seconds = 0.0
        self.last_build = 0.0
        self._ridge = False  # set for good once a block was singular without it
        self._complete = False  # graphs of the current solve

    def _set_parameters(self, p: np.ndarray) -> None:
        """Write the parameters ``p``; the mapped mode's data derived from them follow."""
        self._pbuf[:] = p
        if self._chunked is not None:
            self._chunked.parameters_written()

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
        st, sl, nx, N = self._stages, self._slots, self.model.nx, self.N
        p = ca.MX.sym("p", self._n_params)
        X = ca.MX.sym("X", nx, N)
        lam = ca.MX.sym("lam")
        xv = ca.vec(X)
        q = self._parts(p, N, complete)
        damped, newton = key.endswith("_lam"), key.startswith("newton")
        if key == "cost":
            ins, outs = [xv, p], [self._cost_graph(X, q, N)]
        elif key == "cov":
            S_last = forward_scan(st, sl, X, q, N, lam, False, False, None)[0][0][0]
            ins, outs = [xv, p], [st.inverse(S_last)]
        elif key == "covs":
            ins, outs = [xv, p], [forward_scan(st, sl, X, q, N, lam, False, False, None,
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
            directions, g, cost, free, diag = forward_scan(st, sl, X, q, N, lam, newton, damped,
                                                           bounds, solve=True)
            if bounds is not None:  # fixed variables: a step scaled by the GN diagonal
                scaled = -g / (diag + 1e-300)
                directions = [ca.if_else(1 - free, scaled, d) for d in directions]
            outs = [cost, g] + directions[::-1]  # Newton's first, Gauss-Newton's last
        name = f"gn_{key}" + ("_complete" if complete else "")
        fun = ca.Function(name, ins, outs).expand(name)
        if self.jit and key not in ("cov", "covs"):
            fun = jitted(fun)
        bufs: list[np.ndarray | None] = [self._xbuf, self._pbuf]
        if len(ins) == 3:
            bufs.append(self._lbuf)
        if key == "roll":
            return FastFunction(fun, [self._xbuf, self._pbuf, self._dbuf, self._abuf])
        if key in ("cost", "cov", "covs"):
            return FastFunction(fun, bufs)
        return FastFunction(fun, bufs), FastFunction(fun, bufs)  # two output buffers

    def _build_chunked(self, key: str, complete: bool):
        """The mapped mode's function ``key``: loops over chunks (see :class:`Chunked`)."""
        if self._chunked is None:
            self._chunked = Chunked(self, (lambda n: JIT_CHUNK_SLOTS) if self.jit
                                    else chunk_slots, self.jit)
        ch, nx = self._chunked, self.model.nx
        if key == "cost":
            return ChunkedCost(ch, complete)
        if key == "cov":
            return ChunkedCovariance(ch, complete)
        if key == "covs":
            return ChunkedCovariances(ch, complete)
        if key == "roll":
            return ChunkedRoll(ch)
        bounds = (self.lower[:nx], self.upper[:nx]) if self._bounded else None
        it = ChunkedIteration(ch, key.startswith("newton"), key.endswith("_lam"), bounds,
                               complete)
        return it, it.twin()

    def _parts(self, p, N, complete):
        m = self.model
        nx, nu, ny = m.nx, m.nu, m.ny
        part = {k: p[s] for k, s in self._slices.items()}
        W0 = ca.reshape(part["w0"], nx, nx)
        # complete data: one measurement weight for every slot (passed once, shared)
        WY = part["wr"] if complete else ca.reshape(part["wy"], ny * ny, N)
        q = {"Y": ca.reshape(part["y"], ny, N), "WY": WY, "WQ": part["wq"],
             "U": ca.reshape(part["u"], self.u_width, N), "Up": ca.reshape(part["up"], nu, N),
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

    def cost(self, x: np.ndarray, p: np.ndarray, complete: bool = False) -> float:
        """The cost ``||r(x)||^2`` at ``x`` (flat) for the parameters ``p``."""
        self._xbuf[:] = x
        self._set_parameters(p)
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
        self._set_parameters(p)
        fun = self._function("covs", bool(complete))
        out = fun.evaluate()[0].reshape(self.N, nx, nx).transpose(0, 2, 1)
        return self.model.manifold.unpadded_matrix(out) if self._tangent else out.copy()

    def covariance(self, x: np.ndarray, p: np.ndarray, complete: bool = False) -> np.ndarray:
        """``(J^T J)^{-1}`` block of the last state at ``x`` (the posterior covariance)
        for the parameters ``p`` (``complete`` as in :meth:`solve`)."""
        nx = self.model.nx
        self._xbuf[:] = x
        self._set_parameters(p)
        fun = self._function("cov", bool(complete))
        out = fun.evaluate()[0].reshape(nx, nx, order="F")
        return self.model.manifold.unpadded_matrix(out) if self._tangent else out.copy()

    def _step_to(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        r"""``x`` moved by ``d``; on a manifold the retraction :math:`x \oplus d` of every
        slot by its padded tangent step (see
        :class:`~estim.solvers.least_squares.stages.StageFunctions`)."""
        if not self._tangent:
            return super()._step_to(x, d)
        out = self._retract(x, d)[0].copy()
        return self._project(out) if self._bounded else out

    def _delta(self, xn: np.ndarray, x: np.ndarray) -> np.ndarray:
        r"""The step from ``x`` to ``xn``; on a manifold :math:`x_n \ominus x`, padded."""
        if not self._tangent:
            return xn - x
        M = self.model.manifold
        return M.padded(self._local(x, xn)[0].reshape(self.N, M.ndx)).ravel()
