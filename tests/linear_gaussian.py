"""The 2-state linear-Gaussian model of the particle and ensemble filter tests, its
records and filterpy's exact Kalman filter on them."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter

import estim

A = np.array([[1.0, 0.1], [0.0, 1.0]])
C = np.array([[1.0, 0.0]])
Q = np.diag([1e-3, 1e-2])
R = np.array([[0.1]])
X0, P0 = np.zeros(2), np.eye(2)


def _dynamics(x, u, p):
    return A @ x


def _output(x, u, p):
    return C @ x


def linear_model() -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"], dynamics=_dynamics, output=_output)


def record(T: int, seed: int = 1, r: float = R[0, 0]) -> np.ndarray:
    """Measurements of the linear model, noise variance ``r``."""
    rng = np.random.default_rng(seed)
    x, Y = rng.multivariate_normal(X0, P0), []
    for k in range(T):
        if k:
            x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        Y.append(C @ x + rng.normal(0.0, np.sqrt(r), 1))
    return np.array(Y)


def kalman(Y: np.ndarray, x0=X0, P0=P0, Q=Q) -> tuple[np.ndarray, np.ndarray, float]:
    """filterpy's KF started with an update from (x0, P0): means, covariances and the
    log-likelihood of the record."""
    kf = KalmanFilter(2, 1)
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = A, C, Q, R, np.array(x0, float), np.array(P0, float)
    xs, Ps, ll = [], [], 0.0
    for k, y in enumerate(Y):
        if k:
            kf.predict()
        kf.update(y)
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
        ll += float(kf.log_likelihood)
    return np.array(xs), np.array(Ps), ll
