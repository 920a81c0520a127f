r"""Assertions for comparing estimators in tests: statistical tests with stated error rates.

Each assertion raises an ``AssertionError`` whose message gives the statistic, its
interval and what contributed most, and returns the statistic when it passes:

:func:`assert_better`
    a one-sided paired test over seeds that ``a``'s metric is below ``b``'s. Seed
    :math:`s` gives both estimators the same noise, so the differences
    :math:`d_s = m_b(s) - m_a(s)` are independent over seeds; the test passes when the
    lower confidence bound :math:`\bar d - t_{c, S-1}\, s_d / \sqrt S` exceeds
    ``margin`` times the mean of ``b``'s metric (Student's t; its false-alarm rate is
    ``1 - confidence`` when the expected metrics are equal, for differences close to
    normal: measured in ``tests/test_testing.py``).
:func:`assert_equivalent`
    two one-sided tests (TOST, Schuirmann 1987): the :math:`1 - 2\alpha` confidence
    interval of :math:`\bar d` inside :math:`\pm` ``tolerance`` times the mean of
    ``b``'s metric.
:func:`assert_consistent`
    NEES (per state dimension) against its expectation 1: over seeds, the mean of
    the seeds' time-averaged NEES inside the ``level`` t-interval of 1 (independent
    seeds; the correlation over time does not matter); on one log, the same over 10
    batches of its steps (batch means). NIS, where recorded, likewise per output
    measured.
:func:`assert_close`
    two estimators on one record: estimates and covariances equal to tolerances.

``comparison`` is an :class:`~estim.Comparison` (its per-seed ``rmse`` and ``nees``) or
a mapping ``{label: per-seed values}``.

References
----------
D. J. Schuirmann, "A comparison of the two one-sided tests procedure and the power
approach for assessing the equivalence of average bioavailability", J.
Pharmacokinet. Biopharm. 15(6), 1987; Y. Bar-Shalom, X. R. Li, T. Kirubarajan,
*Estimation with Applications to Tracking and Navigation*, Wiley 2001, sec. 5.4.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import stats

from estim._validate import as_float, did_you_mean
from estim._version import __version__
from estim.compare import Comparison
from estim.estimators.base import Estimator
from estim.experiment import Record
from estim.log import Log
from estim.metrics import nees as nees_of
from estim.metrics import startup_samples
from estim.simulate import replay

__all__ = ["METRICS", "assert_better", "assert_close", "assert_consistent",
           "assert_equivalent", "assert_no_regression", "load_baseline", "save_baseline"]

#: The per-seed metrics a comparison holds.
METRICS = ("rmse", "nees")
#: Batches of one log's steps for :func:`assert_consistent` (batch means).
BATCHES = 10


def _values(comparison: Comparison | Mapping[str, ArrayLike], label: str, metric: str,
            argname: str) -> np.ndarray:
    """The per-seed values of ``metric`` of estimator ``label``."""
    if not isinstance(metric, str) or metric not in METRICS:
        raise ValueError(f"metric must be one of {', '.join(map(repr, METRICS))}, got "
                         f"{metric!r}{did_you_mean(str(metric), list(METRICS))}")
    table: Mapping[str, ArrayLike]
    if isinstance(comparison, Comparison):
        table = comparison.rmse if metric == "rmse" else comparison.nees
    elif isinstance(comparison, Mapping):
        table = comparison
    else:
        raise TypeError(f"comparison must be an estim.Comparison or a dict {{label: per-seed "
                        f"values}}, got {type(comparison).__name__}")
    if label not in table:
        raise ValueError(f"{argname}: {label!r} is not in the comparison; its estimators are "
                         f"{list(table)}{did_you_mean(str(label), list(table))}")
    values = np.asarray(table[label], dtype=float).ravel()
    # NEES per dimension: its distance from consistency, lower being better
    return np.abs(values - 1.0) if metric == "nees" else values


def _level(value: Any, name: str) -> float:
    level = as_float(value, name, expected="a probability in (0, 1)")
    if not 0.0 < level < 1.0:
        raise ValueError(f"{name} must be in (0, 1), got {value!r}")
    return level


def _paired(comparison, a: str, b: str, metric: str) -> tuple[np.ndarray, float]:
    """The differences ``m_b - m_a`` over the seeds both completed, and b's mean."""
    va, vb = _values(comparison, a, metric, "a"), _values(comparison, b, metric, "b")
    if va.shape != vb.shape:
        raise ValueError(f"a and b must have a value per seed each, got {va.size} and "
                         f"{vb.size}")
    ok = np.isfinite(va) & np.isfinite(vb)
    if ok.sum() < 2:
        raise ValueError(f"a paired test needs at least 2 seeds where both {a!r} and "
                         f"{b!r} completed, got {int(ok.sum())}")
    return vb[ok] - va[ok], float(np.mean(vb[ok]))


def _interval(d: np.ndarray, confidence: float, sided: int) -> tuple[float, float, float]:
    """``(mean, lower, upper)``: the ``confidence`` t-interval of the mean of ``d``
    (``sided`` 1: the one-sided bounds at that confidence)."""
    S = d.size
    mean, se = float(d.mean()), float(d.std(ddof=1) / np.sqrt(S))
    q = stats.t.ppf(confidence if sided == 1 else (1 + confidence) / 2, S - 1)
    return mean, mean - q * se, mean + q * se


def _worst(d: np.ndarray, seeds: Sequence[int] | None, k: int = 3,
           by: np.ndarray | None = None) -> str:
    """The ``k`` seeds with the smallest ``by`` (default ``d``) and their ``d``."""
    order = np.argsort(d if by is None else by)[:k]
    names = [seeds[i] if seeds is not None else int(i) for i in order]
    return ", ".join(f"seed {s}: {d[i]:+.3g}" for s, i in zip(names, order, strict=True))


def assert_better(comparison: Comparison | Mapping[str, ArrayLike], a: str, b: str, *,
                  metric: str = "rmse", confidence: float = 0.95,
                  margin: float = 0.0) -> float:
    r"""Assert that estimator ``a`` is better than ``b``: its ``metric`` lower, paired
    over seeds, at ``confidence`` (one-sided t-test; see the module).

    Parameters
    ----------
    comparison : Comparison or dict
        An :func:`~estim.compare` result or ``{label: per-seed values}``.
    a, b : str
        Labels of the estimators.
    metric : {"rmse", "nees"}
        The per-seed metric; ``"nees"`` compares the distance of the time-averaged
        NEES per dimension from 1 (lower: more consistent).
    confidence : float
        One minus the false-alarm rate, in (0, 1).
    margin : float
        How much better, as a fraction of ``b``'s mean metric (0: any improvement).

    Returns
    -------
    float
        The mean improvement :math:`\bar d` (in the metric's units).
    """
    confidence = _level(confidence, "confidence")
    margin = as_float(margin, "margin")
    d, mb = _paired(comparison, a, b, metric)
    mean, lower, _ = _interval(d, confidence, 1)
    seeds = comparison.seeds if isinstance(comparison, Comparison) else None
    if not lower > margin * mb:
        raise AssertionError(
            f"{a!r} is not shown better than {b!r} in {metric} at confidence {confidence:g} "
            f"({d.size} paired seeds): mean improvement {mean:.4g} ({mean / mb:+.2%} of "
            f"{b!r}'s {mb:.4g}), one-sided lower bound {lower:.4g} "
            f"{'<=' if lower <= margin * mb else '>'} the margin {margin * mb:.4g}; the "
            f"seeds where {a!r} did worst: {_worst(d, seeds)}")
    return mean


def assert_equivalent(comparison: Comparison | Mapping[str, ArrayLike], a: str, b: str, *,
                      metric: str = "rmse", tolerance: float = 0.02,
                      confidence: float = 0.95) -> float:
    r"""Assert that ``a`` and ``b`` are equivalent in ``metric``: two one-sided tests at
    ``confidence`` that the mean paired difference lies within :math:`\pm`
    ``tolerance`` times ``b``'s mean (its :math:`1 - 2\alpha` interval inside the
    bounds).

    Returns
    -------
    float
        The mean difference :math:`\overline{m_b - m_a}`.
    """
    confidence = _level(confidence, "confidence")
    tolerance = as_float(tolerance, "tolerance", minimum=0.0)
    d, mb = _paired(comparison, a, b, metric)
    mean, lower, upper = _interval(d, confidence, 1)
    bound = tolerance * abs(mb)
    if not (lower > -bound and upper < bound):
        seeds = comparison.seeds if isinstance(comparison, Comparison) else None
        raise AssertionError(
            f"{a!r} and {b!r} are not shown equivalent in {metric} within +-{tolerance:g} "
            f"of {b!r}'s {mb:.4g} (+-{bound:.4g}) at confidence {confidence:g}: mean "
            f"difference {mean:.4g}, its {2 * confidence - 1:.0%} interval [{lower:.4g}, "
            f"{upper:.4g}] ({d.size} paired seeds); the largest differences: "
            f"{_worst(d, seeds, by=-np.abs(d))}")
    return mean


def _runs(result, burn_in: int | None) -> tuple[list[tuple[Log, int]] | None,
                                               np.ndarray | None]:
    """``(logs with the samples each skips, None)``, or ``(None, per-seed NEES)`` of a
    comparison without logs."""
    if isinstance(result, Comparison):
        if len(result.rows) != 1:
            raise ValueError(f"result: a Comparison of {len(result.rows)} estimators; give "
                             f"a comparison of one estimator (or its logs)")
        name = result.rows[0].name
        if not result.logs.get(name):  # its per-seed NEES, after compare's burn-in
            return None, np.asarray(result.nees[name], dtype=float)
        result = [g for g in result.logs[name] if g is not None]
    logs = [result] if isinstance(result, Log) else result
    if isinstance(logs, str) or not isinstance(logs, Sequence) or not logs or \
            not all(isinstance(g, Log) for g in logs):
        raise TypeError(f"result must be a Log, a list of Logs or a Comparison, got "
                        f"{type(result).__name__}")
    return [(g, startup_samples(len(g)) if burn_in is None else int(burn_in)) for g in logs], \
        None


def _by_seed(per: list[np.ndarray], what: str) -> tuple[np.ndarray, str]:
    """Per-seed means of per-step values, or one log's batch means."""
    if len(per) > 1:
        return np.array([np.nanmean(v) for v in per]), "seeds"
    v = per[0][np.isfinite(per[0])]
    if v.size < 2 * BATCHES:
        raise ValueError(f"result: one log with {v.size} steps of {what}; give at least "
                         f"{2 * BATCHES}, or several seeds")
    return np.array([c.mean() for c in np.array_split(v, BATCHES)]), "batches of steps"


def assert_consistent(result: Log | Sequence[Log] | Comparison, level: float = 0.99,
                      burn_in: int | None = None) -> float:
    r"""Assert that the reported covariances match the errors: the mean NEES per state
    dimension within the ``level`` t-interval of 1 over independent seeds (or over
    batches of one log's steps), and likewise the NIS per measured output where the
    logs record it.

    Parameters
    ----------
    result : Log, list of Log or Comparison
        The runs of one estimator (a comparison of one estimator, with or without its
        logs: without, its per-seed NEES after ``compare``'s burn-in).
    level : float
        One minus the false-alarm rate, in (0, 1).
    burn_in : int, optional
        Samples to leave out at the start of each log (default: the start-up that
        ``compare``'s notes set apart, a tenth; from the guess a filter is not consistent
        by design).

    Returns
    -------
    float
        The mean NEES per dimension.
    """
    level = _level(level, "level")
    runs, per_seed = _runs(result, burn_in)
    if runs is None:
        assert per_seed is not None
        values, what = per_seed[np.isfinite(per_seed)], "seeds"
    else:
        per = [nees_of(g, burn_in=k) / g.P.shape[1] for g, k in runs]
        values, what = _by_seed(per, "NEES")
    if values.size < 2:
        raise ValueError("result: fewer than 2 seeds with a covariance to test")
    _test(values, level, f"NEES per state dimension over {values.size} {what}",
          lambda: "" if runs is None else _contributors(runs))
    if runs is not None:
        per_nis = []
        for g, k in runs:
            measured = np.isfinite(g.y[k:]).sum(axis=1)
            ok = np.isfinite(g.nis[k:]) & (measured > 0)
            if ok.any():
                per_nis.append(g.nis[k:][ok] / measured[ok])
        if per_nis:
            nis, what = _by_seed(per_nis, "NIS")
            _test(nis, level, f"NIS per measured output over {nis.size} {what}", lambda: "")
    return float(values.mean())


def _test(values: np.ndarray, level: float, what: str, where) -> None:
    """``values`` (means of a statistic whose expectation is 1) inside the ``level``
    t-interval about 1, else an ``AssertionError``."""
    mean, lower, upper = _interval(values, level, 2)
    if not (lower <= 1.0 <= upper):
        half = (upper - lower) / 2
        raise AssertionError(
            f"{what}: {mean:.4g}, its {level:.0%} interval [{lower:.4g}, {upper:.4g}] "
            f"excludes 1 (consistent: within +-{half:.3g} of 1); "
            f"{'overconfident' if mean > 1 else 'pessimistic'}{where()}")


def _contributors(runs: list[tuple[Log, int]]) -> str:
    """The three steps whose NEES, averaged over the logs, is largest."""
    T = min(len(g) for g, _ in runs)
    k0 = max(k for _, k in runs)
    per_step = np.nanmean([nees_of(g)[k0:T] / g.P.shape[1] for g, _ in runs], axis=0)
    top = np.argsort(-np.nan_to_num(per_step))[:3]
    t = runs[0][0].t
    return "; the steps that contribute most: " + ", ".join(
        f"k={k0 + i} (t={t[k0 + i]:g}): {per_step[i]:.3g}" for i in sorted(top))


def assert_close(a: Estimator, b: Estimator, record: Record | tuple, *, atol: float = 1e-8,
                 rtol: float = 1e-8) -> None:
    """Assert that two estimators give the same estimates and covariances on one record
    (``record``: a :class:`~estim.Record` or ``(Y, U)``), to ``atol + rtol |b|``; the
    message names the first differing sample and state. The covariances are compared
    where both estimators report one (a step function may return the estimate only)."""
    for name, est in (("a", a), ("b", b)):
        if not isinstance(est, Estimator):
            raise TypeError(f"{name} must be an estim estimator (or an adapter around "
                            f"one: estim.adapters), got {type(est).__name__}")
    atol, rtol = as_float(atol, "atol", minimum=0.0), as_float(rtol, "rtol", minimum=0.0)
    if isinstance(record, Record):
        Y, U = record.y, record.u
    elif isinstance(record, tuple) and len(record) == 2:
        Y, U = record
    else:
        raise TypeError(f"record must be an estim.Record or a pair (Y, U), got "
                        f"{type(record).__name__}")
    la, lb = replay(a, Y, U, warn=False), replay(b, Y, U, warn=False)
    for key in ("x_hat", "P"):
        xa, xb = np.asarray(getattr(la, key)), np.asarray(getattr(lb, key))
        if key == "P" and (np.isnan(xa).all() or np.isnan(xb).all()):
            continue  # one of them reports no covariance
        if xa.shape != xb.shape:
            raise AssertionError(f"{key}: shapes differ, {xa.shape} and {xb.shape}")
        bad = ~np.isclose(xa, xb, atol=atol, rtol=rtol, equal_nan=True)
        if bad.any():
            first = np.argwhere(bad)[0]
            k = int(first[0])
            raise AssertionError(
                f"{key} differs first at sample {k} (t={la.t[k]:g}), entry "
                f"{tuple(int(i) for i in first[1:])}: {xa[tuple(first)]!r} against "
                f"{xb[tuple(first)]!r} (atol {atol:g}, rtol {rtol:g}); {int(bad.sum())} "
                f"entries differ in all")


def save_baseline(comparison: Comparison, path: str | os.PathLike[str]) -> Path:
    """Store a comparison's per-seed metrics as JSON (scenario, seeds, every estimator's
    ``rmse`` and ``nees``, the estim version) for :func:`assert_no_regression`."""
    if not isinstance(comparison, Comparison):
        raise TypeError(f"comparison must be an estim.Comparison, got "
                        f"{type(comparison).__name__}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {"scenario": comparison.scenario, "seeds": [int(s) for s in comparison.seeds],
            "estim": __version__,
            "metrics": {name: {"rmse": _json_values(comparison.rmse[name]),
                               "nees": _json_values(comparison.nees.get(name, []))}
                        for name in comparison.rmse}}
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


def _json_values(values: ArrayLike) -> list[float | None]:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values, float)]


def load_baseline(path: str | os.PathLike[str]) -> dict:
    """A baseline written by :func:`save_baseline` (``ValueError`` naming the file when
    it is not one)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        assert isinstance(data, dict) and {"scenario", "seeds", "metrics"} <= set(data)
    except (OSError, ValueError, AssertionError) as exc:
        raise ValueError(f"baseline {str(path)!r} is not an estim baseline (written by "
                         f"estim.testing.save_baseline): {exc}") from None
    return data


def assert_no_regression(comparison: Comparison, baseline: str | os.PathLike[str] | dict, *,
                         metric: str = "rmse", confidence: float = 0.95,
                         margin: float = 0.0) -> dict[str, float]:
    r"""Assert that no estimator of ``comparison`` got worse than in ``baseline``: for each
    estimator in both, the one-sided paired test (seed by seed, the same seeds) that its
    ``metric`` rose by more than ``margin`` times the baseline's mean must not pass at
    ``confidence``. With the same code the per-seed numbers are identical and the test
    is exact. A baseline of another scenario or another seed set is refused.

    Returns
    -------
    dict
        The mean change of the metric per estimator (positive: worse).
    """
    confidence = _level(confidence, "confidence")
    margin = as_float(margin, "margin", minimum=0.0)
    if not isinstance(comparison, Comparison):
        raise TypeError(f"comparison must be an estim.Comparison, got "
                        f"{type(comparison).__name__}")
    where = "the baseline" if isinstance(baseline, dict) else repr(str(baseline))
    data = baseline if isinstance(baseline, dict) else load_baseline(baseline)
    if data["scenario"] != comparison.scenario:
        raise ValueError(f"baseline: {where} is of scenario {data['scenario']!r}, not "
                         f"{comparison.scenario!r}")
    if [int(s) for s in data["seeds"]] != [int(s) for s in comparison.seeds]:
        raise ValueError(f"baseline: {where} has seeds {_seed_text(data['seeds'])}, the "
                         f"comparison {_seed_text(comparison.seeds)}: paired tests need "
                         f"the same seeds (update the baseline)")
    changes, regressions = {}, []
    for name in comparison.rmse:
        if name not in data["metrics"]:
            continue
        old = np.array([np.nan if v is None else v for v in data["metrics"][name][metric]],
                       dtype=float)
        new = _values(comparison, name, metric, "comparison")
        if metric == "nees":
            old = np.abs(old - 1.0)
        ok = np.isfinite(old) & np.isfinite(new)
        if ok.sum() < 2:
            continue
        d = new[ok] - old[ok]
        kept = [s for s, k in zip(comparison.seeds, ok, strict=True) if k]
        mean, lower, _ = _interval(d, confidence, 1) if d.any() else (0.0, 0.0, 0.0)
        changes[name] = mean
        if lower > margin * float(np.mean(old[ok])):
            regressions.append(f"{name!r}: {metric} {np.mean(old[ok]):.4g} -> "
                               f"{np.mean(new[ok]):.4g} ({mean / np.mean(old[ok]):+.2%}, "
                               f"one-sided lower bound {lower:.3g}; worst "
                               f"{_worst(-d, kept)})")
    if regressions:
        raise AssertionError(f"regression against {where} at confidence {confidence:g}: "
                             + "; ".join(regressions))
    return changes


def _seed_text(seeds: Sequence[int]) -> str:
    seeds = [int(s) for s in seeds]
    if seeds == list(range(seeds[0], seeds[0] + len(seeds))) if seeds else False:
        return f"{seeds[0]}..{seeds[-1]} ({len(seeds)})"
    return str(seeds[:6])[:-1] + (", ...]" if len(seeds) > 6 else "]")
