"""The linear Gaussian model of the ``particles`` book (Chopin & Papaspiliopoulos 2020,
ch. 16) shared by the Bayesian inference benchmarks: its data, the model, priors and
tuning as estim takes them, and the exact Kalman log-likelihood (``tests/ar1.py``, checked
there against filterpy).

:math:`X_0 \\sim N(0, \\sigma_X^2)`, :math:`X_t = \\rho X_{t-1} + U_t`,
:math:`U_t \\sim N(0, \\sigma_X^2)`, :math:`Y_t = X_t + V_t`,
:math:`V_t \\sim N(0, \\sigma_Y^2)`, T = 100 (``particles_reference/lingauss_data.txt``).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import estim
from estim.inference import InverseGamma, Uniform

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE.parent / "tests"))  # the exact likelihood the tests check

from ar1 import ar1_model, evidence, kalman  # noqa: E402, F401 (evidence: for the scripts)

PRIORS = {"rho": Uniform(-1, 1), "varX": InverseGamma(2, 2), "varY": InverseGamma(2, 2)}


def data() -> np.ndarray:
    """The book's record ``(100, 1)``."""
    return np.loadtxt(HERE / "particles_reference" / "lingauss_data.txt")[:, None]


def model() -> estim.Model:
    return ar1_model()


def tuning(th: dict) -> dict:
    """Noise and prior of ReparamLinGauss: X_0 ~ N(0, varX)."""
    return {"Q": [[th["varX"]]], "R": [[th["varY"]]], "P0": [[th["varX"]]]}


def kalman_loglik(Y: np.ndarray, **fixed: float):
    """``theta -> log p(Y | theta)`` for :func:`estim.inference.pmmh` (parameters not in
    ``theta`` from ``fixed``)."""

    def loglik(th: dict) -> float:
        p = {**fixed, **th}
        return float(kalman(Y, p["rho"], p["varX"], p["varY"], p["varX"]))

    return loglik
