"""Non-smoothness diagnostic: switches in a model's equations, and parameters they freeze.

Private functions for the estimators (which decide whether and how to warn):

* :func:`nonsmooth_operations` lists the operations of a model's dynamics and output
  map whose derivative jumps or vanishes (``fmin``, ``fmax``, ``fabs``, ``if_else``,
  ``sign``, ``floor``, comparisons used as numbers, ...) and, for each, the states,
  inputs and fixed parameters its argument depends on. Only a dependence on a state
  (an estimated parameter is a state of an augmented model) matters for the gradient
  of an estimator: a switch on an input or on a fixed parameter is smooth in ``x``.
* :func:`zero_derivative_parameters` finds the augmented parameters whose derivative
  of the dynamics and of the output is exactly zero at every sample of a record: a
  gradient-based fit cannot move them (a threshold inside ``if_else``).
* :func:`advice` turns both into a warning text that names the operation, the state or
  parameter, and the :mod:`estim.soft` helper that replaces it.

The graphs are read from CasADi's SX instruction list: ``model.f_c`` for a continuous
model (each operation once, not once per Runge-Kutta stage; this also covers CVODES
models, whose ``F`` is an MX integrator call), ``model.F`` for a discrete one, and
``model.H``. A function that is neither SX nor expandable to SX is skipped.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from estim._validate import as_inputs, as_record

# CasADi operation -> (name in reports, kind). "kink": continuous, derivative jumps;
# "jump": the value jumps, derivative zero elsewhere; "switch": ``if_else``, whose
# condition's dependence is what matters (the branches are differentiated normally).
_KINKS = {ca.OP_FMIN: "fmin", ca.OP_FMAX: "fmax", ca.OP_FABS: "fabs"}
_JUMPS = {ca.OP_SIGN: "sign", ca.OP_COPYSIGN: "copysign", ca.OP_FLOOR: "floor",
          ca.OP_CEIL: "ceil", ca.OP_FMOD: "fmod", ca.OP_REMAINDER: "remainder"}
_COMPARISONS = {ca.OP_LT: "comparison", ca.OP_LE: "comparison", ca.OP_EQ: "comparison",
                ca.OP_NE: "comparison"}
_LOGIC = {ca.OP_NOT: "logic", ca.OP_AND: "logic", ca.OP_OR: "logic"}
_BOOLEAN = {**_COMPARISONS, **_LOGIC}
_NAMES = {**_KINKS, **_JUMPS, **_BOOLEAN, ca.OP_IF_ELSE_ZERO: "if_else"}
_KIND = {**dict.fromkeys(_KINKS.values(), "kink"), **dict.fromkeys(_JUMPS.values(), "jump"),
         "comparison": "jump", "logic": "jump", "if_else": "switch"}

# what to write instead, per operation
_FIX = {
    "fmin": "replace ca.fmin(a, b) by estim.soft.min(a, b, width)",
    "fmax": "replace ca.fmax(a, b) by estim.soft.max(a, b, width) "
            "(ca.fmax(a, 0) by estim.soft.relu(a, width))",
    "fabs": "replace ca.fabs(a) (or abs(a)) by estim.soft.abs(a, width)",
    "if_else": "replace ca.if_else(s > 0, a, b) by b + estim.soft.step(s, width) * (a - b) "
               "(or by estim.soft.max / min / relu / clip when the branches are a max, "
               "a min or a saturation)",
    "sign": "replace ca.sign(s) by 2 * estim.soft.step(s, width) - 1",
    "copysign": "replace ca.copysign(a, s) by estim.soft.abs(a, width) * "
                "(2 * estim.soft.step(s, width) - 1)",
    "comparison": "a comparison used as a number, e.g. (s > 0) * a, is a step: write "
                  "estim.soft.step(s, width) * a",
    "logic": "a logical operation used as a number is a step: write products of "
             "estim.soft.step(s, width) instead",
    "floor": "floor has no smooth counterpart: keep it out of the estimated quantities "
             "(e.g. a quantised sensor: model it as y plus noise)",
    "ceil": "ceil has no smooth counterpart: keep it out of the estimated quantities",
    "fmod": "fmod has no smooth counterpart: compare wrapped angles through their sine and "
            "cosine instead of wrapping them",
    "remainder": "remainder has no smooth counterpart: compare wrapped angles through their "
                 "sine and cosine instead of wrapping them",
}
_WIDTH = ("width is in the units of the argument: a few per cent of its range, not below its "
          "noise level (too narrow a switch is a jump again for the solver); the helpers "
          "deviate from the exact function by less than width (see 'Models with switches' "
          "in the documentation)")


@dataclass(frozen=True)
class NonSmoothOperation:
    """One kind of non-smooth operation in one part of a model, with what it depends on.

    Attributes
    ----------
    operation : str
        ``"fmin"``, ``"fmax"``, ``"fabs"``, ``"if_else"``, ``"sign"``, ``"copysign"``,
        ``"floor"``, ``"ceil"``, ``"fmod"``, ``"remainder"``, ``"comparison"`` (``<``,
        ``<=``, ``==``, ``!=`` used as a number, not only as an ``if_else`` condition)
        or ``"logic"`` (not, and, or used as a number).
    where : str
        ``"dynamics"`` or ``"output"``.
    kind : str
        ``"kink"`` (continuous, the derivative jumps), ``"jump"`` (the value jumps, the
        derivative is zero elsewhere) or ``"switch"`` (an ``if_else``: either, its
        condition's derivative is zero).
    states : tuple of str
        States its argument depends on (for ``if_else``: its condition). An augmented
        parameter is a state. Empty: smooth in the state, harmless for an estimator.
    inputs, params : tuple of str
        Inputs and fixed parameters its argument depends on.
    count : int
        How many CasADi instructions of this operation share this dependence (one
        ``ca.if_else`` is two).
    """

    operation: str
    where: str
    kind: str
    states: tuple[str, ...]
    inputs: tuple[str, ...]
    params: tuple[str, ...]
    count: int = 1

    @property
    def affects_gradient(self) -> bool:
        """True when the argument depends on a state (or an estimated parameter)."""
        return bool(self.states)

    def __str__(self) -> str:
        verb = "switches on" if self.operation == "if_else" else "depends on"
        if self.states:
            return f"{self.operation} in the {self.where} {verb} {', '.join(self.states)}"
        other = self.inputs + self.params
        what = f"only on {', '.join(other)}" if other else "on nothing that varies"
        return f"{self.operation} in the {self.where} {verb.split()[0]} {what}"


# ---------------------------------------------------------------- the graphs
def _sx_function(fun: ca.Function) -> ca.Function | None:
    if fun.is_a("SXFunction"):
        return fun
    try:
        return fun.expand()
    except RuntimeError:  # an integrator or another call that has no SX form
        return None


def _scan(fun: ca.Function) -> list[tuple[str, int]]:
    """``(operation name, dependency bit mask)`` of every non-smooth instruction.

    Bit ``offset_i + j`` stands for nonzero ``j`` of input ``i``. The instruction list
    reuses work registers, so every value is named by the instruction that produced it.
    A comparison or logical operation is dropped when its value only ever serves as an
    ``if_else`` condition (directly or through other logical operations): the
    ``if_else`` is reported with the condition's dependence instead.
    """
    offsets = np.concatenate([[0], np.cumsum([fun.nnz_in(i) for i in range(fun.n_in())])])
    n = fun.n_instructions()
    ops = [fun.instruction_id(k) for k in range(n)]
    deps = [0] * n
    args: list[list[int]] = [[] for _ in range(n)]   # producing instruction of each operand
    users: list[list[tuple[int, int]]] = [[] for _ in range(n)]  # (instruction, position)
    producer: dict[int, int] = {}
    for k, op in enumerate(ops):
        if op == ca.OP_INPUT:
            i, j = fun.instruction_input(k)
            deps[k] = 1 << int(offsets[i] + j)
        elif op != ca.OP_CONST:
            args[k] = [producer[w] for w in fun.instruction_input(k)]
            mask = 0
            for pos, a in enumerate(args[k]):
                mask |= deps[a]
                users[a].append((k, pos))
            deps[k] = mask
        if op != ca.OP_OUTPUT:
            for w in fun.instruction_output(k):
                producer[w] = k
    condition_only = [False] * n
    for k in range(n - 1, -1, -1):
        if ops[k] in _BOOLEAN:
            condition_only[k] = bool(users[k]) and all(
                (ops[user] == ca.OP_IF_ELSE_ZERO and pos == 0)
                or (ops[user] in _LOGIC and condition_only[user]) for user, pos in users[k])
    found = []
    for k, op in enumerate(ops):
        name = _NAMES.get(op)
        if name is None or condition_only[k]:
            continue
        operands = args[k][:1] if op == ca.OP_IF_ELSE_ZERO else args[k]
        mask = 0
        for a in operands:
            mask |= deps[a]
        found.append((name, mask))
    return found


def nonsmooth_operations(model) -> list[NonSmoothOperation]:
    """The non-smooth operations of a model's dynamics and output map.

    Parameters
    ----------
    model : estim.Model
        Any model; for an augmented one the estimated parameters are states.

    Returns
    -------
    list of NonSmoothOperation
        One entry per operation, part of the model and dependence (dynamics first),
        empty for a smooth model. Entries with ``affects_gradient`` are the ones an
        estimator should warn about; :func:`advice` writes the warning.

    Notes
    -----
    A function with no SX form (an integrator call without ``f_c``) is skipped, and so
    are the insides of a ``never_inline`` CasADi Function called from the equations
    (the call itself is treated as smooth). Under a millisecond for the models of
    :mod:`estim.models` (the 33-state quadrotor included): cheap enough for every
    estimator's constructor.
    """
    labels = list(model.state_names) + list(model.input_names) + list(model.param_names)
    nx, nu = model.nx, model.nu
    # (the transition before a manifold's normalisation: the wrap of an angle state is
    # no switch for the estimators, which take its steps in the tangent space)
    parts = [("dynamics", model.f_c if model.f_c is not None else
              getattr(model, "_F_vector", model.F)),
             ("output", model.H)]
    out: list[NonSmoothOperation] = []
    for where, fun in parts:
        sx = _sx_function(fun)
        if sx is None:
            continue
        try:
            scanned = _scan(sx)
        except (KeyError, IndexError, RuntimeError):  # an instruction layout not foreseen:
            continue                                  # a diagnostic must not break a model
        counts: dict[tuple, int] = {}
        for name, mask in scanned:
            bits = [b for b in range(mask.bit_length()) if mask >> b & 1]
            key = (name,
                   tuple(labels[b] for b in bits if b < nx),
                   tuple(labels[b] for b in bits if nx <= b < nx + nu),
                   tuple(labels[b] for b in bits if b >= nx + nu))
            counts[key] = counts.get(key, 0) + 1
        out.extend(NonSmoothOperation(name, where, _KIND[name], s, i, p, c)
                   for (name, s, i, p), c in sorted(counts.items()))
    return out


# ------------------------------------------------------------ zero derivatives
_CHUNK = 1 << 18  # Jacobian entries per mapped call (bounds the memory on long records)
_HEAD = 32  # samples looked at first


def _any_nonzero(jac: ca.Function, X: np.ndarray, U: np.ndarray, p: np.ndarray,
                 rows: list[int], cols: list[int]) -> np.ndarray:
    """For each column in ``cols``: is ``jac[rows, col]`` nonzero at any sample?

    The first few samples are looked at first, then the rest in chunks, until every
    column has been seen nonzero (a parameter that matters usually does from the start).
    """
    T, nx = X.shape
    n_rows = jac.size1_out(0)
    per_call = int(np.clip(_CHUNK // max(n_rows * nx, 1), 1, T))
    mapped = {}
    hit = np.zeros(len(cols), dtype=bool)
    head = min(_HEAD, per_call, T)
    bounds = [(0, head)] + [(a, min(a + per_call, T)) for a in range(head, T, per_call)]
    for start, stop in bounds:
        size = stop - start
        if size not in mapped:
            mapped[size] = jac.map(size)
        J = mapped[size](X[start:stop].T, U[start:stop].T, p).full()
        J = J.reshape(n_rows, size, nx)[np.ix_(rows, range(size), cols)]
        hit |= (J != 0).any(axis=(0, 1))
        if hit.all():
            break
    return hit


def zero_derivative_parameters(model, X, U=None, names: Sequence[str] | None = None
                               ) -> list[str]:
    """Augmented parameters on which nothing depends along a record.

    A parameter appended by ``model.augment`` is reported when the Jacobian columns of
    its state, ``dF/dtheta`` (rows of the other states) at samples ``0 .. T-2`` and
    ``dh/dtheta`` at samples ``0 .. T-1``, are exactly zero: the cost of a fit does not
    change with it to first order, so Gauss-Newton, Ipopt or an EKF never move it from
    its initial value. The typical cause is a threshold that only sets where an
    ``if_else`` switches, on a record where the switch never sits at the threshold.

    Parameters
    ----------
    model : estim.Model
        An augmented model (``model.augmented`` non-empty), or any model with
        ``names=()``.
    X : (T, nx) array
        The trajectory: an estimate, a fit's starting guess, or the truth.
    U : (T, nu) or (T-1, nu) array, optional
        ``U[k]`` acts from sample k to k+1 and is the held input when ``y_{k+1}`` is
        taken (the convention of ``FullInformation.fit``); for a model with
        ``hold="foh"``, ``(T, nu)``: the input at each sample. Zero if omitted.
    names : sequence of str, optional
        The parameters to check (default: all of ``model.augmented``).

    Returns
    -------
    list of str
        The parameters (in ``names`` order) with a zero derivative at every sample.
    """
    augmented = list(model.augmented)
    names = augmented if names is None else list(names)
    unknown = [n for n in names if n not in augmented]
    if unknown:
        raise ValueError(f"names must be augmented parameters of the model "
                         f"{augmented}, got {unknown}")
    X = as_record(X, model.nx, "X", missing=False, names=model.state_names, what="states")
    T = X.shape[0]
    U = np.zeros((T, model.nu)) if U is None else as_inputs(U, T, model)  # (a diagnostic)
    if not names:
        return []
    if model.sampled:  # inputs at the samples; transitions from each to the next
        U_prev, U = U, np.hstack([U, np.vstack([U[1:], U[-1:]])])
    else:
        U_prev = np.vstack([np.zeros((1, model.nu)), U[:-1]])
    if model.variable_dt:  # at the model's interval: a zero derivative does not hinge on it
        U = np.hstack([U, np.full((T, 1), model.dt)])
    cols = [model.state_names.index(n) for n in names]
    rows = [i for i, n in enumerate(model.state_names) if n not in model.augmented]
    # the dynamics first: parameters usually enter them, and a head of samples shows it
    moves = _any_nonzero(model.F_x, X[:-1], U[:-1], model.p, rows, cols) if T > 1 \
        else np.zeros(len(cols), dtype=bool)
    rest = [c for c, m in zip(cols, moves, strict=True) if not m]
    if rest:
        moves[~moves] = _any_nonzero(model.H_x, X, U_prev, model.p, list(range(model.ny)),
                                     rest)
    return [n for n, m in zip(names, moves, strict=True) if not m]


# -------------------------------------------------------------------- advice
def advice(operations: Sequence[NonSmoothOperation] = (),
           zero_derivative: Sequence[str] = ()) -> str:
    """The warning text for what matters to a gradient, or ``""`` when nothing does.

    Parameters
    ----------
    operations : sequence of NonSmoothOperation
        From :func:`nonsmooth_operations`; entries that do not depend on a state are
        left out of the text.
    zero_derivative : sequence of str
        From :func:`zero_derivative_parameters`.

    Returns
    -------
    str
        One line per finding, each naming the operation and the states or the
        parameter and what to write instead; empty when there is nothing to say.
    """
    relevant = [op for op in operations if op.affects_gradient]
    zero = list(zero_derivative)
    if not relevant and not zero:
        return ""
    if relevant:
        lines = ["the model is not smooth in what is estimated: near a switch a gradient-based "
                 "estimator takes tiny steps, and a parameter that only sets where a switch "
                 "flips never moves"]
    else:
        lines = ["some estimated parameters cannot move on this record"]
    seen = set()
    for op in relevant:
        key = (op.operation, op.where, op.states)
        if key not in seen:
            seen.add(key)
            lines.append(f"- {op}: {_FIX[op.operation]}")
    for name in zero:
        switches = sorted({f"{op.operation} in the {op.where}" for op in relevant
                           if name in op.states})
        line = (f"- {name} has a zero derivative at every sample of the record (neither the "
                f"dynamics nor the output change with it): a gradient-based fit leaves it at "
                f"its initial value")
        if switches:
            line += f"; it sets where {', '.join(switches)} switches: smooth that switch"
        lines.append(line)
    if relevant:
        lines.append(_WIDTH)
    return "\n".join(lines)
