"""The Kalman family: Gaussian filters and smoothers on one fused step.

Open first: :mod:`~estim.estimators.kalman.fused` (``FusedKalman``, the step every filter of
the family shares: predict and update in one compiled call, the whole-record path, the
statuses), then the filter you change.

- :mod:`~estim.estimators.kalman.ekf`, :mod:`~estim.estimators.kalman.ukf`: the extended
  and unscented filters (their linearisation or sigma points, their smoothers);
- :mod:`~estim.estimators.kalman.square_root`: the square-root forms (``form="sqrt"``);
- :mod:`~estim.estimators.kalman.smoothing`: the Rauch-Tung-Striebel smoother on a
  filtered record;
- :mod:`~estim.estimators.kalman.fused_calls`: the fused step's calls over a record and
  over seeds;
- :mod:`~estim.estimators.kalman.imm`: the interacting multiple model filter over Kalman
  modes.
"""
