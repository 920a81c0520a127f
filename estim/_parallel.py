r"""Running :func:`~estim.compare`'s runs on joblib or dask workers.

What it costs: workers take a while to start (a new process imports estim: about
2 s) and each builds its estimators before its first run. :func:`startup` estimates
the start-up from the last measured one of the same backend and number of workers
(about 0.1 s while they are still up), :func:`plan` cuts every estimator's runs into
chunks of similar cost that the workers take in turn (guided self-scheduling), and
:func:`makespan` is the wall time of those chunks on the workers, so
:func:`~estim.compare` can tell whether the workers pay. :func:`dispatch` sends the
chunks (through joblib, or straight to the active ``dask.distributed`` client),
measures the workers' start-up for the next estimate and returns the summaries;
:func:`run_chunk`, the workers' task, builds each estimator once per worker and call.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Mapping

import numpy as np

from estim._runs import Run, Spec, build, run_seed
from estim._workers import run_tasks
from estim.estimators.base import Estimator
from estim.scenarios import Scenario

#: A chunk of runs: ``(name, start, stop)``, runs ``start:stop`` of that estimator.
Task = tuple[str, int, int]
#: Every estimator's cost: ``(setup, per_run, n_runs)`` seconds, seconds, runs.
Costs = Mapping[str, tuple[float, float, int]]


#: Seconds to start workers and import estim in them, before any was measured in this
#: process; then the last measured start-up of the same backend and number of workers.
_COLD_START = {"threading": 0.05}
_COLD_START_DEFAULT = 2.0
#: Seconds from a call to the first run on warm (already started) workers, at least.
_WARM_START = 0.1
#: Seconds to send a chunk to a worker and its results back.
_TASK_OVERHEAD = 0.005
#: loky workers stop after this long idle (joblib's default).
_IDLE_TIMEOUT = 300.0
#: (backend, workers) -> {"end": time.monotonic() of the last call's end, "cold": s, "warm": s}
_POOLS: dict[tuple[str, int], dict[str, float]] = {}


def _loky_alive() -> bool:
    """Whether loky's reusable executor is up (best effort: True when unknown)."""
    try:
        from joblib.externals.loky import reusable_executor

        ex = reusable_executor._executor
        return ex is not None and ex._flags.broken is None and not ex._flags.shutdown
    except Exception:  # noqa: BLE001 - private API; assume alive
        return True


def startup(backend: str, workers: int) -> tuple[float, bool]:
    """Estimated seconds before the workers run (start-up), and whether they are warm."""
    rec = _POOLS.get((backend, workers), {})
    warm = bool(rec) and time.monotonic() - rec["end"] < _IDLE_TIMEOUT and (
        backend != "loky" or _loky_alive())
    if warm:
        return max(rec.get("warm", _WARM_START), _WARM_START), True
    cold = rec.get("cold", _COLD_START.get(backend, _COLD_START_DEFAULT))
    return max(cold, _WARM_START if backend != "threading" else 0.0), False


def plan(costs: Costs, workers: int) -> list[Task]:
    """Split every estimator's runs into chunks of similar cost for ``workers`` workers.

    ``costs[name] = (setup, per_run, n_runs)``: seconds to build the estimator (and
    its first run's extra), seconds per run, runs to do. Returns tasks
    ``(name, start, stop)`` (runs ``start:stop`` of that estimator), in the order to
    dispatch them: guided self-scheduling, each chunk taken from the estimator with
    the most work left and worth half a worker's share of the work left, down to a
    tenth of a worker's share of the total, so the chunks shrink towards the end and
    the workers finish together; the estimators interleave.
    """
    workers = max(1, int(workers))
    left = {name: n for name, (_, _, n) in costs.items() if n > 0}
    pos = dict.fromkeys(left, 0)
    total = sum(costs[name][1] * n for name, n in left.items())
    remaining = total
    floor = total / (10 * workers)
    tasks: list[Task] = []
    while left:
        name = max(left, key=lambda k: costs[k][1] * left[k])
        per = costs[name][1]
        target = max(remaining / (2 * workers), floor)
        k = left[name] if per <= 0 else int(min(max(round(target / per), 1), left[name]))
        if (left[name] - k) * per < floor / 2:  # no crumbs at the end
            k = left[name]
        tasks.append((name, pos[name], pos[name] + k))
        pos[name] += k
        left[name] -= k
        remaining -= k * per
        if not left[name]:
            del left[name]
    return tasks


def makespan(tasks: list[Task], costs: Costs, workers: int) -> float:
    """Wall time of ``tasks`` dealt in order to the first free of ``workers`` workers,
    each building an estimator (``setup``) the first time it runs one of its chunks
    (and ``_TASK_OVERHEAD`` per chunk)."""
    free = [0.0] * max(1, int(workers))
    built: list[set[str]] = [set() for _ in free]
    for name, a, b in tasks:
        w = int(np.argmin(free))
        setup, per, _ = costs[name]
        free[w] += (b - a) * per + (0.0 if name in built[w] else setup) + _TASK_OVERHEAD
        built[w].add(name)
    return max(free)


#: Estimators built by a worker in the current call, by (call, name, thread): a worker
#: builds each estimator once per call, whatever the number of its chunks.
_BUILT: dict[tuple[str, str, int], Estimator | str] = {}
_BUILT_LOCK = threading.Lock()


def run_chunk(scenario: Scenario, spec: Spec, seeds: list[int], burn_in: int,
              keep_logs: bool, key: tuple[str, str] | None = None
              ) -> tuple[int, float, list[Run]]:
    """Run one estimator over some seeds: ``(pid, start time, summaries per seed)``.

    With ``key = (call, name)`` the estimator is built once per process and thread
    for that call (and kept for the call's other chunks)."""
    start = time.time()
    if key is None:
        est = build(spec, scenario)
    else:
        full = (*key, threading.get_ident())
        with _BUILT_LOCK:
            if any(k[0] != key[0] for k in _BUILT):  # a new call: drop the last one's
                _BUILT.clear()
            kept = _BUILT.get(full)
        if kept is None:
            est = build(spec, scenario)
            with _BUILT_LOCK:
                _BUILT[full] = est
        else:
            est = kept
    return os.getpid(), start, [run_seed(scenario, est, s, burn_in, keep_logs) for s in seeds]


def dispatch(scenario: Scenario, specs: Mapping[str, Spec], seeds: list[int],
             tasks: list[Task], burn_in: int, keep_logs: bool, *, n_jobs: int, backend: str,
             workers: int, warm: bool) -> tuple[list[list[Run]], float, float]:
    """Run ``tasks`` (runs ``start:stop`` of ``seeds`` for an estimator) on the workers.

    Parameters
    ----------
    specs : dict
        Every estimator's specification, by name (sent to the workers, which build them).
    n_jobs, backend : int, str
        As :func:`~estim.compare` takes them: a joblib backend, or ``"dask"`` for the
        active ``dask.distributed`` client.
    workers, warm : int, bool
        The number of workers and whether they were up (:func:`startup`): the start-up
        measured here is kept under them for the next estimate.

    Returns
    -------
    runs : list of list of dict
        Every task's summaries, in the order of ``tasks``.
    wall : float
        Seconds of the whole dispatch.
    started : float
        Seconds from the dispatch to the workers' first run, mean over the workers.
    """
    call = f"{os.getpid()}-{time.time_ns()}"
    args = [(scenario, specs[name], seeds[a:b], burn_in, keep_logs, (call, name))
            for name, a, b in tasks]
    t0 = time.time()
    results = run_tasks(run_chunk, args, n_jobs=n_jobs, backend=backend)
    wall = time.time() - t0
    with _BUILT_LOCK:
        _BUILT.clear()  # this process's (threading backend)
    first: dict[int, float] = {}
    runs = []
    for pid, start, res in results:
        runs.append(res)
        first[pid] = min(first.get(pid, np.inf), start - t0)
    rec = _POOLS.setdefault((backend, workers), {})
    started = rec["warm" if warm else "cold"] = max(float(np.mean(list(first.values()))), 0.0)
    rec["end"] = time.monotonic()
    return runs, wall, started
