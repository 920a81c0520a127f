"""What the chains of :mod:`estim.inference` share: the log-prior of a point, the
random walk's initial covariance and its adaptation, and the chains' starts (see
:func:`~estim.inference.pmmh` for the rules)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np

from estim._validate import as_float, as_int
from estim.inference.priors import Prior, check_start

__all__ = ["ChainSettings", "Proposal", "chain_settings", "chain_starts",
           "initial_covariance", "log_prior"]


def log_prior(priors: Sequence[Prior], theta: np.ndarray) -> float:
    total = 0.0
    for prior, value in zip(priors, theta, strict=True):
        total += prior.logpdf(value)
        if total == -math.inf:
            break
    return total


class Proposal:
    """The random walk's covariance and its adaptation (see the module)."""

    def __init__(self, cov0: np.ndarray, adapt: str | None, start: int):
        d = len(cov0)
        self.d, self.adapt, self.start = d, adapt, start
        self.sd2 = 2.38 ** 2 / d
        self.L = np.linalg.cholesky(cov0)
        self.eps = 1e-10 * float(np.mean(np.diag(cov0)))
        self.t, self.mu, self.S = 0, np.zeros(d), np.zeros((d, d))
        if adapt == "vanishing":
            self.S = cov0.copy()
            self.L = math.sqrt(self.sd2) * np.linalg.cholesky(cov0)

    def update(self, theta: np.ndarray) -> None:
        self.t += 1
        t = self.t
        if self.adapt == "haario":  # the running mean and covariance of theta_0..t-1
            delta = theta - self.mu
            self.mu = self.mu + delta / t
            self.S = self.S + np.outer(delta, theta - self.mu)
            if t > self.start:
                C = self.sd2 * (self.S / (t - 1) + self.eps * np.eye(self.d))
                try:
                    self.L = np.linalg.cholesky(C)
                except np.linalg.LinAlgError:
                    pass
        elif self.adapt == "vanishing":
            g = (1.0 / t) ** 0.6
            if t == 1:
                self.mu = theta.copy()
            self.mu = (1 - g) * self.mu + g * theta
            dv = theta - self.mu
            self.S = (1 - g) * self.S + g * np.outer(dv, dv)
            try:
                self.L = math.sqrt(self.sd2) * np.linalg.cholesky(self.S)
            except np.linalg.LinAlgError:
                self.L = 1e-3 * np.eye(self.d)

    @property
    def cov(self) -> np.ndarray:
        return self.L @ self.L.T


def initial_covariance(proposal: object, names: list[str], priors: Sequence[Prior],
                start: np.ndarray) -> np.ndarray:
    """The initial proposal covariance: a matrix, per-parameter standard deviations
    (a number or ``{name: sd}``), or by default a tenth of each prior's spread (its
    interquartile range / 1.349 from draws; ``|start|/10`` or 0.1 where it cannot be
    drawn), checked."""
    d = len(names)
    if proposal is None:
        sds = []
        rng = np.random.default_rng(0)
        for prior, s in zip(priors, start, strict=True):
            try:
                q = np.quantile(prior.sample(rng, 4000), [0.25, 0.75])
                sds.append(0.1 * (q[1] - q[0]) / 1.349)
            except NotImplementedError:
                sds.append(0.1 * max(abs(s), 1.0))
        return np.diag(np.square(sds))
    if isinstance(proposal, Mapping):
        unknown = [k for k in proposal if k not in names]
        if unknown:
            raise ValueError(f"proposal: {unknown} have no prior (parameters: {names})")
        missing = [k for k in names if k not in proposal]
        if missing:
            raise ValueError(f"proposal: no standard deviation for {missing}")
        sd = np.array([as_float(proposal[k], f"proposal[{k!r}]") for k in names])
    else:
        arr = np.asarray(proposal, float) if not isinstance(proposal, str) else None
        if arr is None or arr.ndim not in (0, 2):
            raise TypeError(f"proposal must be a standard deviation, a dict of them by "
                            f"parameter or a ({d}, {d}) covariance matrix, got {proposal!r}")
        if arr.ndim == 2:
            if arr.shape != (d, d) or not np.isfinite(arr).all() or \
                    not np.allclose(arr, arr.T) or np.linalg.eigvalsh(arr).min() <= 0:
                raise ValueError(f"proposal: a covariance matrix must be ({d}, {d}), "
                                 f"symmetric and positive definite (a zero scale never "
                                 f"moves the chain)")
            return arr.copy()
        sd = np.full(d, float(arr))
    if not np.all(np.isfinite(sd)) or np.any(sd <= 0):
        raise ValueError(f"proposal: the standard deviations must be positive and finite, "
                         f"got {dict(zip(names, sd.tolist(), strict=True))} (a zero scale "
                         f"never moves the chain)")
    return np.diag(sd ** 2)


def chain_starts(start: object, names: list[str], priors: dict[str, Prior], n_chains: int,
            rng: np.random.Generator) -> list[np.ndarray]:
    """Each chain's start: given (one dict for all, or one per chain), or drawn from the
    priors; checked inside their support."""
    if start is None:
        out = []
        for _ in range(n_chains):
            point = {}
            for n in names:
                try:
                    point[n] = float(priors[n].sample(rng, 1)[0])
                except NotImplementedError:
                    raise ValueError(f"start: give a start for {n!r} (its prior "
                                     f"{priors[n]!r} cannot be drawn from)") from None
            out.append(point)
    elif isinstance(start, Mapping):
        out = [dict(start)] * n_chains
    elif isinstance(start, Sequence) and len(start) == n_chains and \
            all(isinstance(s, Mapping) for s in start):
        out = [dict(s) for s in start]
    else:
        raise TypeError(f"start must be a dict of parameter values, a list of {n_chains} "
                        f"such dicts (one per chain) or None (drawn from the priors), got "
                        f"{type(start).__name__}")
    for point in out:
        check_start(priors, point)
    return [np.array([float(p[n]) for n in names]) for p in out]


class ChainSettings(NamedTuple):
    """The checked lengths of a run of chains."""

    n_iter: int
    n_chains: int
    warmup: int
    adapt_start: int


def chain_settings(n_iter: object, n_chains: object, warmup: object, adapt_start: object,
                   d: int) -> ChainSettings:
    """``n_iter`` (at least 2), ``n_chains``, ``warmup`` (default ``n_iter // 4``, leaving
    draws) and ``adapt_start`` (default ``max(100, 10 d)``), checked by name."""
    n = as_int(n_iter, "n_iter", minimum=2)
    chains = as_int(n_chains, "n_chains", minimum=1)
    warm = n // 4 if warmup is None else as_int(warmup, "warmup", minimum=0)
    if warm >= n - 1:
        raise ValueError(f"warmup must leave draws: {warm} of n_iter {n}")
    start = max(100, 10 * d) if adapt_start is None else \
        as_int(adapt_start, "adapt_start", minimum=2)
    return ChainSettings(n, chains, warm, start)
