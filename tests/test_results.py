"""One protocol for every result that holds estimates over time: the filters' and
smoothers' whole-record results and the full-information fit work with the metrics,
the plots, ``to_pandas`` and :meth:`Log.from_estimates` as a :class:`~estim.Log` does,
and what is refused names what is accepted."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest

import estim
from estim.estimators.filtering import Estimates
from estim.plotting import plot_errors, plot_estimates, plot_smoothing

matplotlib.use("Agg")

Q, R = np.diag([0.0, 0.06]), 0.01
TUNING = {"Q": Q, "R": R, "x0": [1.2, 0.0], "P0": 0.09}


@pytest.fixture(scope="module")
def record():
    """The textbook pendulum (noise on the angular rate only), 120 samples, and the
    EKF's replay of it: the truth and the reference a filter result must equal."""
    m = estim.models.sine_pendulum()
    log = estim.simulate(m, estim.EKF(m, **TUNING), x0=[1.5, 0.0], n_steps=120, Q=Q, R=R,
                         seed=3)
    return m, log


@pytest.fixture(scope="module")
def results(record):
    m, log = record
    ekf = estim.EKF(m, **TUNING)
    pf = estim.ParticleFilter(m, **TUNING, n_particles=300, seed=0)
    return {
        "EKF.filter": ekf.filter(log.y),
        "EKF.smooth": ekf.smooth(log.y),
        "UKF.smooth": estim.UKF(m, **TUNING).smooth(log.y),
        "EnKF.filter": estim.EnKF(m, **TUNING, n_ensemble=100, seed=0).filter(log.y),
        "ParticleFilter.filter": pf.filter(log.y),
        "ParticleFilter.smooth": pf.smooth(log.y, n_paths=50),
        "FullInformation.fit": estim.FullInformation(m, **TUNING).fit(log.y),
    }


def test_every_result_is_scored_as_a_log_is(record, results):
    m, log = record
    for name, res in results.items():
        assert isinstance(res, Estimates), name
        assert res.state_names == ("theta", "omega"), name
        np.testing.assert_allclose(res.t, log.t, rtol=0, atol=1e-12, err_msg=name)
        err = res.x - log.x
        assert np.array_equal(estim.errors(res, truth=log), err), name
        r = estim.rmse(res, truth=log)
        assert float(r) == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-12), name
        assert set(r.per_state) == {"theta", "omega"}, name
        e = estim.nees(res, truth=log.x)  # the truth as an array
        expect = np.einsum("ti,tij,tj->t", err, np.linalg.inv(res.P), err)
        np.testing.assert_allclose(e, expect, rtol=1e-9, err_msg=name)
    # the whole-record filter is replay: the same scores to the last digits
    assert float(estim.rmse(results["EKF.filter"], truth=log)) == \
        pytest.approx(float(estim.rmse(log)), rel=1e-12)


def test_reprs_say_what_a_result_is(results):
    assert repr(results["EKF.smooth"]) == "<SmoothResult: T=120; states theta, omega; 120 ok>"
    assert repr(results["FullInformation.fit"]).startswith(
        "<FitResult: T=120; states theta, omega; status 'ok'; cost ")
    assert "log_likelihood" in repr(results["ParticleFilter.filter"])


def test_to_pandas_and_from_estimates(record, results):
    pytest.importorskip("pandas")
    m, log = record
    for name, res in results.items():
        frame = res.to_pandas()
        assert frame.index.name == "t" and len(frame) == len(log), name
        assert list(frame.columns) == ["x_hat:theta", "x_hat:omega", "sd:theta", "sd:omega"]
        np.testing.assert_array_equal(frame["sd:omega"], np.sqrt(res.P[:, 1, 1]))
        as_log = estim.Log.from_estimates(res, log, name=name)
        assert as_log.estimator == name and np.array_equal(as_log.x, log.x)
        assert float(estim.rmse(as_log)) == float(estim.rmse(res, truth=log))
    status = estim.Log.from_estimates(results["EKF.smooth"]).status
    assert len(status) == len(log) and "x" not in estim.Log.from_estimates(results["EKF.smooth"])


def test_the_plots_take_results_beside_logs(record, results, tmp_path):
    m, log = record
    runs = {"EKF (replay)": log, **results}
    fig = plot_estimates(runs, tmp_path / "estimates.png")
    assert len(fig.axes) == 2 and (tmp_path / "estimates.png").stat().st_size > 0
    # the truth, then one line per run on every state's axes
    assert len(fig.axes[0].lines) == 1 + len(runs)
    fig = plot_errors(runs, tmp_path / "errors.png")
    np.testing.assert_allclose(fig.axes[1].lines[2].get_ydata(),
                               results["EKF.smooth"].x[:, 1] - log.x[:, 1])
    # a result alone needs its truth, and says so
    with pytest.raises(ValueError, match="needs the truth of 'EKF.smooth'.*truth="):
        plot_errors({"EKF.smooth": results["EKF.smooth"]})
    plot_errors(results["EKF.smooth"], truth=log.x)
    with pytest.raises(TypeError, match="FilterResult, SmoothResult, ParticleFilterResult"):
        plot_estimates({"bad": log.x_hat})


def test_filter_against_smoother_in_one_call(record, results, tmp_path):
    m, log = record
    for name in ("EKF.smooth", "UKF.smooth", "ParticleFilter.smooth"):
        res = results[name]
        fig = plot_smoothing(res, tmp_path / "smoothing.png", truth=log)
        ax = fig.axes[0]
        lines = {line.get_label(): line for line in ax.lines}
        filt = next(v for k, v in lines.items() if k.startswith("filter"))
        smooth = next(v for k, v in lines.items() if k.startswith("smoother"))
        np.testing.assert_array_equal(filt.get_ydata(), res.x_filtered[:, 0])
        np.testing.assert_array_equal(smooth.get_ydata(), res.x[:, 0])
        np.testing.assert_array_equal(lines["truth"].get_ydata(), log.x[:, 0])
        # the legend scores both: the smoother is the better on this record
        f_rmse = float(estim.rmse(res.x_filtered, truth=log))
        s_rmse = float(estim.rmse(res, truth=log))
        assert f"RMSE {f_rmse:.3g}" in filt.get_label()
        assert f"RMSE {s_rmse:.3g}" in smooth.get_label()
        assert len(ax.collections) == 2  # the two ±2σ bands
    # a fit holds no forward pass: the filter is given
    fig = plot_smoothing(results["FullInformation.fit"], truth=log,
                         filtered=results["EKF.filter"], states="omega")
    assert len(fig.axes) == 1
    with pytest.raises(ValueError, match="no filtered estimates: pass filtered="):
        plot_smoothing(results["FullInformation.fit"], truth=log)
    with pytest.raises(TypeError, match="result must be the result of a smoother"):
        plot_smoothing(log)
    with pytest.raises(ValueError, match=r"states \['phi'\]"):
        plot_smoothing(results["EKF.smooth"], states=["phi"])


def test_refusals_name_what_is_accepted(record, results):
    m, log = record
    with pytest.raises(TypeError, match="ParticleSmoothResult, FitResult"):
        estim.rmse({"x": 1}, truth=log)
    with pytest.raises(ValueError, match="truth is required with a ParticleSmoothResult"):
        estim.rmse(results["ParticleFilter.smooth"])
    with pytest.raises(ValueError, match=r"truth has shape \(5, 2\)"):
        estim.rmse(results["EKF.smooth"], truth=log.x[:5])
    with pytest.raises(ValueError, match="t must have shape"):
        estim.EKF(m, **TUNING).smooth(log.y, t=log.t[:5])
    # a particle filter integrates over the model's fixed dt: times at another spacing
    # of a continuous model are refused, not silently relabelled
    with pytest.raises(ValueError, match="fixed dt"):
        estim.ParticleFilter(m, **TUNING, n_particles=10).filter(log.y, t=2 * log.t)
