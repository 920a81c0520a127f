"""Log behaviour, exports and plots; metrics against their definitions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

import estim


@pytest.fixture(scope="module")
def log():
    sc = estim.scenarios.van_der_pol()
    return estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)


def test_log_shapes_time_major_never_squeezed():
    sc = estim.scenarios.batch_reactor(n_steps=50)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    T = 50
    assert log.t.shape == (T,) and log.x.shape == (T, 3) and log.y.shape == (T, 1)
    assert log.u.shape == (T, 0) and log.x_hat.shape == (T, 3) and log.P.shape == (T, 3, 3)
    assert log.solve_time.shape == (T,) and log.status.shape == (T,)
    np.testing.assert_allclose(log.t, 0.25 * np.arange(T))
    assert (log.solve_time > 0).all()
    assert len(log) == T and "x_hat" in log and "z" not in log


def test_course_style_logging():
    log = estim.Log()
    for k in range(4):
        log("y", [float(k)])
        log("x", np.full(3, k))
    assert log.y.shape == (4, 1) and log.x.shape == (4, 3)
    np.testing.assert_array_equal(log.x[:, 0], np.arange(4))
    log("x", np.zeros(3))
    assert log.x.shape == (5, 3)
    with pytest.raises(AttributeError, match="no series 'z'"):
        _ = log.z
    with pytest.raises(ValueError, match="key must be an identifier"):
        log("not a name", 1.0)


def test_appending_to_a_simulated_log(log):
    T = len(log)
    log("extra", 1.0)
    assert log.extra.shape == (1,)
    assert len(log) == T


def test_to_pandas(log):
    frame = log.to_pandas()
    assert len(frame) == len(log)
    assert {"x:x1", "x_hat:x2", "y:y1", "solve_time", "status"} <= set(frame.columns)
    np.testing.assert_array_equal(frame["x_hat:x1"].to_numpy(), log.x_hat[:, 0])


def test_plot_writes_png(log, tmp_path):
    path = tmp_path / "log.png"
    fig = log.plot(path)
    assert path.stat().st_size > 10_000
    assert len(fig.axes) == 2
    # both outputs measure a state directly: the measurements are drawn on its axes
    assert log.output_state == {0: 0, 1: 1}
    assert any(line.get_label() == "measurement" for line in fig.axes[0].lines)


def test_rmse_matches_definition(log):
    e = log.x_hat - log.x
    r = estim.rmse(log)
    assert float(r) == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-14)
    assert r.per_state["x2"] == pytest.approx(np.sqrt(np.mean(e[:, 1] ** 2)), rel=1e-14)
    r10 = estim.rmse(log, burn_in=10, states=["x1"])
    assert float(r10) == pytest.approx(np.sqrt(np.mean(e[10:, 0] ** 2)), rel=1e-14)
    assert "x1=" in repr(r)
    with pytest.raises(ValueError, match="burn_in"):
        estim.rmse(log, burn_in=-1)
    with pytest.raises(ValueError, match="not in the log"):
        estim.rmse(log, states=["q"])


def test_nees_matches_definition(log):
    e = log.x_hat - log.x
    expected = np.array([ek @ np.linalg.solve(Pk, ek) for ek, Pk in zip(e, log.P, strict=True)])
    np.testing.assert_allclose(estim.nees(log), expected, rtol=1e-12)
    assert estim.nis(log).shape == (len(log),)
    assert np.isfinite(estim.nis(log)).all()


def test_chi2_bounds_match_scipy():
    lo, hi = estim.chi2_bounds(3, 50, 0.95)
    assert lo == pytest.approx(stats.chi2.ppf(0.025, 150) / 50)
    assert hi == pytest.approx(stats.chi2.ppf(0.975, 150) / 50)


def test_nis_of_a_correct_linear_filter_is_chi2(linear):
    """On a linear-Gaussian model the innovations are white with covariance S:
    the NIS average over T samples lies in the 99.9 % chi2 interval."""
    sys = linear
    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    T = 3000
    log = estim.simulate(sys.model, est, x0=sys.x0, n_steps=T, Q=sys.Q, R=sys.R, seed=5)
    lo, hi = estim.chi2_bounds(2, T, 0.999)
    assert lo < np.mean(estim.nis(log)) < hi
    # the whole-record result holds the same NIS
    res = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0).filter(log.y, log.u)
    np.testing.assert_allclose(estim.nis(res, burn_in=10), estim.nis(log, burn_in=10),
                               rtol=1e-9)
    with pytest.raises(ValueError, match="nis needs a Log or a filter's result"):
        estim.nis(log.x_hat)


def test_convergence_time():
    log = estim.Log(state_names=["a"])
    log.set("t", np.arange(6) * 0.5)
    log.set("x", np.zeros((6, 1)))
    log.set("x_hat", np.array([[3.0], [1.0], [0.5], [0.05], [0.01], [0.0]]))
    assert estim.convergence_time(log, 0.1) == 1.5
    assert estim.convergence_time(log, 10.0) == 0.0
    log.set("x_hat", np.ones((6, 1)))
    assert estim.convergence_time(log, 0.1) == np.inf


def test_error_and_solve_time_plots(tmp_path):
    from estim.plotting import plot_errors, plot_solve_times

    sc = estim.scenarios.van_der_pol(n_steps=60)
    logs = {"ekf": estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0),
            "mhe": estim.simulate(sc, estim.MHE(sc.model, horizon=8, solver="gauss-newton",
                                                **sc.tuning), seed=0)}
    fig = plot_errors(logs, tmp_path / "err.png")
    assert (tmp_path / "err.png").stat().st_size > 10_000 and len(fig.axes) == 2
    # the band is drawn where the covariance exists: +-2 sigma of the EKF's P
    band = fig.axes[0].collections[0].get_paths()[0].vertices[:, 1]
    assert np.isclose(np.abs(band).max(), 2 * np.sqrt(logs["ekf"].P[:, 0, 0]).max())
    plot_solve_times(logs, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 10_000
    plot_errors(logs["ekf"])


def test_metrics_take_a_log_a_fit_or_arrays():
    """rmse/errors/convergence_time give the same numbers from a Log, from its arrays, and
    from a FitResult with the truth given; nees needs covariances and says so."""
    sc = estim.scenarios.van_der_pol()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    ref = estim.rmse(log)
    for same in (estim.rmse(log.x_hat, truth=log.x), estim.rmse(log.x_hat, truth=log),
                 estim.rmse(log, truth=log.x)):
        assert float(same) == float(ref)
    assert estim.rmse(log.x_hat, truth=log).per_state == ref.per_state
    assert list(estim.rmse(log.x_hat, truth=log.x).per_state) == ["x1", "x2"]
    np.testing.assert_array_equal(estim.errors(log.x_hat, 5, truth=log.x),
                                  estim.errors(log, 5))
    fit = estim.FullInformation(sc.model, **sc.tuning).fit(log.y)
    direct = np.sqrt(np.mean((fit.x - log.x) ** 2))
    assert float(estim.rmse(fit, truth=log)) == pytest.approx(direct, rel=1e-14)
    assert estim.convergence_time(fit, 0.5, truth=log) == \
        estim.convergence_time(fit.x, 0.5, truth=log)
    # one state as a 1-D array
    assert float(estim.rmse(log.x_hat[:, 0], truth=log.x[:, 0])) == \
        pytest.approx(ref.per_state["x1"], rel=1e-14)
    with pytest.raises(ValueError, match="truth is required"):
        estim.rmse(fit)
    with pytest.raises(ValueError, match="truth has shape"):
        estim.rmse(log.x_hat[1:], truth=log.x)
    e = fit.x - log.x  # a fit carries the covariance of every sample
    direct = np.einsum("ki,ki->k", e, np.linalg.solve(fit.P, e[..., None])[..., 0])
    np.testing.assert_allclose(estim.nees(fit, truth=log), direct, rtol=1e-12)
    with pytest.raises(ValueError, match="nees needs covariances"):
        estim.nees(fit.x, truth=log)
    with pytest.raises(TypeError, match="estimate must be"):
        estim.rmse({"x": 1}, truth=log)
