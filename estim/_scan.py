"""A step function scanned over a record in one CasADi Function, built in blocks."""

from __future__ import annotations

from collections.abc import Collection

import casadi as ca
import numpy as np


def blocked_scan(step: ca.Function, N: int, sequences: Collection[int], *,
                 expand: bool = True) -> ca.Function:
    r"""``step`` (``(s, ...) -> (s_new, ...)``) scanned over ``N`` samples.

    The inputs numbered in ``sequences`` take one column per sample (``N`` columns);
    the others are the same at every sample. The result maps ``(s, ...)`` to the last
    state ``s_N`` and, for each other output of ``step``, its ``N`` values side by side.

    It is built as blocks of about :math:`\sqrt N` steps (``mapaccum``) scanned in turn,
    so that the graph and those of its derivatives hold :math:`O(\sqrt N)` calls instead
    of :math:`N` (whose construction would dominate a short run). An ``SXFunction``
    step is expanded within each block (no call overhead per step) unless ``expand``
    is False (for C code generation: the step's code once, called in loops).
    """
    B = max(8, int(np.sqrt(N)))
    n_blocks, rest = divmod(N, B)
    seq = set(sequences)
    args = [ca.MX.sym(n, step.size1_in(i), N if i in seq else 1)
            for i, n in enumerate(step.name_in())]
    n_out = step.n_out()

    def run(fun, s, lo, hi):
        return fun(s, *[a[:, lo:hi] if i + 1 in seq else a for i, a in enumerate(args[1:])])

    def last_state(fun):  # the scan's state output reduced to its last column
        sym = [ca.MX.sym(n, fun.size_in(i)) for i, n in enumerate(fun.name_in())]
        out = fun(*sym)
        return ca.Function(fun.name() + "_last", sym, [out[0][:, -1], *out[1:]],
                           fun.name_in(), fun.name_out())

    parts, s = [], args[0]
    if n_blocks:
        block = last_state(step.mapaccum(f"{step.name()}_{B}", B))
        if expand and step.is_a("SXFunction"):
            block = block.expand()
        outer = last_state(block.mapaccum(f"{step.name()}_{n_blocks}x{B}", n_blocks))
        s, *out = run(outer, s, 0, n_blocks * B)
        parts.append(out)
    if rest:
        s, *out = run(last_state(step.mapaccum(f"{step.name()}_{rest}", rest)), s,
                      n_blocks * B, N)
        parts.append(out)
    outputs = [s] + [ca.horzcat(*[p[j] for p in parts]) for j in range(n_out - 1)]
    return ca.Function(f"{step.name()}_scan_{N}", args, outputs, step.name_in(),
                       step.name_out())
