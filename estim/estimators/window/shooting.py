r"""Single-shooting optimisation-based observer (Oliva & Carnevale).

Measurements enter a buffer of ``w`` samples taken every ``N_Ts`` steps.
Whenever the full buffer receives a new sample, the (augmented) state at the
start of the window (``direction="forward"``) or at the current time
(``direction="backward"``) is chosen so that the outputs predicted by the
model match the buffer,

.. math::
    J(\hat\xi) = \sum_{i=1}^{w} W_1 \|Y_i - h(\hat\xi_i)\|^2_{R^{-1}}
                 + W_2 \|\dot Y_i - \tfrac{d}{dt} h(\hat\xi_i)\|^2_{R^{-1}},

where :math:`\hat\xi_i` is the propagation of the optimised state to the
i-th buffer time, :math:`\dot Y_i` a numerical derivative of the measured
output and :math:`\frac{d}{dt}h = \frac{\partial h}{\partial x} f(x, u)`
its exact counterpart from the model. Between optimisations the estimate is
propagated open loop, so :meth:`step` returns :math:`\hat x_{k|k}` at every
sample.

This module holds the observer (:class:`ShootingObserver`: construction, the buffer,
the step and the diagnostics of each optimisation) and the runs of its methods
(:class:`WindowSearch`). The problem's Functions and the buffer's data are built by
:mod:`estim.estimators.window.shooting_problem`; the subspace of the directions a window
determines, gradient descent and the identifiability diagnostic are in
:mod:`estim.estimators.window.shooting_search`.

References
----------
F. Oliva, D. Carnevale, "Optimisation based observer", report, 2020;
H. K. Khalil, *Nonlinear Systems*, 3rd ed., 2002 (sensitivity equations).
"""

from __future__ import annotations

import time
from collections import deque

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_choice, as_float, as_int
from estim.consistency import consistency_status
from estim.estimators.base import Estimator, StepInfo
from estim.estimators.window.shooting_problem import (
    balanced_weight,
    build_problem,
    derivative_filter,
    window_data,
)
from estim.estimators.window.shooting_search import (
    SearchCost,
    gradient_descent,
    identifiability,
    subspace,
    undetermined,
)
from estim.model import Model
from estim.solvers.weights import weight_factor

__all__ = ["METHODS", "ShootingObserver", "derivative_filter", "scipy_minimize"]

METHODS = ("bfgs", "lbfgsb", "ipopt", "nelder-mead", "gradient")


def scipy_minimize(fun, x0, **options):
    """:func:`scipy.optimize.minimize`, imported on the first solve rather than with
    estim (scipy.optimize takes a third of a second to import)."""
    from scipy.optimize import minimize

    return minimize(fun, x0, **options)


class WindowSearch(Estimator):
    """The search of a window's optimum by the observer's ``method``, the base of
    :class:`ShootingObserver`: the Gauss-Newton Hessian (:meth:`_hessian`), the method
    run from the start (:meth:`_run_method`: scipy's BFGS, L-BFGS-B or Nelder-Mead, Ipopt,
    or gradient descent) and what its result is worth (:meth:`_minimise`). The
    attributes below are set by the observer."""

    method: str
    max_iter: int
    tol: float
    resolution: float | None
    lower: np.ndarray
    upper: np.ndarray
    _J: FastFunction
    _sens: FastFunction
    _grad_sens: FastFunction | None
    _grad_other: FastFunction
    _ipopt: ca.Function | None
    _start_cost: float | None

    def _hessian(self, start, args) -> np.ndarray | None:
        """Gauss-Newton Hessian of the output term (and prior) at ``start``."""
        nx = self.model.nx
        S = self._sens(start, args[0], args[-1])[0].reshape(-1, nx, order="F")
        with np.errstate(over="ignore", invalid="ignore"):  # not finite: None
            H = 2.0 * S.T @ S
        if self.P0 is not None:
            H += 2.0 * np.linalg.inv(self.P0)
        return H if np.isfinite(H).all() else None

    def _minimise(self, start, args):
        """Run the chosen method; returns ``(x, cost, iterations, ok, status)``.

        ``ok`` with status ``"ok"``: converged; with ``"inexact: ..."``: not converged
        (see :meth:`_run_method`) at a finite point no worse than ``start``, which is
        used; not ``ok`` (status without prefix, ``"failed: "`` is added by the caller):
        nothing usable.
        """
        self._start_cost = None  # set by the methods that evaluate it anyway
        x, cost, iters, converged, message = self._run_method(start, args)
        finite = bool(np.isfinite(x).all() and np.isfinite(cost))
        if finite and converged:
            return x, cost, iters, True, "ok"
        if self._start_cost is None:
            self._start_cost = float(self._J(start, *args)[0][0])
        if finite and not cost > self._start_cost:
            return x, cost, iters, True, f"inexact: {message}"
        if not finite:
            message = f"non-finite cost at the method's point ({message})"
        return x, cost, iters, False, message

    def _run_method(self, start, args):
        """The chosen method from ``start``: ``(x, cost, iterations, converged, message)``.

        ``converged`` only when the method's own convergence test passed (the gradient test
        for BFGS and L-BFGS-B, Ipopt's ``Solve_Succeeded``, the simplex's tolerances) and,
        for the subspace methods, no direction was left out; ``message`` says why not.
        """
        if self.method == "gradient":
            return gradient_descent(self._J, self._grad_sens, self._grad_other, start, args,
                                    self.max_iter)
        gtol = np.sqrt(2.0 * self.tol)
        H = None if self.method == "ipopt" else self._hessian(start, args)  # ipopt: its own
        n = len(start)
        try:
            if self.method == "ipopt":
                pvec = np.concatenate([np.ravel(a, order="F") for a in args])
                sol = self._ipopt(x0=np.clip(start, self.lower, self.upper), p=pvec,
                                  lbx=self.lower, ubx=self.upper)
                st = self._ipopt.stats()
                x = np.asarray(sol["x"]).ravel()
                converged = st["return_status"] == "Solve_Succeeded"
                return x, float(sol["f"]), int(st["iter_count"]), converged, st["return_status"]
            cost = SearchCost(start, self._J, args)
            self._start_cost = cost.J0
            if self.method == "lbfgsb":
                # diagonal Gauss-Newton scaling keeps the bounds as boxes
                diag = np.ones(n) if H is None else np.diag(H)
                T = np.diag(1.0 / np.sqrt(diag + 1e-9 * max(float(diag.max()), 1e-300)))
                lo, up = (self.lower - start) / np.diag(T), (self.upper - start) / np.diag(T)
                res = scipy_minimize(lambda z: cost(z, T), np.zeros(n), jac=True,
                                     method="L-BFGS-B", bounds=list(zip(lo, up, strict=True)),
                                     options={"maxiter": self.max_iter, "gtol": gtol,
                                              "ftol": 0.0})
                # converged: the projected (scaled) gradient passes the gradient test; L-BFGS-B
                # also stops when the cost no longer decreases (ftol=0) or its line search fails
                z = np.clip(res.x, lo, up)
                pg = np.clip(z - res.jac, lo, up) - z
                converged = bool(np.isfinite(pg).all() and np.abs(pg).max() <= gtol)
                why = "converged" if converged else (
                    f"max_iter ({self.max_iter}) reached" if res.status == 1 else
                    f"line search stalled before the gradient test ({str(res.message).strip()})")
                x = np.clip(start + T @ z, self.lower, self.upper)
                return x, float(res.fun), int(res.nit), converged, why
            T = subspace(H, start, cost.g0, self.P0, self.resolution)
            kept = T.shape[1]
            if kept == 0:  # nothing determined to the resolution: keep the start
                return (start, cost.J0, 0, False,
                        f"no direction {undetermined(self.resolution)[4:]} (0 of {n})")
            z0 = np.zeros(kept)
            if self.method == "bfgs":
                res = scipy_minimize(lambda z: cost(z, T), z0, jac=True,
                                     method="BFGS",
                                     options={"maxiter": self.max_iter, "gtol": gtol})
                # scipy's BFGS stops with status 0 only on its gradient test; 1: max_iter,
                # 2: precision loss (the line search found no decrease) before it
                converged = res.status == 0
                why = {1: f"max_iter ({self.max_iter}) reached",
                       2: "line search stalled (precision loss) before the gradient test"
                       }.get(res.status, str(res.message).strip())
            else:
                res = scipy_minimize(lambda z: cost(z, T)[0], z0, method="Nelder-Mead",
                                     options={"maxiter": self.max_iter * n,
                                              "xatol": 1e-3 * gtol, "fatol": self.tol})
                converged = res.status == 0
                why = f"{str(res.message).strip()} (max_iter {self.max_iter} per variable)"
            if kept < n:  # optimal in the subspace at best
                out = (f"{n - kept} of {n} directions left out "
                       f"({undetermined(self.resolution)})")
                why = out if converged else f"{why}; {out}"
                converged = False
            return start + T @ res.x, float(res.fun), int(res.nit), converged, why
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            return start, float("nan"), 0, False, str(exc)[:120]


class ShootingObserver(WindowSearch):
    r"""Optimisation-based observer on a downsampled measurement buffer.

    Parameters
    ----------
    model : Model
        Usually ``model.augment(...)`` so that parameters are estimated.
    window : int
        ``w``, the number of buffered samples (>= 1).
    every : int
        ``N_Ts``, steps between buffered samples (>= 1).
    derivative_weight : float or None
        :math:`W_2/W_1`. ``None`` (default) sets it on the first full buffer
        so that both terms have the same magnitude (report sec. 1.2.1); 0
        removes the derivative term. Requires a continuous model.
    derivative_samples : int
        Samples of the quadratic differentiator (:func:`derivative_filter`).
    method : {"bfgs", "lbfgsb", "ipopt", "nelder-mead", "gradient"}
        ``"bfgs"`` (default): scipy's BFGS (fminunc's analogue) with the AD gradient,
        in Gauss-Newton-whitened coordinates (see ``resolution``);
        ``"lbfgsb"``/``"ipopt"``: with the bounds (fmincon's analogue);
        ``"nelder-mead"``: the simplex method (fminsearch's analogue);
        ``"gradient"``: gradient descent :math:`\xi_0 \leftarrow \xi_0 -
        \alpha\, \partial J/\partial \xi_0` with the gradient from the forward
        sensitivity equations (report eqs. 1.8-1.10) and a backtracking step.
    direction : {"forward", "backward"}
        Optimise the state at the window's start and propagate forward, or
        the current state and propagate backward (the report's Figure 2).
    Q : accepted for interchangeability (unused).
    R : float, (ny,) or (ny, ny)
        Output covariance: the residuals are weighted by :math:`R^{-1}`.
    x0 : (nx,) array
        Initial guess.
    P0 : optional
        If given, a prior :math:`\|\xi_0 - \bar\xi\|^2_{P_0^{-1}}` on the
        optimised state around its propagated previous estimate
        (regularisation; none by default).
    lower, upper : optional
        Bounds for ``lbfgsb``/``ipopt`` (default: the model's).
    max_iter : int
        Iterations per optimisation.
    tol : float
        Smallest significant decrease of the cost. The cost is weighted by
        :math:`R^{-1}`, a :math:`\chi^2` statistic in the noise, so a decrease
        far below 1 is not information; the methods stop when the decrease
        they can still predict is below ``tol`` (in the Gauss-Newton-scaled
        variables the gradient tolerance is :math:`\sqrt{2\,tol}`).
    resolution : float or None
        ``"bfgs"`` and ``"nelder-mead"`` optimise along the eigen-directions of
        the window's Gauss-Newton Hessian (whitened, so the Hessian there is the
        identity). ``None`` (default) keeps every direction the Hessian resolves
        numerically: the method reaches the window's least-squares optimum. A number
        keeps only the directions the window determines to a relative standard error
        below it (a truncated Gauss-Newton subspace, see
        :func:`~estim.estimators.window.shooting_search.subspace`, relative to the magnitudes of
        :func:`~estim.estimators.window.shooting_search.scales`, which do not need a non-zero
        start); the others keep the propagated previous estimate, so windows with little
        information (between bursts, without excitation) do not push the estimate around
        (the report's examples use 0.003 and 0.05). The bounded methods use the full
        space.
    history_length : int or None
        Optimisations kept in :attr:`history` (the oldest are dropped, so memory
        stays flat over long runs); None keeps all.

    Notes
    -----
    Statuses of an optimising step (:mod:`estim.estimators.base`): ``"ok"`` only when
    the method converged (its own test: the gradient test of BFGS and L-BFGS-B,
    Ipopt's ``Solve_Succeeded``, the simplex's tolerances, a vanishing gradient or
    decrease for ``"gradient"``) with no direction left out; ``"inexact: <reason>"``
    when the estimate is usable (finite, no worse than the start) but not converged:
    ``max_iter`` reached, a line search that stalled or lost precision before the
    gradient test, or directions left out because the window does not determine them to the
    resolution (``"k of n directions left out"``; ``"no direction determined to the
    resolution ... (0 of n)"`` when the estimate is kept as it is); ``"failed: ..."``
    when nothing usable came out (a non-finite point or cost, or a cost above the
    start's; the propagated estimate is kept). ``"suspect: ..."``
    is appended when the output cost lies beyond :data:`~estim.estimators.base.SUSPECT_TAIL`.

    Attributes
    ----------
    info : StepInfo
        After an optimisation: ``iterations``, ``cost``, ``status`` and
        ``extra`` with ``optimised=True``, ``singular_values`` and
        ``condition`` of the output sensitivity to relative changes,
        :math:`R^{-1/2}\,\partial (Y_1..Y_w)/\partial \xi_0\,\mathrm{diag}(|\xi_0|)`
        (the identifiability diagnostic: a huge condition number means the
        window carries no information on some direction; the Fisher
        information's condition number is its square), ``derivative_weight``
        and ``window_start``.
    history : collections.deque of dict
        One record per optimisation since the last reset, the last
        ``history_length`` of them: ``k`` (sample), ``condition``, ``cost``,
        ``iterations``, ``solve_time``, ``success``, ``derivative_weight``.
    """

    name = "shooting"
    _requires_P0 = False

    def __init__(self, model: Model, *, window: int, every: int, R: ArrayLike, x0: ArrayLike,
                 Q: ArrayLike | None = None, P0: ArrayLike | None = None,
                 derivative_weight: float | None = None, derivative_samples: int = 5,
                 method: str = "bfgs", direction: str = "forward",
                 lower: ArrayLike | None = None, upper: ArrayLike | None = None,
                 max_iter: int = 100, tol: float = 1e-3, resolution: float | None = None,
                 history_length: int | None = 1000):
        super().__init__(model, Q=0.0 if Q is None else Q, R=R, x0=x0, P0=P0)
        if model.variable_dt:
            raise ValueError("ShootingObserver needs samples at the model's fixed dt (its "
                             "buffer and derivative term are built on that grid); model "
                             f"{model.name} was built with variable_dt=True")
        for name, val, least in (("window", window, 1), ("every", every, 1),
                                 ("derivative_samples", derivative_samples, 3),
                                 ("max_iter", max_iter, 1)):
            as_int(val, name, minimum=least, expected=f"an integer >= {least}")
        as_choice(method, METHODS, "method")
        as_choice(direction, ("forward", "backward"), "direction")
        derivative_weight = as_float(derivative_weight, "derivative_weight", minimum=0.0,
                                     allow_none=True, expected=">= 0 or None")
        tol = as_float(tol, "tol", positive=True)
        resolution = as_float(resolution, "resolution", positive=True, allow_none=True)
        if not model.continuous and derivative_weight != 0:
            if derivative_weight is not None:
                raise ValueError("derivative_weight needs a continuous model (ode=): the "
                                 "output derivative comes from dh/dx f(x, u)")
            derivative_weight = 0.0
        if direction == "backward" and not model.continuous:
            raise ValueError("direction='backward' needs a continuous model (ode=)")
        self.window, self.every = int(window), int(every)
        self.derivative_samples = int(derivative_samples)
        self.method, self.direction = method, direction
        self.max_iter = int(max_iter)
        self.tol, self.resolution = tol, resolution
        self.history_length = None if history_length is None else \
            as_int(history_length, "history_length", minimum=1)
        self.lower, self.upper = self._bounds(lower, upper)
        self._fixed_w2 = derivative_weight
        self._tuning_changed()
        self._span = (self.window - 1) * self.every  # steps from first to last sample
        self._F = FastFunction(model.F)  # this estimator's own buffers (thread safety)
        self._build()
        self._reset()
        self._warn_if_not_smooth()

    def _tuning_changed(self) -> None:
        """The output weights of the windows (``R`` is data: the graphs take them per
        window)."""
        self._WR = weight_factor(self.R)  # W^T W = R^-1

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        """Cost, gradient and sensitivity Functions of the shooting problem
        (:func:`~estim.estimators.window.shooting_problem.build_problem`)."""
        fun = build_problem(self.model, self.window, self.every, self.direction,
                            self.method, self.max_iter)
        self._J, self._terms, self._grad_other = fun.J, fun.terms, fun.grad_other
        self._sens, self._traj = fun.sens, fun.traj
        self._grad_sens, self._ipopt = fun.grad_sens, fun.ipopt

    # ------------------------------------------------------------------ state
    def _reset(self) -> None:
        keep = self._span + self.derivative_samples + 1
        self._ys: deque = deque(maxlen=keep)       # every sample's y
        self._us: deque = deque(maxlen=keep)       # input acting after each sample
        self._xs: deque = deque(maxlen=self._span + 1)  # estimates, oldest first
        self._x = self.x0.copy()                   # estimate at the current time
        self._w2 = self._fixed_w2
        self.history: deque = deque(maxlen=self.history_length)

    # ------------------------------------------------------------------- step
    def _step(self, y, u, first):
        t0 = time.perf_counter()
        failure = None
        if not first:
            w = self._transition(u)
            self._us.append(w.copy())
            x = self._F(self._x, w, self.model.p)[0]  # open-loop propagation
            if np.isfinite(x).all():
                self._x = x.copy()
            else:  # re-anchor on the last estimate, projected on the bounds
                self._x = self._anchor(self._x)[0]
                failure = "failed: non-finite prediction F(x, u); re-anchored on the last estimate"
        self._ys.append(y.copy())
        self._xs.append(self._x.copy())
        k = self._k  # index of this sample (Estimator increments after the step)
        ready = k >= self._span and k % self.every == 0 and np.isfinite(y).any()
        if not ready:
            return self._x.copy(), StepInfo(
                status=failure or "ok", success=failure is None,
                solve_time=time.perf_counter() - t0, extra={"optimised": False})
        x, info = self._optimise(t0)
        if failure is not None:
            info.__dict__.update(status=failure + f" ({info.status})", success=False)
        return x, info

    def _window_data(self):
        """Buffer samples Y (ny, w) (0 where missing), derivatives Yd, inputs U (nu, span),
        oldest first, and the output weights WY (ny * ny, w) (zero rows where missing)
        (:func:`~estim.estimators.window.shooting_problem.window_data`)."""
        m = self.model
        us = np.array(self._us).reshape(len(self._us), m.nw)
        Y, Yd, U, WY, self._measured = window_data(
            np.array(self._ys), us, m, self.window, self.every, self.derivative_samples,
            self.R, self._WR)
        return Y, Yd, U, WY

    def _optimise(self, t0):
        m, nx = self.model, self.model.nx
        Y, Yd, U, WY = self._window_data()
        use_d = m.continuous and self._w2 != 0 and np.isfinite(Yd).all()
        Yd = np.where(np.isfinite(Yd), Yd, 0.0)
        # warm start: the propagated previous estimate at the optimised time
        forward = self.direction == "forward"
        start = self._xs[0].copy() if forward else self._x.copy()
        if self._w2 is None and use_d:  # set on the first window with derivatives
            self._w2 = balanced_weight(self._terms, start, U, Y, Yd, WY)
        w2 = self._w2 if use_d and self._w2 else 0.0
        Wp = np.zeros((nx, nx)) if self.P0 is None else np.linalg.cholesky(
            np.linalg.inv(self.P0)).T
        args = (U, Y, Yd, w2, start, Wp.ravel(order="F"), WY)
        x_opt, cost, iters, ok, status = self._minimise(start, args)
        if ok:  # the whole window re-propagated from the optimum
            traj = self._traj(x_opt, U)[0].reshape(nx, -1, order="F").T
            if np.isfinite(traj).all():
                self._xs = deque((row.copy() for row in traj), maxlen=self._span + 1)
                self._x = traj[-1].copy()
            else:  # keep the propagated previous estimate
                ok, status = False, "non-finite propagation from the optimum"
        anchor = x_opt if ok else start
        if ok:  # the output term is chi-square in the noise: flag what the data contradict
            check = consistency_status(float(self._terms(x_opt, *args)[0][0]), self._measured,
                                       "output cost")
            if check != "ok":
                status = check if status == "ok" else f"{status}; {check}"
        # relative sensitivity (columns scaled by |xi|): states span many decades
        sv, cond = identifiability(self._sens(anchor, U, WY)[0].reshape(-1, nx, order="F"),
                                   anchor)
        elapsed = time.perf_counter() - t0
        self.history.append({"k": self._k, "condition": cond, "cost": cost,
                             "iterations": iters, "solve_time": elapsed, "success": ok,
                             "derivative_weight": w2})
        return self._x.copy(), StepInfo(
            status=status if ok else f"failed: {status}", success=ok, iterations=iters,
            solve_time=elapsed, cost=cost,
            extra={"optimised": True, "singular_values": sv, "condition": cond,
                   "derivative_weight": w2, "window_start": anchor.copy()})
