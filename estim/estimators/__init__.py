"""Estimators sharing one protocol (see :mod:`estim.estimators.base`)."""

from estim.estimators.base import Estimator, StepInfo
from estim.estimators.ekf import EKF
from estim.estimators.fie import FitResult, FullInformation
from estim.estimators.mhe import MHE
from estim.estimators.shooting import ShootingObserver
from estim.estimators.ukf import UKF

#: Estimator classes by short name (command line, comparisons).
ESTIMATORS = {"ekf": EKF, "ukf": UKF, "mhe": MHE, "fie": FullInformation,
              "shooting": ShootingObserver}

__all__ = ["EKF", "ESTIMATORS", "MHE", "Estimator", "FitResult", "FullInformation",
           "ShootingObserver", "StepInfo", "UKF"]
