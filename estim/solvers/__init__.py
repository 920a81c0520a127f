"""The shared numerical machinery of the estimators, by family.

Estimators (:mod:`estim.estimators`) state their mathematics and their protocol; what
several of them solve lives here, below them and above the model:

- :mod:`estim.solvers.least_squares`: the least-squares problems of a window or a record
  (projected Gauss-Newton, the NLP on Ipopt, SQP or fatrop, robust reweighting, the
  real-time iteration);
- :mod:`estim.solvers.kalman`: the fused Kalman step and its whole-record scan, the
  Rauch-Tung-Striebel recursion, the triangular algebra of the square-root forms;
- :mod:`estim.solvers.sampling`: resampling and the compiled particle kernel;
- :mod:`~estim.solvers.seeds` and :mod:`~estim.solvers.seed_threads`: one-seed Functions
  run over many seeds, on threads (comparisons, the whole-record filters);
- :mod:`~estim.solvers.weights`: covariances as least-squares weights.
"""
