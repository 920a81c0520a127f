"""estim.testing: the verdicts' measured error rates on well-behaved and hostile cases
(tests/verdict_cases.py), their messages, and their errors for bad input."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import binomtest, ttest_1samp, wilcoxon

import estim
from estim import testing, verdicts

sys.path.insert(0, str(Path(__file__).parent))
import verdict_cases as vc  # noqa: E402


def _ekf(R_factor: float = 1.0):
    return lambda m, t: estim.EKF(m, **{**t, "R": R_factor * np.asarray(t["R"])})


@pytest.fixture(scope="module")
def vdp():
    return estim.scenarios.get("van_der_pol")


def _cp_allows(k: int, n: int, rate: float, side: str) -> bool:
    """Whether ``k`` events in ``n`` sets are consistent (two-sided 99.9 %) with a rate at
    most (``side="most"``) or at least (``"least"``) ``rate``."""
    alternative = "greater" if side == "most" else "less"
    return binomtest(k, n, rate, alternative=alternative).pvalue > 1e-3


def _rates(n_sets: int) -> None:
    """The requirements on the verdicts' error rates, over ``n_sets`` disjoint seed sets
    (tests/verdict_cases.py): consistency of a filter that diverges on about 12 % of its
    seeds rejected in at least 97 % of sets of 50 seeds (the mean-based rule it replaces
    in at most half); the exact Kalman filter's false alarms consistent with at most 1 %,
    also with two of every 50 seeds replaced by outlying (not diverged) ones,
    the well-tuned van der Pol EKF accepted in a share consistent with at least 98 %; the
    R x 10 regression of the pendulum's EKF detected in at least 95 % of sets of 50 seeds
    (the paired t-test in at most half), and in at least 70 % of sets of 20; equal
    estimators with heavy-tailed per-seed RMSE declared different at a rate consistent
    with the nominal 5 %."""
    S = 50
    pend = vc.runs("sine_pendulum", 2 * S * n_sets)
    assert 0.09 < pend.diverged["ekf"].mean() < 0.15  # the hostile case: 1 seed in 8
    rejected = vc.consistency_rejections(pend, "ekf", S, n_sets)
    assert rejected >= 0.97 * n_sets, rejected
    assert vc.consistency_rejections(pend, "ekf", S, n_sets, rule="mean") <= n_sets / 2
    linear = vc.runs("linear", S * n_sets)
    exact = vc.consistency_rejections(linear, "kf", S, n_sets)
    assert _cp_allows(exact, n_sets, 0.01, "most"), exact
    outlying = vc.consistency_rejections(linear, "kf", S, n_sets, outlying=2)
    assert _cp_allows(outlying, n_sets, 0.01, "most"), outlying  # 2 bad seeds fake nothing
    tuned = vc.consistency_rejections(vc.runs("van_der_pol", 2 * S * n_sets), "ekf", S,
                                      n_sets)
    assert _cp_allows(n_sets - tuned, n_sets, 0.98, "least"), tuned
    old, new = pend.rmse["ekf"], pend.rmse["ekf_R10"]
    assert vc.regressions(old, new, S, n_sets, "wilcoxon") >= 0.95 * n_sets
    assert vc.regressions(old, new, S, n_sets, "t") <= n_sets / 2
    assert vc.regressions(old, new, 20, n_sets, "wilcoxon") >= 0.7 * n_sets
    for test in ("wilcoxon", "sign", "t"):
        false = vc.false_better(pend.rmse["ekf"], S, n_sets, test)
        assert _cp_allows(false, n_sets, 0.05, "most"), (test, false)


def test_error_rates_on_hostile_cases():
    _rates(100)


@pytest.mark.slow
def test_error_rates_on_hostile_cases_400_sets():
    """The testing page's table: the same requirements over 400 sets per cell."""
    _rates(400)


def test_the_pendulums_verdicts_and_messages():
    """The divergent pendulum: 50 seeds, the table, the assertion and the notes agree and
    name the diverged seeds; the regression by R x 10 that the mean missed is caught with
    the seeds that drove it."""
    sc = estim.scenarios.get("sine_pendulum")
    res = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(50))
    v = res.rows[0].consistency
    down = [int(s) for s in np.flatnonzero(res.diverged["ekf"])]
    assert v.diverged == down and len(down) >= 2 and not res.rows[0].consistent
    assert f"diverged {len(down)}/50" in res.table()
    listed = ", ".join(map(str, down[:8]))
    assert f"it diverged on {len(down)} of 50 seeds: {listed}" in " ".join(res.notes())
    with pytest.raises(AssertionError, match=rf"NEES not consistent \(overconfident\) at "
                                             rf"level 0.99; diverged on {len(down)} of 50 "
                                             rf"seeds: {listed}"):
        testing.assert_consistent(res)
    base = {"scenario": "sine_pendulum", "seeds": list(range(50)),
            "metrics": {"ekf": {"rmse": list(res.rmse["ekf"]), "nees": list(res.nees["ekf"])}}}
    worse = estim.compare(sc, {"ekf": _ekf(10.0)}, seeds=range(50))
    with pytest.raises(AssertionError, match=r"regression against the baseline \(estimators "
                                             r"ekf; seeds 0..49 \(50\)\) at confidence 0.95: "
                                             r"'ekf': rmse median .* seeds worse, .* better; "
                                             r"Wilcoxon signed-rank p = .*the largest rises: "
                                             r"seed \d+: \+"):
        testing.assert_no_regression(worse, base)
    same = testing.assert_no_regression(res, base)
    assert same["ekf"].p_value == 1.0 and same["ekf"].above == 0  # unchanged: exact
    with pytest.raises(ValueError, match=r"holds the estimators \['ekf'\], the comparison "
                                         r"\['EKF'\]: nothing to compare"):
        testing.assert_no_regression(estim.compare(sc, {"EKF": estim.EKF}, seeds=range(50)),
                                     base)
    for broken, why in (({**base, "metrics": [1, 2]}, "'metrics' must map"),
                        ({**base, "metrics": {"ekf": {"rmse": [0.1] * 3}}},
                         r"'metrics'\['ekf'\]\['rmse'\] must be a list of 50 numbers"),
                        ({"scenario": "x"}, "needs the keys")):
        with pytest.raises(ValueError, match=why):
            testing.assert_no_regression(res, broken)


def test_messages_and_equivalence(vdp):
    res = estim.compare(vdp, {"ekf": estim.EKF, "jit": lambda m, t: estim.EKF(m, **t, jit=True),
                              "R2": _ekf(2.0)}, seeds=range(40))
    gain = testing.assert_better(res, "ekf", "R2")
    d = res.rmse["R2"] - res.rmse["ekf"]
    walsh = [(d[i] + d[j]) / 2 for i in range(40) for j in range(i, 40)]
    assert gain.location == pytest.approx(np.median(walsh)) and gain.mean == pytest.approx(
        d.mean())
    assert gain.p_value == pytest.approx(wilcoxon(d, alternative="greater").pvalue)
    with pytest.raises(AssertionError, match=r"'R2' is not shown better than 'ekf' in rmse "
                                             r"at confidence 0.95 \(40 paired seeds\): "
                                             r"Wilcoxon signed-rank p = .*the seeds where "
                                             r"'R2' did worst"):
        testing.assert_better(res, "R2", "ekf")
    assert testing.assert_better(res, "ekf", "R2", test="t").p_value == pytest.approx(
        ttest_1samp(d, 0, alternative="greater").pvalue)
    testing.assert_equivalent(res, "jit", "ekf", tolerance=1e-6)  # the same numbers
    with pytest.raises(AssertionError, match="not shown equivalent .* within \\+-0.01"):
        testing.assert_equivalent(res, "ekf", "R2", tolerance=0.01)
    testing.assert_equivalent(res, "jit", "ekf", metric="nees", tolerance=1e-6)
    with pytest.raises(ValueError, match="metric must be one of 'rmse', 'nees', got 'rsme'.*"
                                         "did you mean 'rmse'"):
        testing.assert_better(res, "ekf", "R2", metric="rsme")
    with pytest.raises(ValueError, match="test must be one of 'wilcoxon', 'sign', 't', got "
                                         "'wilcox'.*did you mean 'wilcoxon'"):
        testing.assert_better(res, "ekf", "R2", test="wilcox")
    with pytest.raises(ValueError, match=r"b: 'ukf' is not in the comparison; its estimators "
                                         r"are \['ekf', 'jit', 'R2'\]"):
        testing.assert_better(res, "ekf", "ukf")
    with pytest.raises(ValueError, match=r"confidence must be in \(0, 1\), got 1.5"):
        testing.assert_better(res, "ekf", "R2", confidence=1.5)
    with pytest.raises(TypeError, match="comparison must be an estim.Comparison"):
        testing.assert_better([1, 2], "a", "b")
    few = {"a": [1.0, 2, 3, 4], "b": [2.0, 3, 4, 5]}
    with pytest.raises(ValueError, match=r"a paired wilcoxon test at confidence 0.95 needs at "
                                         r"least 5 seeds .* got 4 \(its smallest p-value "
                                         r"with 4 seeds is 0.0625"):
        testing.assert_better(few, "a", "b")
    testing.assert_better(few, "a", "b", test="t")


def test_causes_first():
    """Too few usable seeds: the message starts with what the runs raised."""
    vdp = estim.scenarios.get("van_der_pol", n_steps=20)

    def unfinished(y, u):
        raise NotImplementedError("exercise 3")

    from estim import adapters

    student = adapters.from_function(unfinished, vdp.model, name="student")
    res = estim.compare(vdp, {"student": student, "estim": estim.EKF}, seeds=range(5))
    with pytest.raises(ValueError, match=r"^'student' raised on 5 of 5 seeds \(seed 0: "
                                         r"NotImplementedError: exercise 3\): a paired "
                                         r"wilcoxon test .* got 0"):
        testing.assert_equivalent(res, "student", "estim", tolerance=1e-6)


def test_consistency(vdp):
    """The tuned EKF passes at level 0.99 (over seeds, from the logs or the per-seed
    scores, and on one log by batch means), with the table's verdict; one told R = 0.2
    (the truth 1) fails, naming the steps that contribute most."""
    good = estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(20), keep_logs=True,
                         burn_in=12)
    bare = estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(20), burn_in=12)  # no logs
    for result in (good, bare):
        v = testing.assert_consistent(result)
        assert v is result.rows[0].consistency and v.consistent and result.rows[0].consistent
        assert 0.85 < v.nees_mean < 1.15 and v.diverged == []
    from_logs = testing.assert_consistent(good.logs["ekf"], burn_in=12)
    assert from_logs.mean_level == pytest.approx(good.rows[0].consistency.mean_level)
    assert testing.assert_consistent(good.logs["ekf"], nis=True).consistent
    one = testing.assert_consistent(good.logs["ekf"][0])  # batch means
    assert one.units == "batches of steps" and one.n == 10
    bad = estim.compare(vdp, {"ekf": _ekf(0.2)}, seeds=range(20), keep_logs=True)
    assert bad.rows[0].consistency.grade() == "overconfident"
    with pytest.raises(AssertionError, match=r"NEES not consistent \(overconfident\) at level "
                                             r"0.99; mean chi-square level 0\.\d+ over 20 seeds"
                                             r".*the steps that contribute most"):
        testing.assert_consistent(bad, burn_in=12)
    with pytest.raises(AssertionError, match=r"NEES not consistent \(overconfident\)"):
        testing.assert_consistent(bad)
    with pytest.raises(ValueError, match=r"level must be in \(0, 1\), got 0"):
        testing.assert_consistent(good, level=0)
    with pytest.raises(ValueError, match="a Comparison of 2 estimators"):
        testing.assert_consistent(estim.compare(vdp, {"a": estim.EKF, "b": estim.UKF},
                                                seeds=range(2)))


def test_one_seed_that_diverged_is_not_consistent():
    """With one seed the old column said "yes" at any NEES: a diverged run is named."""
    sc = estim.scenarios.get("sine_pendulum")
    res = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(60))
    seed = int(np.flatnonzero(res.diverged["ekf"])[0])
    one = estim.compare(sc, {"ekf": estim.EKF}, seeds=[seed])
    assert one.rows[0].consistency.grade() == "diverged 1/1"
    with pytest.raises(AssertionError, match=rf"diverged on 1 of 1 seed: {seed} "):
        testing.assert_consistent(one)


def test_assert_close(vdp):
    log = estim.simulate(vdp, estim.EKF(vdp.model, **vdp.tuning), seed=0)
    record = (log.y, log.u)
    testing.assert_close(estim.EKF(vdp.model, **vdp.tuning),
                         estim.EKF(vdp.model, **vdp.tuning, jit=True), record, atol=1e-12)
    with pytest.raises(AssertionError, match=r"x_hat differs first at sample 1 \(t=0\.1\)"):
        testing.assert_close(estim.EKF(vdp.model, **vdp.tuning),
                             estim.UKF(vdp.model, **vdp.tuning), record, atol=1e-9)
    with pytest.raises(TypeError, match="b must be an estim estimator"):
        testing.assert_close(estim.EKF(vdp.model, **vdp.tuning), object(), record)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=3, max_size=40), st.integers(0, 39),
       st.floats(0.0, 1.0))
def test_no_seed_moves_the_level_by_more_than_its_share(levels, which, value):
    """The verdict does not depend on the seeds' order, and one seed, whatever its value
    (short of diverging), moves the mean level by at most 1/S."""
    S = len(levels)
    ratio, down = np.ones(S), np.zeros(S, dtype=bool)
    v = verdicts.consistency(ratio, levels, down, list(range(S)))
    order = np.random.default_rng(S).permutation(S)
    w = verdicts.consistency(ratio, np.asarray(levels)[order], down, list(order))
    assert w.consistent == v.consistent and w.mean_level == pytest.approx(v.mean_level)
    moved = list(levels)
    moved[which % S] = value
    u = verdicts.consistency(ratio, moved, down, list(range(S)))
    assert abs(u.mean_level - v.mean_level) <= 1 / S + 1e-12
