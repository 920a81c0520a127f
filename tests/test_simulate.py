"""The shared closed loop: noise, reproducibility, inputs, controllers, missing data."""

from __future__ import annotations

import numpy as np
import pytest

import estim

SCENARIOS = ["lorenz", "van_der_pol", "batch_reactor", "runaway", "satellite"]


@pytest.mark.parametrize("name", SCENARIOS)
def test_noise_free_run_from_the_truth_stays_on_it(name):
    """EKF from the true state without process noise: the innovations are the
    measurement noise only (R = 1e-30, std 1e-15), so x_hat = x to rounding."""
    sc = estim.scenarios.get(name)
    sc = sc.replace(n_steps=min(sc.n_steps, 300), plant_changes=[])
    log = estim.simulate(sc, estim.EKF(sc.model, **{**sc.tuning, "x0": sc.x0}), seed=0,
                         Q=0.0, R=1e-30)
    scale = np.abs(log.x).max(axis=0).clip(1e-3)
    assert np.max(np.abs(log.x_hat - log.x) / scale) < 1e-12
    assert np.all(log.success)


@pytest.mark.parametrize("name", SCENARIOS)
def test_noise_free_ukf_from_the_truth_stays_within_sigma_point_bias(name):
    """The UKF mean carries curvature terms of order P, so from the truth with a
    tiny P0 and Q (1e-12 relative) it stays within the sigma-point spread
    sqrt(P0) = 1e-6 (relative) of the trajectory."""
    sc = estim.scenarios.get(name)
    sc = sc.replace(n_steps=min(sc.n_steps, 300), plant_changes=[])
    scale = np.maximum(np.abs(sc.x0), 1e-3)
    cov = 1e-12 * scale**2
    ukf = estim.UKF(sc.model, Q=cov, R=sc.R, x0=sc.x0, P0=cov)
    log = estim.simulate(sc, ukf, seed=0, Q=0.0, R=1e-30)
    assert np.max(np.abs(log.x_hat - log.x) / np.abs(log.x).max(axis=0).clip(1e-3)) < 1e-6
    assert np.all(log.success)


@pytest.mark.parametrize("name", SCENARIOS)
def test_same_seed_same_log_other_seed_other_noise(name):
    sc = estim.scenarios.get(name)
    sc = sc.replace(n_steps=min(sc.n_steps, 200))
    ekf = estim.EKF(sc.model, **sc.tuning)
    a = estim.simulate(sc, ekf, seed=7)
    b = estim.simulate(sc, ekf, seed=7)  # the loop resets the estimator
    for key in ("x", "y", "u", "x_hat", "P"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
    c = estim.simulate(sc, ekf, seed=8)
    assert not np.array_equal(a.y, c.y)


def test_noise_statistics_match_Q_and_R(linear):
    """Residuals w_k = x_{k+1} - F(x_k, u_k) and v_k = y_k - h(x_k) have covariances Q and R."""
    sys = linear
    T = 20000
    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    log = estim.simulate(sys.model, est, x0=sys.x0, n_steps=T, Q=sys.Q, R=sys.R, seed=1)
    w = log.x[1:] - log.x[:-1] @ sys.A.T - log.u[:-1] @ sys.B.T
    v = log.y - log.x @ sys.C.T
    # standard error of a sample covariance entry: sqrt((S_ii S_jj + S_ij^2) / T)
    for res, S in ((w, sys.Q), (v, sys.R)):
        se = np.sqrt((np.outer(np.diag(S), np.diag(S)) + S**2) / len(res))
        assert np.all(np.abs(np.cov(res.T) - S) < 5 * se)
        assert np.all(np.abs(res.mean(axis=0)) < 5 * np.sqrt(np.diag(S) / len(res)))


def test_same_noise_whatever_the_estimator():
    sc = estim.scenarios.van_der_pol()
    a = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3)
    b = estim.simulate(sc, estim.UKF(sc.model, **sc.tuning), seed=3)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.y, b.y)


def test_open_loop_inputs_reach_plant_and_estimator(linear):
    sys = linear
    T = 30
    U = np.sin(np.arange(T))[:, None]
    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    log = estim.simulate(sys.model, est, x0=sys.x0, n_steps=T, Q=0.0, R=1e-30, inputs=U, seed=0)
    np.testing.assert_array_equal(log.u, U)
    x = sys.x0.copy()
    for k in range(T):
        np.testing.assert_allclose(log.x[k], x, atol=1e-12)
        x = sys.A @ x + sys.B @ U[k]
    np.testing.assert_allclose(log.x_hat[5:], log.x[5:], atol=1e-6)
    log2 = estim.simulate(sys.model, est, x0=sys.x0, n_steps=T, Q=0.0, R=1e-30,
                          inputs=lambda t: [np.sin(t)], seed=0)
    np.testing.assert_array_equal(log2.u, U)


def test_controller_sees_the_estimate_or_the_truth(linear):
    sys = linear
    seen = []

    def controller(t, x):
        seen.append(np.array(x))
        return -0.1 * x[:1]

    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0 + 1, P0=sys.P0)
    log = estim.simulate(sys.model, est, x0=sys.x0, n_steps=10, Q=sys.Q, R=sys.R,
                         controller=controller, seed=0)
    np.testing.assert_array_equal(np.array(seen), log.x_hat)
    np.testing.assert_allclose(log.u[:, 0], -0.1 * log.x_hat[:, 0])
    seen.clear()
    log = estim.simulate(sys.model, est, x0=sys.x0, n_steps=10, Q=sys.Q, R=sys.R,
                         controller=controller, feedback="truth", seed=0)
    np.testing.assert_array_equal(np.array(seen), log.x)


def test_plant_clipping_and_missing_measurements():
    sc = estim.scenarios.batch_reactor()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0, missing=0.3)
    assert log.x.min() >= 0.0
    frac = np.isnan(log.y).mean()
    assert abs(frac - 0.3) < 5 * np.sqrt(0.3 * 0.7 / log.y.size)
    assert np.all(np.isfinite(log.x_hat))
    mask = np.zeros((sc.n_steps, 1), bool)
    mask[10:20] = True
    log2 = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0, missing=mask)
    assert np.isnan(log2.y[10:20]).all() and np.isfinite(log2.y[20:]).all()
    # while nothing is measured the EKF estimate is the open-loop prediction
    ekf = estim.EKF(sc.model, **sc.tuning)
    for k in range(11):
        ekf.step(log2.y[k])
    for k in range(11, 20):
        np.testing.assert_allclose(log2.x_hat[k], sc.model.f(log2.x_hat[k - 1]), atol=1e-12)


def test_plant_changes_apply_from_their_time():
    sc = estim.scenarios.satellite(excitation=False, fault=True, n_steps=260)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0, R=1e-30)
    m = sc.model
    k = 199
    np.testing.assert_allclose(log.x[k + 1], m.f(log.x[k], log.u[k]), atol=1e-12)
    faulty = m.with_params(I1=0.2, I2=0.16, I3=0.104)
    k = 230
    np.testing.assert_allclose(log.x[k + 1], faulty.f(log.x[k], log.u[k]), atol=1e-12)


def test_failed_update_is_recorded_and_survived(linear):
    """A diverged covariance makes the prediction non-finite: the step re-anchors on the
    last trusted estimate (its covariance not finite: P0) and updates it with the
    measurement, reports the failure as status, and a reset recovers."""
    sys = linear
    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    ref = estim.simulate(sys.model, est, x0=sys.x0, n_steps=8, Q=sys.Q, R=sys.R, seed=0)
    assert np.all(ref.success) and set(ref.status) == {"ok"}
    est.reset()
    xs = [est.step(y, u) for y, u in zip(ref.y[:3], [None, *ref.u[:2]], strict=True)]
    est.P[:] = np.nan
    x = est.step(ref.y[3], ref.u[2])
    assert not est.info.success and est.info.status.startswith("failed")
    C, P0 = sys.C, sys.P0
    K = P0 @ C.T @ np.linalg.inv(C @ P0 @ C.T + sys.R)
    np.testing.assert_allclose(x, xs[-1] + K @ (ref.y[3] - C @ xs[-1]), atol=1e-12)
    assert np.isfinite(est.P).all()
    est.reset()
    np.testing.assert_array_equal(est.step(ref.y[0]), ref.x_hat[0])
    assert est.info.success


def test_bare_model_needs_x0_n_steps_Q_R(linear):
    est = estim.EKF(linear.model, Q=linear.Q, R=linear.R, x0=linear.x0, P0=linear.P0)
    for missing in ("x0", "n_steps", "Q", "R"):
        kwargs = {"x0": linear.x0, "n_steps": 5, "Q": linear.Q, "R": linear.R}
        kwargs.pop(missing)
        with pytest.raises(ValueError, match=missing):
            estim.simulate(linear.model, est, **kwargs)
