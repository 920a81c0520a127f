"""estim.testing: the assertions' measured error rates on van der Pol, their messages,
and their errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import binomtest

import estim
from estim import testing

SETS = 400


def _ekf(R_factor: float = 1.0):
    return lambda m, t: estim.EKF(m, **{**t, "R": R_factor * np.asarray(t["R"])})


@pytest.fixture(scope="module")
def vdp():
    return estim.scenarios.get("van_der_pol")


def _passes(a_sets, b_sets, **kw) -> int:
    n = 0
    for a, b in zip(a_sets, b_sets, strict=True):
        try:
            testing.assert_better({"a": a, "b": b}, "a", "b", **kw)
            n += 1
        except AssertionError:
            pass
    return n


def test_false_alarm_and_detection_rates(vdp):
    """False alarms: the same EKF on two independent blocks of 20 seeds (its expected RMSE
    the same) is declared better in a fraction of 400 seed sets consistent with the
    nominal 5 % (the 99 % Clopper-Pearson interval of the observed rate reaches 5 %).
    Detection: R doubled costs the EKF 5.5 % RMSE; with 50 seeds per set the tuned
    filter is declared better in at least 80 % of 400 sets."""
    S = 20
    res = estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(2 * S * SETS))
    r = res.rmse["ekf"].reshape(SETS, 2, S)
    false = _passes(r[:, 0], r[:, 1])
    ci = binomtest(false, SETS).proportion_ci(0.99)
    assert ci.low <= 0.05 < ci.high + 0.05, (false / SETS, ci)
    S = 50
    res = estim.compare(vdp, {"tuned": estim.EKF, "mistuned": _ekf(2.0)},
                        seeds=range(10_000, 10_000 + S * SETS))
    a, b = (res.rmse[k].reshape(SETS, S) for k in ("tuned", "mistuned"))
    assert 1.04 < b.mean() / a.mean() < 1.07  # a true difference of about 5 %
    detected = _passes(a, b)
    assert detected >= 0.8 * SETS, detected / SETS


def test_messages_and_equivalence(vdp):
    res = estim.compare(vdp, {"ekf": estim.EKF, "jit": lambda m, t: estim.EKF(m, **t, jit=True),
                              "R2": _ekf(2.0)}, seeds=range(40))
    gain = testing.assert_better(res, "ekf", "R2")
    assert gain == pytest.approx(np.mean(res.rmse["R2"] - res.rmse["ekf"]))
    with pytest.raises(AssertionError, match=r"'R2' is not shown better than 'ekf' in rmse "
                                             r"at confidence 0.95 \(40 paired seeds\): mean "
                                             r"improvement -.*the seeds where 'R2' did worst"):
        testing.assert_better(res, "R2", "ekf")
    testing.assert_equivalent(res, "jit", "ekf", tolerance=1e-6)  # the same numbers
    with pytest.raises(AssertionError, match="not shown equivalent .* within \\+-0.01"):
        testing.assert_equivalent(res, "ekf", "R2", tolerance=0.01)
    testing.assert_equivalent(res, "jit", "ekf", metric="nees", tolerance=1e-6)
    with pytest.raises(ValueError, match="metric must be one of 'rmse', 'nees', got 'rsme'.*"
                                         "did you mean 'rmse'"):
        testing.assert_better(res, "ekf", "R2", metric="rsme")
    with pytest.raises(ValueError, match=r"b: 'ukf' is not in the comparison; its estimators "
                                         r"are \['ekf', 'jit', 'R2'\]"):
        testing.assert_better(res, "ekf", "ukf")
    with pytest.raises(ValueError, match=r"confidence must be in \(0, 1\), got 1.5"):
        testing.assert_better(res, "ekf", "R2", confidence=1.5)
    with pytest.raises(TypeError, match="comparison must be an estim.Comparison"):
        testing.assert_better([1, 2], "a", "b")


def test_consistency(vdp):
    """The tuned EKF passes at level 0.99 (over seeds, from the logs or the per-seed
    NEES, and on one log by batch means); one told R = 0.2 (the truth 1) fails, naming
    the steps that contribute most."""
    good = estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(20), keep_logs=True,
                         burn_in=12)
    bare = estim.compare(vdp, {"ekf": estim.EKF}, seeds=range(20), burn_in=12)  # no logs
    for result in (good, good.logs["ekf"], bare):
        assert 0.85 < testing.assert_consistent(result) < 1.15
    assert np.isfinite(testing.assert_consistent(good.logs["ekf"][0]))  # batch means
    bad = estim.compare(vdp, {"ekf": _ekf(0.2)}, seeds=range(20), keep_logs=True)
    with pytest.raises(AssertionError, match=r"NEES per state dimension over 20 seeds: 2\.\d+.*"
                                             r"overconfident; the steps that contribute most"):
        testing.assert_consistent(bad)
    with pytest.raises(ValueError, match=r"level must be in \(0, 1\), got 0"):
        testing.assert_consistent(good, level=0)
    with pytest.raises(ValueError, match="a Comparison of 2 estimators"):
        testing.assert_consistent(estim.compare(vdp, {"a": estim.EKF, "b": estim.UKF},
                                                seeds=range(2)))


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
