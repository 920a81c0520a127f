r"""The runs of :func:`~estim.compare`: one estimator on one seed, and their summary.

:func:`build` makes the estimator of a specification (a class, a factory or an
instance to copy), :func:`run_seed` runs it on a seed through
:func:`~estim.simulate` and keeps what the table needs (RMSE, NEES, step times,
failed and flagged steps, the largest error after the start-up), :func:`run_batch`
does the same for every seed at once through :mod:`estim.batch`, and
:func:`summary` reduces an estimator's runs to the statistics of its row in the
table. A run that raises is recorded with its error, so the other runs go on; the
summaries are plain picklable values, as the workers send them back.
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from estim.estimators.base import Estimator, seeded
from estim.log import Log
from estim.metrics import nees, peak_location, rmse, startup_samples
from estim.model import Model
from estim.scenarios import Scenario
from estim.simulate import simulate
from estim.verdicts import consistency, seed_scores

if TYPE_CHECKING:
    from estim.batch import PlantBatch
    from estim.estimators.kalman.fused import FusedKalman

#: A factory ``(model, tuning) -> estimator``.
Factory = Callable[[Model, dict], Estimator]
#: What names an estimator in :func:`~estim.compare`: a class, a factory or an instance.
Spec = Factory | type[Estimator] | Estimator
#: One run's summary: ``seed`` and either ``error`` (``"ExceptionType: message"``) or
#: ``rmse``, ``per_state``, ``nees`` (the time-averaged NEES/n), ``level``, ``batches``
#: and ``diverged`` (the consistency scores of :func:`estim.verdicts.seed_scores`),
#: ``times`` (or ``step``, one time for every step of a batched run), ``failures``,
#: ``flagged``, ``steps``, ``peak``, ``kind`` and ``caveat``; ``log`` with ``keep_logs``,
#: else None.
Run = dict[str, Any]


def _make(spec: Spec, scenario: Scenario) -> Estimator:
    """An estimator from a class/factory ``(model, tuning)`` or a copy of an instance."""
    if isinstance(spec, Estimator):
        return copy.deepcopy(spec)
    if isinstance(spec, type):  # an estimator class: compare refuses any other class
        return spec(scenario.model, **scenario.tuning)
    est = spec(scenario.model, dict(scenario.tuning))
    if not isinstance(est, Estimator):
        raise TypeError(f"the factory {getattr(spec, '__name__', repr(spec))} returned "
                        f"{type(est).__name__}, not an estimator: a factory is "
                        f"(model, tuning) -> estimator (did it forget to return it?)")
    return est


def _error(exc: BaseException) -> str:
    """``"ExceptionType: first line of the message"`` (picklable, for the table)."""
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0] if lines else ''}"[:300]


def build(spec: Spec, scenario: Scenario) -> Estimator | str:
    """The estimator, or the error its construction raised (then every seed fails alike)."""
    try:
        return _make(spec, scenario)
    except Exception as exc:  # noqa: BLE001 - recorded for every seed
        return _error(exc)


def run_stream(base: int, s: int) -> int:
    """The seed of a randomised estimator's run on the scenario's seed ``s``: its own
    ``base`` and ``s`` mixed by ``numpy.random.SeedSequence``, so that the runs over seeds
    draw independent streams (the same ones at every call)."""
    return int(np.random.SeedSequence([int(base), int(s)]).generate_state(1)[0])


def run_seed(scenario: Scenario, est: Estimator | str, s: int, burn_in: int,
             keep_logs: bool) -> Run:
    """One run's summary (and log) of ``est`` on seed ``s``, or ``est`` itself when it
    is the error its construction raised. A run that raises is recorded with its error."""
    if isinstance(est, str):
        return {"seed": s, "error": est, "log": None}
    try:
        def run() -> Log:
            return simulate(scenario, est, seed=s, warn=False)

        if est._randomised:  # a particle filter, an EnKF: its own stream on this seed
            base = est.seed  # type: ignore[attr-defined]
            log = seeded(est, run_stream(base, s), run)
        else:
            log = run()
        r = rmse(log, burn_in=burn_in)
        has_p = bool(np.isfinite(log.P).any())
        scores = seed_scores(nees(log, burn_in=burn_in), log.P.shape[1]) if has_p else \
            seed_scores(np.array([]), 1)
    except Exception as exc:  # noqa: BLE001 - recorded, the other runs go on
        return {"seed": s, "error": _error(exc),
                "log": getattr(exc, "log", None) if keep_logs else None}
    return {
        "seed": s, "rmse": float(r), "per_state": list(r.per_state.values()),
        "nees": scores["ratio"], "level": scores["level"], "batches": scores["batches"],
        "diverged": scores["diverged"],
        "times": log.solve_time.copy(), "failures": log.failures, "flagged": log.flagged,
        "steps": len(log), "log": log if keep_logs else None,
        "peak": _peak(log, s), "kind": type(est).__name__, "caveat": est.caveat,
    }


def run_batch(scenario: Scenario, filters: dict[str, FusedKalman], seeds: list[int],
              burn_in: int, keep_logs: bool
              ) -> tuple[PlantBatch, dict[str, tuple[list[Run], float, str]]]:
    """Every seed's summary of each filter from the batched path
    (:func:`estim.batch.run_batches`: the plant and every filter over all seeds, with
    the plant's batch, each filter's seconds and how it ran); the seeds it cannot take
    (a plant that left the finite numbers, a failed update) by :func:`run_seed`."""
    from estim.batch import run_batches

    plant, batched = run_batches(scenario, filters, seeds, burn_in, keep_logs)
    return plant, {name: ([r if r is not None else run_seed(scenario, filters[name], s,
                                                            burn_in, keep_logs)
                           for s, r in zip(seeds, runs, strict=True)], seconds, how)
                   for name, (runs, seconds, how) in batched.items()}


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


def summary(runs: list[Run], names: list[str]) -> dict[str, Any]:
    """One estimator's runs (in seed order) summarised: the fields of its
    :class:`~estim.compare.ComparisonRow` but the name. The runs that raised are only
    counted (``errors``); the statistics are over the others.

    Parameters
    ----------
    runs : list of dict
        The runs' summaries (:data:`Run`), in seed order.
    names : list of str
        The state names (the keys of ``rmse_per_state``).
    """
    done = [r for r in runs if "error" not in r]
    errors = {r["seed"]: r["error"] for r in runs if "error" in r}
    nan = float("nan")
    if not done:
        return {"rmse_mean": nan, "rmse_std": nan, "rmse_per_state": dict.fromkeys(names, nan),
                "nees_mean": nan, "consistent": None, "step_median": nan, "step_p90": nan,
                "failures": 0, "runs": 0, "errors": errors}
    errs = np.array([r["rmse"] for r in done])
    ne = np.array([r["nees"] for r in done])
    verdict, se = None, float("nan")
    if np.isfinite(ne).all():
        se = float(np.std(ne, ddof=1) / np.sqrt(len(ne))) if len(ne) > 1 else np.inf
        verdict = consistency(ne, [r["level"] for r in done], [r["diverged"] for r in done],
                              [r["seed"] for r in done], batches=done[0]["batches"])
    size, where = max((r["peak"] for r in done), key=lambda p: -np.inf if p[0] != p[0] else p[0])
    uniform = {r.get("step") for r in done}
    step = next(iter(uniform))
    if len(uniform) == 1 and step is not None:  # batched: one time per step for all
        median = p90 = float(step)
    else:  # a batched run's steps each took its call's time per sample
        t = np.concatenate([r["times"] if r.get("step") is None else
                            np.full(r["steps"], r["step"]) for r in done])
        median, p90 = float(np.median(t)), float(np.percentile(t, 90))
    return {
        "rmse_mean": float(errs.mean()),
        "rmse_std": float(errs.std(ddof=1)) if len(errs) > 1 else 0.0,
        "rmse_per_state": dict(zip(names, np.mean([r["per_state"] for r in done], axis=0)
                                   .tolist(), strict=True)),
        "nees_mean": float(np.mean(ne)) if np.isfinite(ne).all() else nan,
        "consistent": None if verdict is None else verdict.consistent,
        "consistency": verdict, "step_median": median, "step_p90": p90,
        "failures": sum(r["failures"] for r in done),
        "runs": len(done), "flagged": sum(r["flagged"] for r in done),
        "steps": sum(r["steps"] for r in done), "errors": errors, "nees_se": se,
        "largest_error": f"{size:.3g} {where}" if where else "", "kind": done[0]["kind"],
        "caveat": done[0]["caveat"]}
