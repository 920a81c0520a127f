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

The package: :mod:`~estim.observability.lie` builds the observability matrix and
takes its numeric rank, :mod:`~estim.observability.symmetries` reads the symmetries
and classifies the states, :mod:`~estim.observability.symbolic` is the exact path,
:mod:`~estim.observability.sensitivity` the identifiability of an initial state
from one window of data (:func:`window`), and
:mod:`~estim.observability.conditioning` the matrix at given states (:func:`matrix`)
and how well conditioned it is over a plane of two states (:func:`conditioning`).

References
----------
R. Hermann, A. J. Krener, "Nonlinear controllability and observability",
IEEE TAC 22(5), 1977; A. Martinelli, "Continuous symmetries and
observability properties in autonomous navigation", INRIA RR-7049, 2010;
A. Martinelli, "Observability: a new theory based on the group of
invariance", SIAM, 2020.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import (
    _numeric_array,
    as_choice,
    as_float,
    as_int,
    as_seed,
    check_keywords,
)
from estim.model import Model
from estim.observability import lie, symmetries
from estim.observability.conditioning import Conditioning, conditioning, matrix
from estim.observability.lie import ARRANGEMENTS
from estim.observability.sensitivity import WindowReport, window
from estim.observability.symbolic import symbolic_rank

__all__ = ["ARRANGEMENTS", "Conditioning", "ObservabilityReport", "WindowReport", "analyze",
           "conditioning", "matrix", "window"]


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


@check_keywords
def analyze(model: Model, order: int | None = None, inputs: str = "varying",
            method: str = "numeric", at: ArrayLike | None = None, seed: int | None = 0,
            n_points: int = 3,
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
    seed : int or None
        Seed of the random points (None: fresh ones at every call).
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
        model, label = lie.fix_inputs(model, inputs), "fixed " + ", ".join(
            f"{k}={v:g}" for k, v in inputs.items())
        inputs = "varying"
    as_choice(inputs, ("varying", "constant"), "inputs")
    as_choice(method, ("numeric", "symbolic"), "method")
    if arrangement is not None:
        as_choice(arrangement, ARRANGEMENTS, "arrangement")
    if arrangement is not None and not model.continuous:
        raise ValueError("arrangements of Lie derivatives need a continuous model")
    fixed_order = as_int(order, "order", minimum=0, allow_none=True)
    n_points = as_int(n_points, "n_points", minimum=1)
    seed = as_seed(seed)
    highest = as_int(max_order, "max_order", minimum=0, allow_none=True)
    samples = as_int(input_samples, "input_samples", minimum=1, allow_none=True)
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
    samples = 2 * n if samples is None else samples
    highest = highest if highest is not None else n + 2
    orders = [fixed_order] if fixed_order is not None else range(0, highest + 1)
    history: list[int] = []
    result = None
    points: list[list[np.ndarray]] = []
    for k in orders:
        rows, variables = lie.rows(model, k, inputs, arrangement)
        O_fun = ca.Function("O", variables, [ca.densify(ca.vertcat(*rows))])
        if result is None:
            points = lie.points(model, variables, n_points, at, rng)
        pts = [lie.extend(pt, variables, rng) for pt in points]
        if method == "symbolic":
            ranks, s, gap, N = symbolic_rank(O_fun, pts, n)
        else:
            ranks, s, gap, N = _numeric_ranks(O_fun, pts, variables, inputs, arrangement,
                                              samples, rtol, rng)
        rank = max(ranks)
        result = (k, rank, ranks, s, gap, N, sum(int(r.shape[0]) for r in rows))
        history.append(rank)
        if fixed_order is None and (rank == n or (len(history) >= 3
                                                  and history[-1] == history[-3])):
            break
    assert result is not None  # at least one order
    k, rank, ranks, s, gap, N, nrows = result
    sym = symmetries.sparsify(N) if len(N) else np.zeros((0, n))
    observable, joint, unobservable = symmetries.classify(model.state_names, sym)
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


def _numeric_ranks(O_fun: ca.Function, pts: list[list[np.ndarray]], variables: list[ca.SX],
                   inputs: str, arrangement: str | None, samples: int, rtol: float,
                   rng: np.random.Generator
                   ) -> tuple[list[int], np.ndarray, float, np.ndarray]:
    """The numeric rank at every point (its rows stacked over ``samples`` draws of the
    inputs), and at the first point the singular values, the gap and the null space."""
    ranks: list[int] = []
    first = None
    for pt in pts:
        mat = np.vstack([np.asarray(O_fun(*q)).reshape(-1, O_fun.size2_out(0))
                         for q in lie.input_samples(pt, variables, inputs, arrangement,
                                                    samples, rng)])
        r, si, gi, A = lie.numeric_rank(mat, rtol)
        ranks.append(r)
        if first is None:
            first = (si, gi, symmetries.null_space(A, r))
    assert first is not None  # at least one point
    return ranks, *first
