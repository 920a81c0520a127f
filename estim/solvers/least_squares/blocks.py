r"""Dense blocks of the block-tridiagonal Gauss-Newton system, factored and solved in SX.

The structured solver (:mod:`estim.solvers.least_squares.gauss_newton`) eliminates one
:math:`n_x \times n_x` block per slot. Each symmetric block is factored as
:math:`S = L\,\mathrm{diag}(D)\,L^\top` without pivoting and without square roots
(:func:`ldl`, about :math:`n^3/6` operations; indefinite nonsingular blocks of exact
Hessians work too), and the products of the elimination are formed from the factors
(:func:`lower_solve`, :func:`lower_transposed_solve`, :func:`ldl_solve`); symmetric
products compute their lower triangle only (:func:`sym_product`, :func:`gram`).
Everything here builds CasADi SX expressions, unrolled over the block's entries.

References
----------
G. H. Golub, C. F. Van Loan, *Matrix Computations*, 4th ed., sec. 4.1 (LDLᵀ);
J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., sec. 10.3 (Levenberg-Marquardt).
"""

from __future__ import annotations

from typing import Any

import casadi as ca

__all__ = ["damp", "gram", "ldl", "ldl_solve", "lower_solve", "lower_transposed_solve",
           "sym_product", "sym_solve", "total"]

# The scalar operations below call SX.binary directly: the same operation as the
# operators ``+ - *`` (which reach it through an overload dispatch costing about 13
# microseconds a call, against 2), so building the blocks of a seven-state model takes
# a few milliseconds instead of tens.
_binary = ca.SX.binary
_ADD, _SUB, _MUL = ca.OP_ADD, ca.OP_SUB, ca.OP_MUL


def total(terms) -> ca.SX:
    """Sum of SX terms, ``SX(0)`` when there are none (adding to zero folds away)."""
    out = ca.SX(0)
    for t in terms:
        out = _binary(_ADD, out, t)
    return out


def _dot(a, b, n: int) -> ca.SX:
    """``a[0] b[0] + ... + a[n-1] b[n-1]`` summed in that order (scalar SX lists),
    ``SX(0)`` when ``n = 0``."""
    return total(_binary(_MUL, a[m], b[m]) for m in range(n))


def _entries(M) -> list:
    """The entries of an SX matrix as 1x1 SX, column-major: ``M[i, j]`` is entry
    ``i + j * M.shape[0]`` (structural zeros included, as indexing gives them)."""
    return ca.vertsplit(ca.vec(M))


def ldl(S: ca.SX) -> tuple[list[list[Any]], list[Any]]:
    r"""Factors of a symmetric SX block, :math:`S = L\,\mathrm{diag}(D)\,L^\top`, no pivoting.

    Reads the lower triangle only. Returns ``(L, inv_D)`` as nested lists
    (unit lower triangular ``L``, reciprocals of ``D``): about :math:`n^3/6`
    operations and no square roots, so indefinite nonsingular blocks (exact
    Hessians) work too. The products :math:`L_{ik} D_k` are kept from the
    elimination rather than recomputed (Golub and Van Loan, alg. 4.1.2).
    """
    n = S.shape[0]
    Se = _entries(S)
    L: list[list[Any]] = [[None] * n for _ in range(n)]
    LD: list[list[Any]] = [[None] * n for _ in range(n)]  # L[i][k] * D[k]
    inv_D: list[Any] = [None] * n
    for k in range(n):
        Dk = _binary(_SUB, Se[k + k * n], _dot(L[k], LD[k], k))
        inv_D[k] = 1 / Dk
        for i in range(k + 1, n):
            LD[i][k] = _binary(_SUB, Se[i + k * n], _dot(L[i], LD[k], k))
            L[i][k] = _binary(_MUL, LD[i][k], inv_D[k])
    return L, inv_D


def lower_solve(L, B) -> ca.SX:
    """:math:`L^{-1} B` for unit lower triangular ``L`` (nested list)."""
    n, rows = len(L), B.shape[0]
    Be = _entries(B)
    cols = []
    for c in range(B.shape[1]):
        z: list[Any] = [None] * n
        for i in range(n):
            z[i] = _binary(_SUB, Be[i + c * rows], _dot(L[i], z, i))
        cols.append(ca.vertcat(*z))
    return ca.horzcat(*cols)


def lower_transposed_solve(L, b) -> ca.SX:
    r""":math:`L^{-\top} b` for unit lower triangular ``L`` (nested list or SX) and a vector."""
    if isinstance(L, list):
        n = len(L)
        rows = [[L[m][i] for m in range(n)] for i in range(n)]  # the columns of L
    else:
        n, Le = L.shape[0], _entries(L)
        rows = [Le[i * n:(i + 1) * n] for i in range(n)]
    be = _entries(b)
    x: list[Any] = [None] * n
    for i in range(n - 1, -1, -1):
        x[i] = _binary(_SUB, be[i], _dot(rows[i][i + 1:], x[i + 1:], n - 1 - i))
    return ca.vertcat(*x)


def ldl_solve(L: list[list[Any]], inv_D: list[Any], B: ca.SX) -> ca.SX:
    r"""Solve :math:`L D L^\top X = B` column by column (``B`` an SX matrix)."""
    Z = ca.diag(ca.vertcat(*inv_D)) @ lower_solve(L, B)
    return ca.horzcat(*[lower_transposed_solve(L, Z[:, c]) for c in range(B.shape[1])])


def sym_solve(S, B) -> ca.SX:
    """Solve :math:`S X = B` for a symmetric SX block (see :func:`ldl`)."""
    L, inv_D = ldl(S)
    return ldl_solve(L, inv_D, B)


def sym_product(A, B) -> ca.SX:
    """:math:`A^\\top B` for a product known to be symmetric: the lower triangle is
    computed, the upper one mirrors it (same SX nodes)."""
    n = A.shape[1]
    a, b = ca.horzsplit(A), ca.horzsplit(B)
    out: list[Any] = [None] * (n * n)  # column-major
    for j in range(n):
        for i in range(j, n):
            out[i + j * n] = out[j + i * n] = ca.dot(a[i], b[j])
    return ca.reshape(ca.vertcat(*out), n, n)


def gram(A) -> ca.SX:
    """:math:`A^\\top A`, lower triangle computed and mirrored."""
    return sym_product(A, A)


def damp(D, lam) -> ca.SX:
    """Ridge of 1e-12 of the largest diagonal entry (leaves stationary points
    unchanged, keeps singular blocks factorable) plus Marquardt damping
    ``lam |diag D|``.

    The undamped iterations go without (fewer operations); a solve switches
    to this form, with ``lam = 0`` for the ridge alone, once a direction comes
    out non-finite.
    """
    dj = ca.fabs(ca.diag(D))
    return D + ca.diag(1e-12 * ca.fmax(ca.mmax(dj), 1e-300) + lam * dj)
