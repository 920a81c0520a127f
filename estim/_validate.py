"""Argument checking shared by the whole package.

Every public entry point converts user input through these helpers so that a
bad argument fails early with a message naming the argument and what was
expected.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from numbers import Real

import numpy as np


def as_vector(value, n: int, name: str, *, allow_nan: bool = False) -> np.ndarray:
    """Return ``value`` as a float ``(n,)`` array or raise naming ``name``.

    Scalars are accepted only when ``n == 1``; ``(n, 1)`` and ``(1, n)``
    arrays are flattened.
    """
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be numeric, got {type(value).__name__}") from exc
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim == 0 and n == 1:
        arr = arr.reshape(1)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {np.shape(value)}")
    if not allow_nan and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    if allow_nan and np.any(np.isinf(arr)):
        raise ValueError(f"{name} must not contain inf, got {arr}")
    return arr.copy()


def as_covariance(value, n: int, name: str, *, definite: bool = True) -> np.ndarray:
    """Return a symmetric ``(n, n)`` covariance from a scalar, variances or a matrix.

    Parameters
    ----------
    value : float, (n,) array of variances, or (n, n) array
    n : int
        Dimension.
    name : str
        Argument name used in error messages.
    definite : bool
        Require positive definiteness (otherwise positive semi-definiteness).
    """
    if value is None:
        raise ValueError(f"{name} is required (a scalar, a vector of variances or a matrix)")
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be numeric, got {type(value).__name__}") from exc
    if arr.ndim == 0:
        mat = float(arr) * np.eye(n)
    elif arr.ndim == 1 and arr.shape == (n,):
        mat = np.diag(arr)
    elif arr.shape == (n, n):
        mat = arr.copy()
    else:
        raise ValueError(
            f"{name} must be a scalar, a ({n},) vector of variances or a ({n}, {n}) matrix, "
            f"got shape {arr.shape}"
        )
    if not np.all(np.isfinite(mat)):
        raise ValueError(f"{name} must be finite")
    scale = max(1.0, float(np.max(np.abs(mat)))) if n else 1.0
    if not np.allclose(mat, mat.T, rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric")
    mat = 0.5 * (mat + mat.T)
    if n == 0:
        return mat
    eig = np.linalg.eigvalsh(mat)
    if definite and eig[0] <= 0.0:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {eig[0]:.3g})"
        )
    if not definite and eig[0] < -1e-12 * scale:
        raise ValueError(
            f"{name} must be positive semi-definite (smallest eigenvalue {eig[0]:.3g})"
        )
    return mat


def as_bounds(value, names: Sequence[str], name: str, default: float) -> np.ndarray:
    """Bounds as a ``(n,)`` array from None, a scalar, a sequence or a ``{name: value}`` dict."""
    n = len(names)
    out = np.full(n, default, dtype=float)
    if value is None:
        return out
    if isinstance(value, Mapping):
        for key, val in value.items():
            if key not in names:
                raise ValueError(f"{name} names unknown state {key!r}; states are {list(names)}")
            if val is not None:
                out[list(names).index(key)] = _bound_value(val, name)
        return out
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        out[:] = _bound_value(arr, name)
        return out
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar, a ({n},) sequence or a dict, got {arr.shape}")
    if np.any(np.isnan(arr)):
        raise ValueError(f"{name} must not contain NaN")
    return arr.astype(float)


def _bound_value(val, name: str) -> float:
    if not isinstance(val, Real | np.floating | np.integer | np.ndarray):
        raise TypeError(f"{name} entries must be numbers, got {type(val).__name__}")
    v = float(val)
    if np.isnan(v):
        raise ValueError(f"{name} must not contain NaN")
    return v


def as_names(value, name: str, prefix: str) -> list[str]:
    """State/output/input names from a sequence of strings or a count."""
    if value is None:
        return []
    if isinstance(value, int | np.integer):
        if value < 0:
            raise ValueError(f"{name} must be a non-negative count or a list of names")
        return [f"{prefix}{i + 1}" for i in range(int(value))]
    if isinstance(value, str):
        return [value]
    names = list(value)
    for item in names:
        if not isinstance(item, str):
            raise TypeError(f"{name} must be a list of strings, got item {item!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"{name} has duplicate names: {names}")
    return names


def check_options(options: Mapping, allowed: Sequence[str], owner: str) -> None:
    """Raise ``TypeError`` for an unknown keyword option."""
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(
            f"{owner} got unknown option(s) {unknown}; known options are {sorted(allowed)}"
        )
