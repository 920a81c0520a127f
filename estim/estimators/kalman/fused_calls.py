r"""The compiled calls of the fused Kalman filters
(:class:`~estim.estimators.kalman.fused.FusedKalman`): their two steps, the scan over a
whole record and that scan over the records of many seeds.

With ``jit=True`` each is compiled to machine code through the per-machine cache
(:func:`estim._fast.jitted`, :mod:`estim._compile`: built once, loaded by later processes
in milliseconds), with flags that keep CasADi's arithmetic (no fast-math, no contraction
into fused multiply-adds), so the compiled filter gives the interpreted filter's numbers;
without a C compiler they stay interpreted, with one
:class:`~estim.EstimationWarning` per process. CasADi's interpreter spends a few
nanoseconds on every instruction of a step, the compiled code a fraction of that: the
whole-record scan runs several times faster compiled.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim._fast import FastFunction, jitted, may_fail
from estim.estimators.kalman.statuses import record_statuses, reported
from estim.solvers.kalman.kalman import NFLAGS, record_function
from estim.solvers.seed_threads import evaluate
from estim.solvers.seeds import COMPILE_MIN_SAMPLES, seed_map

if TYPE_CHECKING:
    from estim.estimators.kalman.fused import FusedKalman

__all__ = ["RECORD_WINDOW", "JitFunction", "SeedFilter", "filter_seeds", "record_call",
           "scan_record", "step_calls"]

#: :meth:`~estim.estimators.kalman.fused.FusedKalman.filter` keeps its Function for this many
#: record lengths.
RECORD_LENGTHS_KEPT = 8
#: A record longer than this many samples is filtered in windows of this length (the last
#: one padded with missing outputs), continued one from the other: two Functions to build
#: (the first window and a continued one), whatever the length, where one Function for
#: the whole record takes time and memory that grow with it (10^6 samples of van der
#: Pol's EKF: 63 s and 4.9 GB to build).
RECORD_WINDOW = 4096


class JitFunction(FastFunction):
    """A :class:`~estim._fast.FastFunction` that runs ``fun`` compiled through the
    per-machine cache (:attr:`library`; ``fun`` itself without a C compiler, see
    :func:`estim._fast.jitted`).

    :attr:`fun` stays the interpreted Function: what code generation exports, what
    identifies the computation, and what pickles, so that a copy in another process or
    on another machine compiles it again (in practice: loads it from the cache) instead
    of depending on this one's library path.
    """

    #: The Function that runs: the compiled library, or :attr:`fun` without a compiler.
    library: ca.Function

    @property
    def compiled(self) -> bool:
        """Whether the Function runs compiled (False: no C compiler, interpreted)."""
        return self.library is not self.fun

    def _build(self) -> None:
        self.library = jitted(self.fun)
        self.args = [np.zeros(self.fun.numel_in(i)) if b is None else b
                     for i, b in enumerate(self._bound)]
        self.out = [np.zeros(self.fun.numel_out(i)) for i in range(self.fun.n_out())]
        self._buf, self._eval = self.library.buffer()
        self._may_fail = may_fail(self.fun)
        self._build_views()


def step_calls(est: FusedKalman, bound: list) -> tuple[FastFunction, FastFunction]:
    """The filter's update-only and predict-and-update steps on the buffers ``bound``
    (``est._build(predict)``), compiled when ``est.jit``."""
    funs = [est._build(predict=False), est._build(predict=True)]
    if not est.jit:
        return FastFunction(funs[0], bound), FastFunction(funs[1], bound)
    with ThreadPoolExecutor(1) as pool:  # both compiled (or loaded) at once
        other = pool.submit(jitted, funs[1])
        jitted(funs[0])
        other.result()
    return JitFunction(funs[0], bound), JitFunction(funs[1], bound)  # loaded: at once


def record_call(est: FusedKalman, T: int, expand: bool = True, first: bool = True
                ) -> FastFunction:
    """``(s0, Y, W, tuning, P0) -> (S, E, flags)``: the fused step over ``T`` samples
    (:func:`estim.solvers.kalman.kalman.record_function`; not ``first``: a record continued),
    kept in ``est`` for the last :data:`RECORD_LENGTHS_KEPT` record lengths. ``expand``:
    inlined for CasADi's interpreter, or, when ``est.jit``, compiled (the step's code
    once, called in loops); not ``expand``: the form to compile, not compiled."""
    cache = est.__dict__.setdefault("_whole_records", {})
    if (T, expand, first) in cache:
        return cache[T, expand, first]

    def make(inlined: bool) -> ca.Function:
        return record_function(f"{est.name}_record", est.model, est._build, T,
                               expand=inlined, sqrt=est._sqrt, first=first,
                               extra=est._n_adapt)

    fun: FastFunction | None = None
    if est.jit and expand:
        fun = JitFunction(make(False))
        if not fun.compiled:  # no C compiler: the interpreter's (inlined) form
            fun = None
    if fun is None:
        fun = FastFunction(make(expand))
    if len(cache) >= RECORD_LENGTHS_KEPT:  # the oldest length goes
        del cache[next(iter(cache))]
    cache[T, expand, first] = fun
    return fun


def scan_record(est: FusedKalman, Y: np.ndarray, W: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fused step over the record ``Y (T, ny)`` with the transitions' inputs ``W (T,
    nw)`` from ``est``'s state: the filter states ``(T, ns)``, innovations ``(T, ny)``
    and flags ``(T, 9)``, sample by sample (:func:`record_call`; in windows of
    :data:`RECORD_WINDOW` samples beyond that length). After a window with a failed
    update the later windows are not filtered: their rows stay NaN."""
    T, ny = Y.shape
    if T <= RECORD_WINDOW:
        S, E, F = record_call(est, T)(est._s, Y.T, W.T, est._tun, est._P0_data)
        return S.reshape(T, -1), E.reshape(T, -1), F.reshape(T, -1)
    L = RECORD_WINDOW
    n = -(-T // L)
    Yp = np.full((n * L, ny), np.nan)  # missing outputs after the record: predictions
    Yp[:T] = Y
    Wp = np.empty((n * L, W.shape[1]))
    Wp[:T], Wp[T:] = W, W[-1]
    ns = est._s.size
    out = [np.full((n * L, k), np.nan) for k in (ns, ny, NFLAGS)]
    s = est._s.copy()
    for k in range(n):
        rows = slice(k * L, (k + 1) * L)
        fun = record_call(est, L, first=k == 0)
        fun.evaluate_on([s, Yp[rows].ravel(), Wp[rows].ravel(), est._tun, est._P0_data],
                        [o[rows].reshape(-1) for o in out])
        if (out[2][rows, 1] == 0).any():  # a failed update: the step loop takes over
            break
        s = out[0][(k + 1) * L - 1].copy()
    return out[0][:T], out[1][:T], out[2][:T]


class SeedFilter:
    """``est`` over the records of seeds of ``len(u_step)`` samples, chunk by chunk, each
    as :meth:`~estim.estimators.kalman.fused.FusedKalman.step` at every sample after a reset.

    The one-seed scan (:meth:`~estim.estimators.kalman.fused.FusedKalman._whole_record`) runs
    over the seeds through :func:`estim.solvers.seeds.seed_map`: compiled from
    :data:`~estim.solvers.seeds.COMPILE_MIN_SAMPLES` samples (``S`` seeds in all) on, or
    at any size when ``est.jit``. :meth:`run` only evaluates (it may run in another
    thread than :meth:`results`); ``est`` must not step meanwhile.

    Attributes
    ----------
    seconds : float
        Wall time of the evaluations so far.
    how : str
        ``"compiled"`` or ``"interpreted"`` (and why).
    """

    def __init__(self, est: FusedKalman, u_step: np.ndarray, S: int):
        T = len(u_step)
        self.est, self.T, self.seconds = est, T, 0.0
        self.W = est.model.step_transitions(u_step).ravel()
        est.reset()
        key = ("filter", est._predict_update.fun.serialize(), est._update.fun.serialize(), T)
        samples = max(S * T, COMPILE_MIN_SAMPLES) if est.jit else S * T
        self.fun = seed_map(key, lambda expand: est._whole_record(T, expand).fun, samples)
        self.how = self.fun.how

    def run(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The filter states ``(n, T, nx + nx^2)`` and flags ``(n, T, 9)`` of the seeds'
        measurements ``Y (n, T, ny)``."""
        est, n = self.est, len(Y)
        t0 = time.perf_counter()
        Sx, _, F = self.fun([est._s, Y.reshape(n, -1), self.W, est._tun, est._P0_data], n)
        self.seconds += time.perf_counter() - t0
        return Sx.reshape(n, self.T, -1), F.reshape(n, self.T, -1)

    def run_into(self, Y: np.ndarray, Sx: np.ndarray, F: np.ndarray, slot: int) -> float:
        """:meth:`run` into the rows ``Sx (n, T, nx + nx^2)`` and ``F (n, T, 9)`` (C
        contiguous, written in place) with the serial map of ``slot``
        (:func:`estim.solvers.seed_threads.evaluate`: for a pipeline's threads); returns
        the seconds it took (not added to :attr:`seconds`)."""
        est, n = self.est, len(Y)
        t0 = time.perf_counter()
        evaluate(self.fun, slot, [est._s, Y.reshape(n, -1), self.W, est._tun, est._P0_data],
                 [Sx.reshape(n, -1), np.empty((n, Y[0].size)), F.reshape(n, -1)])
        return time.perf_counter() - t0

    def results(self, Sx: np.ndarray, F: np.ndarray) -> dict:
        """``x``, ``P``, ``nis`` and ``status`` (see :func:`filter_seeds`) of :meth:`run`'s
        output."""
        est = self.est
        n, T, nx, nd = len(Sx), self.T, est.model.nx, est.model.ndx
        P = Sx[:, :, nx:nx + nd * nd].reshape(n, T, nd, nd).transpose(0, 1, 3, 2)
        if est._sqrt:
            P = reported(P, True)
        failed = (F[:, :, 1] == 0).any(axis=1)
        status = [None if failed[i] else record_statuses(est, F[i], P[i])[0]
                  for i in range(n)]
        return {"x": Sx[:, :, :nx], "P": P, "nis": np.where(F[:, :, 4] > 0, F[:, :, 0], np.nan),
                "status": status}


def filter_seeds(est: FusedKalman, Y: np.ndarray, u_step: np.ndarray) -> dict:
    r"""Filter the records of several seeds at once, as ``est.step`` at every sample
    after a reset, in one evaluation of :class:`SeedFilter` (the batched path of
    :func:`~estim.compare`).

    Parameters
    ----------
    est : FusedKalman
    Y : (S, T, ny) array
        The seeds' measurements.
    u_step : (T, nu) array
        The input given to ``step`` with each sample (the same for every seed).

    Returns
    -------
    dict
        ``x (S, T, nx)``, ``P (S, T, nx, nx)``, ``nis (S, T)``, ``status`` (per
        seed the status of every sample that is not ``"ok"``, ``{k: status}``; None
        for a seed whose filter met a failed update: its recovery depends on the
        filter's history, so that seed must be run step by step), ``seconds`` (wall
        time of the call over the seeds), ``total`` (with the set-up and the
        statuses) and ``how`` (``"compiled"`` or ``"interpreted"``, see
        :func:`estim.solvers.seeds.seed_map`).
    """
    t0 = time.perf_counter()
    seeds = SeedFilter(est, u_step, len(Y))
    seeds.fun.build(len(Y))  # not timed by run
    out = seeds.results(*seeds.run(Y))
    est.reset()
    out.update(seconds=seeds.seconds, total=time.perf_counter() - t0, how=seeds.how)
    return out
