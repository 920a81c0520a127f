r"""The windowed least-squares estimation NLP shared by MHE and full-information estimation.

Decision variables are the states of ``N`` slots, :math:`X = (x_0, \dots, x_{N-1})`.
The residual vector is

.. math::
    r(X) = \begin{bmatrix}
      a_j W_0 (x_j - \bar x), \; j = 0..N-1 \\
      \omega_j W_Q (x_{j+1} - F(x_j, u_j)) + (1 - \omega_j)(x_{j+1} - x_j),
          \; j = 0..N-2 \\
      W_{y,j} (y_j - h(x_j, u^-_j)), \; j = 0..N-1
    \end{bmatrix}

and the cost :math:`\|r\|^2`. Only the last ``n`` slots hold data
(:math:`s_0 = N - n`): for them :math:`\omega_j = 1`; the unused slots before
them are chained to :math:`x_{s_0}` at no cost (:math:`\omega_j = 0`), so the
optimum of the full-length problem is exactly that of the ``n``-slot problem.
The arrival weight acts on :math:`x_{s_0}` (selected by the one-hot
parameter :math:`a`, one residual block per slot so the Hessian stays
banded); measurement weights :math:`W_{y,j}` carry zero rows for missing
outputs. One NLP thus serves every window length, built once.

**A singular process noise** (:class:`SingularNoiseNLP`): noise on some directions only,
the dynamics exact in the others.

With :math:`Q = G G^\top`, :math:`G = V_r \Lambda_r^{1/2}` (``nx x r``, the eigenvectors
of the :math:`r` positive eigenvalues), a transition is
:math:`x_{j+1} = F(x_j, u_j) + G w_j` with :math:`w_j \sim N(0, I_r)`: the noise has
:math:`r` coordinates, and the state moves exactly by the model in the :math:`n_x - r`
directions without noise. The weights :math:`Q^{-1}` above do not exist; the problem is instead the
multiple-shooting NLP

.. math::
    \min_{x_j, w_j}\; \sum_j a_j \|W_0 (x_j - \bar x)\|^2 + \sum_j \|w_j\|^2
        + \sum_j \|W_{y,j} (y_j - h(x_j, u^-_j))\|^2
    \quad \text{s.t.} \quad
    x_{j+1} = \omega_j \left(F(x_j, u_j) + G w_j\right) + (1 - \omega_j)\, x_j,

the noise variables sized by the noise (:math:`r` per transition), :math:`G` a
parameter (the tuning is data), the window bookkeeping (:math:`a_j`, :math:`\omega_j`)
that of the unconstrained form: the unused slots before the first measured one are
held equal to it. It is solved by Ipopt or fatrop (equality constraints: the
Gauss-Newton solver of the unconstrained form does not apply). On a feasible point its
cost is that of the unconstrained form with the pseudo-inverse weights
:math:`W_Q^\top W_Q = Q^{+}` (what the estimators' consistency test reads).

The Laplace covariances are those of the constrained problem linearised at the optimum:
a Kalman filter over the window from the arrival covariance
:math:`(W_0^\top W_0)^{-1}` with :math:`A_j = \partial F/\partial x`,
:math:`C_j = \partial h/\partial x` at the solution, and the Rauch-Tung-Striebel pass
back (exact on a linear-Gaussian model; without an arrival term the window alone may not
determine the states, and there is no covariance).
"""

from __future__ import annotations

import contextlib
import io
import time

import casadi as ca
import numpy as np

from estim._manifold import NP
from estim.consistency import chi2_limit
from estim.model import Model
from estim.solvers.least_squares.builders import (
    build_eliminated,
    build_fatrop,
    build_singular,
    solve_fatrop,
)
from estim.solvers.least_squares.gauss_newton import StructuredGaussNewton, full_record_constants
from estim.solvers.least_squares.options import (
    SOLVERS,
)
from estim.solvers.least_squares.reweighting import Relinearised, Reweighted, weight_map
from estim.solvers.least_squares.robust import RobustLoss
from estim.solvers.least_squares.solution import Solution
from estim.solvers.weights import measurement_weights, noise_factor

__all__ = ["SINGULAR_SOLVERS", "LeastSquaresNLP", "SingularNoiseNLP"]

#: the solvers of the constrained form of a singular process noise
SINGULAR_SOLVERS = ("ipopt", "fatrop")


class LeastSquaresNLP(Reweighted, Relinearised):
    """Build-once, solve-many windowed estimation problem (see module docstring).

    Parameters
    ----------
    model : Model
    N : int
        Number of slots (window length).
    lower, upper : (nx,) arrays
        State bounds.
    solver : {"ipopt", "sqp", "fatrop"}
    options : dict
        Solver options merged over the defaults.
    diagonal_Q, diagonal_R : bool
        The process and measurement weights are diagonal (cheaper stage
        functions). The weights :math:`W_Q` (:math:`W_Q^\\top W_Q = Q^{-1}`),
        :math:`W_R`, the arrival weight and mean are parameters of every graph,
        given to each :meth:`solve`: the tuning is data.
    full : bool
        Solved only with every slot holding data (``n == N``); the
        Gauss-Newton graph then treats the window bookkeeping as constants.
    loss : RobustLoss, optional
        A robust measurement cost, minimised by reweighted solves (see
        :mod:`estim.solvers.least_squares.robust`); least squares if omitted.
    process_weight : callable, optional
        ``(model, W, x, u) -> M``: each transition's own weight in place of :math:`W_Q`,
        from the ``WQ`` of :meth:`solve` read as ``W`` (a continuous noise; see
        :class:`~estim.solvers.least_squares.reweighting.Relinearised`).
    """

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 solver: str, options: dict, diagonal_Q: bool = False,
                 diagonal_R: bool = False, full: bool = False, loss: RobustLoss | None = None,
                 process_weight=None):
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        self.model, self.N, self.solver_name = model, N, solver
        nx, nu, ny = model.nx, model.nu, model.ny
        self.lbx = np.tile(lower, N)
        self.ubx = np.tile(upper, N)
        self.bounded = bool(np.isfinite(self.lbx).any() or np.isfinite(self.ubx).any())
        # parameter layout
        self._weight_map = weight_map(model, N, process_weight)  # (None: one wq)
        uw = model.nw + (0 if process_weight is None else nx * nx)
        sizes = {"y": N * ny, "wy": N * ny * ny, "u": N * uw, "up": N * nu,
                 "omega": max(N - 1, 0), "a": N, "xbar": nx, "w0": nx * nx, "wq": nx * nx,
                 "wr": ny * ny}
        #: the NLP solvers on a manifold: their variables are tangent steps from chart
        #: centres, the start of each solve (builders.charted)
        self._charts = solver != "gauss-newton" and not model.manifold.euclidean_states
        if self._charts:
            sizes["ref"] = N * nx
            pads = np.zeros(nx, dtype=bool)
            pads[model.manifold.pads] = True
            self._pads = np.tile(pads, N)  # the pads of every slot's step: fixed at 0
        self._slices, start = {}, 0
        for key, size in sizes.items():
            self._slices[key] = slice(start, start + size)
            start += size
        self.np = start
        self._p = np.zeros(self.np)
        # (the estimators check the options by check_solver_options first)
        gn_opts = options if solver == "gauss-newton" else {}
        self.full = bool(full)
        self.gn = StructuredGaussNewton(model, N, self.lbx, self.ubx, self._slices, self.np,
                                        diagonal_Q=diagonal_Q, diagonal_R=diagonal_R,
                                        full=full, interval_weights=uw > model.nw, **gn_opts)
        #: (W_R, its weights tiled over the slots)
        self._wy_complete: tuple[np.ndarray, np.ndarray] | None = None
        self.loss = loss
        self._whitened = None  # the measurement residuals, built on first use
        #: (N, ny): the robust loss's weights of the last solve's measurements
        self.weights: np.ndarray | None = None
        self._complete = False  # the last parameters: every slot holds every output
        if solver == "gauss-newton":  # its graphs are built from the per-slot Functions
            self.reset()
            return
        p = ca.SX.sym("p", self.np)
        part: dict[str, ca.SX | ca.DM] = {k: p[s] for k, s in self._slices.items()}
        Y = ca.reshape(part["y"], ny, N)
        Uw = ca.reshape(part["u"], uw, N)  # transitions' inputs (and weights)
        U, WQd = Uw[:model.nw, :], ca.reshape(part["wq"], nx, nx)
        Up = ca.reshape(part["up"], nu, N)
        a: ca.SX | ca.DM = part["a"]
        xbar = part["xbar"]
        W0 = ca.reshape(part["w0"], nx, nx)
        if diagonal_Q:
            WQd = ca.diag(part["wq"][[i * nx + i for i in range(nx)]])

        def weight(j):  # transition j's: shared, or its own after its input
            return WQd if uw == model.nw else ca.reshape(Uw[model.nw:, j], nx, nx)
        pm = ca.DM(model.p)
        if self.full:  # every slot active, arrival on the first: constants, not parameters
            a, part["omega"] = full_record_constants(N)
        if solver == "fatrop":
            self._solver, self._fatrop = build_fatrop(model, N, self.lbx, self.ubx, options, p,
                                                      Y, U, Up, part, a, xbar, W0, weight, pm)
            self.reset()
            return
        self._solver = build_eliminated(model, N, solver, options, p, Y, U, Up, part, a, xbar,
                                        W0, weight, pm)
        self.reset()

    def _chart_bounds(self, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bounds of the tangent steps from ``centres`` (flat): ``lbx - c``, ``ubx - c``
        on vector states (quaternions and angles have none), 0 on the pads; and the
        start, zero steps."""
        with np.errstate(invalid="ignore"):  # inf - c
            lo, hi = self.lbx - centres, self.ubx - centres
        lo[self._pads] = hi[self._pads] = 0.0
        return lo, hi, np.zeros_like(centres)

    def reset(self) -> None:
        """Forget the warm-start multipliers and the solver's adaptive state."""
        self._lam_x: np.ndarray | None = None
        self._lam_g: np.ndarray | None = None
        self.gn.reset()

    # ------------------------------------------------------------------ solve
    def parameters(self, Y, U, Uprev, n, xbar, W0, WQ, WR, R) -> np.ndarray:
        """Fill the parameter vector for a window with ``n`` measured slots: data,
        arrival mean ``xbar`` and weight ``W0`` (None: no arrival term), the process
        and measurement weight factors ``WQ``, ``WR`` and ``R`` (for the weights of
        partly measured samples)."""
        m, N = self.model, self.N
        nx = m.nx
        p, s = self._p, self._slices
        p[s["wq"]] = WQ.ravel(order="F")
        p[s["wr"]] = WR.ravel(order="F")
        mask = np.isfinite(Y)
        s0 = N - n
        self._complete = False
        if s0 == 0 and mask.all():  # complete data in a full window: the common case
            self._complete = True
            p[s["y"]] = Y.ravel()
            if self._wy_complete is None or not np.array_equal(self._wy_complete[0], WR):
                self._wy_complete = (WR.copy(), np.tile(WR.ravel(order="F"), N))
            p[s["wy"]] = self._wy_complete[1]
            self._set_inputs(p, U)
            p[s["up"]] = Uprev.ravel()
            p[s["omega"]] = 1.0
            p[s["a"]] = 0.0
            p[s["a"].start] = 1.0
            p[s["xbar"]] = xbar
            p[s["w0"]] = 0.0 if W0 is None else W0.ravel(order="F")
            return p
        p[s["y"]] = np.where(mask, Y, 0.0).ravel()          # column-major (ny, N)
        used = mask.copy()
        used[:s0] = False  # the unused slots weigh nothing
        wy = measurement_weights(used, R, WR)
        p[s["wy"]] = wy.transpose(0, 2, 1).ravel()            # each block column-major
        if s0:  # the unused slots evaluate the model at the inputs of the first used one
            U, Uprev = U.copy(), Uprev.copy()  # (stale ones may make it non-finite, and
            U[:s0] = U[s0] if n > 1 else 0.0  # the zero weights of these slots cannot
            Uprev[:s0] = Uprev[s0]             # undo that: 0 * NaN is NaN)
        self._set_inputs(p, U)
        p[s["up"]] = Uprev.ravel()
        omega = np.zeros(max(N - 1, 0))
        omega[s0:] = 1.0
        p[s["omega"]] = omega
        a = np.zeros(N)
        a[s0] = 1.0
        p[s["a"]] = a
        p[s["xbar"]] = xbar
        p[s["w0"]] = (np.zeros((nx, nx)) if W0 is None else W0).ravel(order="F")
        return p

    def solve(self, X0, Y, U, Uprev, n, xbar, W0, WQ, WR, R, robust: bool = False
              ) -> Solution:
        """Solve from the initial guess ``X0 (N, nx)``; never raises on solver failure.

        ``robust``: with the structured Gauss-Newton solver whatever the solver chosen
        (a descent method from any finite start: the estimators' recovery solves).
        With a robust ``loss``, the weighted problems of
        :mod:`estim.solvers.least_squares.robust` are solved until the weights settle; the
        solution's ``weights`` are the final ones.
        """
        if self.full and n != self.N:
            raise ValueError(f"this problem is built for full records (n = {self.N}), got n = {n}")
        p = self.parameters(Y, U, Uprev, n, xbar, W0, WQ, WR, R)
        solve = self._solve if self.loss is None else self._solve_reweighted
        if self._weight_map is None:
            return solve(X0, p, Y, n, W0 is not None, robust)
        return self._relinearised(solve, X0, p, Y, n, W0 is not None, robust)

    def _solve(self, X0, p, Y, n, arrival: bool, robust: bool, same_window: bool = False
               ) -> Solution:
        """One solve for the parameters ``p`` (``same_window``: a re-solve of the
        window of the previous solve: its multipliers are not shifted)."""
        if self.solver_name != "gauss-newton" and not robust:
            x0 = np.clip(np.asarray(X0, float).ravel(), self.lbx, self.ubx)
            if self._charts:  # the charts' centres: the start, on the manifold
                x0 = self.model.manifold.normalise(x0.reshape(self.N, -1), NP).ravel()
                p[self._slices["ref"]] = x0
        if self.solver_name == "fatrop" and not robust:
            # fatrop can stall and never return where the data contradict the start (an
            # outlier in the window, a start in an overflowing region of the model):
            # such windows, whose cost is beyond the chi-square limit of the suspect
            # test, go to the Gauss-Newton solver
            robust = not self.gn.cost(x0, p, self._complete) <= chi2_limit(
                self.degrees_of_freedom(Y, n, arrival))
        if self.solver_name == "gauss-newton" or robust:
            return self._solve_gn(X0, p)
        t0 = time.perf_counter()
        # not started where the model is not finite (the solvers would spend their
        # iterations on it, or crash)
        start = self.gn.cost(x0, p, self._complete)
        if not np.isfinite(start):
            return Solution(np.asarray(X0, float), False,
                            "non-finite cost at the initial guess", 0, start,
                            time.perf_counter() - t0)
        written = io.StringIO()  # CasADi's warnings (e.g. on the multipliers) kept
        try:
            with contextlib.redirect_stderr(written):
                lbx, ubx, z0 = self.lbx, self.ubx, x0
                if self._charts:  # steps from the centres: x = c + z on vector states
                    lbx, ubx, z0 = self._chart_bounds(x0)
                if self.solver_name == "fatrop":
                    sol = solve_fatrop(self._solver, self._fatrop, z0.reshape(self.N, -1), p,
                                       lbx, ubx, self.N, self.model.nx)
                else:
                    args = {"x0": z0, "p": p, "lbx": lbx, "ubx": ubx}
                    if self._lam_x is not None and self.bounded:
                        args["lam_x0"] = (self._lam_x if same_window else
                                          self._shifted(self._lam_x))
                    sol = self._solver(**args)
            stats = self._solver.stats()
        except RuntimeError as exc:  # solver crashed on NaN or similar
            return Solution(np.asarray(X0, float), False,
                            f"error: {str(exc).strip().splitlines()[-1]}"[:200], 0, np.nan,
                            time.perf_counter() - t0, messages=written.getvalue().strip())
        elapsed = time.perf_counter() - t0
        status = str(stats.get("return_status", "unknown"))
        iters = int(stats.get("iter_count", 0))
        z = np.asarray(sol["x"]).ravel()
        X = (z[self._fatrop.xsel] if self.solver_name == "fatrop" else z).reshape(self.N, -1)
        if self._charts:
            M = self.model.manifold
            X = M.retract(x0.reshape(self.N, -1), X[:, M.slots], NP)
        cost = float(sol["f"])
        # sqpmethod stops on a step below min_step_size when Gauss-Newton's linear
        # convergence has reached the stationary point to rounding: a converged solve
        ok = bool(stats.get("success", False)) or status in (
            "Solved_To_Acceptable_Level", "Search_Direction_Becomes_Too_Small")
        ok = ok and np.isfinite(X).all() and np.isfinite(cost)
        usable = ok
        if ok:
            if self.solver_name != "fatrop":
                self._lam_x = np.asarray(sol["lam_x"]).ravel()
            status = "ok"
        elif np.isfinite(X).all():  # an early stop: usable if no worse than the start
            cost = self.gn.cost(X.ravel(), p, self._complete)
            usable = bool(np.isfinite(cost) and not cost > start)
        return Solution(X, ok, status, iters, cost, elapsed, usable,
                        messages=written.getvalue().strip())

    def _solve_gn(self, X0, p, reweight=None) -> Solution:
        """The structured Gauss-Newton solve (see :meth:`StructuredGaussNewton.solve`)."""
        x, ok, status, iters, cost, elapsed = self.gn.solve(X0, p, self._complete, reweight)
        # the iterations only ever decrease the cost: a finite end point is usable
        usable = bool(np.isfinite(cost) and np.isfinite(x).all())
        return Solution(x.reshape(self.N, -1), ok, "ok" if ok else status, iters, cost,
                        elapsed, usable, self.gn.last_build)

    def measured(self, Y: np.ndarray, n: int) -> int:
        """The number of measured values in the last ``n`` slots of ``Y``."""
        return n * self.model.ny if self._complete else int(np.isfinite(Y[self.N - n:]).sum())

    def degrees_of_freedom(self, Y: np.ndarray, n: int, arrival: bool) -> int:
        """Chi-square degrees of freedom of the cost of a window of ``n`` measured slots
        (its measured outputs, and ``ndx`` for an arrival term), for the consistency test
        of :func:`~estim.consistency.consistency_status`."""
        return self.measured(Y, n) + (self.model.ndx if arrival else 0)

    def covariance(self, X: np.ndarray) -> np.ndarray | None:
        """Laplace covariance of the last state, ``[(J^T J)^{-1}]_{N-1,N-1}``, at the
        solution ``X`` for the parameters of the last solve (None if singular)."""
        P = self.covariance_at(np.asarray(X, float).ravel(), self._p, self._complete)
        return P if P is not None and np.isfinite(P).all() else None

    def covariance_at(self, x: np.ndarray, p: np.ndarray, complete: bool
                      ) -> np.ndarray | None:
        """The last slot's Laplace covariance at ``x`` (flat) for the parameters ``p``
        (None where there is none)."""
        return self.gn.covariance(x, p, complete)

    def covariances_at(self, x: np.ndarray, p: np.ndarray, complete: bool
                       ) -> np.ndarray | None:
        """Every slot's Laplace covariance at ``x`` (flat) for the parameters ``p`` (None
        where there is none)."""
        return self.gn.covariances(x, p, complete)

    def _shifted(self, lam: np.ndarray) -> np.ndarray:
        """Bound multipliers moved one slot earlier (the window moved one sample)."""
        nx = self.model.nx
        out = np.empty_like(lam)
        out[:-nx] = lam[nx:]
        out[-nx:] = lam[-nx:]
        return out


class SingularNoiseNLP(LeastSquaresNLP):
    """The windowed problem of :class:`LeastSquaresNLP` with process noise of rank
    ``rank < nx`` (see the module): same parameters and :meth:`solve`, solved as the
    constrained multiple-shooting NLP by ``solver`` (``"ipopt"`` or ``"fatrop"``). The
    weight ``WQ`` given to :meth:`solve` is the pseudo-inverse factor of ``Q``
    (:func:`~estim.solvers.weights.noise_factor`), from which ``G`` is recovered."""

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 solver: str, options: dict, rank: int, diagonal_R: bool = False,
                 full: bool = False):
        if solver not in SINGULAR_SOLVERS:
            raise ValueError(f"solver {solver!r} does not solve the constrained problem of a "
                             f"singular Q; use one of {SINGULAR_SOLVERS}")
        if not model.manifold.euclidean_states:
            raise ValueError("a singular Q on a model with quaternions or angles is not "
                             "supported by the windowed estimators: give every direction a "
                             "variance")
        # the structured Gauss-Newton problem is kept for its cost (on feasible points
        # that of this problem) and its parameter layout
        super().__init__(model, N, lower, upper, "gauss-newton", {}, diagonal_R=diagonal_R,
                         full=full)
        self.solver_name = solver
        self.rank = int(rank)
        nx, r = model.nx, self.rank
        self._g = np.zeros(nx * r)
        self._wq_seen: np.ndarray | None = None
        self._solver, self._layout = build_singular(model, N, solver, options, self._slices,
                                            self.np, r, self.full)
        x = ca.SX.sym("x", nx)
        w = ca.SX.sym("w", model.nw)
        up = ca.SX.sym("up", model.nu)
        pm = ca.DM(model.p)
        #: the transitions of a window, for the start's noise: F(x_j, u_j), j < N - 1
        self._transit = ca.Function("F", [x, w], [model.F(x, w, pm)]).map(max(N - 1, 1))
        self._jac = (ca.Function("A", [x, w], [ca.jacobian(model.F(x, w, pm), x)]).map(N),
                     ca.Function("C", [x, up], [ca.jacobian(model.H(x, up, pm), x)]).map(N))

    def parameters(self, Y, U, Uprev, n, xbar, W0, WQ, WR, R) -> np.ndarray:
        p = super().parameters(Y, U, Uprev, n, xbar, W0, WQ, WR, R)
        if self._wq_seen is None or not np.array_equal(self._wq_seen, WQ):
            G = noise_factor(WQ.T @ WQ, inverse=True)
            if G.shape[1] != self.rank:
                raise ValueError(f"Q has rank {G.shape[1]}, the problem was built for rank "
                                 f"{self.rank}")
            self._g[:] = G.ravel(order="F")
            self._wq_seen = WQ.copy()
        return p

    def _solve(self, X0, p, Y, n, arrival: bool, robust: bool, same_window: bool = False
               ) -> Solution:
        """One solve of the constrained problem (``robust`` does not apply: the start is
        any finite trajectory, the dynamics' gaps closed by the solver)."""
        t0 = time.perf_counter()
        L = self._layout
        x0 = np.clip(np.asarray(X0, float).ravel(), self.lbx, self.ubx)
        start = self.gn.cost(x0, p, self._complete)
        if not np.isfinite(start):
            return Solution(np.asarray(X0, float), False,
                            "non-finite cost at the initial guess", 0, start,
                            time.perf_counter() - t0)
        z0 = np.zeros(L["lbz"].size)
        z0[L["xsel"]] = x0
        z0[L["wsel"]] = self._start_noise(x0, p).ravel()
        lbz, ubz = L["lbz"].copy(), L["ubz"].copy()
        lbz[L["xsel"]], ubz[L["xsel"]] = self.lbx, self.ubx
        written = io.StringIO()
        try:
            with contextlib.redirect_stderr(written):
                sol = self._solver(x0=z0, p=np.concatenate([p, self._g]), lbx=lbz, ubx=ubz,
                                   lbg=0.0, ubg=0.0)
            stats = self._solver.stats()
        except RuntimeError as exc:
            return Solution(np.asarray(X0, float), False,
                            f"error: {str(exc).strip().splitlines()[-1]}"[:200], 0, np.nan,
                            time.perf_counter() - t0, messages=written.getvalue().strip())
        z = np.asarray(sol["x"]).ravel()
        X = z[L["xsel"]].reshape(self.N, -1)
        cost = float(sol["f"])
        status = str(stats.get("return_status", "unknown"))
        ok = bool(stats.get("success", False)) or status == "Solved_To_Acceptable_Level"
        ok = ok and np.isfinite(X).all() and np.isfinite(cost)
        return Solution(X, ok, "ok" if ok else status, int(stats.get("iter_count", 0)),
                        cost, time.perf_counter() - t0, ok,
                        messages=written.getvalue().strip())

    def _start_noise(self, x0: np.ndarray, p: np.ndarray) -> np.ndarray:
        r"""The noise of the start ``x0`` (flat), ``(N - 1, r)``: the least-squares
        :math:`w_j = G^{+} (x_{j+1} - F(x_j, u_j))` on the transitions with data (0 on
        the unused slots). A feasible start (the previous window shifted, its newest
        state predicted) stays feasible: starting the noise at zero instead would open
        every gap the previous solution's noise had closed."""
        m, N, s = self.model, self.N, self._slices
        if N == 1:
            return np.zeros((0, self.rank))
        X = x0.reshape(N, m.nx)
        FX = np.asarray(self._transit(X[:-1].T, p[s["u"]].reshape(N, m.nw)[:-1].T)).T
        G = self._g.reshape(m.nx, self.rank, order="F")
        W = np.linalg.lstsq(G, (X[1:] - FX).T, rcond=None)[0].T
        W[p[s["omega"]] == 0.0] = 0.0
        return np.where(np.isfinite(W), W, 0.0)

    # ------------------------------------------------------------- covariances
    def covariance_at(self, x: np.ndarray, p: np.ndarray, complete: bool
                      ) -> np.ndarray | None:
        P = self.covariances_at(x, p, complete, last_only=True)
        return None if P is None else P[-1]

    def covariances_at(self, x: np.ndarray, p: np.ndarray, complete: bool,
                       last_only: bool = False) -> np.ndarray | None:
        """The Laplace covariances of the slots (see the module), ``(N, nx, nx)``, NaN
        before the first measured slot; None without an arrival term (``last_only``:
        the filter's pass only, the last block exact)."""
        m, N, s = self.model, self.N, self._slices
        nx, ny = m.nx, m.ny
        X = np.asarray(x, float).reshape(N, nx)
        s0 = int(np.argmax(p[s["a"]]))
        W0 = p[s["w0"]].reshape(nx, nx, order="F")
        if not W0.any():
            return None
        G = self._g.reshape(nx, self.rank, order="F")
        Q = G @ G.T
        # the mapped Jacobians, side by side (rows, N * nx): one block per slot
        A = np.asarray(self._jac[0](X.T, p[s["u"]].reshape(N, m.nw).T)).reshape(
            nx, nx, N, order="F").transpose(2, 0, 1)
        C = np.asarray(self._jac[1](X.T, p[s["up"]].reshape(N, m.nu).T)).reshape(
            ny, nx, N, order="F").transpose(2, 0, 1)
        wy = p[s["wy"]].reshape(N, ny, ny).transpose(0, 2, 1)  # each block column-major
        Pf = np.full((N, nx, nx), np.nan)
        Pp = np.full((N, nx, nx), np.nan)
        P = np.linalg.inv(W0.T @ W0)
        for j in range(s0, N):
            if j > s0:
                P = A[j - 1] @ P @ A[j - 1].T + Q
                Pp[j] = P
            M = wy[j] @ C[j]  # whitened output Jacobian (zero rows: not measured)
            PM = P @ M.T
            P = P - PM @ np.linalg.solve(np.eye(ny) + M @ PM, PM.T)
            Pf[j] = P = 0.5 * (P + P.T)
        if last_only:
            return Pf
        Ps = Pf.copy()
        for j in range(N - 2, s0 - 1, -1):
            gain = np.linalg.lstsq(Pp[j + 1], A[j] @ Pf[j], rcond=None)[0].T
            Ps[j] = Pf[j] + gain @ (Ps[j + 1] - Pp[j + 1]) @ gain.T
            Ps[j] = 0.5 * (Ps[j] + Ps[j].T)
        return Ps
