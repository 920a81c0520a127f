"""Moving horizon and full-information estimation on manifold states: the windows are
optima of the intrinsic cost (tangent residuals, the quaternion moved by retraction),
checked against scipy's least_squares on residuals written here with numpy, and the
covariances against the inverse Gauss-Newton matrix of those residuals; the estimates on
the unit sphere, wrapped angles through the windows, and what is refused."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from test_attitude import (
    DT,
    MAG,
    Q_GYRO,
    R_VEC,
    SUN,
    bearing_model,
    qexp,
    qmul,
    rotation,
    scenario,
)

import estim

#: Both solvers stop on steps below 1e-8 relative to 1 + max|x| (estim's default xtol,
#: least_squares' xtol here): their optima may differ by a few of those steps.
STEP_TOL = 1e-7


def qlog(q):
    """The rotation vector phi with Exp(phi) = q (the hemisphere q_w >= 0)."""
    q = q if q[0] >= 0 else -q
    s = np.linalg.norm(q[1:])
    return 2.0 * np.arctan2(s, q[0]) * q[1:] / s if s > 1e-12 else 2.0 * q[1:]


def qinv(q):
    return np.r_[q[0], -q[1:]]


def whitened(P):
    """W with W^T W = P^-1."""
    return np.linalg.cholesky(np.linalg.inv(P)).T


def residuals(Q, Y, U, xbar, Pbar):
    """The window's residuals at the trajectory ``Q (n, 4)``: the arrival
    Log(xbar^-1 q_0), the process Log(F(q_k)^-1 q_{k+1}) with F(q) = q Exp(omega dt),
    and the measurements y - R(q)^T r, each whitened."""
    W0, wq, wr = whitened(Pbar), 1 / np.sqrt(Q_GYRO), 1 / np.sqrt(R_VEC)
    out = [W0 @ qlog(qmul(qinv(xbar), Q[0]))]
    for k in range(len(Q)):
        A = rotation(Q[k]).T
        out.append(wr * (Y[k] - np.r_[A @ SUN, A @ MAG]))
        if k + 1 < len(Q):
            pred = qmul(Q[k], qexp(U[k] * DT))
            out.append(wq * qlog(qmul(qinv(pred), Q[k + 1])))
    return np.concatenate(out)


def moved(Q, delta):
    return np.array([qmul(q, qexp(d)) for q, d in zip(Q, delta.reshape(-1, 3), strict=True)])


def circling(T):
    """The target circling the sensor (tests/test_attitude.py), its bearing and heading
    declared as angles: ``(model, tuning, scenario)`` of ``T`` samples."""
    Q, R = np.diag([1e-4, 1e-4, 1e-6, 1e-6, 1e-8]), np.diag([1e-4, 0.01])
    m = bearing_model(True)
    tuning = dict(Q=Q, R=R, x0=[10.2, 0.2, 1.5, 2.0, 0.2],
                  P0=np.diag([0.1, 0.1, 0.01, 0.01, 1e-4]))
    return m, tuning, estim.Scenario("bearing", m, x0=[10.0, 0.0, np.pi / 2, 2.0, 0.2],
                                     n_steps=T, Q=Q, R=R, tuning=tuning)


def check_optimum(Q, Y, U, xbar, Pbar, cost, P, away=True):
    """``Q`` minimises the residuals: least_squares from there (and, with ``away``, from
    0.05 rad away) finds no better trajectory; the cost is theirs and the covariances
    ``P`` (the last state's ``(3, 3)``, or every state's ``(n, 3, 3)``) the tangent
    blocks of the inverse Gauss-Newton matrix."""
    def fun(delta):
        return residuals(moved(Q, delta), Y, U, xbar, Pbar)

    n = 3 * len(Q)
    starts = [np.zeros(n)] + [np.random.default_rng(0).normal(0, 0.05, n)] * away
    for d0 in starts:
        fit = least_squares(fun, d0, xtol=1e-12, ftol=1e-15, gtol=1e-15)
        assert np.abs(fit.x).max() < STEP_TOL
        np.testing.assert_allclose(np.sum(fit.fun ** 2), cost, rtol=1e-9)
    np.testing.assert_allclose(np.sum(fun(np.zeros(n)) ** 2), cost, rtol=1e-12)
    # the Gauss-Newton matrix of the residuals along the retraction, by central
    # differences (their error ~ h^2 of the residuals' curvature)
    h = 1e-6
    J = np.column_stack([(fun(h * e) - fun(-h * e)) / (2 * h) for e in np.eye(n)])
    cov = np.linalg.inv(J.T @ J)
    blocks = np.array([cov[i:i + 3, i:i + 3] for i in range(0, n, 3)])
    np.testing.assert_allclose(P, blocks if P.ndim == 3 else blocks[-1], rtol=1e-6)


def test_full_information_is_the_intrinsic_optimum():
    sc = scenario(T=30, guess_angle=0.3)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3)
    U = sc.inputs[:-1]
    fie = estim.FullInformation(sc.model, **sc.tuning)
    res = fie.fit(log.y, U)
    assert res.success and res.P.shape == (30, 3, 3) and res.w.shape == (29, 3)
    assert np.abs(np.linalg.norm(res.x, axis=1) - 1).max() < 1e-12
    P0 = sc.tuning["P0"] * np.eye(3)
    # (from 0.05 rad away least_squares comes back to within 4e-10 too: the windows
    # below check that, on fewer variables)
    check_optimum(res.x, log.y, U, np.asarray(sc.tuning["x0"]), P0, res.cost, res.P,
                  away=False)
    # the process residuals reported are the tangent ones
    w = np.array([qlog(qmul(qinv(qmul(res.x[k], qexp(U[k] * DT))), res.x[k + 1]))
                  for k in range(29)])
    np.testing.assert_allclose(res.w, w, atol=1e-12)
    # the recursive form ends where the fit does
    ends = estim.replay(fie, log.y, sc.inputs).x_hat[-1]
    np.testing.assert_allclose(ends, res.x[-1], atol=STEP_TOL)


@pytest.mark.parametrize("arrival_cost", ["filtering", "smoothing"])
def test_each_mhe_window_is_the_intrinsic_optimum(arrival_cost):
    """Every window of a full MHE (its arrival mean and covariance as the estimator
    reports them) is the optimum of its own intrinsic cost."""
    sc = scenario(T=30, guess_angle=0.3)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=4)
    U, N = sc.inputs[:-1], 8
    run = estim.replay(estim.MHE(sc.model, horizon=N, arrival_cost=arrival_cost,
                                 **sc.tuning), log.y, sc.inputs)
    assert np.all(run.success) and run.P.shape == (30, 3, 3)
    assert np.abs(np.linalg.norm(run.x_hat, axis=1) - 1).max() < 1e-12
    for k in (N - 1, 15, 29):
        extra = run.diagnostics[k]
        window = extra["window"]
        Pbar = extra["arrival_covariance"]
        assert window.shape == (N, 4) and Pbar.shape == (3, 3)
        check_optimum(window, log.y[k - N + 1:k + 1], U[k - N + 1:k], extra["arrival_mean"],
                      Pbar, run.cost[k], run.P[k])


@pytest.mark.parametrize("solver", ["ipopt", "sqp", "fatrop"])
def test_every_solver_finds_the_same_windows(solver):
    """Ipopt, SQP and fatrop move in the tangent space too (their variables are steps
    from chart centres at the start, :func:`estim.solvers.least_squares.builders.charted`): the same
    trajectory as the Gauss-Newton solver, whose optimum is checked above, and the same
    MHE estimates and covariances, on the sphere."""
    sc = scenario(T=40, guess_angle=0.3)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3)
    U, M = sc.inputs[:-1], sc.model.manifold
    gn = estim.FullInformation(sc.model, **sc.tuning).fit(log.y, U)
    fit = estim.FullInformation(sc.model, solver=solver, **sc.tuning).fit(log.y, U)
    assert fit.success and np.abs(M.errors(fit.x, gn.x)).max() < STEP_TOL
    np.testing.assert_allclose(fit.cost, gn.cost, rtol=1e-9)
    kw = dict(horizon=8, **sc.tuning)
    a = estim.replay(estim.MHE(sc.model, **kw), log.y, sc.inputs)
    b = estim.replay(estim.MHE(sc.model, solver=solver, **kw), log.y, sc.inputs)
    assert np.all(b.success) and np.abs(M.errors(b.x_hat, a.x_hat)).max() < STEP_TOL
    np.testing.assert_allclose(b.P, a.P, rtol=1e-6)
    assert np.abs(np.linalg.norm(b.x_hat, axis=1) - 1).max() < 1e-12


def test_the_real_time_iteration_on_the_manifold():
    """rti=True: the start-up windows, solved to convergence, are the converged MHE's; then
    one Gauss-Newton step per sample, retracted, within 3 % of the converged MHE's
    attitude error (the accuracy asked of it on vector states), on the sphere."""
    sc = scenario(T=100)
    M = sc.model.manifold
    for seed in range(3):
        log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed)
        a = estim.replay(estim.MHE(sc.model, horizon=10, **sc.tuning), log.y, sc.inputs)
        b = estim.replay(estim.MHE(sc.model, horizon=10, rti=True, **sc.tuning), log.y,
                         sc.inputs)
        assert np.all(b.success) and b.P.shape == (100, 3, 3)
        assert np.abs(np.linalg.norm(b.x_hat, axis=1) - 1).max() < 1e-12
        assert np.abs(M.errors(b.x_hat[:10], a.x_hat[:10])).max() < STEP_TOL
        angle = [np.linalg.norm(M.errors(run.x_hat, log.x), axis=1)[20:].mean()
                 for run in (a, b)]
        assert angle[1] <= 1.03 * angle[0]


def test_bounds_on_the_other_states():
    """A bound on a vector state of a model with angles: every solver keeps it (active
    on 20 of 120 samples) and finds the Gauss-Newton solver's estimates."""
    m, tuning, sc = circling(120)
    y = estim.simulate(sc, estim.EKF(m, **tuning), seed=0, warn=False).y
    runs = {solver: estim.replay(estim.MHE(m, horizon=10, solver=solver,
                                           lower={"speed": 1.995}, **tuning), y, warn=False)
            for solver in ("gauss-newton", "ipopt", "sqp", "fatrop")}
    gn = runs.pop("gauss-newton")
    assert (gn.x_hat[:, 3] <= 1.995 + 1e-12).sum() >= 10
    for run in runs.values():
        assert run.x_hat[:, 3].min() > 1.995 - 1e-7  # (interior-point: within its tol)
        assert np.abs(m.manifold.errors(run.x_hat, gn.x_hat)).max() < STEP_TOL


def test_windows_track_as_the_multiplicative_ekf():
    """Accuracy and consistency on the gyro-driven attitude problem: the MHE's errors
    are the multiplicative EKF's to within a tenth, full information's smoothed ones
    smaller; NEES/3 of the MHE in the 99 % band of its mean over the record."""
    sc = scenario(T=100)
    M = sc.model.manifold
    ekf = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2)
    mhe = estim.simulate(sc, estim.MHE(sc.model, horizon=10, **sc.tuning), seed=2)
    res = estim.FullInformation(sc.model, **sc.tuning).fit(mhe.y, sc.inputs[:-1])

    def angle(x_hat, x):
        return np.linalg.norm(M.errors(x_hat, x), axis=1)[20:].mean()

    a_ekf, a_mhe = angle(ekf.x_hat, ekf.x), angle(mhe.x_hat, mhe.x)
    assert abs(a_mhe - a_ekf) < 0.1 * a_ekf
    assert angle(res.x, mhe.x) < a_mhe
    nees = estim.nees(mhe, burn_in=20)
    from scipy.stats import chi2
    lo, hi = chi2.ppf([0.005, 0.995], 3 * len(nees)) / len(nees)
    assert lo < nees.sum() / len(nees) < hi


def test_wrapped_angles_through_the_windows():
    """The circling target whose bearing crosses +-pi every lap: the MHE and full
    information on the model that declares the heading and the bearing as angles track
    it with every heading in (-pi, pi]."""
    m, tuning, sc = circling(250)
    log = estim.simulate(sc, estim.MHE(m, horizon=10, **tuning), seed=0, warn=False)
    assert np.abs(np.diff(log.y[:, 0])).max() > 6 and np.all(log.success)
    assert np.all(np.abs(log.x_hat[:, 2]) <= np.pi) and estim.rmse(log, burn_in=50) < 0.1
    rti = estim.replay(estim.MHE(m, horizon=10, rti=True, **tuning), log.y, warn=False)
    assert np.all(rti.success) and np.all(np.abs(rti.x_hat[:, 2]) <= np.pi)
    errors = {name: m.manifold.errors(run.x_hat, log.x)[50:]
              for name, run in (("rti", rti), ("converged", log))}
    assert np.sqrt(np.mean(errors["rti"] ** 2)) <= 1.03 * np.sqrt(np.mean(
        errors["converged"] ** 2))  # (the accuracy asked of it on vector states)
    # (from the MHE's estimates: from x0 repeated, the fit may settle on the mirror
    # trajectory, heading + pi with a negative speed, which moves the target alike)
    res = estim.FullInformation(m, **tuning).fit(log.y, guess=log.x_hat)
    assert res.success and np.all(np.abs(res.x[:, 2]) <= np.pi)
    assert np.abs(res.v[:, 0]).max() < 0.1  # wrapped bearing residuals
    assert np.sqrt(np.mean(m.manifold.errors(res.x, log.x)[50:] ** 2)) < \
        estim.rmse(log, burn_in=50)


def test_what_the_windows_refuse():
    sc = scenario(T=5)
    m, t = sc.model, sc.tuning
    for cls, kw in ((estim.MHE, {"horizon": 3}), (estim.FullInformation, {})):
        with pytest.raises(ValueError, match=r"lower/upper: \['q1'\] are quaternion"):
            cls(m, lower={"q1": -0.5}, **kw, **t)
    bearing = bearing_model(True)
    with pytest.raises(ValueError, match=r"lower/upper: \['psi'\]"):
        estim.MHE(bearing, horizon=3, Q=1e-4, R=1e-2, x0=[10.0, 0, 0, 2.0, 0.2], P0=0.1,
                  upper={"psi": 3.0})


@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
def test_smoothers_on_the_manifold(cls):
    """The extended and unscented RTS smoothers with tangent corrections,
    x_s = x (+) G (x_s+ (-) x_pred): on the sphere, 3 x 3 covariances, and as accurate
    as full information (the MAP trajectory) to 2 %, averaged over three seeds; better
    than the filter."""
    sc = scenario(T=100)
    M = sc.model.manifold
    errors = {"smoothed": [], "filtered": [], "map": []}
    for seed in range(3):
        log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed)
        U = sc.inputs[:-1]
        res = cls(sc.model, **sc.tuning).smooth(log.y, U)
        fit = estim.FullInformation(sc.model, **sc.tuning).fit(log.y, U)
        assert res.P.shape == (100, 3, 3) and res.gain.shape == (99, 3, 3)
        assert np.abs(np.linalg.norm(res.x, axis=1) - 1).max() < 1e-12
        for name, x in (("smoothed", res.x), ("filtered", res.x_filtered), ("map", fit.x)):
            errors[name].append(np.linalg.norm(M.errors(x, log.x), axis=1).mean())
    mean = {name: np.mean(v) for name, v in errors.items()}
    assert mean["smoothed"] <= 1.02 * mean["map"]
    assert mean["smoothed"] < 0.9 * mean["filtered"]


@pytest.mark.parametrize("kind", [estim.EKF, estim.UKF])
def test_imm_on_the_manifold(kind):
    """The IMM mixes its modes on the manifold (weighted Karcher means, tangent spreads):
    two identical modes give the filter itself; a quiet and an agile mode keep the
    estimate on the sphere, the covariance 3 x 3 and the error at the filter's."""
    sc = scenario(T=80)
    M = sc.model.manifold
    log = estim.simulate(sc, kind(sc.model, **sc.tuning), seed=5)
    same = estim.IMM({"a": kind(sc.model, **sc.tuning), "b": kind(sc.model, **sc.tuning)},
                     transition=[[0.9, 0.1], [0.2, 0.8]])
    twin = estim.replay(same, log.y, sc.inputs)
    assert np.abs(M.errors(twin.x_hat, log.x_hat)).max() < 1e-12
    np.testing.assert_allclose(twin.P, log.P, rtol=1e-9, atol=1e-18)
    agile = dict(sc.tuning, Q=100 * Q_GYRO)
    imm = estim.IMM({"quiet": kind(sc.model, **sc.tuning), "agile": kind(sc.model, **agile)},
                    transition=[[0.95, 0.05], [0.05, 0.95]])
    run = estim.replay(imm, log.y, sc.inputs)
    assert run.P.shape == (80, 3, 3) and np.all(run.success)
    assert np.abs(np.linalg.norm(run.x_hat, axis=1) - 1).max() < 1e-12
    error = [np.linalg.norm(M.errors(x, log.x), axis=1)[20:].mean()
             for x in (run.x_hat, log.x_hat)]
    assert error[0] < 1.3 * error[1]
    mu = np.array([list(d["mode_probabilities"].values()) for d in run.diagnostics])
    np.testing.assert_allclose(mu.sum(axis=1), 1.0, rtol=1e-12)
    assert mu[20:, 0].mean() > 0.5  # the data are quiet


def test_clipping_on_the_other_states():
    """clip=True on a model with angles clips the vector states (here the speed, against
    a lower bound above the truth) and leaves the heading wrapped; a bound on the angle
    itself is refused."""
    m, tuning, sc = circling(120)
    y = estim.simulate(sc, estim.EKF(m, **tuning), seed=0, warn=False).y
    free = estim.replay(estim.EKF(m, **tuning), y, warn=False)
    clipped = estim.replay(estim.EKF(m, clip=True, lower={"speed": 2.005}, **tuning), y,
                           warn=False)
    assert (free.x_hat[:, 3] < 2.005).sum() > 10  # the bound binds
    assert clipped.x_hat[:, 3].min() >= 2.005 and np.all(clipped.success)
    assert np.all(np.abs(clipped.x_hat[:, 2]) <= np.pi)
    with pytest.raises(ValueError, match=r"lower/upper: \['psi'\]"):
        estim.EKF(m, clip=True, lower={"psi": -1.0}, **tuning)


def test_particle_smoother_on_the_manifold():
    """Forward filtering, backward simulation with the tangent transition density: the
    paths on the sphere, their Karcher means as accurate as full information (within
    the Monte Carlo error of 100 paths: 10 %) and far better than the filter's."""
    sc = scenario(T=60)
    M = sc.model.manifold
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=1)
    U = sc.inputs[:-1]
    res = estim.ParticleFilter(sc.model, n_particles=2000, **sc.tuning).smooth(
        log.y, U, n_paths=100)
    fit = estim.FullInformation(sc.model, **sc.tuning).fit(log.y, U)
    filt = estim.ParticleFilter(sc.model, n_particles=2000, **sc.tuning).filter(log.y, U)
    assert res.P.shape == (60, 3, 3) and filt.P.shape == (60, 3, 3)
    assert np.abs(np.linalg.norm(res.paths, axis=2) - 1).max() < 1e-12
    error = [np.linalg.norm(M.errors(x, log.x), axis=1)[10:].mean()
             for x in (res.x, fit.x, filt.x)]
    assert error[0] <= 1.1 * error[1] and error[0] < 0.8 * error[2]


def test_linearised_proposals_on_the_manifold():
    """The particle filter's EKF and UKF proposals in the tangent space: two different
    importance densities whose likelihood estimates are both unbiased, so the means of
    exp(log L) over 20 seeds agree within three standard errors; both far less
    variable than the bootstrap filter's, and on the sphere."""
    sc = scenario(T=20)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=1)
    U = sc.inputs[:-1]

    def loglik(proposal, seeds):
        pf = estim.ParticleFilter(sc.model, n_particles=500, proposal=proposal,
                                  **sc.tuning)
        out = []
        for s in seeds:
            pf.seed = s  # (filter resets: the stream of this seed)
            out.append(pf.filter(log.y, U).log_likelihood)
        return np.array(out)

    ll = {p: loglik(p, range(20)) for p in ("ekf", "ukf")}
    c = ll["ekf"].mean()
    w = {p: np.exp(v - c) for p, v in ll.items()}
    se = np.hypot(*(v.std(ddof=1) / np.sqrt(len(v)) for v in w.values()))
    assert abs(w["ekf"].mean() - w["ukf"].mean()) < 3 * se
    boot = loglik("bootstrap", range(10))
    assert max(v.std() for v in ll.values()) < 0.2 * boot.std()
    run = estim.ParticleFilter(sc.model, n_particles=500, proposal="ukf", **sc.tuning)
    x = estim.replay(run, log.y, sc.inputs).x_hat
    assert np.abs(np.linalg.norm(x, axis=1) - 1).max() < 1e-12


@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
def test_square_root_forms_on_the_manifold(cls):
    """form="sqrt" carries the triangular factor through the multiplicative update (the
    reset Jacobian applied to the factor and re-triangularised): the covariance form's
    estimates and covariances to 1e-10 on the attitude problem and on the circling
    target with angles."""
    sc = scenario(T=100)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2)
    a = estim.replay(cls(sc.model, **sc.tuning), log.y, sc.inputs)
    b = estim.replay(cls(sc.model, form="sqrt", **sc.tuning), log.y, sc.inputs)
    assert np.abs(sc.model.manifold.errors(b.x_hat, a.x_hat)).max() < 1e-10
    np.testing.assert_allclose(b.P, a.P, rtol=1e-10, atol=1e-10 * np.abs(a.P).max())
    assert np.abs(np.linalg.norm(b.x_hat, axis=1) - 1).max() < 1e-12
    m, tuning, bs = circling(250)
    y = estim.simulate(bs, estim.EKF(m, **tuning), seed=0, warn=False).y
    a = estim.replay(cls(m, **tuning), y, warn=False)
    b = estim.replay(cls(m, form="sqrt", **tuning), y, warn=False)
    assert np.abs(m.manifold.errors(b.x_hat, a.x_hat)).max() < 1e-10
