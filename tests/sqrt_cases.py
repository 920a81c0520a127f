"""Linear-Gaussian systems on which the covariance form of a Kalman filter loses
definiteness, for the square-root form's tests and benchmark.

Each case is a linear model ``x+ = A x + w``, ``y = C x + v`` with ``w ~ N(0, Q)``
(``Q`` may be singular), ``v ~ N(0, R)``, the initial state drawn from the filter's
prior ``N(x0, P0)``. The filters are then exact: at every sample the normalised
estimation error squared ``e_k' P_k^-1 e_k`` is chi-square with ``nx`` degrees of
freedom, independent across runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy import linalg, stats

import estim


@dataclass
class Case:
    name: str
    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    T: int

    def model(self) -> estim.Model:
        Ad, Cd = ca.DM(self.A), ca.DM(self.C)
        return estim.Model(states=len(self.A), outputs=len(self.C),
                           dynamics=lambda x, u, p: Ad @ x, output=lambda x, u, p: Cd @ x,
                           name=self.name)

    def record(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The true states ``(T, nx)`` and measurements ``(T, ny)`` of one run."""
        rng = np.random.default_rng(seed)
        nx, ny = len(self.A), len(self.C)
        GQ, GR, G0 = (_root(M) for M in (self.Q, self.R, self.P0))
        x = self.x0 + G0 @ rng.standard_normal(nx)
        X, Y = np.empty((self.T, nx)), np.empty((self.T, ny))
        for k in range(self.T):
            X[k] = x
            Y[k] = self.C @ x + GR @ rng.standard_normal(ny)
            x = self.A @ x + GQ @ rng.standard_normal(nx)
        return X, Y


def _root(M: np.ndarray) -> np.ndarray:
    """A square root of a semi-definite matrix, for drawing its noise."""
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.maximum(w, 0.0))


def cases(T: int = 40) -> list[Case]:
    """The three hard cases, ``T`` samples each: a constant-velocity target whose position
    is measured almost exactly (``R = 1e-12``, ``Q = 0``, ``P0 = 1e6 I``), a badly scaled
    state (components of about 1e6 and 1e-6, measured through their sum) and a joint
    state/parameter estimate (a constant acceleration with noise variance 1e-20)."""
    dt = 1.0
    cv = np.array([[1.0, dt], [0.0, 1.0]])
    exact = Case("nearly exact position", cv, np.array([[1.0, 0.0]]), np.zeros((2, 2)),
                 np.array([[1e-12]]), np.zeros(2), 1e6 * np.eye(2), T)
    scaled = Case("badly scaled state", np.diag([0.99, 0.99]), np.array([[1.0, 1e12]]),
                  np.diag([1e6, 1e-18]), np.array([[1e-6]]), np.zeros(2),
                  np.diag([1e12, 1e-12]), T)
    # position, velocity and a constant acceleration (the parameter), position measured
    A3 = np.array([[1.0, dt, dt ** 2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    joint = Case("joint parameter", A3, np.array([[1.0, 0.0, 0.0]]),
                 np.diag([0.0, 0.0, 1e-20]), np.array([[1e-12]]), np.zeros(3),
                 np.diag([1e6, 1e6, 1e2]), T)
    return [exact, scaled, joint]


def run(case: Case, cls: type, form: str, seed: int, **options) -> dict:
    r"""One run of ``cls(..., form=form)`` step by step: the failed steps (not
    ``info.success``), the steps whose covariance is not positive definite, the NEES of
    every sample (NaN where the covariance is not definite) and the mean seconds of a
    step. The NEES :math:`\|L^{-1} e\|^2` uses the Cholesky factor of ``info.P`` in
    the covariance form and the filter's own factor in the square-root form (forming
    :math:`P = S S^\top` first would square its condition number)."""
    X, Y = case.record(seed)
    nx = len(case.A)
    est = cls(case.model(), Q=case.Q, R=case.R, x0=case.x0, P0=case.P0, form=form,
              **options)
    failed = indefinite = 0
    nees = np.full(case.T, np.nan)
    seconds = 0.0
    for k in range(case.T):
        t0 = time.perf_counter()
        x = est.step(Y[k])
        seconds += time.perf_counter() - t0
        info = est.info
        failed += not info.success
        if form == "sqrt":
            L = est._s[nx:].reshape(nx, nx, order="F")  # the filter state [x; vec(S)]
            definite = bool(np.all(np.diag(L) > 0))
        else:
            try:
                L, definite = np.linalg.cholesky(info.P), True
            except np.linalg.LinAlgError:
                definite = False
        if not definite:
            indefinite += 1
            continue
        z = linalg.solve_triangular(L, x - X[k], lower=True)
        nees[k] = z @ z
    return {"failed": failed, "indefinite": indefinite, "nees": nees,
            "seconds": seconds / case.T}


def nees_band(n_runs: int, nx: int, n_samples: int, level: float = 0.95
              ) -> tuple[float, float]:
    """The band the NEES summed over ``n_runs`` independent runs stays in at every one
    of ``n_samples`` samples with probability at least ``level``: at each sample that sum
    is chi-square with ``n_runs * nx`` degrees of freedom, and each sample's two-sided
    interval has the tail ``(1 - level) / n_samples`` (Bonferroni: the estimation errors
    of successive samples are correlated, so the samples are not independent)."""
    dof = n_runs * nx
    tail = (1 - level) / n_samples / 2
    return float(stats.chi2.ppf(tail, dof)), float(stats.chi2.ppf(1 - tail, dof))
