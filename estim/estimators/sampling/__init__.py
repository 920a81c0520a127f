"""The sampling family: estimators that carry a cloud of particles or ensemble members.

Open first: :mod:`~estim.estimators.sampling.particle` (``ParticleFilter``: proposals,
resampling, likelihood), then:

- :mod:`~estim.estimators.sampling.particle_compiled`: its whole record in compiled code
  (``jit=True``), with the graphs of :mod:`~estim.estimators.sampling.particle_graphs`;
- :mod:`~estim.estimators.sampling.particle_smoothing`: the particle smoothers;
- :mod:`~estim.estimators.sampling.enkf`: the ensemble Kalman filters;
- :mod:`~estim.estimators.sampling.ensembles`: what both share (noise drawn from square
  roots of covariances, points about an estimate with their mean and deviations, a
  model's Functions over many points).
"""
