r"""Observability and identifiability analysis: rank condition and continuous symmetries.

For a continuous model :math:`\dot x = f(x, u)`, :math:`y = h(x, u)`, the
observability codistribution is spanned by the gradients of the output and
its time derivatives,

.. math::
    \mathcal O_k = \frac{\partial}{\partial x}
    \begin{bmatrix} h \\ \dot h \\ \vdots \\ h^{(k)} \end{bmatrix},
    \qquad
    \frac{d}{dt}\varphi(x, u, \dot u, \dots) = \frac{\partial\varphi}{\partial x} f
    + \sum_j \frac{\partial\varphi}{\partial u^{(j)}} u^{(j+1)},

(extended Lie derivatives: with ``inputs="varying"`` the input derivatives are
free variables; with ``inputs="constant"`` they are zero). The system is
locally weakly observable where :math:`\mathcal O_k` has rank :math:`n`
(Hermann & Krener 1977). Where it does not, the null space of
:math:`\mathcal O_k` holds the continuous symmetries (Martinelli): directions
along which the state can move without changing the output. A state is
observable iff every symmetry has a zero component on it; states coupled
only through symmetries among themselves are jointly observable (some
combination of them is); a state that can move alone is unobservable.

The rank is computed in floating point at several random points, with the
rows normalised, from the singular values and the gap that separates them,
never by exact-arithmetic pivoting on floating-point numbers (which
overestimates ranks). ``method="symbolic"`` (sympy) evaluates the same
matrix exactly at random rational points.

Local weak observability is a local, generic property: it says that nearby
states are distinguishable by the output over short times, not that the
state is globally determined (Lorenz with ``y = x3`` passes the rank test
although ``(x1, x2) -> (-x1, -x2)`` leaves the output unchanged).

References
----------
R. Hermann, A. J. Krener, "Nonlinear controllability and observability",
IEEE TAC 22(5), 1977; A. Martinelli, "Continuous symmetries and
observability properties in autonomous navigation", INRIA RR-7049, 2010;
A. Martinelli, "Observability: a new theory based on the group of
invariance", SIAM, 2020.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import (
    _numeric_array,
    as_choice,
    as_covariance,
    as_float,
    as_input_table,
    as_int,
    as_seed,
    as_vector,
    check_keywords,
)
from estim.model import Model

ARRANGEMENTS = ("permutation", "combination", "drift2ndOrder")


@dataclass
class ObservabilityReport:
    """Result of :func:`analyze`.

    Attributes
    ----------
    model : str
    state_names : list of str
    rank : int
        Generic rank of the observability matrix (the largest over the points).
    n : int
        Number of states.
    order : int
        Highest derivative order used.
    observable, unobservable : list of str
    jointly_observable : list of list of str
        Groups of states of which only combinations are observable.
    symmetries : (n - rank, n) array
        A sparsified basis of the null space at the first point, one row per
        symmetry, in state coordinates.
    singular_values : (n,) array
        Of the row-normalised observability matrix at the first point.
    gap : float
        ``s[rank-1] / s[rank]`` at that point (inf at full rank): the margin
        that decided the rank.
    ranks : list of int
        Rank at every point; ``point_dependent`` is True when they differ.
    rows : int
        Rows of the observability matrix.
    method, inputs : str
    seconds : float
        Wall time of the analysis.
    """

    model: str
    state_names: list[str]
    rank: int
    n: int
    order: int
    observable: list[str]
    jointly_observable: list[list[str]]
    unobservable: list[str]
    symmetries: np.ndarray
    singular_values: np.ndarray
    gap: float
    ranks: list[int]
    rows: int
    method: str
    inputs: str
    seconds: float
    notes: list[str] = field(default_factory=list)

    @property
    def point_dependent(self) -> bool:
        return len(set(self.ranks)) > 1

    @property
    def is_observable(self) -> bool:
        """Locally weakly observable at generic points (full rank)."""
        return self.rank == self.n

    def summary(self) -> str:
        verdict = ("locally weakly observable" if self.is_observable else
                   f"not observable: rank {self.rank} of {self.n}")
        lines = [f"{self.model}: {verdict} (order {self.order}, {self.rows} rows, "
                 f"{self.method}, inputs {self.inputs}, {len(self.ranks)} points, "
                 f"{self.seconds * 1e3:.1f} ms)",
                 f"  singular values: {np.array2string(self.singular_values, precision=2)}; "
                 f"gap {self.gap:.3g}"]
        if self.point_dependent:
            lines.append(f"  the rank depends on the point: {self.ranks}")
        lines.append(f"  observable: {', '.join(self.observable) or '-'}")
        if self.jointly_observable:
            groups = "; ".join("(" + ", ".join(g) + ")" for g in self.jointly_observable)
            lines.append(f"  jointly observable: {groups}")
        lines.append(f"  unobservable: {', '.join(self.unobservable) or '-'}")
        for row in self.symmetries:
            terms = [f"{v:+.3g} d{name}" for v, name in zip(row, self.state_names, strict=True)
                     if v != 0]
            lines.append("  symmetry: " + " ".join(terms))
        lines.extend("  note: " + n for n in self.notes)
        return "\n".join(lines)

    __str__ = summary

    def __repr__(self) -> str:
        return self.summary()

    def _repr_html_(self) -> str:
        rows = "".join(
            f"<tr><td>{name}</td><td>{self._status(name)}</td></tr>" for name in self.state_names)
        return (f"<p><b>{self.model}</b>: rank {self.rank} of {self.n} (order {self.order}, "
                f"gap {self.gap:.3g})</p><table><tr><th>state</th><th>class</th></tr>"
                f"{rows}</table>")

    def _status(self, name: str) -> str:
        if name in self.observable:
            return "observable"
        if name in self.unobservable:
            return "unobservable"
        return "jointly observable"


# ------------------------------------------------------------------ derivatives
def _control_affine_fields(model: Model):
    """``(f0, [f1, ...])`` as CasADi expressions in ``x`` if ``f`` is affine in ``u``."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    p = ca.DM(model.p)
    f = model.f_c(x, u, p)
    B = ca.jacobian(f, u)
    if ca.depends_on(B, u):
        raise ValueError("the arrangements need a control-affine model (f linear in u)")
    f0 = ca.substitute(f, u, ca.DM.zeros(model.nu))
    return x, f0, [B[:, i] for i in range(model.nu)]


def _lie_rows(model: Model, order: int, inputs: str, arrangement: str | None):
    """Symbolic rows of the observability matrix up to ``order`` and the variables
    they depend on (x first). Returns ``(rows_per_order, variables)``."""
    nx, nu = model.nx, model.nu
    p = ca.DM(model.p)
    if arrangement is not None:
        x, f0, fs = _control_affine_fields(model)
        u = ca.SX.sym("u", nu)
        if ca.depends_on(model.H(x, u, p), u):
            raise ValueError("the arrangements need an output independent of the inputs; use "
                             "inputs='varying' (extended Lie derivatives) instead")
        h = model.H(x, ca.DM.zeros(nu), p)
        fields = [f0, *fs]
        words = _words(arrangement, len(fields), order)
        rows = []
        cache = {(): h}
        for k in range(order + 1):
            exprs = []
            for w in (w for w in words if len(w) == k):
                phi = cache[w[:-1]] if k else h
                if k:
                    phi = ca.jtimes(phi, x, fields[w[-1]])
                    cache[w] = phi
                exprs.append(phi)
            rows.append(ca.jacobian(ca.vertcat(*exprs), x) if exprs else ca.SX(0, nx))
        return rows, [x]
    x = ca.SX.sym("x", nx)
    us = [ca.SX.sym(f"u{j}", nu) for j in range(order + 1)]  # u, u', u'', ...
    continuous = model.continuous
    if not continuous:  # discrete: y_k = h(F^k(x)) with an input sequence
        rows, xk = [], x
        for k in range(order + 1):
            uk = us[0] if inputs == "constant" else us[k]
            rows.append(ca.jacobian(model.H(xk, uk, p), x))
            xk = model.F(xk, uk, p)
        return rows, [x, *(us[:1] if inputs == "constant" else us)]
    f = model.f_c(x, us[0], p)
    phi = model.H(x, us[0], p)
    rows = [ca.jacobian(phi, x)]
    for k in range(1, order + 1):
        dphi = ca.jtimes(phi, x, f)
        if inputs == "varying" and nu:
            for j in range(k):
                dphi += ca.jtimes(phi, us[j], us[j + 1])
        phi = dphi
        rows.append(ca.jacobian(phi, x))
    used = us[:1] if inputs == "constant" or not nu else us
    return rows, [x, *used]


def _words(arrangement: str, m: int, order: int) -> list[tuple[int, ...]]:
    """Sequences of vector-field indices (0 = drift) applied to ``h``, by order.

    ``"permutation"``: every ordered sequence of fields, repetitions included
    (PyNOA's notebooks append ``f1 f1``, ``f1 f1 f1``, ...);
    ``"combination"``: every increasing sequence of distinct fields;
    ``"drift2ndOrder"``: order 1 all fields, order 2 only pairs of the drift
    with an input field.
    """
    words: list[tuple[int, ...]] = [()]
    for k in range(1, order + 1):
        if arrangement == "permutation":
            words += list(itertools.product(range(m), repeat=k))
        elif arrangement == "combination":
            words += list(itertools.combinations(range(m), k))
        else:
            if k == 1:
                words += [(i,) for i in range(m)]
            elif k == 2:
                words += [(0, i) for i in range(1, m)]
    return words


# ------------------------------------------------------------------- numerics
def _points(model: Model, variables, n_points: int, at, rng) -> list[list[np.ndarray]]:
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


def _numeric_rank(obs: np.ndarray, rtol: float):
    """Rank of the row-normalised matrix from its singular values, and the gap."""
    norms = np.linalg.norm(obs, axis=1)
    keep = norms > 1e-12 * max(float(norms.max()), 1e-300) if len(norms) else norms > 0
    A = obs[keep] / norms[keep, None] if keep.any() else np.zeros((1, obs.shape[1]))
    s = np.linalg.svd(A, compute_uv=False)
    s = np.concatenate([s, np.zeros(obs.shape[1] - len(s))])
    top = max(float(s[0]), 1e-300)
    rank = int(np.sum(s > rtol * top))
    gap = float(s[rank - 1] / s[rank]) if 0 < rank < len(s) and s[rank] > 0 else float("inf")
    return rank, s, gap, A


def _sparsify(N: np.ndarray, tol: float = 1e-9) -> np.ndarray:
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


def _classify(names, N: np.ndarray, tol: float = 1e-6):
    """Observable / jointly observable groups / unobservable from a null-space basis."""
    n = len(names)
    if N.shape[0] == 0:
        return list(names), [], []
    Q, _ = np.linalg.qr(N.T)  # orthonormal basis of the null space
    support = np.abs(N) > tol
    observable = [names[i] for i in range(n) if not support[:, i].any()]
    unobservable = [names[i] for i in range(n) if np.linalg.norm(Q.T[:, i]) > 1 - tol]
    rest = [i for i in range(n) if support[:, i].any() and names[i] not in unobservable]
    # group the rest by shared symmetries (connected components)
    groups, seen = [], set()
    for i in rest:
        if i in seen:
            continue
        comp, stack = set(), [i]
        while stack:
            j = stack.pop()
            if j in comp:
                continue
            comp.add(j)
            for row in support:
                if row[j]:
                    stack.extend(k for k in np.flatnonzero(row) if k in rest)
        seen |= comp
        groups.append([names[k] for k in sorted(comp)])
    return observable, groups, unobservable


@check_keywords
def analyze(model: Model, order: int | None = None, inputs: str = "varying",
            method: str = "numeric", at: ArrayLike | None = None, seed: int = 0, n_points: int = 3,
            arrangement: str | None = None, max_order: int | None = None,
            rtol: float = 1e-9, input_samples: int | None = None) -> ObservabilityReport:
    """Observability rank condition and continuous symmetries of a model.

    Parameters
    ----------
    model : Model
        Continuous (``ode``) or discrete (``dynamics``); unknown parameters
        must be states (``model.augment(...)``).
    order : int, optional
        Highest derivative (continuous) or sample (discrete) order. ``None``
        raises the order until the rank has not grown for two consecutive
        orders (or is full), up to ``max_order`` (default ``nx + 2``).
    inputs : {"varying", "constant"} or dict
        Inputs as arbitrary time functions (their derivatives are free
        variables) or as unknown constants; a dict ``{name: value}`` fixes
        those inputs (e.g. zero torque) and lets the others vary.
    method : {"numeric", "symbolic"}
        Floating-point SVD at random points, or exact rational arithmetic with
        sympy (optional extra) at random rational points.
    at : (nx,) or (k, nx) array, optional
        State(s) to evaluate at (first points).
    seed : int
        Seed of the random points.
    n_points : int
        Number of evaluation points.
    arrangement : {"permutation", "combination", "drift2ndOrder"}, optional
        PyNOA's arrangements of Lie derivatives along the control-affine
        fields ``f0, f1, ...`` (the model must be affine in ``u``).
    rtol : float
        Singular values below ``rtol`` times the largest (rows normalised)
        count as zero.
    input_samples : int, optional
        With ``inputs="varying"``: draws of the inputs and their derivatives
        stacked at every state point (default ``2 nx``), so that few output
        derivatives suffice.

    Returns
    -------
    ObservabilityReport
    """
    t0 = time.perf_counter()
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    label = None
    if isinstance(inputs, dict):
        for key, value in inputs.items():
            as_float(value, f"inputs[{key!r}]")
        model, label = _fix_inputs(model, inputs), "fixed " + ", ".join(
            f"{k}={v:g}" for k, v in inputs.items())
        inputs = "varying"
    as_choice(inputs, ("varying", "constant"), "inputs")
    as_choice(method, ("numeric", "symbolic"), "method")
    if arrangement is not None:
        as_choice(arrangement, ARRANGEMENTS, "arrangement")
    if arrangement is not None and not model.continuous:
        raise ValueError("arrangements of Lie derivatives need a continuous model")
    order = as_int(order, "order", minimum=0, allow_none=True)
    n_points = as_int(n_points, "n_points", minimum=1)
    seed = as_seed(seed)
    max_order = as_int(max_order, "max_order", minimum=0, allow_none=True)
    input_samples = as_int(input_samples, "input_samples", minimum=1, allow_none=True)
    rtol = as_float(rtol, "rtol", positive=True, expected="a number in (0, 1)")
    if rtol >= 1:
        raise ValueError(f"rtol must be a number in (0, 1), got {rtol!r}")
    if at is not None:
        at_arr = _numeric_array(at, "at")
        if at_arr.ndim not in (1, 2) or at_arr.shape[-1] != model.nx:
            raise ValueError(f"at must have shape ({model.nx},) or (k, {model.nx}), "
                             f"got {at_arr.shape}")
        if not np.isfinite(at_arr).all():
            raise ValueError("at must be finite")
    n = model.nx
    rng = np.random.default_rng(seed)
    input_samples = 2 * n if input_samples is None else input_samples
    max_order = max_order if max_order is not None else n + 2
    orders = [order] if order is not None else range(0, max_order + 1)
    history: list[int] = []
    result = None
    for k in orders:
        rows, variables = _lie_rows(model, k, inputs, arrangement)
        O_fun = ca.Function("O", variables, [ca.densify(ca.vertcat(*rows))])
        if result is None:
            points = _points(model, variables, n_points, at, rng)
        pts = [_extend(pt, variables, rng) for pt in points]
        if method == "symbolic":
            ranks, s, gap, N = _symbolic_rank(O_fun, pts, n)
        else:
            ranks, s, gap, N = [], None, None, None
            for i, pt in enumerate(pts):
                mat = np.vstack([np.asarray(O_fun(*q)).reshape(-1, n)
                                 for q in _input_samples(pt, variables, inputs, arrangement,
                                                         input_samples, rng)])
                r, si, gi, A = _numeric_rank(mat, rtol)
                ranks.append(r)
                if i == 0:
                    s, gap = si, gi
                    _, _, Vt = np.linalg.svd(A)
                    N = Vt[r:] if r < n else np.zeros((0, n))
        rank = max(ranks)
        result = (k, rank, ranks, s, gap, N, sum(int(r.shape[0]) for r in rows))
        history.append(rank)
        if order is None and (rank == n or (len(history) >= 3 and history[-1] == history[-3])):
            break
    k, rank, ranks, s, gap, N, nrows = result
    sym = _sparsify(N) if len(N) else np.zeros((0, n))
    observable, joint, unobservable = _classify(model.state_names, sym)
    notes = []
    if rank == n:
        notes.append("local weak observability: nearby states are distinguishable; discrete "
                     "symmetries (global ambiguities) are not detected by the rank test")
    return ObservabilityReport(
        model=model.name, state_names=list(model.state_names), rank=rank, n=n, order=k,
        observable=observable, jointly_observable=joint, unobservable=unobservable,
        symmetries=sym, singular_values=s, gap=gap, ranks=ranks, rows=nrows, method=method,
        inputs=label or (inputs if model.nu else "none"), seconds=time.perf_counter() - t0,
        notes=notes)


def _fix_inputs(model: Model, values: dict) -> Model:
    """The model with some inputs fixed to given values (the others stay inputs)."""
    unknown = set(values) - set(model.input_names)
    if unknown:
        raise ValueError(f"inputs names unknown inputs {sorted(unknown)}; "
                         f"inputs are {model.input_names}")
    free = [n for n in model.input_names if n not in values]
    p = ca.DM(model.p)

    def full(u):
        parts, j = [], 0
        for name in model.input_names:
            if name in values:
                parts.append(ca.DM(float(values[name])))
            else:
                parts.append(u[j])
                j += 1
        return ca.vertcat(*parts) if parts else ca.DM.zeros(0, 1)

    kwargs = {"ode": lambda x, u, _: model.f_c(x, full(u), p)} if model.continuous else \
        {"dynamics": lambda x, u, _: model.F(x, full(u), p)}
    return Model(states=model.state_names, outputs=model.output_names, inputs=free,
                 output=lambda x, u, _: model.H(x, full(u), p), dt=model.dt,
                 lower=model.lower, upper=model.upper, name=model.name, **kwargs)


def _input_samples(pt, variables, inputs, arrangement, count, rng):
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


def _extend(pt, variables, rng):
    """Points for a higher order need values for the new input-derivative variables."""
    out = list(pt[:len(variables)])
    for v in variables[len(out):]:
        out.append(rng.standard_normal(v.numel()))
    return out


def _symbolic_rank(O_fun: ca.Function, pts, n):
    """Exact rank and null space at random rational points with sympy (small models).

    The observability matrix is translated from CasADi to sympy once; at each
    point every variable is replaced by a nearby rational, and the rank and
    null space are computed in exact rational arithmetic.
    """
    try:
        import sympy as sp
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("method='symbolic' needs sympy: pip install 'estim[symbolic]'") from exc
    from estim._sympy import function_to_sympy

    syms, outs = function_to_sympy(O_fun)
    rows = O_fun.size1_out(0)
    out = outs[0]
    dense = O_fun.sparsity_out(0).is_dense()
    if not dense:
        raise ValueError("internal: the observability matrix must be dense")
    M = sp.Matrix(rows, n, lambda i, j: out[i + j * rows])
    flat = [s for group in syms for s in group]
    ranks, first = [], None
    for pt in pts:
        vals = np.concatenate([np.ravel(v) for v in pt])
        Mi = M.subs({s: sp.Rational(round(v * 256), 256) for s, v in zip(flat, vals,
                                                                             strict=True)})
        ranks.append(int(Mi.rank()))
        if first is None:
            first = Mi
    _, s, gap, _ = _numeric_rank(np.array(first.evalf(), dtype=float), 1e-12)
    null = first.nullspace()
    N = np.array([[float(v) for v in vec] for vec in null]) if null else np.zeros((0, n))
    return ranks, s, (gap if ranks[0] < n else float("inf")), N


# -------------------------------------------------------------- window analysis
@dataclass
class WindowReport:
    """Local identifiability of ``x0`` from one window of data (:func:`window`).

    Attributes
    ----------
    sensitivity : (m, nx) array
        ``R^{-1/2} d(y_0 .. y_N) / d x_0`` (whitened if ``R`` is given).
    singular_values : (nx,) array
    rank : int
    condition : float
        ``s_max / s_min`` (inf when singular).
    fisher : (nx, nx) array or None
        ``S^T S`` with the whitened sensitivity (given ``R``).
    crb_std : (nx,) array or None
        Cramer-Rao lower bound on the standard deviation of each state of
        ``x0`` (inf where not identifiable).
    """

    sensitivity: np.ndarray
    singular_values: np.ndarray
    rank: int
    condition: float
    fisher: np.ndarray | None
    crb_std: np.ndarray | None


@check_keywords
def window(model: Model, x0: ArrayLike, n_steps: int, inputs: ArrayLike | None = None,
           R: ArrayLike | None = None, every: int = 1, rtol: float = 1e-9) -> WindowReport:
    """Identifiability of the initial state from ``n_steps`` samples along a trajectory.

    Parameters
    ----------
    model : Model
        Continuous or discrete (the sampled map ``F`` is used either way).
    x0 : (nx,) array
        Initial state of the window.
    n_steps : int
        Steps of the window (samples ``0, every, 2 every, ...`` up to it).
    inputs : (n_steps, nu) array, optional
        Inputs applied after each step (zero if omitted).
    R : float, (ny,) or (ny, ny), optional
        Output covariance: whitens the sensitivity and gives the Fisher
        information and the Cramer-Rao bound.
    every : int
        Keep every ``every``-th sample (a downsampled buffer).
    rtol : float
        Singular values below ``rtol`` times the largest count as zero.
    """
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    x0 = as_vector(x0, model.nx, "x0")
    n_steps = as_int(n_steps, "n_steps", minimum=0)
    every = as_int(every, "every", minimum=1)
    rtol = as_float(rtol, "rtol", positive=True, expected="a number in (0, 1)")
    if rtol >= 1:
        raise ValueError(f"rtol must be a number in (0, 1), got {rtol!r}")
    U = np.zeros((n_steps, model.nu)) if inputs is None else \
        as_input_table(inputs, n_steps, model.nu)
    Rm = None if R is None else as_covariance(R, model.ny, "R")
    x = ca.SX.sym("x", model.nx)
    p = ca.DM(model.p)
    xs, ys = x, []
    u_prev = ca.DM.zeros(model.nu)
    for k in range(n_steps + 1):
        if k % every == 0:
            ys.append(model.H(xs, u_prev, p))
        if k < n_steps:
            xs = model.F(xs, ca.DM(U[k]), p)
            u_prev = ca.DM(U[k])
    S = np.asarray(ca.Function("S", [x], [ca.jacobian(ca.vertcat(*ys), x)])(x0))
    fisher = crb = None
    if Rm is not None:
        W = np.linalg.cholesky(np.linalg.inv(Rm)).T
        S = (np.kron(np.eye(len(ys)), W)) @ S
        fisher = S.T @ S
    s = np.linalg.svd(S, compute_uv=False)
    rank = int(np.sum(s > rtol * max(float(s[0]), 1e-300)))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    if fisher is not None:
        try:
            crb = np.sqrt(np.diag(np.linalg.inv(fisher))) if rank == model.nx else \
                np.full(model.nx, np.inf)
        except np.linalg.LinAlgError:
            crb = np.full(model.nx, np.inf)
    return WindowReport(S, s, rank, cond, fisher, crb)
