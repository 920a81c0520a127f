r"""An SX Function evaluated on many points at once, one numpy operation per instruction.

A particle filter, an ensemble or a batch of seeds evaluates the same small
Function (a model's transition, its output, a log-density) at thousands of points.
CasADi's ``map`` runs its virtual machine once per point and instruction;
:func:`vectorised` instead turns the Function's algorithm (its list of
instructions, :meth:`casadi.Function.instruction_id`) into a Python function
whose every line is one numpy operation over all the points, so the interpreter's
cost is paid once per instruction, not once per instruction and point:

.. math::
    \text{time} \approx n_\text{instr} \, (c_\text{numpy} + N\,c_\text{elem}),

a few microseconds per instruction plus about a nanosecond per point and
instruction.

Inputs are arrays of shape ``(n_i, N)`` (a column per point) or ``(n_i,)``
(the same values at every point, e.g. parameters); outputs have shape
``(n_o, N)``. Floating-point results equal CasADi's evaluation to the last bit
for the arithmetic operations and ``sqrt``; elementary functions (``exp``,
``sin``, ...) come from numpy's implementations and may differ in the last
unit. Operations without a numpy counterpart here (a call of another Function,
``remainder``, ...) make :func:`vectorised` return None: the caller then keeps
CasADi's ``map``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

__all__ = ["c_kernel", "vectorised"]

#: numpy expression of each unary (``{0}``) and binary (``{0}``, ``{1}``) operation
_OPS: dict[int, str] = {
    ca.OP_ASSIGN: "{0}",
    ca.OP_ADD: "{0} + {1}",
    ca.OP_SUB: "{0} - {1}",
    ca.OP_MUL: "{0} * {1}",
    ca.OP_DIV: "{0} / {1}",
    ca.OP_NEG: "-{0}",
    ca.OP_TWICE: "2.0 * {0}",
    ca.OP_SQ: "{0} * {0}",
    ca.OP_INV: "1.0 / {0}",
    ca.OP_SQRT: "_np.sqrt({0})",
    ca.OP_EXP: "_np.exp({0})",
    ca.OP_LOG: "_np.log({0})",
    ca.OP_POW: "_np.power({0}, {1})",
    ca.OP_CONSTPOW: "_np.power({0}, {1})",
    ca.OP_SIN: "_np.sin({0})",
    ca.OP_COS: "_np.cos({0})",
    ca.OP_TAN: "_np.tan({0})",
    ca.OP_ASIN: "_np.arcsin({0})",
    ca.OP_ACOS: "_np.arccos({0})",
    ca.OP_ATAN: "_np.arctan({0})",
    ca.OP_SINH: "_np.sinh({0})",
    ca.OP_COSH: "_np.cosh({0})",
    ca.OP_TANH: "_np.tanh({0})",
    ca.OP_ASINH: "_np.arcsinh({0})",
    ca.OP_ACOSH: "_np.arccosh({0})",
    ca.OP_ATANH: "_np.arctanh({0})",
    ca.OP_ATAN2: "_np.arctan2({0}, {1})",
    ca.OP_HYPOT: "_np.hypot({0}, {1})",
    ca.OP_EXPM1: "_np.expm1({0})",
    ca.OP_LOG1P: "_np.log1p({0})",
    ca.OP_ERF: "_erf({0})",
    ca.OP_FABS: "_np.abs({0})",
    ca.OP_SIGN: "_np.sign({0})",
    ca.OP_COPYSIGN: "_np.copysign({0}, {1})",
    ca.OP_FLOOR: "_np.floor({0})",
    ca.OP_CEIL: "_np.ceil({0})",
    ca.OP_FMOD: "_np.fmod({0}, {1})",
    ca.OP_FMIN: "_np.fmin({0}, {1})",
    ca.OP_FMAX: "_np.fmax({0}, {1})",
    ca.OP_LT: "_f({0} < {1})",
    ca.OP_LE: "_f({0} <= {1})",
    ca.OP_EQ: "_f({0} == {1})",
    ca.OP_NE: "_f({0} != {1})",
    ca.OP_NOT: "_f({0} == 0.0)",
    ca.OP_AND: "_f(_np.logical_and({0} != 0.0, {1} != 0.0))",
    ca.OP_OR: "_f(_np.logical_or({0} != 0.0, {1} != 0.0))",
    ca.OP_IF_ELSE_ZERO: "_np.where({0} != 0.0, {1}, 0.0)",
}


def _f(condition) -> np.ndarray | float:
    """A comparison's result as CasADi gives it: 1.0 or 0.0."""
    return np.asarray(condition, dtype=float) if isinstance(condition, np.ndarray) \
        else float(condition)


def source(fun: ca.Function) -> str | None:
    """The Python source of :func:`vectorised`'s function for ``fun`` (None if some
    instruction has no numpy counterpart)."""
    if not fun.is_a("SXFunction"):
        return None
    lines = [f"def {_name(fun)}({', '.join(f'a{i}' for i in range(fun.n_in()))}):"]
    outs: list[list[str | None]] = [[None] * fun.nnz_out(i) for i in range(fun.n_out())]
    for k in range(fun.n_instructions()):
        op, a, o = fun.instruction_id(k), fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_INPUT:
            lines.append(f"    w{o[0]} = a{a[0]}[{a[1]}]")
        elif op == ca.OP_CONST:
            lines.append(f"    w{o[0]} = {_literal(float(fun.instruction_constant(k)))}")
        elif op == ca.OP_OUTPUT:
            # outputs are read at the end: copy the value now, its work slot may be reused
            lines.append(f"    o{o[0]}_{o[1]} = w{a[0]}")
            outs[o[0]][o[1]] = f"o{o[0]}_{o[1]}"
        elif op in _OPS and 1 <= len(a) <= 2 and min(a) >= 0:
            args = [f"w{i}" for i in a]
            lines.append(f"    w{o[0]} = " + _OPS[op].format(*args))
        else:
            return None
    # every output (n_o, N): rows not written are structural zeros
    for i, rows in enumerate(outs):
        entries = ", ".join("0.0" if r is None else r for r in rows)
        lines.append(f"    r{i} = _rows(({entries}{',' if len(rows) == 1 else ''}), n)")
    lines.append("    return [" + ", ".join(f"r{i}" for i in range(fun.n_out())) + "]")
    return "\n".join(lines)


def _literal(value: float) -> str:
    """A float as Python source (``repr`` is exact; inf and NaN through numpy)."""
    if value != value:
        return "_np.nan"
    if value in (np.inf, -np.inf):
        return "_np.inf" if value > 0 else "-_np.inf"
    return repr(value)


def _name(fun: ca.Function) -> str:
    name = "".join(c if c.isalnum() else "_" for c in fun.name())
    return f"vectorised_{name}"


def _rows(rows: tuple, n: int) -> np.ndarray:
    """Stack output rows (arrays of ``n`` points or scalars) into ``(len(rows), n)``; a
    single row computed here (not a view of an input) is returned without a copy."""
    if len(rows) == 1 and isinstance(rows[0], np.ndarray) and rows[0].base is None \
            and rows[0].shape == (n,) and rows[0].dtype == np.float64:
        return rows[0].reshape(1, n)
    out = np.empty((len(rows), n))
    for i, r in enumerate(rows):
        out[i] = r
    return out


def vectorised(fun: ca.Function) -> Callable[..., list[np.ndarray]] | None:
    """``fun`` (an SX Function with dense outputs) as a function of column-stacked points.

    Parameters
    ----------
    fun : casadi.Function
        An SX Function (``MX`` ones: expand them first).

    Returns
    -------
    callable or None
        ``g(*args, n=N)``: ``args[i]`` of shape ``(fun.nnz_in(i), N)`` or
        ``(fun.nnz_in(i),)`` (broadcast to every point), returning the list of the
        outputs, each ``(fun.nnz_out(i), N)`` (the nonzeros of each output in
        CasADi's column-major order). None when an instruction has no numpy
        counterpart (see the module).
    """
    src = source(fun)
    if src is None:
        return None
    head, body = src.split("\n", 1)
    head = head[:-2] + ", n):" if fun.n_in() else head[:-2] + "n):"
    scope: dict[str, Any] = {"_np": np, "_f": _f, "_rows": _rows}
    if "_erf(" in src:  # scipy.special only when needed
        from scipy import special
        scope["_erf"] = special.erf
    code = compile(head + "\n" + body, f"<vectorised {fun.name()}>", "exec")
    exec(code, scope)  # noqa: S102 - source generated above from the Function's algorithm
    inner = scope[_name(fun)]

    def call(*args: np.ndarray, n: int) -> list[np.ndarray]:
        with np.errstate(all="ignore"):  # as CasADi: inf and NaN propagate silently
            return inner(*args, n)

    return call


#: C expression of each unary and binary operation (CasADi's generated code's meaning)
_C_OPS: dict[int, str] = {
    ca.OP_ASSIGN: "{0}", ca.OP_ADD: "{0} + {1}", ca.OP_SUB: "{0} - {1}",
    ca.OP_MUL: "{0} * {1}", ca.OP_DIV: "{0} / {1}", ca.OP_NEG: "-{0}",
    ca.OP_TWICE: "2.0 * {0}", ca.OP_SQ: "{0} * {0}", ca.OP_INV: "1.0 / {0}",
    ca.OP_SQRT: "sqrt({0})", ca.OP_EXP: "exp({0})", ca.OP_LOG: "log({0})",
    ca.OP_POW: "pow({0}, {1})", ca.OP_CONSTPOW: "pow({0}, {1})", ca.OP_SIN: "sin({0})",
    ca.OP_COS: "cos({0})", ca.OP_TAN: "tan({0})", ca.OP_ASIN: "asin({0})",
    ca.OP_ACOS: "acos({0})", ca.OP_ATAN: "atan({0})", ca.OP_SINH: "sinh({0})",
    ca.OP_COSH: "cosh({0})", ca.OP_TANH: "tanh({0})", ca.OP_ASINH: "asinh({0})",
    ca.OP_ACOSH: "acosh({0})", ca.OP_ATANH: "atanh({0})", ca.OP_ATAN2: "atan2({0}, {1})",
    ca.OP_HYPOT: "hypot({0}, {1})", ca.OP_EXPM1: "expm1({0})", ca.OP_LOG1P: "log1p({0})",
    ca.OP_ERF: "erf({0})", ca.OP_FABS: "fabs({0})",
    ca.OP_SIGN: "({0} < 0.0 ? -1.0 : ({0} > 0.0 ? 1.0 : {0}))",
    ca.OP_COPYSIGN: "copysign({0}, {1})", ca.OP_FLOOR: "floor({0})", ca.OP_CEIL: "ceil({0})",
    ca.OP_FMOD: "fmod({0}, {1})", ca.OP_FMIN: "fmin({0}, {1})", ca.OP_FMAX: "fmax({0}, {1})",
    ca.OP_LT: "(double)({0} < {1})", ca.OP_LE: "(double)({0} <= {1})",
    ca.OP_EQ: "(double)({0} == {1})", ca.OP_NE: "(double)({0} != {1})",
    ca.OP_NOT: "(double)({0} == 0.0)",
    ca.OP_AND: "(double)({0} != 0.0 && {1} != 0.0)",
    ca.OP_OR: "(double)({0} != 0.0 || {1} != 0.0)",
    ca.OP_IF_ELSE_ZERO: "({0} != 0.0 ? {1} : 0.0)",
}


def _c_literal(value: float) -> str:
    """A float as a C expression, exactly (hexadecimal; inf and NaN by their macros)."""
    if value != value:
        return "NAN"
    if value in (np.inf, -np.inf):
        return "INFINITY" if value > 0 else "(-INFINITY)"
    return f"({value.hex()})"


def c_kernel(fun: ca.Function, name: str, varying: set[int]) -> str | None:
    r"""The C source of ``fun`` evaluated at ``n`` points, one loop over the points.

    ``static void name(size_t n, const double *a0, ..., double *r0, ...)``: input ``i``
    in ``varying`` is ``(nnz_in(i), n)`` row-major (row ``j`` of point ``p`` at
    ``a_i[j n + p]``), the other inputs are ``(nnz_in(i),)``, the same at every point
    (dense inputs); every output is dense, ``(numel_out(i), n)`` in column-major order,
    its structural zeros written as 0. The instructions that depend on no varying
    input are evaluated once, before the loop; the rest, straight-line code in the
    loop, which a C compiler vectorises over the points when it holds no call of the
    math library. Each operation is written as CasADi's own generated code writes it,
    so compiled without fast-math and without contraction it computes what CasADi's
    virtual machine computes. None when an instruction has no C counterpart here (a
    call of another Function).
    """
    if not fun.is_a("SXFunction"):
        return None
    params = [f"const double *restrict a{i}" for i in range(fun.n_in())] + \
        [f"double *restrict r{i}" for i in range(fun.n_out())]
    before: list[str] = []
    inside: list[str] = []
    slot: dict[int, tuple[str, bool]] = {}  # work slot -> (C name, varies)
    written: set[tuple[int, int]] = set()
    dense = [fun.sparsity_out(i).find() for i in range(fun.n_out())]  # nonzero -> entry
    for k in range(fun.n_instructions()):
        op, a, o = fun.instruction_id(k), fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_INPUT:
            var = a[0] in varying
            ref = f"a{a[0]}[{a[1]} * n + i]" if var else f"a{a[0]}[{a[1]}]"
            name_k, expr = f"t{k}", ref
        elif op == ca.OP_CONST:
            name_k, expr, var = f"t{k}", _c_literal(float(fun.instruction_constant(k))), False
        elif op == ca.OP_OUTPUT:
            src, var = slot[a[0]]
            row = dense[o[0]][o[1]]
            inside.append(f"r{o[0]}[{row} * n + i] = {src};")
            written.add((o[0], row))
            continue
        elif op in _C_OPS and 1 <= len(a) <= 2 and min(a) >= 0:
            args = [slot[i] for i in a]
            var = any(v for _, v in args)
            name_k, expr = f"t{k}", _C_OPS[op].format(*(n_ for n_, _ in args))
        else:
            return None
        (inside if var else before).append(f"const double {name_k} = {expr};")
        slot[o[0]] = (name_k, var)
    zeros = [f"r{i}[{j} * n + i] = 0.0;" for i in range(fun.n_out())
             for j in range(fun.numel_out(i)) if (i, j) not in written]
    body = "\n".join(f"    {line}" for line in before)
    loop = "\n".join(f"        {line}" for line in inside + zeros)
    return (f"static void {name}(size_t n, {', '.join(params)})\n{{\n{body}\n"
            f"    for (size_t i = 0; i < n; ++i) {{\n{loop}\n    }}\n}}\n")
