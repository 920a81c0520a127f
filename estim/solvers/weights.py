r"""Weights of the least-squares costs from covariances.

A residual :math:`r` with covariance :math:`C` enters a cost as :math:`\|W r\|^2` with
:math:`W^\top W = C^{-1}` (:func:`weight_factor`): the process term with :math:`Q`, the
measurements with :math:`R`, the arrival term with the arrival covariance. A sample
whose outputs are partly missing weighs the measured ones by the marginal of
:math:`R` over them (:func:`measurement_weights`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["is_diagonal", "is_singular", "measurement_weights", "noise_factor",
           "pseudo_weight_factor", "weight_factor"]

#: eigenvalues below this fraction of the largest are zero (a singular covariance)
SINGULAR = 1e-12


def is_diagonal(M: np.ndarray) -> bool:
    """Whether ``M`` is a diagonal matrix (its graphs then use the diagonal only)."""
    return bool(np.array_equal(M, np.diag(np.diag(M))))


def weight_factor(cov: np.ndarray) -> np.ndarray:
    """``W`` with ``W^T W = cov^{-1}``, so ``||W r||^2 = r^T cov^{-1} r``."""
    L = np.linalg.cholesky(np.linalg.inv(cov))
    return L.T


def _spectrum(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eigenvalues, eigenvectors and the mask of the positive ones of a symmetric
    positive semi-definite ``cov``."""
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    return lam, V, lam > SINGULAR * max(float(lam[-1]), 0.0)


def is_singular(cov: np.ndarray) -> bool:
    """Whether the positive semi-definite ``cov`` has a zero eigenvalue (below
    :data:`SINGULAR` of the largest): a direction without noise."""
    return not _spectrum(np.asarray(cov, dtype=float))[2].all()


def noise_factor(cov: np.ndarray, inverse: bool = False) -> np.ndarray:
    r"""``G`` ``(n, r)`` with :math:`G G^\top` = ``cov`` (:math:`V_r \Lambda_r^{1/2}`, the
    ``r`` positive eigenvalues); with ``inverse``, ``cov`` is a pseudo-inverse
    :math:`Q^{+}` and :math:`G G^\top = Q`."""
    lam, V, keep = _spectrum(np.asarray(cov, dtype=float))
    scale = 1.0 / np.sqrt(lam[keep]) if inverse else np.sqrt(lam[keep])
    return V[:, keep] * scale


def pseudo_weight_factor(cov: np.ndarray) -> np.ndarray:
    r"""``W`` ``(n, n)`` with :math:`W^\top W = \mathrm{cov}^{+}`: the whitening of the
    directions with noise, zero rows for those without."""
    lam, V, keep = _spectrum(np.asarray(cov, dtype=float))
    W = np.zeros_like(V)
    W[keep] = (V[:, keep] / np.sqrt(lam[keep])).T
    return W


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
