r"""Seeded Monte Carlo comparison of several estimators on one scenario.

Every estimator sees the same noise for a given seed, so differences in the
table are the estimators', not the draws'. Runs go through joblib: with
``n_jobs=1`` they run in this process; with ``n_jobs>1`` in worker
processes (``backend="loky"``), and any joblib backend works, e.g. a dask
cluster::

    from dask.distributed import Client
    client = Client("tcp://scheduler:8786")       # or Client() for a local cluster
    estim.compare(sc, estimators, seeds=range(200), n_jobs=16, backend="dask")

The numbers do not depend on how the runs were distributed.

With ``n_jobs != 1`` the first runs of every estimator are done in this
process and timed; the rest go to the workers only when that pays for
starting them (see :func:`compare`), in chunks of similar cost
(:func:`_plan`), and each worker builds an estimator once per call.
"""

from __future__ import annotations

import copy
import html
import importlib.util
import os
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from estim._validate import as_bool, as_float, as_int, check_keywords
from estim.estimators.base import Estimator
from estim.log import Log
from estim.metrics import nees, peak_location, rmse, startup_samples
from estim.model import Model
from estim.scenarios import Scenario
from estim.simulate import FAILED_FRACTION, simulate
from estim.solvers.seeds import threads as seed_threads

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure

Factory = Callable[[Model, dict], Estimator]


@dataclass
class ComparisonRow:
    """Summary of one estimator over all seeds.

    ``rmse_mean``/``rmse_std``: RMSE over all states, mean and standard
    deviation over seeds; ``rmse_per_state``: mean per state. ``nees_mean``:
    time-averaged NEES divided by ``nx`` (1 for a consistent filter), mean over
    seeds; ``consistent``: within two standard errors (over seeds) of 1
    (None without covariance). ``step_median``/``step_p90``: seconds per step.
    ``failures``: steps that failed (``success`` False: the estimator re-anchored);
    ``flagged``: successful steps whose status was not ``"ok"`` (``"inexact"``,
    ``"suspect"``); ``steps``: steps of the completed runs. ``runs``: runs that
    completed; ``errors``: ``{seed: "ExceptionType: message"}`` of the runs that
    raised (the statistics are over the completed runs). ``nees_se``: standard
    error of ``nees_mean`` over seeds; ``largest_error``: the largest absolute
    error of any state, where and when; ``kind``: the estimator's class name;
    ``caveat``: a known limitation of its configuration
    (:attr:`Estimator.caveat`).
    """

    name: str
    rmse_mean: float
    rmse_std: float
    rmse_per_state: dict[str, float]
    nees_mean: float
    consistent: bool | None
    step_median: float
    step_p90: float
    failures: int
    runs: int
    flagged: int = 0
    steps: int = 0
    errors: dict[int, str] = field(default_factory=dict)
    nees_se: float = float("nan")
    largest_error: str = ""
    kind: str = ""
    caveat: str = ""

    def notes(self) -> list[str]:
        """What went wrong in these runs, a line each (empty when nothing did)."""
        out = []
        if self.errors:
            total = self.runs + len(self.errors)
            seed, message = next(iter(self.errors.items()))
            out.append(f"{self.name}: {len(self.errors)} of {total} runs raised and are left "
                       f"out (seed {seed}: {message})")
        if self.steps and self.failures > FAILED_FRACTION * self.steps:
            out.append(f"{self.name}: {self.failures} of {self.steps} steps failed "
                       f"({100 * self.failures / self.steps:.0f} %): the estimates there are "
                       f"re-anchored, see the logs' status")
        if self.steps and self.flagged > FAILED_FRACTION * self.steps:
            out.append(f"{self.name}: {self.flagged} of {self.steps} steps flagged "
                       f"({100 * self.flagged / self.steps:.0f} %): inexact solves, or NIS/cost "
                       f"beyond the 1e-9 chi-square tail (outliers, or an estimator the data "
                       f"contradict); see the logs' status")
        return out


@dataclass
class Comparison:
    """Result of :func:`compare`: one row per estimator, per-seed RMSEs, logs if kept.

    Attributes
    ----------
    scenario : str
        Scenario name.
    seeds : list of int
    rows : list of ComparisonRow
    rmse : dict of str -> (n_seeds,) array
        RMSE of every run, per estimator, in seed order (NaN for a run that raised).
    logs : dict of str -> list of Log
        Every run's log (with ``keep_logs=True``); a run that raised has the log of
        the steps it completed, or None.
    remarks : dict of str -> str
        The scenario's :attr:`~estim.Scenario.remarks` (what is known about an
        estimator class on it), used by :meth:`notes`.
    parallel : str
        With ``n_jobs != 1``, how the runs were distributed and why ("serial: ..."
        or "parallel (...): ..."), printed under the table; empty with ``n_jobs=1``.
    batched : str
        Which estimators ran all seeds in one batched call (``compare(batch=)``) and
        how long that took, printed under the table; empty when none did.
    """

    scenario: str
    seeds: list[int]
    rows: list[ComparisonRow]
    rmse: dict[str, np.ndarray]
    logs: dict[str, list[Log]] = field(default_factory=dict)
    remarks: dict[str, str] = field(default_factory=dict)
    parallel: str = ""
    batched: str = ""

    #: What the columns mean, printed under the table.
    LEGEND = ("RMSE: root mean square error over states, samples and seeds. NEES/n: "
              "normalised estimation error squared per state, averaged over time and seeds; "
              "1 when the reported covariance matches the errors, above 1 overconfident, "
              "below 1 pessimistic. cons.: NEES/n within two standard errors (over the "
              "seeds) of 1; '-' without a covariance. step: wall time per step. failed: "
              "steps that failed and were re-anchored; flagged: inexact or suspect steps.")

    def notes(self) -> list[str]:
        r"""Why a row looks the way it does, a line per estimator that needs one.

        A row gets a note when a run raised, steps failed or were flagged
        (:meth:`ComparisonRow.notes`), when it is inconsistent (how far its
        errors are from the :math:`\sigma` it reports: :math:`\sqrt{NEES/n}`
        times), or when its RMSE is more than three times the best row's (with
        its largest error). The estimator's :attr:`~estim.Estimator.caveat` and
        the scenario's remark about its class follow, when there are such.
        """
        finite = [r for r in self.rows if np.isfinite(r.rmse_mean)]
        best = min(finite, key=lambda r: r.rmse_mean) if finite else None
        out: list[str] = []
        explained: dict[str, list[str]] = {}
        for r in self.rows:
            parts = []
            if r.consistent is False and np.isfinite(r.nees_mean) and r.nees_mean > 0:
                ratio = float(np.sqrt(r.nees_mean))
                side = ("overconfident: its errors are" if r.nees_mean > 1 else
                        "pessimistic: its errors are only")
                parts.append(f"inconsistent, NEES/n {r.nees_mean:.3g} ± {2 * r.nees_se:.2g} "
                             f"({side} {ratio:.2g}× the σ it reports)")
            if best is not None and r is not best and r.rmse_mean > 3 * best.rmse_mean:
                parts.append(f"RMSE {r.rmse_mean / best.rmse_mean:.0f}× the best "
                             f"({best.name}); after the start-up its largest error is "
                             f"{r.largest_error}")
            if parts:
                out.append(f"{r.name}: " + "; ".join(parts))
                why = r.caveat or self.remarks.get(r.kind, "")
                if why:
                    explained.setdefault(why, []).append(r.name)
            out += r.notes()
        out += [f"{', '.join(names)}: {why}" for why, names in explained.items()]
        return out

    def table(self) -> str:
        """Plain-text table."""
        w = max([22] + [len(r.name) + 2 for r in self.rows])
        head = (f"{'estimator':<{w}}{'RMSE mean':>11}{'± std':>9}{'NEES/n':>9}{'cons.':>7}"
                f"{'step med':>11}{'step p90':>11}{'failed':>8}{'flagged':>9}")
        lines = [f"{self.scenario}: {len(self.seeds)} seed(s)", head, "-" * len(head)]
        for r in self.rows:
            cons = "-" if r.consistent is None else ("yes" if r.consistent else "no")
            lines.append(f"{r.name:<{w}}{r.rmse_mean:>11.4g}{r.rmse_std:>9.2g}"
                         f"{r.nees_mean:>9.3g}{cons:>7}{_fmt_time(r.step_median):>11}"
                         f"{_fmt_time(r.step_p90):>11}{r.failures:>8}{r.flagged:>9}")
        lines += [""] + textwrap.wrap(self.LEGEND, width=len(head))
        notes = self.notes()
        if notes:
            lines += ["", "Notes:"]
            for n in notes:
                lines += textwrap.wrap(n, width=len(head), initial_indent="  ",
                                       subsequent_indent="    ")
        if self.parallel:
            lines += [""] + textwrap.wrap(f"Runs: {self.parallel}", width=len(head))
        if self.batched:
            lines += [""] + textwrap.wrap(f"Batched: {self.batched}", width=len(head))
        return "\n".join(lines)

    def plot(self, path: str | os.PathLike[str] | None = None, *, kind: str = "overview",
             seed_index: int = 0) -> Figure:
        r"""Figures of the kept logs (needs ``compare(..., keep_logs=True)`` and matplotlib).

        Parameters
        ----------
        path : str or Path, optional
            Write the figure there (PNG by extension).
        kind : {"overview", "errors", "times"}
            ``"overview"``: truth and every estimator's estimate per state for
            one seed, and the RMSE of every seed as box plots
            (:func:`estim.plotting.plot_comparison`); ``"errors"``: the
            estimation error per state with the :math:`\pm 2\sigma` bands
            of the estimators that report a covariance
            (:func:`estim.plotting.plot_errors`); ``"times"``: the wall time of
            every step (:func:`estim.plotting.plot_solve_times`).
        seed_index : int
            Which seed to draw, as an index into :attr:`seeds`.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from estim import plotting

        kinds = ("overview", "errors", "times")
        if kind not in kinds:
            raise ValueError(f"kind must be one of {kinds}, got {kind!r}")
        seed_index = as_int(seed_index, "seed_index")
        if not self.logs:
            raise ValueError("Comparison.plot needs the logs: run compare(..., keep_logs=True)")
        if not -len(self.seeds) <= seed_index < len(self.seeds):
            raise ValueError(f"seed_index {seed_index} is out of range for "
                             f"{len(self.seeds)} seed(s)")
        if kind == "overview":
            return plotting.plot_comparison(self, path, seed_index=seed_index)
        logs = {name: logs[seed_index] for name, logs in self.logs.items()
                if logs[seed_index] is not None}
        if kind == "errors":
            return plotting.plot_errors(logs, path)
        return plotting.plot_solve_times(logs, path)

    def to_pandas(self) -> pd.DataFrame:
        """The rows as a DataFrame indexed by estimator (needs pandas)."""
        import pandas as pd

        return pd.DataFrame([r.__dict__ for r in self.rows]).set_index("name")

    def __str__(self) -> str:
        return self.table()

    def __repr__(self) -> str:
        return self.table()

    def _repr_html_(self) -> str:
        head = "".join(f"<th>{h}</th>" for h in ("estimator", "RMSE mean", "± std", "NEES/n",
                                                 "consistent", "step median", "step p90",
                                                 "failed", "flagged"))
        body = "".join(
            f"<tr><td>{html.escape(r.name)}</td><td>{r.rmse_mean:.4g}</td>"
            f"<td>{r.rmse_std:.2g}</td><td>{r.nees_mean:.3g}</td><td>{r.consistent}</td>"
            f"<td>{_fmt_time(r.step_median)}</td><td>{_fmt_time(r.step_p90)}</td>"
            f"<td>{r.failures}</td><td>{r.flagged}</td></tr>" for r in self.rows)
        notes = "".join(f"<li>{html.escape(n)}</li>" for n in self.notes())
        return (f"<p><b>{self.scenario}</b>: {len(self.seeds)} seed(s)</p>"
                f"<table><tr>{head}</tr>{body}</table>"
                f"<p><small>{html.escape(self.LEGEND)}</small></p>"
                + (f"<p><b>Notes</b></p><ul>{notes}</ul>" if notes else "")
                + (f"<p><small>Runs: {html.escape(self.parallel)}</small></p>"
                   if self.parallel else "")
                + (f"<p><small>Batched: {html.escape(self.batched)}</small></p>"
                   if self.batched else ""))


def _fmt_time(seconds: float) -> str:
    if not np.isfinite(seconds):
        return "-"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} µs"
    if seconds < 1:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def _make(spec, scenario: Scenario) -> Estimator:
    """An estimator from a class/factory ``(model, tuning)`` or a copy of an instance."""
    if isinstance(spec, Estimator):
        return copy.deepcopy(spec)
    if isinstance(spec, type) and issubclass(spec, Estimator):
        return spec(scenario.model, **scenario.tuning)
    return spec(scenario.model, dict(scenario.tuning))


def _error(exc: BaseException) -> str:
    """``"ExceptionType: first line of the message"`` (picklable, for the table)."""
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"[:300]


def _build(spec, scenario: Scenario) -> Estimator | str:
    """The estimator, or the error its construction raised (then every seed fails alike)."""
    try:
        return _make(spec, scenario)
    except Exception as exc:  # noqa: BLE001 - recorded for every seed
        return _error(exc)


def _run_seed(scenario: Scenario, est: Estimator | str, s: int, burn_in: int,
              keep_logs: bool) -> dict:
    """One run's summary (and log). A run that raises is recorded with its error."""
    if isinstance(est, str):
        return {"seed": s, "error": est, "log": None}
    try:
        log = simulate(scenario, est, seed=s, warn=False)
        r = rmse(log, burn_in=burn_in)
        has_p = bool(np.isfinite(log.P).any())
        ne = float(np.nanmean(nees(log, burn_in=burn_in))) / scenario.model.nx \
            if has_p else np.nan
    except Exception as exc:  # noqa: BLE001 - recorded, the other runs go on
        return {"seed": s, "error": _error(exc),
                "log": getattr(exc, "log", None) if keep_logs else None}
    return {
        "seed": s, "rmse": float(r), "per_state": list(r.per_state.values()), "nees": ne,
        "times": log.solve_time.copy(), "failures": log.failures, "flagged": log.flagged,
        "steps": len(log), "log": log if keep_logs else None,
        "peak": _peak(log, s), "kind": type(est).__name__, "caveat": est.caveat,
    }


#: Estimators built by a worker in the current call, by (call, name, thread): a worker
#: builds each estimator once per call, whatever the number of its chunks.
_BUILT: dict[tuple[str, str, int], Estimator | str] = {}
_BUILT_LOCK = threading.Lock()


def _run_chunk(scenario: Scenario, spec, seeds: list[int], burn_in: int, keep_logs: bool,
               key: tuple[str, str] | None = None):
    """Run one estimator over some seeds: ``(pid, start time, summaries per seed)``.

    With ``key = (call, name)`` the estimator is built once per process and thread
    for that call (and kept for the call's other chunks)."""
    start = time.time()
    if key is None:
        est = _build(spec, scenario)
    else:
        full = (*key, threading.get_ident())
        with _BUILT_LOCK:
            if any(k[0] != key[0] for k in _BUILT):  # a new call: drop the last one's
                _BUILT.clear()
            est = _BUILT.get(full)
        if est is None:
            est = _build(spec, scenario)
            with _BUILT_LOCK:
                _BUILT[full] = est
    return os.getpid(), start, [_run_seed(scenario, est, s, burn_in, keep_logs) for s in seeds]


def _run_batch(scenario: Scenario, est: Estimator, plant, burn_in: int, keep_logs: bool
               ) -> tuple[list[dict], float, str]:
    """Every seed's summary from the batched path (and the call's seconds and how it
    ran); the seeds it cannot take (a plant
    that left the finite numbers, a failed update) by :func:`_run_seed`."""
    from estim.batch import run_seeds

    runs, seconds, how = run_seeds(scenario, est, plant, burn_in, keep_logs)
    return [r if r is not None else _run_seed(scenario, est, s, burn_in, keep_logs)
            for s, r in zip(plant.seeds, runs, strict=True)], seconds, how


def _peak(log: Log, seed: int) -> tuple[float, str]:
    """The largest absolute estimation error of a run after the start-up transient (the
    first 10 % of the samples, as the error plots shade it), and where:
    ``"0.67 in C_C at t = 12.5 (seed 0)"``."""
    err = np.abs(log.x_hat - log.x)
    err[:startup_samples(len(err))] = np.nan
    if not np.isfinite(err).any():
        return float("nan"), ""
    k, j = np.unravel_index(int(np.nanargmax(err)), err.shape)
    return float(err[k, j]), peak_location(log.state_names[j], log.t[k], seed)


def _row(name: str, runs: list[dict], names: list[str]) -> ComparisonRow:
    """Summary of one estimator's runs (in seed order); failed runs only counted."""
    done = [r for r in runs if "error" not in r]
    errors = {r["seed"]: r["error"] for r in runs if "error" in r}
    nan = float("nan")
    if not done:
        return ComparisonRow(name=name, rmse_mean=nan, rmse_std=nan,
                             rmse_per_state=dict.fromkeys(names, nan), nees_mean=nan,
                             consistent=None, step_median=nan, step_p90=nan, failures=0,
                             runs=0, errors=errors)
    errs = np.array([r["rmse"] for r in done])
    ne = np.array([r["nees"] for r in done])
    consistent, se = None, float("nan")
    if np.isfinite(ne).all():
        se = float(np.std(ne, ddof=1) / np.sqrt(len(ne))) if len(ne) > 1 else np.inf
        consistent = bool(abs(np.mean(ne) - 1.0) <= 2 * se)
    size, where = max((r["peak"] for r in done), key=lambda p: -np.inf if p[0] != p[0] else p[0])
    uniform = {r.get("step") for r in done}
    if len(uniform) == 1 and None not in uniform:  # batched: one time per step for all
        median = p90 = float(uniform.pop())
    else:  # a batched run's steps each took its call's time per sample
        t = np.concatenate([r["times"] if r.get("step") is None else
                            np.full(r["steps"], r["step"]) for r in done])
        median, p90 = float(np.median(t)), float(np.percentile(t, 90))
    return ComparisonRow(
        name=name, rmse_mean=float(errs.mean()),
        rmse_std=float(errs.std(ddof=1)) if len(errs) > 1 else 0.0,
        rmse_per_state=dict(zip(names, np.mean([r["per_state"] for r in done], axis=0)
                                .tolist(), strict=True)),
        nees_mean=float(np.mean(ne)) if np.isfinite(ne).all() else nan,
        consistent=consistent, step_median=median, step_p90=p90,
        failures=sum(r["failures"] for r in done),
        runs=len(done), flagged=sum(r["flagged"] for r in done),
        steps=sum(r["steps"] for r in done), errors=errors, nees_se=se,
        largest_error=f"{size:.3g} {where}" if where else "", kind=done[0]["kind"],
        caveat=done[0]["caveat"])


def _plan(costs: Mapping[str, tuple[float, float, int]], workers: int
          ) -> list[tuple[str, int, int]]:
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
    tasks = []
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


def _makespan(tasks: list[tuple[str, int, int]], costs: Mapping[str, tuple[float, float, int]],
              workers: int) -> float:
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


def _startup(backend: str, workers: int) -> tuple[float, bool]:
    """Estimated seconds before the workers run (start-up), and whether they are warm."""
    rec = _POOLS.get((backend, workers), {})
    warm = bool(rec) and time.monotonic() - rec["end"] < _IDLE_TIMEOUT and (
        backend != "loky" or _loky_alive())
    if warm:
        return max(rec.get("warm", _WARM_START), _WARM_START), True
    cold = rec.get("cold", _COLD_START.get(backend, _COLD_START_DEFAULT))
    return max(cold, _WARM_START if backend != "threading" else 0.0), False


def _fmt_s(seconds: float) -> str:
    return f"{seconds:.2g} s" if seconds < 10 else f"{seconds:.0f} s"


@check_keywords
def compare(scenario: Scenario, estimators: Mapping[str, Factory | type | Estimator],
            seeds: Iterable[int] = range(5), *, n_jobs: int = 1, backend: str = "loky",
            keep_logs: bool = False, burn_in: int = 0, progress: bool | None = None,
            min_parallel_seconds: float | None = None, batch: bool | None = None
            ) -> Comparison:
    """Run every estimator on the scenario for every seed (same noise per seed).

    Parameters
    ----------
    scenario : Scenario
    estimators : dict
        Name to an estimator class, a factory ``(model, tuning) -> estimator``,
        or a ready instance (copied for every worker).
    seeds : iterable of int
        Noise seeds; seed ``s`` gives the same noise to every estimator.
    n_jobs : int
        Parallel jobs through joblib (``-1``: all cores). 1 runs in this process.
    backend : str
        ``"loky"`` (processes, default), ``"threading"`` or any other joblib
        backend (``"ray"`` after ``ray.util.joblib.register_ray()``);
        ``"dask"`` submits the runs to the active ``dask.distributed`` client
        (create one first: ``Client()`` for a local cluster or
        ``Client("tcp://scheduler:8786")``).
    keep_logs : bool
        Keep every :class:`~estim.Log` in ``result.logs``.
    burn_in : int
        Samples skipped by RMSE and NEES.
    progress : bool, optional
        Show a tqdm progress bar (default: when stderr is a terminal and there
        are more than 20 runs).
    min_parallel_seconds : float, optional
        With ``n_jobs != 1``: the first two runs of every estimator are done in
        this process and timed, giving each estimator's cost (build and first
        run's extra, then seconds per run). By default the other runs go to the
        workers only when the estimated parallel time (the workers' start-up,
        measured on the last cold start in this process, about 2 s before any,
        or about 0.1 s when they are still up from a call with the same backend
        and ``n_jobs``, plus the busiest worker's share) is at most 80 % of the
        estimated serial time; otherwise they run here. A number: in parallel
        when the estimated serial time of the other runs is at least that many
        seconds (``0``: always). :attr:`Comparison.parallel` says what was done
        and why. The numbers are the same either way.
    batch : bool, optional
        Run the filters that support it (:class:`~estim.EKF`, :class:`~estim.UKF`)
        over all seeds at once (see :mod:`estim.batch`): the plant of every seed
        in one compiled call, then each such filter over every record in one
        compiled call, on the machine's cores. The numbers are those of the
        per-run path (a seed whose filter meets a failed update is run per run);
        their ``step`` time is that call's time per sample. By default (None)
        whenever the scenario's inputs are known in advance (no controller);
        ``False``: never; ``True``: a ValueError if the scenario cannot be batched.
        :attr:`Comparison.batched` says what was batched.

    Returns
    -------
    Comparison
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be an estim.Scenario, got {type(scenario).__name__}")
    seeds, n_jobs, burn_in, keep_logs, progress = _check_compare(
        scenario, estimators, seeds, n_jobs, backend, keep_logs, burn_in, progress)
    if min_parallel_seconds is not None:
        min_parallel_seconds = as_float(min_parallel_seconds, "min_parallel_seconds",
                                        minimum=0.0)
    batch = as_bool(batch, "batch", allow_none=True)
    if batch is not False:
        from estim import batch as batching  # numpy/CasADi batches, loaded when used

        why = batching.unsupported(scenario)
        if why and batch:
            raise ValueError(f"batch=True: the runs of {scenario.name} cannot be batched: "
                             f"{why}")
        batch = not why
    workers = (os.cpu_count() or 1) if n_jobs < 0 else int(n_jobs)
    total = len(estimators) * len(seeds)
    show = progress if progress is not None else (total > 20 and sys.stderr.isatty())
    bar = _bar(total, show)
    per_name: dict[str, list[dict]] = {name: [] for name in estimators}
    # this process: every run with n_jobs=1; else the first two runs of every estimator,
    # timed (build + first run, then a run), to decide whether workers pay
    built, costs = {}, {}
    pilot = seeds if n_jobs == 1 else seeds[:2]
    plant, batched = None, []
    for name, spec in estimators.items():
        t0 = time.perf_counter()
        built[name] = _build(spec, scenario)
        build = time.perf_counter() - t0
        if batch and hasattr(built[name], "_batchable") and built[name]._batchable():
            plant = plant or batching.simulate_plant(scenario, seeds)
            per_name[name], seconds, how = _run_batch(scenario, built[name], plant,
                                                      burn_in, keep_logs)
            batched.append(f"{name} ({_fmt_s(seconds)}, {how})")
            costs[name] = (0.0, 0.0, 0)
            bar.update(len(seeds))
            continue
        times = []
        for s in pilot:
            t1 = time.perf_counter()
            per_name[name].append(_run_seed(scenario, built[name], s, burn_in, keep_logs))
            times.append(time.perf_counter() - t1)
            bar.update(1)
        setup = build + (times[0] - times[-1] if len(times) > 1 else 0.0)
        costs[name] = (max(setup, 0.0), times[-1], len(seeds) - len(pilot))
    rest = seeds[len(pilot):] if any(n for _, _, n in costs.values()) else []
    note = ""
    if rest:
        serial_s = sum(per * n for _, per, n in costs.values())
        tasks = _plan(costs, workers)
        startup, warm = _startup(backend, workers)
        par_s = startup + _makespan(tasks, costs, workers)
        estimate = (f"{len(rest) * len(estimators)} runs estimated at {_fmt_s(serial_s)} "
                    f"in this process, {_fmt_s(par_s)} on {workers} workers (starting "
                    f"{'warm' if warm else 'cold'} workers: about {_fmt_s(startup)})")
        if min_parallel_seconds is None:
            go = par_s <= 0.8 * serial_s
        else:
            go = serial_s >= min_parallel_seconds
        if not go:
            note = f"serial: {estimate}"
            for name in estimators:
                if not costs[name][2]:
                    continue
                for s in rest:
                    per_name[name].append(_run_seed(scenario, built[name], s, burn_in,
                                                    keep_logs))
                    bar.update(1)
    bar.close()
    if rest and go:
        del built
        call = f"{os.getpid()}-{time.time_ns()}"
        args = [(scenario, estimators[name], rest[a:b], burn_in, keep_logs, (call, name))
                for name, a, b in tasks]
        t0 = time.time()
        if backend == "dask":
            # straight to the active dask.distributed client (a local or remote cluster)
            from dask.distributed import get_client

            client = get_client()
            results = client.gather([client.submit(_run_chunk, *a, pure=False) for a in args])
        else:
            import joblib.parallel as jp
            from joblib import Parallel, delayed

            if backend not in jp.BACKENDS and backend in getattr(jp, "EXTERNAL_BACKENDS", {}):
                jp.EXTERNAL_BACKENDS[backend]()  # joblib registers dask/ray lazily
            results = Parallel(n_jobs=n_jobs, backend=backend, verbose=0, batch_size=1)(
                delayed(_run_chunk)(*a) for a in args)
        wall = time.time() - t0
        with _BUILT_LOCK:
            _BUILT.clear()  # this process's (threading backend)
        first: dict[int, float] = {}
        for (name, _, _), (pid, start, res) in zip(tasks, results, strict=True):
            per_name[name].extend(res)
            first[pid] = min(first.get(pid, np.inf), start - t0)
        rec = _POOLS.setdefault((backend, workers), {})
        rec["warm" if warm else "cold"] = max(float(np.mean(list(first.values()))), 0.0)
        rec["end"] = time.monotonic()
        how = "forced, " if min_parallel_seconds is not None else ""
        note = (f"parallel ({how}{len(tasks)} chunks): {estimate}; took {_fmt_s(wall)}, "
                f"the workers started in {_fmt_s(rec['warm' if warm else 'cold'])}")
    elif n_jobs != 1 and not rest and len(batched) < len(estimators):
        note = "serial: every run was one of the first runs, timed in this process"
    batch_note = ""
    if batched:
        threads = seed_threads(len(seeds))
        batch_note = (f"{', '.join(batched)}: the {len(seeds)} runs of each filtered at once "
                      f"(whole records over all seeds, on {threads} thread(s)), "
                      f"after the plant of every seed ({_fmt_s(plant.seconds)}, {plant.how}); "
                      f"their step time is that call's time per sample")
    rows, all_rmse, logs = [], {}, {}
    names = scenario.model.state_names
    order = {s: i for i, s in enumerate(seeds)}
    for name, runs in per_name.items():
        runs.sort(key=lambda r: order[r["seed"]])
        rows.append(_row(name, runs, names))
        all_rmse[name] = np.array([r.get("rmse", np.nan) for r in runs])
        if keep_logs:
            logs[name] = [r["log"] for r in runs]
    return Comparison(scenario.name, seeds, rows, all_rmse, logs, remarks=scenario.remarks,
                      parallel=note, batched=batch_note)


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _bar(total: int, show: bool):
    if not show:
        return _NoBar()
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover - optional extra
        return _NoBar()
    return tqdm(total=total, unit="run", leave=False)


def _check_compare(scenario: Scenario, estimators, seeds, n_jobs, backend, keep_logs, burn_in,
                   progress):
    """Check the arguments of :func:`compare` before any run."""
    if not isinstance(estimators, Mapping):
        raise TypeError(f"estimators must be a dict {{label: class, factory or estimator}}, "
                        f"got {type(estimators).__name__}")
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    for name, spec in estimators.items():
        if not isinstance(name, str):
            raise TypeError(f"estimators labels must be strings, got {name!r}")
        if not (callable(spec) or isinstance(spec, Estimator)):
            raise TypeError(f"estimators[{name!r}] must be a class, a factory or an estimator")
        if isinstance(spec, type) and not issubclass(spec, Estimator):
            raise TypeError(f"estimators[{name!r}] must be an estimator class, a factory or "
                            f"an estimator, got the class {spec.__name__}")
        if isinstance(spec, Estimator) and (spec.model.nx, spec.model.ny, spec.model.nu) != (
                scenario.model.nx, scenario.model.ny, scenario.model.nu):
            raise ValueError(f"estimators[{name!r}] was built for a model of other dimensions "
                             f"than the scenario's")
    if isinstance(seeds, str | bytes) or not hasattr(seeds, "__iter__"):
        raise TypeError(f"seeds must be an iterable of seeds (e.g. range(5)), "
                        f"got {type(seeds).__name__}")
    seeds = [as_int(s, f"seeds[{i}]", minimum=0) for i, s in enumerate(seeds)]
    if not seeds:
        raise ValueError("seeds must contain at least one seed")
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must not repeat a seed, got {seeds}")
    n_jobs = as_int(n_jobs, "n_jobs", expected="a non-zero integer (-1: all cores)")
    if n_jobs == 0:
        raise ValueError("n_jobs must be a non-zero integer (-1: all cores), got 0")
    if not isinstance(backend, str):
        raise TypeError(f"backend must be a string (a joblib backend or 'dask'), "
                        f"got {type(backend).__name__}")
    keep_logs = as_bool(keep_logs, "keep_logs")
    progress = as_bool(progress, "progress", allow_none=True)
    burn_in = as_int(burn_in, "burn_in", minimum=0)
    if burn_in >= scenario.n_steps:
        raise ValueError(f"burn_in ({burn_in}) must be shorter than the scenario "
                         f"({scenario.n_steps} steps)")
    if n_jobs != 1:
        if backend == "dask":
            if importlib.util.find_spec("dask") is None or \
                    importlib.util.find_spec("dask.distributed") is None:
                raise ImportError('backend="dask" needs dask.distributed: '
                                  'pip install "estim[dask]"')
        elif importlib.util.find_spec("joblib") is None:
            raise ImportError(f"n_jobs={n_jobs} runs in parallel through joblib: "
                              "pip install joblib (a dependency of estim)")
    return seeds, n_jobs, burn_in, keep_logs, progress
