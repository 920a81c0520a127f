"""The priors of Bayesian parameter inference (``estim.inference``): their log-densities
against scipy.stats, their draws, and what they refuse (an improper prior, a start outside
the support)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from estim import inference
from estim.inference.priors import as_priors, check_start

CASES = [
    (inference.Normal(1.5, 0.7), stats.norm(1.5, 0.7)),
    (inference.LogNormal(0.3, 0.5), stats.lognorm(0.5, scale=math.exp(0.3))),
    (inference.Uniform(-2.0, 3.0), stats.uniform(-2.0, 5.0)),
    (inference.Gamma(2.5, 0.4), stats.gamma(2.5, scale=0.4)),
    (inference.InverseGamma(3.0, 2.0), stats.invgamma(3.0, scale=2.0)),
    (inference.HalfNormal(1.3), stats.halfnorm(scale=1.3)),
    (inference.Beta(2.0, 5.0), stats.beta(2.0, 5.0)),
]


@pytest.mark.parametrize("prior, ref", CASES, ids=[type(p).__name__ for p, _ in CASES])
def test_log_densities_are_scipys(prior, ref):
    """Inside the support the log-density is scipy's to 1e-12; outside it is -inf; the
    draws follow the distribution (Kolmogorov-Smirnov at 1e-3 on 4000 draws: a 0.1 %
    false-alarm rate)."""
    lo, hi = ref.ppf(0.001), ref.ppf(0.999)
    for theta in np.linspace(lo, hi, 25):
        assert prior.logpdf(theta) == pytest.approx(ref.logpdf(theta), rel=1e-12, abs=1e-12)
    for outside in (prior.low - 1.0, prior.high + 1.0, math.nan, math.inf):
        if math.isfinite(outside) and prior.low <= outside <= prior.high:
            continue
        assert prior.logpdf(outside) == -math.inf
    draws = prior.sample(np.random.default_rng(1), 4000)
    assert stats.kstest(draws, ref.cdf).pvalue > 1e-3


def test_any_log_density_with_its_support():
    prior = inference.LogDensity(lambda t: -abs(t), low=-5.0, high=5.0)
    assert prior.logpdf(2.0) == -2.0 and prior.logpdf(6.0) == -math.inf
    with pytest.raises(TypeError, match="cannot be sampled"):
        prior.sample(np.random.default_rng(0), 3)
    priors = as_priors({"a": inference.Normal(0.0, 1.0), "b": lambda t: -t * t})
    assert isinstance(priors["b"], inference.LogDensity)


def test_what_the_priors_refuse():
    with pytest.raises(ValueError, match="low < high"):
        inference.Uniform(1.0, 1.0)
    with pytest.raises(ValueError, match="high must be a finite number"):
        inference.Uniform(0.0, math.inf)  # improper
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="sd must be positive"):
            inference.Normal(0.0, bad)
    with pytest.raises(ValueError, match="shape must be positive"):
        inference.Gamma(0.0, 1.0)
    with pytest.raises(TypeError, match="non-empty dict"):
        as_priors([inference.Normal(0.0, 1.0)])
    with pytest.raises(TypeError, match=r"priors\['a'\] must be a prior"):
        as_priors({"a": 3.0})
    priors = as_priors({"rho": inference.Uniform(-1.0, 1.0), "s": inference.HalfNormal(1.0)})
    with pytest.raises(ValueError, match=r"outside the support of the prior: rho = 1.5"):
        check_start(priors, {"rho": 1.5, "s": 0.3})
    with pytest.raises(ValueError, match="no value for"):
        check_start(priors, {"rho": 0.5})
    check_start(priors, {"rho": 0.5, "s": 0.3})
