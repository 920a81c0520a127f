"""Convergence diagnostics of Markov chains (``estim.inference.rhat``, ``ess``): against
closed forms on autoregressive chains, on chains that disagree, and against arviz (when it
is installed)."""

from __future__ import annotations

import numpy as np
import pytest

from estim.inference import ess, rhat


def ar1(rho: float, chains: int, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = np.zeros((chains, n))
    e = rng.normal(size=(chains, n))
    x[:, 0] = e[:, 0] / np.sqrt(1 - rho ** 2)  # stationary from the start
    for t in range(1, n):
        x[:, t] = rho * x[:, t - 1] + e[:, t]
    return x


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9])
def test_ess_of_autoregressive_chains(rho):
    """Four AR(1) chains of 5000 draws: the effective sample size of the mean is
    n (1 - rho) / (1 + rho); the estimate within 25 % of it (its own spread: over seeds
    0-19, a standard deviation of 7 % and 16.5 % at worst at rho = 0.9, 6 % at worst for
    rho <= 0.5; this seed: -10 %), and R-hat below 1.01."""
    x = ar1(rho, 4, 5000, seed=0)
    want = x.size * (1 - rho) / (1 + rho)
    assert abs(ess(x) / want - 1) < 0.25
    assert rhat(x) < 1.01


def test_rhat_sees_chains_that_disagree():
    """A chain shifted by one standard deviation, a chain three times as wide (the folded
    R-hat) and random walks (a trend inside each chain: its halves disagree) all give R-hat
    beyond 1.05; the shifted chains' effective sample size collapses."""
    rng = np.random.default_rng(1)
    shifted = rng.normal(size=(4, 1000))
    shifted[0] += 1.0
    wide = rng.normal(size=(4, 1000))
    wide[0] *= 3.0
    walks = np.cumsum(rng.normal(size=(4, 1000)), axis=1)
    for x in (shifted, wide, walks):
        assert rhat(x) > 1.05
    assert ess(shifted) < 100


def test_the_diagnostics_are_arviz():
    """The same numbers as arviz's rank-normalised split R-hat and bulk ESS (to 1e-12),
    on autoregressive, heavy-tailed, shifted and antithetic chains."""
    az = pytest.importorskip("arviz")
    rng = np.random.default_rng(2)
    shifted = rng.normal(size=(4, 800))
    shifted[1] += 0.7
    cases = [ar1(0.9, 4, 3000, 3), rng.standard_t(3, size=(3, 777)), shifted,
             (-1.0) ** np.arange(400) * rng.normal(size=(2, 400))]
    for x in cases:
        assert rhat(x) == pytest.approx(float(az.rhat(x, method="rank")), rel=1e-12)
        assert ess(x) == pytest.approx(float(az.ess(x, method="bulk")), rel=1e-12)


def test_what_the_diagnostics_refuse():
    with pytest.raises(ValueError, match="at least 4 draws"):
        rhat(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="must be finite"):
        ess(np.array([[0.0, 1.0, np.nan, 2.0, 3.0]]))
    with pytest.raises(ValueError, match="one quantity"):
        rhat(np.zeros((2, 3, 4)))
    assert np.isnan(rhat(np.ones((2, 10))))
