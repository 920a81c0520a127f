r"""Moving horizon estimation: a least-squares trajectory fit over the last N samples.

The estimator (:class:`MHE`) holds its construction, tuning and step; the window's
bookkeeping and arrival cost are in :mod:`estim.estimators.window.mhe_window`, the real-time
iteration (``rti=True``) in :mod:`estim.estimators.window.mhe_rti`, and the solvers in
:mod:`estim.solvers`.
"""

from __future__ import annotations

import time
from collections import deque

import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_bool, as_choice, as_int
from estim.estimators.base import StepInfo
from estim.estimators.manifold_steps import unit_bounds
from estim.estimators.window.mhe_rti import (
    RTI_STARTUP_ITERATIONS,
    RTI_STARTUP_XTOL,
    RealTimeIteration,
)
from estim.estimators.window.noise import (
    check_new_q,
    noise_solver,
    noise_weight,
    window_problem,
)
from estim.model import Model
from estim.solvers.kalman.continuous import noise_density
from estim.solvers.least_squares.options import (
    check_solver_options,
    jit_options,
    resolve_solver,
)
from estim.solvers.least_squares.robust import as_loss
from estim.solvers.weights import is_diagonal, weight_factor

__all__ = ["ARRIVAL_COSTS", "MHE", "RTI_STARTUP_ITERATIONS", "RTI_STARTUP_XTOL"]

ARRIVAL_COSTS = ("none", "fixed", "filtering", "smoothing")


class MHE(RealTimeIteration):
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
        :math:`\bar P_s = P_0`, :math:`\bar x_s` the previous window's estimate of :math:`x_s`.
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
        :math:`N`, the number of measurements in a full window (>= 1; with one, the
        window is the measurement update alone: with the filtering arrival cost, the
        iterated EKF run to convergence).
    Q : float, (nx,) or (nx, nx)
        Process-noise covariance: positive definite (weights :math:`Q^{-1}`), or
        singular, noise on some directions only (the dynamics exact in the others: a
        constrained window solved by Ipopt or fatrop, see
        :class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`).
    Qc : (nq, nq) array, optional
        In place of ``Q``: a continuous noise's density, as :class:`~estim.FullInformation`.
    R, x0, P0 :
        Measurement covariance, initial guess and its covariance. ``P0`` may
        be omitted with ``arrival_cost="none"``.
    arrival_cost : {"none", "fixed", "filtering", "smoothing"}
    lower, upper : optional
        State bounds (default: the model's).
    solver : {"auto", "gauss-newton", "ipopt", "sqp", "fatrop"}
        ``"auto"`` (default): the fastest for the problem, ``"gauss-newton"`` for these
        least-squares problems with box bounds (Ipopt for a singular ``Q``;
        :func:`~estim.solvers.least_squares.options.resolve_solver`), also in
        :attr:`solver` and ``info.extra["solver"]``. ``"gauss-newton"``: the
        structure-exploiting projected Gauss-Newton solver of
        :mod:`estim.solvers.least_squares.gauss_newton` (block-tridiagonal, bounds by
        projection; fastest). ``"ipopt"``: interior point, exact Hessian. ``"sqp"``:
        CasADi's ``sqpmethod``, Gauss-Newton Hessian :math:`2J^\top J`, ``qrqp`` QPs.
        ``"fatrop"``: the structure-exploiting interior point solver, stage-wise.
    solver_options : dict, optional
        Passed to the solver (merged over the defaults), e.g. ``{"ipopt.tol": 1e-10}``.
        For ``"gauss-newton"``: ``max_iter``, ``xtol``, ``ftol`` (relative predicted
        decrease, default 1e-13), ``newton`` (exact-Hessian steps from the start),
        ``jit`` (as ``jit=True``) and ``mode`` (``"unrolled"``: one expanded graph,
        ``"mapped"``: expanded chunks of slots called in a loop, ``"auto"``: unrolled
        below about two million instructions: 4200 slots of Lorenz, 850 of 7 states).
    loss : {"squared", "huber", "soft_l1", "cauchy", "student-t"}
        The measurement cost. ``"squared"``: least squares, as above. The robust
        losses replace :math:`\|y_k - h(x_k)\|^2_{R^{-1}}` by
        :math:`\sum_i \rho(r_{k,i})` over the whitened residual components
        :math:`r_k = W_R (y_k - h(x_k))` (:math:`W_R^\top W_R = R^{-1}`), so a few
        gross outliers no longer pull the estimate; minimised by iteratively
        reweighted least squares, inside the Gauss-Newton iterations (or by
        reweighted solves for the NLP solvers). See :mod:`estim.solvers.least_squares.robust`.
    f_scale, dof : float, optional
        Where a robust loss leaves the quadratic, in standard deviations (default 1.345
        for huber and soft_l1, 2.385 for cauchy: 95 % efficiency on Gaussian noise);
        ``loss="student-t"`` takes ``dof`` (above 2): MAP under Student-t noise of scale R.
    max_lag : int
        How many of the latest steps a late (out-of-sequence) measurement may
        belong to (0: none are kept). See :meth:`insert`.
    jit : bool
        Compiled code (a C compiler; built once per machine and cached), as the filters'
        ``jit=True``; the same as ``solver_options={"jit": True}``.
    rti : bool
        Real-time iteration: once the window is full, one Gauss-Newton step per
        sample from the shifted previous window instead of a converged solve, split
        into :meth:`prepare` (the linearisation and elimination along the window,
        before the measurement arrives) and the feedback in :meth:`step` (the new
        measurement's part, :math:`O(N n_x^2)`; see :mod:`estim.solvers.least_squares.rti`).
        Bounds by projection of the step. Needs the Gauss-Newton solver, the squared
        loss, ``max_lag=0`` and a per-transition ``Q``. ``info.solve_time`` is the
        feedback's time (with the preparation's when :meth:`step` prepared the window
        itself), ``info.extra["preparation_time"]`` the preparation's; ``info.cost`` the
        window's cost at the new estimate and the status its consistency, as for the
        converged MHE. A step that is not finite is solved to convergence instead.

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
    _manifold_aware = True  # with the Gauss-Newton solver, not the real-time iteration

    def __init__(self, model: Model, *, horizon: int, R: ArrayLike, Q: ArrayLike | None = None,
                 x0: ArrayLike, P0: ArrayLike | None = None, arrival_cost: str = "filtering",
                 lower: ArrayLike | None = None, upper: ArrayLike | None = None,
                 solver: str = "auto", solver_options: dict | None = None,
                 loss: str = "squared", f_scale: float | None = None, max_lag: int = 0,
                 rti: bool = False, jit: bool = False, Qc: ArrayLike | None = None,
                 dof: float | None = None):
        Q, self.Qc = noise_density(model, Q, Qc)
        arrival_cost = as_choice(arrival_cost, ARRIVAL_COSTS, "arrival_cost")
        self.rti = as_bool(rti, "rti")
        self._loss = as_loss(loss, f_scale, dof)
        self.max_lag = as_int(max_lag, "max_lag", minimum=0)
        self._requires_P0 = arrival_cost != "none"
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.horizon = as_int(horizon, "horizon", minimum=1)
        solver_options, self.jit = jit_options(jit, solver_options)
        solver, self._rank = noise_solver(self.Q, solver, resolve_solver(solver, solver_options),
                                          who="MHE", model=model, loss=self._loss, rti=self.rti,
                                          continuous=self.Qc is not None, x0=self.x0)
        solver_options = check_solver_options(solver, solver_options)
        self.arrival_cost = arrival_cost
        self.solver = solver
        self.lower, self.upper = self._bounds(lower, upper)
        unit_bounds(model, self.lower, self.upper)
        self._diagonal = {"Q": is_diagonal(self.Q), "R": is_diagonal(self.R)}
        self._nlp = window_problem(model, self.horizon, self.lower, self.upper, solver,
                                   solver_options or {}, self._rank, self._diagonal, self._loss,
                                   continuous=self.Qc is not None)
        self._cov_step = FastFunction(self._build_cov_step())
        if self.rti:
            self._build_rti(solver, solver_options or {})
        self._F = FastFunction(model.F)  # this estimator's own buffers (thread safety)
        self._tuning_changed()
        self._reset()
        self._warn_if_not_smooth()

    _check_tuning = check_new_q

    def _tuning_changed(self) -> None:
        if self.rti:  # Q^-1, or a continuous noise's density (weights made from it)
            Qinv = np.linalg.inv(self.Q) if self.Qc is None else self.Q
            M = self.model.manifold
            self._rti_Qinv[:] = (Qinv if M.euclidean_states else
                                 M.padded_matrix(Qinv)).ravel(order="F")
            self._rti_R[:] = self.R.ravel(order="F")
        self._WQ = noise_weight(self, self.Q, self._rank)
        self._WR = weight_factor(self.R)
        if self.P0 is not None:  # the fixed arrival cost uses P0 at every step
            self._W0 = self._weight_factor(self.P0)
        prepared = getattr(self, "_prepared", None)
        before = getattr(self, "_before_prepare", None)
        if self.rti and prepared is not None and before is not None:
            # a window prepared with the old tuning (its arrival cost moved on with it):
            # back to the state before prepare(), and prepared again with the new tuning
            self._restore(before)
            self._dt = self._prepared_dt
            self._prepare(prepared[0])

    def prepare(self, u: ArrayLike | None = None, dt: float | None = None) -> None:
        r"""The preparation phase of the real-time iteration (``rti=True``): before the
        next measurement arrives, shift the window, predict its newest state and
        linearise and eliminate the window up to that state, with the input ``u`` that
        :meth:`step` will get with the measurement.

        The following :meth:`step` then only adds the measurement (the feedback
        phase). Calling :meth:`step` without :meth:`prepare` does both. Until the
        window is full (the first ``horizon`` samples) a step solves the window to
        convergence, and :meth:`prepare` does nothing. Calling it again before the
        step does nothing (a different ``u`` then raises a ValueError). ``dt``: the
        interval to the arriving sample, for a model built with ``variable_dt=True``
        (default the model's); :meth:`step` then takes the same ``dt`` or none, and a
        different one is refused. A :meth:`set_tuning` between the two phases
        linearises the prepared window again with the new tuning.
        """
        if not self.rti:
            raise ValueError("prepare() is the preparation phase of the real-time "
                             "iteration: build the MHE with rti=True")
        u = self._check_u(u)
        self._dt = None if dt is None else self._check_dt(dt)
        if self._prepared is not None:  # prepared already: the window has moved
            if not np.array_equal(self._prepared[0], u):
                raise ValueError(f"prepare() was called already with u = "
                                 f"{self._prepared[0]}: step with that input first")
            return
        if self._first or self._n < self.horizon:  # filling: step solves the window
            return
        self._before_prepare = self._state()  # for a set_tuning before the step
        self._prepare(u)

    # ------------------------------------------------------- late measurements
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
    def _step(self, y: np.ndarray, u: np.ndarray, first: bool
              ) -> tuple[np.ndarray, StepInfo]:
        N = self.horizon
        t0 = time.perf_counter()
        if self.rti:
            out = self._rti_step(y, u, first)
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
                   **({"solver_messages": sol.messages} if sol.messages else {}),
                   **({} if self._loss is None or self._nlp.weights is None else
                      {"measurement_weights": self._nlp.weights[s0:].copy(),
                       "outliers": sol.outliers})})
