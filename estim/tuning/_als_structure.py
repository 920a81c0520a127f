r"""The free entries of ``Q`` and ``R`` in autocovariance least squares.

ALS estimates a covariance through its free entries :math:`\theta`: each structure
(``"diagonal"``, ``"full"``, ``"scalar"`` or a symmetric boolean mask of the free
entries) is a basis of symmetric matrices :math:`B_i` with

.. math::
    Q_w(\theta) = \sum_i \theta_i B_i, \qquad Q = G\, Q_w\, G^\top,

so that the innovation autocovariances stay linear in :math:`\theta`. When every
:math:`B_i` is diagonal, :math:`Q_w \succeq 0` is simply :math:`\theta \ge 0`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from estim._validate import as_choice

STRUCTURES = ("diagonal", "full", "scalar")


@dataclass
class _Block:
    """The free entries of one covariance (``Q``, or ``Q_w`` with a shaping matrix, or
    ``R``): ``basis[i]`` is the symmetric matrix multiplying parameter ``i``."""

    name: str
    basis: list[np.ndarray]
    diagonal: bool  # every basis matrix is diagonal (PSD is then non-negativity)

    def matrix(self, theta: np.ndarray) -> np.ndarray:
        r""":math:`\sum_i \theta_i B_i` for ``theta (len(basis),)``."""
        return np.tensordot(theta, np.asarray(self.basis), axes=1)


def _block(spec: str | np.ndarray | list, n: int, name: str) -> _Block:
    """The basis of a covariance of size ``n`` with structure ``spec``."""
    eye = np.eye(n)
    if isinstance(spec, str):
        spec = as_choice(spec, STRUCTURES, f"structure[{name!r}]")
        if spec == "scalar":
            return _Block(name, [eye], True)
        if spec == "diagonal":
            return _Block(name, [np.outer(eye[i], eye[i]) for i in range(n)], True)
        mask = np.ones((n, n), dtype=bool)
    else:
        mask = np.asarray(spec)
        if mask.dtype != bool:
            raise TypeError(f"structure[{name!r}] must be 'diagonal', 'full', 'scalar' or a "
                            f"boolean mask of the free entries, got an array of {mask.dtype}")
        if mask.shape != (n, n):
            raise ValueError(f"structure[{name!r}] as a mask must have shape ({n}, {n}), "
                             f"got {mask.shape}")
        if not np.array_equal(mask, mask.T):
            raise ValueError(f"structure[{name!r}] must be a symmetric mask")
        if not mask.diagonal().all():
            raise ValueError(f"structure[{name!r}] must leave the whole diagonal free (a "
                             f"covariance with a zero variance has no correlations)")
    basis = []
    for i in range(n):
        for j in range(i, n):
            if mask[i, j]:
                E = np.zeros((n, n))
                E[i, j] = E[j, i] = 1.0
                basis.append(E)
    return _Block(name, basis, all(np.count_nonzero(B - np.diag(np.diag(B))) == 0
                                   for B in basis))


def _structures(structure: object, ng: int, ny: int) -> tuple[_Block, _Block]:
    """The blocks of ``Q_w (ng, ng)`` and ``R (ny, ny)`` for the ``structure`` argument
    of :func:`~estim.tuning.als` (one structure for both, or a dict of them)."""
    if isinstance(structure, Mapping):
        unknown = sorted(set(structure) - {"Q", "R"})
        if unknown:
            raise ValueError(f"structure names unknown covariances {unknown}; it maps 'Q' "
                             f"and/or 'R' to a structure")
        q, r = structure.get("Q", "diagonal"), structure.get("R", "diagonal")
    else:
        q = r = structure
    if not isinstance(q, str | np.ndarray | list) or not isinstance(r, str | np.ndarray | list):
        raise TypeError(f"structure must be 'diagonal', 'full', 'scalar', a boolean mask or "
                        f"a dict of them for 'Q' and 'R', got {structure!r}")
    return _block(q, ng, "Q"), _block(r, ny, "R")


def _qbasis(block: _Block, G: np.ndarray) -> list[np.ndarray]:
    r"""The basis of ``Q = G Q_w Gᵀ``: :math:`G B_i G^\top`."""
    return [G @ B @ G.T for B in block.basis]
