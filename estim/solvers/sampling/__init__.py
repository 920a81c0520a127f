"""The numerics of the sampling family: resampling schemes
(:mod:`~estim.solvers.sampling.resampling`, open first) and the compiled particle kernel
with its C driver (:mod:`~estim.solvers.sampling.particle_kernel`, the driver in
``templates/``)."""
