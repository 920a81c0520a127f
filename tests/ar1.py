"""The scalar AR(1) state observed in noise of the Bayesian inference tests (the linear
Gaussian model of the ``particles`` book, chapter 16) and its exact log-likelihood."""

from __future__ import annotations

import math

import numpy as np

import estim


def ar1_model() -> estim.Model:
    """:math:`x_{k+1} = \\rho x_k` (the noise from ``Q``), :math:`y_k = x_k` (``R``)."""
    return estim.Model(states=["x"], outputs=["y"], params={"rho": 0.9},
                       dynamics=lambda x, u, p: p["rho"] * x, output=lambda x, u, p: x)


def kalman(Y: np.ndarray, rho, q, r, p0):
    """The exact log-likelihood of the record ``Y (T, 1)``, elementwise over arrays (or
    numbers: then in plain floats, for speed) of the parameters: the Kalman filter from
    :math:`N(0, p_0)`."""
    log = np.log if isinstance(rho, np.ndarray) else math.log
    m, P, total = 0.0 * rho, 1.0 * p0, 0.0
    for k, yk in enumerate(Y[:, 0].tolist()):
        if k:
            m, P = rho * m, rho * rho * P + q
        S = P + r
        e = yk - m
        total = total - 0.5 * (log(2 * math.pi * S) + e * e / S)
        K = P / S
        m, P = m + K * e, (1 - K) * P
    return total


def evidence(Y: np.ndarray, n: tuple[int, int, int] = (100, 90, 90)
             ) -> tuple[float, dict[str, float]]:
    """:math:`\\log p(y)` and the posterior means of the book's model (its priors:
    :math:`\rho \\sim U(-1, 1)`, the variances InvGamma(2, 2); :math:`X_0 \\sim
    N(0, \\sigma_X^2)`) by the midpoint rule over :math:`\rho` and the logarithms of the
    variances on an ``n`` grid (the integrand is negligible beyond its ranges)."""
    from scipy import stats

    rho = np.linspace(-1, 1, n[0] + 1)[:-1] + 1 / n[0]
    lq, lr = np.linspace(-5, 4, n[1]), np.linspace(-7, 3, n[2])
    R, LQ, LR = np.meshgrid(rho, lq, lr, indexing="ij")
    q, r = np.exp(LQ), np.exp(LR)
    a = kalman(Y, R, q, r, q) + math.log(0.5) + stats.invgamma.logpdf(q, 2, scale=2) + \
        stats.invgamma.logpdf(r, 2, scale=2) + LQ + LR
    top = a.max()
    w = np.exp(a - top)
    vol = (2 / n[0]) * (lq[1] - lq[0]) * (lr[1] - lr[0])
    means = {"rho": float((w * R).sum() / w.sum()), "varX": float((w * q).sum() / w.sum()),
             "varY": float((w * r).sum() / w.sum())}
    return float(top + np.log(w.sum() * vol)), means
