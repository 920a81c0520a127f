"""Low-overhead numeric evaluation of CasADi Functions.

A normal ``casadi.Function`` call from Python converts every argument to a
``DM`` and every result back, which costs 15-25 µs per call. CasADi's
``Function.buffer()`` evaluates directly on preallocated memory instead
(well under 1 µs for small functions). :class:`FastFunction` owns one such
buffer with dense float64 input and output arrays that the caller fills and
reads in place.
"""

from __future__ import annotations

import threading
import warnings
from typing import Any

import casadi as ca
import numpy as np

_WARNED: set[str] = set()
_WARN_LOCK = threading.Lock()


def jitted(fun: ca.Function) -> ca.Function:
    """``fun`` compiled to machine code through the per-machine cache
    (:func:`estim._compile.compiled`: compiled once, loaded by later processes), or
    ``fun`` itself, with one :class:`~estim.EstimationWarning` per process saying why,
    when no C compiler is available."""
    from estim._compile import compiled
    from estim.exceptions import CompilerUnavailable

    try:
        return compiled(fun)
    except CompilerUnavailable as exc:
        with _WARN_LOCK:
            first = str(exc) not in _WARNED
            _WARNED.add(str(exc))
        if first:
            from estim.exceptions import EstimationWarning

            warnings.warn(f"jit=True: {exc}", EstimationWarning, stacklevel=3)
        return fun


class FastFunction:
    """Evaluate a CasADi Function on preallocated numpy buffers.

    Parameters
    ----------
    fun : casadi.Function
        Function with dense inputs. Outputs are densified automatically.
    args : list of arrays or None, optional
        Arrays to bind as inputs instead of fresh buffers (``None`` entries get
        fresh ones). Two FastFunctions bound to the same array read the same
        memory, which lets an estimator keep its state where the compiled code
        reads it.

    Notes
    -----
    ``args[i]`` is a flat float array of ``fun.numel_in(i)`` entries
    (column-major for matrices), ``out[i]`` likewise. An evaluation that fails inside
    (a Newton solve of a model's algebraic equations that breaks down, an external call)
    leaves every output NaN, never what the buffers held: the estimators' checks of
    non-finite values then fail the step instead of reading zeros. :meth:`__call__`
    copies its arguments in, evaluates and returns views of the outputs,
    which are overwritten by the next call: copy what must be kept.
    Instances pickle by rebuilding the buffer (the Function is serialised).
    """

    def __init__(self, fun: ca.Function, args: list[np.ndarray | None] | None = None):
        if any(not fun.sparsity_out(i).is_dense() for i in range(fun.n_out())):
            fun = _densified(fun)
        self.fun = fun
        self._bound = list(args) if args is not None else [None] * fun.n_in()
        if len(self._bound) != fun.n_in():
            raise ValueError(f"args must have {fun.n_in()} entries, got {len(self._bound)}")
        for i, a in enumerate(self._bound):
            if a is not None and (a.dtype != np.float64 or a.ndim != 1 or
                                  a.size != fun.numel_in(i) or not a.flags.c_contiguous):
                raise ValueError(f"args[{i}] must be a contiguous float64 array of "
                                 f"{fun.numel_in(i)} entries")
        self._build()

    def _build(self) -> None:
        fun = self.fun
        self.args = [np.zeros(fun.numel_in(i)) if b is None else b
                     for i, b in enumerate(self._bound)]
        self.out = [np.zeros(fun.numel_out(i)) for i in range(fun.n_out())]
        self._buf, self._eval = fun.buffer()
        self._may_fail = may_fail(fun)
        self._build_views()

    def _failed(self, out: list[np.ndarray]) -> None:
        """After an evaluation: ``out`` all NaN if it failed (CasADi's return code; asked
        only of a Function that can fail, :func:`may_fail`)."""
        if self._may_fail and self._buf.ret():
            for r in out:
                r.fill(np.nan)

    def _build_views(self) -> None:
        """Point the buffer at :attr:`args` and :attr:`out`."""
        self._point(self.args, self.out)

    def _point(self, args: list[np.ndarray], out: list[np.ndarray]) -> None:
        """Point the buffer at the arrays ``args`` (inputs) and ``out`` (outputs).

        CasADi's stubs ask for a size in bytes after the buffer; the wrapper takes
        one argument, a memoryview, and reads the size from it.
        """
        for i, a in enumerate(args):
            self._buf.set_arg(i, a.data)  # type: ignore[call-arg]
        for i, r in enumerate(out):
            self._buf.set_res(i, r.data)  # type: ignore[call-arg]

    def __call__(self, *args) -> list[np.ndarray]:
        for dst, src in zip(self.args, args, strict=True):
            dst[:] = np.ravel(src, order="F")
        self._eval()
        self._failed(self.out)
        return self.out

    def evaluate(self) -> list[np.ndarray]:
        """Evaluate on whatever is currently in :attr:`args`."""
        self._eval()
        self._failed(self.out)
        return self.out

    def evaluate_on(self, args: list[np.ndarray], out: list[np.ndarray]) -> None:
        """Evaluate reading ``args`` and writing ``out`` in place (contiguous float64
        arrays of the inputs' and outputs' sizes, e.g. rows of larger arrays), then point
        the buffer back at :attr:`args` and :attr:`out`."""
        try:
            self._point(args, out)
            self._eval()
            self._failed(out)
        finally:
            self._point(self.args, self.out)

    def __getstate__(self):
        return {"fun": self.fun.serialize(), "bound": self._bound}

    def __setstate__(self, state):
        self.fun = ca.Function.deserialize(state["fun"])
        self._bound = state["bound"]
        self._build()


def may_fail(fun: ca.Function) -> bool:
    """Whether an evaluation of ``fun`` can fail: an MX Function or one that calls other
    Functions (a Newton solve, an integrator, a callback); a plain SX graph cannot."""
    return not fun.is_a("SXFunction") or bool(fun.find_functions())


def _densified(fun: ca.Function) -> ca.Function:
    """Wrap ``fun`` so every output is dense."""
    args: Any = fun.sx_in() if fun.is_a("SXFunction") else fun.mx_in()  # SX or MX symbols
    return ca.Function(fun.name() + "_dense", args, [ca.densify(o) for o in fun.call(args)],
                       fun.name_in(), fun.name_out())
