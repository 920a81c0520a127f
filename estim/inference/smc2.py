r"""SMC²: sequential Monte Carlo over the parameters, each parameter particle with its own
particle filter (Chopin, Jacob & Papaspiliopoulos 2013).

:math:`N_\theta` parameter particles :math:`\theta^i` are drawn from the prior, each
carrying a particle filter of :math:`N_x` particles run in the compiled kernel
(:class:`~estim.ParticleFilter` with ``jit=True``). At every sample :math:`k` each filter
takes one step, and its likelihood increment :math:`\hat p(y_k \mid y_{0:k-1},
\theta^i)` multiplies the parameter particle's weight; the log-evidence estimate is

.. math::
    \log \hat p(y_{0:k}) = \sum_{j \leq k} \log \sum_i \bar\omega^i_{j-1}
    \hat p(y_j \mid y_{0:j-1}, \theta^i),

unbiased for :math:`p(y_{0:k})` on the natural scale. When the parameter particles'
effective sample size falls below ``ess_threshold`` :math:`\cdot N_\theta` they are
resampled (systematic) and moved by PMMH steps (``n_moves`` of them, or until
their acceptance rates add up to one): a Gaussian random walk
of covariance :math:`(2.38^2/d)\,\widehat{\mathrm{Cov}}(\theta)` (the weighted cloud's),
whose likelihood is a new filter over :math:`y_{0:k}`; the filter of an accepted move
replaces the particle's. The moves leave the posterior of :math:`\theta` given
:math:`y_{0:k}` invariant, so the cloud stays a sample of it at every :math:`k`.

References
----------
N. Chopin, P. E. Jacob, O. Papaspiliopoulos, "SMC²: an efficient algorithm for
sequential analysis of state space models", J. R. Stat. Soc. B 75(3), 2013; N. Chopin,
O. Papaspiliopoulos, *An Introduction to Sequential Monte Carlo*, Springer 2020, ch. 18.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from estim._progress import bar
from estim._validate import as_float, as_int, as_seed
from estim.estimators.sampling.particle import ParticleFilter
from estim.inference.likelihood import ParticleLikelihood, run_log_likelihood
from estim.inference.priors import Prior, as_priors
from estim.inference.proposals import log_prior
from estim.solvers.sampling.resampling import effective_sample_size, resample

__all__ = ["SMC2Result", "smc2"]

#: the most PMMH steps per parameter particle at one resampling
MAX_MOVES = 20


@dataclass(frozen=True, repr=False)
class SMC2Result:
    """What :func:`smc2` returns.

    Attributes
    ----------
    names : list of str
        The parameters.
    theta : (n_theta, d) array
        The parameter particles after the last sample, with normalised ``weights``.
    log_evidence : float
        :math:`\\log \\hat p(y_{0:T-1})`; ``log_evidence_increments (T,)`` its terms.
    ess : (T,) array
        The parameter particles' effective sample size after each sample's reweighting.
    moves : list of (int, float)
        The samples where the cloud was resampled and moved, and the acceptance rate of
        its moves there.
    seconds : float
    details : dict
        Settings and the points without likelihood.
    """

    names: list[str]
    theta: np.ndarray
    weights: np.ndarray
    log_evidence: float
    log_evidence_increments: np.ndarray
    ess: np.ndarray
    moves: list[tuple[int, float]]
    seconds: float
    details: dict = field(default_factory=dict)

    def mean(self) -> dict[str, float]:
        """The posterior means (weighted)."""
        m = self.weights @ self.theta
        return dict(zip(self.names, m.tolist(), strict=True))

    def sd(self) -> dict[str, float]:
        """The posterior standard deviations (weighted)."""
        m = self.weights @ self.theta
        v = self.weights @ (self.theta - m) ** 2
        return dict(zip(self.names, np.sqrt(v).tolist(), strict=True))

    def __repr__(self) -> str:
        mean, sd = self.mean(), self.sd()
        acc = [a for _, a in self.moves]
        parts = ", ".join(f"{n} {mean[n]:.4g} +- {sd[n]:.3g}" for n in self.names)
        return (f"SMC2Result({len(self.weights)} parameter particles: {parts}; log-evidence "
                f"{self.log_evidence:.3f}; {len(self.moves)} moves, acceptance "
                f"{np.mean(acc) if acc else float('nan'):.3f}; {self.seconds:.1f} s)")


class _Filters:
    """The parameter particles' filters: each one's kernel data for the whole record
    (rows, prior tuning) and its particles between steps, run one step at a time through
    the filter's kernel."""

    def __init__(self, L: ParticleLikelihood):
        self.L, self.pf = L, L.pf
        self.k = L.pf._kernel
        self.data: list[dict | None] = []
        self.X: list[np.ndarray | None] = []
        self.W: list[np.ndarray | None] = []

    def prepare(self, theta: np.ndarray) -> dict | None:
        """The kernel data of ``theta`` (None where its tuning fails)."""
        L, pf = self.L, self.pf
        if not L.apply(theta):
            return None
        rows = pf._kernel_rows(L.Y, L.W)
        rows["w"] = rows["w"].copy()
        return {"rows": rows, "x0": pf.x0.copy(), "tun0": pf._first_tuning(rows["tun"][0])}

    def step(self, data: dict, X: np.ndarray | None, W: np.ndarray | None, start: int,
             stop: int) -> tuple[float, np.ndarray | None, np.ndarray | None]:
        """Samples ``start:stop`` from particles ``X``, weights ``W`` (None: equal; the
        prior when ``start`` is 0): the log-likelihood of those samples and the particles
        after (``-inf`` and None when no weight is left)."""
        k = self.k
        assert k is not None
        if start:
            assert X is not None
            k.set_particles(X, W)
        value, _ = run_log_likelihood(self.pf, data["rows"], start, stop,
                                      (data["x0"], data["tun0"]))
        if value == -math.inf:
            return value, None, None
        return value, k.X.copy(), None if k.equal else k.W.copy()


def smc2(pf: ParticleFilter, Y: ArrayLike, U: ArrayLike | None = None, *,
         priors: Mapping[str, Prior | Callable], tuning: Callable[[dict], Mapping] | None = None,
         n_theta: int = 500, ess_threshold: float = 0.5, n_moves: int | None = None,
         seed: int = 0,
         t: ArrayLike | None = None, progress: bool | None = None) -> SMC2Result:
    r"""SMC² over the parameters named by ``priors`` (see the module).

    Parameters
    ----------
    pf : ParticleFilter
        The filter of every parameter particle (its ``n_particles`` :math:`N_x`, proposal
        and resampling), built with ``jit=True``.
    Y, U, t, priors, tuning :
        As for :func:`~estim.inference.pmmh`; every prior must be one that can be
        drawn from (the parameter particles start as its draws).
    n_theta : int
        Parameter particles :math:`N_\theta`.
    ess_threshold : float in (0, 1]
        Resample and move the parameter particles when their effective sample size
        falls below this fraction of them.
    n_moves : int, optional
        PMMH steps per parameter particle at each resampling; default: as many as it
        takes for the acceptance rates of the steps to add up to 1 (each particle moved
        once on average), at most :data:`MAX_MOVES`.
    seed : int
        The random numbers (the parameter particles', and the kernel's streams).
    progress : bool, optional
        A progress bar over the samples.
    """
    t0 = time.perf_counter()
    pri = as_priors(priors)
    names = list(pri)
    n_theta = as_int(n_theta, "n_theta", minimum=2)
    n_moves = None if n_moves is None else as_int(n_moves, "n_moves", minimum=1)
    ess_threshold = as_float(ess_threshold, "ess_threshold", positive=True, maximum=1.0)
    seed = as_seed(seed) or 0
    if not isinstance(pf, ParticleFilter):
        raise TypeError(f"pf must be an estim.ParticleFilter, got {type(pf).__name__}")
    if pf._kernel is None:
        raise ValueError("smc2 runs every parameter particle's filter in the compiled "
                         "kernel: build the ParticleFilter with jit=True (on a model the "
                         "kernel can take: Euclidean states, no integrator calls)")
    L = ParticleLikelihood(pf, Y, U, names=names, tuning=tuning, t=t)
    rng = np.random.default_rng(seed)
    pf._kernel.seed(int(rng.integers(2 ** 62)))
    prior_list = [pri[n] for n in names]
    try:
        theta = np.column_stack([p.sample(rng, n_theta) for p in prior_list])
    except NotImplementedError:
        raise ValueError("smc2 starts from draws of the priors: a LogDensity prior "
                         "cannot be drawn from") from None
    d, T = len(names), L.T
    F = _Filters(L)
    data = [F.prepare(th) for th in theta]
    X: list = [None] * n_theta
    Wp: list = [None] * n_theta
    loglik = np.where([dd is None for dd in data], -np.inf, 0.0)
    logw = loglik.copy()
    lp = np.array([log_prior(prior_list, th) for th in theta])
    incs, ess_hist, moves = np.empty(T), np.empty(T), []
    with bar(T, "smc2", "sample", show=progress) as prog:
        for k in range(T):
            inc = np.full(n_theta, -np.inf)
            for i in range(n_theta):
                dd = data[i]
                if dd is None or (k and X[i] is None):
                    continue
                inc[i], X[i], Wp[i] = F.step(dd, X[i], Wp[i], k, k + 1)
            top = logw.max()
            wbar = np.exp(logw - top)
            wbar /= wbar.sum()
            with np.errstate(invalid="ignore"):
                contrib = np.where(wbar > 0, wbar * np.exp(inc - inc.max()), 0.0)
            incs[k] = float(inc.max() + np.log(contrib.sum()))
            loglik = loglik + inc
            logw = logw + inc
            w = np.exp(logw - logw.max())
            w /= w.sum()
            ess_hist[k] = effective_sample_size(w)
            if ess_hist[k] < ess_threshold * n_theta and k + 1 < T:
                idx = resample(w, "systematic", rng)
                theta, loglik, lp = theta[idx], loglik[idx], lp[idx]
                data = [data[i] for i in idx]
                X, Wp = [X[i] for i in idx], [Wp[i] for i in idx]
                logw = np.zeros(n_theta)
                cov = np.atleast_2d(np.cov(theta.T)) * 2.38 ** 2 / d
                cov += 1e-12 * np.eye(d) * max(float(np.mean(np.diag(cov))), 1e-300)
                try:
                    chol = np.linalg.cholesky(cov)
                except np.linalg.LinAlgError:
                    chol = np.diag(np.sqrt(np.maximum(np.diag(cov), 1e-300)))
                accepted, rates = 0, list[float]()
                while len(rates) < MAX_MOVES and (
                        len(rates) < (n_moves or 1) if n_moves else sum(rates) < 1.0):
                    before = accepted
                    for i in range(n_theta):
                        cand = theta[i] + chol @ rng.standard_normal(d)
                        lpc = log_prior(prior_list, cand)
                        if lpc == -math.inf:
                            continue
                        dc = F.prepare(cand)
                        if dc is None:
                            continue
                        llc, Xc, Wc = F.step(dc, None, None, 0, k + 1)
                        if math.log(rng.uniform()) < llc + lpc - loglik[i] - lp[i]:
                            theta[i], loglik[i], lp[i] = cand, llc, lpc
                            data[i], X[i], Wp[i] = dc, Xc, Wc
                            accepted += 1
                    rates.append((accepted - before) / n_theta)
                moves.append((k, float(np.mean(rates))))
            prog.update(1)
    w = np.exp(logw - logw.max())
    w /= w.sum()
    L.restore()
    return SMC2Result(names, theta, w, float(incs.sum()), incs, ess_hist, moves,
                      time.perf_counter() - t0,
                      {"n_theta": n_theta, "n_particles": pf.n_particles,
                       "n_moves": n_moves, "ess_threshold": ess_threshold,
                       "failures": dict(L.failures)})
