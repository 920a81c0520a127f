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
from estim.solvers.least_squares.builders import build_eliminated, build_fatrop, solve_fatrop
from estim.solvers.least_squares.gauss_newton import StructuredGaussNewton, full_record_constants
from estim.solvers.least_squares.options import (
    SOLVERS,
)
from estim.solvers.least_squares.reweighting import Reweighted
from estim.solvers.least_squares.robust import RobustLoss
from estim.solvers.least_squares.solution import Solution
from estim.solvers.weights import measurement_weights

__all__ = ["LeastSquaresNLP"]


class LeastSquaresNLP(Reweighted):
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
    """

    def __init__(self, model: Model, N: int, lower: np.ndarray, upper: np.ndarray,
                 solver: str, options: dict, diagonal_Q: bool = False,
                 diagonal_R: bool = False, full: bool = False, loss: RobustLoss | None = None):
        if solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {solver!r}")
        self.model, self.N, self.solver_name = model, N, solver
        nx, nu, ny = model.nx, model.nu, model.ny
        self.lbx = np.tile(lower, N)
        self.ubx = np.tile(upper, N)
        self.bounded = bool(np.isfinite(self.lbx).any() or np.isfinite(self.ubx).any())
        # parameter layout
        sizes = {"y": N * ny, "wy": N * ny * ny, "u": N * model.nw, "up": N * nu,
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
                                        full=full, **gn_opts)
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
        U = ca.reshape(part["u"], model.nw, N)  # transitions' inputs
        Up = ca.reshape(part["up"], nu, N)
        a: ca.SX | ca.DM = part["a"]
        xbar = part["xbar"]
        W0 = ca.reshape(part["w0"], nx, nx)
        WQd = ca.diag(part["wq"][[i * nx + i for i in range(nx)]]) if diagonal_Q else \
            ca.reshape(part["wq"], nx, nx)
        pm = ca.DM(model.p)
        if self.full:  # every slot active, arrival on the first: constants, not parameters
            a, part["omega"] = full_record_constants(N)
        if solver == "fatrop":
            self._solver, self._fatrop = build_fatrop(model, N, self.lbx, self.ubx, options, p,
                                                      Y, U, Up, part, a, xbar, W0, WQd, pm)
            self.reset()
            return
        self._solver = build_eliminated(model, N, solver, options, p, Y, U, Up, part, a, xbar,
                                        W0, WQd, pm)
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
            p[s["u"]] = U.ravel()
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
        p[s["u"]] = U.ravel()
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
        if self.loss is None:
            return self._solve(X0, p, Y, n, W0 is not None, robust)
        return self._solve_reweighted(X0, p, Y, n, W0 is not None, robust)

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
        P = self.gn.covariance(np.asarray(X, float).ravel(), self._p, self._complete)
        return P if np.isfinite(P).all() else None

    def _shifted(self, lam: np.ndarray) -> np.ndarray:
        """Bound multipliers moved one slot earlier (the window moved one sample)."""
        nx = self.model.nx
        out = np.empty_like(lam)
        out[:-nx] = lam[nx:]
        out[-nx:] = lam[-nx:]
        return out
