"""estim.adapters: filterpy filters and plain step functions in estim's loop, compared on
equal terms with estim's filters."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import (
    ExtendedKalmanFilter,
    KalmanFilter,
    MerweScaledSigmaPoints,
    UnscentedKalmanFilter,
)
from linear_gaussian import P0, X0, A, C, Q, R, linear_model, record

import estim
from estim import adapters, testing


def _kf() -> KalmanFilter:
    kf = KalmanFilter(2, 1)
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = A, C, Q, R, X0.copy(), P0.copy()
    return kf


def test_filterpy_kalman_filter_is_estims_filter_on_a_linear_model():
    """filterpy's KalmanFilter in the loop equals estim's EKF on the same linear model,
    estimates and covariances (assert_close), and in compare (equivalent RMSE, the same
    NIS); reset restores the filter as it was wrapped."""
    m = linear_model()
    ekf = estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0)
    wrapped = adapters.from_filterpy(_kf(), m)
    Y = record(80)
    testing.assert_close(wrapped, ekf, (Y, None), atol=1e-12, rtol=1e-10)
    a, b = estim.replay(wrapped, Y), estim.replay(ekf, Y)
    np.testing.assert_allclose(a.nis, b.nis, rtol=1e-9)
    assert a.estimator == "filterpy KalmanFilter"
    sc = estim.Scenario("linear", m, x0=X0, n_steps=60, Q=Q, R=R,
                        tuning=dict(Q=Q, R=R, x0=X0, P0=P0))
    res = estim.compare(sc, {"filterpy": wrapped, "ekf": estim.EKF}, seeds=range(8))
    testing.assert_equivalent(res, "filterpy", "ekf", tolerance=1e-9)
    np.testing.assert_allclose(res.nees["filterpy"], res.nees["ekf"], rtol=1e-9)


def test_filterpy_extended_and_unscented_filters_on_van_der_pol():
    """filterpy's EKF (its predict through the model's map and Jacobian) and UKF (Merwe
    points, the same alpha, beta, kappa) equal estim's EKF and UKF on van der Pol."""
    sc = estim.scenarios.get("van_der_pol", n_steps=60)
    m, t = sc.model, sc.tuning
    log = estim.simulate(sc, None, seed=3)

    class VdpEKF(ExtendedKalmanFilter):
        def predict(self, u=0):
            self.F = m.jacobians(self.x.ravel())[0]
            super().predict(u)

        def predict_x(self, u=0):
            self.x = m.f(self.x.ravel()).reshape(-1, 1)

    fekf = VdpEKF(2, 2)
    fekf.x, fekf.P = np.reshape(t["x0"], (2, 1)).astype(float), np.eye(2) * t["P0"]
    fekf.Q, fekf.R = np.eye(2) * t["Q"], np.eye(2) * t["R"]
    testing.assert_close(adapters.from_filterpy(fekf, m, name="filterpy ekf"),
                         estim.EKF(m, **t), (log.y, None), atol=1e-10, rtol=1e-9)
    points = MerweScaledSigmaPoints(2, alpha=1.0, beta=2.0, kappa=0.0)  # the default
    fukf = UnscentedKalmanFilter(2, 2, dt=m.dt, fx=lambda x, dt: m.f(x),
                                 hx=lambda x: m.h(x), points=points)
    fukf.x, fukf.P = np.array(t["x0"], float), np.eye(2) * t["P0"]
    fukf.Q, fukf.R = np.eye(2) * t["Q"], np.eye(2) * t["R"]
    testing.assert_close(adapters.from_filterpy(fukf, m), estim.UKF(m, **t),
                         (log.y, None), atol=1e-10, rtol=1e-9)


def test_a_step_function_in_the_loop():
    """A hand-written Kalman filter as a closure, with its reset: the same as the EKF."""
    m = linear_model()
    state = {}

    def reset():
        state.update(x=X0.copy(), P=P0.copy(), first=True)

    def my_filter(y, u):
        x, P = state["x"], state["P"]
        if not state["first"]:
            x, P = A @ x, A @ P @ A.T + Q
        S = C @ P @ C.T + R
        K = P @ C.T @ np.linalg.inv(S)
        x = x + K @ (y - C @ x)
        P = (np.eye(2) - K @ C) @ P @ (np.eye(2) - K @ C).T + K @ R @ K.T
        state.update(x=x, P=P, first=False)
        return x, P

    reset()
    student = adapters.from_function(my_filter, m, reset=reset)
    assert student.name == "my_filter"
    testing.assert_close(student, estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0), (record(50), None),
                         atol=1e-12)
    only_x = adapters.from_function(lambda y, u: np.full(2, np.nan), m, name="lost")
    log = estim.replay(only_x, record(5), warn=False)
    assert not log.success.any() and "not finite" in log.status[0]


def test_bad_adapters_are_named():
    m = linear_model()
    with pytest.raises(TypeError, match="filt must be a filterpy KalmanFilter"):
        adapters.from_filterpy(object(), m)
    with pytest.raises(TypeError, match="step must be a function"):
        adapters.from_function("my filter", m)
    with pytest.raises(ValueError, match=r"filt has 3 states but model has 2"):
        adapters.from_filterpy(KalmanFilter(3, 1), m)
    two = KalmanFilter(dim_x=2, dim_z=2)  # both states measured
    two.F, two.H = A, np.eye(2)
    with pytest.raises(ValueError, match=r"filt measures 1 outputs \(dim_z\) but model has 2"):
        adapters.from_filterpy(_kf(), estim.Model(
            states=["p", "v"], outputs=["y1", "y2"], dynamics=lambda x, u, p: A @ x,
            output=lambda x, u, p: x))
    wrapped = adapters.from_filterpy(two, estim.Model(
        states=["p", "v"], outputs=["y1", "y2"], dynamics=lambda x, u, p: A @ x,
        output=lambda x, u, p: x))
    with pytest.raises(ValueError, match=r"update with every output; y has NaN in \[1\]"):
        wrapped.step([0.1, np.nan])
    with pytest.raises(TypeError, match="set its tuning on the wrapped object"):
        wrapped.set_tuning(Q=1.0)
    bad = adapters.from_function(lambda y, u: [1.0, 2.0, 3.0], m)
    with pytest.raises(ValueError, match="the estimate must be 2 numbers, got \\(3,\\)"):
        bad.step([0.0])
