r"""Particle Gibbs with ancestor sampling (Lindsten, Jordan & Schön 2014): a Gibbs sampler
over the parameters and the whole state trajectory.

Each iteration alternates two exact conditional moves:

1. **the trajectory given the parameters**, by conditional SMC with ancestor sampling: a
   bootstrap particle filter of :math:`N` particles in which the last particle is
   held to the current trajectory :math:`x^*_{0:T-1}`; the other :math:`N-1` take their
   ancestors from the weights (multinomial) and move by the model, and the held
   particle's ancestor is drawn anew with probabilities
   :math:`\propto W^i_{k-1}\, N(x^*_k;\, F(x^i_{k-1}),\, Q)`, which lets the trajectory
   change over its whole length even with few particles; the new trajectory is one
   traced back from the final weights. The kernel leaves :math:`p(x_{0:T-1} \mid y,
   \theta)` invariant for any :math:`N \geq 2`;
2. **the parameters given the trajectory**: the user's exact draw
   ``update(x, theta, rng)`` from :math:`p(\theta \mid x, y)` (conditionally conjugate
   priors), or ``theta_steps`` random-walk Metropolis steps on the complete-data
   log-density

   .. math::
       \log p(x, y \mid \theta) = \log N(x_0; x_0, P_0) + \sum_{k\geq 1}
       \log N(x_k;\, F(x_{k-1}),\, Q) + \sum_k \ell(y_k \mid x_k)

   plus the log-prior, adapted as :func:`~estim.inference.pmmh`'s proposal (Haario).

The trajectories are kept (thinned to at most ``keep_paths`` per chain) in
``details["paths"]``.

References
----------
F. Lindsten, M. I. Jordan, T. B. Schön, "Particle Gibbs with ancestor sampling", J.
Mach. Learn. Res. 15, 2014; C. Andrieu, A. Doucet, R. Holenstein, "Particle Markov chain
Monte Carlo methods", J. R. Stat. Soc. B 72(3), 2010.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_int, as_seed
from estim._workers import run_tasks
from estim.estimators.sampling.ensembles import square_root
from estim.estimators.sampling.particle import ParticleFilter
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

__all__ = ["complete_log_density", "conditional_smc", "particle_gibbs"]


def _checked(L: ParticleLikelihood) -> None:
    pf = L.pf
    if pf.proposal != "bootstrap" or not pf.model.manifold.euclidean_states:
        raise ValueError("particle_gibbs needs a bootstrap ParticleFilter on a model "
                         "without quaternion or angle states")
    if np.linalg.eigvalsh(pf.Q).min() <= 0:
        raise ValueError("particle_gibbs needs a positive definite Q (the held "
                         "trajectory's ancestors are drawn by the transition density)")


def conditional_smc(L: ParticleLikelihood, ref: np.ndarray | None,
                    rng: np.random.Generator) -> np.ndarray:
    """One conditional SMC sweep with ancestor sampling at the filter's current
    parameters (see the module): the new trajectory ``(T, nx)``; ``ref`` None runs the
    plain filter (the first iteration)."""
    pf = L.pf
    N, T, nx = pf.n_particles, L.T, pf.model.nx
    assert pf.P0 is not None
    LQ = square_root(pf.Q)
    LQi = np.linalg.inv(np.linalg.cholesky(pf.Q))
    X = np.empty((T, nx, N))
    A = np.zeros((T, N), dtype=np.intp)
    logw = np.zeros(N)
    free = N - 1 if ref is not None else N
    for k in range(T):
        y = L.Y[k]
        observed = ~np.isnan(y)
        WR, _, _, _, miss = pf._measured(observed)
        w = L.W[k]
        if k == 0:
            Xk = pf.x0[:, None] + square_root(pf.P0) @ rng.standard_normal((nx, N))
        else:
            Wp = np.exp(logw - logw.max())
            c = np.cumsum(Wp)
            c /= c[-1]
            Wp /= Wp.sum()
            a = np.searchsorted(c, rng.random(free), side="right").clip(0, N - 1)
            Fx = pf._transit(X[k - 1], w, n=N)[0]
            Xk = np.empty((nx, N))
            Xk[:, :free] = Fx[:, a] + LQ @ rng.standard_normal((nx, free))
            A[k, :free] = a  # (multinomial ancestors)
            if ref is not None:  # the held particle's ancestor, drawn anew
                d = LQi @ (ref[k][:, None] - Fx)
                la = np.log(Wp + 1e-300) - 0.5 * (d * d).sum(axis=0)
                ca = np.cumsum(np.exp(la - la.max()))
                A[k, N - 1] = min(int(np.searchsorted(ca, rng.random() * ca[-1],
                                                      side="right")), N - 1)
        if ref is not None:
            Xk[:, N - 1] = ref[k]
        X[k] = Xk
        if observed.any():
            _, ell = pf._weigh(Xk, w, np.where(observed, y, 0.0), WR, miss, n=N)
            logw = np.where(np.isfinite(ell[0]), ell[0], -np.inf)
        else:
            logw = np.zeros(N)
        if not np.isfinite(logw.max()):
            logw = np.zeros(N)  # (no weight left: the step carries no information)
    cf = np.cumsum(np.exp(logw - logw.max()))
    b = min(int(np.searchsorted(cf, rng.random() * cf[-1], side="right")), N - 1)
    path = np.empty((T, nx))
    for k in range(T - 1, -1, -1):
        path[k] = X[k][:, b]
        b = A[k, b]
    return path


def complete_log_density(L: ParticleLikelihood, theta: np.ndarray, x: np.ndarray) -> float:
    r""":math:`\log p(x, y \mid \theta)` of a trajectory ``x (T, nx)`` (see the module;
    ``-inf`` where the tuning fails or ``Q`` is singular)."""
    if not L.apply(theta):
        return -math.inf
    pf = L.pf
    assert pf.P0 is not None
    T, nx = x.shape
    try:
        LQ, L0 = np.linalg.cholesky(pf.Q), np.linalg.cholesky(pf.P0)
    except np.linalg.LinAlgError:
        return -math.inf

    def gaussian(D: np.ndarray, C: np.ndarray) -> float:
        Z = np.linalg.solve(C, D)
        return float(-0.5 * (Z * Z).sum() - D.shape[1] * (np.log(np.diag(C)).sum()
                                                           + 0.5 * nx * math.log(2 * math.pi)))

    total = gaussian((x[0] - pf.x0)[:, None], L0)
    if T > 1:
        Fx = pf._transit(x[:-1].T, L.W[1:].T, n=T - 1)[0]
        total += gaussian(x[1:].T - Fx, LQ)
    observed = ~np.isnan(L.Y)
    patterns, which = np.unique(observed, axis=0, return_inverse=True)
    for j, obs in enumerate(patterns):
        if not obs.any():
            continue
        rows = np.flatnonzero(which.ravel() == j)
        WR, const, _, _, miss = pf._measured(obs)
        Y0 = np.where(obs, L.Y[rows], 0.0)
        _, ell = pf._weigh(x[rows].T, L.W[rows].T, Y0.T, WR, miss, n=len(rows))
        total += float(ell[0].sum()) + pf._constant(const) * len(rows)
    return total if math.isfinite(total) else -math.inf


def _chain(L: ParticleLikelihood, priors: Sequence[Prior], start: np.ndarray,
           cov0: np.ndarray, n_iter: int, update: Callable | None, theta_steps: int,
           adapt_start: int, keep_paths: int, seed: np.random.SeedSequence) -> dict:
    rng = np.random.default_rng(seed)
    d = len(start)
    theta = start.copy()
    prop = Proposal(cov0, "haario", adapt_start)
    draws, ll, lp = np.empty((n_iter, d)), np.empty(n_iter), np.empty(n_iter)
    acc = np.zeros(n_iter, dtype=bool)
    every = max(1, n_iter // keep_paths)
    paths = []
    L.apply(theta)
    x = conditional_smc(L, None, rng)
    for i in range(n_iter):
        if i:  # the trajectory given theta, then theta given the trajectory
            L.apply(theta)
            x = conditional_smc(L, x, rng)
            if update is not None:
                new = update(x.copy(), L.dict(theta), rng)
                theta = np.array([float(new[n]) for n in L.names])
                acc[i] = True
                ell = complete_log_density(L, theta, x)
            else:
                lpr = log_prior(priors, theta)
                ell = complete_log_density(L, theta, x)
                for _ in range(theta_steps):
                    cand = theta + prop.L @ rng.standard_normal(d)
                    lpc = log_prior(priors, cand)
                    if lpc == -math.inf:
                        continue
                    ellc = complete_log_density(L, cand, x)
                    if math.log(rng.uniform()) < ellc + lpc - ell - lpr:
                        theta, ell, lpr, acc[i] = cand, ellc, lpc, True
                prop.update(theta)
        else:
            acc[i] = True
            ell = complete_log_density(L, theta, x)
        draws[i], lp[i], ll[i] = theta, log_prior(priors, theta), ell
        if i % every == 0:
            paths.append(x)
    return {"draws": draws, "ll": ll, "lp": lp, "acc": acc, "paths": np.array(paths),
            "cov": prop.cov, "failures": dict(L.failures)}


def particle_gibbs(pf: ParticleFilter, Y: ArrayLike, U: ArrayLike | None = None, *,
                   priors: Mapping[str, Prior | Callable],
                   tuning: Callable[[dict], Mapping] | None = None,
                   update: Callable[[np.ndarray, dict, np.random.Generator], Mapping]
                   | None = None,
                   start: Mapping[str, float] | Sequence[Mapping[str, float]] | None = None,
                   n_iter: int = 2000, n_chains: int = 4, warmup: int | None = None,
                   proposal: Any = None, theta_steps: int = 1, adapt_start: int | None = None,
                   keep_paths: int = 1000, seed: int = 0, n_jobs: int = 1,
                   backend: str = "loky", t: ArrayLike | None = None) -> Posterior:
    r"""Particle Gibbs with ancestor sampling (see the module).

    Parameters
    ----------
    pf : ParticleFilter
        A bootstrap filter with a positive definite ``Q``; its ``n_particles`` (a few
        dozen often suffice: the ancestor sampling keeps the chain moving).
    Y, U, t, priors, tuning, start, n_iter, n_chains, warmup, seed, n_jobs, backend :
        As for :func:`~estim.inference.pmmh`.
    update : callable, optional
        ``update(x (T, nx), theta: dict, rng) -> dict``: an exact draw of all the
        parameters given the trajectory and the data (conditionally conjugate priors).
        Default: ``theta_steps`` adaptive random-walk Metropolis steps on the
        complete-data log-density (``proposal`` and ``adapt_start`` as for PMMH).
    keep_paths : int
        Trajectories kept per chain (thinned evenly), in ``details["paths"]``
        ``(chains, kept, T, nx)``.

    Returns
    -------
    Posterior
        The parameters' chains (``log_likelihood``: the complete-data log-density of
        each state; ``accepted``: the parameters' moves) and the trajectories.
    """
    t0 = time.perf_counter()
    pri = as_priors(priors)
    names = list(pri)
    n_iter, n_chains, warmup, adapt_start = chain_settings(n_iter, n_chains, warmup,
                                                           adapt_start, len(names))
    theta_steps = as_int(theta_steps, "theta_steps", minimum=1)
    keep_paths = as_int(keep_paths, "keep_paths", minimum=1)
    if update is not None and not callable(update):
        raise TypeError(f"update must be a function (x, theta, rng) -> dict or None, got "
                        f"{type(update).__name__}")
    if not isinstance(pf, ParticleFilter):
        raise TypeError(f"pf must be an estim.ParticleFilter, got {type(pf).__name__}")
    L = ParticleLikelihood(pf, Y, U, names=names, tuning=tuning, t=t)
    _checked(L)
    seed = as_seed(seed) or 0
    ss = np.random.SeedSequence(seed)
    starts = chain_starts(start, names, pri, n_chains,
                          np.random.default_rng(ss.spawn(1)[0]))
    prior_list = [pri[n] for n in names]
    cov0 = initial_covariance(proposal, names, prior_list, starts[0])
    tasks = [(L, prior_list, starts[c], cov0, n_iter, update, theta_steps, adapt_start,
              keep_paths, s) for c, s in enumerate(ss.spawn(n_chains + 1)[1:])]
    out = run_tasks(_chain, tasks, n_jobs=as_int(n_jobs, "n_jobs", minimum=1),
                    backend=backend)
    L.restore()
    details = {"n_particles": pf.n_particles, "theta_steps": theta_steps,
               "update": "exact (user)" if update is not None else "random-walk Metropolis",
               "paths": np.stack([o["paths"] for o in out]),
               "final_proposal": [o["cov"] for o in out],
               "failures": [o["failures"] for o in out]}
    return Posterior(names, np.stack([o["draws"] for o in out]),
                     np.stack([o["ll"] for o in out]), np.stack([o["lp"] for o in out]),
                     np.stack([o["acc"] for o in out]), warmup,
                     "particle Gibbs with ancestor sampling", time.perf_counter() - t0,
                     details, L)
