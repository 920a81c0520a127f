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

    from estim.estimators.ekf import EKF
    from estim.estimators.enkf import EnKF
    from estim.estimators.fie import FitResult, FullInformation
    from estim.estimators.imm import IMM
    from estim.estimators.mhe import MHE
    from estim.estimators.particle import ParticleFilter
    from estim.estimators.shooting import ShootingObserver
    from estim.estimators.ukf import UKF

    #: Estimator classes (or, for ``imm``, a constructor on one model) by short name
    #: (command line, comparisons): each is called as ``f(model, Q=, R=, x0=, P0=, ...)``.
    ESTIMATORS: dict[str, Callable[..., Estimator]]

#: Where each lazily imported name is defined.
_LAZY = {"EKF": "estim.estimators.ekf", "EnKF": "estim.estimators.enkf",
         "FitResult": "estim.estimators.fie",
         "FullInformation": "estim.estimators.fie", "IMM": "estim.estimators.imm",
         "MHE": "estim.estimators.mhe",
         "ParticleFilter": "estim.estimators.particle",
         "ShootingObserver": "estim.estimators.shooting", "UKF": "estim.estimators.ukf"}

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
