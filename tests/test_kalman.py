"""EKF and UKF against the exact Kalman filter (filterpy) and on the benchmark systems."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_linear
from filterpy.kalman import KalmanFilter

import estim

FILTERS = [estim.EKF, estim.UKF]


def _record(sys, T=60, seed=1):
    rng = np.random.default_rng(seed)
    nx, nu = sys.A.shape[0], sys.B.shape[1]
    U = rng.standard_normal((T, nu))
    x = sys.x0 + np.linalg.cholesky(sys.P0) @ rng.standard_normal(nx)
    Y = []
    for k in range(T):
        Y.append(sys.C @ x + np.linalg.cholesky(sys.R) @ rng.standard_normal(len(sys.R)))
        x = sys.A @ x + sys.B @ U[k] + np.linalg.cholesky(sys.Q) @ rng.standard_normal(nx)
    return np.array(Y), U


def _kalman(sys, Y, U):
    """filterpy's KalmanFilter: update on y_0 from the prior, then predict/update."""
    kf = KalmanFilter(dim_x=sys.A.shape[0], dim_z=sys.C.shape[0], dim_u=sys.B.shape[1])
    kf.F, kf.B, kf.H, kf.Q, kf.R = sys.A, sys.B, sys.C, sys.Q, sys.R
    kf.x, kf.P = sys.x0.copy(), sys.P0.copy()
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            kf.predict(u=U[k - 1])
        kf.update(y)
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("cls", FILTERS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_kalman_filter_on_linear_gaussian(cls, seed):
    sys = make_linear(seed)
    Y, U = _record(sys, seed=seed + 10)
    x_ref, P_ref = _kalman(sys, Y, U)
    est = cls(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    for k, y in enumerate(Y):
        x = est.step(y, U[k - 1] if k else None)
        np.testing.assert_allclose(x, x_ref[k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(est.info.P, P_ref[k], rtol=0, atol=1e-9)
        assert est.info.success and est.info.status == "ok"


@pytest.mark.parametrize("cls", FILTERS)
def test_missing_outputs_equal_reduced_kalman_update(cls, linear):
    """NaN rows are dropped exactly: same as a Kalman update with those rows removed."""
    sys = linear
    Y, U = _record(sys, T=30)
    Y[5, 0] = np.nan
    Y[9, :] = np.nan
    Y[12, 1] = np.nan
    est = cls(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    x, P = sys.x0.copy(), sys.P0.copy()
    for k, y in enumerate(Y):
        if k:
            x = sys.A @ x + sys.B @ U[k - 1]
            P = sys.A @ P @ sys.A.T + sys.Q
        rows = np.isfinite(y)
        if rows.any():
            C, R = sys.C[rows], sys.R[np.ix_(rows, rows)]
            S = C @ P @ C.T + R
            K = np.linalg.solve(S, C @ P).T
            x = x + K @ (y[rows] - C @ x)
            P = P - K @ S @ K.T
        xe = est.step(y, U[k - 1] if k else None)
        np.testing.assert_allclose(xe, x, atol=1e-9)
        np.testing.assert_allclose(est.info.P, P, atol=1e-9)


def test_ekf_covariance_symmetric_and_nis_matches_definition(linear):
    sys = linear
    Y, U = _record(sys, T=20)
    est = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    x, P = sys.x0.copy(), sys.P0.copy()
    for k, y in enumerate(Y):
        if k:
            x = sys.A @ x + sys.B @ U[k - 1]
            P = sys.A @ P @ sys.A.T + sys.Q
        e = y - sys.C @ x
        S = sys.C @ P @ sys.C.T + sys.R
        est.step(y, U[k - 1] if k else None)
        np.testing.assert_allclose(est.info.innovation, e, atol=1e-9)
        assert est.info.nis == pytest.approx(e @ np.linalg.solve(S, e), rel=1e-9)
        assert np.array_equal(est.info.P, est.info.P.T)
        K = np.linalg.solve(S, sys.C @ P).T
        x, P = x + K @ e, P - K @ S @ K.T


@pytest.mark.parametrize("cls", FILTERS)
def test_reset_reproduces_the_run(cls, linear):
    sys = linear
    Y, U = _record(sys, T=15)
    est = cls(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    first = [est.step(y, U[k - 1] if k else None) for k, y in enumerate(Y)]
    est.reset()
    second = [est.step(y, U[k - 1] if k else None) for k, y in enumerate(Y)]
    np.testing.assert_array_equal(first, second)


def test_batch_reactor_ekf_converges_to_wrong_state_and_clip_stays_nonnegative():
    """Seed 002 (KU Leuven session 5, exercises 3-4)."""
    sc = estim.scenarios.batch_reactor()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    assert float(estim.rmse(log)) > 0.1
    assert log.x_hat.min() < -0.1  # partly negative concentrations
    clipped = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning, clip=True), seed=0)
    assert clipped.x_hat.min() >= 0.0
    assert np.all(clipped.success)
    # projecting the filter state forgets the wrong basin: the late error is far smaller
    late, late_clip = estim.rmse(log, burn_in=200), estim.rmse(clipped, burn_in=200)
    assert float(late_clip) < 0.1 * float(late)


@pytest.mark.parametrize("cls", FILTERS)
@pytest.mark.parametrize("name", ["van_der_pol", "lorenz", "batch_reactor"])
def test_filters_are_consistent_on_benchmark_scenarios(cls, name):
    """Monte Carlo NEES test (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4).

    With the initial guess drawn from N(x0, P0) and the true noise
    covariances, a consistent filter has E[NEES] = nx. The per-run
    time-averaged NEES values are independent across runs, so their mean
    must lie within 3 standard errors (estimated from the runs) of nx.
    """
    sc = estim.scenarios.get(name)
    n_runs = 16
    P0 = np.eye(sc.model.nx) * (0.05**2 if name == "batch_reactor" else 1.0)
    per_run = []
    for s in range(n_runs):
        rng = np.random.default_rng(1000 + s)
        guess = sc.x0 + rng.multivariate_normal(np.zeros(sc.model.nx), P0)
        est = cls(sc.model, **{**sc.tuning, "x0": guess, "P0": P0})
        log = estim.simulate(sc, est, seed=s)
        assert np.all(log.success)
        per_run.append(np.mean(estim.nees(log)))
    mean, se = np.mean(per_run), np.std(per_run, ddof=1) / np.sqrt(n_runs)
    assert abs(mean - sc.model.nx) < 3 * se + 1e-12, (mean, se)
