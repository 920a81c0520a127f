r"""Convergence diagnostics of Markov chains: the rank-normalised split :math:`\hat R` and
the bulk effective sample size (Vehtari, Gelman, Simpson, Carpenter & Bürkner 2021).

For ``M`` chains of ``N`` draws of one quantity, each chain is split in halves (``2M``
chains of :math:`n = \lfloor N/2 \rfloor`; a trend within a chain then shows as
disagreement between its halves), and the draws are replaced by their normal scores
:math:`z = \Phi^{-1}((r - 3/8)/(S + 1/4))` (:math:`r` the rank among all :math:`S` draws;
robust to heavy tails). With the between- and within-chain variances
:math:`B = \frac{n}{2M - 1}\sum_m (\bar z_m - \bar z)^2`,
:math:`W = \frac{1}{2M}\sum_m s_m^2` and
:math:`\widehat{\mathrm{var}}^+ = \frac{n-1}{n} W + \frac{B}{n}`:

* :math:`\hat R = \max(\hat R_\text{bulk}, \hat R_\text{folded})`,
  :math:`\hat R_\cdot = \sqrt{\widehat{\mathrm{var}}^+ / W}`, the folded one of the scores
  of :math:`|\theta - \operatorname{median}\theta|` (differences in spread); chains that
  agree give :math:`\hat R \approx 1`, and 1.01 is the usual limit;
* the bulk effective sample size :math:`S_\text{eff} = 2Mn / \hat\tau`,
  :math:`\hat\tau = -1 + 2\sum_t \hat\rho_t` over Geyer's initial positive and
  monotone sequence of the paired autocorrelations :math:`\hat\rho_t + \hat\rho_{t+1}`,
  :math:`\hat\rho_t = 1 - (W - \bar\gamma_t)/\widehat{\mathrm{var}}^+`,
  :math:`\bar\gamma_t` the chains' mean autocovariance at lag :math:`t` (by FFT), as
  Stan's reference manual states it, bounded by :math:`2Mn \log_{10}(2Mn)`.

References
----------
A. Vehtari, A. Gelman, D. Simpson, B. Carpenter, P.-C. Bürkner, "Rank-normalization,
folding, and localization: an improved R-hat for assessing convergence of MCMC",
Bayesian Analysis 16(2), 2021; C. J. Geyer, "Practical Markov chain Monte Carlo",
Statistical Science 7(4), 1992.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["ess", "rhat"]


def _chains(draws: ArrayLike) -> np.ndarray:
    """``(M, N)`` chains of one quantity, checked, split in halves: ``(2M, N // 2)``."""
    x = np.asarray(draws, dtype=float)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2:
        raise ValueError(f"draws must be (chains, draws) of one quantity, got shape {x.shape}")
    if x.shape[1] < 4:
        raise ValueError(f"draws: each chain needs at least 4 draws, got {x.shape[1]}")
    if not np.isfinite(x).all():
        raise ValueError("draws must be finite")
    n = x.shape[1] // 2
    return np.concatenate([x[:, :n], x[:, x.shape[1] - n:]])


def _scores(x: np.ndarray) -> np.ndarray:
    """The normal scores of the draws' ranks (ties averaged)."""
    from scipy import stats  # ~0.4 s to import: on first use, not with estim.testing

    r = stats.rankdata(x, method="average").reshape(x.shape)
    return stats.norm.ppf((r - 0.375) / (x.size + 0.25))


def _variances(z: np.ndarray) -> tuple[float, float]:
    """``(W, var+)`` of split chains ``z (m, n)``."""
    m, n = z.shape
    W = float(z.var(axis=1, ddof=1).mean())
    B = n * float(z.mean(axis=1).var(ddof=1)) if m > 1 else 0.0
    return W, (n - 1) / n * W + B / n


def rhat(draws: ArrayLike) -> float:
    r"""The rank-normalised split :math:`\hat R` of chains ``(M, N)`` of one quantity (see
    the module): about 1 when the chains agree; beyond 1.01 they have not mixed. NaN
    when every draw is the same."""
    x = _chains(draws)
    if np.ptp(x) == 0:
        return float("nan")
    out = []
    for y in (x, np.abs(x - np.median(x))):
        W, var = _variances(_scores(y))
        out.append(np.sqrt(var / W) if W > 0 else np.inf)
    return float(max(out))


def ess(draws: ArrayLike) -> float:
    """The bulk effective sample size of chains ``(M, N)`` of one quantity (see the
    module): the number of independent draws with the same precision of the mean."""
    z = _scores(_chains(draws))
    m, n = z.shape
    W, var = _variances(z)
    if not W > 0:
        return float("nan")
    d = z - z.mean(axis=1, keepdims=True)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    f = np.fft.rfft(d, size, axis=1)
    acov = np.fft.irfft(f * np.conj(f), size, axis=1)[:, :n].mean(axis=0) / n  # biased
    rho = np.zeros(n)
    rho[0] = 1.0

    def lag(t: int) -> float:
        return float(1 - (W - acov[t]) / var)

    rho[1] = lag(1)
    # Geyer's initial positive sequence: the pairs (rho_{t+1}, rho_{t+2}) while positive
    t, last_even, pair = 1, 1.0, 1.0 + rho[1]
    while t < n - 3 and pair > 0:
        last_even, odd = lag(t + 1), lag(t + 2)
        pair = last_even + odd
        if pair >= 0:
            rho[t + 1], rho[t + 2] = last_even, odd
        t += 2
    max_t = t - 2
    if last_even > 0:  # the first even lag beyond the sequence, once
        rho[max_t + 1] = last_even
    # and monotone: no pair above the one before it
    for t in range(1, max_t - 1, 2):
        if rho[t + 1] + rho[t + 2] > rho[t - 1] + rho[t]:
            rho[t + 1] = rho[t + 2] = (rho[t - 1] + rho[t]) / 2
    tau = -1 + 2 * rho[:max_t + 1].sum() + rho[max_t + 1:max_t + 2].sum()
    return float(m * n / max(tau, 1.0 / np.log10(max(m * n, 10))))
