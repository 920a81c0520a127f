r"""Smooth replacements for the switches of a model: ``relu``, ``max``, ``min``, ``abs``,
``step``, ``clip``, and ``sqrt`` (a square root with a bounded slope at 0).

A model written with ``ca.fmin``, ``ca.fmax``, ``ca.fabs`` or ``ca.if_else`` on a state
has a derivative that jumps where the switch flips: Gauss-Newton and Ipopt can then cut
their steps to nothing near the switch, and a parameter that only sets where a switch sits (a
threshold inside ``if_else``) has a zero derivative and never moves. Each helper here is
the non-smooth function with its corner rounded over a ``width`` chosen by the user, in
the units of the argument; the error against the exact function is bounded by a multiple
of ``width`` (given in each docstring), and all derivatives are continuous.

The same call works on CasADi symbols (``SX``, ``MX``, ``DM``: the result is an
expression of that type, so it can go straight into a model's equations) and on numbers
(floats, lists, numpy arrays: a numpy result, broadcast as numpy does), with the same
numbers on both. ``width`` is a positive number.

Every helper is built from analytic operations only (``tanh``, ``exp``, ``expm1``,
``log1p``, ``hypot``), never from ``fmax``, ``fabs`` or ``if_else``: its algorithmic
derivatives of every order are those of the smooth function at every point, including at
the corner itself, and the estimators' check for switches (see "Models with switches" in
the documentation) finds nothing to report in a model written with them. Values and
derivatives stay finite for any finite argument: there is no ``exp`` of a large positive
number.

The common building block is the softplus :math:`s(z) = \log(1 + e^z)`, evaluated as

.. math:: s(z) = t + \operatorname{log1p}\big(\operatorname{expm1}(-t) + e^{z - t}\big),
          \qquad t = z\,\tfrac{1 + \tanh(z/2)}{2},

an identity for any shift :math:`t`; this smooth :math:`t \approx \max(z, 0)` keeps both
exponents below 0.28. The textbook stable form
:math:`\max(z, 0) + \operatorname{log1p}(e^{-|z|})` is exact in value but, built from
``fmax`` and ``fabs``, its algorithmic second derivative at :math:`z = 0` is 0 instead of
1/4.

Examples
--------
>>> import casadi as ca
>>> from estim import soft
>>> round(float(soft.relu(0.0, 0.1)), 4)         # 0.1 log 2
0.0693
>>> h = ca.SX.sym("h")
>>> overflow = 2.0 * soft.relu(h - 0.8, 0.01)    # 2 max(h - 0.8, 0), weir at 0.8
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import _numeric_array, as_float

__all__ = ["abs", "clip", "max", "min", "relu", "sqrt", "step"]

#: What the helpers take: CasADi expressions or numbers and arrays. They return a CasADi
#: expression when any argument is one, else a numpy value.
Operand = ca.SX | ca.MX | ca.DM | ArrayLike

#: An operand converted for one backend by :func:`_args`: a CasADi ``SX``, ``MX`` or
#: ``DM``, a numpy float or a float array (the arithmetic of each works with floats).
_Value = Any

LOG2 = float(np.log(2.0))

_CASADI_TYPES = (ca.SX, ca.MX, ca.DM)
_CA = SimpleNamespace(tanh=ca.tanh, exp=ca.exp, expm1=ca.expm1, log1p=ca.log1p,
                      hypot=ca.hypot, sqrt=ca.sqrt)
_NP = SimpleNamespace(tanh=np.tanh, exp=np.exp, expm1=np.expm1, log1p=np.log1p,
                      hypot=np.hypot, sqrt=np.sqrt)


# ----------------------------------------------------------------- plumbing
def _width(width) -> float:
    return as_float(width, "width", positive=True)


def _args(**named: Operand) -> tuple[SimpleNamespace, list[_Value]]:
    """The operation namespace and the arguments, converted for one backend.

    With any CasADi argument, every argument becomes CasADi (a numpy array a ``DM``) and
    the result is an expression; otherwise every argument becomes a float array (a
    numpy scalar for a scalar), refused with a message naming it if not numeric.
    """
    out: list[_Value] = []
    if any(isinstance(v, _CASADI_TYPES) for v in named.values()):
        for name, v in named.items():
            if isinstance(v, _CASADI_TYPES):
                out.append(v)
            else:
                arr = _numeric_array(v, name)
                out.append(float(arr) if arr.ndim == 0 else ca.DM(arr))
        return _CA, out
    for name, v in named.items():
        arr = _numeric_array(v, name)
        out.append(arr[()] if arr.ndim == 0 else arr)
    return _NP, out


def _finite_bound(value: _Value, name: str) -> None:
    """Refuse an infinite or NaN numeric bound (symbols are not checked)."""
    if isinstance(value, ca.SX | ca.MX):
        return
    arr = np.asarray(value.full() if isinstance(value, ca.DM) else value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {value}")


def _softplus(z: _Value, op: SimpleNamespace) -> _Value:
    r""":math:`\log(1 + e^z)` for any finite ``z``, from analytic operations only."""
    t = z * (1 + op.tanh(z / 2)) / 2
    return t + op.log1p(op.expm1(-t) + op.exp(z - t))


# ------------------------------------------------------------------ helpers
def relu(x: Operand, width: float) -> Any:
    r"""Smooth :math:`\max(x, 0)`: the softplus of width :math:`w`.

    .. math:: \operatorname{relu}_w(x) = w \log\big(1 + e^{x / w}\big)

    Always above :math:`\max(x, 0)`, by at most :math:`w \log 2 \approx 0.69\,w` (at
    :math:`x = 0`) and by less than :math:`w e^{-|x|/w}` elsewhere. Positive down to
    :math:`x \approx -745\,w`, where it underflows to 0 (mind a square root of it: keep
    the argument above that by bounds). Its derivative is
    :func:`step`, the logistic function (continuous, between 0 and 1); its second
    derivative is at most :math:`1 / (4w)`.

    Parameters
    ----------
    x : CasADi expression, float or array
        Argument.
    width : float
        :math:`w > 0`, in the units of ``x``: the corner is rounded over a few ``width``.

    Returns
    -------
    CasADi expression of the argument's type, or numpy float / array

    Examples
    --------
    >>> from estim import soft
    >>> soft.relu([-1.0, 0.0, 1.0], 0.1).round(4)
    array([0.    , 0.0693, 1.    ])
    """
    w = _width(width)
    op, (xv,) = _args(x=x)
    return w * _softplus(xv / w, op)


def max(a: Operand, b: Operand, width: float) -> Any:  # noqa: A001 - the smooth counterpart of the builtin
    r"""Smooth :math:`\max(a, b)`, the softplus of the difference.

    .. math:: \max\nolimits_w(a, b) = b + w \log\big(1 + e^{(a - b)/w}\big)
              = w \log\big(e^{a/w} + e^{b/w}\big)

    Symmetric in ``a`` and ``b``; always above :math:`\max(a, b)`, by at most
    :math:`w \log 2` (where :math:`a = b`). Derivatives are continuous:
    :math:`\partial/\partial a = \sigma((a - b)/w)`, the logistic :func:`step`.

    Parameters
    ----------
    a, b : CasADi expression, float or array
        Arguments (broadcast together).
    width : float
        :math:`w > 0`, in the units of ``a`` and ``b``.

    Returns
    -------
    CasADi expression, or numpy float / array

    Examples
    --------
    >>> from estim import soft
    >>> round(float(soft.max(2.0, 1.0, 0.1)), 6)     # 2 + 0.1 log(1 + e^-10)
    2.000005
    """
    w = _width(width)
    op, (av, bv) = _args(a=a, b=b)
    return bv + w * _softplus((av - bv) / w, op)


def min(a: Operand, b: Operand, width: float) -> Any:  # noqa: A001 - the smooth counterpart of the builtin
    r"""Smooth :math:`\min(a, b)`.

    .. math:: \min\nolimits_w(a, b) = a - w \log\big(1 + e^{(a - b)/w}\big)
              = -\max\nolimits_w(-a, -b)

    Symmetric; always below :math:`\min(a, b)`, by at most :math:`w \log 2` (where
    :math:`a = b`). :math:`\partial/\partial a = \sigma((b - a)/w)`.

    Parameters
    ----------
    a, b : CasADi expression, float or array
        Arguments (broadcast together).
    width : float
        :math:`w > 0`, in the units of ``a`` and ``b``.

    Returns
    -------
    CasADi expression, or numpy float / array

    Examples
    --------
    A level capped at the rim height 0.8, smoothly:

    >>> import casadi as ca
    >>> from estim import soft
    >>> h = ca.SX.sym("h")
    >>> level = soft.min(h, 0.8, 0.01)       # instead of ca.fmin(h, 0.8)
    >>> round(float(soft.min(0.5, 0.8, 0.01)), 6)
    0.5
    """
    w = _width(width)
    op, (av, bv) = _args(a=a, b=b)
    return av - w * _softplus((av - bv) / w, op)


def abs(x: Operand, width: float) -> Any:  # noqa: A001 - the smooth counterpart of the builtin
    r"""Smooth :math:`|x|` (pseudo-Huber).

    .. math:: \operatorname{abs}_w(x) = \sqrt{x^2 + w^2} - w
              = \frac{x^2}{\sqrt{x^2 + w^2} + w}

    (evaluated in the second form: no cancellation near 0, no overflow). Exactly 0 at
    :math:`x = 0`, never negative, and below :math:`|x|` by less than :math:`w` (the gap
    is :math:`w - w^2 / (2|x|) + \dots` for large :math:`|x|`; it is :math:`x^2/(2w)`
    near 0, a parabola). The derivative :math:`x / \sqrt{x^2 + w^2}` is continuous and
    tends to :math:`\pm 1` algebraically (0.995 at :math:`|x| = 10w`); the second
    derivative is at most :math:`1/w` (at 0).

    Parameters
    ----------
    x : CasADi expression, float or array
        Argument.
    width : float
        :math:`w > 0`, in the units of ``x``.

    Returns
    -------
    CasADi expression, or numpy float / array

    Examples
    --------
    >>> from estim import soft
    >>> soft.abs([-3.0, 0.0, 4.0], 1.0).round(6)      # sqrt(x^2 + 1) - 1
    array([2.162278, 0.      , 3.123106])
    """
    w = _width(width)
    op, (xv,) = _args(x=x)
    return xv * (xv / (op.hypot(xv, w) + w))


def step(x: Operand, width: float) -> Any:
    r"""Smooth Heaviside step :math:`[x > 0]`: the logistic function.

    .. math:: \operatorname{step}_w(x) = \frac{1}{1 + e^{-x/w}}
              = \tfrac12\big(1 + \tanh\tfrac{x}{2w}\big)

    Between 0 and 1, :math:`\tfrac12` at :math:`x = 0` (where the exact step jumps, the
    error is :math:`\tfrac12`), within :math:`e^{-|x|/w}` of the step elsewhere (below
    :math:`10^{-4}` beyond :math:`|x| > 9.2\,w`). It is the derivative of :func:`relu`,
    with slope :math:`1/(4w)` at 0. Use it for an ``if_else`` on a state:
    ``ca.if_else(s > 0, a, b)`` becomes ``b + step(s, w) * (a - b)``.

    Parameters
    ----------
    x : CasADi expression, float or array
        Argument.
    width : float
        :math:`w > 0`, in the units of ``x``.

    Returns
    -------
    CasADi expression, or numpy float / array

    Examples
    --------
    >>> from estim import soft
    >>> soft.step([-0.5, 0.0, 0.5], 0.1).round(4)
    array([0.0067, 0.5   , 0.9933])
    """
    w = _width(width)
    op, (xv,) = _args(x=x)
    return (1 + op.tanh(xv / (2 * w))) / 2


def clip(x: Operand, lower: Operand, upper: Operand, width: float) -> Any:
    r"""Smooth :math:`\min(\max(x, l), u)`: a saturation with rounded corners.

    .. math:: \operatorname{clip}_w(x) = l + w \log\big(1 + e^{(x - l)/w}\big)
              - w \log\big(1 + e^{(x - u)/w}\big)

    Stays inside :math:`[l, u]` (strictly inside but for rounding), is increasing with slope
    :math:`\sigma((x - l)/w) - \sigma((x - u)/w)` in :math:`(0, 1)`, and is within
    :math:`w \log 2` of the exact clip (above it near :math:`l`, below it near
    :math:`u`, exact up to :math:`w e^{-d/w}` at a distance :math:`d` from both
    corners; far outside, it is the bound up to a rounding of :math:`10^{-16}|x|`).
    Choose :math:`w` well below :math:`u - l`.

    Parameters
    ----------
    x : CasADi expression, float or array
        Argument.
    lower, upper : CasADi expression, float or array
        Finite bounds :math:`l < u` (checked when numeric).
    width : float
        :math:`w > 0`, in the units of ``x``.

    Returns
    -------
    CasADi expression, or numpy float / array

    Examples
    --------
    A valve opening commanded outside its range:

    >>> from estim import soft
    >>> soft.clip([-0.5, 0.5, 1.5], 0.0, 1.0, 0.01).round(6)
    array([0. , 0.5, 1. ])
    """
    w = _width(width)
    op, (xv, low, high) = _args(x=x, lower=lower, upper=upper)
    _finite_bound(low, "lower")
    _finite_bound(high, "upper")
    if not isinstance(low, ca.SX | ca.MX) and not isinstance(high, ca.SX | ca.MX):
        lo, up = (np.asarray(v.full() if isinstance(v, ca.DM) else v, dtype=float)
                  for v in (low, high))
        try:
            ordered = bool(np.all(lo < up))
        except ValueError:
            raise ValueError(f"lower and upper must have shapes that broadcast, got "
                             f"{lo.shape} and {up.shape}") from None
        if not ordered:
            raise ValueError(f"lower must be less than upper, got lower={low}, "
                             f"upper={high}")
    return low + w * _softplus((xv - low) / w, op) - w * _softplus((xv - high) / w, op)


def sqrt(x: Operand, width: float) -> Any:
    r"""Smooth :math:`\sqrt{\max(x, 0)}`, with a bounded slope at 0: the textbook tank
    outflow :math:`a\sqrt{h}` at an empty tank, whose derivative is infinite there.

    .. math:: \operatorname{sqrt}_w(x) = \frac{r}{\sqrt{r + w}}, \qquad
              r = \operatorname{relu}_w(x)

    Below :math:`\sqrt{\max(x, 0)}` for :math:`x \ge w` and within
    :math:`0.53\sqrt{w}` of it everywhere (the largest difference at :math:`x = 0`); for
    :math:`x \gg w` the difference is about :math:`w / (2\sqrt x)`. Its derivative is
    continuous and at most about :math:`0.35/\sqrt{w}` (where the exact one is
    infinite); for :math:`x \ll -w` it is 0, as the exact function.

    Parameters
    ----------
    x : CasADi expression, float or array
        Argument.
    width : float
        :math:`w > 0`, in the units of ``x``.

    Returns
    -------
    CasADi expression of the argument's type, or numpy float / array

    Examples
    --------
    >>> from estim import soft
    >>> soft.sqrt([-1.0, 0.0, 0.25, 4.0], 1e-4).round(4)
    array([0.    , 0.0053, 0.4999, 2.    ])
    """
    op, _ = _args(x=x)
    r = relu(x, width)
    return r / op.sqrt(r + _width(width))
