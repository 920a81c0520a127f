r"""Particle marginal Metropolis-Hastings: Markov chains over a model's parameters whose
likelihood is the particle filter's unbiased estimate (Andrieu, Doucet & Holenstein 2010).

From the chain's state :math:`(\theta, \hat\ell)` a random walk proposes
:math:`\theta' = \theta + L\varepsilon`, :math:`\varepsilon \sim N(0, I)`; a
:math:`\theta'` outside the priors' support is rejected at once, otherwise the particle
filter estimates :math:`\hat\ell' = \log\hat p(y \mid \theta')` with new random numbers
and the move is accepted with probability

.. math::
    \min\Bigl(1,\ \exp\bigl(\hat\ell' + \log p(\theta') - \hat\ell - \log p(\theta)
    \bigr)\Bigr).

The estimate is kept with its point (never estimated again there), which makes the
chain's stationary distribution the exact posterior :math:`p(\theta \mid y)` whatever the
number of particles; fewer particles only make the chain stickier. The spread of
:math:`\hat\ell` decides how sticky: about 1 to 1.7 is efficient (Doucet, Pitt,
Deligiannidis & Kohn 2015), above 3 the chain can stay for hundreds of iterations where
an over-estimate put it. :func:`pmmh` measures that spread at the start and at the
posterior mean and warns beyond :data:`STICKY_SD`.

The proposal's covariance :math:`LL^\top` is adapted from the chain's own history:

* ``adapt="haario"`` (Haario, Saksman & Tamminen 2001): after ``adapt_start``
  iterations, :math:`s_d\,(\widehat{\mathrm{Cov}}(\theta_{0:t}) + \epsilon I)`,
  :math:`s_d = 2.38^2/d`;
* ``adapt="vanishing"`` (Andrieu & Thoms 2008): :math:`\mu_t = \mu_{t-1} +
  \gamma_t(\theta_t - \mu_{t-1})`, :math:`\Sigma_t = (1-\gamma_t)\Sigma_{t-1} +
  \gamma_t(\theta_t - \mu_t)(\theta_t - \mu_t)^\top`, :math:`\gamma_t = (t+1)^{-0.6}`,
  from the first iteration, the proposal :math:`(2.38^2/d)\,\Sigma_t` (the scheme of the
  ``particles`` library's PMMH);
* ``adapt=None``: the initial covariance throughout.

``correlation`` :math:`\rho > 0` runs the correlated pseudo-marginal chain
(:mod:`estim.inference.likelihood`): the auxiliary normals move by
:math:`z' = \rho z + \sqrt{1-\rho^2}\varepsilon` with each proposal, so the two estimates'
errors largely cancel in the ratio.

Chains run in parallel through the engine of :func:`~estim.compare`
(:mod:`estim._workers`: joblib processes, or a dask cluster).

References
----------
C. Andrieu, A. Doucet, R. Holenstein, "Particle Markov chain Monte Carlo methods",
J. R. Stat. Soc. B 72(3), 2010; H. Haario, E. Saksman, J. Tamminen, "An adaptive
Metropolis algorithm", Bernoulli 7(2), 2001; C. Andrieu, J. Thoms, "A tutorial on
adaptive MCMC", Statistics and Computing 18(4), 2008; A. Doucet, M. K. Pitt, G.
Deligiannidis, R. Kohn, "Efficient implementation of Markov chain Monte Carlo when using
an unbiased likelihood estimator", Biometrika 102(2), 2015; G. Deligiannidis, A. Doucet,
M. K. Pitt, "The correlated pseudo-marginal method", J. R. Stat. Soc. B 80(5), 2018.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._progress import bar
from estim._validate import as_choice, as_float, as_int, as_seed
from estim._workers import run_tasks
from estim.estimators.sampling.particle import ParticleFilter
from estim.exceptions import EstimationWarning
from estim.inference.likelihood import ParticleLikelihood
from estim.inference.posterior import Posterior
from estim.inference.priors import Prior, as_priors
from estim.inference.proposals import (
    Proposal,
    chain_settings,
    chain_starts,
    initial_covariance,
    log_prior,
)

__all__ = ["pmmh"]

#: the log-likelihood estimate's standard deviation beyond which chains stick (warned)
STICKY_SD = 3.0
#: the runs of the filter that measure that spread
SPREAD_RUNS = 20


class ExactLikelihood:
    """A user's exact log-likelihood ``fn(theta: dict) -> float`` as a chain calls it."""

    def __init__(self, fn: Callable[[dict], float], names: Sequence[str]):
        self.fn, self.names = fn, list(names)
        self.failures: dict[str, Any] = {"not finite": 0}

    def __call__(self, theta: np.ndarray, seed: int) -> float:
        value = float(self.fn(dict(zip(self.names, theta.tolist(), strict=True))))
        if not math.isfinite(value):
            self.failures["not finite"] += 1
            return -math.inf
        return value


def _chain(target: Any, priors: Sequence[Prior], start: np.ndarray, cov0: np.ndarray,
           n_iter: int, adapt: str | None, adapt_start: int, correlation: float,
           seed: np.random.SeedSequence, show: bool | None) -> dict:
    """One chain (a worker's task): its states, log-likelihoods, log-priors, accepted
    moves, final proposal covariance and the target's failures."""
    rng = np.random.default_rng(seed)
    d = len(start)
    theta = np.asarray(start, float).copy()
    prop = Proposal(cov0, adapt, adapt_start)
    draws, ll, lp = np.empty((n_iter, d)), np.empty(n_iter), np.empty(n_iter)
    acc = np.zeros(n_iter, dtype=bool)
    cpm = correlation > 0
    keep = math.sqrt(1.0 - correlation ** 2)
    if cpm:
        z = rng.standard_normal(target.auxiliary_size())
        ell = target.correlated(theta, z)
    else:
        ell = target(theta, int(rng.integers(2 ** 62)))
    lpr = log_prior(priors, theta)
    draws[0], ll[0], lp[0], acc[0] = theta, ell, lpr, True
    with bar(n_iter - 1, "pmmh", "iteration", show=show) as progress:
        for i in range(1, n_iter):
            cand = theta + prop.L @ rng.standard_normal(d)
            lpc = log_prior(priors, cand)
            if lpc > -math.inf:
                if cpm:
                    zc = correlation * z + keep * rng.standard_normal(z.shape)
                    ellc = target.correlated(cand, zc)
                else:
                    ellc = target(cand, int(rng.integers(2 ** 62)))
                log_ratio = ellc + lpc - ell - lpr
                if ell == -math.inf:  # (a start without likelihood: any move out of it)
                    log_ratio = math.inf if ellc > -math.inf else -math.inf
                if math.log(rng.uniform()) < log_ratio:
                    theta, ell, lpr, acc[i] = cand, ellc, lpc, True
                    if cpm:
                        z = zc
            draws[i], ll[i], lp[i] = theta, ell, lpr
            if adapt is not None:
                prop.update(theta)
            progress.update(1)
    return {"draws": draws, "ll": ll, "lp": lp, "acc": acc, "cov": prop.cov,
            "failures": dict(target.failures)}


def _spread(target: Any, theta: np.ndarray, correlation: float, seed: int) -> float:
    r"""The standard deviation of the log-likelihood estimate at ``theta`` over
    :data:`SPREAD_RUNS` runs (with ``correlation``: of the difference of two estimates
    whose auxiliary normals are that correlated, what the acceptance ratio sees, over
    :data:`SPREAD_RUNS` pairs, divided by :math:`\sqrt 2` to compare with the plain
    estimate's)."""
    rng = np.random.default_rng(seed)
    if correlation > 0:
        keep = math.sqrt(1 - correlation ** 2)
        diffs = []
        for _ in range(SPREAD_RUNS):
            z = rng.standard_normal(target.auxiliary_size())
            z2 = correlation * z + keep * rng.standard_normal(z.shape)
            diffs.append(target.correlated(theta, z2) - target.correlated(theta, z))
        return float(np.std(diffs, ddof=1) / math.sqrt(2))
    values = [target(theta, int(rng.integers(2 ** 62))) for _ in range(SPREAD_RUNS)]
    return float(np.std(values, ddof=1))


def pmmh(pf: ParticleFilter | Callable[[dict], float], Y: ArrayLike | None = None,
         U: ArrayLike | None = None, *, priors: Mapping[str, Prior | Callable],
         tuning: Callable[[dict], Mapping] | None = None,
         start: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
         n_iter: int = 5000, n_chains: int = 4, warmup: int | None = None,
         proposal: Any = None, adapt: str | None = "haario", adapt_start: int | None = None,
         correlation: float = 0.0, seed: int = 0, n_jobs: int = 1, backend: str = "loky",
         t: ArrayLike | None = None, progress: bool | None = None) -> Posterior:
    r"""Particle marginal Metropolis-Hastings chains over the parameters (see the module).

    Parameters
    ----------
    pf : ParticleFilter or callable
        The particle filter that estimates the likelihood (its particles, proposal and
        resampling; ``jit=True`` runs each estimate in one compiled call), or an exact
        log-likelihood ``fn(theta: dict) -> float`` (a Kalman filter's on a linear
        model: then ``Y`` is not used).
    Y, U, t :
        The record, as for :meth:`ParticleFilter.filter <estim.ParticleFilter.filter>`.
    priors : dict
        ``{name: prior}`` (:mod:`estim.inference.priors`, or a log-density function):
        the parameters, in this order. Names of the model's parameters set them
        (:meth:`~estim.ParticleFilter.set_params`); others only reach ``tuning``.
    tuning : callable, optional
        ``tuning(theta: dict) -> dict`` with some of ``"Q"``, ``"R"``, ``"x0"``, ``"P0"``:
        the noise covariances and the prior as functions of the parameters.
    start : dict, list of dict or None
        Each chain's first point (one dict for all, or one per chain); default: drawn
        from the priors. Refused outside the priors' support.
    n_iter, n_chains, warmup : int
        Iterations per chain (the start included), chains, and the iterations of each
        chain left out of the summaries (default ``n_iter // 4``).
    proposal : float, dict, (d, d) array or None
        The random walk's initial covariance (see :func:`initial_covariance`): standard
        deviations (one for all, or by name) or a covariance matrix; default a tenth of
        each prior's spread.
    adapt : {"haario", "vanishing", None}
        The adaptation of the proposal (see the module). ``adapt_start``: the iterations
        before Haario's adaptation starts (default ``max(100, 10 d)``).
    correlation : float in [0, 1)
        :math:`\rho` of the correlated pseudo-marginal method (0: independent estimates;
        0.99 or more with few particles). Runs the filter's Functions in numpy.
    seed : int
        The chains' random numbers (their own streams, spawned from it); the same seed
        gives the same chains on any number of workers.
    n_jobs, backend :
        Workers for the chains, as :func:`~estim.compare` takes them.
    progress : bool, optional
        A progress bar per chain run in this process (``n_jobs=1``); default: shown on a
        terminal or in Jupyter once a chain lasts a few seconds (:mod:`estim._progress`).

    Returns
    -------
    Posterior
        The chains and their diagnostics (``details``: the settings, the spread of the
        log-likelihood estimate at the start and at the posterior mean, the final
        proposal covariances, the points without likelihood).

    Warns
    -----
    EstimationWarning
        The log-likelihood estimate's standard deviation above :data:`STICKY_SD` at the
        start or at the posterior mean (too few particles: the chains stick), an
        acceptance rate below 2 % after the warm-up, or :math:`\hat R > 1.05`.
    """
    t0 = time.perf_counter()
    pri = as_priors(priors)
    names = list(pri)
    n_iter, n_chains, warmup, adapt_start = chain_settings(n_iter, n_chains, warmup,
                                                           adapt_start, len(names))
    adapt = None if adapt is None else as_choice(adapt, ("haario", "vanishing"), "adapt")
    correlation = as_float(correlation, "correlation", minimum=0.0, maximum=1.0)
    if correlation >= 1.0:
        raise ValueError("correlation must be below 1 (1 never renews the random numbers)")
    seed = as_seed(seed) or 0
    n_jobs = as_int(n_jobs, "n_jobs", minimum=1)
    if isinstance(pf, ParticleFilter):
        if Y is None:
            raise ValueError("Y: the record is required with a particle filter")
        target: Any = ParticleLikelihood(pf, Y, U, names=names, tuning=tuning, t=t)
        method = "PMMH" + (f", correlated (rho = {correlation:g})" if correlation else "")
    elif callable(pf):
        if correlation:
            raise ValueError("correlation needs a particle filter (an exact likelihood has "
                             "no random numbers to correlate)")
        target, method = ExactLikelihood(pf, names), "Metropolis-Hastings (exact likelihood)"
    else:
        raise TypeError(f"pf must be an estim.ParticleFilter or a log-likelihood function "
                        f"theta -> float, got {type(pf).__name__}")
    ss = np.random.SeedSequence(seed)
    starts = chain_starts(start, names, pri, n_chains,
                          np.random.default_rng(ss.spawn(1)[0]))
    prior_list = [pri[n] for n in names]
    cov0 = initial_covariance(proposal, names, prior_list, starts[0])
    details: dict[str, Any] = {"n_particles": getattr(pf, "n_particles", None),
                               "adapt": adapt, "adapt_start": adapt_start,
                               "correlation": correlation, "proposal": cov0}
    particle = isinstance(target, ParticleLikelihood)
    if particle:  # too few particles: the estimate's spread at the start
        sd0 = _spread(target, starts[0], correlation, seed)
        details["loglik_sd_start"] = sd0
        if sd0 > STICKY_SD:
            warnings.warn(_sticky("the start", sd0, correlation, target.pf.n_particles),
                          EstimationWarning, stacklevel=2)
    show = progress if n_jobs == 1 else False  # (workers' bars would garble)
    tasks = [(target, prior_list, starts[c], cov0, n_iter, adapt, adapt_start, correlation,
              s, show) for c, s in enumerate(ss.spawn(n_chains + 1)[1:])]
    out = run_tasks(_chain, tasks, n_jobs=n_jobs, backend=backend)
    details["final_proposal"] = [o["cov"] for o in out]
    details["failures"] = [o["failures"] for o in out]
    post = Posterior(names, np.stack([o["draws"] for o in out]),
                     np.stack([o["ll"] for o in out]), np.stack([o["lp"] for o in out]),
                     np.stack([o["acc"] for o in out]), warmup, method,
                     time.perf_counter() - t0, details, target if particle else None)
    _diagnose(post, target, correlation, seed)
    if particle:
        target.restore()
    return post


def _sticky(where: str, sd: float, correlation: float, n: int) -> str:
    what = "the difference of correlated estimates" if correlation else "the estimate"
    more = int(math.ceil(n * (sd / 1.5) ** 2))
    return (f"pmmh: the log-likelihood estimate is too noisy at {where}: the standard "
            f"deviation of {what} is {sd:.2f} (over {SPREAD_RUNS} runs; efficient chains "
            f"need about 1 to 1.7, above {STICKY_SD:g} they stick for hundreds of "
            f"iterations). Use more particles (about {more} instead of {n}), a better "
            f"proposal (proposal='ekf'), or correlation=0.99")


def _diagnose(post: Posterior, target: Any, correlation: float, seed: int) -> None:
    """The spread at the posterior mean, the acceptance and R-hat: warned when they say
    the chains cannot be trusted."""
    if isinstance(target, ParticleLikelihood):
        mean = np.array(list(post.mean().values()))
        if target.apply(mean):
            sd = _spread(target, mean, correlation, seed + 1)
            post.details["loglik_sd"] = sd
            if sd > STICKY_SD:
                warnings.warn(_sticky("the posterior mean", sd, correlation,
                                      target.pf.n_particles), EstimationWarning,
                              stacklevel=3)
    acc = post.acceptance
    if acc.min() < 0.02:
        warnings.warn(f"pmmh: chain(s) {np.flatnonzero(acc < 0.02).tolist()} accepted "
                      f"below 2 % of their moves after the warm-up ({acc.min():.3f}): they "
                      f"barely move; the summaries are not to be trusted", EstimationWarning,
                      stacklevel=3)
    if post.draws.shape[0] > 1:
        worst = max(post.rhat().items(), key=lambda kv: kv[1])
        if worst[1] > 1.05:
            warnings.warn(f"pmmh: the chains disagree: R-hat of {worst[0]} is "
                          f"{worst[1]:.3f} (> 1.05): run longer chains or check for "
                          f"several modes", EstimationWarning, stacklevel=3)
