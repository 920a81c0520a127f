"""The rank and null space of the observability matrix in exact rational arithmetic
(sympy, an optional dependency: ``pip install 'estim[symbolic]'``).

The observability matrix is translated from CasADi to sympy once; at each point
every variable is replaced by a nearby rational (a multiple of 1/256), and the rank
and null space are computed exactly. Practical for small models.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from estim.observability.lie import numeric_rank


def symbolic_rank(O_fun: ca.Function, pts: list[list[np.ndarray]], n: int
                  ) -> tuple[list[int], np.ndarray, float, np.ndarray]:
    """Exact rank at every point of ``pts``, and at the first one the singular values,
    the gap and a basis of the null space (one vector a row).

    ``O_fun`` maps the variables of a point to the dense observability matrix with
    ``n`` columns.
    """
    try:
        import sympy as sp
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("method='symbolic' needs sympy: pip install 'estim[symbolic]'") from exc
    from estim._sympy import function_to_sympy

    syms, outs = function_to_sympy(O_fun)
    n_rows = O_fun.size1_out(0)
    out = outs[0]
    dense = O_fun.sparsity_out(0).is_dense()
    if not dense:
        raise ValueError("internal: the observability matrix must be dense")
    M = sp.Matrix(n_rows, n, lambda i, j: out[i + j * n_rows])
    flat = [s for group in syms for s in group]

    def at(pt: list[np.ndarray]):
        vals = np.concatenate([np.ravel(v) for v in pt])
        return M.subs({s: sp.Rational(round(v * 256), 256) for s, v in zip(flat, vals,
                                                                            strict=True)})

    first = at(pts[0])
    ranks = [int(first.rank())] + [int(at(pt).rank()) for pt in pts[1:]]
    _, s, gap, _ = numeric_rank(np.array(first.evalf(), dtype=float), 1e-12)
    null = first.nullspace()
    N = np.array([[float(v) for v in vec] for vec in null]) if null else np.zeros((0, n))
    return ranks, s, (gap if ranks[0] < n else float("inf")), N
