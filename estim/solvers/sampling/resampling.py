r"""Resampling of weighted particles, and the effective sample size.

Given normalised weights :math:`W_1..W_N` (:math:`\sum_i W_i = 1`), a resampling
scheme draws :math:`N` ancestor indices :math:`a_j` with
:math:`E[\#\{j: a_j = i\}] = N W_i` (unbiased). The schemes differ in the
variance of those counts (Douc, Cappé, Moulines 2005; Chopin, Papaspiliopoulos
2020, ch. 9):

``"multinomial"``
    :math:`N` independent draws from the weights.
``"stratified"``
    one uniform draw in each stratum :math:`[(j-1)/N, j/N)`.
``"systematic"``
    one uniform draw :math:`U`, the points :math:`(j - 1 + U)/N` (lowest variance
    in practice, the default of most particle filters).
``"residual"``
    :math:`\lfloor N W_i \rfloor` copies of each particle, the rest drawn
    multinomially from the residual weights.

Every scheme inverts the cumulative weights by binary search
(:func:`numpy.searchsorted`), so a particle of weight zero is never drawn.

References
----------
R. Douc, O. Cappé, E. Moulines, "Comparison of resampling schemes for particle
filtering", ISPA 2005; N. Chopin, O. Papaspiliopoulos, *An Introduction to
Sequential Monte Carlo*, Springer 2020, ch. 9.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = ["distinct_particles", "RESAMPLING", "effective_sample_size", "resample"]

#: The resampling schemes by name.
RESAMPLING = ("systematic", "stratified", "residual", "multinomial")


def effective_sample_size(W: np.ndarray) -> float:
    r"""Kish's effective sample size :math:`1 / \sum_i W_i^2` of normalised weights
    ``W`` ``(N,)``: :math:`N` for equal weights, 1 when one particle holds them all."""
    return float(1.0 / (W * W).sum())  # (not np.dot: no threaded BLAS call)


def distinct_particles(X: np.ndarray) -> int:
    """The number of distinct particles among the columns of ``X`` ``(nx, N)``: the
    distinct values of one fixed generic combination of the rows (two different
    particles have the same combination with probability zero)."""
    weights = np.sqrt(np.arange(2.0, 2.0 + X.shape[0]))  # square roots of 2, 3, ...
    return int(np.unique(weights @ X).size)


@lru_cache(maxsize=8)
def _indices(N: int) -> np.ndarray:
    """``arange(N)``, kept (read-only) for the particle counts of every step."""
    out = np.arange(N)
    out.flags.writeable = False
    return out


def _inverse(W: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Indices ``i`` with ``C_{i-1} <= u < C_i`` for the cumulative weights ``C``."""
    c = np.cumsum(W)
    c[-1] = 1.0  # rounding must not leave a point beyond the last particle
    return np.searchsorted(c, u, side="right")


def resample(W: np.ndarray, scheme: str, rng: np.random.Generator,
             n: int | None = None) -> np.ndarray:
    """Ancestor indices ``(n,)`` (default ``n = len(W)``) drawn from the normalised
    weights ``W`` ``(N,)`` by ``scheme`` (see the module), with the generator ``rng``."""
    N = len(W)
    n = N if n is None else n
    if scheme == "systematic":  # the points (j + U) / n, counted per particle: O(N)
        c = np.cumsum(W)
        c *= n
        c[-1] = n
        c -= rng.random()
        edges = np.ceil(c, out=c).astype(np.intp)  # points below each cumulative weight
        counts = np.empty(N, dtype=np.intp)
        counts[0] = edges[0]
        np.subtract(edges[1:], edges[:-1], out=counts[1:])
        return np.repeat(_indices(N), counts)
    if scheme == "stratified":
        return _inverse(W, (rng.random(n) + np.arange(n)) / n)
    if scheme == "multinomial":
        return _inverse(W, rng.random(n))
    if scheme == "residual":
        copies = np.floor(n * W).astype(np.intp)
        left = n - int(copies.sum())
        fixed = np.repeat(np.arange(N), copies)
        if left == 0:
            return fixed
        rest = n * W - copies
        return np.concatenate([fixed, _inverse(rest / rest.sum(), rng.random(left))])
    raise ValueError(f"resampling must be one of {', '.join(map(repr, RESAMPLING))}, "
                     f"got {scheme!r}")
