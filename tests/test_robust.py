"""Robust measurement costs (Huber, soft L1, Cauchy) for MHE and full information:
the losses against scipy's, the fits against ``scipy.optimize.least_squares`` with the
same loss, and the van der Pol MHE with 5 % of 100-sigma outliers."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import least_squares

import estim
from estim.solvers.least_squares.robust import DEFAULT_SCALES, OUTLIER_SIGMA, RobustLoss

TUNING = dict(Q=0.01, R=1.0, x0=[0.0, 0.0], P0=1.0)


@pytest.mark.parametrize("name", ["huber", "soft_l1", "cauchy"])
@pytest.mark.parametrize("c", [0.5, 1.345, 3.0])
def test_losses_are_twice_scipys(name, c):
    """scipy's cost of a residual vector that does not depend on x, with its loss and
    f_scale, is half estim's (estim's costs are sums of squares without the 1/2)."""
    r = np.array([0.0, 0.3, -1.0, 1.3, -2.0, 7.5, -40.0, 1e3])
    loss = RobustLoss(name, c)
    for k, rk in enumerate(r):
        ref = least_squares(lambda x, rk=rk: np.array([rk]) + 0 * x, [0.0], loss=name,
                            f_scale=c, max_nfev=1).cost
        assert loss.rho(r)[k] == pytest.approx(2 * ref, rel=1e-12, abs=1e-300)
    # near zero the loss is the square; the weight is rho'(r) / 2r, in (0, 1]
    assert loss.rho(np.array([1e-4]))[0] == pytest.approx(1e-8, rel=1e-6)
    h = 1e-6
    for rk in r[1:]:
        slope = (loss.rho(np.array([rk + h])) - loss.rho(np.array([rk - h])))[0] / (2 * h)
        assert loss.weight(np.array([rk]))[0] == pytest.approx(slope / (2 * rk), rel=1e-5)
    w = loss.weight(r)
    assert np.all((w > 0) & (w <= 1)) and w[0] == 1.0


def _record(T, seed, outliers, rate=None):
    m = estim.models.van_der_pol()
    log = estim.simulate(m, estim.EKF(m, **TUNING), x0=[1.5, 1.5], n_steps=T, Q=0.01,
                         R=1.0, seed=seed)
    X, Y = log.x, log.y.copy()
    rng = np.random.default_rng(1000 + seed)
    if rate is not None:
        mask = rng.random(Y.shape) < rate
    else:
        mask = np.zeros(Y.size, bool)
        mask[rng.choice(Y.size, outliers, replace=False)] = True
        mask = mask.reshape(Y.shape)
    Yo = Y.copy()
    Yo[mask] = X[mask] + 100.0 * rng.choice([-1.0, 1.0], size=mask.sum())
    return m, X, Y, Yo, mask


def _scipy_fit(m, Y, name, c):
    """The full-information problem of :class:`estim.FullInformation` with prior
    x0 = 0, P0 = I, Q = 0.01 I, R = I, its measurement residuals under the loss, solved
    by least_squares (trf) to 1e-15, with the exact Jacobian."""
    T = len(Y)
    nm = 2 + 2 * (T - 1)   # prior and process residuals: squared
    Z = ca.MX.sym("Z", 2, T)
    Fx = m.F.map(T - 1)(Z[:, :-1], ca.DM.zeros(0, T - 1), m.p)
    r = ca.vertcat(Z[:, 0], ca.vec((Z[:, 1:] - Fx) / 0.1), ca.vec(ca.DM(Y.T) - Z))
    fun = ca.Function("r", [ca.vec(Z)], [r, ca.jacobian(r, ca.vec(Z))])
    # z is column-major (2, T), which is estim's (T, 2) trajectory row by row

    loss = RobustLoss(name, c)

    def rho(z):  # scipy's convention: a function of z = f**2, with two derivatives
        out = np.vstack([z, np.ones_like(z), np.zeros_like(z)])
        s = np.sqrt(z[nm:])
        out[0, nm:] = loss.rho(s)
        out[1, nm:] = loss.weight(s)            # d rho / dz = rho'(s) / 2s
        h = 1e-6 * (1 + z[nm:])
        out[2, nm:] = (loss.weight(np.sqrt(z[nm:] + h)) -
                       loss.weight(np.sqrt(np.maximum(z[nm:] - h, 0)))) / (2 * h)
        return out

    return least_squares(lambda z: np.asarray(fun(z)[0]).ravel(),
                         np.zeros(2 * T), jac=lambda z: fun(z)[1].full(), loss=rho,
                         method="trf", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=5000)


@pytest.mark.parametrize("name", ["huber", "cauchy"])
@pytest.mark.parametrize("solver", ["gauss-newton", "ipopt"])
def test_full_information_matches_least_squares(name, solver):
    m, X, _, Yo, mask = _record(60, seed=3, outliers=6)
    c = DEFAULT_SCALES[name]
    ref = _scipy_fit(m, Yo, name, c)
    res = estim.FullInformation(m, solver=solver, loss=name, **TUNING).fit(Yo)
    assert res.status == "ok"
    # IRLS stops when its step is below xtol (1e-8) x (1 + max|x|); its linear rate
    # near this optimum (about 0.5) leaves a few times that
    np.testing.assert_allclose(res.x.ravel(), ref.x, atol=1e-6)
    assert res.cost == pytest.approx(2 * ref.cost, rel=1e-10)
    # the outliers are the values the loss weighted down, and only they are far out
    w = res.measurement_weights
    assert w.shape == (60, 2)
    inlier = RobustLoss(name, c).weight(np.array([OUTLIER_SIGMA]))[0]  # 6.1 sigma
    assert np.all(w[mask] < 0.02) and np.all(w[~mask] > inlier)
    # the plain fit is pulled away by them, the robust one is not
    plain = estim.FullInformation(m, **TUNING).fit(Yo)
    assert plain.measurement_weights is None
    rmse = [np.sqrt(np.mean((f.x - X) ** 2)) for f in (plain, res)]
    assert rmse[1] < 0.5 < 3.0 < rmse[0]


def test_a_huge_scale_is_least_squares():
    """Far beyond every residual, the robust fit is the least-squares fit (RTS smoother)."""
    m, _, Y, _, _ = _record(80, seed=5, outliers=0)
    plain = estim.FullInformation(m, **TUNING).fit(Y)
    wide = estim.FullInformation(m, loss="huber", f_scale=1e6, **TUNING).fit(Y)
    np.testing.assert_allclose(wide.x, plain.x, atol=1e-9)
    assert wide.cost == pytest.approx(plain.cost, rel=1e-12)
    assert np.all(wide.measurement_weights == 1.0)


def test_missing_values_and_long_records():
    """NaN values carry no weight; the mapped (chunked) graphs reweight like the
    unrolled one."""
    m, _, _, Yo, mask = _record(300, seed=2, outliers=10)
    Yo[50:60, 0] = np.nan
    Yo[100] = np.nan
    fits = [estim.FullInformation(m, loss="huber", solver_options={"mode": mode},
                                  **TUNING).fit(Yo) for mode in ("unrolled", "mapped")]
    assert all(f.status == "ok" for f in fits)
    # the chunked sums round differently: the linearly converging reweighted
    # iterations may stop one step apart, each within its tolerance
    np.testing.assert_allclose(fits[0].x, fits[1].x, atol=1e-6)
    w = fits[0].measurement_weights
    assert np.all(w[np.isnan(Yo)] == 1.0)
    assert np.all(w[mask & np.isfinite(Yo)] < 0.02)


def test_robust_mhe_with_five_percent_outliers():
    """van der Pol, MHE (N = 15, Gauss-Newton): 5 % of the values replaced by
    100-sigma outliers. The Huber MHE stays within 1.2x of its outlier-free RMSE,
    reports the steps ok and the outliers it saw; the least-squares MHE loses track."""
    rmse = {}
    for seed in range(4):
        m, X, Y, Yo, mask = _record(200, seed=seed, outliers=None, rate=0.05)
        assert mask.sum() >= 12
        for loss in ("squared", "huber"):
            for data, YY in (("clean", Y), ("outliers", Yo)):
                est = estim.MHE(m, horizon=15, solver="gauss-newton", loss=loss, **TUNING)
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", estim.EstimationWarning)
                    log = estim.replay(est, YY, None, X)
                e = log.x_hat[20:] - X[20:]
                rmse.setdefault((loss, data), []).append(np.sqrt(np.mean(np.sum(e**2, 1))))
                if loss == "huber" and data == "outliers":
                    # an outlier in the very first sample (one of two values) is
                    # undecidable: "suspect"; every later step is ok
                    assert np.all(log.status[1:] == "ok")
                    seen = [d["outliers"] for d in log.diagnostics]
                    # each outlier is seen in up to 15 windows
                    assert sum(seen) >= 14 * mask[:-14].sum()
    mean = {k: np.mean(v) for k, v in rmse.items()}
    assert mean["huber", "outliers"] <= 1.2 * mean["squared", "clean"]
    assert mean["huber", "clean"] <= 1.05 * mean["squared", "clean"]
    assert mean["squared", "outliers"] > 10 * mean["squared", "clean"]


@pytest.mark.parametrize("solver", ["ipopt", "sqp", "fatrop"])
def test_mhe_solvers_agree(solver):
    """The NLP solvers' reweighted solves reach the Gauss-Newton solver's estimates."""
    m, X, _, Yo, _ = _record(60, seed=1, outliers=None, rate=0.05)
    logs = [estim.replay(estim.MHE(m, horizon=10, solver=s, loss="cauchy", **TUNING), Yo,
                         None, X) for s in ("gauss-newton", solver)]
    np.testing.assert_allclose(logs[1].x_hat, logs[0].x_hat, atol=1e-5)


def test_full_information_steps_with_a_robust_loss():
    m, X, _, Yo, _ = _record(60, seed=4, outliers=4)
    log = estim.replay(estim.FullInformation(m, loss="huber", **TUNING), Yo, None, X)
    fit = estim.FullInformation(m, loss="huber", **TUNING).fit(Yo)
    assert np.all(log.status[2:] == "ok")
    np.testing.assert_allclose(log.x_hat[-1], fit.x[-1], atol=1e-6)


def test_lost_track_is_not_hidden_as_outliers():
    """Half the values of the window beyond 6.1 sigma is the estimate's fault, not the
    data's: the step is suspect."""
    m, X, Y, _, _ = _record(40, seed=0, outliers=0)
    est = estim.MHE(m, horizon=10, solver="gauss-newton", loss="huber", **TUNING)
    with pytest.warns(estim.EstimationWarning, match="steps failed"):
        log = estim.replay(est, Y + 50.0, None, X)
    assert not np.any(log.status[10:] == "ok")
    assert all(s.startswith(("suspect", "failed")) for s in log.status[10:])


@pytest.mark.parametrize("cls", ["MHE", "FullInformation"])
def test_bad_arguments(cls):
    m = estim.models.van_der_pol()
    kw = dict(TUNING, horizon=5) if cls == "MHE" else dict(TUNING)
    make = getattr(estim, cls)
    with pytest.raises(ValueError, match=r"loss must be one of .*did you mean 'huber'"):
        make(m, loss="hubber", **kw)
    with pytest.raises(TypeError, match="loss must be one of"):
        make(m, loss=1, **kw)
    with pytest.raises(ValueError, match="f_scale must be a positive number"):
        make(m, loss="huber", f_scale=0.0, **kw)
    with pytest.raises(ValueError, match="f_scale must be a positive number or None, got inf"):
        make(m, loss="cauchy", f_scale=np.inf, **kw)
    with pytest.raises(ValueError, match="f_scale applies to a robust loss"):
        make(m, f_scale=2.0, **kw)


def test_multi_rate_record_is_the_kalman_smoother():
    """The multi-rate example of docs/robust.md: position at 10 Hz, velocity at 1 Hz (NaN
    between); full information equals filterpy's KF + RTS with each sample's measured
    rows (the model is linear: RK4 of a linear ODE is a matrix)."""
    from filterpy.kalman import KalmanFilter, rts_smoother

    m = estim.Model(states=["p", "v"], outputs=["p_meas", "v_meas"],
                    ode=lambda x, u, p: [x[1], -0.5 * x[0]], output=lambda x, u, p: x,
                    dt=0.1, name="oscillator")
    log = estim.simulate(m, estim.EKF(m, Q=1e-4, R=[1e-2, 1e-4], x0=[1, 0], P0=1.0),
                         x0=[1.0, 0.0], n_steps=300, Q=1e-4, R=[1e-2, 1e-4], seed=0)
    Y = log.y.copy()
    Y[np.arange(len(Y)) % 10 != 0, 1] = np.nan
    fit = estim.FullInformation(m, Q=1e-4, R=[1e-2, 1e-4], x0=[1, 0], P0=1.0).fit(Y)
    A = np.asarray(m.F_x(np.zeros(2), [], m.p))
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.x, kf.P, kf.F, kf.Q = np.array([1.0, 0.0]), np.eye(2), A, 1e-4 * np.eye(2)
    R = np.diag([1e-2, 1e-4])
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            kf.predict()
        rows = np.flatnonzero(np.isfinite(y))
        kf.update(y[rows], R=R[np.ix_(rows, rows)], H=np.eye(2)[rows])
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    xs_s = rts_smoother(np.array(xs), np.array(Ps), np.repeat(A[None], len(Y), 0),
                        np.repeat(kf.Q[None], len(Y), 0))[0]
    np.testing.assert_allclose(fit.x, xs_s, atol=1e-8)
    np.testing.assert_allclose(fit.P_last, Ps[-1], atol=1e-10)


def test_the_student_t_loss_is_the_t_likelihood():
    """``loss="student-t", dof=nu``: the loss is twice the negative log-density of
    Student's t (scipy.stats) less its value at zero, its weight rho'(r) / 2r; the
    full-information fit is scipy's least_squares with that loss written from the density
    (to 1e-6, the IRLS stopping rule, and the same cost to 1e-10), and it resists the
    100-sigma outliers that pull the least-squares fit away."""
    from scipy import stats

    nu = 4.0
    r = np.array([0.0, 0.3, -1.0, 1.3, -2.0, 7.5, -40.0, 1e3])
    loss = RobustLoss("student-t", nu)
    want = -2 * (stats.t.logpdf(r, nu) - stats.t.logpdf(0.0, nu))
    np.testing.assert_allclose(loss.rho(r), want, rtol=1e-12, atol=1e-14)
    h = 1e-6
    for rk in r[1:]:
        slope = (loss.rho(np.array([rk + h])) - loss.rho(np.array([rk - h])))[0] / (2 * h)
        assert loss.weight(np.array([rk]))[0] == pytest.approx(slope / (2 * rk), rel=1e-5)
    m, X, _, Yo, mask = _record(60, seed=3, outliers=6)
    T, nm = len(Yo), 2 + 2 * 59
    Z = ca.MX.sym("Z", 2, T)
    Fx = m.F.map(T - 1)(Z[:, :-1], ca.DM.zeros(0, T - 1), m.p)
    res_ = ca.vertcat(Z[:, 0], ca.vec((Z[:, 1:] - Fx) / 0.1), ca.vec(ca.DM(Yo.T) - Z))
    fun = ca.Function("r", [ca.vec(Z)], [res_, ca.jacobian(res_, ca.vec(Z))])

    def rho(z):  # the t's: (nu + 1) log(1 + z / nu) of z = r^2, on the measurements
        out = np.vstack([z, np.ones_like(z), np.zeros_like(z)])
        zm = z[nm:]
        out[0, nm:] = (nu + 1) * np.log1p(zm / nu)
        out[1, nm:] = (nu + 1) / (nu + zm)
        out[2, nm:] = -(nu + 1) / (nu + zm) ** 2
        return out

    ref = least_squares(lambda z: np.asarray(fun(z)[0]).ravel(), np.zeros(2 * T),
                        jac=lambda z: fun(z)[1].full(), loss=rho, method="trf", xtol=1e-15,
                        ftol=1e-15, gtol=1e-15, max_nfev=5000)
    fit = estim.FullInformation(m, loss="student-t", dof=nu, **TUNING).fit(Yo)
    assert fit.status == "ok"
    np.testing.assert_allclose(fit.x.ravel(), ref.x, atol=1e-6)
    assert fit.cost == pytest.approx(2 * ref.cost, rel=1e-10)
    assert np.all(fit.measurement_weights[mask] < 0.01)
    plain = estim.FullInformation(m, **TUNING).fit(Yo)
    rmse = [np.sqrt(np.mean((f.x - X) ** 2)) for f in (plain, fit)]
    assert rmse[1] < 0.5 < 3.0 < rmse[0]
    log = estim.replay(estim.MHE(m, horizon=10, loss="student-t", dof=nu, **TUNING), Yo)
    assert np.sqrt(np.mean((log.x_hat - X) ** 2)) < 0.6


def test_what_the_student_t_loss_refuses():
    m = estim.models.van_der_pol()
    with pytest.raises(TypeError, match="needs dof="):
        estim.MHE(m, horizon=5, loss="student-t", **TUNING)
    with pytest.raises(ValueError, match="give loss='student-t'"):
        estim.FullInformation(m, dof=4, **TUNING)
    with pytest.raises(ValueError, match="dof must be above 2"):
        estim.FullInformation(m, loss="student-t", dof=2, **TUNING)
    with pytest.raises(ValueError, match="f_scale applies to"):
        estim.MHE(m, horizon=5, loss="student-t", dof=4, f_scale=2.0, **TUNING)
