"""Quaternions and angles as manifold states: the EKF against a textbook multiplicative
EKF written here with numpy (Markley & Crassidis, ch. 6), the UKF's tangent sigma points,
the consistency over seeds, wrapped angles, and the declaration's errors."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.stats import chi2

import estim
from estim._manifold import NP, Manifold, wrap

DT = 0.1
SUN, MAG = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.6, 0.8])  # inertial directions
Q_GYRO, R_VEC = 1e-6, 1e-4


def _qmul_sym(a, b):
    aw, ax, ay, az = (a[i] for i in range(4))
    bw, bx, by, bz = (b[i] for i in range(4))
    return ca.vertcat(aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)


def attitude_model() -> estim.Model:
    """Gyro-driven attitude: q+ = q (x) Exp(omega dt) (the gyro rates the input), a sun
    sensor and a magnetometer measuring the inertial directions in body axes,
    R(q)^T r."""
    def step(q, w, p):
        n = ca.sqrt(ca.sumsqr(w)) * DT
        half = ca.if_else(n > 0, ca.sin(n / 2) / ca.if_else(n > 0, n, 1), 0.5)
        return _qmul_sym(q, ca.vertcat(ca.cos(n / 2), half * w * DT))

    def body(q, r):
        qc = ca.vertcat(q[0], -q[1], -q[2], -q[3])
        return _qmul_sym(_qmul_sym(qc, ca.vertcat(0, *r)), q)[1:]

    return estim.Model(states=["q0", "q1", "q2", "q3"], inputs=["wx", "wy", "wz"],
                       outputs=["sx", "sy", "sz", "mx", "my", "mz"], dynamics=step,
                       output=lambda q, u, p: ca.vertcat(body(q, SUN), body(q, MAG)),
                       quaternions=[("q0", "q1", "q2", "q3")], dt=DT, name="attitude")


# ------------------------------------------------------------ the numpy reference
def qmul(a, b):
    aw, av, bw, bv = a[0], a[1:], b[0], b[1:]
    return np.r_[aw * bw - av @ bv, aw * bv + bw * av + np.cross(av, bv)]


def qexp(phi):
    n = np.linalg.norm(phi)
    if n == 0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.r_[np.cos(n / 2), np.sin(n / 2) * phi / n]


def rotation(q):
    """The rotation matrix R(q) (body to inertial) of a unit quaternion."""
    w, v = q[0], q[1:]
    vx = skew(v)
    return np.eye(3) + 2 * w * vx + 2 * vx @ vx


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def right_jacobian(phi):
    """The right Jacobian of SO(3) (Chirikjian 2011; Sola et al. 2018, eq. 143)."""
    t = np.linalg.norm(phi)
    K = skew(phi)
    if t < 1e-8:
        return np.eye(3) - K / 2 + K @ K / 6
    return np.eye(3) - (1 - np.cos(t)) / t**2 * K + (t - np.sin(t)) / t**3 * K @ K


def textbook_mekf(Y, U, q0, P0):
    """Markley & Crassidis (2014), sec. 6.2.1, with a gyro as input (no bias): propagate
    q- = q (x) Exp(omega dt), P- = Phi P Phi^T + Q with Phi = R(Exp(omega dt))^T; update
    with the body vectors b = R(q-)^T r, H = [b x], delta = K (y - b), q+ = q- (x)
    Exp(delta), Joseph form; then the reset of the covariance to the new reference,
    P+ = J_r(delta) P+ J_r(delta)^T."""
    q, P = np.array(q0, dtype=float), np.array(P0, dtype=float)
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            dq = qexp(U[k - 1] * DT)
            q = qmul(q, dq)
            q /= np.linalg.norm(q)
            Phi = rotation(dq).T
            P = Phi @ P @ Phi.T + Q_GYRO * np.eye(3)
        A = rotation(q).T  # the attitude matrix, inertial to body
        b = np.r_[A @ SUN, A @ MAG]
        H = np.vstack([skew(A @ SUN), skew(A @ MAG)])
        R = R_VEC * np.eye(6)
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        delta = K @ (y - b)
        q = qmul(q, qexp(delta))
        q /= np.linalg.norm(q)
        IKH = np.eye(3) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        J = right_jacobian(delta)
        P = J @ P @ J.T
        xs.append(q.copy())
        Ps.append(P.copy())
    return np.array(xs), np.array(Ps)


def scenario(T=150, guess_angle=0.1):
    k = np.arange(T)
    U = 0.1 * np.column_stack([np.sin(0.05 * k), np.cos(0.03 * k), 0.5 * np.ones(T)])
    guess = [np.cos(guess_angle / 2), np.sin(guess_angle / 2), 0.0, 0.0]
    return estim.Scenario("attitude", attitude_model(), x0=[1.0, 0.0, 0.0, 0.0], n_steps=T,
                          Q=Q_GYRO, R=R_VEC, inputs=U,
                          tuning=dict(Q=Q_GYRO, R=R_VEC, x0=guess, P0=0.05))


# -------------------------------------------------------------------- the checks
def test_manifold_operations_against_closed_forms():
    """Exp/Log inverse to rounding; the tangent Jacobian of the retraction's local
    coordinates at a nonzero step is the right Jacobian of SO(3) (closed form); wrap
    lands in (-pi, pi]."""
    M = Manifold(["q0", "q1", "q2", "q3", "psi"], ["b"], [("q0", "q1", "q2", "q3")],
                 ["psi"], ["b"])
    rng = np.random.default_rng(1)
    for scale in (1e-9, 1e-4, 0.5, 2.5):
        q = rng.standard_normal(4)
        x = np.r_[q / np.linalg.norm(q), 3.0]
        d = rng.standard_normal(4)
        d[:3] *= scale / np.linalg.norm(d[:3])
        np.testing.assert_allclose(M.local(x, M.retract(x, d, NP), NP),
                                   np.r_[d[:3], wrap(d[3])], atol=1e-15)
        np.testing.assert_allclose(M.retract(x, d, NP)[:4], qmul(x[:4], qexp(d[:3])),
                                   atol=1e-15)
    np.testing.assert_allclose(wrap(np.array([np.pi, -np.pi, 3 * np.pi, 0.1 - 2 * np.pi])),
                               [np.pi, np.pi, np.pi, 0.1], atol=1e-15)
    phi = np.array([0.3, -0.2, 0.5])
    e, xs = ca.SX.sym("e", 3), ca.SX.sym("x", 4)
    M3 = Manifold(["a", "b", "c", "d"], [], [("a", "b", "c", "d")])
    jac = ca.Function("J", [xs, e], [ca.jacobian(
        M3.local(M3.retract(xs, ca.DM(phi)), M3.retract(xs, phi + e)), e)])
    np.testing.assert_allclose(np.asarray(jac([1.0, 0, 0, 0], np.zeros(3))),
                               right_jacobian(phi), atol=1e-14)


def test_ekf_equals_the_textbook_mekf():
    sc = scenario()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    xs, Ps = textbook_mekf(log.y, sc.inputs, sc.tuning["x0"], 0.05 * np.eye(3))
    np.testing.assert_allclose(log.x_hat, xs, atol=1e-10)
    np.testing.assert_allclose(log.P, Ps, rtol=1e-9, atol=1e-16)
    assert log.P.shape == (sc.n_steps, 3, 3) and log.manifold is not None
    for X in (log.x, log.x_hat):  # on the unit sphere at every step
        assert np.abs(np.linalg.norm(X, axis=1) - 1).max() < 1e-12
    # the attitude error is an angle: |theta| = 2 acos(|q_hat . q|)
    angle = np.linalg.norm(estim.errors(log), axis=1)
    dots = np.clip(np.abs(np.sum(log.x * log.x_hat, axis=1)), 0, 1)
    np.testing.assert_allclose(angle, 2 * np.arccos(dots), atol=1e-7)
    # the whole-record filter is the step loop
    fr = estim.EKF(sc.model, **sc.tuning).filter(log.y, sc.inputs[:-1])
    np.testing.assert_allclose(fr.x, log.x_hat, atol=1e-14)


@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
def test_consistent_over_seeds(cls):
    """NEES/3 averaged over 100 seeds at each step against the two-sided 95 % band of
    chi2(300)/300; the steps inside the band are about 95 % (at least 88 %, three
    binomial standard deviations below), and the average over all steps and seeds lies
    in the band of chi2(3 S T')/(S T') widened to the same 95 % of its steps."""
    sc = scenario(T=60, guess_angle=0.05).replace(
        tuning=dict(Q=Q_GYRO, R=R_VEC, x0=[1.0, 0.0, 0.0, 0.0], P0=0.05**2 / 3))
    S, burn = 100, 10
    nees, est = [], cls(sc.model, **sc.tuning)  # simulate resets it
    for seed in range(S):
        # the truth starts from a random attitude error drawn from the prior
        err = np.random.default_rng(1000 + seed).normal(0, 0.05 / np.sqrt(3), 3)
        truth = sc.replace(x0=qexp(err))
        log = estim.simulate(truth, est, seed=seed)
        nees.append(estim.nees(log, burn_in=burn))
        assert np.abs(np.linalg.norm(log.x_hat, axis=1) - 1).max() < 1e-12
    per_step = np.mean(nees, axis=0) / 3
    lo, hi = chi2.ppf([0.025, 0.975], 3 * S) / (3 * S)
    inside = np.mean((per_step > lo) & (per_step < hi))
    assert inside >= 0.88, (inside, per_step.min(), per_step.max())
    assert lo < per_step.mean() < hi


def test_ukf_on_the_manifold_matches_the_ekf():
    """On small noise the UKF's tangent sigma points give the EKF's estimates to the
    linearisation error, on the sphere, with a 3 x 3 covariance."""
    sc = scenario()
    a = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2)
    for points in ("merwe", "cubature"):
        b = estim.simulate(sc, estim.UKF(sc.model, points=points, **sc.tuning), seed=2)
        assert b.P.shape == (sc.n_steps, 3, 3) and np.all(b.success)
        assert np.abs(np.linalg.norm(b.x_hat, axis=1) - 1).max() < 1e-12
        late = slice(20, None)
        assert np.abs(estim.errors(b)[late] - estim.errors(a)[late]).max() < 1e-4


def bearing_model(wrapped: bool) -> estim.Model:
    """A target circling the sensor at constant speed; the bearing atan2(py, px) is
    measured, an angle output when ``wrapped``; the heading psi (an angle state) turns at
    the rate omega."""
    def f(x, u, p):
        return ca.vertcat(x[0] + DT * x[3] * ca.cos(x[2]), x[1] + DT * x[3] * ca.sin(x[2]),
                          x[2] + DT * x[4], x[3], x[4])

    return estim.Model(states=["px", "py", "psi", "speed", "omega"],
                       outputs=["bearing", "range"], dynamics=f,
                       output=lambda x, u, p: ca.vertcat(ca.atan2(x[1], x[0]),
                                                         ca.sqrt(x[0] ** 2 + x[1] ** 2)),
                       angles=["psi"] if wrapped else None,
                       output_angles=["bearing"] if wrapped else None, dt=DT)


def test_wrapped_bearings_stay_consistent():
    """A target circling the origin: its bearing crosses +-pi every lap. The filter that
    wraps the innovation (and the heading) tracks it with NEES about 5; the same filter
    without the declaration sees 2 pi jumps in the innovation and fails."""
    T = 400
    x0 = [10.0, 0.0, np.pi / 2, 2.0, 0.2]  # a circle of radius 10 about the sensor
    Q, R = np.diag([1e-4, 1e-4, 1e-6, 1e-6, 1e-8]), np.diag([1e-4, 0.01])
    logs = {}
    for wrapped in (True, False):
        m = bearing_model(wrapped)
        sc = estim.Scenario("bearing", m, x0=x0, n_steps=T, Q=Q, R=R,
                            tuning=dict(Q=Q, R=R, x0=[10.2, 0.2, 1.5, 2.0, 0.2],
                                        P0=np.diag([0.1, 0.1, 0.01, 0.01, 1e-4])))
        logs[wrapped] = estim.simulate(sc, estim.EKF(m, **sc.tuning), seed=0, warn=False)
    good, bad = logs[True], logs[False]
    assert np.abs(np.diff(good.y[:, 0])).max() > 6  # the bearing crossed +-pi
    assert np.all(good.success)
    assert 0.5 < np.mean(estim.nees(good, burn_in=50)) / 5 < 2
    assert np.all(np.abs(good.x_hat[:, 2]) <= np.pi)  # the heading kept wrapped
    assert estim.rmse(good, burn_in=50) < 0.1
    assert np.nanmax(bad.nis) > 1e4 or estim.rmse(bad, burn_in=50) > 1.0


def test_declarations_are_checked():
    common = dict(states=["q0", "q1", "q2", "q3", "w"], outputs=["y"], dt=0.1,
                  dynamics=lambda x, u, p: x, output=lambda x, u, p: x[4])
    with pytest.raises(ValueError, match="four state names"):
        estim.Model(quaternions=[("q0", "q1", "q2")], **common)
    with pytest.raises(ValueError, match=r"quaternions: 'qx' is not one of the states"):
        estim.Model(quaternions=[("q0", "q1", "q2", "qx")], **common)
    with pytest.raises(ValueError, match="names a state twice"):
        estim.Model(quaternions=[("q0", "q1", "q1", "q2")], **common)
    with pytest.raises(ValueError, match="belong to two quaternions"):
        estim.Model(quaternions=[("q0", "q1", "q2", "q3"), ("q3", "q2", "q1", "w")], **common)
    with pytest.raises(ValueError, match=r"angles: \['q1'\] are quaternion components"):
        estim.Model(quaternions=[("q0", "q1", "q2", "q3")], angles=["q1"], **common)
    with pytest.raises(ValueError, match="output_angles: 'z' is not one of the outputs"):
        estim.Model(output_angles=["z"], **common)
    with pytest.raises(TypeError, match="quaternions must be a list of 4-tuples"):
        estim.Model(quaternions="q0", **common)
    m = estim.Model(quaternions=[("q0", "q1", "q2", "q3")], **common)
    assert (m.nx, m.ndx) == (5, 4)
    with pytest.warns(estim.EstimationWarning, match="norm 2; normalised to 1"):
        ekf = estim.EKF(m, Q=1e-4, R=1e-2, x0=[2.0, 0, 0, 0, 1.0], P0=0.1)
    np.testing.assert_allclose(ekf.x0[:4], [1.0, 0, 0, 0])
    with pytest.raises(ValueError, match="x0: the quaternion at states .* is zero"):
        estim.EKF(m, Q=1e-4, R=1e-2, x0=[0.0, 0, 0, 0, 1.0], P0=0.1)
    with pytest.raises(ValueError, match=r"Q must be .* \(4, 4\) matrix"):
        estim.EKF(m, Q=np.eye(5), R=1e-2, x0=[1.0, 0, 0, 0, 1.0], P0=0.1)
    with pytest.raises(ValueError, match=r"ShootingObserver does not handle the "
                                         r"quaternions .* model.euclidean\(\)"):
        estim.ShootingObserver(m, window=3, every=2, R=1e-2, x0=[1.0, 0, 0, 0, 1.0])
    mhe = estim.MHE(m.euclidean(), horizon=5, Q=1e-4, R=1e-2, x0=[1.0, 0, 0, 0, 1.0], P0=0.1)
    assert mhe.model.ndx == 5
    with pytest.raises(ValueError, match=r"lower/upper: \['q0'\] are quaternion"):
        estim.EKF(m, Q=1e-4, R=1e-2, x0=[1.0, 0, 0, 0, 1.0], P0=0.1, clip=True,
                  lower={"q0": 0.0})


@pytest.mark.parametrize("make", [
    lambda m, t: estim.EnKF(m, n_ensemble=100, **t),
    lambda m, t: estim.EnKF(m, n_ensemble=100, variant="etkf", inflation=1.02, **t),
    lambda m, t: estim.ParticleFilter(m, n_particles=2000, **t)],
    ids=["enkf", "etkf", "pf"])
def test_ensembles_and_particles_on_the_manifold(make):
    """The EnKF (members moved by retraction, anomalies in the tangent space) and the
    bootstrap particle filter (noise in the tangent space, the weighted Karcher mean)
    keep every estimate on the unit sphere and track the attitude about as well as the
    EKF, with a 3 x 3 covariance; on the circling target they keep the heading wrapped
    and track it."""
    sc = scenario(T=100)
    ekf = estim.rmse(estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=1), burn_in=20)
    log = estim.simulate(sc, make(sc.model, sc.tuning), seed=1)
    assert log.P.shape == (100, 3, 3) and np.all(log.success)
    assert np.abs(np.linalg.norm(log.x_hat, axis=1) - 1).max() < 1e-12
    assert estim.rmse(log, burn_in=20) < 1.3 * ekf
    assert 0.5 < np.nanmean(estim.nees(log, burn_in=20)) / 3 < 2.5
    m = bearing_model(True)
    Q, R = np.diag([1e-4, 1e-4, 1e-6, 1e-6, 1e-8]), np.diag([1e-4, 0.01])
    tuning = dict(Q=10 * Q, R=R, x0=[10.2, 0.2, 1.5, 2.0, 0.2],
                  P0=np.diag([0.1, 0.1, 0.01, 0.01, 1e-4]))  # (10 Q: no impoverishment)
    bs = estim.Scenario("circling", m, x0=[10.0, 0, np.pi / 2, 2.0, 0.2], n_steps=250, Q=Q,
                        R=R, tuning=tuning)
    lg = estim.simulate(bs, make(m, tuning), seed=0, warn=False)
    assert np.abs(np.diff(lg.y[:, 0])).max() > 6 and np.all(lg.success)
    assert np.all(np.abs(lg.x_hat[:, 2]) <= np.pi) and estim.rmse(lg, burn_in=50) < 0.1
