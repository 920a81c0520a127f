"""The measured error rates of estim's verdicts (estim.verdicts, estim.testing), on
well-behaved filters and on hostile ones: the cases, the rates over disjoint sets of
seeds, and the table of the testing page.

``python tests/verdict_cases.py [sets]`` prints the table (400 sets by default, about a
minute); ``tests/test_verdicts.py`` checks the same rates on fewer sets (and on 400 with
``-m slow``).

Every rate is the share of disjoint seed sets (no seed in two sets) on which a verdict
fell one way, with its 95 % Clopper-Pearson interval. The per-seed scores of a seed do
not depend on the other seeds, so a set's verdict is the one ``estim.testing`` gives on
a comparison of exactly those seeds.
"""

from __future__ import annotations

import sys
from functools import cache
from pathlib import Path

import numpy as np
from scipy import stats

import estim
from estim import testing, verdicts

sys.path.insert(0, str(Path(__file__).parent))
import linear_gaussian as lg  # noqa: E402

LEVEL, CONFIDENCE = 0.99, 0.95


def _r_times(factor: float):
    return lambda m, t: estim.EKF(m, **{**t, "R": factor * np.asarray(t["R"])})


@cache
def runs(case: str, n_seeds: int) -> estim.Comparison:
    """The per-seed scores of a case's filters over seeds ``0 .. n_seeds - 1``, after the
    start-up that comparisons set apart (a tenth of the samples)."""
    if case == "sine_pendulum":  # diverges: the EKF on about 12 %, the UKF on about 7 %
        return estim.compare(estim.scenarios.get("sine_pendulum"),
                             {"ekf": estim.EKF, "ekf_R10": _r_times(10.0), "ukf": estim.UKF},
                             seeds=range(n_seeds), burn_in=30)
    if case == "van_der_pol":  # a well-tuned EKF
        return estim.compare(estim.scenarios.get("van_der_pol"), {"ekf": estim.EKF},
                             seeds=range(n_seeds), burn_in=12)
    if case == "linear":  # the exact Kalman filter, started from the truth: consistent
        return estim.compare(lg.linear_model(), {"kf": estim.EKF}, seeds=range(n_seeds),
                             x0=[1.0, 0.5], n_steps=100, Q=lg.Q, R=lg.R, burn_in=10,
                             tuning={"Q": lg.Q, "R": lg.R, "x0": [1.0, 0.5],
                                     "P0": 1e-9 * np.eye(2)})
    raise ValueError(case)


def blocks(n_sets: int, size: int, start: int = 0) -> list[slice]:
    return [slice(start + i * size, start + (i + 1) * size) for i in range(n_sets)]


def consistency_rejections(res: estim.Comparison, name: str, size: int, n_sets: int,
                           rule: str = "verdict", outlying: int = 0) -> int:
    """On how many of ``n_sets`` disjoint sets of ``size`` seeds the consistency of
    ``name`` is rejected at level 0.99: by estim's verdict (``"verdict"``), or by the
    rules it replaced, the t-interval of the mean NEES/n about 1 (``"mean"``: the former
    ``assert_consistent``) and the mean within two standard errors of 1 (``"2se"``: the
    former table column). ``outlying``: that many seeds of each set replaced by an
    outlying seed that did not diverge (NEES/n 5 on every step, its chi-square level
    0.993): what a few bad seeds of a consistent filter can do."""
    rejected = 0
    seeds = np.asarray(res.seeds)
    for b in blocks(n_sets, size):
        ne, level = res.nees[name][b].copy(), res.nees_level[name][b].copy()
        ne[:outlying] = 5.0
        level[:outlying] = stats.chi2.cdf(5.0 * 2, 2)
        if rule == "verdict":
            v = verdicts.consistency(ne, level, res.diverged[name][b], seeds[b], level=LEVEL)
            rejected += not v.consistent
        else:
            mean, se = ne.mean(), ne.std(ddof=1) / np.sqrt(size)
            q = stats.t.ppf((1 + LEVEL) / 2, size - 1) if rule == "mean" else 2.0
            rejected += abs(mean - 1.0) > q * se
    return rejected


def regressions(old: np.ndarray, new: np.ndarray, size: int, n_sets: int,
                test: str) -> int:
    """On how many of ``n_sets`` disjoint sets of ``size`` seeds
    :func:`estim.testing.assert_no_regression` (at 0.95) calls ``new`` a regression of
    ``old`` (the same seeds)."""
    found = 0
    for b in blocks(n_sets, size):
        seeds = list(range(size))
        base = {"scenario": "s", "seeds": seeds, "metrics": {"f": {"rmse": list(old[b])}}}
        res = estim.Comparison("s", seeds, [], {"f": new[b]})
        try:
            testing.assert_no_regression(res, base, confidence=CONFIDENCE, test=test)
        except AssertionError:
            found += 1
    return found


def false_better(values: np.ndarray, size: int, n_sets: int, test: str) -> int:
    """Equal estimators: one filter on two disjoint blocks of seeds, ``a`` on one and
    ``b`` on the other; on how many of ``n_sets`` pairs of blocks ``assert_better`` (at
    0.95) declares ``a`` better."""
    found = 0
    for i in range(n_sets):
        a = values[2 * i * size:(2 * i + 1) * size]
        b = values[(2 * i + 1) * size:(2 * i + 2) * size]
        try:
            testing.assert_better({"a": a, "b": b}, "a", "b", confidence=CONFIDENCE,
                                  test=test)
            found += 1
        except AssertionError:
            pass
    return found


def interval(k: int, n: int) -> str:
    ci = stats.binomtest(k, n).proportion_ci(0.95)
    return f"{k / n:.1%} [{ci.low:.1%}, {ci.high:.1%}]"


def table(n_sets: int = 400) -> list[str]:
    """The error-rate table of the testing page, ``n_sets`` sets per cell."""
    S, S20 = 50, 20
    pend, vdp, lin = (runs(c, 2 * S * n_sets) for c in ("sine_pendulum", "van_der_pol",
                                                        "linear"))
    rows = ["| case | verdict | estim (now) | mean t-interval (before) | 2 SE (before, table) |",
            "|---|---|---|---|---|"]
    for title, res, name, what in (
            ("sine pendulum, EKF (diverges on "
             f"{pend.diverged['ekf'].mean():.0%} of seeds)", pend, "ekf", "rejected"),
            (f"sine pendulum, UKF (diverges on {pend.diverged['ukf'].mean():.0%})", pend,
             "ukf", "rejected"),
            ("van der Pol, EKF (well tuned)", vdp, "ekf", "accepted"),
            ("linear-Gaussian, exact Kalman filter", lin, "kf", "accepted"),
            ("the exact Kalman filter with 1 outlying seed in 50", lin, "kf", "accepted"),
            ("the exact Kalman filter with 2 outlying seeds in 50", lin, "kf", "accepted")):
        cells = []
        outlying = int(title.split(" with ")[1][0]) if " with " in title else 0
        for rule in ("verdict", "mean", "2se"):
            k = consistency_rejections(res, name, S, n_sets, rule, outlying)
            cells.append(interval(k if what == "rejected" else n_sets - k, n_sets))
        rows.append(f"| {title}, sets of {S} | consistency {what} | " + " | ".join(cells) + " |")
    rows += ["", "| case | seeds per set | Wilcoxon (default) | sign test | paired t-test |",
             "|---|---|---|---|---|"]
    old, new = pend.rmse["ekf"], pend.rmse["ekf_R10"]
    for size in (S, S20):
        cells = [interval(regressions(old, new, size, n_sets, t), n_sets)
                 for t in verdicts.TESTS]
        rows.append(f"| sine pendulum, EKF told R x 10: regression detected | {size} | "
                    + " | ".join(cells) + " |")
    for title, values in (("sine pendulum EKF (heavy-tailed RMSE)", pend.rmse["ekf"]),
                          ("van der Pol EKF", vdp.rmse["ekf"])):
        for size in (S, S20):
            n = min(n_sets, len(values) // (2 * size))
            cells = [interval(false_better(values, size, n, t), n) for t in verdicts.TESTS]
            rows.append(f"| {title}, equal estimators: false 'better' | {size} | "
                        + " | ".join(cells) + " |")
    return rows


if __name__ == "__main__":
    print("\n".join(table(int(sys.argv[1]) if len(sys.argv) > 1 else 400)))
