"""Monte Carlo comparisons: serial, parallel and dask runs agree; tables and reprs."""

from __future__ import annotations

import numpy as np
import pytest

import estim
from estim import cli


def _estimators():
    return {"ekf": estim.EKF,
            "mhe": lambda m, t: estim.MHE(m, horizon=8, solver="gauss-newton", **t)}


def _check_same(a, b):
    for ra, rb in zip(a.rows, b.rows, strict=True):
        assert ra.name == rb.name
        assert ra.rmse_mean == rb.rmse_mean and ra.nees_mean == rb.nees_mean
        assert ra.rmse_per_state == rb.rmse_per_state and ra.failures == rb.failures
    for name in a.rmse:
        np.testing.assert_array_equal(a.rmse[name], b.rmse[name])


def test_parallel_equals_serial():
    sc = estim.scenarios.van_der_pol(n_steps=60)
    serial = estim.compare(sc, _estimators(), seeds=range(4))
    parallel = estim.compare(sc, _estimators(), seeds=range(4), n_jobs=2)
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
                                backend="dask")
    _check_same(serial, on_dask)


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
    with pytest.raises(TypeError, match="scenario must be"):
        estim.compare(sc.model, {"ekf": estim.EKF})
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
