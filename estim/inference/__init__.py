"""Bayesian parameter inference (to come): particle marginal Metropolis-Hastings, particle
Gibbs and SMC², with the particle filter (:mod:`estim.estimators.sampling`) as the
likelihood engine.

Its layer is above the estimators and the simulation loop and below the comparisons
(``[tool.importlinter]`` in ``pyproject.toml``; docs/architecture.md).
"""
