"""The window family: estimators that solve a least-squares problem over a window of
samples or the whole record.

Open first: :mod:`~estim.estimators.window.fie` (full-information estimation: the problem
over a whole record, built once and solved by :mod:`estim.solvers.least_squares`), then:

- :mod:`~estim.estimators.window.mhe`: moving horizon estimation, the same problem over
  a sliding window with an arrival cost; :mod:`~estim.estimators.window.mhe_window` moves
  the window and its arrival cost, :mod:`~estim.estimators.window.mhe_rti` its real-time
  iteration (``rti=True``);
- :mod:`~estim.estimators.window.shooting`: the single-shooting observer that identifies
  parameters (its problem in :mod:`~estim.estimators.window.shooting_problem`, its start
  search in :mod:`~estim.estimators.window.shooting_search`).
"""
