r"""The real-time iteration of moving horizon estimation (``MHE(rti=True)``), sample by
sample.

The compiled preparation, feedback and cost Functions of :mod:`estim.solvers.least_squares.rti` take
one Gauss-Newton step per sample on the window of :mod:`estim.estimators.window.mhe_window`:
the preparation (:meth:`RealTimeIteration._prepare`, before the measurement arrives)
shifts the window and linearises and eliminates it up to its newest state, and the
feedback (:meth:`RealTimeIteration._feedback`) adds the measurement, projects the step
on the bounds and reports the window's cost and its consistency. While the window fills
(:meth:`RealTimeIteration._startup`), and when a feedback step is not finite or its cost
is beyond the chi-square tail, the sample's window is solved to convergence by projected
Gauss-Newton steps with the same Functions, and restarted on the last trusted estimate
when that solve is not usable, as the converged MHE restarts
(:meth:`RealTimeIteration._solve_window`); a restart that is not finite either is left
to the converged solver.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np

from estim._fast import FastFunction, jitted
from estim.consistency import consistency_status
from estim.estimators.base import StepInfo
from estim.estimators.window.mhe_window import MovingWindow
from estim.model import Model
from estim.solvers.kalman.continuous import interval_weight
from estim.solvers.least_squares.robust import RobustLoss

#: While the window fills, the real-time iteration's projected Gauss-Newton steps stop
#: below this step (relative to ``1 + max|X|``) or after this many iterations.
RTI_STARTUP_XTOL = 1e-10
RTI_STARTUP_ITERATIONS = 50


class WindowSolve(NamedTuple):
    """A window solved by :meth:`RealTimeIteration._converge`."""

    X: np.ndarray  #: (N, nx) the window found
    P: np.ndarray  #: (nx * nx) its newest state's covariance, column-major
    iterations: int
    converged: bool
    cost: float  #: the window's weighted sum of squares (its chi-square statistic)
    check: str  #: ``"ok"`` or ``"suspect: ..."``


def _moved(est: RealTimeIteration, X: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The window ``X (N, nx)`` moved by the steps ``D``: ``X + D``, on a manifold the
    retraction of each slot by its padded tangent step (the Function the C export
    calls too: :meth:`Manifold.window_moves <estim._manifold.Manifold.window_moves>`)."""
    if est.model.manifold.euclidean_states:
        return X + D
    return est._rti_retract(X.ravel(), D.ravel())[0].reshape(X.shape).copy()


def _delta(est: RealTimeIteration, X_to: np.ndarray, X: np.ndarray) -> np.ndarray:
    """The step from ``X`` to ``X_to``: ``X_to - X``, on a manifold in the tangent space."""
    if est.model.manifold.euclidean_states:
        return X_to - X
    return est._rti_local(X.ravel(), X_to.ravel())[0].copy()


def _arrival_matrix(model: Model, Pbar: np.ndarray | None) -> np.ndarray:
    """The arrival covariance the preparation reads: ``Pbar`` (on a manifold padded to
    ``nx x nx``, a unit diagonal on the pads), the identity without an arrival cost."""
    if Pbar is None:
        return np.eye(model.nx)
    M = model.manifold
    return Pbar if M.euclidean_states else M.padded_matrix(Pbar)


class RealTimeIteration(MovingWindow):
    """The real-time iteration on the window, the base of :class:`~estim.MHE` (used
    when it is built with ``rti=True``; the tuning's buffers ``_rti_Qinv`` and ``_rti_R``
    are written by its ``_tuning_changed``)."""

    rti: bool
    _loss: RobustLoss | None
    _bounded: bool
    _rti_Qinv: np.ndarray
    _rti_R: np.ndarray
    _rti_y: np.ndarray
    _rti_mask: np.ndarray
    _rti_free: np.ndarray
    #: the phases' Functions; on a manifold also its moves (Manifold.window_moves)
    _rti_prepare: FastFunction
    _rti_feedback: FastFunction
    _rti_cost: FastFunction
    _rti_retract: FastFunction
    _rti_local: FastFunction
    #: The preparation of the next step: ``(u, its time)``, or None before it; and the
    #: interval it was prepared for (None: the model's).
    _prepared: tuple[np.ndarray, float] | None
    _prepared_dt: float | None = None
    #: The window's state before the last prepare() (MovingWindow._state), or None.
    _before_prepare: dict | None = None

    def _build_rti(self, solver: str, options: dict) -> None:
        """The real-time iteration's two compiled phases (see
        :mod:`~estim.solvers.least_squares.rti`)."""
        from estim.solvers.least_squares import rti

        if solver != "gauss-newton":
            raise ValueError(f"rti=True takes one Gauss-Newton step per sample: give "
                             f"solver='gauss-newton' (or 'auto'), got {solver!r}")
        if self.horizon < 2:
            raise ValueError("rti=True needs horizon >= 2 (its preparation linearises the "
                             "window's transitions; one sample has none): horizon=1 is the "
                             "converged measurement update, without rti")
        if self._loss is not None:
            raise ValueError("rti=True needs loss='squared' (a robust loss reweights "
                             "between iterations)")
        if self.max_lag:
            raise ValueError("rti=True does not keep the states that max_lag needs: "
                             "give max_lag=0")
        m, N = self.model, self.horizon
        prepare, feedback, cost = rti.build(m, N, interval_weight if self.Qc is not None else None)
        if options.get("jit"):
            prepare, feedback, cost = jitted(prepare), jitted(feedback), jitted(cost)
        # the tuning where every phase reads it (set by _tuning_changed), the feedback's
        # inputs where the preparation writes them, the cost's where the preparation reads
        self._rti_Qinv, self._rti_R = np.zeros(m.nx * m.nx), np.zeros(m.ny * m.ny)
        bound: list[np.ndarray | None] = [*[None] * 10, self._rti_Qinv, self._rti_R, None]
        self._rti_prepare = FastFunction(prepare, bound)
        out, args = self._rti_prepare.out, self._rti_prepare.args
        self._rti_y, self._rti_mask = np.zeros(m.ny), np.zeros(m.ny)
        self._rti_free = np.ones(m.nx)
        self._rti_feedback = FastFunction(feedback, [out[0], out[1], out[2], out[3],
                                                     self._rti_y, self._rti_mask,
                                                     self._rti_R, out[4], out[5],
                                                     self._rti_free])
        bound = [None, *args[1:12], self._rti_y, self._rti_mask]
        self._rti_cost = FastFunction(cost, bound)
        if not m.manifold.euclidean_states:
            self._rti_retract, self._rti_local = map(FastFunction, m.manifold.window_moves(N))
        self._bounded = bool(np.isfinite(self.lower).any() or np.isfinite(self.upper).any())

    def _reset(self) -> None:
        """The window's state (:meth:`MovingWindow._reset`), and nothing prepared."""
        super()._reset()
        self._prepared = self._before_prepare = None

    # ---------------------------------------------------------------- phases
    def _prepare(self, u: np.ndarray) -> tuple[np.ndarray, float]:
        """The preparation of the full window for the arriving sample's input ``u`` (and
        interval ``_dt``): shift the window and linearise it; returns (and keeps)
        ``(u, its time)``."""
        t0 = time.perf_counter()
        self._prepared_dt = self._dt
        self._shift(u)
        self._linearise(u)
        self._prepared = (u.copy(), time.perf_counter() - t0)
        return self._prepared

    def _linearise(self, u: np.ndarray, free: np.ndarray | None = None) -> None:
        """Evaluate the preparation Function for the window as it will be once the
        arriving sample (input ``u``) is in: its ``n + 1`` newest slots used, any unused
        ones before them chained to the first used one; ``free`` (N, nx): the variables
        that may move (default all)."""
        m, N = self.model, self.horizon
        s0 = N - (self._n + 1)  # the first used slot
        mask = np.isfinite(self._Y[:N - 1])
        mask[:s0] = False
        U, Up = self._U[:N - 1].copy(), np.vstack([self._Uprev[:N - 1], u])
        if s0:  # the unused slots evaluate the model at the first used one's inputs
            U[:s0] = U[s0] if s0 < N - 1 else 0.0
            Up[:s0] = Up[s0]
        args = self._rti_prepare.args  # each input flat, column-major
        args[0][:] = self._X.ravel()
        args[1][:] = np.where(mask, self._Y[:N - 1], 0.0).ravel()
        args[2][:] = mask.ravel()
        args[3][:] = U.ravel()
        args[4][:] = Up.ravel()
        args[5][:], args[6][:] = 0.0, 0.0
        args[5][s0], args[6][s0:] = 1.0, 1.0
        args[7][:] = self._xbar
        arrival = self.arrival_cost != "none"
        Pbar = (self.P0 if self.arrival_cost == "fixed" else self._Pbar) if arrival else None
        args[8][:] = _arrival_matrix(m, Pbar).ravel(order="F")
        args[9][:] = float(arrival)
        args[12][:] = 1.0 if free is None else free.ravel()
        self._rti_free[:] = 1.0 if free is None else free[-1]
        self._rti_prepare.evaluate()

    def _rti_step(self, y: np.ndarray, u: np.ndarray, first: bool
                  ) -> tuple[np.ndarray, StepInfo] | None:
        """A step of the real-time iteration: while the window fills, the start-up's
        converged solve; once it is full, the feedback on the prepared window (prepared
        here when :meth:`MHE.prepare <estim.MHE.prepare>` was not called). None if the
        step is not finite: the window, with room for the sample, is then to be solved
        to convergence."""
        self._before_prepare = None  # the step consumes the preparation
        if self._prepared is None and (first or self._n < self.horizon):
            out = self._startup(y, u, first)  # the window fills: projected Gauss-Newton
            if out is None:  # not finite: the converged solver
                self._prepared = (u.copy(), 0.0)  # (the data shifted already)
            return out
        inside = self._prepared is None  # this step prepares the window itself
        prepared = self._prepared
        if prepared is None:
            prepared = self._prepare(u)
        elif not np.array_equal(prepared[0], u):
            raise ValueError(f"step got u = {u}, but prepare() prepared the window for "
                             f"u = {prepared[0]}: give step the input given to prepare")
        elif self._dt is not None and self._dt != self._prepared_dt:
            before = self.model.dt if self._prepared_dt is None else self._prepared_dt
            raise ValueError(f"step got dt = {self._dt:g}, but prepare() prepared the window "
                             f"for dt = {before:g}: give prepare the interval "
                             f"(prepare(u, dt=...))")
        return self._feedback(y, u, prepared[1], inside)

    def _startup(self, y: np.ndarray, u: np.ndarray, first: bool
                 ) -> tuple[np.ndarray, StepInfo] | None:
        """A step while the window fills (``rti=True``): the window, shifted for the
        arriving sample, solved to convergence (:meth:`_solve_window`)."""
        t0 = time.perf_counter()
        if not first:
            self._shift(u)
        return self._solve_window(y, u, t0, 0, "gauss-newton (rti start-up)")

    def _solve_window(self, y: np.ndarray, u: np.ndarray, t0: float, iterations: int,
                      solver: str) -> tuple[np.ndarray, StepInfo] | None:
        """The window with the arriving sample solved to convergence (:meth:`_converge`)
        and taken, as the converged MHE takes its solve: a window that is not finite, or
        whose iterations stop early at a cost the data do not support, is restarted on
        the last trusted estimate with this measurement alone (:meth:`_anchor_window`)
        and solved again, with the status ``"failed: ...; re-anchored ..."``. None if
        that is not finite either (the converged solver then takes the window).
        ``iterations``: Gauss-Newton steps taken before on this sample."""
        out = self._converge(y, u)
        failure = None
        if out is None or (not out.converged and out.check != "ok"):
            failure = ("the window's Gauss-Newton steps are not finite" if out is None else
                       f"the window's Gauss-Newton steps did not converge in "
                       f"{RTI_STARTUP_ITERATIONS} at cost {out.cost:.3g}")
            iterations += 0 if out is None else out.iterations
            self._anchor_window()
            out = self._converge(y, u)
            if out is None:
                return None
        status = self._solve_status(failure, True, out.converged, f"the Gauss-Newton steps "
                                    f"did not converge in {RTI_STARTUP_ITERATIONS}",
                                    out.check, "window")
        return self._rti_accept(out.X, out.P, y, u, out.cost, status,
                                failure is None and out.converged and out.check == "ok",
                                iterations + out.iterations, time.perf_counter() - t0, 0.0,
                                solver)

    def _converge(self, y: np.ndarray, u: np.ndarray) -> WindowSolve | None:
        """The window (its data shifted, the sample ``(y, u)`` arriving) solved by
        projected Gauss-Newton with the preparation and feedback Functions
        (:class:`WindowSolve`), or None if a step is not finite. Each iteration
        linearises at ``X``; the variables at a bound whose gradient points out of the
        box are held (step 0), the others' step halved (at most 30 times) until the
        projected point does not raise the cost. Stops on a step below ``xtol``
        relative to ``1 + max|X|``, or after ``max_iter`` iterations (not converged);
        ``P``: the last state's block of the inverse Gauss-Newton matrix."""
        m, N = self.model, self.horizon
        s0 = N - (self._n + 1)
        self._X[:s0] = self._X[s0]
        self._rti_measurement(y)
        X = self._X.copy()
        ones = np.ones((N, m.nx))
        cost = self._rti_cost
        iteration = 0
        while iteration < RTI_STARTUP_ITERATIONS:
            iteration += 1
            self._X[:] = X
            self._linearise(u)
            dX, P, grad_y = (o.copy() for o in self._rti_feedback.evaluate())
            G = self._rti_prepare.out[6].reshape(N, m.nx).copy()
            G[-1] += grad_y
            held = ((X <= self.lower) & (G > 0)) | ((X >= self.upper) & (G < 0))
            held[:s0] = False
            if held.any():
                self._linearise(u, ones - held)
                dX = self._rti_feedback.evaluate()[0].copy()
            dX = dX.reshape(N, m.nx)
            cost.args[0][:] = X.ravel()
            before = cost.evaluate()[0][0]
            t = 1.0
            for _ in range(31):
                trial = np.clip(_moved(self, X, t * dX), self.lower, self.upper)
                cost.args[0][:] = trial.ravel()
                if cost.evaluate()[0][0] <= before:
                    break
                t *= 0.5
            step, X = _delta(self, trial, X), trial
            if not (np.isfinite(X).all() and np.isfinite(P).all()):
                return None
            if np.abs(step).max() <= RTI_STARTUP_XTOL * (1 + np.abs(X).max()):
                break
        self._X[:] = X
        self._linearise(u)  # the covariance at the window found
        P = self._rti_feedback.evaluate()[1]
        if not np.isfinite(P).all():
            return None
        value, check = self._rti_check(X)
        return WindowSolve(X, P, iteration, iteration < RTI_STARTUP_ITERATIONS, value, check)

    def _feedback(self, y: np.ndarray, u: np.ndarray, preparation: float, inside: bool
                  ) -> tuple[np.ndarray, StepInfo] | None:
        """The feedback phase: the prepared window with the measurement ``y``. A step
        that is not finite or ``"suspect"`` (cost beyond the chi-square tail) is not
        taken: the window is solved to convergence (:meth:`_solve_window`), so that an
        outlier or a lost linearisation does not carry an absurd window on. ``solve_time``
        is the feedback's, with the preparation's if this step prepared (``inside``)."""
        N = self.horizon
        t0 = time.perf_counter()
        self._rti_measurement(y)
        dX, P, _ = self._rti_feedback.evaluate()
        X = _moved(self, self._X, dX.reshape(N, -1))
        if self._bounded:
            np.clip(X, self.lower, self.upper, out=X)
        solver = "gauss-newton (rti)"
        if np.isfinite(X).all() and np.isfinite(P).all():
            cost, check = self._rti_check(X)
            if check == "ok":
                self._prepared = None
                return self._rti_accept(X, P, y, u, cost, check, True, 1,
                                        time.perf_counter() - t0 +
                                        (preparation if inside else 0.0),
                                        preparation, solver)
        out = self._solve_window(y, u, t0 - (preparation if inside else 0.0), 1,
                                 solver + ", the window solved to convergence")
        if out is not None:
            self._prepared = None
        return out

    # ---------------------------------------------------------------- helpers
    def _rti_check(self, X: np.ndarray) -> tuple[float, str]:
        """The window's cost at ``X`` (the sum of its squared weighted residuals, the
        newest measurement included) and its consistency: ``"suspect: ..."`` beyond the
        chi-square tail of the measured values (and ``nx`` for an arrival cost), as for
        the converged MHE."""
        cost = self._rti_cost
        cost.args[0][:] = X.ravel()
        value = 2.0 * float(cost.evaluate()[0][0])
        measured = int(self._rti_prepare.args[2].sum() + self._rti_mask.sum())
        dof = measured + (self.model.ndx if self.arrival_cost != "none" else 0)
        return value, consistency_status(value, dof, "cost")

    def _rti_measurement(self, y: np.ndarray) -> None:
        """The newest measurement where the feedback and cost Functions read it."""
        self._rti_mask[:] = mask = np.isfinite(y)
        self._rti_y[:] = np.where(mask, y, 0.0)

    def _rti_accept(self, X: np.ndarray, P: np.ndarray, y: np.ndarray, u: np.ndarray,
                    cost: float, status: str, trust: bool, iterations: int,
                    solve_time: float, preparation: float, solver: str
                    ) -> tuple[np.ndarray, StepInfo]:
        """Take the window ``X`` found for the arriving sample ``(y, u)``: the window's
        data, the estimate (trusted if ``trust``) and the step's :class:`StepInfo`."""
        m, N = self.model, self.horizon
        self._X[:] = X
        self._Y[N - 1] = y
        self._Uprev[N - 1] = u
        self._n += 1
        x_hat = X[-1].copy()
        P = P.reshape(m.nx, m.nx, order="F").copy()
        if not m.manifold.euclidean_states:  # the tangent block
            P = m.manifold.unpadded_matrix(P)
        if trust:
            self._trusted = (x_hat.copy(), P)
        self._history.append(x_hat.copy())
        return x_hat, StepInfo(
            status=status, success=True, iterations=iterations, solve_time=solve_time, P=P,
            cost=cost,
            extra={"window": self._X[N - self._n:].copy(), "arrival_mean": self._xbar.copy(),
                   "arrival_covariance": None if self._Pbar is None else self._Pbar.copy(),
                   "preparation_time": preparation, "solver": solver})
