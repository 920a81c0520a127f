r"""Moving horizon estimation: a least-squares trajectory fit over the last N samples."""

from __future__ import annotations

import time
from collections import deque

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction, jitted
from estim._validate import as_bool, as_choice, as_int
from estim.estimators.base import Estimator, StepInfo, consistency_status
from estim.model import Model
from estim.solvers.nlp import (
    LeastSquaresNLP,
    check_solver_options,
    is_diagonal,
    resolve_solver,
    weight_factor,
)
from estim.solvers.robust import as_loss

ARRIVAL_COSTS = ("none", "fixed", "filtering", "smoothing")

#: While the window fills, the real-time iteration's projected Gauss-Newton steps stop
#: below this step (relative to ``1 + max|X|``) or after this many iterations.
RTI_STARTUP_XTOL = 1e-10
RTI_STARTUP_ITERATIONS = 50


class MHE(Estimator):
    r"""Moving horizon estimator with Ipopt, Gauss-Newton SQP or fatrop.

    At time :math:`T` the window holds the last :math:`N` measurements
    :math:`y_s, \dots, y_T` (:math:`s = T - N + 1`) and the estimator solves

    .. math::
        \min_{x_s, \dots, x_T}\;
        \Gamma_s(x_s)
        + \sum_{k=s}^{T-1} \|x_{k+1} - F(x_k, u_k)\|^2_{Q^{-1}}
        + \sum_{k=s}^{T} \|y_k - h(x_k, u_{k-1})\|^2_{R^{-1}}
        \quad \text{s.t.}\; \underline x \le x_k \le \overline x,

    returning :math:`\hat x_T`. The arrival cost is
    :math:`\Gamma_s(x) = \|x - \bar x_s\|^2_{\bar P_s^{-1}}` with, by
    ``arrival_cost``:

    ``"none"``
        :math:`\Gamma_s = 0` (the seeds' ``priorupdate='none'``).
    ``"fixed"``
        :math:`\bar P_s = P_0`, :math:`\bar x_s` the previous window's
        estimate of :math:`x_s`.
    ``"filtering"``
        :math:`\bar x_s = F(\hat x_{s-1}, u_{s-1})` from the MHE's own past
        estimate and :math:`\bar P_s` from the EKF Riccati recursion along
        the MHE estimates (Rao, Rawlings & Mayne 2003). On a linear-Gaussian
        model without active bounds this reproduces the Kalman filter exactly.
    ``"smoothing"``
        :math:`\bar x_s` the previous window's (smoothed) estimate of
        :math:`x_s`, :math:`\bar P_s` from the filtering recursion (the common
        approximation; it counts the measurements shared by two windows twice).

    Before :math:`N` measurements exist the window simply holds all of them
    (full-information estimation with the prior ``x0, P0``); it is never
    padded with copies of old measurements. The NLP is built once for the
    full horizon and re-solved every step, warm-started from the shifted
    previous solution (primal and bound multipliers).

    Parameters
    ----------
    model : Model
    horizon : int
        :math:`N`, the number of measurements in a full window (>= 1).
    Q : float, (nx,) or (nx, nx)
        Process-noise covariance; must be positive definite (weights are
        :math:`Q^{-1}`; give parameters a small variance).
    R, x0, P0 :
        Measurement covariance, initial guess and its covariance. ``P0`` may
        be omitted with ``arrival_cost="none"``.
    arrival_cost : {"none", "fixed", "filtering", "smoothing"}
    lower, upper : optional
        State bounds (default: the model's).
    solver : {"auto", "gauss-newton", "ipopt", "sqp", "fatrop"}
        ``"auto"`` (default): the fastest solver for the problem, which for these
        least-squares problems with box bounds is ``"gauss-newton"``
        (:func:`~estim.solvers.nlp.resolve_solver`); the choice is
        :attr:`solver` and ``info.extra["solver"]``.
        ``"gauss-newton"``: the structure-exploiting projected Newton/Gauss-Newton
        solver of :mod:`estim.solvers.gauss_newton` (block-tridiagonal solve,
        bounds by projection; fastest). ``"ipopt"``: interior point with the
        exact Hessian, the general-purpose path. ``"sqp"``: CasADi's
        ``sqpmethod`` with the Gauss-Newton Hessian :math:`2J^\top J` and the
        ``qrqp`` active-set QP solver (fast when warm-started).
        ``"fatrop"``: the structure-exploiting interior point solver fatrop on
        the stage-wise formulation.
    solver_options : dict, optional
        Passed to the solver (merged over the defaults), e.g.
        ``{"ipopt.tol": 1e-10}`` or ``{"max_iter": 20}``. For
        ``"gauss-newton"``: ``max_iter``, ``xtol``, ``newton`` (exact-Hessian
        steps from the start), ``jit`` (compile to machine code; needs a C
        compiler) and ``mode`` (``"unrolled"``: one expanded graph,
        ``"mapped"``: expanded chunks of slots called in a loop, or
        ``"auto"``: unrolled while the graph stays below about two million
        instructions: 4200 slots of the Lorenz model, 850 of a seven-state one).
    loss : {"squared", "huber", "soft_l1", "cauchy"}
        The measurement cost. ``"squared"``: least squares, as above. The robust
        losses replace :math:`\|y_k - h(x_k)\|^2_{R^{-1}}` by
        :math:`\sum_i \rho(r_{k,i})` over the whitened residual components
        :math:`r_k = W_R (y_k - h(x_k))` (:math:`W_R^\top W_R = R^{-1}`), so a few
        gross outliers no longer pull the estimate; minimised by iteratively
        reweighted least squares, inside the Gauss-Newton iterations (or by
        reweighted solves for the NLP solvers). See :mod:`estim.solvers.robust`.
    f_scale : float, optional
        Where a robust loss leaves the quadratic, in standard deviations (default:
        1.345 for huber and soft_l1, 2.385 for cauchy: 95 % efficiency on Gaussian
        noise), as ``scipy.optimize.least_squares``'s.
    max_lag : int
        How many of the latest steps a late (out-of-sequence) measurement may
        belong to (0: none are kept). See :meth:`insert`.
    rti : bool
        Real-time iteration: once the window is full, one Gauss-Newton step per
        sample from the shifted previous window instead of a converged solve, split
        into :meth:`prepare` (the linearisation and elimination along the window,
        before the measurement arrives) and the feedback in :meth:`step` (the new
        measurement's part, :math:`O(N n_x^2)`; see :mod:`estim.solvers.rti`).
        Bounds by projection of the step. Needs the Gauss-Newton solver, the squared
        loss and ``max_lag=0``. ``info.solve_time`` is the feedback's time (with the
        preparation's when :meth:`step` prepared the window itself, as in
        :func:`~estim.simulate`), ``info.extra["preparation_time"]`` the
        preparation's; ``info.cost`` is the window's cost at the new estimate and the
        status its consistency (``"suspect: ..."`` beyond the chi-square tail, as for the
        converged MHE). A step that is not finite is solved to convergence instead.

    Attributes
    ----------
    info : StepInfo
        ``status``, ``iterations``, ``solve_time``, ``cost``, ``P`` (the
        Laplace covariance of :math:`\hat x_T`, the last block of
        :math:`(J^\top J)^{-1}` at the solution: the Kalman filter's covariance
        on a linear-Gaussian model with the filtering arrival cost; None where
        the window does not determine the state) and ``extra`` with
        ``window`` (the estimated trajectory, (n, nx)), ``arrival_mean`` and
        ``arrival_covariance``; with a robust loss also ``measurement_weights``
        ((n, ny): 1 for a value treated as Gaussian, small for an outlier) and
        ``outliers`` (the number of measured values in the window beyond 6.1
        standard deviations; they are left out of the ``"suspect"`` test unless
        they are half the window's values or more).

    References
    ----------
    C. V. Rao, J. B. Rawlings, D. Q. Mayne, "Constrained state estimation for
    nonlinear discrete-time systems", IEEE TAC 48(2), 2003;
    J. B. Rawlings, D. Q. Mayne, M. M. Diehl, *Model Predictive Control:
    Theory, Computation, and Design*, 2nd ed., 2017, ch. 4.
    """

    name = "mhe"

    def __init__(self, model: Model, *, horizon: int, Q: ArrayLike, R: ArrayLike,
                 x0: ArrayLike, P0: ArrayLike | None = None, arrival_cost: str = "filtering",
                 lower: ArrayLike | None = None, upper: ArrayLike | None = None,
                 solver: str = "auto", solver_options: dict | None = None,
                 loss: str = "squared", f_scale: float | None = None, max_lag: int = 0,
                 rti: bool = False):
        arrival_cost = as_choice(arrival_cost, ARRIVAL_COSTS, "arrival_cost")
        self.rti = as_bool(rti, "rti")
        self._loss = as_loss(loss, f_scale)
        self.max_lag = as_int(max_lag, "max_lag", minimum=0)
        self._requires_P0 = arrival_cost != "none"
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        horizon = as_int(horizon, "horizon", minimum=1)
        if np.linalg.eigvalsh(self.Q)[0] <= 0:
            raise ValueError("Q must be positive definite for MHE (the weights are Q^-1); "
                             "give every state, parameters included, a small variance")
        solver = resolve_solver(solver, solver_options)
        solver_options = check_solver_options(solver, solver_options)
        self.horizon = horizon
        self.arrival_cost = arrival_cost
        self.solver = solver
        self.lower, self.upper = self._bounds(lower, upper)
        self._diagonal = {"Q": is_diagonal(self.Q), "R": is_diagonal(self.R)}
        self._nlp = LeastSquaresNLP(model, self.horizon, self.lower, self.upper, solver,
                                    solver_options or {}, diagonal_Q=self._diagonal["Q"],
                                    diagonal_R=self._diagonal["R"], loss=self._loss)
        self._cov_step = FastFunction(self._build_cov_step())
        if self.rti:
            self._build_rti(solver, solver_options or {})
        self._F = FastFunction(model.F)  # this estimator's own buffers (thread safety)
        self._tuning_changed()
        self._reset()
        self._warn_if_not_smooth()

    def _check_tuning(self, new: dict) -> None:
        if "Q" in new and np.linalg.eigvalsh(new["Q"])[0] <= 0:
            raise ValueError("Q must be positive definite for MHE (the weights are Q^-1)")

    def _tuning_changed(self) -> None:
        if self.rti:
            self._rti_Qinv[:] = np.linalg.inv(self.Q).ravel(order="F")
            self._rti_R[:] = self.R.ravel(order="F")
        self._WQ = weight_factor(self.Q)
        self._WR = weight_factor(self.R)
        if self.P0 is not None:  # the fixed arrival cost uses P0 at every step
            self._W0 = weight_factor(self.P0)

    # ------------------------------------------------------------------ build
    def _build_cov_step(self) -> ca.Function:
        """EKF covariance step at x: update with the measured rows, then predict."""
        m = self.model
        nx, nu, ny = m.nx, m.nu, m.ny
        x, u, up = ca.SX.sym("x", nx), ca.SX.sym("u", m.nw), ca.SX.sym("u_prev", nu)
        mask = ca.SX.sym("mask", ny)
        P = ca.SX.sym("P", nx, nx)
        Q, R = ca.SX.sym("Q", nx, nx), ca.SX.sym("R", ny, ny)  # the tuning is data
        p = ca.DM(m.p)
        D = ca.diag(mask)
        C = D @ m.H_x(x, up, p)
        Rm = D @ R @ D + ca.diag(1 - mask)
        S = C @ P @ C.T + Rm
        K = ca.solve(0.5 * (S + S.T), C @ P).T
        IKC = ca.DM.eye(nx) - K @ C
        Pu = IKC @ P @ IKC.T + K @ Rm @ K.T
        A = m.F_x(x, u, p)
        Pn = A @ Pu @ A.T + Q
        return ca.Function("mhe_cov_step", [x, u, up, mask, ca.vec(P), ca.vec(Q), ca.vec(R)],
                           [ca.vec(0.5 * (Pn + Pn.T)), ca.vec(0.5 * (Pu + Pu.T))])

    def _build_rti(self, solver: str, options: dict) -> None:
        """The real-time iteration's two compiled phases (see :mod:`~estim.solvers.rti`)."""
        from estim.solvers import rti

        if solver != "gauss-newton":
            raise ValueError(f"rti=True takes one Gauss-Newton step per sample: give "
                             f"solver='gauss-newton' (or 'auto'), got {solver!r}")
        if self._loss is not None:
            raise ValueError("rti=True needs loss='squared' (a robust loss reweights "
                             "between iterations)")
        if self.max_lag:
            raise ValueError("rti=True does not keep the states that max_lag needs: "
                             "give max_lag=0")
        m = self.model
        prepare, feedback, cost = rti.build(m, self.horizon)
        if options.get("jit"):
            prepare, feedback, cost = jitted(prepare), jitted(feedback), jitted(cost)
        # the tuning where every phase reads it (set by _tuning_changed), the feedback's
        # inputs where the preparation writes them, the cost's where the preparation reads
        self._rti_Qinv, self._rti_R = np.zeros(m.nx * m.nx), np.zeros(m.ny * m.ny)
        self._rti_prepare = FastFunction(prepare, [None] * 10 + [self._rti_Qinv,
                                                                 self._rti_R, None])
        out, args = self._rti_prepare.out, self._rti_prepare.args
        self._rti_y, self._rti_mask = np.zeros(m.ny), np.zeros(m.ny)
        self._rti_free = np.ones(m.nx)
        self._rti_feedback = FastFunction(feedback, [out[0], out[1], out[2], out[3],
                                                     self._rti_y, self._rti_mask,
                                                     self._rti_R, out[4], out[5],
                                                     self._rti_free])
        self._rti_cost = FastFunction(cost, [None] + args[1:12] + [self._rti_y,
                                                                   self._rti_mask])
        self._bounded = bool(np.isfinite(self.lower).any() or np.isfinite(self.upper).any())

    def prepare(self, u: ArrayLike | None = None) -> None:
        r"""The preparation phase of the real-time iteration (``rti=True``): before the
        next measurement arrives, shift the window, predict its newest state and
        linearise and eliminate the window up to that state, with the input ``u`` that
        :meth:`step` will get with the measurement.

        The following :meth:`step` then only adds the measurement (the feedback
        phase). Calling :meth:`step` without :meth:`prepare` does both. Until the
        window is full (the first ``horizon`` samples) a step solves the window to
        convergence, and :meth:`prepare` does nothing. Calling it again before the
        step does nothing (a different ``u`` then raises a ValueError).
        """
        if not self.rti:
            raise ValueError("prepare() is the preparation phase of the real-time "
                             "iteration: build the MHE with rti=True")
        u = self._check_u(u)
        if self._prepared is not None:  # prepared already: the window has moved
            if not np.array_equal(self._prepared[0], u):
                raise ValueError(f"prepare() was called already with u = "
                                 f"{self._prepared[0]}: step with that input first")
            return
        if self._first or self._n < self.horizon:  # filling: step solves the window
            return
        t0 = time.perf_counter()
        self._shift(u)
        self._linearise(u)
        self._prepared = (u.copy(), time.perf_counter() - t0)

    def _linearise(self, u: np.ndarray, free: np.ndarray | None = None) -> None:
        """Evaluate the preparation Function for the window as it will be once the
        arriving sample (input ``u``) is in: its ``n + 1`` newest slots used, any unused
        ones before them chained to the first used one; ``free`` (N, nx): the variables
        that may move (default all)."""
        m, N = self.model, self.horizon
        nx = m.nx
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
        args[5][:] = 0.0
        args[5][s0] = 1.0
        args[6][:] = 0.0
        args[6][s0:] = 1.0
        args[7][:] = self._xbar
        arrival = self.arrival_cost != "none"
        Pbar = self.P0 if self.arrival_cost == "fixed" else self._Pbar
        args[8][:] = (Pbar if arrival else np.eye(nx)).ravel(order="F")
        args[9][:] = float(arrival)
        args[12][:] = 1.0 if free is None else free.ravel()
        self._rti_free[:] = 1.0 if free is None else free[-1]
        self._rti_prepare.evaluate()

    # ------------------------------------------------------------------ state
    def _reset(self) -> None:
        m, N = self.model, self.horizon
        self._W0 = None if self.P0 is None else weight_factor(self.P0)  # reset may change P0
        self._Y = np.full((N, m.ny), np.nan)      # window measurements, oldest first
        self._U = np.zeros((N, m.nw))             # _U[j]: input from slot j to j+1
        self._Uprev = np.zeros((N, m.nu))         # input held when y of slot j was taken
        self._X = np.tile(self.x0, (N, 1))        # current/previous window solution
        self._n = 0                               # measurements in the window
        self._xbar = self.x0.copy()
        self._Pbar = None if self.P0 is None else self.P0.copy()
        self._history: list[np.ndarray] = []      # MHE estimates of the window's times
        # the last estimate (and covariance) of a step reported "ok" or "inexact":
        # where a failed step re-anchors
        self._trusted = (self.x0.copy(), None if self.P0 is None else self.P0.copy())
        self._nlp.reset()
        # the state before each of the last max_lag steps, with the step's data
        self._past: deque = deque(maxlen=self.max_lag)
        self._prepared = None  # the real-time iteration's preparation: (u, its time)

    # ------------------------------------------------------- late measurements
    def _state(self) -> dict:
        """Everything a step reads and changes (copies of what it changes in place)."""
        nlp = self._nlp
        return {"_Y": self._Y.copy(), "_U": self._U.copy(), "_Uprev": self._Uprev.copy(),
                "_X": self._X.copy(), "_n": self._n, "_xbar": self._xbar.copy(),
                "_Pbar": None if self._Pbar is None else self._Pbar.copy(),
                "_history": list(self._history), "_trusted": self._trusted,
                "_first": self._first, "_k": self._k, "_u_last": self._u_last.copy(),
                "_info": self._info,
                "nlp": (nlp._lam_x, nlp.gn._ridge, nlp.weights)}

    def _restore(self, state: dict) -> None:
        state = dict(state)
        self._nlp._lam_x, self._nlp.gn._ridge, self._nlp.weights = state.pop("nlp")
        for key, value in state.items():
            setattr(self, key, value.copy() if isinstance(value, np.ndarray) else value)
        self._history = list(self._history)

    def insert(self, y: ArrayLike, lag: int) -> np.ndarray:
        """Add a measurement that arrived late and return the new current estimate.

        ``y`` (ny,) was taken at the step ``lag`` steps before the latest one
        (``lag = 0``: the latest step itself); its finite entries replace that
        step's values (NaN entries leave them as they were: typically a sensor
        whose value was missing then). The MHE goes back to its state before that
        step and runs that step and every later one again with their own data, so
        the estimate, ``info`` and everything that follows are exactly those of a run
        that had the measurement on time. Needs ``max_lag > lag``; costs ``lag + 1``
        steps.
        """
        lag = as_int(lag, "lag", minimum=0)
        if lag >= len(self._past):
            kept = len(self._past)
            raise ValueError(f"lag must be below the number of steps kept ({kept}: "
                             f"max_lag={self.max_lag}, {self._k} steps so far), got {lag}")
        y = np.asarray(self._check_y(y), dtype=float)
        entries = list(self._past)
        i = len(entries) - 1 - lag
        state, y_old, u, dt = entries[i]
        merged = np.where(np.isfinite(y), y, y_old)
        self._restore(state)
        self._past = deque(entries[:i], maxlen=self.max_lag)
        x_hat = self.step(merged, u, dt=dt)
        for _, y_k, u_k, dt_k in entries[i + 1:]:
            x_hat = self.step(y_k, u_k, dt=dt_k)
        return x_hat

    # ------------------------------------------------------------------- step
    def _slide(self, u: np.ndarray) -> None:
        """Drop the oldest measurement and move the arrival cost to the next time."""
        y_old, u_old, up_old = self._Y[0].copy(), self._U[0].copy(), self._Uprev[0].copy()
        x_est = self._history[0]  # MHE estimate of the time that leaves the window
        if self.arrival_cost in ("filtering", "smoothing"):
            mask = np.isfinite(y_old).astype(float)
            Pn, _ = self._cov_step(x_est, u_old, up_old, mask, self._Pbar.ravel(order="F"),
                                   self.Q, self.R)
            Pn = Pn.reshape(self.model.nx, self.model.nx, order="F")
            # a non-finite linearisation: the covariance grows as for a random walk
            self._Pbar = Pn.copy() if np.isfinite(Pn).all() else self._Pbar + self.Q
        xbar = self._X[1].copy()  # previous window's estimate of the new first time
        if self.arrival_cost == "filtering":
            pred = self._F(x_est, u_old, self.model.p)[0]
            xbar = pred.copy() if np.isfinite(pred).all() else xbar
        if self.arrival_cost != "none":
            self._xbar = xbar
        for arr in (self._Y, self._U, self._Uprev, self._X):
            arr[:-1] = arr[1:]
        self._history.pop(0)
        self._n -= 1

    def _arrival_weight(self) -> np.ndarray | None:
        """The arrival weight factor :math:`W` with :math:`W^\\top W = \\bar P^{-1}`."""
        if self.arrival_cost == "none":
            return None
        if self.arrival_cost == "fixed":
            return self._W0  # P0 is constant: factored at reset, not every step
        try:
            W = weight_factor(self._Pbar)
        except np.linalg.LinAlgError:  # lost definiteness: back to the prior's spread
            self._Pbar, W = self.P0.copy(), self._W0
        return W

    def _solve(self, robust: bool = False):
        """Solve the current window (``robust``: by Gauss-Newton, see
        :meth:`LeastSquaresNLP.solve`); the solution and the consistency of its cost."""
        nlp, weight = self._nlp, self._arrival_weight()
        sol = nlp.solve(self._X, self._Y, self._U, self._Uprev, self._n, self._xbar,
                        weight, self._WQ, self._WR, self.R, robust=robust)
        measured = nlp.measured(self._Y, self._n)
        dof = measured + (self.model.nx if weight is not None else 0)
        return sol, sol.consistency(dof, measured)

    def _reanchor(self, y, u) -> None:
        """Restart the window after a failed solve: only this measurement, the arrival
        cost on the last trusted estimate with its covariance inflated by ``P0``."""
        N = self.horizon
        x, P = self._anchor(*self._trusted)
        self._Y[:] = np.nan
        self._Y[N - 1] = y
        self._Uprev[N - 1] = u
        self._X[:] = x
        self._n = 1
        self._history.clear()
        if self.arrival_cost != "none":
            self._xbar = x
        if self.arrival_cost in ("filtering", "smoothing"):
            self._Pbar = P

    def _shift(self, u: np.ndarray) -> None:
        """Make room for the arriving sample: the window's data one slot left (the
        arrival cost moved on when the window was full) and the new slot's warm start,
        the prediction of the previous estimate."""
        m, N = self.model, self.horizon
        self._U[N - 1] = self._transition(u)  # from the newest slot to the one arriving
        if self._n == N:
            self._slide(u)
        else:  # window still growing: shift the data one slot left
            for arr in (self._Y, self._U, self._Uprev, self._X):
                arr[:-1] = arr[1:]
        pred = self._F(self._X[N - 2], self._U[N - 2], m.p)[0]
        self._X[N - 1] = pred if np.isfinite(pred).all() else self._X[N - 2]

    def _step(self, y, u, first):
        N = self.horizon
        t0 = time.perf_counter()
        if self.rti and self._prepared is None and (first or self._n < N):
            out = self._startup(y, u, first)  # the window fills: projected Gauss-Newton
            if out is not None:
                return out
            t0 = time.perf_counter()  # not finite: the converged solver
            self._prepared = (u.copy(), 0.0)  # (the data shifted already)
        elif self.rti and not first and (self._prepared is not None or self._n == N):
            inside = self._prepared is None  # this step prepares the window itself
            if inside:
                self.prepare(u)
            elif not np.array_equal(self._prepared[0], u):
                raise ValueError(f"step got u = {u}, but prepare() prepared the window for "
                                 f"u = {self._prepared[0]}: give step the input given to "
                                 f"prepare")
            out = self._feedback(y, u, self._prepared[1], inside)
            if out is not None:
                return out
            t0 = time.perf_counter()  # not finite: the window solved to convergence
        elif self.max_lag:  # the state before this step, for a late measurement
            self._past.append((self._state(), y.copy(), u.copy(), self._dt))
        if not first and self._prepared is None:
            self._shift(u)
        self._prepared = None
        self._Y[N - 1] = y
        self._Uprev[N - 1] = u
        self._n += 1
        self._X[:N - self._n] = self._X[N - self._n]
        sol, check = self._solve()
        failure = None
        # an unusable solve, or an early stop whose cost the data do not support: restart
        # from the last trusted estimate with this measurement
        if not sol.usable or (not sol.success and check != "ok"):
            failure = self._failure(sol.usable, sol.status, sol.cost)
            self._reanchor(y, u)
            sol, check = self._solve(robust=True)
        s0 = N - self._n
        if sol.usable:
            self._X[:] = sol.X
            x_hat = sol.X[-1].copy()
        else:
            x_hat = self._X[-1].copy()  # the anchor itself
        elapsed = time.perf_counter() - t0  # the estimate; its covariance is extra
        P = self._nlp.covariance(self._X) if sol.usable else None
        status = self._solve_status(failure, sol.usable, sol.success, sol.status, check,
                                    "window")
        if failure is None and check == "ok":
            self._trusted = (x_hat.copy(), P)
        self._history.append(x_hat.copy())
        return x_hat.copy(), StepInfo(
            status=status, success=failure is None, iterations=sol.iterations,
            solve_time=elapsed, P=P, cost=sol.cost,
            extra={"window": self._X[s0:].copy(), "arrival_mean": self._xbar.copy(),
                   "arrival_covariance": None if self._Pbar is None else self._Pbar.copy(),
                   "solver_time": sol.solve_time, "solver": self.solver,
                   **({} if self._loss is None or self._nlp.weights is None else
                      {"measurement_weights": self._nlp.weights[s0:].copy(),
                       "outliers": sol.outliers})})

    def _rti_check(self, X: np.ndarray) -> tuple[float, str]:
        """The window's cost at ``X`` (the sum of its squared weighted residuals, the
        newest measurement included) and its consistency: ``"suspect: ..."`` beyond the
        chi-square tail of the measured values (and ``nx`` for an arrival cost), as for
        the converged MHE."""
        cost = self._rti_cost
        cost.args[0][:] = X.ravel()
        value = 2.0 * float(cost.evaluate()[0][0])
        measured = int(self._rti_prepare.args[2].sum() + self._rti_mask.sum())
        dof = measured + (self.model.nx if self.arrival_cost != "none" else 0)
        return value, consistency_status(value, dof, "cost")

    def _startup(self, y: np.ndarray, u: np.ndarray, first: bool):
        """A step while the window fills (``rti=True``): projected Gauss-Newton on the
        window with the preparation and feedback Functions, iterated to convergence.

        Each iteration linearises at ``X``; the variables at a bound whose gradient
        points out of the box are held (their step 0) and the step of the others is
        halved (at most 30 times) until the projected point does not raise the cost.
        Stops when the step is below ``xtol`` relative to ``1 + max|X|``, or after
        ``max_iter`` iterations (then ``"inexact"``); the covariance is the one of the
        window found (its last state's block of the inverse Gauss-Newton matrix). None if
        a step is not finite (the window is then solved by the converged solver)."""
        m, N = self.model, self.horizon
        t0 = time.perf_counter()
        if not first:
            self._shift(u)
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
                trial = np.clip(X + t * dX, self.lower, self.upper)
                cost.args[0][:] = trial.ravel()
                if cost.evaluate()[0][0] <= before:
                    break
                t *= 0.5
            step, X = trial - X, trial
            if not (np.isfinite(X).all() and np.isfinite(P).all()):
                return None
            if np.abs(step).max() <= RTI_STARTUP_XTOL * (1 + np.abs(X).max()):
                break
        converged = iteration < RTI_STARTUP_ITERATIONS
        self._X[:] = X
        self._linearise(u)  # the covariance at the window found
        P = self._rti_feedback.evaluate()[1]
        if not np.isfinite(P).all():
            return None
        cost, check = self._rti_check(X)
        status = self._solve_status(None, True, converged, f"the start-up's Gauss-Newton "
                                    f"steps did not converge in {RTI_STARTUP_ITERATIONS}",
                                    check, "window")
        return self._rti_accept(X, P, y, u, cost, status, converged and check == "ok",
                                iteration, time.perf_counter() - t0, 0.0,
                                "gauss-newton (rti start-up)")

    def _feedback(self, y: np.ndarray, u: np.ndarray, preparation: float, inside: bool):
        """The feedback phase of the real-time iteration: the prepared window with the
        measurement ``y``; None (the window prepared, to be solved) if the step is not
        finite. Its ``solve_time`` is the feedback's time, with the preparation's when
        this step prepared the window itself (``inside``)."""
        N = self.horizon
        t0 = time.perf_counter()
        self._rti_measurement(y)
        dX, P, _ = self._rti_feedback.evaluate()
        X = self._X + dX.reshape(N, -1)
        if self._bounded:
            np.clip(X, self.lower, self.upper, out=X)
        if not (np.isfinite(X).all() and np.isfinite(P).all()):
            return None
        self._prepared = None
        cost, check = self._rti_check(X)
        return self._rti_accept(X, P, y, u, cost, check, check == "ok", 1,
                                time.perf_counter() - t0 + (preparation if inside else 0.0),
                                preparation, "gauss-newton (rti)")

    def _rti_measurement(self, y: np.ndarray) -> None:
        """The newest measurement where the feedback and cost Functions read it."""
        mask = np.isfinite(y)
        self._rti_y[:] = np.where(mask, y, 0.0)
        self._rti_mask[:] = mask

    def _rti_accept(self, X: np.ndarray, P: np.ndarray, y: np.ndarray, u: np.ndarray,
                    cost: float, status: str, trust: bool, iterations: int,
                    solve_time: float, preparation: float, solver: str):
        """Take the window ``X`` found for the arriving sample ``(y, u)``: the window's
        data, the estimate (trusted if ``trust``) and the step's :class:`StepInfo`."""
        m, N = self.model, self.horizon
        self._X[:] = X
        self._Y[N - 1] = y
        self._Uprev[N - 1] = u
        self._n += 1
        x_hat = X[-1].copy()
        P = P.reshape(m.nx, m.nx, order="F").copy()
        if trust:
            self._trusted = (x_hat.copy(), P)
        self._history.append(x_hat.copy())
        return x_hat, StepInfo(
            status=status, success=True, iterations=iterations, solve_time=solve_time, P=P,
            cost=cost,
            extra={"window": self._X[N - self._n:].copy(), "arrival_mean": self._xbar.copy(),
                   "arrival_covariance": None if self._Pbar is None else self._Pbar.copy(),
                   "preparation_time": preparation, "solver": solver})
