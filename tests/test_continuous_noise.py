"""Continuous-time process noise (``Qc=``): the exact discretisation against closed forms,
the continuous-discrete EKF and UKF and the extended smoother against the exact Kalman
filter and filterpy's RTS smoother on irregular time stamps, and what is refused."""

from __future__ import annotations

from functools import partial

import casadi as ca
import numpy as np
import pytest

import estim
from estim._compile import compiler
from estim.solvers.kalman.continuous import van_loan

Q_DENSITY, R_VAR = 0.7, 0.05
DTS = np.logspace(-3, 1, 13)


def wiener_velocity_qd(dt: float, q: float = Q_DENSITY) -> np.ndarray:
    """The Wiener velocity model's Q_d(dt), known exactly."""
    return q * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])


@pytest.mark.parametrize("symbolic", [False, True])
def test_van_loan_is_the_closed_form_for_any_interval(symbolic):
    """Q_d and Phi of the Wiener velocity (A nilpotent) and of Ornstein-Uhlenbeck
    (x' = -theta x, Q_d = s (1 - e^{-2 theta dt}) / (2 theta)) to 1e-12 relative for dt from
    1e-3 to 10, as numbers and as a CasADi Function of a symbolic interval (measured:
    7.4e-15 at worst)."""
    A1, W1 = np.array([[0.0, 1.0], [0.0, 0.0]]), np.diag([0.0, Q_DENSITY])
    theta, s = 1.3, 0.5
    A2, W2 = np.array([[-theta]]), np.array([[s]])
    if symbolic:
        d = ca.SX.sym("dt")
        funs = [ca.Function("vl", [d], list(van_loan(ca.DM(A), ca.DM(W), d)))
                for A, W in ((A1, W1), (A2, W2))]

        def disc(i, dt):
            return [np.asarray(v) for v in funs[i](dt)]
    else:
        def disc(i, dt):
            return van_loan(*((A1, W1), (A2, W2))[i], dt)

    for dt in DTS:
        Phi, Qd = disc(0, dt)
        ref = wiener_velocity_qd(dt)
        assert np.abs(Qd - ref).max() <= 1e-12 * np.abs(ref).max()
        np.testing.assert_allclose(Phi, [[1.0, dt], [0.0, 1.0]], rtol=1e-12, atol=0)
        Phi, Qd = disc(1, dt)
        ref = s * (1 - np.exp(-2 * theta * dt)) / (2 * theta)
        assert abs(Qd[0, 0] - ref) <= 1e-12 * ref
        assert abs(Phi[0, 0] - np.exp(-theta * dt)) <= 1e-12 * np.exp(-theta * dt)


def wiener_velocity(**kw) -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"],
                       ode=lambda x, u, p: ca.vertcat(x[1], 0), output=lambda x, u, p: x[0],
                       variable_dt=True, dt=0.1, noise_input=[[0.0], [1.0]], **kw)


def irregular_record(T: int = 60, seed: int = 0, lo: float = 1e-3, hi: float = 1.0,
                     uniform: float | None = None):
    """Stamps with intervals log-uniform in [lo, hi] (default 1 ms to 1 s; or all
    ``uniform``) and the Wiener velocity's positions measured at them (the exact
    transition of each interval)."""
    rng = np.random.default_rng(seed)
    dts = np.full(T - 1, uniform) if uniform else \
        np.exp(rng.uniform(np.log(lo), np.log(hi), T - 1))
    x, Y = np.array([0.0, 1.0]), []
    for k in range(T):
        if k:
            x = np.array([[1.0, dts[k - 1]], [0.0, 1.0]]) @ x + rng.multivariate_normal(
                np.zeros(2), wiener_velocity_qd(dts[k - 1]))
        Y.append([x[0] + rng.normal(0.0, np.sqrt(R_VAR))])
    return np.concatenate([[0.0], np.cumsum(dts)]), dts, np.array(Y)


def exact_rts(xs, Ps, dts):
    """filterpy's RTS smoother of the exact Kalman filter's ``(xs, Ps)``, each interval's
    exact transition and Q_d."""
    from filterpy.kalman import rts_smoother

    Fs = [np.array([[1.0, dt], [0.0, 1.0]]) for dt in dts] + [np.eye(2)]
    Qs = [wiener_velocity_qd(dt) for dt in dts] + [np.eye(2)]
    xr, Pr, _, _ = rts_smoother(xs, Ps, Fs, Qs)
    return xr, Pr


def exact_kalman(Y, dts, x0, P0):
    """The Kalman filter of the exact discretisation, interval by interval (numpy)."""
    x, P, xs, Ps = x0.copy(), P0.copy(), [], []
    H = np.array([[1.0, 0.0]])
    for k, y in enumerate(Y):
        if k:
            F = np.array([[1.0, dts[k - 1]], [0.0, 1.0]])
            x, P = F @ x, F @ P @ F.T + wiener_velocity_qd(dts[k - 1])
        S = H @ P @ H.T + R_VAR
        K = P @ H.T / S
        x, P = x + (K * (y - H @ x)).ravel(), P - K @ S @ K.T
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("make", [
    lambda m, **t: estim.EKF(m, **t),
    lambda m, **t: estim.UKF(m, **t),
    lambda m, **t: estim.UKF(m, **t, points="cubature"),
    pytest.param(lambda m, **t: estim.EKF(m, **t, jit=True), marks=pytest.mark.skipif(
        compiler() is None, reason="no C compiler"))], ids=["ekf", "ukf", "ckf", "ekf-jit"])
def test_continuous_discrete_filters_are_the_exact_kalman_filter(make):
    """On the Wiener velocity model the moment equations are polynomials of degree <= 3 in
    time, which the Runge-Kutta sub-steps integrate exactly: over intervals from 1 ms to
    1 s the CD-EKF and CD-UKF (any rule) are the Kalman filter of the exact
    discretisation, to 1e-12, in ``filter`` and ``step``; the extended and unscented
    smoothers are filterpy's RTS smoother on that discretisation."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    f = make(wiener_velocity(), Qc=Q_DENSITY, R=R_VAR, x0=x0, P0=P0)
    xs, Ps = exact_kalman(Y, dts, x0, P0)
    res = f.filter(Y, t=t)
    np.testing.assert_allclose(res.x, xs, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.P, Ps, rtol=0, atol=1e-12)
    log = estim.replay(f, Y, t=t)
    np.testing.assert_allclose(log.x_hat, xs, rtol=0, atol=1e-12)
    assert set(res.status) == {"ok"}
    # the continuous-discrete extended and unscented smoothers
    xr, Pr = exact_rts(xs, Ps, dts)
    sm = f.smooth(Y, t=t)
    np.testing.assert_allclose(sm.x, xr, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sm.P, Pr, rtol=0, atol=1e-12)


@pytest.mark.parametrize("make", [estim.EKF, estim.UKF, partial(estim.UKF, points="cubature5")],
                         ids=["ekf", "ukf", "ukf-cubature5"])
def test_the_square_root_form_integrates_the_factor(make):
    """``EKF(Qc=..., form="sqrt")`` and ``UKF(...)`` carry the factor S by its own moment
    equation, dS/dt = S Phi(S^-1 dP/dt S^-T) (the UKF's dP/dt from sigma points drawn from
    S itself), which is not polynomial in time even where P is: the error against the exact
    filter falls at Runge-Kutta's fourth order as the sub-steps double (measured: 4.9e-4,
    2.9e-5, 1.8e-6 in the means at 4, 8, 16 sub-steps, for every filter; intervals up to 1 s
    with a tight posterior make it stiff), and every step stays ok."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    xs, Ps = exact_kalman(Y, dts, x0, P0)
    errors = []
    for n in (4, 8, 16):
        res = make(wiener_velocity(), Qc=Q_DENSITY, R=R_VAR, x0=x0, P0=P0, form="sqrt",
                   substeps=n).filter(Y, t=t)
        assert set(res.status) == {"ok"}
        errors.append(max(np.abs(res.x - xs).max(), np.abs(res.P - Ps).max()))
    assert errors[0] / errors[1] > 10 and errors[1] / errors[2] > 10
    assert errors[2] < 1e-5


def test_iterated_smoothers_with_a_continuous_noise(monkeypatch):
    """``EKF(Qc=...).smooth(iterations=K)`` (the IEKS, each interval's Q_d at the
    trajectory) and ``UKF(Qc=...).smooth(iterations=K)`` (the IPLS, the SDE's moments
    over each interval): on the Wiener velocity both are filterpy's RTS smoother on the
    exact discretisation after one more pass (measured 2.1e-14, 2.3e-14), and on van der
    Pol the IEKS converges to ``FullInformation(Qc=...)``'s optimum, its fixed point
    (measured 5.2e-11 in the means with the fit's weights re-linearised until they settle
    to 1e-12; with the default 1e-4, 7e-7)."""
    import estim.solvers.least_squares.reweighting as reweighting

    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    xs, Ps = exact_kalman(Y, dts, x0, P0)
    xr, Pr = exact_rts(xs, Ps, dts)
    for F in (estim.EKF, estim.UKF):
        sm = F(wiener_velocity(), Qc=Q_DENSITY, R=R_VAR, x0=x0, P0=P0).smooth(
            Y, t=t, iterations=3)
        assert sm.converged and sm.iterations == 2
        np.testing.assert_allclose(sm.x, xr, rtol=0, atol=1e-12)
        np.testing.assert_allclose(sm.P, Pr, rtol=0, atol=1e-12)
    m, t, Y = van_der_pol_stamps(noise=0.2, r=0.3)
    kw = {"Qc": 0.04 * np.eye(2), "R": 0.09, "x0": [2.0, 0.0], "P0": 0.1}
    monkeypatch.setattr(reweighting, "RELINEARISED", 1e-12)
    monkeypatch.setattr(reweighting, "RELINEARISATIONS", 20)
    fit = estim.FullInformation(m, **kw).fit(Y, t=t)
    assert fit.status == "ok"
    sm = estim.EKF(m, substeps=8, **kw).smooth(Y, t=t, iterations=30)
    assert sm.converged and sm.iterations < 30
    np.testing.assert_allclose(sm.x, fit.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sm.P, fit.P, rtol=0, atol=1e-9)
    ipls = estim.UKF(m, substeps=8, **kw).smooth(Y, t=t, iterations=30)
    assert ipls.converged and np.isfinite(ipls.P).all()


def van_der_pol_stamps(noise: float = 0.05, r: float = 0.1, seed: int = 1):
    """Van der Pol (mu = 2) with ``variable_dt``, 100 samples with intervals log-uniform in
    [0.01, 0.3] s, a diffusion of ``noise`` on each state and position measurements of
    standard deviation ``r``: ``(model, t, Y)``."""
    m = estim.Model(states=["x1", "x2"], outputs=["y"],
                    ode=lambda x, u, p: ca.vertcat(x[1], 2 * (1 - x[0] ** 2) * x[1] - x[0]),
                    output=lambda x, u, p: x[0], variable_dt=True, dt=0.1)
    rng = np.random.default_rng(seed)
    dts = np.exp(rng.uniform(np.log(0.01), np.log(0.3), 99))
    t = np.concatenate([[0.0], np.cumsum(dts)])
    x, Y = np.array([2.0, 0.0]), []
    for k in range(100):
        if k:
            x = np.asarray(m.F(x, [dts[k - 1]], m.p)).ravel() + \
                rng.normal(0.0, noise * np.sqrt(dts[k - 1]), 2)
        Y.append([x[0] + rng.normal(0.0, r)])
    return m, t, np.array(Y)


def test_the_square_root_ukf_meets_the_covariance_form_on_a_nonlinear_flow():
    """On van der Pol (mu = 2, stamps from 10 ms to 0.3 s) the square-root CD-UKF and the
    covariance one integrate the same moment equations (the factor's sigma points are the
    Cholesky factor's), each by its own Runge-Kutta steps: their difference falls at the
    fourth order as the sub-steps double (measured: 3.7e-5, 1.6e-6, 8.0e-8, 4.5e-9 at 4 to
    32 sub-steps)."""
    m, t, Y = van_der_pol_stamps()
    gaps = []
    for n in (4, 8, 16, 32):
        kw = {"Qc": 0.0025 * np.eye(2), "R": 0.01, "x0": [2.0, 0.0], "P0": 0.1, "substeps": n}
        a = estim.UKF(m, form="sqrt", **kw).filter(Y, t=t)
        b = estim.UKF(m, **kw).filter(Y, t=t)
        assert set(a.status) == set(b.status) == {"ok"}
        gaps.append(max(np.abs(a.x - b.x).max(), np.abs(a.P - b.P).max()))
    assert all(g0 / g1 > 12 for g0, g1 in zip(gaps[:-1], gaps[1:], strict=True))
    assert gaps[-1] < 1e-8


def test_a_per_transition_q_is_wrong_on_irregular_stamps():
    """The trap the option removes: with intervals from 1 ms to 1 s, the Kalman filter
    with one Q (the exact Q_d of the mean interval) is not the exact filter, the CD-EKF is."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    xs, _ = exact_kalman(Y, dts, x0, P0)
    one_q = estim.EKF(wiener_velocity(), Q=wiener_velocity_qd(dts.mean()), R=R_VAR, x0=x0,
                      P0=P0).filter(Y, t=t)
    assert np.abs(one_q.x - xs).max() > 0.05


def test_ornstein_uhlenbeck_with_sub_steps():
    """A decaying state, irregular stamps: the CD-EKF's covariance approaches the exact
    filter's as the sub-steps grow (RK4: the error falls about 16-fold per doubling); with
    ``discretisation="van-loan"`` it is the exact filter's to 1e-12."""
    theta, s = 1.3, 0.5
    m = estim.Model(states=["x"], outputs=["y"], ode=lambda x, u, p: -theta * x,
                    output=lambda x, u, p: x, variable_dt=True, dt=0.1)
    t, dts, Y = irregular_record(40, seed=2)
    P, Ps = 1.0, []
    for k in range(len(Y)):
        if k:
            e = np.exp(-theta * dts[k - 1])
            P = e * P * e + s * (1 - e * e) / (2 * theta)
        P = P - P * P / (P + R_VAR)
        Ps.append(P)
    errors = [np.abs(estim.EKF(m, Qc=s, R=R_VAR, x0=[0.0], P0=1.0, substeps=n).filter(
        Y, t=t).P[:, 0, 0] - Ps).max() for n in (2, 4, 8)]
    assert errors[2] < errors[1] < errors[0] < 1e-4
    assert errors[0] / errors[1] > 8 and errors[1] / errors[2] > 8
    # the exact discretisation of the (here exact) linearisation: exact with one sub-step
    vl = estim.EKF(m, Qc=s, R=R_VAR, x0=[0.0], P0=1.0, substeps=1, discretisation="van-loan")
    np.testing.assert_allclose(vl.filter(Y, t=t).P[:, 0, 0], Ps, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="give Qc"):
        estim.EKF(m, Q=1.0, R=R_VAR, x0=[0.0], P0=1.0, discretisation="van-loan")


def test_what_continuous_noise_refuses():
    m = wiener_velocity()
    kw = {"R": R_VAR, "x0": [0.0, 0.0], "P0": 1.0}
    with pytest.raises(ValueError, match="not both"):
        estim.EKF(m, Q=1.0, Qc=0.7, **kw)
    with pytest.raises(TypeError, match="missing the process noise: 'Q'"):
        estim.UKF(m, **kw)
    discrete = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: x,
                           output=lambda x, u, p: x)
    with pytest.raises(ValueError, match="needs a continuous model"):
        estim.EKF(discrete, Qc=1.0, R=1.0, x0=[0.0], P0=1.0)
    with pytest.raises(ValueError, match="noise_input must be an"):
        estim.Model(states=2, outputs=1, ode=lambda x, u, p: x, output=lambda x, u, p: x[0],
                    dt=0.1, noise_input=np.ones((3, 1)))
    with pytest.raises(ValueError, match="noise_input= says how"):
        estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: x,
                    output=lambda x, u, p: x, noise_input=[1.0])
    with pytest.raises(ValueError, match="Qc must be a scalar"):
        estim.EKF(m, Qc=np.eye(2), **kw)  # one noise input: Qc is 1 x 1
    with pytest.raises(ValueError, match="positive semi-definite"):
        estim.EKF(m, Qc=-1.0, **kw)
    f = estim.EKF(m, Qc=0.7, **kw)
    with pytest.raises(ValueError, match="spectral density"):
        f.set_tuning(Q=1.0)
    f.step([0.1])
    with pytest.raises(ValueError, match="dt must be a positive number"):
        f.step([0.2], dt=-1.0)
    with pytest.raises(ValueError, match="dt must be a positive number"):
        f.step([0.2], dt=0.0)
    with pytest.raises(ValueError, match="strictly increasing"):
        f.filter(np.zeros((3, 1)), t=[0.0, 1.0, 1.0])


@pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")
@pytest.mark.parametrize("kind", ["ekf", "ukf", "ukf_sqrt"])
def test_the_exported_filter_takes_the_interval(kind, tmp_path):
    """``variable_dt`` in the C export: ``step(f, y, u, dt, x_hat, P)``, the continuous
    noise inside the step; over the irregular record the same estimates, covariances and
    statuses as Python to 1e-10, a non-positive interval refused (-1, the filter
    unchanged), and the example program reads the stamps from the record's first column."""
    import csv
    import ctypes
    import subprocess

    from codegen_build import build

    from estim import codegen

    t, dts, Y = irregular_record(40, seed=3)
    F = estim.EKF if kind == "ekf" else estim.UKF
    f = F(wiener_velocity(), Qc=Q_DENSITY, R=R_VAR, x0=[0.0, 1.0], P0=1.0,
          form="sqrt" if kind.endswith("sqrt") else "covariance")
    codegen.export(f, tmp_path, name=f"cd_{kind}")
    lib = ctypes.CDLL(str(build(tmp_path, f"cd_{kind}")))
    d = ctypes.POINTER(ctypes.c_double)
    step = getattr(lib, f"cd_{kind}_step")
    step.argtypes = [ctypes.c_void_p, d, d, ctypes.c_double, d, d]
    getattr(lib, f"cd_{kind}_size").restype = ctypes.c_size_t
    memory = np.zeros(int(getattr(lib, f"cd_{kind}_size")()) // 8 + 1)
    assert getattr(lib, f"cd_{kind}_init")(ctypes.c_void_p(memory.ctypes.data)) == 0
    res = f.filter(Y, t=t)
    xs, Ps, codes = [], [], []
    for k, y in enumerate(Y):
        y = np.ascontiguousarray(y, dtype=float)
        x, P = np.empty(2), np.empty(4)
        if k == 5:  # a non-positive interval: refused, nothing changed
            assert step(ctypes.c_void_p(memory.ctypes.data), y.ctypes.data_as(d), None,
                        -1.0, x.ctypes.data_as(d), P.ctypes.data_as(d)) == -1
        codes.append(step(ctypes.c_void_p(memory.ctypes.data), y.ctypes.data_as(d), None,
                          float(dts[k - 1]) if k else 0.0, x.ctypes.data_as(d),
                          P.ctypes.data_as(d)))
        xs.append(x.copy())
        Ps.append(P.reshape(2, 2, order="F").copy())
    np.testing.assert_allclose(np.array(xs), res.x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.array(Ps), res.P, rtol=0, atol=1e-10)
    assert codes == [0 if s == "ok" else 1 for s in res.status]
    # the example program: t, y per line
    record = tmp_path / "record.csv"
    record.write_text("t,y\n" + "".join(f"{a!r},{b!r}\n" for a, b in zip(
        t.tolist(), Y[:, 0].tolist(), strict=True)))
    subprocess.run(["make", "-s", "example"], cwd=tmp_path, check=True,
                   capture_output=True)
    out = tmp_path / "estimates.csv"
    subprocess.run([str(tmp_path / f"cd_{kind}_example"), str(record), str(out)],
                   check=True, capture_output=True)
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["status", "p", "v", "sd_p", "sd_v"]
    np.testing.assert_allclose(np.array(rows[1:], dtype=float)[:, 1:3], res.x, rtol=0,
                               atol=1e-10)


def square_wiener_velocity() -> estim.Model:
    """The Wiener velocity with the identity noise input (Qc = diag(0, q)), the same
    noise as ``wiener_velocity()``'s one column with density q."""
    return estim.Model(states=["p", "v"], outputs=["y"],
                       ode=lambda x, u, p: ca.vertcat(x[1], 0), output=lambda x, u, p: x[0],
                       variable_dt=True, dt=0.1)


@pytest.mark.parametrize("estimator", ["ekf", "ukf"])
def test_the_likelihood_of_a_continuous_noise_is_the_exact_one(estimator):
    """``log_likelihood(..., Qc=, t=)`` on irregular stamps: the exact Kalman filter's
    log-likelihood (numpy, the exact discretisation of every interval) to 1e-10."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    x, P, ll = x0.copy(), P0.copy(), 0.0
    H = np.array([[1.0, 0.0]])
    for k, y in enumerate(Y):
        if k:
            F = np.array([[1.0, dts[k - 1]], [0.0, 1.0]])
            x, P = F @ x, F @ P @ F.T + wiener_velocity_qd(dts[k - 1])
        S = float((H @ P @ H.T)[0, 0]) + R_VAR
        e = float(y[0] - (H @ x)[0])
        ll -= 0.5 * (np.log(S) + e * e / S + np.log(2 * np.pi))
        K = P @ H.T / S
        x, P = x + (K * e).ravel(), P - K @ K.T * S
    got = estim.tuning.log_likelihood(square_wiener_velocity(), Y, Qc=np.diag([0.0, Q_DENSITY]),
                                      R=R_VAR, x0=x0, P0=P0, t=t, estimator=estimator)
    assert got == pytest.approx(ll, abs=1e-10)
    # the noise input's one column: Qc is (1, 1)
    got = estim.tuning.log_likelihood(wiener_velocity(), Y, Qc=Q_DENSITY, R=R_VAR, x0=x0,
                                      P0=P0, t=t, estimator=estimator)
    assert got == pytest.approx(ll, abs=1e-10)
    with pytest.raises(ValueError, match="one of them"):
        estim.tuning.log_likelihood(square_wiener_velocity(), Y, Q=1.0, Qc=1.0, R=R_VAR, t=t)
    with pytest.raises(ValueError, match=r"Qc must be .*\(1, 1\)"):
        estim.tuning.log_likelihood(wiener_velocity(), Y, Qc=np.eye(2), R=R_VAR, t=t)


def test_maximum_likelihood_recovers_a_spectral_density():
    """On 1500 irregular samples the density q (0.7) and R (0.05) are recovered within
    2.5 standard errors (measured: 0.824 +- 0.087 and 0.0519 +- 0.0021), the position's
    zero density at its boundary with the square noise input; with the model's one
    column the same estimates without a boundary."""
    t, _, Y = irregular_record(1500, seed=5)
    res = estim.tuning.maximum_likelihood(
        square_wiener_velocity(), Y, t=t, continuous=True, Q0=np.diag([1e-8, 0.3]), R0=0.1,
        x0=[0.0, 1.0], P0=np.diag([1.0, 2.0]), starts=1)
    assert abs(res.Q[1, 1] - Q_DENSITY) < 2.5 * res.stderr["Q"][1, 1]
    assert abs(res.R[0, 0] - R_VAR) < 2.5 * res.stderr["R"][0, 0]
    assert res.status.startswith("boundary: Q[0,0]")
    assert res.details["noise"].startswith("continuous")
    # through the noise input's one column: the density alone, the same optimum, no
    # boundary (and the default start, a hundredth of the prior seen through L, reaches it)
    for Q0 in (0.3, None):
        one = estim.tuning.maximum_likelihood(
            wiener_velocity(), Y, t=t, continuous=True, Q0=Q0, R0=0.1, x0=[0.0, 1.0],
            P0=np.diag([1.0, 2.0]), starts=1)
        assert one.status == "ok" and one.Q.shape == (1, 1)
        assert one.Q[0, 0] == pytest.approx(res.Q[1, 1], rel=1e-4)
        assert one.stderr["Q"][0, 0] == pytest.approx(res.stderr["Q"][1, 1], rel=1e-3)
        assert one.R[0, 0] == pytest.approx(res.R[0, 0], rel=1e-4)


def test_als_estimates_a_spectral_density():
    """``als(..., continuous=True)``: the density's basis discretised per interval keeps the
    autocovariance equations linear. On a uniform record it is the per-transition ALS with
    the basis Q_d(dt) (the same estimate to rounding, with the same gain); on 3000 samples
    of the Wiener velocity (q = 0.7, R = 0.05) with intervals log-uniform in [0.01, 0.5] s
    (the time-varying equations along EKF(Qc=)) two passes give q within 2 standard errors
    (measured 0.626 +- 0.059 and R 0.0515 +- 0.0016, against maximum likelihood's
    0.639 +- 0.052 and 0.0517 +- 0.0015). The error rate of the 2-standard-error bounds on
    such records is measured by benchmarks/continuous_als.py (100 records of 2000
    samples: benchmarks/results/continuous_als.md)."""
    t, _, Y = irregular_record(3000, seed=1, uniform=0.1)
    L = np.array([[0.5], [0.8]])  # a stable fixed gain for both designs
    cont = estim.tuning.als(wiener_velocity(), Y, t=t, continuous=True, gain=L)
    fixed = estim.Model(states=["p", "v"], outputs=["y"], dt=0.1,
                        ode=lambda x, u, p: ca.vertcat(x[1], 0), output=lambda x, u, p: x[0])
    G = np.linalg.cholesky(wiener_velocity_qd(0.1, 1.0))  # Q = q Q_d(0.1; 1) = G (q I) G^T
    per = estim.tuning.als(fixed, Y, gain=L, G=G, structure={"Q": "scalar"})
    assert cont.details["linearization"] == "time-invariant" and cont.Q.shape == (1, 1)
    assert cont.Q[0, 0] == pytest.approx(per.details["Q_w"][0, 0], rel=1e-9)
    assert cont.R[0, 0] == pytest.approx(per.R[0, 0], rel=1e-9)
    assert cont.details["noise"].startswith("continuous")
    t, _, Y = irregular_record(3000, seed=1, lo=0.01, hi=0.5)
    res = estim.tuning.als(wiener_velocity(), Y, t=t, continuous=True, x0=[0.0, 1.0],
                           P0=np.diag([1.0, 2.0]), iterations=2)
    assert res.details["linearization"] == "time-varying"
    assert abs(res.Q[0, 0] - Q_DENSITY) < 2 * res.stderr["Q"][0, 0]
    assert abs(res.R[0, 0] - R_VAR) < 2 * res.stderr["R"][0, 0]
    assert res.check.p_value > 0.01  # the tuned CD-EKF's innovations are white
    with pytest.raises(ValueError, match="t: the intervals run from"):
        estim.tuning.als(wiener_velocity(), Y, t=t)  # one Q for every interval: refused
    with pytest.raises(ValueError, match="G: with continuous=True"):
        estim.tuning.als(wiener_velocity(), Y, t=t, continuous=True, G=np.ones((2, 1)))
    discrete = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: 0.9 * x,
                           output=lambda x, u, p: x)
    with pytest.raises(ValueError, match="needs a continuous model"):
        estim.tuning.als(discrete, Y, continuous=True)


@pytest.mark.parametrize("solver", ["auto", "sqp"])
def test_full_information_weighs_each_interval_by_its_own_noise(solver):
    """``FullInformation(Qc=...)`` on irregular stamps (1 ms to 1 s): each defect weighed
    by the inverse of the exact Q_d of its interval, so the fit is filterpy's RTS
    smoother on the exact discretisation (the Laplace covariances too, with the
    Gauss-Newton solver; measured: 1.6e-14 in the means, 2.3e-10 in the covariances,
    whose weights at 1 ms span seven decades)."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    xs, Ps = exact_kalman(Y, dts, x0, P0)
    xr, Pr = exact_rts(xs, Ps, dts)
    fit = estim.FullInformation(wiener_velocity(), Qc=Q_DENSITY, R=R_VAR, x0=x0, P0=P0,
                                solver=solver).fit(Y, t=t)
    assert fit.status == "ok"
    np.testing.assert_allclose(fit.x, xr, rtol=0, atol=1e-9)
    if solver == "auto":
        np.testing.assert_allclose(fit.P, Pr, rtol=0, atol=1e-8)


def test_moving_horizon_with_continuous_noise_is_the_exact_filter():
    """``MHE(Qc=...)`` with the filtering arrival cost, whose covariance moves on with
    the Q_d of the interval leaving the window: on the linear-Gaussian model every
    estimate is the exact Kalman filter's (measured: 7.7e-10; with ``rti=True``, 2.1e-8),
    where the same MHE with one per-transition Q (the exact Q_d of 1 ms) is far off and
    flags it."""
    t, dts, Y = irregular_record()
    x0, P0 = np.array([0.0, 1.0]), np.diag([1.0, 2.0])
    xs, _ = exact_kalman(Y, dts, x0, P0)
    log = estim.replay(estim.MHE(wiener_velocity(), horizon=10, Qc=Q_DENSITY, R=R_VAR,
                                 x0=x0, P0=P0), Y, t=t)
    assert set(log.status) == {"ok"}
    np.testing.assert_allclose(log.x_hat, xs, rtol=0, atol=1e-8)
    # the real-time iteration: each transition's weight made at the prepared window, one
    # Gauss-Newton step, exact on the linear model up to the conditioning of weights
    # spanning seven decades (measured 2.1e-8)
    rti = estim.replay(estim.MHE(wiener_velocity(), horizon=10, Qc=Q_DENSITY, R=R_VAR,
                                 x0=x0, P0=P0, rti=True), Y, t=t)
    assert set(rti.status) == {"ok"}
    np.testing.assert_allclose(rti.x_hat, xs, rtol=0, atol=1e-7)
    one_q = estim.replay(estim.MHE(wiener_velocity(), horizon=10, R=R_VAR, x0=x0, P0=P0,
                                   Q=wiener_velocity_qd(1e-3)), Y, t=t)
    assert np.abs(one_q.x_hat - xs).max() > 0.1
    assert sum(s.startswith("suspect") for s in one_q.status) > 10


def test_what_the_windowed_estimators_refuse_with_continuous_noise():
    m = wiener_velocity()
    kw = {"R": R_VAR, "x0": [0.0, 0.0], "P0": 1.0}
    with pytest.raises(ValueError, match="not both"):
        estim.MHE(m, horizon=5, Q=1.0, Qc=0.7, **kw)
    with pytest.raises(ValueError, match="needs a continuous model"):
        estim.FullInformation(estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: x,
                                          output=lambda x, u, p: x), Qc=1.0, R=1.0)
    fie = estim.FullInformation(m, Qc=0.7, **kw)
    with pytest.raises(ValueError, match="spectral density"):
        fie.set_tuning(Q=1.0)
    # a constant parameter as a state: the noise never reaches it
    drift = estim.Model(states=["p", "v", "b"], outputs=["y"],
                        ode=lambda x, u, p: ca.vertcat(x[1] + x[2], 0, 0),
                        output=lambda x, u, p: x[0], dt=0.1,
                        noise_input=[[0.0], [1.0], [0.0]])
    with pytest.raises(ValueError, match="does not reach every state"):
        estim.MHE(drift, horizon=5, Qc=0.7, R=R_VAR, x0=np.zeros(3), P0=1.0)
