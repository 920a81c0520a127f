"""Monte Carlo comparisons: serial, parallel and dask runs agree; tables and reprs."""

from __future__ import annotations

import importlib
import itertools

import numpy as np
import pytest

import estim
from estim import cli

compare_module = importlib.import_module("estim.compare")  # estim.compare is the function


def _estimators():
    return {"ekf": estim.EKF,
            "mhe": lambda m, t: estim.MHE(m, horizon=8, solver="gauss-newton", **t)}


def _check_same(a, b):
    for ra, rb in zip(a.rows, b.rows, strict=True):
        assert ra.name == rb.name
        np.testing.assert_equal((ra.rmse_mean, ra.nees_mean, ra.rmse_per_state, ra.failures),
                                (rb.rmse_mean, rb.nees_mean, rb.rmse_per_state, rb.failures))
    for name in a.rmse:
        np.testing.assert_array_equal(a.rmse[name], b.rmse[name])


def test_parallel_equals_serial():
    sc = estim.scenarios.van_der_pol(n_steps=60)
    serial = estim.compare(sc, _estimators(), seeds=range(4))
    parallel = estim.compare(sc, _estimators(), seeds=range(4), n_jobs=2,
                             min_parallel_seconds=0)
    assert parallel.parallel.startswith("parallel (forced")
    _check_same(serial, parallel)
    # and the numbers are those of single simulate runs
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2)
    assert serial.rmse["ekf"][2] == float(estim.rmse(log))


def test_local_dask_cluster_equals_serial():
    distributed = pytest.importorskip("dask.distributed")
    sc = estim.scenarios.van_der_pol(n_steps=40)
    serial = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(3))
    with distributed.Client(n_workers=2, threads_per_worker=1, processes=False,
                            dashboard_address=None):
        on_dask = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(3), n_jobs=2,
                                backend="dask", min_parallel_seconds=0, batch=False)
    assert on_dask.parallel.startswith("parallel")
    _check_same(serial, on_dask)


def test_small_workload_runs_serially(monkeypatch):
    # workers that take a second to start do not pay for a few EKF runs
    monkeypatch.setattr(compare_module, "_startup", lambda backend, workers: (1.0, False))
    sc = estim.scenarios.van_der_pol(n_steps=60)
    serial = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(4))
    assert serial.parallel == "" and "Runs:" not in serial.table()
    res = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(4), n_jobs=2, batch=False)
    assert res.parallel.startswith("serial: 2 runs estimated at ")
    assert "starting cold workers: about 1 s" in res.parallel
    assert "Runs: serial:" in res.table() and "Runs: serial:" in res._repr_html_()
    _check_same(serial, res)
    # every run among the timed first ones
    assert estim.compare(sc, {"ekf": estim.EKF}, seeds=[3, 1], n_jobs=2,
                         batch=False).parallel == (
        "serial: every run was one of the first runs, timed in this process")


def test_forced_parallel_equals_serial_bit_for_bit():
    sc = estim.scenarios.van_der_pol(n_steps=50)
    est = {**_estimators(), "broken": lambda m, t: estim.EKF(m, **{**t, "R": -1.0})}
    seeds = [7, 3, 11, 0, 5, 2, 9]
    serial = estim.compare(sc, est, seeds=seeds, keep_logs=True)
    for backend in ("loky", "threading"):
        par = estim.compare(sc, est, seeds=seeds, n_jobs=2, backend=backend, keep_logs=True,
                            min_parallel_seconds=0)
        assert par.parallel.startswith("parallel (forced, ")
        _check_same(serial, par)
        assert par.rows[2].errors == serial.rows[2].errors and len(par.rows[2].errors) == 7
        for name in ("ekf", "mhe"):
            for a, b in zip(serial.logs[name], par.logs[name], strict=True):
                np.testing.assert_array_equal(a.x_hat, b.x_hat)
                np.testing.assert_array_equal(a.P, b.P)
    with pytest.raises(ValueError, match="min_parallel_seconds"):
        estim.compare(sc, {"ekf": estim.EKF}, n_jobs=2, min_parallel_seconds=-1)


def test_plan_splits_by_cost():
    # (setup, seconds per run, runs): "b" costs 4x "a" per run
    costs = {"a": (0.2, 0.01, 200), "b": (0.5, 0.04, 100), "c": (0.0, 0.0, 3)}
    tasks = compare_module._plan(costs, 2)
    for name, (_, _, n) in costs.items():  # every run once, in order
        spans = [(a, b) for k, a, b in tasks if k == name]
        assert spans[0][0] == 0 and spans[-1][1] == n
        assert all(b0 == a1 for (_, b0), (a1, _) in itertools.pairwise(spans))
    cost = [(b - a) * costs[k][1] for k, a, b in tasks if costs[k][1] > 0]
    total = 200 * 0.01 + 100 * 0.04
    # guided: the first chunk is half a worker's share, then they shrink to a tenth
    assert cost[0] == pytest.approx(total / 4, rel=0.05)
    assert all(c2 <= max(c1, 1.5 * total / 20) for c1, c2 in itertools.pairwise(cost))
    assert min(cost) >= total / 20 * 0.9 and len(tasks) < 20
    # the estimators interleave, the one with more work left first
    assert [k for k, _, _ in tasks[:4]] == ["b", "b", "a", "b"]
    assert {k for k, _, _ in tasks[-4:]} >= {"a", "b"}
    # the two workers finish within a small chunk of each other
    makespan = compare_module._makespan(tasks, costs, 2)
    assert makespan <= (total + 2 * 0.7) / 2 + total / 20
    # one worker: the same runs; nothing to run: no chunk
    assert compare_module._makespan(compare_module._plan(costs, 1), costs, 1) >= total
    assert compare_module._plan({"a": (0.1, 0.01, 0)}, 2) == []


def test_table_consistency_and_logs():
    sc = estim.scenarios.van_der_pol()
    res = estim.compare(sc, {"ekf": estim.EKF,
                             "ekf-bad-R": lambda m, t: estim.EKF(m, **{**t, "R": 0.01})},
                        seeds=range(8), keep_logs=True)
    ok, bad = res.rows
    assert ok.consistent and not bad.consistent and bad.nees_mean > 3
    assert len(res.logs["ekf"]) == 8 and isinstance(res.logs["ekf"][0], estim.Log)
    text = res.table()
    assert "NEES/n" in text and "ekf-bad-R" in text
    assert "<table>" in res._repr_html_()
    frame = res.to_pandas()
    assert list(frame.index) == ["ekf", "ekf-bad-R"]


def test_ready_instance_is_copied():
    sc = estim.scenarios.van_der_pol(n_steps=30)
    inst = estim.EKF(sc.model, **sc.tuning)
    a = estim.compare(sc, {"ekf": inst}, seeds=range(2))
    b = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(2))
    _check_same(a, b)


def test_compare_bad_input():
    sc = estim.scenarios.van_der_pol(n_steps=10)
    with pytest.raises(TypeError, match=r"scenario: compare on a bare Model needs \['x0', "
                                        r"'n_steps', 'Q', 'R', 'tuning'\] as keywords"):
        estim.compare(sc.model, {"ekf": estim.EKF})
    with pytest.raises(TypeError, match="scenario must be an estim.Scenario or an estim.Model"):
        estim.compare("van_der_pol", {"ekf": estim.EKF})
    with pytest.raises(ValueError, match="at least one estimator"):
        estim.compare(sc, {})
    with pytest.raises(ValueError, match="at least one seed"):
        estim.compare(sc, {"ekf": estim.EKF}, seeds=[])
    with pytest.raises(TypeError, match="must be a class, a factory"):
        estim.compare(sc, {"ekf": 3})
    with pytest.raises(ValueError, match="n_jobs"):
        estim.compare(sc, {"ekf": estim.EKF}, n_jobs=0)


def test_cli_observe(capsys):
    assert cli.main(["observe", "martinelli_simple"]) == 0
    out = capsys.readouterr().out
    assert "rank 2 of 3" in out and "jointly observable: (phi_R, theta_R)" in out
    assert cli.main(["observe", "nonexistent"]) == 2


def test_log_html_repr():
    sc = estim.scenarios.van_der_pol(n_steps=20)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    html = log._repr_html_()
    assert "RMSE" in html and "x_hat" in html
    rep = estim.observability.analyze(estim.models.martinelli_simple())
    assert "jointly observable" in rep._repr_html_()


@pytest.mark.parametrize("kind", ["pf", "pf-compiled", "enkf"])
def test_a_randomised_estimator_draws_its_own_stream_on_every_seed(kind):
    """A particle filter or an EnKF restarts its stream at every reset; over the seeds of
    a comparison each run must still draw its own numbers, or the runs share their Monte
    Carlo error and the verdicts over seeds count one draw many times. On a noiseless
    plant every seed's record is the same, so whatever differs between two runs is the
    estimator's own randomness: it differs across seeds, and a second comparison repeats
    it bit for bit."""
    m = estim.Model(states=["p", "v"], outputs=["y"], dt=0.1,
                    dynamics=lambda x, u, p: np.array([[1.0, 0.1], [0.0, 1.0]]) @ x,
                    output=lambda x, u, p: x[:1])
    tuning = {"Q": np.diag([1e-3, 1e-2]), "R": 0.1, "x0": [0.0, 1.0], "P0": np.eye(2)}
    sc = estim.Scenario("still", m, x0=[0.0, 1.0], n_steps=20, Q=np.zeros((2, 2)),
                        R=1e-24, tuning=tuning)
    if kind == "enkf":
        make = estim.EnKF(m, **tuning, n_ensemble=20, seed=3)
    else:
        make = estim.ParticleFilter(m, **tuning, n_particles=50, seed=3,
                                    jit=kind == "pf-compiled")
    runs = [estim.compare(sc, {"f": make}, seeds=[0, 1, 2], keep_logs=True, progress=False)
            for _ in range(2)]
    logs = runs[0].logs["f"]
    np.testing.assert_allclose(logs[0].y, logs[1].y, rtol=0, atol=1e-11)  # one record
    assert np.abs(logs[0].x_hat - logs[1].x_hat).max() > 1e-3
    assert np.abs(logs[1].x_hat - logs[2].x_hat).max() > 1e-3
    for a, b in zip(logs, runs[1].logs["f"], strict=True):
        np.testing.assert_array_equal(a.x_hat, b.x_hat)
    # the estimator keeps its own seed: a run of its own is what it was
    assert make.seed == 3
