"""Estimators sharing one protocol (see :mod:`estim.estimators.base`)."""

from estim.estimators.base import Estimator, StepInfo
from estim.estimators.ekf import EKF
from estim.estimators.ukf import UKF

#: Estimator classes by short name (command line, comparisons).
ESTIMATORS = {"ekf": EKF, "ukf": UKF}

__all__ = ["EKF", "ESTIMATORS", "Estimator", "StepInfo", "UKF"]
