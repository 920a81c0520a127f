r"""Weights of the least-squares costs from covariances.

A residual :math:`r` with covariance :math:`C` enters a cost as :math:`\|W r\|^2` with
:math:`W^\top W = C^{-1}` (:func:`weight_factor`): the process term with :math:`Q`, the
measurements with :math:`R`, the arrival term with the arrival covariance. A sample
whose outputs are partly missing weighs the measured ones by the marginal of
:math:`R` over them (:func:`measurement_weights`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["is_diagonal", "measurement_weights", "weight_factor"]


def is_diagonal(M: np.ndarray) -> bool:
    """Whether ``M`` is a diagonal matrix (its graphs then use the diagonal only)."""
    return bool(np.array_equal(M, np.diag(np.diag(M))))


def weight_factor(cov: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T W = cov^{-1}``, so ``||W r||^2 = r^T cov^{-1} r``."""
    L = np.linalg.cholesky(np.linalg.inv(cov))
    return L.T


def measurement_weights(mask: np.ndarray, R: np.ndarray, WR: np.ndarray) -> np.ndarray:
    """``(T, ny, ny)``: the weight factor of each sample's measured outputs (``mask``
    (T, ny)): ``WR`` where every output is measured, the factor of the marginal of
    ``R`` over the measured rows (zero elsewhere) where some are, zero where none."""
    wy = np.zeros((len(mask), len(R), len(R)))
    full = mask.all(axis=1)
    wy[full] = WR
    for j in np.flatnonzero(~full & mask.any(axis=1)):
        rows = np.flatnonzero(mask[j])
        wy[j][np.ix_(rows, rows)] = weight_factor(R[np.ix_(rows, rows)])
    return wy
