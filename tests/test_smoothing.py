"""Covariances of every sample (FullInformation) and the extended / unscented RTS
smoothers (EKF.smooth, UKF.smooth) against filterpy and numpy references."""

from __future__ import annotations

import tracemalloc

import casadi as ca
import numpy as np
import pytest
from conftest import make_linear
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from test_kalman import _record

import estim


def _relative(a, b) -> float:
    """Largest difference relative to the largest entry of the reference."""
    return float(np.abs(a - b).max() / np.abs(b).max())


def _missing(Y):
    """Whole rows and single outputs missing."""
    Y = Y.copy()
    Y[[3, 17, 18]] = np.nan
    Y[[8, 25], 0] = np.nan
    Y[30, 1] = np.nan
    return Y


def _filterpy_rts(sys, Y):
    """filterpy's ``batch_filter`` (``update_first``: ``x0, P0`` is the prior of
    :math:`x_0`) and ``rts_smoother``; smoothed and filtered means and covariances.

    A missing row is ``None``; a single missing output gets a zero row of ``H`` and a
    decoupled unit variance in ``R`` (its gain column is then zero: the update of the
    measured rows alone). filterpy's smoother has no inputs: ``U = 0``.
    """
    nx, ny = sys.A.shape[0], sys.C.shape[0]
    kf = KalmanFilter(dim_x=nx, dim_z=ny)
    kf.F, kf.H, kf.Q, kf.R = sys.A, sys.C, sys.Q, sys.R
    kf.x, kf.P = sys.x0.copy(), sys.P0.copy()
    zs, Hs, Rs = [], [], []
    for y in Y:
        rows = np.isfinite(y)
        H, R = sys.C * rows[:, None], sys.R * np.outer(rows, rows)
        R[~rows, ~rows] = 1.0
        zs.append(np.where(rows, y, 0.0) if rows.any() else None)
        Hs.append(H)
        Rs.append(R)
    xf, Pf, _, _ = kf.batch_filter(zs, Hs=Hs, Rs=Rs, update_first=True)
    xs, Ps, _, _ = kf.rts_smoother(xf, Pf)
    return xs, Ps, xf, Pf


def _extended_rts(f, f_x, h, h_x, Q, R, x0, P0, Y, U):
    """Extended Kalman filter (update first) and RTS smoother in plain numpy; ``U[k]``
    acts from sample k to k+1, NaN outputs are left out of the update."""
    T = len(Y)
    xf, Pf = [], []
    x, P = np.array(x0, float), np.array(P0, float)
    for k in range(T):
        if k:
            A = f_x(x, U[k - 1])
            x, P = f(x, U[k - 1]), A @ P @ A.T + Q
        rows = np.isfinite(Y[k])
        if rows.any():
            C = h_x(x)[rows]
            S = C @ P @ C.T + R[np.ix_(rows, rows)]
            K = np.linalg.solve(S, C @ P).T
            x = x + K @ (Y[k][rows] - h(x)[rows])
            P = P - K @ S @ K.T
        xf.append(x)
        Pf.append(P)
    xs, Ps = [xf[-1]], [Pf[-1]]
    for k in range(T - 2, -1, -1):
        A = f_x(xf[k], U[k])
        Pp = A @ Pf[k] @ A.T + Q
        G = np.linalg.solve(Pp, A @ Pf[k]).T
        xs.insert(0, xf[k] + G @ (xs[0] - f(xf[k], U[k])))
        Ps.insert(0, Pf[k] + G @ (Ps[0] - Pp) @ G.T)
    return np.array(xs), np.array(Ps)


def _linear_rts(sys, Y, U):
    A, B, C = sys.A, sys.B, sys.C
    return _extended_rts(lambda x, u: A @ x + B @ u, lambda x, u: A, lambda x: C @ x,
                         lambda x: C, sys.Q, sys.R, sys.x0, sys.P0, Y, U)


# ------------------------------------------------------------ FullInformation.P
@pytest.mark.parametrize("mode", ["unrolled", "mapped"])
@pytest.mark.parametrize("T", [40, 300])  # 300: the covariances in chunks, either mode
@pytest.mark.parametrize("missing", [False, True])
def test_fit_covariances_equal_rts_smoother(mode, T, missing):
    sys = make_linear(0)
    Y, _ = _record(sys, T=T, seed=4)
    if missing:
        Y = _missing(Y)
    xs, Ps, _, Pf = _filterpy_rts(sys, Y)
    fie = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                                solver_options={"mode": mode})
    res = fie.fit(Y, 0)
    assert res.success and res.P.shape == (T, 4, 4)
    assert _relative(res.P, Ps) < 1e-8
    assert _relative(res.x, xs) < 1e-8
    np.testing.assert_array_equal(res.P_last, res.P[-1])
    assert _relative(res.P[-1], Pf[-1]) < 1e-8  # the smoother's last is the filter's
    again = fie.fit(Y, 0)  # P_last read first, alone: the same numbers
    np.testing.assert_array_equal(again.P_last, again.P[-1])


def test_ipopt_fit_has_the_same_covariances():
    sys = make_linear(1)
    Y, _ = _record(sys, T=40, seed=2)
    Y = _missing(Y)
    _, Ps, _, _ = _filterpy_rts(sys, Y)
    fie = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                                solver="ipopt", solver_options={"ipopt.tol": 1e-12})
    res = fie.fit(Y, 0)
    assert res.solver == "ipopt" and _relative(res.P, Ps) < 1e-8


def test_robust_fit_covariances_are_those_of_the_reweighted_problem():
    """With a diagonal R, the final weight w of a whitened output scales its variance:
    the covariances are the RTS smoother's with R_k = diag(R_ii / w_ki)."""
    sys = make_linear(1)
    R = np.diag(np.diag(sys.R))
    Y, U = _record(sys, T=60, seed=3)
    Y[20, 0] += 30.0
    Y[33, 1] -= 20.0
    res = estim.FullInformation(sys.model, Q=sys.Q, R=R, x0=sys.x0, P0=sys.P0,
                                loss="huber").fit(Y, 0)
    w = res.measurement_weights
    assert w[20, 0] < 0.1 and w[33, 1] < 0.1
    # the reference: the update with the reweighted variances, sample by sample
    x, P, Pf, Pp = sys.x0, sys.P0, [], []
    for k in range(len(Y)):
        if k:
            x, P = sys.A @ x, sys.A @ P @ sys.A.T + sys.Q
        Pp.append(P)
        S = sys.C @ P @ sys.C.T + np.diag(np.diag(R) / w[k])
        K = np.linalg.solve(S, sys.C @ P).T
        x, P = x + K @ (Y[k] - sys.C @ x), P - K @ S @ K.T
        Pf.append(P)
    Ps = [Pf[-1]]
    for k in range(len(Y) - 2, -1, -1):
        G = np.linalg.solve(Pp[k + 1], sys.A @ Pf[k]).T
        Ps.insert(0, Pf[k] + G @ (Ps[0] - Pp[k + 1]) @ G.T)
    # (the weights are those of the last iterate, converged to xtol)
    assert _relative(res.P, np.array(Ps)) < 1e-6
    np.testing.assert_array_equal(res.P_last, res.P[-1])


def test_covariances_with_active_bounds():
    """The batch reactor near equilibrium, a concentration at its bound: the
    unconstrained Laplace covariances at the constrained optimum, alike in both modes."""
    sc = estim.scenarios.batch_reactor()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    kw = dict(Q=0.002**2, R=0.25**2, x0=[0.1, 0.2, 0.6], P0=1.0)
    fits = [estim.FullInformation(sc.model, solver_options={"mode": mode}, **kw).fit(
        log.y[300:430]) for mode in ("unrolled", "mapped")]
    assert (fits[0].x <= 1e-12).any()  # a bound is active
    assert (np.linalg.eigvalsh(fits[0].P) > 0).all()
    assert _relative(fits[1].P, fits[0].P) < 1e-10
    np.testing.assert_array_equal(fits[0].P_last, fits[0].P[-1])


def test_long_record_in_mapped_mode_equals_numpy_rts():
    sys = make_linear(2, nx=3, ny=2)
    Y, U = _record(sys, T=5000, seed=6)
    Y[::7, 1] = np.nan
    xs, Ps = _linear_rts(sys, Y, U)
    res = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                                solver_options={"mode": "mapped"}).fit(Y, U[:-1])
    assert _relative(res.P, Ps) < 1e-8 and _relative(res.x, xs) < 1e-8
    nees = estim.nees(res, truth=xs)  # the errors from the reference: almost zero
    assert nees.shape == (5000,) and np.nanmax(nees) < 1e-10


def test_covariances_of_a_long_record_form_no_dense_matrix():
    """T = 20 000 samples of three states: a dense (3T)^2 inverse would take 29 GB;
    the recursion's arrays stay in tens of megabytes (numpy's allocations are traced)."""
    sys = make_linear(3, nx=3, ny=1)
    Y, U = _record(sys, T=20_000, seed=1)
    res = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0
                                ).fit(Y, U[:-1])
    tracemalloc.start()
    try:
        P = res.P
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert P.shape == (20_000, 3, 3) and np.isfinite(P).all()
    assert peak < 100e6
    assert (np.linalg.eigvalsh(P) > 0).all()


def test_nees_of_a_fit_on_its_own_model():
    """Seeded linear-Gaussian data: the errors of the smoothed states against the truth,
    weighted by P, average n_x (a chi-square mean; the loose bound allows for the
    correlation of neighbouring smoothed errors)."""
    sys = make_linear(0)
    rng = np.random.default_rng(11)
    T, nx = 4000, 4
    x = sys.x0 + np.linalg.cholesky(sys.P0) @ rng.standard_normal(nx)
    X, Y = [], []
    for _ in range(T):
        X.append(x)
        Y.append(sys.C @ x + np.linalg.cholesky(sys.R) @ rng.standard_normal(2))
        x = sys.A @ x + np.linalg.cholesky(sys.Q) @ rng.standard_normal(nx)
    res = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0
                                ).fit(np.array(Y), 0)
    nees = estim.nees(res, truth=np.array(X))
    assert 0.8 * nx < nees.mean() < 1.2 * nx


# ------------------------------------------------------------ EKF/UKF.smooth
@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
@pytest.mark.parametrize("missing", [False, True])
def test_smoothers_equal_the_kalman_smoother_on_linear_models(cls, missing):
    sys = make_linear(1)
    Y, _ = _record(sys, T=50, seed=9)
    if missing:
        Y = _missing(Y)
    xs, Ps, xf, Pf = _filterpy_rts(sys, Y)
    res = cls(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0).smooth(Y, 0)
    assert res.success and res.P.shape == (50, 4, 4) and res.gain.shape == (49, 4, 4)
    for ours, ref in ((res.x, xs), (res.P, Ps), (res.x_filtered, xf), (res.P_filtered, Pf)):
        assert _relative(ours, ref) < 1e-10


@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_smoothers_and_fit_read_inputs_alike(cls, hold):
    """A continuous linear model (RK4 is linear in x and u): the smoothers and the
    full-information fit are the same RTS smoother, with the same inputs."""
    rng = np.random.default_rng(5)
    A = ca.DM([[0.0, 1.0], [-2.0, -0.3]])
    m = estim.Model(states=2, outputs=1, inputs=1, ode=lambda x, u, p: A @ x + ca.vertcat(0, u),
                    output=lambda x, u, p: x[0], dt=0.1, hold=hold)
    T = 80
    U = rng.standard_normal((T if hold == "foh" else T - 1, 1))
    Y = rng.standard_normal((T, 1))
    Y[[5, 6, 40]] = np.nan
    kw = dict(Q=[1e-3, 2e-3], R=0.1, x0=[0.5, 0.0], P0=1.0)
    fit = estim.FullInformation(m, **kw).fit(Y, U)
    res = cls(m, **kw).smooth(Y, U)
    assert _relative(res.x, fit.x) < 1e-8 and _relative(res.P, fit.P) < 1e-8


def _pendulum():
    """A damped pendulum (explicit Euler), a torque input and outputs sin(angle), rate."""
    dt = 0.1

    def F(x, u, p):
        return ca.vertcat(x[0] + dt * x[1], x[1] + dt * (-9.81 * ca.sin(x[0]) - 0.3 * x[1] + u))

    model = estim.Model(states=["theta", "omega"], outputs=2, inputs=1, dynamics=F,
                        output=lambda x, u, p: ca.vertcat(ca.sin(x[0]), x[1]), dt=dt)

    def f(x, u):
        return np.array([x[0] + dt * x[1],
                         x[1] + dt * (-9.81 * np.sin(x[0]) - 0.3 * x[1] + u[0])])

    def f_x(x, u):
        return np.array([[1.0, dt], [-dt * 9.81 * np.cos(x[0]), 1.0 - 0.3 * dt]])

    def h(x):
        return np.array([np.sin(x[0]), x[1]])

    def h_x(x):
        return np.array([[np.cos(x[0]), 0.0], [0.0, 1.0]])

    return model, (f, f_x, h, h_x)


@pytest.mark.parametrize("missing", [False, True])
def test_extended_smoother_equals_numpy_on_a_nonlinear_model(missing):
    model, funs = _pendulum()
    T, Q, R = 120, np.diag([1e-4, 4e-3]), np.diag([0.05**2, 0.1**2])
    U = 0.5 * np.sin(0.2 * np.arange(T))[:, None]
    log = estim.simulate(model, estim.EKF(model, Q=Q, R=R, x0=[1.0, 0.0], P0=0.1),
                         x0=[1.2, 0.0], n_steps=T, Q=Q, R=R, seed=3, inputs=U)
    Y = _missing(log.y) if missing else log.y
    xs, Ps = _extended_rts(*funs, Q, R, [1.0, 0.0], 0.1 * np.eye(2), Y, log.u)
    res = estim.EKF(model, Q=Q, R=R, x0=[1.0, 0.0], P0=0.1).smooth(Y, log.u)
    assert _relative(res.x, xs) < 1e-9 and _relative(res.P, Ps) < 1e-9
    assert np.sqrt(np.mean((res.x - log.x) ** 2)) < np.sqrt(np.mean((res.x_filtered - log.x)
                                                                    ** 2))


@pytest.mark.parametrize("missing", [False, True])
def test_unscented_smoother_equals_filterpy_on_a_nonlinear_model(missing):
    """filterpy's ``UnscentedKalmanFilter``, updating first from the prior, then its
    ``rts_smoother`` (which calls ``fx(x, dt)``: a model without inputs)."""
    sc = estim.scenarios.van_der_pol()
    m, tun = sc.model, sc.tuning
    log = estim.simulate(sc, estim.UKF(m, **tun), seed=1)
    Y = _missing(log.y) if missing else log.y
    points = MerweScaledSigmaPoints(m.nx, alpha=1.0, beta=2.0, kappa=0.0)  # the default
    ukf = UnscentedKalmanFilter(dim_x=m.nx, dim_z=m.ny, dt=m.dt, points=points,
                                fx=lambda x, dt: m.f(x), hx=lambda x: m.h(x))
    est = estim.UKF(m, **tun)
    ukf.x, ukf.P, ukf.Q, ukf.R = est.x0.copy(), est.P0.copy(), est.Q, est.R
    xf, Pf = [], []
    for k, y in enumerate(Y):
        if k:
            ukf.predict()
        else:
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
        rows = np.isfinite(y)
        if rows.all():
            ukf.update(y)
        elif rows.any():
            idx = np.flatnonzero(rows)
            ukf.update(y[idx], R=est.R[np.ix_(idx, idx)], hx=lambda x, idx=idx: m.h(x)[idx])
        xf.append(ukf.x.copy())
        Pf.append(ukf.P.copy())
    xs, Ps, _ = ukf.rts_smoother(np.array(xf), np.array(Pf))
    res = est.smooth(Y)
    assert _relative(res.x_filtered, np.array(xf)) < 1e-8
    assert _relative(res.x, xs) < 1e-8 and _relative(res.P, Ps) < 1e-8
    e = estim.nees(res, truth=log)
    assert e.shape == (len(Y),) and np.isfinite(e).all()


def test_smooth_checks_its_arguments():
    sys = make_linear(0)
    ekf = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    with pytest.raises(ValueError, match="Y"):
        ekf.smooth(np.zeros((10, 3)))
    with pytest.raises(ValueError, match="U"):
        ekf.smooth(np.zeros((10, 2)), np.zeros((4, 1)))
    with pytest.raises(ValueError, match="Y"):
        ekf.smooth(np.full((10, 2), np.inf))
