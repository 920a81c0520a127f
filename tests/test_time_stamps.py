"""Irregular time stamps: ``Model(..., variable_dt=True)`` integrates each transition over
its own interval, in ``Model.f``, ``step(y, u, dt=)``, ``replay(..., t=)`` and
``FullInformation.fit(..., t=)``. References: ``scipy.integrate.solve_ivp`` for the
transitions, filterpy's Kalman filter and RTS smoother with each step's exact
``F_k = expm(A dt_k)`` for the estimators on a linear model."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter, rts_smoother
from scipy.integrate import solve_ivp
from scipy.linalg import expm

import estim

A = np.array([[0.0, 1.0], [-2.0, -0.3]])   # a damped oscillator
B = np.array([0.0, 1.0])
Q, R, P0 = 1e-3, 0.05, 0.5
X0 = np.array([1.0, 0.0])


def _oscillator(**kw) -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["p_meas"], inputs=["f"],
                       ode=lambda x, u, p: ca.DM(A) @ x + ca.DM(B) * u[0],
                       output=lambda x, u, p: x[0], dt=0.1, name="oscillator", **kw)


def _times(T=80, seed=0):
    rng = np.random.default_rng(seed)
    return np.concatenate([[0.0], np.cumsum(rng.uniform(0.02, 0.3, T - 1))])


@pytest.mark.parametrize("integrator, substeps, tol", [("rk4", 64, 1e-11), ("euler", 1, None),
                                                       ("cvodes", 1, 1e-8)])
@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_a_transition_is_the_ode_over_its_interval(integrator, substeps, tol, hold):
    m = estim.Model(states=["x1", "x2"], outputs=["y"], inputs=["u"],
                    ode=lambda x, u, p: ca.vertcat(x[1], (1 - x[0] ** 2) * x[1] - x[0] + u[0]),
                    output=lambda x, u, p: x[0], dt=0.1, integrator=integrator,
                    substeps=substeps, hold=hold, variable_dt=True)
    assert m.nw == (2 if hold == "foh" else 1) + 1
    x0, u0, u1 = np.array([1.0, 0.5]), 0.3, -0.4
    for h in (0.013, 0.1, 0.37):
        def u_of(t, h=h):
            return u0 + (u1 - u0) * t / h if hold == "foh" else u0

        ref = solve_ivp(lambda t, x: [x[1], (1 - x[0] ** 2) * x[1] - x[0] + u_of(t)],
                        (0, h), x0, rtol=1e-12, atol=1e-12).y[:, -1]
        got = m.f(x0, [u0], [u1], dt=h) if hold == "foh" else m.f(x0, [u0], dt=h)
        if tol is None:  # Euler: exactly one step of its formula over h
            f0 = [x0[1], (1 - x0[0] ** 2) * x0[1] - x0[0] + u0]
            np.testing.assert_allclose(got, x0 + h * np.array(f0), rtol=1e-14)
        else:
            np.testing.assert_allclose(got, ref, atol=tol)
    # without dt: the model's own dt; the Jacobian takes the same interval
    np.testing.assert_array_equal(m.f(x0, [u0], dt=0.1), m.f(x0, [u0]))
    A1 = m.jacobians(x0, [u0], dt=0.37)[0]
    eps = 1e-6
    num = np.column_stack([(m.f(x0 + eps * e, [u0], dt=0.37) - m.f(x0 - eps * e, [u0], dt=0.37))
                           / (2 * eps) for e in np.eye(2)])
    np.testing.assert_allclose(A1, num, atol=1e-7)


def _record(t, seed=1):
    """The oscillator sampled at ``t`` (exact discretisation, ZOH force), noisy output."""
    rng = np.random.default_rng(seed)
    T = len(t)
    U = 0.5 * np.sin(t)[:, None]                      # U[k] acts from t[k] to t[k+1]
    X, x = np.zeros((T, 2)), X0.copy()
    for k in range(T):
        X[k] = x
        if k < T - 1:
            h = t[k + 1] - t[k]
            M = expm(np.block([[A, B[:, None]], [np.zeros((1, 3))]]) * h)
            x = M[:2, :2] @ x + M[:2, 2] * U[k, 0] + np.sqrt(Q) * rng.standard_normal(2)
    Y = X[:, :1] + np.sqrt(R) * rng.standard_normal((T, 1))
    return X, U, Y


def _kalman(t, U, Y):
    """filterpy's KF (update first from x0, P0) and RTS smoother with F_k = expm(A dt_k)."""
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.Q, kf.R, kf.H = X0.copy(), P0 * np.eye(2), Q * np.eye(2), R * np.eye(1), \
        np.array([[1.0, 0.0]])
    xs, Ps, Fs = [], [], [np.eye(2)]
    for k, y in enumerate(Y):
        if k:
            h = t[k] - t[k - 1]
            M = expm(np.block([[A, B[:, None]], [np.zeros((1, 3))]]) * h)
            kf.F, kf.B = M[:2, :2], M[:2, 2:]
            kf.predict(u=U[k - 1])
            Fs.append(M[:2, :2])
        kf.update(y)
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    Fs = np.array(Fs[1:] + [np.eye(2)])   # filterpy's rts_smoother: Fs[k] from x_k
    return np.array(xs), np.array(Ps), Fs


def test_estimators_on_irregular_samples_are_the_kalman_filter():
    """EKF, UKF and MHE (filtering arrival cost) with replay(t=) equal the Kalman filter
    with each interval's exact F; RK4 with 40 substeps is expm to 1e-12 here."""
    t = _times()
    X, U, Y = _record(t)
    xs, Ps, _ = _kalman(t, U, Y)
    m = _oscillator(substeps=40, variable_dt=True)
    tuning = dict(Q=Q, R=R, x0=X0, P0=P0)
    for est in (estim.EKF(m, **tuning), estim.UKF(m, **tuning),
                estim.MHE(m, horizon=8, solver="gauss-newton", **tuning),
                estim.MHE(m, horizon=8, solver="ipopt", **tuning)):
        log = estim.replay(est, Y, U, X, t=t)
        assert np.all(log.status == "ok")
        np.testing.assert_allclose(log.x_hat, xs, atol=1e-8, err_msg=type(est).__name__)
    # the intervals matter: the same data at the model's fixed dt are far off
    fixed = estim.replay(estim.EKF(m, **tuning), Y, U, X)
    assert np.abs(fixed.x_hat - xs).max() > 0.1


def test_full_information_on_irregular_samples_is_the_rts_smoother():
    t = _times()
    X, U, Y = _record(t)
    xs, Ps, Fs = _kalman(t, U, Y)
    m = _oscillator(substeps=40, variable_dt=True)
    fit = estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y, U, t=t)
    assert fit.status == "ok"
    # reference: the same problem solved as a batch least squares (exact F_k, B_k)
    T = len(t)
    rows, rhs = [], []
    W0, WQ, WR = 1 / np.sqrt(P0), 1 / np.sqrt(Q), 1 / np.sqrt(R)
    for i in range(2):
        r = np.zeros(2 * T)
        r[i] = W0
        rows.append(r)
        rhs.append(W0 * X0[i])
    for k in range(T - 1):
        h = t[k + 1] - t[k]
        M = expm(np.block([[A, B[:, None]], [np.zeros((1, 3))]]) * h)
        for i in range(2):
            r = np.zeros(2 * T)
            r[2 * (k + 1) + i] = WQ
            r[2 * k:2 * k + 2] = -WQ * M[i, :2]
            rows.append(r)
            rhs.append(WQ * M[i, 2] * U[k, 0])
    for k in range(T):
        r = np.zeros(2 * T)
        r[2 * k] = WR
        rows.append(r)
        rhs.append(WR * Y[k, 0])
    ref = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0].reshape(T, 2)
    np.testing.assert_allclose(fit.x, ref, atol=1e-8)
    np.testing.assert_allclose(fit.x[-1], xs[-1], atol=1e-8)     # the filter's last state
    np.testing.assert_allclose(fit.P_last, Ps[-1], atol=1e-10)
    # and the recursive form agrees
    log = estim.replay(estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0), Y, U, X, t=t)
    np.testing.assert_allclose(log.x_hat, xs, atol=1e-8)
    # regular stamps at the model's dt are the default
    t_reg = np.arange(len(t)) * 0.1
    a = estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y, U, t=t_reg)
    b = estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y, U)
    np.testing.assert_allclose(a.x, b.x, atol=1e-12)   # arange * 0.1: rounding apart
    # filterpy's rts_smoother (no input term): a record fitted without inputs
    X2, _, Y2 = _record(t, seed=3)
    xs2, Ps2, Fs2 = _kalman(t, np.zeros_like(U), Y2)
    smooth = rts_smoother(xs2, Ps2, Fs2, np.repeat(Q * np.eye(2)[None], len(t), 0))[0]
    fit2 = estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y2, np.zeros_like(U), t=t)
    np.testing.assert_allclose(fit2.x, smooth, atol=1e-8)


def test_fixed_dt_models_refuse_other_intervals():
    m = _oscillator()
    t = _times(20)
    X, U, Y = _record(t)
    ekf = estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="variable_dt=True"):
        estim.replay(ekf, Y, U, X, t=t)
    with pytest.raises(ValueError, match="variable_dt=True"):
        estim.FullInformation(m, Q=Q, R=R).fit(Y, U, t=t)
    with pytest.raises(ValueError, match="variable_dt=True"):
        ekf.step(Y[0], U[0], dt=0.2)
    with pytest.raises(ValueError, match="variable_dt=True"):
        m.f(X0, [0.0], dt=0.2)
    # time stamps at the model's spacing are fine (and change nothing)
    t_reg = 5.0 + np.arange(20) * 0.1
    a = estim.replay(estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0), Y, U, X, t=t_reg)
    b = estim.replay(estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0), Y, U, X)
    np.testing.assert_array_equal(a.x_hat, b.x_hat)
    np.testing.assert_array_equal(a.t, t_reg)
    # a discrete model takes any increasing times (labels)
    d = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: 0.9 * x,
                    output=lambda x, u, p: x)
    estim.replay(estim.EKF(d, Q=0.1, R=0.1, x0=[0.0], P0=1.0), np.ones((5, 1)),
                 t=[0.0, 0.1, 0.5, 0.6, 2.0])


def test_bad_intervals_and_unsupported_uses():
    m = _oscillator(variable_dt=True)
    ekf = estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0)
    for bad in (0.0, -0.1, np.nan, np.inf):
        with pytest.raises(ValueError, match="dt"):
            ekf.step([0.0], [0.0], dt=bad)
    with pytest.raises(TypeError, match="dt"):
        ekf.step([0.0], [0.0], dt="0.1")
    with pytest.raises(ValueError, match="t must be strictly increasing"):
        estim.replay(ekf, np.zeros((3, 1)), t=[0.0, 0.2, 0.2])
    with pytest.raises(ValueError, match="ShootingObserver needs samples at the model's fixed"):
        estim.ShootingObserver(m, window=5, every=1, R=R, x0=X0)
    with pytest.raises(ValueError, match="variable_dt=True needs a continuous model"):
        estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: x,
                    output=lambda x, u, p: x, variable_dt=True)
    with pytest.raises(TypeError, match="variable_dt"):
        _oscillator(variable_dt="yes")
    assert "variable" in repr(m)
    k = estim.Model(states=["x"], outputs=["y"], ode=lambda x, u, p: -p["k"] * x,
                    output=lambda x, u, p: x, params={"k": 1.0}, dt=0.1, variable_dt=True)
    assert k.augment("k").variable_dt and k.with_params(k=2.0).variable_dt


def test_simulate_with_a_variable_dt_model_uses_its_dt():
    a = estim.simulate(_oscillator(variable_dt=True),
                       estim.EKF(_oscillator(variable_dt=True), Q=Q, R=R, x0=X0, P0=P0),
                       x0=X0, n_steps=30, Q=Q, R=R, seed=4, inputs=lambda t: [np.sin(t)])
    b = estim.simulate(_oscillator(), estim.EKF(_oscillator(), Q=Q, R=R, x0=X0, P0=P0),
                       x0=X0, n_steps=30, Q=Q, R=R, seed=4, inputs=lambda t: [np.sin(t)])
    np.testing.assert_allclose(a.x, b.x, atol=1e-14)
    np.testing.assert_allclose(a.x_hat, b.x_hat, atol=1e-12)


# ------------------------------------------------------- late measurements (MHE)
@pytest.mark.parametrize("solver, arrival", [("gauss-newton", "filtering"),
                                             ("gauss-newton", "smoothing"),
                                             ("gauss-newton", "fixed"),
                                             ("ipopt", "filtering"), ("sqp", "none")])
def test_a_late_measurement_gives_the_estimates_of_an_on_time_one(solver, arrival):
    """van der Pol: y_30 (one output of it) is missing at step 30 and arrives at step 34;
    from then on the MHE's estimates are those of the run that had it on time, to the
    last bit (the MHE goes back and runs the steps again)."""
    sc = estim.scenarios.van_der_pol(n_steps=60)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2)
    Y = log.y.copy()
    Y[12, 1] = np.nan                       # missing for good in both runs
    late = Y.copy()
    late[30, 0] = np.nan

    def mhe():
        return estim.MHE(sc.model, horizon=10, solver=solver, arrival_cost=arrival,
                         max_lag=6, **sc.tuning)

    on_time = estim.replay(mhe(), Y)
    est = mhe()
    got = []
    for k, y in enumerate(late):
        x = est.step(y)
        if k == 34:
            x = est.insert([Y[30, 0], np.nan], lag=4)
            assert est.info.status == on_time.status[k]
        got.append(x)
    got = np.array(got)
    np.testing.assert_array_equal(got[34:], on_time.x_hat[34:])
    assert np.abs(got[30:34] - on_time.x_hat[30:34]).max() > 0   # before it arrived
    # the value replaced nothing measured: the second output of step 30 stays
    np.testing.assert_array_equal(est._past[-1][1], Y[59])


def test_late_measurement_arguments():
    sc = estim.scenarios.van_der_pol(n_steps=10)
    est = estim.MHE(sc.model, horizon=5, solver="gauss-newton", max_lag=3, **sc.tuning)
    with pytest.raises(ValueError, match=r"lag must be below the number of steps kept \(0"):
        est.insert([0.0, 0.0], lag=0)
    for y in np.random.default_rng(0).standard_normal((5, 2)):
        last = est.step(y)
    with pytest.raises(ValueError, match=r"lag must be below .*max_lag=3"):
        est.insert([0.0, 0.0], lag=3)
    with pytest.raises(ValueError, match="lag must be"):
        est.insert([0.0, 0.0], lag=-1)
    with pytest.raises(ValueError, match="y must"):
        est.insert([0.0, np.inf], lag=1)
    x = est.insert([np.nan, np.nan], lag=2)     # nothing new: the same estimate again
    np.testing.assert_array_equal(x, last)
    plain = estim.MHE(sc.model, horizon=5, solver="gauss-newton", **sc.tuning)
    plain.step([0.0, 0.0])
    with pytest.raises(ValueError, match="max_lag=0"):
        plain.insert([0.0, 0.0], lag=0)
