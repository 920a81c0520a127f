"""Seeded Monte Carlo comparison of several estimators on one scenario."""

from __future__ import annotations

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
    """Summary of one estimator over all seeds (RMSE over all states)."""

    name: str
    rmse_mean: float
    rmse_std: float
    rmse_per_state: dict[str, float]
    nees_mean: float
    step_median: float
    step_p90: float
    failures: int
    runs: int


@dataclass
class Comparison:
    """Result of :func:`compare`: one row per estimator, plus the logs if kept."""

    scenario: str
    seeds: list[int]
    rows: list[ComparisonRow]
    rmse: dict[str, np.ndarray]
    logs: dict[str, list[Log]] = field(default_factory=dict)

    def table(self) -> str:
        """Plain-text table."""
        head = (f"{'estimator':<22}{'RMSE mean':>11}{'± std':>9}{'NEES':>10}"
                f"{'step med':>11}{'step p90':>11}{'failed':>8}")
        lines = [f"{self.scenario}: {len(self.seeds)} seed(s)", head, "-" * len(head)]
        for r in self.rows:
            lines.append(f"{r.name:<22}{r.rmse_mean:>11.4g}{r.rmse_std:>9.2g}"
                         f"{r.nees_mean:>10.3g}{_fmt_time(r.step_median):>11}"
                         f"{_fmt_time(r.step_p90):>11}{r.failures:>8}")
        return "\n".join(lines)

    def to_pandas(self):
        """The rows as a DataFrame indexed by estimator (needs pandas)."""
        import pandas as pd

        return pd.DataFrame([r.__dict__ for r in self.rows]).set_index("name")

    def __str__(self) -> str:
        return self.table()


def _fmt_time(seconds: float) -> str:
    if not np.isfinite(seconds):
        return "-"
    if seconds < 1e-3:
        return f"{seconds * 1e6:.1f} µs"
    if seconds < 1:
        return f"{seconds * 1e3:.2f} ms"
    return f"{seconds:.2f} s"


def compare(scenario: Scenario, estimators: Mapping[str, Factory | type],
            seeds: Iterable[int] = range(5), keep_logs: bool = False,
            burn_in: int = 0) -> Comparison:
    """Run every estimator on the scenario for every seed (same noise per seed).

    Parameters
    ----------
    scenario : Scenario
    estimators : dict
        Name to an estimator class or a factory ``(model, tuning) -> estimator``.
    seeds : iterable of int
        Noise seeds; seed ``s`` gives the same noise to every estimator.
    keep_logs : bool
        Keep every :class:`~estim.Log` in ``result.logs``.
    burn_in : int
        Samples skipped by the RMSE.

    Returns
    -------
    Comparison
    """
    if not isinstance(scenario, Scenario):
        raise TypeError(f"scenario must be an estim.Scenario, got {type(scenario).__name__}")
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("seeds must contain at least one seed")
    rows, all_rmse, logs = [], {}, {}
    for name, factory in estimators.items():
        if not callable(factory):
            raise TypeError(f"estimators[{name!r}] must be a class or a factory")
        est = factory(scenario.model, dict(scenario.tuning))
        errs, per_state, nees_means, times, failures = [], [], [], [], 0
        kept = []
        for s in seeds:
            log = simulate(scenario, est, seed=s)
            r = rmse(log, burn_in=burn_in)
            errs.append(float(r))
            per_state.append(list(r.per_state.values()))
            nees_means.append(float(np.nanmean(nees(log))) if np.isfinite(log.P).any()
                              else np.nan)
            times.append(log.solve_time)
            failures += int(np.count_nonzero(~log.success))
            if keep_logs:
                kept.append(log)
        t = np.concatenate(times)
        names = scenario.model.state_names
        rows.append(ComparisonRow(
            name=name, rmse_mean=float(np.mean(errs)),
            rmse_std=float(np.std(errs, ddof=1)) if len(errs) > 1 else 0.0,
            rmse_per_state=dict(zip(names, np.mean(per_state, axis=0).tolist(), strict=True)),
            nees_mean=float(np.nanmean(nees_means)) if np.isfinite(nees_means).any()
            else float("nan"),
            step_median=float(np.median(t)), step_p90=float(np.percentile(t, 90)),
            failures=failures, runs=len(seeds)))
        all_rmse[name] = np.array(errs)
        if keep_logs:
            logs[name] = kept
    return Comparison(scenario.name, seeds, rows, all_rmse, logs)
