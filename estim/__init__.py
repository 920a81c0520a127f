"""estim: nonlinear state and parameter estimation on one model definition.

>>> import estim
>>> sc = estim.scenarios.batch_reactor()
>>> log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
>>> float(estim.rmse(log)) > 0.1   # the EKF from the bad guess converges wrongly
True
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from estim import models, scenarios
from estim._version import __version__ as __version__
from estim.compare import Comparison, compare
from estim.estimators.base import EstimationWarning, Estimator, StepInfo
from estim.log import Log
from estim.metrics import RMSE, chi2_bounds, convergence_time, errors, nees, nis, rmse
from estim.model import Model
from estim.scenarios import Record, Scenario
from estim.simulate import replay, simulate

if TYPE_CHECKING:
    from estim import adapters as adapters  # not in __all__: imported on first use
    from estim import codegen as codegen
    from estim import consistency as consistency
    from estim import exceptions as exceptions
    from estim import inference as inference
    from estim import observability, records, smooth, soft, tuning
    from estim import plotting as plotting
    from estim import testing as testing
    from estim import verdicts as verdicts
    from estim.estimators.kalman.ekf import EKF
    from estim.estimators.kalman.imm import IMM
    from estim.estimators.kalman.ukf import UKF
    from estim.estimators.sampling.enkf import EnKF
    from estim.estimators.sampling.particle import ParticleFilter
    from estim.estimators.window.fie import FitResult, FullInformation
    from estim.estimators.window.mhe import MHE
    from estim.estimators.window.shooting import ShootingObserver
    from estim.uncertainty import ParameterEstimates, parameter_uncertainty

__all__ = [
    "EKF", "MHE", "UKF", "Comparison", "EnKF", "EstimationWarning", "Estimator",
    "FitResult",
    "FullInformation", "IMM", "Log", "Model", "ParameterEstimates", "ParticleFilter", "RMSE",
    "Record", "Scenario", "ShootingObserver", "StepInfo", "chi2_bounds",
    "compare", "convergence_time", "errors", "models", "nees", "nis", "observability",
    "parameter_uncertainty", "records", "replay", "rmse", "scenarios", "simulate", "smooth",
    "soft", "tuning",
]

#: Names imported on first use (PEP 562): the estimators and the modules that
#: ``import estim`` does not need, so that it stays fast.
_LAZY = {"EKF": "estim.estimators.kalman.ekf", "EnKF": "estim.estimators.sampling.enkf",
         "FitResult": "estim.estimators.window.fie",
         "FullInformation": "estim.estimators.window.fie", "IMM": "estim.estimators.kalman.imm",
         "MHE": "estim.estimators.window.mhe",
         "ParticleFilter": "estim.estimators.sampling.particle",
         "ShootingObserver": "estim.estimators.window.shooting",
         "UKF": "estim.estimators.kalman.ukf",
         "codegen": "estim.codegen", "observability": "estim.observability",
         "records": "estim.records", "adapters": "estim.adapters",
         "testing": "estim.testing", "plotting": "estim.plotting",
         "verdicts": "estim.verdicts", "inference": "estim.inference",
         "consistency": "estim.consistency", "exceptions": "estim.exceptions",
         "uncertainty": "estim.uncertainty",
         "soft": "estim.soft", "smooth": "estim.smooth", "tuning": "estim.tuning",
         "ParameterEstimates": "estim.uncertainty",
         "parameter_uncertainty": "estim.uncertainty"}

if not TYPE_CHECKING:  # type checkers see the imports above, and no catch-all
    def __getattr__(name: str) -> Any:
        if name not in _LAZY:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        module = importlib.import_module(_LAZY[name])
        value = module if module.__name__ == f"{__name__}.{name}" else getattr(module, name)
        globals()[name] = value  # imported once: later look-ups do not come here
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
