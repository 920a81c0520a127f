"""The ensemble Kalman filter against the exact Kalman filter (filterpy), on Lorenz-63
with one state measured, and its seeding, recovery and argument checks."""

from __future__ import annotations

import pickle

import casadi as ca
import numpy as np
import pytest
from linear_gaussian import P0, X0, A, Q, R, kalman, linear_model, record

import estim
from estim.estimators.sampling.enkf import VARIANTS, EnKF


@pytest.mark.parametrize("variant", VARIANTS)
def test_mean_converges_to_the_kalman_filter_as_one_over_root_n(variant):
    """The RMS difference between the ensemble mean and the exact posterior mean over
    the record, averaged over 10 seeds, falls as N^(-1/2): the log-log slope over
    N = 50, 200, 800 is -0.49 (stochastic) and -0.51 (etkf) on average over 20 groups
    of 10 seeds, with a standard deviation of 0.05 between groups; the band is 4 of
    them."""
    Y = record(40)
    x_kf, _, _ = kalman(Y)
    m, sizes = linear_model(), (50, 200, 800)
    rms = [np.mean([np.sqrt(((EnKF(m, Q=Q, R=R, x0=X0, P0=P0, n_ensemble=N, variant=variant,
                                   seed=s).filter(Y).x - x_kf) ** 2).mean())
                    for s in range(10)]) for N in sizes]
    slope = np.polyfit(np.log(sizes), np.log(rms), 1)[0]
    assert -0.7 < slope < -0.3, (slope, rms)


@pytest.mark.parametrize("variant", VARIANTS)
def test_large_ensemble_matches_the_kalman_filter(variant):
    """With 20 000 members the means are within 0.05 posterior standard deviations of
    the exact ones and the covariances within 6 % (correlation scale) at every sample
    (over 20 seeds the largest were 0.035 and 0.033)."""
    Y = record(40)
    x_kf, P_kf, _ = kalman(Y)
    r = EnKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, n_ensemble=20000, variant=variant,
             seed=0).filter(Y)
    d = np.sqrt(np.diagonal(P_kf, axis1=1, axis2=2))
    assert r.success and all(s == "ok" for s in r.status)
    assert np.abs((r.x - x_kf) / d).max() < 0.05
    assert np.abs((r.P - P_kf) / (d[:, :, None] * d[:, None, :])).max() < 0.06


def test_analysis_is_the_kalman_update_of_the_forecast_ensemble():
    """Without process noise the forecast ensemble's mean and covariance are exactly the
    Kalman forecast of the previous analysis, A x and A P A^T: the ETKF's analysis
    then has exactly the Kalman analysis mean and covariance, the stochastic one
    exactly its mean (centred perturbations; the covariance only in expectation)."""
    m, y = linear_model(), np.array([[0.4], [0.7]])
    Q0 = np.zeros((2, 2))
    for variant in VARIANTS:
        f = EnKF(m, Q=Q0, R=R, x0=X0, P0=P0, n_ensemble=7, variant=variant, seed=3)
        x1 = f.step(y[0])
        P1 = f.info.P
        x2 = f.step(y[1])
        x_kf, P_kf, _ = kalman(y[1:], x0=A @ x1, P0=A @ P1 @ A.T, Q=Q0)
        assert np.allclose(x2, x_kf[0], rtol=0, atol=1e-12)
        if variant == "etkf":
            assert np.allclose(f.info.P, P_kf[0], rtol=0, atol=1e-12)
            assert np.allclose(f.ensemble.mean(axis=1), x2, rtol=0, atol=1e-12)


def test_inflation_scales_the_forecast_anomalies():
    """``inflation`` multiplies the forecast anomalies, so the covariance by its square."""
    m, Q0 = linear_model(), np.zeros((2, 2))
    f = EnKF(m, Q=Q0, R=R, x0=X0, P0=P0, n_ensemble=10, inflation=1.5)
    f.step(np.array([0.3]))
    P1 = f.info.P
    f.step(np.array([np.nan]))  # nothing measured: the forecast is the analysis
    assert np.allclose(f.info.P, 1.5 ** 2 * A @ P1 @ A.T, rtol=1e-12, atol=0)


def _lorenz_x1() -> estim.Model:
    """Lorenz-63 (estim.models.lorenz's Euler map) with its first state measured."""
    def ode(x, u, p):
        return ca.vertcat(p["sigma"] * (x[1] - x[0]), x[0] * (p["rho"] - x[2]) - x[1],
                          x[0] * x[1] - p["beta"] * x[2])

    return estim.Model(states=["x1", "x2", "x3"], outputs=["y1"], ode=ode,
                       output=lambda x, u, p: x[0], dt=0.02, integrator="euler",
                       params={"sigma": 10.0, "rho": 28.0, "beta": 8.0 / 3.0},
                       name="lorenz_x1")


def test_lorenz_with_one_state_measured():
    """The Lorenz scenario's noise and guess (estim.scenarios.lorenz) with only x1
    measured: 25 members track, both variants, as the EKF does on this record (x1 at
    every sample, std 0.1); RMSE over the second half 0.070 and 0.068 (EKF 0.068)."""
    m, T = _lorenz_x1(), 400
    log = estim.simulate(m, None, seed=0, x0=[-10.0, -12.0, 27.0], n_steps=T, Q=0.02 ** 2,
                         R=0.1 ** 2)
    X, Y = np.asarray(log.x), np.asarray(log.y)
    tuning = dict(Q=0.02 ** 2, R=0.1 ** 2, x0=[-9.0, -11.0, 26.0], P0=1.0)
    for est in (EnKF(m, n_ensemble=25, **tuning),
                EnKF(m, n_ensemble=25, variant="etkf", **tuning), estim.EKF(m, **tuning)):
        xh = np.asarray(estim.replay(est, Y).x_hat)
        rmse = np.sqrt(((xh[T // 2:] - X[T // 2:]) ** 2).mean())
        assert rmse < 0.15, (type(est).__name__, rmse)


def test_lorenz_sparse_measurements_where_the_ekf_diverges():
    """x1 measured every 12th sample (0.24 time units) with variance 2 (the classical
    setting of Miller, Ghil, Gauthiez 1994 and Evensen 1997, on this Euler map), seed
    0: the EKF's estimate diverges (non-finite Jacobians, re-anchored steps), the ETKF
    with 25 members stays within the attractor's scale (RMSE 4.4 over the second half;
    the attractor's spread is about 8.5). Over seeds 0-9 the EKF diverged on all ten,
    the ETKF on none (RMSE 2.9-7.9), the stochastic EnKF on three."""
    m, T = _lorenz_x1(), 1000
    log = estim.simulate(m, None, seed=0, x0=[-10.0, -12.0, 27.0], n_steps=T, Q=0.02 ** 2,
                         R=2.0)
    X, Y = np.asarray(log.x), np.asarray(log.y).copy()
    Y[np.arange(T) % 12 != 0] = np.nan
    tuning = dict(Q=0.02 ** 2, R=2.0, x0=[-9.0, -11.0, 26.0], P0=1.0)
    etkf = estim.replay(EnKF(m, n_ensemble=25, variant="etkf", **tuning), Y)
    xh = np.asarray(etkf.x_hat)
    assert np.all(np.asarray(etkf.success))
    assert np.sqrt(((xh[T // 2:] - X[T // 2:]) ** 2).mean()) < 6.0
    with pytest.warns(estim.EstimationWarning, match="failed"):
        ekf = estim.replay(estim.EKF(m, **tuning), Y)
    assert np.abs(np.asarray(ekf.x_hat)[T // 2:]).max() > 1e6


@pytest.mark.parametrize("variant", VARIANTS)
def test_seeded_runs_are_identical_and_reset_restarts_the_stream(variant):
    m, Y = linear_model(), record(10)
    kw = dict(Q=Q, R=R, x0=X0, P0=P0, n_ensemble=30, variant=variant)
    a, b = EnKF(m, seed=7, **kw), EnKF(m, seed=7, **kw)
    ra, rb = a.filter(Y), b.filter(Y)
    assert np.array_equal(ra.x, rb.x) and np.array_equal(ra.P, rb.P)
    assert np.array_equal(a.filter(Y).x, ra.x)  # filter resets
    c = pickle.loads(pickle.dumps(a))
    assert np.array_equal(c.filter(Y).x, ra.x)
    assert not np.array_equal(EnKF(m, seed=8, **kw).filter(Y).x, ra.x)
    log = estim.replay(a, Y)  # step by step gives what filter gives
    assert np.array_equal(np.asarray(log.x_hat), ra.x)
    assert ra.P.shape == (10, 2, 2) and ra.nis.shape == (10,) and len(ra.status) == 10


def test_simulate_and_compare():
    sc = estim.scenarios.lorenz(n_steps=60)
    log = estim.simulate(sc, EnKF(sc.model, n_ensemble=25, **sc.tuning), seed=0)
    assert float(estim.rmse(log)) < 0.1
    table = estim.compare(sc, {"enkf": EnKF(sc.model, n_ensemble=25, **sc.tuning),
                               "etkf": lambda m, t: EnKF(m, variant="etkf", **t)},
                          seeds=range(2))
    assert all(np.isfinite(r).all() and np.all(r < 0.1) for r in table.rmse.values())


@pytest.mark.parametrize("variant", VARIANTS)
def test_missing_outputs(variant):
    sc = estim.scenarios.lorenz()
    f = EnKF(sc.model, variant=variant, **sc.tuning)
    f.step(np.array([-18.0, 15.0, 76.6]))  # h(x0)
    assert f.info.status == "ok" and np.isfinite(f.info.nis)
    x = f.step(np.array([np.nan, 15.1, np.nan]))
    info = f.info
    assert np.isfinite(x).all() and info.innovation[0] == info.innovation[2] == 0.0
    assert info.innovation[1] != 0.0 and np.isfinite(info.nis)
    P = info.P
    f.step(np.full(3, np.nan))  # nothing measured: the forecast is kept
    assert np.isnan(f.info.nis) and f.info.status == "ok"
    assert not np.array_equal(f.info.P, P) and np.all(np.linalg.eigvalsh(f.info.P) > 0)


@pytest.mark.parametrize("variant", VARIANTS)
def test_non_finite_ensemble_reanchors(variant):
    """Members where h is not defined (log of a negative state) fail the step: the
    ensemble is drawn again around the last trusted estimate and analyses the same
    measurement; when that fails too, the re-anchored ensemble is kept."""
    m = estim.Model(states=["a"], outputs=["y"], dynamics=lambda x, u, p: x,
                    output=lambda x, u, p: ca.log(x))
    f = EnKF(m, Q=1e-4, R=0.01, x0=1.0, P0=0.01, variant=variant)
    f.step(np.array([0.0]))
    assert f.info.status == "ok"
    f.set_tuning(Q=100.0)  # the forecast spreads below zero
    x = f.step(np.array([0.0]))
    assert f.info.status.startswith("failed: non-finite ensemble; re-anchored")
    assert "no update" not in f.info.status and not f.info.success
    assert np.isfinite(x).all() and abs(x[0] - 1.0) < 0.2
    f.set_tuning(Q=1e-4)
    f.step(np.array([0.0]))
    assert f.info.success
    f.set_tuning(Q=100.0, P0=100.0)  # and the re-anchored ensemble too
    x = f.step(np.array([0.0]))
    assert f.info.status.endswith("(no update: the new ensemble's analysis is not finite "
                                  "either)")
    assert np.isfinite(x).all() and np.isfinite(f.info.P).all()


def test_outlier_is_suspect():
    f = EnKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0)
    f.step(np.array([0.1]))
    f.step(np.array([100.0]))
    assert f.info.status.startswith("suspect: NIS") and f.info.success


def test_bad_arguments_are_named():
    m = linear_model()
    kw = dict(Q=Q, R=R, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="n_ensemble"):
        EnKF(m, n_ensemble=1, **kw)
    for bad in (2.5, True, "50"):
        with pytest.raises(TypeError, match="n_ensemble"):
            EnKF(m, n_ensemble=bad, **kw)
    with pytest.raises(ValueError, match="did you mean 'etkf'"):
        EnKF(m, variant="etfk", **kw)
    with pytest.raises(TypeError, match="variant"):
        EnKF(m, variant=1, **kw)
    for bad in (0.9, 0.0, -1.0, np.inf):
        with pytest.raises(ValueError, match="inflation"):
            EnKF(m, inflation=bad, **kw)
    with pytest.raises(TypeError, match="inflation"):
        EnKF(m, inflation="1.1", **kw)
    with pytest.raises(TypeError, match="seed"):
        EnKF(m, seed=1.5, **kw)
    with pytest.raises(ValueError, match="P0"):
        EnKF(m, Q=Q, R=R, x0=X0, P0=None)
    with pytest.raises(TypeError, match="n_members"):
        EnKF(m, n_members=10, **kw)
    with pytest.raises(ValueError, match="Y"):
        EnKF(m, **kw).filter(np.ones((5, 2)))


def test_model_integrated_by_cvodes_runs_through_map():
    """A transition that calls CasADi's integrator has no numpy counterpart: the members
    go through CasADi's map, and agree with the RK4 model's to the integrators' error."""
    def ode(x, u, p):
        return ca.vertcat(x[1], -x[0])

    kw = dict(states=["a", "b"], outputs=["y"], ode=ode, output=lambda x, u, p: x[0],
              dt=0.1)
    Y = np.cos(0.1 * np.arange(10))[:, None]
    runs = [EnKF(estim.Model(integrator=i, **kw), Q=1e-4, R=0.01, x0=[1.0, 0.0], P0=0.1,
                 n_ensemble=20).filter(Y) for i in ("cvodes", "rk4")]
    assert runs[0].success and np.allclose(runs[0].x, runs[1].x, rtol=0, atol=1e-4)
