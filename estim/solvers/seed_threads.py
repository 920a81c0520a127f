r"""A one-seed Function run over a chunk of seeds by one of several threads of a pipeline.

:class:`~estim.solvers.seeds.SeedMap` evaluates a batch with CasADi's threaded map, which
starts its threads at every call: over a chunk of :data:`~estim.solvers.seeds.CHUNK` van
der Pol EKF records of 1000 samples that costs half as much again as the serial map
(0.057 s against 0.038 s of processor time for 256 seeds). A pipeline that already runs
its chunks in several threads (:func:`estim.batch.run_batches`) evaluates each chunk with
:func:`evaluate`, the serial map of its thread's *slot*: the same Function on the same
rows, so the same numbers, bit for bit. CasADi releases the GIL while it evaluates.
"""

from __future__ import annotations

import threading
import weakref

import numpy as np

from estim._fast import FastFunction
from estim.solvers.seeds import SeedMap

__all__ = ["evaluate"]

#: Per SeedMap: the serial maps of every slot, by number of seeds.
_MAPS: weakref.WeakKeyDictionary[SeedMap, dict[tuple[int, int], FastFunction]] = \
    weakref.WeakKeyDictionary()
_LOCK = threading.Lock()


def evaluate(smap: SeedMap, slot: int, inputs: list[np.ndarray],
             outputs: list[np.ndarray]) -> None:
    """``smap``'s Function over ``n`` seeds into ``outputs`` (each ``(n, size)``, a row per
    seed, written in place), with the serial map of ``slot`` (one thread uses a slot at a
    time). Each input is either the same for all seeds (a flat array of its size) or
    ``(n, size)``, a row per seed (column-major within a row)."""
    n = len(outputs[0])
    with _LOCK:
        maps = _MAPS.setdefault(smap, {})
        ff = maps.get((slot, n))
        if ff is None:
            ff = maps[slot, n] = FastFunction(smap.fun.map(n))
    ff.evaluate_on([np.tile(a, n) if a.ndim == 1 else a.reshape(-1)
                    for a in (np.ascontiguousarray(a, dtype=float) for a in inputs)],
                   [o.reshape(-1) for o in outputs])
