"""Bayesian parameter inference: the priors of the parameters
(:mod:`~estim.inference.priors`) and the chains' diagnostics
(:mod:`~estim.inference.chains`); to come, particle marginal Metropolis-Hastings, particle
Gibbs and SMC², with the particle filter (:mod:`estim.estimators.sampling`) as the
likelihood engine.

Its layer is above the estimators and the simulation loop and below the comparisons
(``[tool.importlinter]`` in ``pyproject.toml``; docs/architecture.md).
"""

from estim.inference.chains import ess, rhat
from estim.inference.likelihood import ParticleLikelihood
from estim.inference.particle_gibbs import particle_gibbs
from estim.inference.pmmh import pmmh
from estim.inference.posterior import Forecast, Posterior, StatePosterior
from estim.inference.priors import (
    Beta,
    Gamma,
    HalfNormal,
    InverseGamma,
    LogDensity,
    LogNormal,
    Normal,
    Prior,
    Uniform,
)
from estim.inference.smc2 import SMC2Result, smc2

__all__ = ["Beta", "Forecast", "Gamma", "HalfNormal", "InverseGamma", "LogDensity", "LogNormal",
           "Normal", "ParticleLikelihood", "Posterior", "Prior", "StatePosterior", "Uniform",
           "SMC2Result", "ess", "particle_gibbs", "pmmh", "rhat", "smc2"]
