r"""Triangular factors for the square-root filters: QR triangularisation, rank-one
Cholesky downdates and triangular solves, written with CasADi SX operations (unrolled,
so they compile into a filter's step) and their numpy counterparts for the data.

A covariance :math:`P` is carried as a lower-triangular factor :math:`S` with
:math:`P = S S^\top`. A sum of covariances :math:`\sum_i A_i A_i^\top = A A^\top`,
:math:`A = [A_1, A_2, \dots]` (:math:`n \times m`, :math:`m \ge n`), has the factor
:math:`\operatorname{tria}(A) = L` from the QR factorisation :math:`A^\top = Q_r R`,
:math:`L = R^\top` (Householder reflections applied to the rows of :math:`A`), with a
non-negative diagonal: the Cholesky factor of :math:`A A^\top` where that is definite,
and a valid factor where it is only semi-definite. The factor is formed by orthogonal
transformations of :math:`A`, never from :math:`A A^\top`, which squares the condition
number.

References
----------
G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., 2013, sec. 5.1-5.2
(Householder QR) and 6.5.4 (Cholesky updating and downdating);
M. Grewal, A. Andrews, *Kalman Filtering: Theory and Practice*, 4th ed., 2015, ch. 7.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

__all__ = ["checked_cholesky", "cholesky", "cholesky_downdate", "psd_factor", "solve_lower",
           "tria", "tria_numpy"]


def tria(A: ca.SX) -> ca.SX:
    r"""Lower-triangular :math:`L` (``(n, n)``) with :math:`L L^\top = A A^\top` and a
    non-negative diagonal, from Householder reflections of the rows of ``A``.

    Parameters
    ----------
    A : (n, m) SX, m >= n
        The pre-array.

    Returns
    -------
    (n, n) SX
        Row ``i``'s reflection zeroes ``A[i, i+1:]``; a zero row leaves a zero column
        (a semi-definite :math:`A A^\top` is factored without division by zero).
    """
    W = ca.SX(A)
    n, m = W.shape
    if m < n:
        raise ValueError(f"tria needs at least as many columns as rows, got {n}x{m}")
    for i in range(n):
        x = W[i, i:]
        r = ca.sqrt(ca.sumsqr(x))
        s = ca.if_else(x[0] >= 0, 1, -1)
        if i + 1 < n:
            # the reflection I - 2 v v' / v'v with v = x + s r e_1, written with v / r
            # (entries at most 2) and 2 r^2 / v'v = 1 / (1 + |x_1| / r): no square of a
            # tiny r to overflow (a measurement noise of 1e-300 leaves the rows below
            # of order 1 and this row of order 1e-150)
            scaled = ca.if_else(r > 0, x / r, ca.DM.zeros(1, m - i))
            w = ca.horzcat(scaled[0] + s, scaled[1:]) if m - i > 1 else scaled[0] + s
            gain = ca.if_else(r > 0, 1 / (1 + ca.fabs(scaled[0])), 0)
            rows = W[i + 1:, i:]
            rows = rows - ((rows @ w.T) * gain) @ w
            W[i + 1:, i:] = rows
            W[i + 1:, i] = -s * W[i + 1:, i]  # the diagonal entry -s r made r >= 0
        W[i, i] = r
        if i + 1 < m:
            W[i, i + 1:] = ca.SX.zeros(1, m - i - 1)
    return W[:, :n]


def cholesky_downdate(L: ca.SX, v: ca.SX) -> ca.SX:
    r"""Lower-triangular :math:`L'` with :math:`L' L'^\top = L L^\top - v v^\top`.

    The rotations of Golub & Van Loan (sec. 6.5.4): column by column
    :math:`r = \sqrt{L_{kk}^2 - v_k^2}`, :math:`c = r / L_{kk}`,
    :math:`s = v_k / L_{kk}`, :math:`L_{k+1:,k} \leftarrow (L_{k+1:,k} - s v_{k+1:})/c`,
    :math:`v_{k+1:} \leftarrow c v_{k+1:} - s L_{k+1:,k}`. Where the result would not be
    positive definite a square root of a negative number (NaN) marks it.

    Parameters
    ----------
    L : (n, n) SX
        Lower-triangular factor with a positive diagonal.
    v : (n,) SX

    Returns
    -------
    (n, n) SX
    """
    L = ca.SX(L)
    v = ca.SX(v)
    n = L.shape[0]
    for k in range(n):
        Lkk = L[k, k]
        r = ca.sqrt(Lkk ** 2 - v[k] ** 2)
        c, s = r / Lkk, v[k] / Lkk
        L[k, k] = r
        if k + 1 < n:
            col = (L[k + 1:, k] - s * v[k + 1:]) / c
            L[k + 1:, k] = col
            v[k + 1:] = c * v[k + 1:] - s * col
    return L


def cholesky(A: ca.SX) -> ca.SX:
    r"""The lower-triangular :math:`L` with :math:`L L^\top = A` of a symmetric positive
    definite ``A`` ``(n, n)``, as expressions (Cholesky–Banachiewicz, row by row); not
    finite where ``A`` is not definite."""
    n = A.shape[0]
    L = [[ca.SX(0)] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = A[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), ca.SX(0))
            L[i][j] = ca.sqrt(acc) if i == j else acc / L[j][j]
    return ca.vertcat(*[ca.horzcat(*row) for row in L]) if n else ca.SX(0, 0)


def checked_cholesky(A, tol: float = 0.0) -> tuple[ca.SX, ca.SX]:
    r"""Lower Cholesky factor :math:`L` (:math:`L L^\top = A`, from the upper triangle of
    ``A`` as LAPACK's upper factorisation reads it) and whether every pivot is positive
    (with ``tol``, above ``tol`` times the largest diagonal entry: a rank-deficient
    matrix, definite only by rounding, is not)."""
    n = A.shape[0]
    L = [[ca.SX(0)] * n for _ in range(n)]
    definite = ca.SX(1)
    floor = tol * ca.mmax(ca.diag(A)) if tol else 0
    for j in range(n):
        d = A[j, j] - sum((L[j][k] ** 2 for k in range(j)), ca.SX(0))
        definite = ca.logic_and(definite, d > floor)
        L[j][j] = ca.sqrt(d)
        for i in range(j + 1, n):
            L[i][j] = (A[j, i] - sum((L[i][k] * L[j][k] for k in range(j)), ca.SX(0))) / L[j][j]
    return ca.vertcat(*[ca.horzcat(*row) for row in L]), definite


def solve_lower(L: ca.SX, B: ca.SX, transpose: bool = False) -> ca.SX:
    r""":math:`L^{-1} B` (or :math:`L^{-\top} B` with ``transpose``) by substitution, for
    a lower-triangular ``L`` ``(n, n)`` and ``B`` ``(n, k)``."""
    n = L.shape[0]
    rows: list = [None] * n
    order = range(n - 1, -1, -1) if transpose else range(n)
    for i in order:
        acc = B[i, :]
        done = range(i + 1, n) if transpose else range(i)
        for j in done:
            acc = acc - (L[j, i] if transpose else L[i, j]) * rows[j]
        rows[i] = acc / L[i, i]
    return ca.vertcat(*rows) if n else ca.SX(B)


def tria_numpy(A: np.ndarray) -> np.ndarray:
    r"""The numpy counterpart of :func:`tria`: lower-triangular :math:`L` with
    :math:`L L^\top = A A^\top` and a non-negative diagonal (``A`` ``(n, m)``,
    ``m >= n``), from LAPACK's QR of :math:`A^\top`."""
    L = np.linalg.qr(np.asarray(A, dtype=float).T).R.T
    return L * np.where(np.diag(L) < 0, -1.0, 1.0)


def psd_factor(A: np.ndarray) -> np.ndarray:
    r"""Lower-triangular :math:`L` with :math:`L L^\top = A` for a symmetric positive
    semi-definite ``A`` (``(n, n)``): the Cholesky factor where ``A`` is definite,
    otherwise the triangularised square root :math:`\operatorname{tria}(V \sqrt{\Lambda})`
    of its eigendecomposition (negative rounding-level eigenvalues taken as 0)."""
    A = np.asarray(A, dtype=float)
    try:
        return np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (A + A.T))
        return tria_numpy(V * np.sqrt(np.maximum(w, 0.0)))
