"""estim: nonlinear state and parameter estimation on one model definition.

>>> import estim
>>> sc = estim.scenarios.batch_reactor()
>>> log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
>>> float(estim.rmse(log)) > 0.1   # the EKF from the bad guess converges wrongly
True
"""

from estim import models, observability, scenarios, smooth
from estim.compare import Comparison, compare
from estim.estimators import (
    EKF,
    MHE,
    UKF,
    Estimator,
    FitResult,
    FullInformation,
    ShootingObserver,
    StepInfo,
)
from estim.estimators.base import EstimationWarning
from estim.log import Log
from estim.metrics import RMSE, chi2_bounds, convergence_time, errors, nees, nis, rmse
from estim.model import Model
from estim.scenarios import Record, Scenario
from estim.simulate import replay, simulate

__all__ = [
    "EKF", "MHE", "UKF", "Comparison", "EstimationWarning", "Estimator", "FitResult",
    "FullInformation", "Log", "Model", "RMSE", "Record", "Scenario", "ShootingObserver",
    "StepInfo", "chi2_bounds",
    "compare", "convergence_time", "errors", "models", "nees", "nis", "observability", "replay",
    "rmse", "scenarios", "simulate", "smooth",
]
__version__ = "0.1.0"
