r"""Full-information estimation: the least-squares trajectory over a whole record."""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, TypeAlias, TypeVar

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._progress import bar as progress_bar
from estim._smoothness import advice, nonsmooth_operations, zero_derivative_parameters
from estim._validate import _numeric_array, as_inputs, as_intervals, as_record
from estim.estimators.base import EstimationWarning, Estimator, StepInfo
from estim.estimators.filtering import Estimates, stamped
from estim.estimators.manifold_steps import unit_bounds
from estim.estimators.window.noise import (
    check_tuning_noise,
    noise_solver,
    noise_weight,
    window_problem,
)
from estim.model import Model
from estim.solvers.kalman.continuous import noise_density
from estim.solvers.least_squares.nlp import LeastSquaresNLP
from estim.solvers.least_squares.options import (
    check_solver_options,
    jit_options,
    resolve_solver,
)
from estim.solvers.least_squares.robust import as_loss
from estim.solvers.least_squares.solution import Solution
from estim.solvers.weights import is_diagonal, weight_factor

if TYPE_CHECKING:
    from estim.uncertainty import ParameterEstimates


_T = TypeVar("_T")
#: A value of :class:`FitResult` computed on first access: the function that computes it
#: (replaced by ``(value,)`` once called), or None when there is none.
_Lazy: TypeAlias = Callable[[], _T] | tuple[_T] | None


def _finite_or_none(P: np.ndarray | None) -> np.ndarray | None:
    return P if P is not None and np.isfinite(P).all() else None


def _rows(P: np.ndarray | None, pad: int) -> np.ndarray | None:
    """``P`` after its first ``pad`` slots (None stays None: no covariance)."""
    return None if P is None else P[pad:]


def _residual_map(model: Model, T: int) -> FastFunction:
    """Residuals of a trajectory in one call.

    Inputs ``X (nx, T)``, ``U (nw, T)`` (transitions), ``U_prev (nu, T)``, ``Y (ny, T)``, flat
    column-major (a C-ordered ``(T, nx)`` array raveled as it is); outputs
    ``w (nx, T-1) = X[:, 1:] - F(X[:, :-1], U[:, :-1])`` and
    ``v (ny, T) = Y - h(X, U_prev)``. Expanded to one SX graph when the model
    allows it.
    """
    nx, nu, ny, pm = model.nx, model.nu, model.ny, ca.DM(model.p)
    M = model.manifold
    X, U, Up, Y = (ca.MX.sym(n, k, T) for n, k in (("X", nx), ("U", model.nw), ("Up", nu),
                                                    ("Y", ny)))
    if T == 1:
        w = ca.MX(M.ndx, 0)
    elif M.euclidean_states:
        w = X[:, 1:] - model.F.map(T - 1)(X[:, :-1], U[:, :-1], pm)
    else:  # the tangent vectors x_{k+1} - F(x_k) on the manifold
        a, b = ca.SX.sym("x", nx), ca.SX.sym("x_next", nx)
        local = ca.Function("local", [a, b], [M.local(a, b)])
        w = local.map(T - 1)(model.F.map(T - 1)(X[:, :-1], U[:, :-1], pm), X[:, 1:])
    v = M.output_difference(Y, model.H.map(T)(X, Up, pm)) if not M.output_angles else \
        ca.horzcat(*[M.output_difference(Y[:, k], model.H(X[:, k], Up[:, k], pm))
                     for k in range(T)])
    fun = ca.Function("residuals", [X, U, Up, Y], [w, v])
    try:
        fun = fun.expand()
    except RuntimeError:  # e.g. an integrator inside the model: stays mapped
        pass
    return FastFunction(fun)


@dataclass(frozen=True, repr=False)
class FitResult(Estimates):
    """Solution of :meth:`FullInformation.fit`.

    Attributes
    ----------
    x : (T, nx) array
        Smoothed trajectory :math:`\\hat x_0, \\dots, \\hat x_{T-1}`.
    w : (T-1, nx) array
        Process-noise estimates :math:`\\hat w_k = \\hat x_{k+1} - F(\\hat x_k, u_k)`;
        computed on first access.
    v : (T, ny) array
        Output residuals :math:`y_k - h(\\hat x_k)` (NaN where not measured);
        computed on first access.
    cost : float
        Optimal cost (sum of weighted squares; with a robust ``loss``, its measurement
        part is the sum of the loss over the whitened components).
    iterations : int
    status : str
        ``"ok"`` or the solver's reason for stopping.
    success : bool
    solve_time : float
        Seconds spent in the solver (without building graphs).
    build_time : float
        Seconds spent building compiled graphs during this fit (the first fit of a
        record length builds them; later ones reuse them).
    solver : str
        The solver that ran (what ``solver="auto"`` chose, or the one named).
    P : (T, nx, nx) array or None
        Laplace covariance of every sample: the diagonal blocks of
        :math:`(J^\top J)^{-1}` at the optimum, from a backward recursion over
        the block-tridiagonal factors (:math:`O(T n_x^3)`, no dense inverse);
        the Rauch-Tung-Striebel smoother's covariances on a linear-Gaussian model
        with a prior. With active bounds, the unconstrained approximation at the
        constrained optimum; with a robust loss, that of the final reweighted
        problem. None if the solve failed or the matrix is singular; computed
        on first access.
    P_last : (nx, nx) array or None
        Laplace covariance of the last state, ``P[-1]`` (the Kalman filter's
        covariance on a linear-Gaussian model with a prior); computed on first
        access, alone unless ``P`` was read first.
    measurement_weights : (T, ny) array or None
        With a robust ``loss``: the final weight of each whitened measurement
        component, in (0, 1] (1: treated as Gaussian; small: an outlier). None for
        least squares.
    t, state_names, manifold :
        Sample times, state names and the states' manifold (see
        :class:`~estim.estimators.filtering.Estimates`).
    _residuals, _covariance, _covariances : callable or None
        Internal: compute ``(w, v)``, ``P_last`` and ``P`` when first read.
    _context : tuple or None
        Internal: ``(model, prior, lower, upper)`` of the fit, for :meth:`parameters`.
    """

    x: np.ndarray
    cost: float
    iterations: int
    status: str
    success: bool
    solve_time: float
    build_time: float = 0.0
    measurement_weights: np.ndarray | None = None
    solver: str = ""
    _residuals: _Lazy[tuple[np.ndarray, np.ndarray]] = field(default=None, repr=False,
                                                             compare=False)
    _covariance: _Lazy[np.ndarray | None] = field(default=None, repr=False, compare=False)
    _covariances: _Lazy[np.ndarray | None] = field(default=None, repr=False, compare=False)
    _context: tuple | None = field(default=None, repr=False, compare=False)

    def _lazy(self, name: str):
        value = getattr(self, name)
        if callable(value):  # computed once, on first access
            value = (value(),)
            object.__setattr__(self, name, value)
        return None if value is None else value[0]

    @property
    def w(self) -> np.ndarray:
        return self._lazy("_residuals")[0]

    @property
    def v(self) -> np.ndarray:
        return self._lazy("_residuals")[1]

    @property
    def P(self) -> np.ndarray | None:
        return self._lazy("_covariances")

    @property
    def P_last(self) -> np.ndarray | None:
        if not callable(self._covariances) and self._covariances is not None:
            P = self._covariances[0]  # already computed: its last block
            return None if P is None else P[-1]
        return self._lazy("_covariance")

    def parameters(self, scale: str = "none", warn: bool = True) -> ParameterEstimates:
        r"""Standard errors, correlations and intervals of the augmented parameters.

        The parameters' block of ``P_last``, the Laplace approximation
        :math:`[(J^\top J)^{-1}]_{\theta\theta}` at the optimum; see
        :func:`estim.parameter_uncertainty`, which this calls.

        Parameters
        ----------
        scale : {"none", "residual"}
            ``"none"``: ``R`` is known; ``"residual"``: rescaled by the residual
            variance, Student's t intervals.
        warn : bool
            Warn (:class:`~estim.EstimationWarning`) about poorly determined parameters.

        Returns
        -------
        ParameterEstimates
        """
        from estim.uncertainty import _estimates

        return _estimates(self, scale=scale, warn=warn, stacklevel=2)

    @property
    def params(self) -> dict[str, float]:
        """The augmented parameters' estimates by name (the last sample's)."""
        from estim.uncertainty import _values

        return _values(self)

    @property
    def stderr(self) -> dict[str, float]:
        """The augmented parameters' standard errors by name (see :meth:`parameters`)."""
        from estim.uncertainty import _estimates

        est = _estimates(self, stacklevel=2)
        return dict(zip(est.names, est.stderr.tolist(), strict=True))

    def confidence(self, level: float = 0.95) -> dict[str, tuple[float, float]]:
        """The augmented parameters' confidence intervals by name (see :meth:`parameters`).

        Parameters
        ----------
        level : float
            Confidence level in (0, 1).

        Returns
        -------
        dict of str -> (float, float)
            ``(lower, upper)`` of each parameter.
        """
        from estim.uncertainty import _estimates

        est = _estimates(self, stacklevel=2)
        return {n: (float(lo), float(hi))
                for n, (lo, hi) in zip(est.names, est.interval(level), strict=True)}


def _record(model: Model, Y: ArrayLike, U: ArrayLike | None, t: ArrayLike | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A record checked for :meth:`FullInformation.fit`: ``Y (T, ny)``, the transitions'
    inputs ``W (T, nw)`` (the last row unused) and the measurements' inputs ``(T, nu)``."""
    m = model
    Y = as_record(Y, m.ny, "Y", names=m.output_names, what="outputs")
    T = Y.shape[0]
    if np.isnan(Y).all():
        raise ValueError("Y has no measured value")
    U = as_inputs(U, T, m)
    dts = as_intervals(t, T, m)
    if m.sampled:  # inputs at the samples: transitions from each to the next
        W, Uy = np.hstack([U, np.vstack([U[1:], U[-1:]])]), U
    else:
        Uy = np.empty_like(U)
        Uy[0] = 0.0
        Uy[1:] = U[:-1]
        W = U
    if m.variable_dt:  # each transition's interval (the model's dt without t)
        W = np.hstack([W, np.full((T, 1), m.dt)])
        if dts is not None:
            W[:-1, -1] = dts
    return Y, W, Uy


def _result(model: Model, solver: str, maps: dict[int, FastFunction], nlp: LeastSquaresNLP,
            sol: Solution, Y: np.ndarray, U: np.ndarray, Uprev: np.ndarray, pad: int = 0
            ) -> FitResult:
    """The :class:`FitResult` of the solve ``sol`` of ``nlp``, whose record ``Y``, ``U``,
    ``Uprev`` fills its slots after the first ``pad``: the trajectory, and the residuals
    and covariances to compute on first access (``maps``: the residual maps by record
    length, built once)."""
    m, Xfull = model, sol.X
    X = Xfull[pad:].copy()
    T = len(X)
    # residuals and covariance are evaluated on first access, maybe after other
    # fits or after the caller changed its arrays: snapshots
    data = (X.ravel(), U.ravel().copy(), Uprev.ravel().copy(), Y.ravel().copy())

    def residuals() -> tuple[np.ndarray, np.ndarray]:
        if T not in maps:
            maps[T] = _residual_map(m, T)
        w, v = maps[T](*data)
        return w.reshape(T - 1, m.ndx).copy(), v.reshape(T, m.ny).copy()

    p_snapshot, complete = nlp._p.copy(), nlp._complete
    cov = (lambda: _finite_or_none(nlp.covariance_at(Xfull.ravel(), p_snapshot, complete))) \
        if sol.success else None
    covs = (lambda: _finite_or_none(
        _rows(nlp.covariances_at(Xfull.ravel(), p_snapshot, complete), pad))) \
        if sol.success else None
    return FitResult(x=X, cost=sol.cost, iterations=sol.iterations, status=sol.status,
                     success=sol.success, solve_time=sol.solve_time,
                     build_time=sol.build_time, solver=solver,
                     measurement_weights=None if nlp.loss is None or nlp.weights is None
                     else nlp.weights[pad:].copy(),
                     _residuals=residuals, _covariance=cov, _covariances=covs)


class FullInformation(Estimator):
    r"""Full-information estimation (batch maximum a posteriori trajectory).

    .. math::
        \min_{x_0, \dots, x_{T-1}}\;
        \|x_0 - \bar x_0\|^2_{P_0^{-1}}
        + \sum_{k=0}^{T-2} \|x_{k+1} - F(x_k, u_k)\|^2_{Q^{-1}}
        + \sum_{k=0}^{T-1} \|y_k - h(x_k, u_{k-1})\|^2_{R^{-1}}
        \quad\text{s.t.}\; \underline x \le x_k \le \overline x

    The prior term is present when ``x0`` and ``P0`` are both given (zero
    prior weighting otherwise, as in OpEn's estimation example). On a
    linear-Gaussian model with a prior the solution is the Rauch-Tung-Striebel
    smoother.

    The default solver (``"auto"``) is the structure-exploiting projected Gauss-Newton/
    Newton method of :mod:`estim.solvers.least_squares.gauss_newton`: each iteration is
    a block-tridiagonal solve (a Riccati recursion on the linearised model),
    :math:`O(T n_x^3)`, evaluated by one expanded SX graph (longer records: about
    4200 samples of a three-state model, 850 of a seven-state one; expanded chunks
    called in a loop), so the cost is linear in
    :math:`T`. ``solver="ipopt"`` (or ``"fatrop"``,
    ``"sqp"``) solves the same problem with CasADi's NLP solvers.

    Parameters
    ----------
    model : Model
    Q : float, (nx,) or (nx, nx)
        Process-noise covariance: positive definite (weights :math:`Q^{-1}`), or
        singular, with noise on some directions only (the dynamics then hold exactly
        in the others: a constrained problem, the noise variables sized by the rank of
        ``Q``, solved by Ipopt or fatrop; see
        :class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`).
    Qc : (nq, nq) array, optional
        In place of ``Q``, for a continuous model: the spectral density of the noise
        entering through the model's ``noise_input`` :math:`L`. Each transition is then
        weighed by the inverse of the :math:`Q_d(\Delta t_k)` of its own interval (Van
        Loan's, of the drift linearised at :math:`x_k`: exact on a linear model); the
        noise must reach every state. See docs/continuous_noise.md.
    R : float, (ny,) or (ny, ny)
        Measurement-noise covariance.
    x0, P0 : optional
        Prior mean and covariance of the first state. ``x0`` alone is only
        the initial guess of :meth:`step`.
    lower, upper : optional
        State bounds (default: the model's); handled by projection in
        Gauss-Newton, as constraints by the NLP solvers.
    solver : {"auto", "gauss-newton", "ipopt", "sqp", "fatrop"}
        As for :class:`~estim.MHE`: ``"auto"`` is ``"gauss-newton"`` for these
        problems; the choice is :attr:`solver`, ``FitResult.solver`` and
        ``info.extra["solver"]``.
    solver_options : dict, optional
        As for :class:`~estim.MHE`.
    loss, f_scale, dof : optional
        A robust measurement cost (``"huber"``, ``"soft_l1"``, ``"cauchy"``,
        ``"student-t"`` with ``dof``) and its scale, as for :class:`~estim.MHE`; the fit
        then reports the final weight of every measured value in
        ``FitResult.measurement_weights``.
    jit : bool
        Compiled code, as for :class:`~estim.MHE` (``solver_options={"jit": True}``).

    References
    ----------
    C. V. Rao, J. B. Rawlings, D. Q. Mayne (2003), IEEE TAC 48(2);
    H. E. Rauch, F. Tung, C. T. Striebel (1965), AIAA J. 3(8);
    B. M. Bell (1994), "The iterated Kalman smoother as a Gauss-Newton
    method", SIAM J. Optim. 4(3).
    """

    name = "fie"
    _manifold_aware = True  # with the Gauss-Newton solver
    _requires_P0 = False

    def __init__(self, model: Model, *, Q: ArrayLike | None = None, R: ArrayLike,
                 x0: ArrayLike | None = None,
                 P0: ArrayLike | None = None, lower: ArrayLike | None = None,
                 upper: ArrayLike | None = None,
                 solver: str = "auto", solver_options: dict | None = None,
                 loss: str = "squared", f_scale: float | None = None, jit: bool = False,
                 Qc: ArrayLike | None = None, dof: float | None = None):
        Q, self.Qc = noise_density(model, Q, Qc)
        solver_options, self.jit = jit_options(jit, solver_options)
        requested, solver = solver, resolve_solver(solver, solver_options)
        self._loss = as_loss(loss, f_scale, dof)
        self._prior = x0 is not None and P0 is not None
        self._x0_given = x0 is not None
        if P0 is not None and x0 is None:
            raise ValueError("P0 was given without x0: the prior needs its mean x0")
        if x0 is None:  # the start: zeros (identity quaternions)
            x0 = np.zeros(model.nx)
            x0[[g[0] for g in model.manifold.quaternions]] = 1.0
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        solver, self._rank = noise_solver(self.Q, requested, solver, model=model,
                                          who="full-information estimation", loss=self._loss,
                                          continuous=self.Qc is not None, x0=self.x0)
        solver_options = check_solver_options(solver, solver_options)
        self.lower, self.upper = self._bounds(lower, upper)
        unit_bounds(model, self.lower, self.upper)
        self.solver = solver
        self.solver_options = solver_options
        self._diagonal = {"Q": is_diagonal(self.Q), "R": is_diagonal(self.R)}
        self._nlps: dict[tuple[int, bool], LeastSquaresNLP] = {}
        self._maps: dict[int, FastFunction] = {}
        self._F = FastFunction(model.F)  # this estimator's own buffers (thread safety)
        self._tuning_changed()
        self._reset()
        self._warn_if_not_smooth()

    def _check_tuning(self, new: dict) -> None:
        if "Q" in new:
            check_tuning_noise(self, new["Q"], self._rank)
        if "P0" in new and not (self._x0_given or "x0" in new):
            raise ValueError("P0 was given without x0: the prior needs its mean x0")

    def set_tuning(self, *, Q: ArrayLike | None = None, R: ArrayLike | None = None,
                   P0: ArrayLike | None = None, x0: ArrayLike | None = None) -> None:
        new = self._validated_tuning(Q=Q, R=R, P0=P0, x0=x0)
        self._x0_given = self._x0_given or "x0" in new  # a prior needs its mean
        self.__dict__.update(new)
        self._tuning_changed()

    set_tuning.__doc__ = Estimator.set_tuning.__doc__

    def _tuning_changed(self) -> None:
        self._WQ = noise_weight(self, self.Q, self._rank)
        self._WR = weight_factor(self.R)
        P0 = self.P0 if self._x0_given else None  # a prior needs its mean
        self._W0 = None if P0 is None else self._weight_factor(P0)
        self._prior = self._W0 is not None

    def _problem(self, N: int, full: bool) -> LeastSquaresNLP:
        """The problem of N slots, built once (``full``: fit's exact-length records)."""
        if (N, full) not in self._nlps:
            self._nlps[N, full] = window_problem(
                self.model, N, self.lower, self.upper, self.solver, self.solver_options,
                self._rank, self._diagonal, self._loss, full=full,
                continuous=self.Qc is not None)
        return self._nlps[N, full]

    # ------------------------------------------------------------------ batch
    def fit(self, Y: ArrayLike, U: ArrayLike | None = None, guess: ArrayLike | None = None, *,
            Q: ArrayLike | None = None, R: ArrayLike | None = None,
            t: ArrayLike | None = None) -> FitResult:
        """Solve over the whole record.

        Parameters
        ----------
        Y : (T, ny) array
            Measurements; NaN entries are missing outputs.
        U : (T-1, nu) or (T, nu) array, optional
            ``U[k]`` acts from sample k to k+1 (and is the held input when
            ``y_{k+1}`` is taken). With ``hold="foh"``, ``(T, nu)``: the input at
            each sample, linear in between. Required for a model with inputs
            (``U=0``: zero inputs, on purpose).
        guess : (T, nx) array, optional
            Initial trajectory; default ``x0`` repeated (zeros without ``x0``).
        Q, R : optional
            Covariances for this fit only (default: the estimator's, see
            :meth:`set_tuning`); nothing is rebuilt.
        t : (T,) array, optional
            Sample times: a model built with ``variable_dt=True`` integrates from
            each sample to the next over ``t[k+1] - t[k]`` (default: the model's
            ``dt``); a continuous model with a fixed ``dt`` refuses other spacings.

        Returns
        -------
        FitResult
        """
        weights = None
        if Q is not None or R is not None:
            new = self._validated_tuning(Q=Q, R=R)
            Qf, Rf = new.get("Q", self.Q), new.get("R", self.R)
            weights = (noise_weight(self, Qf, self._rank), weight_factor(Rf), Rf)
        Yr, W, Uy = _record(self.model, Y, U, t)
        T, nx = Yr.shape[0], self.model.nx
        if guess is None:
            X0 = np.empty((T, nx))
            X0[:] = self.x0
        else:
            X0 = _numeric_array(guess, "guess")
            if X0.shape != (T, nx):
                raise ValueError(f"guess must have shape ({T}, {nx}), got {X0.shape}")
            if not np.isfinite(X0).all():
                raise ValueError("guess must be finite")
        # a long fit reports its iterations (a bar after 2 s, see estim._progress)
        with progress_bar(None, f"FullInformation.fit, {T} samples", "it") as bar:
            res = self._solve(Yr, W, Uy, X0, T, full=True, weights=weights, progress=bar)[0]
        # (the first nu columns of the transitions' inputs: the input at each sample)
        frozen = zero_derivative_parameters(self.model, res.x, W[:, :self.model.nu]) \
            if self.model.augmented and res.success else []
        if frozen:  # they kept their initial values: not an optimum in them
            warnings.warn(f"FullInformation.fit on {self.model.name}: "
                          f"{advice(nonsmooth_operations(self.model), frozen)}",
                          EstimationWarning, stacklevel=3)
            res = replace(res, success=True, status=f"inexact: {', '.join(frozen)} "
                          f"{'has' if len(frozen) == 1 else 'have'} a zero derivative over "
                          f"the record and kept the initial value")
        res = replace(res, _context=(self.model, self._prior, self.lower, self.upper))
        return stamped(res, self.model, t)

    def _solve(self, Y, U, Uprev, X0, capacity: int, full: bool = False, prior=None,
               robust: bool = False, weights=None, progress=None
               ) -> tuple[FitResult, Solution]:
        """Solve on a problem of ``capacity >= T`` slots, the record in the last ``T``.

        The unused leading slots are chained to the first state at no cost
        (see :mod:`estim.solvers.least_squares.nlp`), so the optimum is that of the
        ``T``-sample problem; one problem then serves every shorter record.
        ``prior``: ``(mean, weight factor or None)`` of the first sample (default
        ``x0`` with ``P0``'s); ``robust``: solved by Gauss-Newton whatever the solver;
        ``weights``: ``(W_Q, W_R, R)`` (default the estimator's).
        Returns the result and the solver's :class:`~estim.solvers.least_squares.solution.Solution`
        (whether the trajectory is usable, the outliers of a robust loss).
        """
        m, T, C = self.model, Y.shape[0], capacity
        pad = C - T
        if pad:
            Y = np.vstack([np.full((pad, m.ny), np.nan), Y])
            U = np.vstack([np.zeros((pad, m.nw)), U])
            Uprev = np.vstack([np.zeros((pad, m.nu)), Uprev])
            X0 = np.vstack([np.repeat(X0[:1], pad, axis=0), X0])
        nlp = self._problem(C, full=full and pad == 0)
        if full:  # a fit does not depend on earlier fits (warm-start multipliers, ridge)
            nlp.reset()
        xbar, W0 = (self.x0, self._W0) if prior is None else prior
        WQ, WR, R = (self._WQ, self._WR, self.R) if weights is None else weights
        nlp.gn.progress = progress
        try:
            sol = nlp.solve(X0, Y, U, Uprev, T, xbar, W0, WQ, WR, R, robust=robust)
        finally:
            nlp.gn.progress = None
        return _result(m, self.solver, self._maps, nlp, sol, Y[pad:], U[pad:], Uprev[pad:],
                       pad), sol

    # ------------------------------------------------------------ recursive
    def _reset(self) -> None:
        self._tuning_changed()  # reset may have changed P0
        for nlp in self._nlps.values():  # as if freshly built
            nlp.reset()
        self._Ys: list[np.ndarray] = []
        self._Ws: list[np.ndarray] = []  # the transitions' inputs
        self._Us: list[np.ndarray] = []  # the inputs of the samples' measurements
        self._X: np.ndarray | None = None
        self._start = (self.x0.copy(), self._W0)  # prior of the record's first sample
        # the last estimate (and covariance) of a step reported "ok" or "inexact":
        # where a failed step re-anchors
        self._trusted = (self.x0.copy(), None if self.P0 is None else self.P0.copy())

    def _solve_record(self, robust: bool = False) -> tuple[FitResult, bool, str]:
        """Solve the record held so far, warm-started from the previous trajectory plus
        the prediction of its last state; the result, whether it is usable, and the
        consistency of its cost (``"ok"`` or ``"suspect: ..."``)."""
        m, T = self.model, len(self._Ys)
        Y = np.array(self._Ys)
        U = np.vstack([np.array(self._Ws).reshape(T - 1, m.nw), np.zeros((1, m.nw))])
        Uprev = np.array(self._Us).reshape(T, m.nu)
        if self._X is None or len(self._X) != T - 1:
            guess = np.repeat(self._start[0][None, :], T, axis=0)
        else:
            pred = self._F(self._X[-1], U[-2], m.p)[0]
            guess = np.vstack([self._X, pred if np.isfinite(pred).all() else self._X[-1]])
        capacity = max(8, 1 << (T - 1).bit_length())  # doubles: log2(T) problems built
        res, sol = self._solve(Y, U, Uprev, guess, capacity, prior=self._start, robust=robust)
        measured = int(np.isfinite(Y).sum())
        dof = measured + (0 if self._start[1] is None else m.ndx)
        return res, sol.usable, sol.consistency(dof, measured)

    def _step(self, y, u, first):
        t0 = time.perf_counter()
        if self._Ys:
            self._Ws.append(self._transition(u).copy())
        self._Us.append(u.copy())
        self._Ys.append(y.copy())
        res, usable, check = self._solve_record()
        failure = None
        if not usable or (not res.success and check != "ok"):
            # restart the record at this sample, the last trusted estimate its prior
            failure = self._failure(usable, res.status, res.cost)
            x, P = self._anchor(*self._trusted)
            self._Ys, self._Ws, self._Us = [y.copy()], [], [u.copy()]
            self._start = (x, None if P is None else self._weight_factor(P))
            self._X = None
            res, usable, check = self._solve_record(robust=True)
        x_hat = res.x[-1].copy() if usable else self._start[0].copy()
        self._X = res.x if usable else np.repeat(self._start[0][None, :], len(self._Ys), 0)
        P = res.P_last if usable else None
        status = self._solve_status(failure, usable, res.success, res.status, check, "record")
        if failure is None and check == "ok":
            self._trusted = (x_hat.copy(), P)
        return x_hat, StepInfo(
            status=status, success=failure is None, iterations=res.iterations,
            solve_time=time.perf_counter() - t0, P=P, cost=res.cost,
            extra={"trajectory": self._X, "solver": self.solver})
