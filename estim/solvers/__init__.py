"""The shared numerical machinery of the estimators.

Estimators (:mod:`estim.estimators`) state their mathematics and their protocol; what
several of them solve lives here, below them and above the model:

- :mod:`~estim.solvers.gauss_newton`: projected Gauss-Newton on the block-tridiagonal
  least-squares problem of a window or a record;
- :mod:`~estim.solvers.nlp`: that problem as one NLP (Ipopt, SQP, fatrop or the
  Gauss-Newton solver), with robust reweighting (:mod:`~estim.solvers.robust`);
- :mod:`~estim.solvers.rti`: the real-time iteration of the moving horizon estimator;
- :mod:`~estim.solvers.kalman`: the fused Kalman step and its whole-record scan;
- :mod:`~estim.solvers.triangular`: QR triangularisation, Cholesky downdates and
  triangular solves for the square-root filters;
- :mod:`~estim.solvers.rts`: the Rauch-Tung-Striebel backward recursion;
- :mod:`~estim.solvers.seeds`: one-seed Functions run over many seeds.
"""
