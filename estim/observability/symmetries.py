"""Continuous symmetries: the null space of the observability matrix, and what it says
about each state.

A symmetry is a direction along which the state can move without changing the
output. A state is observable iff every symmetry has a zero component on it; states
coupled only through symmetries among themselves are jointly observable (some
combination of them is); a state that can move alone is unobservable.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def null_space(A: np.ndarray, rank: int) -> np.ndarray:
    """An orthonormal basis ``(n - rank, n)`` of the null space of ``A`` ``(m, n)`` of
    the given rank, from its right singular vectors."""
    n = A.shape[1]
    _, _, Vt = np.linalg.svd(A)
    return Vt[rank:] if rank < n else np.zeros((0, n))


def sparsify(N: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Reduced row echelon form of a null-space basis (rows), entries below tol zeroed,
    each row scaled so its largest entry is 1."""
    A = N.copy()
    r, n = A.shape
    row = 0
    for col in range(n):
        if row >= r:
            break
        piv = row + int(np.argmax(np.abs(A[row:, col])))
        if abs(A[piv, col]) < 1e-8:
            continue
        A[[row, piv]] = A[[piv, row]]
        A[row] /= A[row, col]
        for i in range(r):
            if i != row:
                A[i] -= A[i, col] * A[row]
        row += 1
    A[np.abs(A) < tol] = 0.0
    for i in range(r):
        m = np.max(np.abs(A[i]))
        if m > 0:
            A[i] /= A[i][np.argmax(np.abs(A[i]))]
    return A


def classify(names: Sequence[str], N: np.ndarray, tol: float = 1e-6
             ) -> tuple[list[str], list[list[str]], list[str]]:
    """Observable / jointly observable groups / unobservable from a null-space basis
    ``N`` (one symmetry a row)."""
    n = len(names)
    if N.shape[0] == 0:
        return list(names), [], []
    Q, _ = np.linalg.qr(N.T)  # orthonormal basis of the null space
    support = np.abs(N) > tol
    observable = [names[i] for i in range(n) if not support[:, i].any()]
    unobservable = [names[i] for i in range(n) if np.linalg.norm(Q.T[:, i]) > 1 - tol]
    rest = [i for i in range(n) if support[:, i].any() and names[i] not in unobservable]
    # group the rest by shared symmetries (connected components)
    groups: list[list[str]] = []
    seen: set[int] = set()
    for i in rest:
        if i in seen:
            continue
        comp: set[int] = set()
        stack = [i]
        while stack:
            j = stack.pop()
            if j in comp:
                continue
            comp.add(j)
            for row in support:
                if row[j]:
                    stack.extend(int(k) for k in np.flatnonzero(row) if k in rest)
        seen |= comp
        groups.append([names[k] for k in sorted(comp)])
    return observable, groups, unobservable
