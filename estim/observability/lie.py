r"""The observability matrix from Lie derivatives, and its rank at random points.

For a continuous model the rows of order :math:`k` are the state gradient of the
:math:`k`-th time derivative of the output, by extended Lie derivatives

.. math::
    \frac{d}{dt}\varphi(x, u, \dot u, \dots) = \frac{\partial\varphi}{\partial x} f
    + \sum_j \frac{\partial\varphi}{\partial u^{(j)}} u^{(j+1)}

(the input derivatives free variables with inputs varying, zero with inputs
constant); for a discrete model those of :math:`y_k = h(F^k(x))`. PyNOA's
arrangements apply words of the control-affine fields :math:`f_0, f_1, \dots`
instead. The rank is taken in floating point from the singular values of the
row-normalised matrix (:func:`numeric_rank`), at random points drawn by
:func:`points` inside the model's bounds.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_vector
from estim.model import Model

ARRANGEMENTS = ("permutation", "combination", "drift2ndOrder")


def control_affine_fields(model: Model) -> tuple[ca.SX, ca.SX, list[ca.SX]]:
    """``(x, f0, [f1, ...])`` as CasADi expressions in ``x`` if ``f`` is affine in ``u``."""
    if model.f_c is None:
        raise ValueError("arrangements of Lie derivatives need a continuous model")
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    p = ca.DM(model.p)
    f = model.f_c(x, u, p)
    B = ca.jacobian(f, u)
    if ca.depends_on(B, u):
        raise ValueError("the arrangements need a control-affine model (f linear in u)")
    f0 = ca.substitute(f, u, ca.DM.zeros(model.nu))
    return x, f0, [B[:, i] for i in range(model.nu)]


def rows(model: Model, order: int, inputs: str, arrangement: str | None
         ) -> tuple[list[ca.SX], list[ca.SX]]:
    """Symbolic rows of the observability matrix up to ``order`` and the variables
    they depend on (x first). Returns ``(rows_per_order, variables)``."""
    if arrangement is not None:
        return _arranged_rows(model, order, arrangement)
    nx, nu = model.nx, model.nu
    p = ca.DM(model.p)
    x = ca.SX.sym("x", nx)
    us = [ca.SX.sym(f"u{j}", nu) for j in range(order + 1)]  # u, u', u'', ...
    if model.f_c is None:  # discrete: y_k = h(F^k(x)) with an input sequence
        out, xk = [], x
        for k in range(order + 1):
            uk = us[0] if inputs == "constant" else us[k]
            out.append(ca.jacobian(model.H(xk, uk, p), x))
            xk = model.F(xk, uk, p)
        return out, [x, *(us[:1] if inputs == "constant" else us)]
    f = model.f_c(x, us[0], p)
    phi = model.H(x, us[0], p)
    out = [ca.jacobian(phi, x)]
    for k in range(1, order + 1):
        dphi = ca.jtimes(phi, x, f)
        if inputs == "varying" and nu:
            for j in range(k):
                dphi += ca.jtimes(phi, us[j], us[j + 1])
        phi = dphi
        out.append(ca.jacobian(phi, x))
    used = us[:1] if inputs == "constant" or not nu else us
    return out, [x, *used]


def _arranged_rows(model: Model, order: int, arrangement: str
                   ) -> tuple[list[ca.SX], list[ca.SX]]:
    """:func:`rows` by an arrangement of Lie derivatives along the control-affine
    fields (the output independent of the inputs)."""
    nx, nu = model.nx, model.nu
    p = ca.DM(model.p)
    x, f0, fs = control_affine_fields(model)
    u = ca.SX.sym("u", nu)
    if ca.depends_on(model.H(x, u, p), u):
        raise ValueError("the arrangements need an output independent of the inputs; use "
                         "inputs='varying' (extended Lie derivatives) instead")
    h = model.H(x, ca.DM.zeros(nu), p)
    fields = [f0, *fs]
    all_words = words(arrangement, len(fields), order)
    out = []
    cache: dict[tuple[int, ...], ca.SX] = {(): h}
    for k in range(order + 1):
        exprs = []
        for w in (w for w in all_words if len(w) == k):
            phi = cache[w[:-1]] if k else h
            if k:
                phi = ca.jtimes(phi, x, fields[w[-1]])
                cache[w] = phi
            exprs.append(phi)
        out.append(ca.jacobian(ca.vertcat(*exprs), x) if exprs else ca.SX(0, nx))
    return out, [x]


def words(arrangement: str, m: int, order: int) -> list[tuple[int, ...]]:
    """Sequences of vector-field indices (0 = drift) applied to ``h``, by order.

    ``"permutation"``: every ordered sequence of fields, repetitions included
    (PyNOA's notebooks append ``f1 f1``, ``f1 f1 f1``, ...);
    ``"combination"``: every increasing sequence of distinct fields;
    ``"drift2ndOrder"``: order 1 all fields, order 2 only pairs of the drift
    with an input field.
    """
    out: list[tuple[int, ...]] = [()]
    for k in range(1, order + 1):
        if arrangement == "permutation":
            out += list(itertools.product(range(m), repeat=k))
        elif arrangement == "combination":
            out += list(itertools.combinations(range(m), k))
        else:
            if k == 1:
                out += [(i,) for i in range(m)]
            elif k == 2:
                out += [(0, i) for i in range(1, m)]
    return out


def fix_inputs(model: Model, values: Mapping[str, float]) -> Model:
    """The model with some inputs fixed to given values (the others stay inputs)."""
    unknown = set(values) - set(model.input_names)
    if unknown:
        raise ValueError(f"inputs names unknown inputs {sorted(unknown)}; "
                         f"inputs are {model.input_names}")
    free = [n for n in model.input_names if n not in values]
    p = ca.DM(model.p)

    def full(u: ca.SX) -> Any:
        parts: list[Any] = []
        j = 0
        for name in model.input_names:
            if name in values:
                parts.append(ca.DM(float(values[name])))
            else:
                parts.append(u[j])
                j += 1
        return ca.vertcat(*parts) if parts else ca.DM.zeros(0, 1)

    H = model.H
    rhs = model.f_c if model.f_c is not None else model.F  # ode or dynamics

    def equation(x: ca.SX, u: ca.SX, _: Mapping[str, ca.SX]) -> Any:
        return rhs(x, full(u), p)

    return Model(states=model.state_names, outputs=model.output_names, inputs=free,
                 output=lambda x, u, _: H(x, full(u), p), dt=model.dt,
                 lower=model.lower, upper=model.upper, name=model.name,
                 ode=equation if model.continuous else None,
                 dynamics=None if model.continuous else equation)


# ------------------------------------------------------------------- numerics
def points(model: Model, variables: list[ca.SX], n_points: int, at: ArrayLike | None,
           rng: np.random.Generator) -> list[list[np.ndarray]]:
    """Random evaluation points: states inside finite bounds, inputs and their
    derivatives standard normal; ``at`` fixes the state of the first points."""
    pts = []
    lo, hi = model.lower, model.upper
    ats = [] if at is None else [as_vector(a, model.nx, "at") for a in np.atleast_2d(at)]
    for i in range(max(n_points, len(ats))):
        if i < len(ats):
            x = ats[i]
        else:
            x = rng.standard_normal(model.nx) * 1.5
            both = np.isfinite(lo) & np.isfinite(hi)
            x[both] = lo[both] + (hi[both] - lo[both]) * rng.uniform(0.1, 0.9, both.sum())
            only_lo = np.isfinite(lo) & ~np.isfinite(hi)
            x[only_lo] = lo[only_lo] + rng.uniform(0.2, 2.0, only_lo.sum())
            only_hi = ~np.isfinite(lo) & np.isfinite(hi)
            x[only_hi] = hi[only_hi] - rng.uniform(0.2, 2.0, only_hi.sum())
        pts.append([x] + [rng.standard_normal(v.numel()) for v in variables[1:]])
    return pts


def input_samples(pt: list[np.ndarray], variables: list[ca.SX], inputs: str,
                  arrangement: str | None, count: int, rng: np.random.Generator
                  ) -> list[list[np.ndarray]]:
    """The point with ``count`` random draws of the input variables (same state).

    With inputs varying, the codistribution is spanned over all input histories:
    rows at several values of ``(u, u', u'', ...)`` at one state belong to the
    same matrix and reach its generic rank at a low order. Constant inputs and
    the arrangements (inputs already factored out) use the point as it is.
    """
    if inputs != "varying" or arrangement is not None or len(variables) == 1:
        return [pt]
    return [pt] + [[pt[0]] + [rng.standard_normal(v.numel()) for v in variables[1:]]
                   for _ in range(count - 1)]


def extend(pt: list[np.ndarray], variables: list[ca.SX], rng: np.random.Generator
           ) -> list[np.ndarray]:
    """Points for a higher order need values for the new input-derivative variables."""
    out = list(pt[:len(variables)])
    for v in variables[len(out):]:
        out.append(rng.standard_normal(v.numel()))
    return out


def numeric_rank(obs: np.ndarray, rtol: float, scale: float | None = None
                 ) -> tuple[int, np.ndarray, float, np.ndarray]:
    """Rank of the row-normalised matrix from its singular values, and the gap.

    Rows below ``1e-12 * scale`` count as zero and are dropped (``scale``: the largest
    row's norm, of this matrix by default; over a grid of points, the grid's, so that
    where every row vanishes the rank is 0 rather than that of rounding errors scaled
    to unit length).

    Returns ``(rank, s, gap, A)``: the singular values ``s`` (padded with zeros to the
    number of columns), ``gap = s[rank-1] / s[rank]`` (inf at full rank) and the
    row-normalised matrix ``A`` (rows of zero norm dropped).
    """
    norms = np.linalg.norm(obs, axis=1)
    top = (float(norms.max()) if len(norms) else 0.0) if scale is None else float(scale)
    keep = norms > 1e-12 * max(top, 1e-300) if len(norms) else norms > 0
    A = obs[keep] / norms[keep, None] if keep.any() else np.zeros((1, obs.shape[1]))
    s = np.linalg.svd(A, compute_uv=False)
    s = np.concatenate([s, np.zeros(obs.shape[1] - len(s))])
    top = max(float(s[0]), 1e-300)
    rank = int(np.sum(s > rtol * top))
    gap = float(s[rank - 1] / s[rank]) if 0 < rank < len(s) and s[rank] > 0 else float("inf")
    return rank, s, gap, A
