"""Translate a CasADi SX Function into sympy expressions (for exact arithmetic)."""

from __future__ import annotations

import casadi as ca


def _ops(sp):
    unary = {
        ca.OP_NEG: lambda a: -a, ca.OP_EXP: sp.exp, ca.OP_LOG: sp.log, ca.OP_SQRT: sp.sqrt,
        ca.OP_SQ: lambda a: a**2, ca.OP_TWICE: lambda a: 2 * a, ca.OP_SIN: sp.sin,
        ca.OP_COS: sp.cos, ca.OP_TAN: sp.tan, ca.OP_ASIN: sp.asin, ca.OP_ACOS: sp.acos,
        ca.OP_ATAN: sp.atan, ca.OP_SINH: sp.sinh, ca.OP_COSH: sp.cosh, ca.OP_TANH: sp.tanh,
        ca.OP_ASINH: sp.asinh, ca.OP_ACOSH: sp.acosh, ca.OP_ATANH: sp.atanh,
        ca.OP_FABS: sp.Abs, ca.OP_SIGN: sp.sign, ca.OP_INV: lambda a: 1 / a,
        ca.OP_FLOOR: sp.floor, ca.OP_CEIL: sp.ceiling, ca.OP_ERF: sp.erf,
        ca.OP_NOT: lambda a: sp.Piecewise((1, sp.Eq(a, 0)), (0, True)),
        ca.OP_ASSIGN: lambda a: a,
    }
    binary = {
        ca.OP_ADD: lambda a, b: a + b, ca.OP_SUB: lambda a, b: a - b,
        ca.OP_MUL: lambda a, b: a * b, ca.OP_DIV: lambda a, b: a / b,
        ca.OP_POW: lambda a, b: a**b, ca.OP_CONSTPOW: lambda a, b: a**b,
        ca.OP_ATAN2: sp.atan2, ca.OP_FMIN: sp.Min, ca.OP_FMAX: sp.Max,
        ca.OP_HYPOT: lambda a, b: sp.sqrt(a**2 + b**2),
        ca.OP_LT: lambda a, b: sp.Piecewise((1, a < b), (0, True)),
        ca.OP_LE: lambda a, b: sp.Piecewise((1, a <= b), (0, True)),
        ca.OP_EQ: lambda a, b: sp.Piecewise((1, sp.Eq(a, b)), (0, True)),
        ca.OP_NE: lambda a, b: sp.Piecewise((1, sp.Ne(a, b)), (0, True)),
        ca.OP_IF_ELSE_ZERO: lambda c, a: sp.Piecewise((a, sp.Ne(c, 0)), (0, True)),
        ca.OP_COPYSIGN: lambda a, b: sp.Abs(a) * sp.sign(b),
    }
    return unary, binary


def function_to_sympy(fun: ca.Function):
    """Symbols for every input nonzero and sympy expressions for every output nonzero.

    Returns ``(inputs, outputs)``: ``inputs[i]`` is the list of symbols of input
    ``i`` (column-major nonzeros), ``outputs[i]`` the list of expressions of
    output ``i``. Only SX Functions (``fun.is_a("SXFunction")``) are supported.
    """
    import sympy as sp

    if not fun.is_a("SXFunction"):
        fun = fun.expand()
    unary, binary = _ops(sp)
    inputs = [[sp.Symbol(f"{fun.name_in(i)}_{j}", real=True) for j in range(fun.nnz_in(i))]
              for i in range(fun.n_in())]
    outputs = [[sp.Integer(0)] * fun.nnz_out(i) for i in range(fun.n_out())]
    work: dict[int, object] = {}
    for k in range(fun.n_instructions()):
        op = fun.instruction_id(k)
        ins, outs = fun.instruction_input(k), fun.instruction_output(k)
        if op == ca.OP_INPUT:
            work[outs[0]] = inputs[ins[0]][ins[1]]
        elif op == ca.OP_OUTPUT:
            outputs[outs[0]][outs[1]] = work[ins[0]]
        elif op == ca.OP_CONST:
            c = fun.instruction_constant(k)
            work[outs[0]] = sp.nsimplify(c, rational=True) if c == int(c) or abs(c) < 1e6 \
                else sp.Float(c)
        elif op in unary:
            work[outs[0]] = unary[op](work[ins[0]])
        elif op in binary:
            work[outs[0]] = binary[op](work[ins[0]], work[ins[1]])
        else:
            names = {getattr(ca, n): n[3:].lower() for n in dir(ca) if n.startswith("OP_")}
            raise NotImplementedError(
                f"the CasADi operation {names.get(op, op)!r} (operation {op}) has no sympy "
                f"translation: use method='numeric' for this model")
    return inputs, outputs
