r"""Assertions for comparing estimators in tests: statistical tests with stated error rates.

Each assertion raises an ``AssertionError`` whose message gives the statistic, its
p-value or interval and what drove it, and returns the test's result when it passes.
The tests are those of :mod:`estim.verdicts`, the same rules the comparison table, its
notes and the pytest plugin use:

:func:`assert_better`
    a one-sided paired test over seeds that ``a``'s metric is below ``b``'s. Seed
    :math:`s` gives both estimators the same noise, so the differences
    :math:`d_s = m_b(s) - m_a(s) - \text{margin}\cdot\mathrm{median}(m_b)` are
    independent over seeds. By default Wilcoxon's signed-rank test: its false-alarm rate
    is ``1 - confidence`` whenever the differences are symmetric about zero (two
    interchangeable estimators), however heavy-tailed they are, and a few divergent
    seeds cannot outvote the typical seed as they do a mean (``test="t"``: Student's
    t-test on the mean; ``test="sign"``: the sign test).
:func:`assert_equivalent`
    two one-sided tests (TOST, Schuirmann 1987) of the same kind, that the differences
    lie within :math:`\pm` ``tolerance`` times ``b``'s median metric.
:func:`assert_consistent`
    the consistency verdict of :func:`estim.verdicts.consistency`: no more diverged
    seeds than a consistent estimator would show (named in the message), and the NEES
    of the typical step following its chi-square law (its probability level 1/2 on
    average over independent seeds; one log: over batches of its steps).
:func:`assert_no_regression`
    the one-sided paired test of :func:`assert_better`, against the per-seed metrics a
    baseline stored; the message lists the seeds whose change drove the verdict.
:func:`assert_close`
    two estimators on one record: estimates and covariances equal to tolerances.

``comparison`` is an :class:`~estim.Comparison` (its per-seed ``rmse`` and ``nees``) or
a mapping ``{label: per-seed values}``. The measured false-alarm and detection rates,
on well-behaved filters and on hostile cases (a filter that diverges on a tenth of its
seeds, heavy-tailed metrics), are on the testing page of the documentation and in
``tests/test_testing.py``.

References
----------
D. J. Schuirmann, "A comparison of the two one-sided tests procedure and the power
approach for assessing the equivalence of average bioavailability", J.
Pharmacokinet. Biopharm. 15(6), 1987; F. Wilcoxon, "Individual comparisons by ranking
methods", Biometrics Bulletin 1(6), 1945; Y. Bar-Shalom, X. R. Li, T. Kirubarajan,
*Estimation with Applications to Tracking and Navigation*, Wiley 2001, sec. 5.4.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_float, did_you_mean
from estim._version import __version__
from estim.compare import Comparison
from estim.estimators.base import Estimator
from estim.experiment import Record
from estim.inference.posterior import Posterior, agreement
from estim.log import Log
from estim.metrics import nees as nees_of
from estim.metrics import nis as nis_of
from estim.metrics import startup_samples
from estim.simulate import replay
from estim.verdicts import (
    TESTS,
    Consistency,
    PairedTest,
    SeedScores,
    consistency,
    paired,
    seed_range_text,
    seed_scores,
    smallest_p,
)

__all__ = ["METRICS", "TESTS", "Consistency", "PairedTest", "assert_better", "assert_close",
           "assert_consistent", "assert_equivalent", "assert_no_regression",
           "assert_posterior_close", "load_baseline",
           "record", "recording", "save_baseline"]

#: The per-seed metrics a comparison holds.
METRICS = ("rmse", "nees")

#: Where the assertions report themselves (pass or fail), when something listens: the
#: pytest plugin sets a list per test (:func:`recording`).
_RECORDS: list[dict] | None = None


def recording(records: list[dict] | None) -> list[dict] | None:
    """Send every assertion's outcome (``{"assertion", "passed", "text"}``) to ``records``
    from now on (None: nowhere); the previous list is returned. The pytest plugin uses
    it to list each test's assertions in its summary and report."""
    global _RECORDS
    previous, _RECORDS = _RECORDS, records
    return previous


def record(assertion: str, passed: bool, text: str, **extra: Any) -> None:
    """Report an outcome to the list :func:`recording` set (nothing when none is set)."""
    if _RECORDS is not None:
        _RECORDS.append({"assertion": assertion, "passed": passed, "text": text, **extra})


def _verdict(assertion: str, passed: bool, text: str, **extra: Any) -> None:
    """Record the outcome, then raise an ``AssertionError`` with ``text`` if it failed."""
    record(assertion, passed, text, **extra)
    if not passed:
        raise AssertionError(text)


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


def _test_name(test: Any) -> str:
    if test not in TESTS:
        raise ValueError(f"test must be one of {', '.join(map(repr, TESTS))}, got {test!r}"
                         f"{did_you_mean(str(test), list(TESTS))}")
    return str(test)


def _causes(comparison: object, labels: Sequence[str]) -> str:
    """What the runs of ``labels`` raised, estimator by estimator: ``"'student' raised on
    5 of 5 seeds (seed 0: NotImplementedError: exercise 3)"``; empty when none did."""
    if not isinstance(comparison, Comparison):
        return ""
    out = []
    for row in comparison.rows:
        if row.name in labels and row.errors:
            seed, message = next(iter(row.errors.items()))
            out.append(f"{row.name!r} raised on {len(row.errors)} of "
                       f"{row.runs + len(row.errors)} seeds (seed {seed}: {message})")
    return "; ".join(out)


def _paired(comparison, a: str, b: str, metric: str, confidence: float, test: str,
            alternative: str = "greater") -> tuple[np.ndarray, np.ndarray, list[int]]:
    """``(m_a, m_b, seeds)`` over the seeds both completed; the runs' own errors first
    when too few did for the test to reach ``confidence``."""
    va, vb = _values(comparison, a, metric, "a"), _values(comparison, b, metric, "b")
    if va.shape != vb.shape:
        raise ValueError(f"a and b must have a value per seed each, got {va.size} and "
                         f"{vb.size}")
    ok = np.isfinite(va) & np.isfinite(vb)
    names = comparison.seeds if isinstance(comparison, Comparison) else range(va.size)
    seeds = [int(s) for s, k in zip(names, ok, strict=True) if k]
    n, need = int(ok.sum()), _needed(confidence, test, alternative)
    if n < need:
        causes = _causes(comparison, (a, b))
        raise ValueError(
            (f"{causes}: " if causes else "") +
            f"a paired {test} test at confidence {confidence:g} needs at least {need} seeds "
            f"where both {a!r} and {b!r} completed, got {n}"
            + ("" if causes or test == "t" else
               f" (its smallest p-value with {n} seeds is {smallest_p(n, test, alternative):.3g}"
               f"; give more seeds, or test='t')"))
    return va[ok], vb[ok], seeds


def _needed(confidence: float, test: str, alternative: str = "greater") -> int:
    """The fewest seeds with which ``test`` can reach ``confidence`` (at least 2)."""
    need = 2
    while smallest_p(need, test, alternative) >= 1 - confidence:
        need += 1
    return need


def _changes(d: np.ndarray, seeds: Sequence[int], k: int = 3, worst: bool = True) -> str:
    """The ``k`` seeds with the smallest (``worst``) or largest ``d``, with their ``d``."""
    order = np.argsort(d if worst else -d)[:k]
    return ", ".join(f"seed {seeds[i]}: {d[i]:+.3g}" for i in order)


def assert_better(comparison: Comparison | Mapping[str, ArrayLike], a: str, b: str, *,
                  metric: str = "rmse", confidence: float = 0.95, margin: float = 0.0,
                  test: str = "wilcoxon") -> PairedTest:
    r"""Assert that estimator ``a`` is better than ``b``: its ``metric`` lower, paired
    over seeds, at ``confidence`` (a one-sided paired test; see the module).

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
        One minus the false-alarm rate, in (0, 1). A rank or sign test needs at least
        :math:`\log_2(1 / (1 - \text{confidence}))` seeds (5 at 0.95).
    margin : float
        How much better, as a fraction of ``b``'s median metric over seeds (0: any
        improvement).
    test : {"wilcoxon", "sign", "t"}
        The paired test (:func:`estim.verdicts.paired`).

    Returns
    -------
    PairedTest
        The test of :math:`d_s = m_b(s) - m_a(s) - \text{margin}\cdot\mathrm{median}(m_b)`
        (its ``location``: the improvement beyond the margin).
    """
    confidence, test = _level(confidence, "confidence"), _test_name(test)
    margin = as_float(margin, "margin")
    ma, mb, seeds = _paired(comparison, a, b, metric, confidence, test)
    shift = margin * float(np.median(mb))
    d = mb - ma - shift
    r = paired(d, "greater", test)
    passed = r.p_value < 1 - confidence
    claim = (f"no worse than {b!r} by more than {-shift:.4g}" if margin < 0 else
             f"better than {b!r}" + (f" by more than {shift:.4g}" if margin else ""))
    text = (f"{a!r} {'is' if passed else 'is not'} shown {claim} in {metric} at "
            f"confidence {confidence:g} ({r.n} paired seeds): {r.text()}; median "
            f"{metric} {np.median(ma):.4g} against {np.median(mb):.4g}, mean {np.mean(ma):.4g} "
            f"against {np.mean(mb):.4g}; the seeds where {a!r} did worst: {_changes(d, seeds)}")
    _verdict("assert_better", passed, text, p_value=r.p_value)
    return r


def assert_equivalent(comparison: Comparison | Mapping[str, ArrayLike], a: str, b: str, *,
                      metric: str = "rmse", tolerance: float = 0.02,
                      confidence: float = 0.95, test: str = "wilcoxon") -> PairedTest:
    r"""Assert that ``a`` and ``b`` are equivalent in ``metric``: two one-sided paired
    tests at ``confidence`` that the differences :math:`m_b(s) - m_a(s)` lie above
    :math:`-\delta` and below :math:`+\delta`, :math:`\delta` = ``tolerance`` times ``b``'s
    median metric (TOST; Wilcoxon's signed-rank tests by default).

    Returns
    -------
    PairedTest
        The test of the differences, with the larger of the two one-sided p-values.
    """
    confidence, test = _level(confidence, "confidence"), _test_name(test)
    tolerance = as_float(tolerance, "tolerance", minimum=0.0)
    ma, mb, seeds = _paired(comparison, a, b, metric, confidence, test)
    d, bound = mb - ma, tolerance * abs(float(np.median(mb)))
    lower, upper = paired(d + bound, "greater", test), paired(d - bound, "less", test)
    r = dataclasses.replace(paired(d, "two-sided", test),
                            p_value=max(lower.p_value, upper.p_value))
    passed = r.p_value < 1 - confidence
    text = (f"{a!r} and {b!r} {'are' if passed else 'are not'} shown equivalent in {metric} "
            f"within +-{tolerance:g} of the median of {b!r}, {np.median(mb):.4g} "
            f"(+-{bound:.4g}), at "
            f"confidence {confidence:g} ({r.n} paired seeds): the larger one-sided p-value "
            f"{r.p_value:.3g} (above -{bound:.3g}: {lower.p_value:.3g}; below +{bound:.3g}: "
            f"{upper.p_value:.3g}); differences {r.text().split(', ', 1)[1]}; the largest "
            f"differences: {_changes(-np.abs(d), seeds)}")
    _verdict("assert_equivalent", passed, text, p_value=r.p_value)
    return r


def _runs(result, burn_in: int | None) -> tuple[list[tuple[Log, int]], list[int]]:
    """The logs with the samples each skips, and their names (seeds)."""
    seeds: list[int] | None = None
    if isinstance(result, Comparison):
        name = result.rows[0].name
        kept = [(s, g) for s, g in zip(result.seeds, result.logs[name], strict=True)
                if g is not None]
        seeds, result = [s for s, _ in kept], [g for _, g in kept]
    logs = [result] if isinstance(result, Log) else result
    if isinstance(logs, str) or not isinstance(logs, Sequence) or not logs or \
            not all(isinstance(g, Log) for g in logs):
        raise TypeError(f"result must be a Log, a list of Logs or a Comparison, got "
                        f"{type(result).__name__}")
    skip = [startup_samples(len(g)) if burn_in is None else int(burn_in) for g in logs]
    return list(zip(logs, skip, strict=True)), seeds or list(range(len(logs)))


def _from_logs(runs: list[tuple[Log, int]], seeds: list[int], level: float,
               what: str) -> Consistency | None:
    scores: list[SeedScores] = []
    for g, k in runs:
        if what == "NEES":
            scores.append(seed_scores(nees_of(g, burn_in=k), g.P.shape[1]))
        else:  # NIS: the outputs measured at each step are its degrees of freedom
            scores.append(seed_scores(nis_of(g, burn_in=k), np.isfinite(g.y[k:]).sum(axis=1)))
    return consistency([s["ratio"] for s in scores], [s["level"] for s in scores],
                       [s["diverged"] for s in scores], seeds, level=level,
                       batches=scores[0]["batches"] if len(scores) == 1 else None, what=what)


def assert_consistent(result: Log | Sequence[Log] | Comparison, level: float = 0.99,
                      burn_in: int | None = None, *, nis: bool = False) -> Consistency:
    r"""Assert that the reported covariances match the errors: the verdict of
    :func:`estim.verdicts.consistency`, the one the comparison table's ``cons.`` column
    gives at level 0.99.

    It fails when more seeds diverged than a consistent estimator would show (a seed
    diverged when its NEES is beyond the 1e-8 tail of chi-square on a tenth of its
    steps; the message names them), or when the NEES of the typical step is off: the
    mean over seeds of each seed's average chi-square probability level outside its
    interval about 1/2 (one log: over 10 batches of its steps). The false-alarm rate is
    at most ``1 - level``.

    Parameters
    ----------
    result : Log, list of Log or Comparison
        The runs of one estimator. A comparison of one estimator is judged on its own
        per-seed scores (after ``compare``'s burn-in), exactly as its table; its logs are
        read only with ``burn_in`` or ``nis``.
    level : float
        One minus the false-alarm rate, in (0, 1).
    burn_in : int, optional
        Samples to leave out at the start of each log (default: a comparison's own
        burn-in; for logs, the start-up that ``compare``'s notes set apart, a tenth).
    nis : bool
        Test the NIS per measured output by the same rule too (from the logs; each test
        at ``level``).

    Returns
    -------
    Consistency
        The verdict (its diverged seeds, its statistics).
    """
    level = _level(level, "level")
    if isinstance(result, Comparison):
        if len(result.rows) != 1:
            raise ValueError(f"result: a Comparison of {len(result.rows)} estimators; give "
                             f"a comparison of one estimator (or its logs)")
        row = result.rows[0]
        if burn_in is None and not nis:
            verdict = row.consistency
            if verdict is not None and verdict.level != level:
                S = result.nees_batches[row.name]
                verdict = consistency(result.nees[row.name], result.nees_level[row.name],
                                      result.diverged[row.name], result.seeds, level=level,
                                      batches=next((b for b in S if b), None))
            if verdict is None:
                causes = _causes(result, [row.name])
                raise ValueError((f"{causes}: " if causes else "") + "result: no seed with "
                                 "a covariance to test")
            _consistency_verdict(verdict, lambda: "")
            return verdict
        if not result.logs.get(row.name):
            raise ValueError("result: burn_in= or nis=True reads the logs: run compare(..., "
                             "keep_logs=True), or give the comparison's own verdict")
    runs, seeds = _runs(result, burn_in)
    verdict = _from_logs(runs, seeds, level, "NEES")
    if verdict is None:
        raise ValueError("result: no log with a covariance to test (or one log with too few "
                         "steps)")
    _consistency_verdict(verdict, lambda: _contributors(runs))
    if nis:
        of_nis = _from_logs(runs, seeds, level, "NIS")
        if of_nis is not None:
            _consistency_verdict(of_nis, lambda: "")
    return verdict


def _consistency_verdict(v: Consistency, where: Callable[[], str]) -> None:
    text = v.summary()
    _verdict("assert_consistent", v.consistent,
             text + ("" if v.consistent else where()), grade=v.grade())


def _contributors(runs: list[tuple[Log, int]]) -> str:
    """The three steps whose NEES, averaged over the logs, is largest."""
    T = min(len(g) for g, _ in runs)
    k0 = max(k for _, k in runs)
    per_step = np.nanmean([nees_of(g)[k0:T] / g.P.shape[1] for g, _ in runs], axis=0)
    top = np.argsort(-np.nan_to_num(per_step))[:3]
    t = runs[0][0].t
    return "; the steps that contribute most: " + ", ".join(
        f"k={k0 + i} (t={t[k0 + i]:g}): {per_step[i]:.3g}" for i in sorted(top))


def assert_posterior_close(posterior: Posterior, reference: Posterior | Mapping[str, float],
                           *, confidence: float = 0.99) -> None:
    """Assert that chains' posterior means agree with a reference (other chains, such
    as an exact-likelihood Metropolis-Hastings run, or exact values) within their
    combined Monte Carlo standard errors, each parameter at ``confidence`` with a
    Bonferroni correction; chains with R-hat above 1.05 or fewer than 100 effective
    draws fail as not judgeable (:func:`estim.inference.posterior.agreement`)."""
    passed, text = agreement(posterior, dict(reference) if isinstance(reference, Mapping)
                             else reference, _level(confidence, "confidence"))
    _verdict("assert_posterior_close", passed, text)


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
    except (OSError, ValueError) as exc:
        raise ValueError(f"baseline {str(path)!r} is not an estim baseline (written by "
                         f"estim.testing.save_baseline): {exc}") from None
    return _checked_baseline(data, repr(str(path)))


def _checked_baseline(data: object, where: str) -> dict:
    """``data`` if it has the form :func:`save_baseline` writes (scenario, seeds, and per
    estimator a value or null per seed for each metric), else a ``ValueError`` saying
    what is wrong."""
    def bad(what: str) -> ValueError:
        return ValueError(f"baseline: {where} is not an estim baseline (written by "
                          f"estim.testing.save_baseline): {what}")

    if not isinstance(data, dict) or not {"scenario", "seeds", "metrics"} <= set(data):
        raise bad("it needs the keys 'scenario', 'seeds' and 'metrics'")
    seeds = data["seeds"]
    if not isinstance(seeds, list) or not all(isinstance(s, int) for s in seeds):
        raise bad("'seeds' must be a list of integers")
    if not isinstance(data["metrics"], dict) or not data["metrics"]:
        raise bad("'metrics' must map estimator labels to their per-seed metrics")
    for name, metrics in data["metrics"].items():
        if not isinstance(metrics, dict):
            raise bad(f"'metrics'[{name!r}] must map {list(METRICS)} to per-seed values")
        for key, values in metrics.items():
            if not isinstance(values, list) or len(values) != len(seeds) or not all(
                    v is None or isinstance(v, int | float) for v in values):
                raise bad(f"'metrics'[{name!r}][{key!r}] must be a list of {len(seeds)} "
                          f"numbers (null for a run that raised)")
    return data



def assert_no_regression(comparison: Comparison, baseline: str | os.PathLike[str] | dict, *,
                         metric: str = "rmse", confidence: float = 0.95,
                         margin: float = 0.0, test: str = "wilcoxon") -> dict[str, PairedTest]:
    r"""Assert that no estimator of ``comparison`` got worse than in ``baseline``: for each
    estimator in both, the one-sided paired test of :func:`assert_better` (seed by seed,
    the same seeds) that :math:`m_\text{new}(s) - m_\text{old}(s) - \text{margin}\cdot
    \mathrm{median}(m_\text{old})` is above zero must not pass at ``confidence``. With
    the same code the per-seed numbers are identical ("unchanged", whatever the number
    of seeds). A baseline of another scenario or another seed set is refused. Pass or
    fail, the outcome is recorded with what was checked (the pytest plugin prints it).

    Returns
    -------
    dict
        The test per estimator in both (its ``location``: the typical rise, positive:
        worse; p-value 1 when unchanged). A baseline that is malformed or shares no
        estimator with the comparison is a ``ValueError``: nothing passes having
        compared nothing.
    """
    confidence, test = _level(confidence, "confidence"), _test_name(test)
    margin = as_float(margin, "margin", minimum=0.0)
    if not isinstance(comparison, Comparison):
        raise TypeError(f"comparison must be an estim.Comparison, got "
                        f"{type(comparison).__name__}")
    where = "the baseline" if isinstance(baseline, dict) else repr(str(baseline))
    data = _checked_baseline(baseline, where) if isinstance(baseline, dict) else \
        load_baseline(baseline)
    common = [name for name in comparison.rmse if name in data["metrics"]]
    if not common:
        raise ValueError(f"baseline: {where} holds the estimators {list(data['metrics'])}, "
                         f"the comparison {list(comparison.rmse)}: nothing to compare "
                         f"(update the baseline)")
    if data["scenario"] != comparison.scenario:
        raise ValueError(f"baseline: {where} is of scenario {data['scenario']!r}, not "
                         f"{comparison.scenario!r}")
    if [int(s) for s in data["seeds"]] != [int(s) for s in comparison.seeds]:
        raise ValueError(f"baseline: {where} has seeds {seed_range_text(data['seeds'])}, the "
                         f"comparison {seed_range_text(comparison.seeds)}: paired tests need "
                         f"the same seeds (update the baseline)")
    results: dict[str, PairedTest] = {}
    lines: list[str] = []
    regressions: list[str] = []
    for name in comparison.rmse:
        if name not in data["metrics"]:
            lines.append(f"{name!r}: not in the baseline")
            continue
        if metric not in data["metrics"][name]:
            raise ValueError(f"baseline: {where} has no {metric!r} of {name!r}")
        old = np.array([np.nan if v is None else v for v in data["metrics"][name][metric]],
                       dtype=float)
        if metric == "nees":
            old = np.abs(old - 1.0)
        new = _values(comparison, name, metric, "comparison")
        ok = np.isfinite(old) & np.isfinite(new)
        seeds = [int(s) for s, k in zip(comparison.seeds, ok, strict=True) if k]
        d = new[ok] - old[ok] - margin * float(np.median(old[ok])) if ok.any() else new[ok]
        lost = int(np.isfinite(old).sum() - ok.sum())
        lost_text = f"; {lost} seeds that completed before now raised" if lost > 0 else ""
        if not d.any() and not lost:
            results[name] = paired(d, "greater", test)
            lines.append(f"{name!r}: unchanged on all {d.size} seeds")
            continue
        if d.size < _needed(confidence, test):
            causes = _causes(comparison, [name])
            raise ValueError((f"{causes}: " if causes else "") + f"{name!r} changed, and "
                             f"{d.size} seeds are too few for a paired {test} test at "
                             f"confidence {confidence:g} (at least "
                             f"{_needed(confidence, test)})")
        r = results[name] = paired(d, "greater", test)
        worse = r.p_value < 1 - confidence or lost > 0
        line = (f"{name!r}: {metric} median {np.median(old[ok]):.4g} -> "
                f"{np.median(new[ok]):.4g}, mean {np.mean(old[ok]):.4g} -> "
                f"{np.mean(new[ok]):.4g}; {r.above} of {r.n} seeds worse, {r.below} "
                f"better; {r.text(counts=False)}{lost_text}; the largest rises: "
                f"{_changes(d, seeds, worst=False)}")
        (regressions if worse else lines).append(line)
    checked = (f"against {where} (estimators {', '.join(comparison.rmse)}; seeds "
               f"{seed_range_text(comparison.seeds)}) at confidence {confidence:g}")
    text = (f"regression {checked}: " + "; ".join(regressions) if regressions else
            f"no regression {checked}") + ("; " + "; ".join(lines) if lines else "")
    _verdict("assert_no_regression", not regressions, text,
             baseline=data.get("path", where))
    return results
