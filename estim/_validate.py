"""Argument checking shared by the whole package.

Every public entry point converts user input through these helpers so that a
bad argument fails early with a message naming the argument and what was
expected.
"""

from __future__ import annotations

import difflib
import functools
import inspect
import operator
from collections.abc import Callable, Mapping, Sequence
from numbers import Real
from typing import Any, Literal, TypeVar, overload

import numpy as np


def as_vector(value, n: int, name: str, *, allow_nan: bool = False) -> np.ndarray:
    """Return ``value`` as a float ``(n,)`` array or raise naming ``name``.

    Scalars are accepted only when ``n == 1``; ``(n, 1)`` and ``(1, n)``
    arrays are flattened. Booleans, strings and complex numbers are refused.
    """
    arr = _numeric_array(value, name)
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim == 0 and n == 1:
        arr = arr.reshape(1)
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {np.shape(value)}")
    if not allow_nan and not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr}")
    if allow_nan and np.any(np.isinf(arr)):
        raise ValueError(f"{name} must not contain inf, got {arr}")
    return arr.copy()


#: The largest entry of a covariance (beyond, products of covariances overflow).
HUGE_COVARIANCE = 1e150


def as_covariance(value, n: int, name: str, *, definite: bool = True) -> np.ndarray:
    """Return a symmetric ``(n, n)`` covariance from a scalar, variances or a matrix.

    Parameters
    ----------
    value : float, (n,) array of variances, or (n, n) array
    n : int
        Dimension.
    name : str
        Argument name used in error messages.
    definite : bool
        Require positive definiteness (otherwise positive semi-definiteness).
    """
    if value is None:
        raise ValueError(f"{name} is required (a scalar, a vector of variances or a matrix)")
    arr = _numeric_array(value, name)
    if not np.all(np.isfinite(arr)):  # (before inf * eye, whose zeros would give NaN)
        raise ValueError(f"{name} must be finite")
    if arr.size and np.max(np.abs(arr)) > HUGE_COVARIANCE:
        raise ValueError(f"{name} must have entries below {HUGE_COVARIANCE:g} (the filters' "
                         f"products of covariances overflow beyond), got "
                         f"{np.max(np.abs(arr)):.3g}")
    if arr.ndim == 0:
        mat = float(arr) * np.eye(n)
    elif arr.ndim == 1 and arr.shape == (n,):
        mat = np.diag(arr)
    elif arr.shape == (n, n):
        mat = arr.copy()
    else:
        raise ValueError(
            f"{name} must be a scalar, a ({n},) vector of variances or a ({n}, {n}) matrix, "
            f"got shape {arr.shape}"
        )
    scale = max(1.0, float(np.max(np.abs(mat)))) if n else 1.0
    if not np.allclose(mat, mat.T, rtol=1e-10, atol=1e-12 * scale):
        raise ValueError(f"{name} must be symmetric")
    with np.errstate(over="ignore"):
        mat = 0.5 * mat + 0.5 * mat.T  # (halved first: no overflow near 1.8e308)
    if n == 0:
        return mat
    eig = np.linalg.eigvalsh(mat)
    if definite and eig[0] <= 0.0:
        raise ValueError(
            f"{name} must be positive definite (smallest eigenvalue {eig[0]:.3g})"
        )
    if not definite and eig[0] < -1e-12 * scale:
        raise ValueError(
            f"{name} must be positive semi-definite (smallest eigenvalue {eig[0]:.3g})"
        )
    return mat


def as_bounds(value, names: Sequence[str], name: str, default: float) -> np.ndarray:
    """Bounds as a ``(n,)`` array from None, a scalar, a sequence or a ``{name: value}`` dict."""
    n = len(names)
    out = np.full(n, default, dtype=float)
    if value is None:
        return out
    if isinstance(value, Mapping):
        for key, val in value.items():
            if key not in names:
                raise ValueError(f"{name} names unknown state {key!r}; states are {list(names)}")
            if val is not None:
                out[list(names).index(key)] = _bound_value(val, name)
        return out
    if isinstance(value, str):
        raise TypeError(f"{name} must be a number, a sequence or a dict, got {_show(value)}")
    arr = _numeric_array(value, name)
    if arr.ndim == 0:
        out[:] = _bound_value(arr, name)
        return out
    if arr.shape != (n,):
        raise ValueError(f"{name} must be a scalar, a ({n},) sequence or a dict, got {arr.shape}")
    if np.any(np.isnan(arr)):
        raise ValueError(f"{name} must not contain NaN")
    return arr.astype(float)


def _bound_value(val, name: str) -> float:
    if isinstance(val, bool | np.bool_) or not isinstance(
            val, Real | np.floating | np.integer | np.ndarray):
        raise TypeError(f"{name} entries must be numbers, got {_show(val)}")
    v = float(val)
    if np.isnan(v):
        raise ValueError(f"{name} must not contain NaN")
    return v


def as_names(value, name: str, prefix: str) -> list[str]:
    """State/output/input names from a sequence of strings or a count."""
    if value is None:
        return []
    if isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be a count or a list of names, got {value!r}")
    if isinstance(value, int | np.integer):
        if value < 0:
            raise ValueError(f"{name} must be a non-negative count or a list of names")
        return [f"{prefix}{i + 1}" for i in range(int(value))]
    if isinstance(value, str):
        return [value]
    if isinstance(value, Mapping | float | np.floating):
        raise TypeError(f"{name} must be a count or a list of names, got {_show(value)}")
    try:
        names = list(value)
    except TypeError:
        raise TypeError(f"{name} must be a count or a list of names, got {_show(value)}"
                        ) from None
    for item in names:
        if not isinstance(item, str):
            raise TypeError(f"{name} must be a list of strings, got item {item!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"{name} has duplicate names: {names}")
    return names


# ------------------------------------------------------------------ scalars
def _show(value, limit: int = 60) -> str:
    """A short ``repr`` for error messages."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _holds_bool(value) -> bool:
    """True for a boolean, a boolean array, or a (nested) list/tuple holding one."""
    if isinstance(value, bool | np.bool_):
        return True
    if isinstance(value, np.ndarray):
        return value.dtype == bool
    if isinstance(value, list | tuple):
        return any(_holds_bool(v) for v in value)
    return False


def by_name(value, names: Sequence[str] | None, name: str, what: str = "columns"):
    """A pandas ``DataFrame`` read by column name: its columns ``names``, in that order,
    as an array (other columns are ignored); a missing name is a ``ValueError`` naming it.
    A frame with unnamed columns (``0, 1, ...``), a ``Series`` and anything else are
    returned as they are, to be read by position."""
    columns = getattr(value, "columns", None)
    if names is None or columns is None or not type(value).__module__.startswith("pandas"):
        return value
    cols = list(columns)
    if cols == list(range(len(cols))):
        return value.to_numpy()
    missing = [n for n in names if n not in cols]
    if missing:
        raise ValueError(f"{name} is a DataFrame without the column(s) {missing}: it has "
                         f"{cols}, the model's {what} are {list(names)} (rename the columns, "
                         f"or pass {name}.to_numpy() to read them by position)")
    return value[list(names)].to_numpy()


def _numeric_array(value, name: str) -> np.ndarray:
    """``value`` as a float array (as ``np.asarray(value, dtype=float)``); None,
    booleans, strings, complex numbers and ragged nestings are refused."""
    if value is None:
        raise TypeError(f"{name} must be numeric, got None")
    if _holds_bool(value):
        raise TypeError(f"{name} must be numeric, got booleans: {_show(value)}")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nesting
        raise ValueError(f"{name} must be a rectangular numeric array, got {_show(value)}"
                         ) from exc
    kind = raw.dtype.kind
    if kind == "c":
        raise TypeError(f"{name} must be real, got complex numbers: {_show(value)}")
    if kind == "O" and any(v is None or isinstance(v, str | bool | np.bool_)
                           for v in raw.flat):
        kind = "U"
    if kind not in "iufO":
        raise TypeError(f"{name} must be numeric, got {type(value).__name__} {_show(value)}")
    try:
        return np.asarray(raw, dtype=float)
    except OverflowError:  # a Python integer beyond the float range
        raise ValueError(f"{name} must be within the float range, got {_show(value)}"
                         ) from None
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be numeric, got {type(value).__name__} "
                        f"{_show(value)}") from exc


def as_record(value, n: int, name: str, *, missing: bool = True,
              names: Sequence[str] | None = None, what: str = "columns") -> np.ndarray:
    """A time-major record: ``value`` as a ``(T, n)`` float array with ``T >= 1`` (a
    ``(T,)`` array when ``n == 1``). With ``missing``, NaN entries are allowed (a
    missing sample); ±inf is refused naming the first row that holds one, as is any
    non-finite entry without ``missing``. A pandas DataFrame is read by the column
    ``names`` (:func:`by_name`; ``what`` says whose names they are)."""
    arr = _numeric_array(by_name(value, names, name, what), name)
    if arr.ndim == 1 and n == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] != n:
        raise ValueError(f"{name} must have shape (T, {n}), got {arr.shape}")
    if arr.shape[0] < 1:
        raise ValueError(f"{name} must hold at least one sample")
    bad = np.isinf(arr) if missing else ~np.isfinite(arr)
    rows = np.flatnonzero(bad.any(axis=1))
    if len(rows):
        what = "must not contain inf" if missing else "must be finite"
        hint = " (use NaN for a missing output)" if missing else ""
        raise ValueError(f"{name} {what}: row {rows[0]} is {arr[rows[0]]}{hint}")
    return arr


def as_input_table(value, T: int, nu: int, name: str = "inputs",
                   names: Sequence[str] | None = None) -> np.ndarray:
    """An input signal given as a table, ``(T, nu)`` float (``(T,)`` when ``nu == 1``),
    finite: one row per step of a simulation. A pandas DataFrame is read by the input
    ``names``."""
    U = _numeric_array(by_name(value, names, name, "inputs"), name)
    if U.ndim == 1 and nu == 1:
        U = U[:, None]
    if U.shape != (T, nu):
        raise ValueError(f"{name} must have shape ({T}, {nu}) = (n_steps, nu), got {U.shape}")
    if not np.isfinite(U).all():
        raise ValueError(f"{name} must be finite")
    return U


def as_inputs(value, T: int, model, name: str = "U") -> np.ndarray:
    """The inputs of a ``T``-sample record as a ``(T, nu)`` float array. ``(T-1, nu)`` is
    accepted for a held input (``U[k]`` acts from sample k to k+1; the last row, never
    used, is zero); a model with ``hold="foh"`` takes ``(T, nu)``, the input at each
    sample. A number is that input at every sample (``U=0``: zero inputs, on purpose).
    None is an empty record for a model without inputs, and refused for one with inputs
    (a silent zero input would fit the wrong problem). Non-finite inputs are refused. A
    pandas DataFrame is read by the model's input names."""
    nu = model.nu
    if value is None:
        if nu:
            raise ValueError(
                f"{name} is required: {model.name} has nu = {nu} input(s) "
                f"{model.input_names}; give {name} ({T - 1}, {nu}) (or ({T}, {nu})), or "
                f"{name}=0 to run with zero inputs on purpose")
        return np.zeros((T, 0))
    if isinstance(value, int | float | np.integer | np.floating) and \
            not isinstance(value, bool | np.bool_):
        value = np.full((T, nu), float(value))
    U = _numeric_array(by_name(value, model.input_names, name, "inputs"), name)
    if U.ndim == 1 and nu == 1:
        U = U[:, None]
    if U.shape == (T - 1, nu) and not model.sampled:
        U = np.vstack([U, np.zeros((1, nu))])
    if U.shape != (T, nu):
        expected = f"({T}, {nu}), the input at each sample (hold='foh')" \
            if model.sampled else f"({T - 1}, {nu}) or ({T}, {nu})"
        raise ValueError(f"{name} must have shape {expected}, got {U.shape}")
    if not np.isfinite(U).all():
        raise ValueError(f"{name} must be finite")
    return U


def as_intervals(t, T: int, model, name: str = "t") -> np.ndarray | None:
    """The intervals ``t[k+1] - t[k]`` (``(T-1,)``) of sample times ``t`` for a model
    built with ``variable_dt=True`` (None when ``t`` is None). A continuous model with
    a fixed ``dt`` takes time stamps only at that spacing (to 1e-6 of it): anything
    else would be integrated over the wrong intervals, so it is refused, naming
    ``variable_dt``. A discrete model takes any increasing times (labels only)."""
    if t is None:
        return None
    ts = _numeric_array(t, name)
    if ts.shape != (T,):
        raise ValueError(f"{name} must have shape ({T},), got {ts.shape}")
    if not np.isfinite(ts).all():
        raise ValueError(f"{name} must be finite")
    dts = np.diff(ts)
    if len(dts) and not (dts > 0).all():
        k = int(np.flatnonzero(dts <= 0)[0]) + 1
        raise ValueError(f"{name} must be strictly increasing: {name}[{k}] = {ts[k]:g}, "
                         f"{name}[{k - 1}] = {ts[k - 1]:g}")
    if model.variable_dt:
        return dts
    if model.continuous and len(dts) and np.abs(dts - model.dt).max() > 1e-6 * model.dt:
        raise ValueError(f"{name} has intervals from {dts.min():g} to {dts.max():g}, but "
                         f"{model.name} integrates over a fixed dt = {model.dt:g}: build the "
                         f"model with variable_dt=True to integrate over each interval")
    return None


@overload
def as_bool(value, name: str, *, allow_none: Literal[False] = False) -> bool: ...


@overload
def as_bool(value, name: str, *, allow_none: bool) -> bool | None: ...


def as_bool(value, name: str, *, allow_none: bool = False) -> bool | None:
    """``value`` if it is a bool (Python or numpy), else ``TypeError`` naming ``name``.

    Strings, numbers and None (unless ``allow_none``) are refused: ``bool("no")``
    is True, so guessing would turn a switch on that was meant off.
    """
    if value is None and allow_none:
        return None
    if isinstance(value, bool | np.bool_):
        return bool(value)
    expected = "True, False or None" if allow_none else "True or False"
    raise TypeError(f"{name} must be {expected}, got {_show(value)}")


def _int_phrase(minimum: int | None) -> str:
    if minimum is None:
        return "an integer"
    if minimum == 1:
        return "a positive integer"
    if minimum == 0:
        return "a non-negative integer"
    return f"an integer >= {minimum}"


@overload
def as_int(value, name: str, *, minimum: int | None = None, allow_none: Literal[False] = False,
           expected: str | None = None) -> int: ...


@overload
def as_int(value, name: str, *, minimum: int | None = None, allow_none: bool,
           expected: str | None = None) -> int | None: ...


def as_int(value, name: str, *, minimum: int | None = None, allow_none: bool = False,
           expected: str | None = None) -> int | None:
    """``value`` as an ``int``; Python and numpy integers only (not bools, not floats).

    Parameters
    ----------
    value : object
        The argument.
    name : str
        Argument name used in error messages.
    minimum : int, optional
        Smallest accepted value (``ValueError`` below it).
    allow_none : bool
        Return None for None.
    expected : str, optional
        What the message says is expected (default from ``minimum``, e.g.
        "a positive integer").
    """
    if value is None and allow_none:
        return None
    phrase = expected or _int_phrase(minimum) + (" or None" if allow_none else "")
    if isinstance(value, bool | np.bool_):
        raise TypeError(f"{name} must be {phrase}, got {value!r}")
    try:
        out = operator.index(value)
    except TypeError:
        raise TypeError(f"{name} must be {phrase}, got {_show(value)}") from None
    if minimum is not None and out < minimum:
        raise ValueError(f"{name} must be {phrase}, got {_show(value)}")
    return out


def _float_phrase(minimum, maximum, positive, finite) -> str:
    if positive:
        text = "a positive number"
    elif minimum == 0:
        text = "a non-negative number"
    elif minimum is not None:
        text = f"a number >= {minimum:g}"
    else:
        text = "a finite number" if finite else "a number"
    if maximum is not None:
        text += f" <= {maximum:g}"
    return text


@overload
def as_float(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
             positive: bool = False, finite: bool = True, allow_none: Literal[False] = False,
             expected: str | None = None) -> float: ...


@overload
def as_float(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
             positive: bool = False, finite: bool = True, allow_none: bool,
             expected: str | None = None) -> float | None: ...


def as_float(value, name: str, *, minimum: float | None = None, maximum: float | None = None,
             positive: bool = False, finite: bool = True, allow_none: bool = False,
             expected: str | None = None) -> float | None:
    """``value`` as a ``float``; Python and numpy integers and floats (not bools, not strings).

    Parameters
    ----------
    value : object
        The argument.
    name : str
        Argument name used in error messages.
    minimum, maximum : float, optional
        Accepted range, bounds included (``ValueError`` outside).
    positive : bool
        Require ``value > 0``.
    finite : bool
        Refuse inf (NaN is always refused).
    allow_none : bool
        Return None for None.
    expected : str, optional
        What the message says is expected (default from the other arguments).
    """
    if value is None and allow_none:
        return None
    def message() -> str:  # (built only for an error: the checks run on every step)
        phrase = expected or _float_phrase(minimum, maximum, positive, finite) + (
            " or None" if allow_none else "")
        return f"{name} must be {phrase}, got {_show(value)}"

    if not (type(value) is float or type(value) is np.float64):  # (those: no ABC look-up)
        if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iuf":
            value = value[()]
        if isinstance(value, bool | np.bool_) or not isinstance(value, Real):
            raise TypeError(message())
    try:
        out = float(value)
    except OverflowError:  # a Python integer beyond the float range
        raise ValueError(message()) from None
    if out != out or (finite and abs(out) == np.inf) or (positive and out <= 0) \
            or (minimum is not None and out < minimum) \
            or (maximum is not None and out > maximum):
        raise ValueError(message())
    return out


def as_seed(value, name: str = "seed") -> int | None:
    """A random seed: None or a non-negative integer (not a bool)."""
    return as_int(value, name, minimum=0, allow_none=True,
                  expected="None or a non-negative integer")


def as_choice(value, choices: Sequence[str], name: str) -> str:
    """``value`` if it is one of the strings ``choices`` (``TypeError`` for a non-string,
    ``ValueError`` with a suggestion for an unknown one)."""
    if not isinstance(value, str):
        raise TypeError(f"{name} must be one of {tuple(choices)}, got {_show(value)}")
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}"
                         f"{did_you_mean(value, choices)}")
    return value


def did_you_mean(value: str, choices: Sequence[str]) -> str:
    """``"; did you mean 'x'?"`` for the nearest of ``choices``, or ``""``."""
    close = difflib.get_close_matches(value, list(choices), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


# ----------------------------------------------------------------- keywords
_BY_KEYWORD = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
_BY_POSITION = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)


def _quoted(names) -> str:
    return ", ".join(repr(n) for n in names)


def unknown_keywords_message(owner: str, unknown: Sequence[str], known: Sequence[str],
                             missing: Sequence[str] = ()) -> str:
    """``"<owner> got unknown option 'x'; did you mean 'y'? Known options: ..."``.

    A suggestion is looked for among the required names not given first, then
    among all known names.
    """
    hints = []
    for key in unknown:
        close = difflib.get_close_matches(key, list(missing), n=1, cutoff=0.6) or \
            difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
        if close:
            note = " (required, not given)" if close[0] in missing else ""
            hints.append(f"{close[0]!r}{note}" if len(unknown) == 1 else
                         f"{close[0]!r} for {key!r}{note}")
    plural = "s" if len(unknown) > 1 else ""
    text = f"{owner} got unknown option{plural} {_quoted(unknown)}"
    text += ("; did you mean " + ", ".join(hints) + "?") if hints else "."
    return text + f" Known options: {', '.join(known)}"


class _Signature:
    """What :func:`check_keywords` needs to know about a callable's parameters."""

    def __init__(self, func: Callable):
        params = list(inspect.signature(func).parameters.values())
        self.method = bool(params) and params[0].name in ("self", "cls")
        self.positional = [p.name for p in params if p.kind in _BY_POSITION]
        self.known = [p.name for p in params if p.kind in _BY_KEYWORD
                      and p.name not in ("self", "cls")]
        self.required = [p.name for p in params if p.default is p.empty
                         and p.kind in _BY_POSITION + _BY_KEYWORD
                         and p.name not in ("self", "cls")]
        self.var_positional = any(p.kind is p.VAR_POSITIONAL for p in params)
        self.var_keyword = any(p.kind is p.VAR_KEYWORD for p in params)

    def check(self, owner: str, args: tuple, kwargs: Mapping) -> None:
        covered = self.positional[:len(args)]
        missing = [n for n in self.required if n not in kwargs and n not in covered]
        if not self.var_keyword:
            unknown = [k for k in kwargs if k not in self.known]
            if unknown:
                raise TypeError(unknown_keywords_message(owner, unknown, self.known, missing))
        twice = [n for n in covered if n in kwargs and n not in ("self", "cls")]
        if twice:
            raise TypeError(f"{owner} got {_quoted(twice)} both by position and by keyword")
        if not self.var_positional and len(args) > len(self.positional):
            shift = 1 if self.method else 0
            names = [n for n in self.positional if n not in ("self", "cls")]
            raise TypeError(
                f"{owner} takes {len(self.positional) - shift} positional argument(s) "
                f"({_quoted(names) or 'none'}) but got {len(args) - shift}; give the others "
                f"by keyword (options: {', '.join(self.known)})")
        if missing:
            word = "options" if len(missing) > 1 else "option"
            raise TypeError(f"{owner} is missing the required {word} {_quoted(missing)}")


_F = TypeVar("_F", bound=Callable[..., Any])


@overload
def check_keywords(func: _F, *, owner: str | None = None) -> _F: ...


@overload
def check_keywords(func: None = None, *, owner: str | None = None) -> Callable[[_F], _F]: ...


def check_keywords(func: Callable | None = None, *, owner: str | None = None) -> Any:
    """Decorator: check keyword names against ``func``'s signature before calling it.

    Unknown keywords raise ``TypeError("<owner> got unknown option 'clipp'; did
    you mean 'clip'? Known options: ...")``, then missing required ones
    ``TypeError`` naming them, before ``func`` does any work. ``owner`` is the
    name in the messages (default: the class of ``self`` for methods named
    ``__init__``, else the function's qualified name). The wrapper keeps
    ``func``'s name, docstring and signature (``functools.wraps``).
    """
    if func is None:
        return lambda f: check_keywords(f, owner=owner)
    if getattr(func, "_checks_keywords", False):
        return func
    sig = _Signature(func)
    is_init = func.__name__ == "__init__"

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        who = owner or (type(args[0]).__name__ if is_init and args else func.__qualname__)
        sig.check(who, args, kwargs)
        return func(*args, **kwargs)

    wrapper.__dict__["_checks_keywords"] = True  # read by the getattr above
    return wrapper


def check_call(func: Callable, kwargs: Mapping, owner: str) -> None:
    """Check keyword arguments meant for ``func`` (e.g. forwarded ``**kwargs``)."""
    _Signature(getattr(func, "__wrapped__", func)).check(owner, (), kwargs)
