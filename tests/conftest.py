"""Shared fixtures: a random linear-Gaussian system written through estim.Model."""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import matplotlib
import numpy as np
import pytest

import estim

matplotlib.use("Agg")


@dataclass
class LinearSystem:
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    model: estim.Model


def _spd(rng, n, scale):
    M = rng.standard_normal((n, n))
    return scale * (M @ M.T / n + 0.5 * np.eye(n))


def make_linear(seed: int = 0, nx: int = 4, nu: int = 1, ny: int = 2) -> LinearSystem:
    """x+ = A x + B u + w, y = C x + v with random, full-matrix covariances."""
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((nx, nx))
    A *= 0.95 / max(abs(np.linalg.eigvals(A)))
    B = rng.standard_normal((nx, nu))
    C = rng.standard_normal((ny, nx))
    Q = _spd(rng, nx, 0.05)
    R = _spd(rng, ny, 0.2)
    P0 = _spd(rng, nx, 1.0)
    x0 = rng.standard_normal(nx)
    Ad, Bd, Cd = ca.DM(A), ca.DM(B), ca.DM(C)
    model = estim.Model(states=nx, outputs=ny, inputs=nu,
                        dynamics=lambda x, u, p: Ad @ x + Bd @ u,
                        output=lambda x, u, p: Cd @ x, name="linear")
    return LinearSystem(A, B, C, Q, R, x0, P0, model)


@pytest.fixture
def linear() -> LinearSystem:
    return make_linear()


@pytest.fixture(scope="module")
def fresh_cache(tmp_path_factory):
    """A library cache of the module's own (a new directory: nothing compiled by other
    runs) for the compiled filters."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("ESTIM_CACHE_DIR", str(tmp_path_factory.mktemp("estim-cache")))
        yield
