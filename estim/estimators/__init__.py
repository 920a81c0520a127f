"""Estimators sharing one protocol (see :mod:`estim.estimators.base`).

The estimator classes are imported on first use (PEP 562), so that
``import estim`` does not load every estimator and its dependencies.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from estim.estimators.base import Estimator, StepInfo

if TYPE_CHECKING:
    from collections.abc import Callable

    from estim.estimators.kalman.ekf import EKF
    from estim.estimators.kalman.imm import IMM
    from estim.estimators.kalman.ukf import UKF
    from estim.estimators.sampling.enkf import EnKF
    from estim.estimators.sampling.particle import ParticleFilter
    from estim.estimators.window.fie import FitResult, FullInformation
    from estim.estimators.window.mhe import MHE
    from estim.estimators.window.shooting import ShootingObserver

    #: Estimator classes (or, for ``imm``, a constructor on one model) by short name
    #: (command line, comparisons): each is called as ``f(model, Q=, R=, x0=, P0=, ...)``.
    ESTIMATORS: dict[str, Callable[..., Estimator]]

#: Where each lazily imported name is defined.
_LAZY = {"EKF": "estim.estimators.kalman.ekf", "EnKF": "estim.estimators.sampling.enkf",
         "FitResult": "estim.estimators.window.fie",
         "FullInformation": "estim.estimators.window.fie", "IMM": "estim.estimators.kalman.imm",
         "MHE": "estim.estimators.window.mhe",
         "ParticleFilter": "estim.estimators.sampling.particle",
         "ShootingObserver": "estim.estimators.window.shooting",
         "UKF": "estim.estimators.kalman.ukf"}

#: The short names of :data:`ESTIMATORS` and their classes.
_SHORT_NAMES = {"ekf": "EKF", "ukf": "UKF", "mhe": "MHE", "fie": "FullInformation",
                "shooting": "ShootingObserver", "pf": "ParticleFilter", "enkf": "EnKF",
                "imm": "IMM.noise_levels"}

__all__ = ["EKF", "ESTIMATORS", "EnKF", "IMM", "MHE", "Estimator", "FitResult",
           "FullInformation",
           "ParticleFilter",
           "ShootingObserver", "StepInfo", "UKF"]


if not TYPE_CHECKING:  # type checkers see the imports above, and no catch-all
    def __getattr__(name: str) -> Any:
        if name == "ESTIMATORS":
            value = {}
            for short, path in _SHORT_NAMES.items():
                cls, _, method = path.partition(".")
                value[short] = getattr(__getattr__(cls), method) if method else __getattr__(cls)
        elif name in _LAZY:
            value = getattr(importlib.import_module(_LAZY[name]), name)
        else:
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        globals()[name] = value  # imported once: later look-ups do not come here
        return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
