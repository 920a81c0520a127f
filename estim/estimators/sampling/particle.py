r"""Bootstrap particle filter on any :class:`~estim.Model`.

The posterior :math:`p(x_k \mid y_{0:k})` is carried by :math:`N` particles
:math:`x^i_k` with normalised weights :math:`W^i_k` (Gordon, Salmond, Smith 1993;
Chopin, Papaspiliopoulos 2020, ch. 10). At every step after the first,

.. math::
    x^i_k = F(x^i_{k-1}, u_{k-1}) + L_Q v^i, \quad v^i \sim N(0, I), \quad
    L_Q L_Q^\top = Q,

    \log W^i_k = \log W^i_{k-1} + \ell(y_k \mid x^i_k) - \log \sum_j W^j_{k-1}
    e^{\ell(y_k \mid x^j_k)},

with the measurement log-density :math:`\ell` Gaussian,
:math:`\ell = \log N(y_k;\, h(x^i_k), R)` over the measured outputs, or any
log-density the user writes (``loglik``). The first step draws
:math:`x^i_0 \sim N(x_0, P_0)` and weights them by :math:`y_0`. When the
effective sample size :math:`1/\sum_i (W^i)^2` falls below ``ess_threshold``
:math:`\cdot N` the particles are resampled (:mod:`estim.solvers.sampling.resampling`).
The log-likelihood estimate :math:`\log \hat p(y_{0:k}) = \sum_k \log \sum_i
W^i_{k-1} e^{\ell(y_k \mid x^i_k)}` is unbiased for the likelihood (not its
logarithm) at every :math:`N`.

Propagation and weighting of all particles are one call per step of a function
generated from the model's CasADi graph with one numpy operation per
instruction over all particles (:mod:`estim._vectorised`), or CasADi's ``map``
for a model whose graph calls other Functions (an integrator).

References
----------
N. J. Gordon, D. J. Salmond, A. F. M. Smith, "Novel approach to
nonlinear/non-Gaussian Bayesian state estimation", IEE Proc. F 140(2), 1993;
A. Doucet, S. Godsill, C. Andrieu, "On sequential Monte Carlo sampling methods for
Bayesian filtering", Statistics and Computing 10(3), 2000;
N. Chopin, O. Papaspiliopoulos, *An Introduction to Sequential Monte Carlo*,
Springer 2020.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._manifold import NP
from estim._validate import as_bool, as_choice, as_float, as_int, as_seed
from estim.estimators.base import StepInfo, seeded
from estim.estimators.filtering import Estimates, stamped
from estim.estimators.sampling.ensembles import (
    deviations,
    draw_about,
    over_points,
    run_record,
    square_root,
)
from estim.estimators.sampling.particle_compiled import CompiledParticles, step_status
from estim.estimators.sampling.particle_graphs import (
    definite,
    graphs,
    measured_tuning,
    prior_tuning,
    proposal_rule,
)
from estim.estimators.sampling.particle_smoothing import ParticleSmoothResult, backward_simulation
from estim.model import Model
from estim.solvers.sampling.resampling import (
    RESAMPLING,
    distinct_particles,
    effective_sample_size,
    resample,
)

__all__ = ["ParticleFilter", "ParticleFilterResult"]

#: the proposals: the transition (bootstrap), or the transition updated by the
#: measurement, linearised at the predicted particle ("ekf") or through the
#: unscented transform of its transition density ("ukf")
PROPOSALS = ("bootstrap", "ekf", "ukf")


@dataclass(frozen=True, repr=False)
class ParticleFilterResult(Estimates):
    """A record filtered by :meth:`ParticleFilter.filter`.

    Attributes
    ----------
    x : (T, nx) array
        Weighted means of the particles after each update.
    P : (T, ndx, ndx) array
        Their weighted covariances.
    ess : (T,) array
        Effective sample sizes after each update (before resampling).
    log_likelihood : float
        The estimate :math:`\\log \\hat p(y_{0:T-1})` (its exponential is unbiased).
    log_likelihood_increments : (T,) array
        Its terms :math:`\\log \\hat p(y_k \\mid y_{0:k-1})`.
    status : tuple of str
        The status of every sample.
    success : bool
        Every step succeeded.
    t, state_names, manifold :
        Sample times, state names and the states' manifold (see
        :class:`~estim.estimators.filtering.Estimates`).
    """

    x: np.ndarray
    P: np.ndarray
    ess: np.ndarray
    log_likelihood: float
    log_likelihood_increments: np.ndarray
    status: tuple[str, ...]
    success: bool


def _spread(D: np.ndarray, W: np.ndarray) -> np.ndarray:
    """The weighted second moment ``sum_i W_i D[:, i] D[:, i]^T`` of deviations ``D``
    ``(n, N)``, entry by entry (long vectors: no threaded BLAS call per step)."""
    n = D.shape[0]
    DW = D * W
    if n == 1:
        return np.array([[float((DW[0] * D[0]).sum())]])
    P = np.empty((n, n))
    for i in range(n):
        for j in range(i + 1):
            P[i, j] = P[j, i] = float((DW[i] * D[j]).sum())
    return P


def _innovation(y: np.ndarray, observed: np.ndarray, Yh: np.ndarray, Wp: np.ndarray | None,
                Ro: np.ndarray) -> tuple[np.ndarray, float]:
    """``y`` less the particles' predicted outputs ``Yh`` ``(ny, N)`` under the previous
    weights ``Wp`` (None: equal), and its NIS against their spread plus ``Ro``, the
    measured outputs' block of ``R`` (0 and NaN without a measured output)."""
    e = np.zeros(len(y))
    if not observed.any():
        return e, float("nan")
    if not observed.all():
        Yh = Yh[observed]
    yb = Yh.sum(axis=1) / Yh.shape[1] if Wp is None else (Yh * Wp).sum(axis=1)
    if not np.isfinite(yb).all():  # lost particles: without them
        ok = np.isfinite(Yh).all(axis=0)
        Wp = (np.ones(Yh.shape[1]) if Wp is None else Wp) * ok
        Wp = Wp / Wp.sum() if Wp.sum() > 0 else None
        if Wp is None:
            return e, float("nan")
        Yh = np.where(ok, Yh, 0.0)
        yb = (Yh * Wp).sum(axis=1)
    eo = y[observed] - yb
    e[observed] = eo
    D = Yh - yb[:, None]
    if len(eo) == 1:  # one measured output: its variance directly
        d = D[0]
        var = float((d * d).sum()) / len(d) if Wp is None else float((d * d * Wp).sum())
        return e, float(eo[0] ** 2 / (var + Ro[0, 0]))
    if Wp is None:
        Wp = np.full(Yh.shape[1], 1.0 / Yh.shape[1])
    S = _spread(D, Wp) + Ro
    try:
        return e, float(eo @ np.linalg.solve(S, eo))
    except np.linalg.LinAlgError:
        return e, float("nan")


def _moments(model: Model, X: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The weighted mean (on a manifold: the weighted Karcher mean) and covariance of the
    particles ``X`` ``(nx, N)``."""
    x_hat, D = deviations(model, X, W)
    return x_hat, _spread(D, W)


def _update(X: np.ndarray, ell: np.ndarray, observed: np.ndarray, const: float,
            W_prev: np.ndarray | None, support: tuple[np.ndarray, np.ndarray] | None
            ) -> tuple[np.ndarray | None, float, np.ndarray]:
    r"""Normalised weights :math:`W_k \propto W_{k-1} e^{\ell}` (``W_prev`` None:
    equal; zero outside the ``support``), the log-likelihood term (``const`` added: the
    Gaussian's constant, 0 for a user's log-density) and the particles (non-finite ones
    zeroed, their weight zero); ``(None, nan, X)`` when no weight is left."""
    N = X.shape[1]
    if not observed.any():
        ell = np.zeros(N)
    a = ell if W_prev is None else ell + np.log(W_prev)
    if support is not None:  # outside the support: weight zero
        inside = ((X >= support[0]) & (X <= support[1])).all(axis=0)
        a = np.where(inside, a, -np.inf)
    top = a.max()  # NaN if any is NaN
    finite = bool(np.isfinite(X.sum()))  # (NaN and inf propagate; an overflow of
    # the sum alone only takes the slow path below)
    if not (np.isfinite(top) and finite):  # the slow path: some particles are lost
        ok = np.isfinite(X).all(axis=0) & ~np.isnan(a)
        a = np.where(ok, a, -np.inf)
        top = a.max()
        if not np.isfinite(top):
            return None, float("nan"), X
        X = np.where(ok, X, 0.0)
    W = np.exp(a - top)
    s = W.sum()
    W /= s
    # log sum_i W_prev_i e^{l_i}
    inc = float(top + np.log(s / N if W_prev is None else s))
    return W, inc + const, X


def _smooth(self: ParticleFilter, Y: ArrayLike, U: ArrayLike | None = None, *,
            n_paths: int = 100, t: ArrayLike | None = None, seed: int | None = None
            ) -> ParticleSmoothResult:
    """Smoothed trajectories of a whole record by forward-filtering
    backward-simulation (:mod:`estim.estimators.sampling.particle_smoothing`).

    Parameters
    ----------
    Y, U :
        The record, as for :meth:`filter` (which runs first, from a :meth:`reset`).
    n_paths : int
        Number of trajectories drawn backwards (cost ``O(T N n_paths)``).
    t : (T,) array, optional
        Sample times, kept in the result.
    seed : int, optional
        The random numbers of this call, forward pass and backward draws (as for
        :meth:`filter`).

    Returns
    -------
    ParticleSmoothResult
        ``paths (n_paths, T, nx)``, their mean ``x (T, nx)`` and covariances
        ``P (T, nx, nx)``, the filter's ``x_filtered``, ``P_filtered`` and its whole
        result ``filtered`` (its log-likelihood estimate, ESS and statuses: no second
        forward pass needed); a singular ``Q`` handled exactly
        (:mod:`~estim.estimators.sampling.particle_smoothing`).
    """
    if seed is not None:
        return seeded(self, seed, lambda: self.smooth(Y, U, n_paths=n_paths, t=t))
    n_paths = as_int(n_paths, "n_paths", minimum=1)
    self._trace = []
    try:
        filtered = self.filter(Y, U, t=t)
        trace = self._trace
    finally:
        self._trace = None
    M = self.model.manifold
    return backward_simulation(self._transit, self.Q, trace, self._rng, n_paths,
                               None if M.euclidean_states else M, filtered)


def _set_params(self: ParticleFilter, **values: float) -> None:
    """Change the model's parameter values in this filter, from the next step on; nothing
    is rebuilt (the compiled steps take the parameters as data, so a chain over them
    costs one filter run per point). ``pf.set_params(rho=0.9)``; unknown names and
    values that are not finite numbers are refused by name."""
    p = self._p.copy()
    names = self.model.param_names
    for key, val in values.items():
        if key not in names:
            raise ValueError(f"unknown parameter {key!r}; the model's parameters are "
                             f"{names}")
        p[names.index(key)] = as_float(val, f"parameter {key!r}")
    self._p = p


def _params(self: ParticleFilter) -> dict[str, float]:
    """The parameter values the filter runs with (the model's, or :meth:`set_params`')."""
    return dict(zip(self.model.param_names, self._p.tolist(), strict=True))


def _stage_input(self: ParticleFilter, u: np.ndarray) -> np.ndarray:
    """The per-particle Functions' input of a step: the transition input, then the
    parameters."""
    if not self.model.nw:
        return self._p
    return np.concatenate([self._transition(u), self._p])


class ParticleFilter(CompiledParticles):
    r"""Bootstrap particle filter (sequential importance resampling; see the module).

    Parameters
    ----------
    model : Model
    Q, R, x0, P0 :
        Process-noise covariance (additive, may be singular), measurement-noise
        covariance (the Gaussian log-density; also the innovation's covariance
        reported with a custom ``loglik``), initial guess and its covariance.
    n_particles : int
        Number of particles :math:`N` (at least 2).
    resampling : {"systematic", "stratified", "residual", "multinomial"}
        The resampling scheme (:mod:`estim.solvers.sampling.resampling`).
    ess_threshold : float in (0, 1]
        Resample when the effective sample size falls below ``ess_threshold * N``
        (1: at every step).
    loglik : callable, optional
        ``loglik(y, yhat, p)``: the measurement log-density of ``y`` (ny,) given the
        prediction ``yhat = h(x)`` (ny,) and the model's parameters ``p`` (a dict of
        names), as a scalar CasADi expression. Student-t noise with 3 degrees of
        freedom and scale 0.3 on one output:
        ``lambda y, yhat, p: -2 * ca.log1p(((y[0] - yhat[0]) / 0.3) ** 2 / 3)``;
        Laplace noise of scale 0.3: ``lambda y, yhat, p: -ca.fabs(y[0] - yhat[0]) / 0.3``
        (constant terms only shift :attr:`ParticleFilterResult.log_likelihood`). A
        missing output enters as ``y_i = yhat_i``: exact for a log-density that is a
        sum over outputs whose terms vanish at a zero residual. Default: Gaussian with
        covariance ``R``.
    proposal : {"bootstrap", "ekf", "ukf"}
        Where new particles are drawn: from the transition,
        :math:`N(F(x^i_{k-1}), Q)` (``"bootstrap"``, the default), or from the
        transition updated by :math:`y_k` with the output linearised at
        :math:`\bar x^i = F(x^i_{k-1})` (``"ekf"``, Doucet, Godsill, Andrieu 2000):
        :math:`N(\bar x^i + K_i (y_k - h(\bar x^i)),\, (I - K_i C_i) Q)`,
        :math:`K_i = Q C_i^\top (C_i Q C_i^\top + R)^{-1}`, the weights multiplied by
        the transition density over the proposal's; or with the output's moments
        taken by the unscented transform of :math:`N(\bar x^i, Q)` (``"ukf"``, the
        unscented particle filter of van der Merwe, Doucet, de Freitas, Wan 2000, with
        the :math:`2 n_x` spherical-cubature points: :math:`K_i = P_{xy} P_{yy}^{-1}`,
        covariance :math:`Q - K_i P_{yy} K_i^\top`), which follows a curved output
        over the spread of :math:`Q` where the linearisation sees only its slope at
        :math:`\bar x^i`. Both are exact (the optimal proposal) for a linear output,
        and lose far fewer particles than the bootstrap when the measurements are
        precise. They need a positive definite ``Q``.
    points, order : str, int
        The unscented proposal's rule (:mod:`estim.solvers.quadrature`): ``"cubature"``
        (default, above), ``"gauss-hermite"`` of ``order`` or ``"cubature5"`` (up to four
        states): positive weights only, so the proposal's covariance stays definite.
    lower, upper : optional
        The support of the state (default: the model's bounds): a particle outside gets
        weight zero, as under a prior truncated to the bounds (concentrations that
        cannot be negative, a tank that cannot overfill). The estimates, weighted means
        of particles inside, stay inside.
    seed : int
        Seed of the filter's random numbers (``numpy.random.default_rng``; with
        ``jit=True`` the compiled path's own streams); every :meth:`reset` starts the
        same stream again, so a run is reproducible bit for bit. Over the seeds of
        :func:`~estim.compare` each run draws its own stream, from this seed and the
        run's (independent runs, the same at every call).
    jit : bool
        Run the steps compiled (:mod:`estim.solvers.sampling.particle_kernel`): :meth:`filter`
        in one call of machine code for the whole record, :meth:`step` in one call
        each, with the random numbers drawn there too; several times faster (the model's
        two kernels take a few tenths of a second to compile, once per machine). The
        same filter with other random numbers. Models with quaternion or angle states,
        a model whose graph calls an integrator, or a machine without a C compiler stay
        interpreted, with an :class:`~estim.EstimationWarning`. Default False.

    Notes
    -----
    ``info.P`` is the weighted covariance of the particles after the update,
    ``info.extra`` holds ``"ess"`` (before resampling), ``"log_likelihood"``
    (this step's term) and ``"resampled"``. The innovation is
    :math:`y_k - \sum_i W^i_{k-1} h(x^i_k)`, its NIS taken against the particles'
    predicted output covariance plus ``R``. When every weight is zero or not
    finite, the step fails and re-anchors: new particles from
    :math:`N(\hat x, P + P_0)` around the last trusted estimate, weighted by the
    same measurement.
    """

    name = "pf"
    _manifold_aware = True
    _randomised = True

    def __init__(self, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                 P0: ArrayLike, n_particles: int = 1000, resampling: str = "systematic",
                 ess_threshold: float = 0.5, loglik: Callable | None = None,
                 proposal: str = "bootstrap", lower: ArrayLike | None = None,
                 upper: ArrayLike | None = None, seed: int = 0, jit: bool = False,
                 points: str = "cubature", order: int = 3):
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.lower, self.upper = self._bounds(lower, upper)
        bounded = np.isfinite(self.lower).any() or np.isfinite(self.upper).any()
        self._support = (self.lower[:, None], self.upper[:, None]) if bounded else None
        self.n_particles = as_int(n_particles, "n_particles", minimum=2,
                                  expected="an integer >= 2")
        self.resampling = as_choice(resampling, RESAMPLING, "resampling")
        self.ess_threshold = as_float(ess_threshold, "ess_threshold", positive=True,
                                      maximum=1.0, expected="a number in (0, 1]")
        if loglik is not None and not callable(loglik):
            raise TypeError(f"loglik must be a function (y, yhat, p) -> scalar expression "
                            f"or None, got {type(loglik).__name__}")
        self.proposal = as_choice(proposal, PROPOSALS, "proposal")
        self.points, self.order = points, order
        self._rule = proposal_rule(self.proposal, points, order, self.model.ndx)
        seed_ = as_seed(seed)
        self.seed = 0 if seed_ is None else seed_
        self.loglik = loglik
        self.jit = as_bool(jit, "jit")
        self._p = self.model.p.astype(float)
        self._build()
        self._tuning_changed()
        self._reset()

    def _build(self) -> None:
        g = graphs(self.model, self.loglik, self.proposal, self._rule)
        self._weigh, self._advance, self._transit = (
            over_points(f) for f in (g.weigh, g.advance, g.transit))
        self._start = None if g.start is None else over_points(g.start)
        self._trace: list | None = None  # smooth's forward pass: (X, W, w) per sample
        if self.jit:
            self._compile(g)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        for key in ("_weigh", "_advance", "_start", "_transit"):  # built again
            del state[key]
        state["_kernel"] = self._kernel_state()  # (the compiled state, without its library)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        kernel = state.pop("_kernel", None)
        self.__dict__.update(state)
        self._build()
        self._kernel_restore(kernel)

    # ------------------------------------------------------------ tuning
    def _check_tuning(self, new: dict) -> None:
        if getattr(self, "proposal", "bootstrap") != "bootstrap" and "Q" in new:
            definite(new["Q"])

    def _tuning_changed(self) -> None:
        if self.proposal != "bootstrap":
            definite(self.Q)
        self._LQ = square_root(self.Q).ravel(order="F")
        # copies of a particle stay copies only where the transition adds no noise: with
        # a definite Q every particle is distinct after a step, and none need counting
        self._may_collapse = bool(np.linalg.eigvalsh(self.Q)[0] <= 0)
        self._whitening: dict[bytes, tuple[np.ndarray, float, np.ndarray, np.ndarray,
                                           np.ndarray]] = {}

    def _measured(self, observed: np.ndarray
                  ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        """:func:`~estim.estimators.sampling.particle_graphs.measured_tuning`, kept by pattern."""
        key = observed.tobytes()
        if key not in self._whitening:
            self._whitening[key] = measured_tuning(self.Q, self.R, self._LQ, self.proposal,
                                                   observed)
        return self._whitening[key]

    def _reset(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._X: np.ndarray | None = None
        self._W: np.ndarray | None = None  # the weights after the last step (None: equal)
        self._trusted = (self.x0.copy(), None if self.P0 is None else self.P0.copy())
        self._kernel_reset(self.seed)

    # -------------------------------------------------------------- step
    def _step(self, y, u, first):
        m, N, nx = self.model, self.n_particles, self.model.ndx
        observed = ~np.isnan(y)
        w = self._stage_input(u)
        if self._kernel is not None:
            return self._compiled_step(y, w, first)
        WR, const, Ro, tun, miss = self._measured(observed)
        y0 = y if Ro.shape[0] == len(y) else np.where(observed, y, 0.0)
        if (first or self._X is None) and self._start is not None:
            V = self._rng.standard_normal((nx, N))
            X, Yh, ell = self._start(self.x0, V, w, prior_tuning(self.P0, tun), y0, WR, miss, n=N)
        elif first or self._X is None:
            X = draw_about(m, self._rng, self.x0, self.P0, N)
            Yh, ell = self._weigh(X, w, y0, WR, miss, n=N)
        else:
            V = self._rng.standard_normal((nx, N))
            X, Yh, ell = self._advance(self._X, V, w, tun, y0, WR, miss, n=N)
        W, inc, X = _update(X, ell[0], observed, self._constant(const), self._W,
                            self._support)
        if W is None:  # every weight zero or not finite: re-anchor
            return self._anchor_step(y, w, observed)
        return self._settled(y, w, observed, X, Yh, W, inc, "ok")

    def _anchor_step(self, y: np.ndarray, w: np.ndarray, observed: np.ndarray
                     ) -> tuple[np.ndarray, StepInfo]:
        """A step that left no weight: new particles from :math:`N(\\hat x, P + P_0)`
        about the last trusted estimate, weighted by the same measurement."""
        m, N = self.model, self.n_particles
        WR, const, Ro, _, miss = self._measured(observed)
        y0 = y if Ro.shape[0] == len(y) else np.where(observed, y, 0.0)
        x_t, P_t = self._anchor(*self._trusted)
        assert P_t is not None  # (P0 is required)
        X = draw_about(m, self._rng, x_t, P_t, N)
        Yh, ell = self._weigh(X, w, y0, WR, miss, n=N)
        W, inc, X = _update(X, ell[0], observed, self._constant(const), None, self._support)
        status = ("failed: every particle weight is zero or not finite; re-anchored on the "
                  "last trusted estimate with P + P0")
        if W is None:
            W, inc = np.full(N, 1.0 / N), float("nan")
            status += " (no update: the new particles' weights are not finite either)"
        return self._settled(y, w, observed, X, Yh, W, inc, status)

    def _settled(self, y, w, observed, X, Yh, W, inc, status):
        """The step's estimate, status and resampling from the updated particles ``X``,
        their predicted outputs ``Yh`` and weights ``W`` (``status`` "ok" or the
        re-anchoring's failure)."""
        m, N = self.model, self.n_particles
        Ro = self._measured(observed)[2]
        success = status == "ok"
        x_hat, P = _moments(m, X, W)
        ess = effective_sample_size(W)
        if m.manifold.output_angles:  # each predicted output angle moved next to y
            y0 = np.where(observed, y, 0.0)
            Yh = y0[:, None] - m.manifold.output_difference(y0, Yh.T, NP).T
        e, nis = _innovation(y, observed, Yh, self._W, Ro)
        if success:  # the weights' or the cloud's collapse, the measurement's NIS
            status = step_status(ess, nis, int(observed.sum()), N,
                                 distinct_particles(X) if self._may_collapse else N)
        if status == "ok":
            self._trusted = (x_hat, P)
        if self._trace is not None:
            self._trace.append((X, W, w))
        resampled = ess < self.ess_threshold * N or not W.all()
        if resampled:
            X = X[:, resample(W, self.resampling, self._rng)]
        self._X, self._W = X, None if resampled else W
        info = StepInfo._fast(status=status, success=success, P=P, innovation=e, nis=nis)
        info.extra.update(ess=ess, log_likelihood=inc, resampled=bool(resampled))
        return x_hat, info

    @property
    def particles(self) -> tuple[np.ndarray, np.ndarray]:
        """The particles ``(N, nx)`` and their normalised weights ``(N,)`` after the last
        step (equal weights after a resampling); before any step, empty arrays."""
        N = self.n_particles
        if self._X is None:
            return np.empty((0, self.model.nx)), np.empty(0)
        return self._X.T.copy(), np.full(N, 1.0 / N) if self._W is None else self._W.copy()

    # ------------------------------------------------------------ record
    def filter(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None, seed: int | None = None) -> ParticleFilterResult:
        """Filter a whole record (after a :meth:`reset`): what :func:`~estim.replay` gives.

        ``Y (T, ny)`` (NaN where missing) and ``U`` as in :meth:`EKF.filter
        <estim.EKF.filter>`; the sample times ``t (T,)`` are kept in the result (default
        :math:`k\\,\\Delta t`). ``seed``: this call's random numbers instead of the
        constructor's (independent runs of one record: a Monte Carlo over seeds, the
        likelihood estimates of a particle MCMC chain); the filter is left as that run
        left it, and the next :meth:`reset` starts the constructor's stream again.
        Returns a :class:`ParticleFilterResult`.
        """
        if seed is not None:
            return seeded(self, seed, lambda: self.filter(Y, U, t=t))
        if self._kernel is not None:  # the whole record in compiled calls
            X, P, statuses, ess, inc = self._compiled_filter(Y, U)
        else:
            X, P, infos = run_record(self, Y, U)
            inc = np.array([info.extra["log_likelihood"] for info in infos])
            statuses = [info.status for info in infos]
            ess = np.array([info.extra["ess"] for info in infos])
        status = tuple(statuses)
        res = ParticleFilterResult(
            x=X, P=P, ess=ess, log_likelihood=float(inc.sum()), log_likelihood_increments=inc,
            status=status, success=not any(s.startswith("failed") for s in status))
        return stamped(res, self.model, t, fixed_dt=True)

    smooth = _smooth
    set_params = _set_params
    params = property(_params)
    _stage_input = _stage_input
