r"""One-seed CasADi Functions run over many seeds: mapped in chunks, in threads, in place.

A Monte Carlo batch (:mod:`estim.batch`) and a filter's records of several seeds
(:meth:`EKF._filter_seeds <estim.EKF>`) evaluate the same Function of one seed's
record on every seed. :func:`seed_map` builds it once per key (kept for the last
:data:`_MAPPED_KEPT`), compiled to C when the batch is large enough
(:data:`COMPILE_MIN_SAMPLES`, through :mod:`estim._compile`, whose flags keep the
interpreter's arithmetic), and :class:`SeedMap` calls its map over chunks of
:data:`CHUNK` seeds on the machine's cores, reading and writing the seeds' rows in place.
"""

from __future__ import annotations

import hashlib
import os
import threading
from collections import OrderedDict
from collections.abc import Callable

import casadi as ca
import numpy as np

from estim._compile import compiled
from estim._fast import FastFunction
from estim.exceptions import CompilerUnavailable


def threads(n: int) -> int:
    """Threads for a map over ``n`` seeds: the machine's cores, at most ``n``."""
    return max(1, min(n, os.cpu_count() or 1))


#: Seeds per call of a mapped Function: CasADi builds the dense patterns of a map's
#: inputs and outputs when it creates it, at a cost that grows with their size, so
#: long batches are run as a loop over calls of this many seeds.
CHUNK = 32


class SeedMap:
    """A one-seed Function over many seeds: calls of its map over :data:`CHUNK` seeds
    (in threads, on the machine's cores) in a loop.

    Parameters
    ----------
    fun : casadi.Function
        The Function of one seed, dense inputs and outputs.
    how : str
        ``"compiled"`` or ``"interpreted"`` (and why), for the notes.
    """

    def __init__(self, fun: ca.Function, how: str):
        self.fun, self.how = fun, how
        self.lock = threading.Lock()
        self._maps: dict[int, FastFunction] = {}

    def _map(self, n: int) -> FastFunction:
        if n not in self._maps:
            nt = threads(n)
            self._maps[n] = FastFunction(self.fun.map(n, "thread", nt) if nt > 1
                                         else self.fun.map(n))
        return self._maps[n]

    def build(self, S: int) -> None:
        """Build the maps a call over ``S`` seeds uses (so that timing a call does not
        time their construction)."""
        with self.lock:
            for lo in range(0, S, CHUNK):
                self._map(min(CHUNK, S - lo))

    def __call__(self, inputs: list[np.ndarray], S: int) -> list[np.ndarray]:
        """Evaluate over ``S`` seeds: each input either the same for all seeds (a flat
        array of the input's size) or ``(S, size)``, one row per seed (column-major
        within a row); returns every output as ``(S, size)``. The map reads and writes
        the rows of a chunk in place (no copies)."""
        fun = self.fun
        inputs = [np.ascontiguousarray(a, dtype=float) for a in inputs]
        outs = [np.empty((S, fun.numel_out(i))) for i in range(fun.n_out())]
        with self.lock:
            tiled: dict[int, list] = {}
            for lo in range(0, S, CHUNK):
                n = min(CHUNK, S - lo)
                ff = self._map(n)
                if n not in tiled:  # the shared inputs, once per chunk size
                    tiled[n] = [np.tile(a, n) if a.ndim == 1 else None for a in inputs]
                ff.evaluate_on([t if t is not None else a[lo:lo + n].reshape(-1)
                                for a, t in zip(inputs, tiled[n], strict=True)],
                               [o[lo:lo + n].reshape(-1) for o in outs])
        return outs


#: Batches of at least this many samples (seeds × samples) are compiled to C when a C
#: compiler is present (once per machine: see :mod:`estim._compile`); smaller ones, and
#: every batch without a compiler, run in CasADi's interpreter.
COMPILE_MIN_SAMPLES = 20_000

#: Functions of one seed, by a hash of what they compute: a later comparison of the same
#: model and filter reuses them (building a map costs more than running it).
_MAPPED: OrderedDict[str, SeedMap] = OrderedDict()
_MAPPED_KEPT = 16
_MAPPED_LOCK = threading.Lock()


def seed_map(key: tuple, make: Callable[[bool], ca.Function], samples: int) -> SeedMap:
    """The one-seed Function ``make`` builds, ready to run over seeds (:class:`SeedMap`),
    kept under ``key`` (anything that determines it, e.g. the serialised step and the
    record length) for the last :data:`_MAPPED_KEPT` keys.

    ``make(expand)`` builds the Function (``expand``: inlined for CasADi's interpreter;
    else in the form to compile). With ``samples`` (seeds × samples) of at least
    :data:`COMPILE_MIN_SAMPLES` it is compiled (:func:`estim._compile.compiled`, once per
    machine), else, or without a C compiler, interpreted."""
    compile_ = samples >= COMPILE_MIN_SAMPLES
    digest = hashlib.sha256(repr((key, compile_)).encode()).hexdigest()
    with _MAPPED_LOCK:
        hit = _MAPPED.get(digest)
        if hit is not None:
            _MAPPED.move_to_end(digest)
            return hit
    made = None
    how = "interpreted"
    if compile_:
        try:
            made = SeedMap(compiled(make(False)), "compiled")
        except CompilerUnavailable as exc:
            how = f"interpreted ({exc})"
    if made is None:
        made = SeedMap(make(True), how)
    with _MAPPED_LOCK:
        _MAPPED[digest] = made
        while len(_MAPPED) > _MAPPED_KEPT:
            _MAPPED.popitem(last=False)
    return made
