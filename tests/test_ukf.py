"""estim.UKF against filterpy's UnscentedKalmanFilter with the same sigma points, and its
missing outputs against a numpy unscented update on the measured rows."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from conftest import make_linear
from filterpy.kalman import JulierSigmaPoints, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.linalg import cholesky

import estim
from estim.estimators.kalman.ukf import sigma_weights

POINTS = {"merwe": {}, "julier": {"kappa": 1.0}, "cubature": {}}


class CubaturePoints:
    """The cubature set in filterpy's sigma-point interface (filterpy's own
    ``spherical_radial_sigmas``: the rows of the upper Cholesky factor of ``n P``)."""

    def __init__(self, n):
        self.n = n
        self.Wm = np.full(2 * n, 0.5 / n)
        self.Wc = self.Wm.copy()

    def num_sigmas(self):
        return 2 * self.n

    def sigma_points(self, x, P):
        U = cholesky(self.n * P)
        return np.vstack([x + U, x - U])


def _filterpy_points(points, n, kappa=0.0):
    if points == "merwe":
        return MerweScaledSigmaPoints(n, alpha=1.0, beta=2.0, kappa=kappa)
    if points == "julier":
        return JulierSigmaPoints(n, kappa=kappa)
    return CubaturePoints(n)


def _filterpy(model, est, points, Y, U, kappa=0.0):
    """filterpy's UKF on a record: update from the prior's sigma points on y_0, then
    predict/update (the model's compiled F and h, the input passed to both)."""
    pts = _filterpy_points(points, model.nx, kappa)
    ukf = UnscentedKalmanFilter(
        dim_x=model.nx, dim_z=model.ny, dt=model.dt, points=pts,
        fx=lambda x, dt, u: np.asarray(model.F(x, u, model.p)).ravel(),
        hx=lambda x, u: np.asarray(model.H(x, u, model.p)).ravel())
    ukf.x, ukf.P, ukf.Q, ukf.R = est.x0.copy(), est.P0.copy(), est.Q.copy(), est.R.copy()
    xs, Ps = [], []
    for k, y in enumerate(Y):
        u = U[k - 1] if k else np.zeros(model.nu)
        if k:
            ukf.predict(u=u)
        else:
            ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
        ukf.update(y, u=u)
        ukf.P = 0.5 * (ukf.P + ukf.P.T)
        xs.append(ukf.x.copy())
        Ps.append(ukf.P.copy())
    return np.array(xs), np.array(Ps)


def _run(est, Y, U):
    xs, Ps, nis = [], [], []
    for k, y in enumerate(Y):
        xs.append(est.step(y, U[k - 1] if k else None))
        assert est.info.status == "ok", (k, est.info.status)
        Ps.append(est.info.P)
        nis.append(est.info.nis)
    return np.array(xs), np.array(Ps), np.array(nis)


def _linear_record(seed=0, T=40):
    sys = make_linear(seed)
    rng = np.random.default_rng(seed + 100)
    U = rng.standard_normal((T, 1))
    x, Y = sys.x0.copy(), []
    for k in range(T):
        Y.append(sys.C @ x + rng.multivariate_normal(np.zeros(2), sys.R))
        x = sys.A @ x + sys.B @ U[k] + rng.multivariate_normal(np.zeros(4), sys.Q)
    return sys, np.array(Y), U


def _van_der_pol_record(T=150):
    sc = estim.scenarios.van_der_pol(n_steps=T)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3)
    return sc, np.array(log.y), np.zeros((len(log.y), sc.model.nu))


@pytest.mark.parametrize("points", list(POINTS))
def test_equals_filterpy_on_a_linear_model(points):
    sys, Y, U = _linear_record()
    est = estim.UKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0, points=points,
                    **POINTS[points])
    x, P, _ = _run(est, Y, U)
    x_ref, P_ref = _filterpy(sys.model, est, points, Y, U, **POINTS[points])
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("points", list(POINTS))
def test_equals_filterpy_on_van_der_pol(points):
    sc, Y, U = _van_der_pol_record()
    est = estim.UKF(sc.model, points=points, **POINTS[points], **sc.tuning)
    x, P, _ = _run(est, Y, U)
    x_ref, P_ref = _filterpy(sc.model, est, points, Y, U, **POINTS[points])
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-10)


def test_sigma_points_are_filterpys():
    sys = make_linear(1)
    rng = np.random.default_rng(0)
    x = rng.standard_normal(4)
    for points, kw in POINTS.items():
        est = estim.UKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0, points=points, **kw)
        ref = _filterpy_points(points, 4, kw.get("kappa", 0.0))
        np.testing.assert_allclose(est.sigma_points(x, sys.P0), ref.sigma_points(x, sys.P0),
                                   rtol=0, atol=1e-14)
        c, Wm, Wc = sigma_weights(points, 4, 1.0, 2.0, kw.get("kappa", 0.0))
        np.testing.assert_allclose(Wm, ref.Wm, rtol=1e-14)
        np.testing.assert_allclose(Wc, ref.Wc, rtol=1e-14)
        assert Wm.sum() == pytest.approx(1.0, abs=1e-12)
        # a stack of means and covariances at once
        stack = est.sigma_points(np.array([x, -x]), np.array([sys.P0, 2 * sys.P0]))
        np.testing.assert_allclose(stack[1], ref.sigma_points(-x, 2 * sys.P0), atol=1e-14)
    # filterpy's example spread (a negative centre weight), the former default
    narrow = estim.UKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0, alpha=0.1)
    ref = MerweScaledSigmaPoints(4, alpha=0.1, beta=2.0, kappa=0.0)
    np.testing.assert_allclose(narrow.sigma_points(x, sys.P0), ref.sigma_points(x, sys.P0),
                               rtol=0, atol=1e-14)
    np.testing.assert_allclose(narrow._Wc, ref.Wc, rtol=1e-14)


def _numpy_ukf(est, Y, U):
    """The unscented filter in numpy, the update on the measured rows of each y only."""
    m = est.model
    _, Wm, Wc = sigma_weights(est.points, m.nx, est.alpha, est.beta, est.kappa)
    F = lambda x, u: np.asarray(m.F(x, u, m.p)).ravel()  # noqa: E731
    h = lambda x, u: np.asarray(m.H(x, u, m.p)).ravel()  # noqa: E731
    x, P = est.x0.copy(), est.P0.copy()
    xs, Ps, nis = [], [], []
    for k, y in enumerate(Y):
        u = U[k - 1] if k else np.zeros(m.nu)
        if k:
            X = np.array([F(s, u) for s in est.sigma_points(x, P)])
            x = Wm @ X
            P = (X - x).T @ np.diag(Wc) @ (X - x) + est.Q
        rows = np.flatnonzero(np.isfinite(y))
        if rows.size:
            sig = est.sigma_points(x, P)
            Z = np.array([h(s, u)[rows] for s in sig])
            zp = Wm @ Z
            S = (Z - zp).T @ np.diag(Wc) @ (Z - zp) + est.R[np.ix_(rows, rows)]
            Pxz = (sig - x).T @ np.diag(Wc) @ (Z - zp)
            K = Pxz @ np.linalg.inv(S)
            e = y[rows] - zp
            x = x + K @ e
            P = P - K @ S @ K.T
            P = 0.5 * (P + P.T)
            nis.append(e @ np.linalg.solve(S, e))
        else:
            nis.append(np.nan)
        xs.append(x.copy())
        Ps.append(P.copy())
    return np.array(xs), np.array(Ps), np.array(nis)


@pytest.mark.parametrize("points", list(POINTS))
def test_missing_outputs_are_dropped_exactly(points):
    """Rows of y that are NaN (one of two, or both) are left out of the update exactly."""
    sc, Y, U = _van_der_pol_record(T=80)
    Y = Y.copy()
    Y[5:15, 0] = np.nan
    Y[20:25, 1] = np.nan
    Y[30:33] = np.nan
    Y[0, 1] = np.nan
    est = estim.UKF(sc.model, points=points, **POINTS[points], **sc.tuning)
    x, P, nis = _run(est, Y, U)
    x_ref, P_ref, nis_ref = _numpy_ukf(est, Y, U)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(nis, nis_ref, rtol=1e-9, atol=1e-12)
    assert np.isnan(nis[31])


def test_missing_outputs_on_a_linear_model_equal_the_reduced_kalman_update():
    sys, Y, U = _linear_record(seed=2)
    Y[3:9, 1] = np.nan
    Y[12] = np.nan
    est = estim.UKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    x, P, _ = _run(est, Y, U)
    x_ref, P_ref, _ = _numpy_ukf(est, Y, U)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=1e-10)


def test_options_are_checked():
    sc = estim.scenarios.van_der_pol(n_steps=5)
    with pytest.raises(ValueError, match="points"):
        estim.UKF(sc.model, points="simplex", **sc.tuning)
    with pytest.raises(ValueError, match="kappa"):
        estim.UKF(sc.model, points="julier", kappa=-2.0, **sc.tuning)


def test_a_non_finite_update_keeps_the_prediction_then_re_anchors():
    """Sigma points where h is not finite fail the update: the prediction of a trusted
    estimate is kept; the next failure re-anchors on it with P + P0. Every returned
    estimate is finite."""
    model = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: x,
                        output=lambda x, u, p: np.sqrt(x), name="root")
    est = estim.UKF(model, Q=1e-4, R=0.01, x0=[0.01], P0=1.0)
    x = est.step([0.1])
    assert est.info.status.startswith("failed: update") and "kept the prediction" in \
        est.info.status and not est.info.success
    np.testing.assert_array_equal(x, [0.01])
    np.testing.assert_array_equal(est.info.P, [[1.0]])
    x = est.step([0.1])
    assert "re-anchored on the last trusted estimate with P + P0 (no update" in est.info.status
    np.testing.assert_array_equal(x, [0.01])
    np.testing.assert_allclose(est.info.P, [[2.0]])
    # a good measurement model recovers at once
    est = estim.UKF(model, Q=1e-4, R=0.01, x0=[4.0], P0=1.0)
    est.step([2.0])
    assert est.info.status == "ok"


def test_filtering_imports_no_filterpy():
    code = ("import sys, estim; sc = estim.scenarios.van_der_pol(n_steps=5); "
            "u = estim.UKF(sc.model, **sc.tuning); u.step([0.1, 0.2]); u.step([0.2, 0.1]); "
            "u.smooth([[0.1, 0.2], [0.2, 0.1]]); print('filterpy' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert out.strip() == "False"
