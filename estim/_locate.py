r"""Where a model's equations stop being finite: the equation, and the operation.

When a filter's prediction or update is not finite, :func:`locate` evaluates the model's
transition and output (and their Jacobians) at the estimate and names what is not finite
(``"F entry 'h2'"``, ``"dh/dx of output 'y'"``); for the first such entry it walks the
entry's expression graph for an operation applied outside its domain: a square root or a
power of a negative number, a logarithm of a non-positive one, a division by zero
(``"sqrt of -0.013"``). It runs only after a failed step, on CasADi's symbolic graph
(SX models; a model whose functions are called, e.g. a DAE's Newton solve, is named by
entry only).
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

__all__ = ["after_failure", "first_located", "locate"]

#: Nodes of an entry's graph examined at most.
MAX_NODES = 4000
_DOMAIN = {ca.OP_SQRT: ("sqrt", lambda a: a[0] < 0),
           ca.OP_LOG: ("log", lambda a: a[0] <= 0),
           ca.OP_DIV: ("division", lambda a: a[1] == 0),
           ca.OP_POW: ("power", lambda a: a[0] < 0 and a[1] != round(a[1])),
           ca.OP_CONSTPOW: ("power", lambda a: a[0] < 0 and a[1] != round(a[1]))}


def locate(model: Any, x: np.ndarray, w: np.ndarray, u: np.ndarray) -> str:
    """What is not finite at state ``x`` (transition input ``w``, measurement input
    ``u``): ``"F entry 'h2': sqrt of -0.013"``; empty when everything is finite."""
    if not np.isfinite(x).all():
        return ""
    p = model.p
    parts = (("F entry", model.F, (x, w, p), model.state_names),
             ("dF/dx of", model.F_x, (x, w, p), model.state_names),
             ("output", model.H, (x, u, p), model.output_names),
             ("dh/dx of output", model.H_x, (x, u, p), model.output_names))
    for what, fun, args, names in parts:
        try:
            value = np.asarray(fun(*args), dtype=float)
        except RuntimeError:
            continue
        if np.isfinite(value).all():
            continue
        rows = np.flatnonzero(~np.isfinite(value).all(axis=1))
        row = int(rows[0])
        where = _operation(fun, args, row)
        return f"{what} {names[row]!r} is {value[row][~np.isfinite(value[row])][0]}" + (
            f": {where}" if where else "") + f" at {np.round(x, 6).tolist()}"
    return ""


def _operation(fun: ca.Function, args: tuple, row: int) -> str:
    """The first operation of output row ``row`` of the SX function ``fun`` applied
    outside its domain at ``args``, as text (empty if none is found)."""
    if not fun.is_a("SXFunction"):
        return ""
    syms = [ca.SX.sym(f"a{i}", fun.size1_in(i), fun.size2_in(i)) for i in range(fun.n_in())]
    expr = fun(*syms)
    entry = ca.vec(expr[row, :]) if expr.size2() > 1 else expr[row]
    flat = ca.vertcat(*[ca.vec(s) for s in syms])
    numbers = np.concatenate([np.ravel(np.asarray(a, dtype=float), order="F") for a in args])
    seen: set[int] = set()
    stack, found = [entry[i] for i in range(entry.numel())], []
    while stack and len(seen) < MAX_NODES:
        node = stack.pop()
        key = node.element_hash()
        if key in seen or node.is_leaf():
            continue
        seen.add(key)
        deps = [node.dep(i) for i in range(node.n_dep())]
        if node.op() in _DOMAIN:
            found.append((node, deps))
        stack.extend(deps)
    if not found:
        return ""
    evaluate = ca.Function("args", [flat], [ca.vertcat(*[d for _, deps in found
                                                         for d in deps])])
    values = np.asarray(evaluate(numbers), dtype=float).ravel()
    i = 0
    for node, deps in found:
        name, bad = _DOMAIN[node.op()]
        a = values[i:i + len(deps)]
        i += len(deps)
        if np.isfinite(a).all() and bad(a):
            return f"{name} of {a[0]:.4g}" if name != "division" else "division by zero"
    return ""


def first_located(model: Any, points: Any) -> str:
    """What :func:`locate` finds at the first of ``points``, ``(x, w, u)`` triples, where
    it finds something; empty otherwise (a diagnosis that raises counts as nothing: it
    must never break what called it)."""
    for x, w, u in points:
        try:
            text = locate(model, np.asarray(x, dtype=float), w, u)
        except Exception:  # noqa: BLE001 - a diagnosis must never break the caller
            text = ""
        if text:
            return text
    return ""


def after_failure(model: Any, x_prev: np.ndarray, x_prior: np.ndarray, w: np.ndarray) -> str:
    """`` (not finite: ...)`` for a failed filter step: what :func:`locate` finds at the
    prediction ``x_prior`` (the output and its Jacobian there), else at the previous
    estimate ``x_prev`` (the transition); empty when it finds nothing."""
    u = np.asarray(model.measurement_input(w), dtype=float)
    text = first_located(model, ((x, w, u) for x in (x_prior, x_prev)))
    return f" (not finite: {text})" if text else ""
