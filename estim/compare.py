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
"""

from __future__ import annotations

import copy
import os
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from estim.estimators.base import Estimator
from estim.log import Log
from estim.metrics import nees, rmse
from estim.model import Model
from estim.scenarios import Scenario
from estim.simulate import simulate

Factory = Callable[[Model, dict], Estimator]


@dataclass
class ComparisonRow:
    """Summary of one estimator over all seeds.

    ``rmse_mean``/``rmse_std``: RMSE over all states, mean and standard
    deviation over seeds; ``rmse_per_state``: mean per state. ``nees_mean``:
    time-averaged NEES divided by ``nx`` (1 for a consistent filter), mean over
    seeds; ``consistent``: within two standard errors (over seeds) of 1
    (None without covariance). ``step_median``/``step_p90``: seconds per step.
    ``failures``: steps whose status was not ``"ok"``.
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
        RMSE of every run, per estimator, in seed order.
    logs : dict of str -> list of Log
        Every run's log (with ``keep_logs=True``).
    """

    scenario: str
    seeds: list[int]
    rows: list[ComparisonRow]
    rmse: dict[str, np.ndarray]
    logs: dict[str, list[Log]] = field(default_factory=dict)

    def table(self) -> str:
        """Plain-text table."""
        w = max([22] + [len(r.name) + 2 for r in self.rows])
        head = (f"{'estimator':<{w}}{'RMSE mean':>11}{'± std':>9}{'NEES/n':>9}{'cons.':>7}"
                f"{'step med':>11}{'step p90':>11}{'failed':>8}")
        lines = [f"{self.scenario}: {len(self.seeds)} seed(s)", head, "-" * len(head)]
        for r in self.rows:
            cons = "-" if r.consistent is None else ("yes" if r.consistent else "no")
            lines.append(f"{r.name:<{w}}{r.rmse_mean:>11.4g}{r.rmse_std:>9.2g}"
                         f"{r.nees_mean:>9.3g}{cons:>7}{_fmt_time(r.step_median):>11}"
                         f"{_fmt_time(r.step_p90):>11}{r.failures:>8}")
        return "\n".join(lines)

    def to_pandas(self):
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
                                                 "failed"))
        body = "".join(
            f"<tr><td>{r.name}</td><td>{r.rmse_mean:.4g}</td><td>{r.rmse_std:.2g}</td>"
            f"<td>{r.nees_mean:.3g}</td><td>{r.consistent}</td>"
            f"<td>{_fmt_time(r.step_median)}</td><td>{_fmt_time(r.step_p90)}</td>"
            f"<td>{r.failures}</td></tr>" for r in self.rows)
        return (f"<p><b>{self.scenario}</b>: {len(self.seeds)} seed(s)</p>"
                f"<table><tr>{head}</tr>{body}</table>")


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


def _run_chunk(scenario: Scenario, spec, seeds: list[int], burn_in: int, keep_logs: bool):
    """Run one estimator over some seeds; summaries (and logs) per seed."""
    est = _make(spec, scenario)
    out = []
    for s in seeds:
        log = simulate(scenario, est, seed=s)
        r = rmse(log, burn_in=burn_in)
        has_p = bool(np.isfinite(log.P).any())
        out.append({
            "seed": s, "rmse": float(r), "per_state": list(r.per_state.values()),
            "nees": float(np.nanmean(nees(log, burn_in=burn_in))) / scenario.model.nx
            if has_p else np.nan,
            "times": log.solve_time.copy(),
            "failures": int(np.count_nonzero(log.status != "ok")),
            "log": log if keep_logs else None,
        })
    return out


def _chunks(seeds: list[int], n: int) -> list[list[int]]:
    n = max(1, min(n, len(seeds)))
    return [list(c) for c in np.array_split(np.asarray(seeds), n) if len(c)]


def compare(scenario: Scenario, estimators: Mapping[str, Factory | type | Estimator],
            seeds: Iterable[int] = range(5), *, n_jobs: int = 1, backend: str = "loky",
            keep_logs: bool = False, burn_in: int = 0, progress: bool | None = None
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

    Returns
    -------
    Comparison
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be an estim.Scenario, got {type(scenario).__name__}")
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    for name, spec in estimators.items():
        if not (callable(spec) or isinstance(spec, Estimator)):
            raise TypeError(f"estimators[{name!r}] must be a class, a factory or an estimator")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("seeds must contain at least one seed")
    if not isinstance(n_jobs, int | np.integer) or n_jobs == 0:
        raise ValueError(f"n_jobs must be a non-zero integer, got {n_jobs!r}")
    workers = (os.cpu_count() or 1) if n_jobs < 0 else int(n_jobs)
    tasks = [(name, chunk) for name in estimators
             for chunk in (_chunks(seeds, 2 * workers) if workers > 1 else [seeds])]
    total = len(estimators) * len(seeds)
    show = progress if progress is not None else (total > 20 and sys.stderr.isatty())
    if n_jobs == 1:
        results = []
        bar = _bar(total, show)
        for name, chunk in tasks:
            results.append(_run_chunk(scenario, estimators[name], chunk, burn_in, keep_logs))
            bar.update(len(chunk))
        bar.close()
    elif backend == "dask":
        # straight to the active dask.distributed client (a local or remote cluster)
        from dask.distributed import get_client

        client = get_client()
        futures = [client.submit(_run_chunk, scenario, estimators[name], chunk, burn_in,
                                 keep_logs, pure=False) for name, chunk in tasks]
        results = client.gather(futures)
    else:
        import joblib.parallel as jp
        from joblib import Parallel, delayed

        if backend not in jp.BACKENDS and backend in getattr(jp, "EXTERNAL_BACKENDS", {}):
            jp.EXTERNAL_BACKENDS[backend]()  # joblib registers dask/ray lazily
        results = Parallel(n_jobs=n_jobs, backend=backend, verbose=0)(
            delayed(_run_chunk)(scenario, estimators[name], chunk, burn_in, keep_logs)
            for name, chunk in tasks)
    per_name: dict[str, list[dict]] = {name: [] for name in estimators}
    for (name, _), res in zip(tasks, results, strict=True):
        per_name[name].extend(res)
    rows, all_rmse, logs = [], {}, {}
    names = scenario.model.state_names
    for name, runs in per_name.items():
        runs.sort(key=lambda r: seeds.index(r["seed"]))
        errs = np.array([r["rmse"] for r in runs])
        ne = np.array([r["nees"] for r in runs])
        consistent = None
        if np.isfinite(ne).all():
            se = np.std(ne, ddof=1) / np.sqrt(len(ne)) if len(ne) > 1 else np.inf
            consistent = bool(abs(np.mean(ne) - 1.0) <= 2 * se)
        t = np.concatenate([r["times"] for r in runs])
        rows.append(ComparisonRow(
            name=name, rmse_mean=float(errs.mean()),
            rmse_std=float(errs.std(ddof=1)) if len(errs) > 1 else 0.0,
            rmse_per_state=dict(zip(names, np.mean([r["per_state"] for r in runs], axis=0)
                                    .tolist(), strict=True)),
            nees_mean=float(np.mean(ne)) if np.isfinite(ne).all() else float("nan"),
            consistent=consistent, step_median=float(np.median(t)),
            step_p90=float(np.percentile(t, 90)), failures=sum(r["failures"] for r in runs),
            runs=len(runs)))
        all_rmse[name] = errs
        if keep_logs:
            logs[name] = [r["log"] for r in runs]
    return Comparison(scenario.name, seeds, rows, all_rmse, logs)


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
