"""The batched Monte Carlo path (estim.batch): the plant of every seed and a filter over
every record in compiled calls give exactly what simulate's loop gives, seed by seed."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest
from models import two_tanks

import estim
from estim import batch
from estim._compile import compiler
from estim.solvers import seeds

FILTERS = {"EKF": estim.EKF, "UKF": estim.UKF,
           "EKF gated": lambda m, t: estim.EKF(m, **t, gate=1e-3),
           "UKF clipped": lambda m, t: estim.UKF(m, **t, clip=True, points="julier")}
LOG_KEYS = ("t", "x", "y", "u", "x_hat", "P", "nis", "status", "success", "iterations", "cost")


def _inputs_scenario(hold: str) -> estim.Scenario:
    m = estim.Model(states=["q", "v"], outputs=["q"], inputs=["u"],
                    ode=lambda x, u, p: ca.vertcat(x[1], -p["k"] * x[0] - 1.4 * x[1] + 3 * u[0]),
                    output=lambda x, u, p: x[0] + 0.1 * u[0], params={"k": 49.0}, dt=0.05,
                    hold=hold, name=f"spring ({hold})")
    T = 120
    return estim.Scenario(f"spring {hold}", m, x0=[0.0, 0.0], n_steps=T, Q=1e-4, R=1e-3,
                          inputs=np.sin(0.3 * np.arange(T))[:, None],
                          plant_changes=[(2.0, {"k": 30.0})],
                          tuning=dict(Q=1e-4, R=1e-3, x0=[0.2, 0.0], P0=0.5))


def _tanks() -> estim.Scenario:
    """Square-root outflows: an estimate clipped to an empty tank makes the EKF's update
    non-finite for some seeds (recovered by re-anchoring, which the batch cannot do)."""
    m = two_tanks()
    return estim.Scenario("tanks", m, x0=[0.5, 0.5], n_steps=60, Q=1e-4, R=0.01,
                          inputs=lambda t: [0.3], clip=True,
                          tuning=dict(Q=1e-4, R=0.01, x0=[0.5, 0.05], P0=1.0))


SCENARIOS = {
    "van_der_pol": lambda: estim.scenarios.van_der_pol(n_steps=150),
    "batch_reactor": lambda: estim.scenarios.batch_reactor(n_steps=200),
    "spring zoh": lambda: _inputs_scenario("zoh"),
    "spring foh": lambda: _inputs_scenario("foh"),
    "tanks": _tanks,
}


def _same(a: estim.Comparison, b: estim.Comparison) -> None:
    """Two comparisons agree number for number (step times aside), logs included."""
    assert [r.name for r in a.rows] == [r.name for r in b.rows]
    for ra, rb in zip(a.rows, b.rows, strict=True):
        for key, va in ra.__dict__.items():
            if key in ("step_median", "step_p90"):
                continue
            vb = rb.__dict__[key]
            if isinstance(va, float) and np.isnan(va):
                assert np.isnan(vb), (ra.name, key)
            elif isinstance(va, dict):
                assert va.keys() == vb.keys()
                np.testing.assert_array_equal(list(va.values()), list(vb.values()))
            else:
                assert va == vb, (ra.name, key, va, vb)
    for name in a.rmse:
        np.testing.assert_array_equal(a.rmse[name], b.rmse[name])
    for name in a.logs:
        for la, lb in zip(a.logs[name], b.logs[name], strict=True):
            assert (la is None) == (lb is None)
            if la is None:
                continue
            for key in LOG_KEYS:
                va, vb = getattr(la, key), getattr(lb, key)
                if va.dtype == object:
                    assert list(va) == list(vb), (name, key)
                else:
                    np.testing.assert_array_equal(va, vb, err_msg=f"{name}: {key}")


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_the_plant_batch_is_simulate(name):
    sc = SCENARIOS[name]()
    seeds = [0, 3, 11]
    plant = batch.simulate_plant(sc, seeds)
    assert plant.finite.all()
    est = estim.EKF(sc.model, **sc.tuning)
    for i, s in enumerate(seeds):
        log = estim.simulate(sc, est, seed=s, warn=False)
        np.testing.assert_array_equal(plant.x[i], log.x)
        np.testing.assert_array_equal(plant.y[i], log.y)
        np.testing.assert_array_equal(plant.u, log.u)
        np.testing.assert_array_equal(plant.t, log.t)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_compare_batched_equals_per_run(name):
    sc = SCENARIOS[name]()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", estim.EstimationWarning)
        a = estim.compare(sc, FILTERS, seeds=range(5), keep_logs=True, burn_in=3)
        b = estim.compare(sc, FILTERS, seeds=range(5), keep_logs=True, burn_in=3,
                          batch=False)
    assert a.batched.startswith("EKF (") and "UKF clipped (" in a.batched
    assert "Batched: " in a.table() and "Batched: " in a._repr_html_()
    assert b.batched == "" and "Batched" not in b.table()
    _same(a, b)
    if name == "tanks":  # some seeds' filters failed: those ran per run
        assert any(r.failures for r in a.rows)
    if name == "van_der_pol":
        assert any(r.flagged for r in a.rows if r.name == "EKF gated")


def test_per_run_estimators_and_plants_that_blow_up():
    """An MHE next to batched filters runs per run; a plant that leaves the finite
    numbers is the per-run path's error for every estimator."""
    m = estim.Model(states=["x"], outputs=["y"], dynamics=lambda x, u, p: x * x, dt=1.0,
                    output=lambda x, u, p: x, name="square")
    sc = estim.Scenario("square", m, x0=[1.0], n_steps=40, Q=0.01 ** 2, R=0.1,
                        tuning=dict(Q=1e-4, R=0.1, x0=[1.0], P0=0.1))
    est = {"EKF": estim.EKF, "MHE": lambda mm, t: estim.MHE(mm, horizon=5, **t)}
    a = estim.compare(sc, est, seeds=range(8), keep_logs=True)
    b = estim.compare(sc, est, seeds=range(8), keep_logs=True, batch=False)
    assert a.batched.startswith("EKF (") and "MHE" not in a.batched
    _same(a, b)
    errors = a.rows[0].errors
    assert errors and all(e.startswith("FloatingPointError: the plant state became "
                                       "non-finite") for e in errors.values())
    assert 0 < a.rows[0].runs < 8
    assert a.logs["EKF"][min(errors)] is not None  # the steps before the blow-up


def test_when_the_batch_does_not_apply():
    sc = estim.scenarios.van_der_pol(n_steps=30)
    closed = estim.Scenario("closed loop", sc.model, x0=sc.x0, n_steps=30, Q=sc.Q, R=sc.R,
                            controller=lambda t, x: [], tuning=sc.tuning)
    res = estim.compare(closed, {"EKF": estim.EKF}, seeds=range(2))
    assert res.batched == ""
    with pytest.raises(ValueError, match="batch=True.*controller"):
        estim.compare(closed, {"EKF": estim.EKF}, seeds=range(2), batch=True)
    with pytest.raises(TypeError, match="batch"):
        estim.compare(sc, {"EKF": estim.EKF}, batch="yes")
    with pytest.raises(ValueError, match="cannot be batched"):
        batch.simulate_plant(closed, [0])


@pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")
def test_compiled_batches_equal_interpreted_ones(monkeypatch, tmp_path):
    """Above COMPILE_MIN_SAMPLES the plant and the filters are compiled to C: the same
    numbers, bit for bit (no fast-math, no contraction into fused multiply-adds)."""
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(tmp_path / "cache"))
    sc = estim.scenarios.van_der_pol(n_steps=100)
    est = {"EKF": estim.EKF, "UKF": estim.UKF}
    monkeypatch.setattr(seeds, "COMPILE_MIN_SAMPLES", 10 ** 12)
    interpreted = estim.compare(sc, est, seeds=range(4), keep_logs=True)
    monkeypatch.setattr(seeds, "COMPILE_MIN_SAMPLES", 0)
    compiled = estim.compare(sc, est, seeds=range(4), keep_logs=True)
    assert "interpreted" in interpreted.batched and "compiled" not in interpreted.batched
    assert compiled.batched.count("compiled") == 3  # the plant and both filters
    _same(interpreted, compiled)
    assert len(list((tmp_path / "cache").glob("*.so"))) == 3


def test_without_a_compiler_the_batch_is_interpreted(monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setattr(seeds, "COMPILE_MIN_SAMPLES", 0)
    monkeypatch.setattr(seeds, "_MAPPED", type(seeds._MAPPED)())
    sc = estim.scenarios.van_der_pol(n_steps=60)
    res = estim.compare(sc, {"EKF": estim.EKF}, seeds=range(3))
    assert "interpreted (no C compiler found ($CC = '/nonexistent/cc')" in res.batched
    ref = estim.compare(sc, {"EKF": estim.EKF}, seeds=range(3), batch=False)
    _same(res, ref)


class _Counting(estim.EKF):
    """An EKF whose step does something of its own: it must be run step by step."""

    steps = 0

    def _step(self, y, u, first):
        type(self).steps += 1
        return super()._step(y, u, first)


def test_a_filter_with_its_own_step_runs_per_run():
    sc = estim.scenarios.van_der_pol(n_steps=30)
    res = estim.compare(sc, {"EKF": estim.EKF, "counting": _Counting}, seeds=range(3))
    assert res.batched.startswith("EKF (") and "counting" not in res.batched
    assert _Counting.steps == 3 * 30
    np.testing.assert_array_equal(res.rmse["EKF"], res.rmse["counting"])
