"""The iterated EKF (``EKF(iterations=K)``) against a plain numpy implementation of the
textbook's algorithm and the exact Kalman filter, and the iterated extended smoother
against full-information estimation, the MAP problem it solves by Gauss-Newton."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from linear_gaussian import P0, X0, Q, R, kalman, linear_model, record

import estim
from estim._compile import compiler

PEND = estim.models.sine_pendulum()
QP = np.diag([1e-4, 0.06])
TUNING = {"Q": QP, "R": 0.01, "x0": [1.2, 0.0], "P0": 0.09}


@pytest.fixture(scope="module")
def pendulum_record():
    return estim.simulate(PEND, None, x0=[1.5, 0.0], n_steps=300, Q=QP, R=0.01, seed=1)


def iekf_reference(Y: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray]:
    """Särkkä & Svensson (2023), algorithm 7.x (the iterated EKF), in numpy, the prior on
    the first sample as estim puts it."""
    m = PEND
    x, P = np.array([1.2, 0.0]), 0.09 * np.eye(2)
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            A = np.asarray(m.F_x(x, [], m.p))
            x = np.asarray(m.F(x, [], m.p)).ravel()
            P = A @ P @ A.T + QP
        xb, Pb, xi = x, P, x
        for _ in range(K):
            H = np.asarray(m.H_x(xi, [], m.p))
            h = np.asarray(m.H(xi, [], m.p)).ravel()
            S = H @ Pb @ H.T + 0.01
            G = Pb @ H.T @ np.linalg.inv(S)
            xi = xb + G @ (y - h - H @ (xb - xi))
        x, P = xi, Pb - G @ S @ G.T
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("jit", [False, True])
def test_the_iterated_ekf_is_the_textbook_algorithm(pendulum_record, jit):
    if jit and compiler() is None:
        pytest.skip("no C compiler")
    Y = pendulum_record.y
    for K in (2, 5):
        ekf = estim.EKF(PEND, **TUNING, iterations=K, jit=jit)
        log = estim.replay(ekf, Y)
        x, P = iekf_reference(Y, K)
        np.testing.assert_allclose(log.x_hat, x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(log.P, P, rtol=0, atol=1e-12)
        assert ekf.info.iterations == K
        # the whole-record call is the step loop
        np.testing.assert_array_equal(ekf.filter(Y).x, log.x_hat)
    # one iteration is the EKF, to the bit
    plain = estim.replay(estim.EKF(PEND, **TUNING), Y)
    once = estim.replay(estim.EKF(PEND, **TUNING, iterations=1), Y)
    np.testing.assert_array_equal(once.x_hat, plain.x_hat)
    assert estim.EKF(PEND, **TUNING).info.iterations == 0


def test_on_a_linear_model_iterating_changes_nothing():
    Y = record(30, seed=3)
    x_kf, P_kf, _ = kalman(Y)
    log = estim.replay(estim.EKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, iterations=4), Y)
    np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-12)


def test_the_iterated_smoother_is_full_information(pendulum_record):
    """Each pass of the iterated extended RTS smoother is a Gauss-Newton step on the
    record's MAP problem: converged, its means and covariances are full information's
    (Gauss-Newton and Ipopt, tight tolerances) to 1e-10."""
    Y = pendulum_record.y
    ekf = estim.EKF(PEND, **TUNING)
    first = ekf.smooth(Y)
    res = ekf.smooth(Y, iterations=100)
    assert res.converged and 2 < res.iterations < 100
    assert first.iterations == 1 and first.converged
    for solver, options in (("gauss-newton", {"xtol": 1e-15, "ftol": 1e-25, "max_iter": 500}),
                            ("ipopt", {"ipopt.tol": 1e-14})):
        fit = estim.FullInformation(PEND, **TUNING, solver=solver,
                                    solver_options=options).fit(Y, guess=first.x)
        assert fit.success
        np.testing.assert_allclose(res.x, fit.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.P, fit.P, rtol=0, atol=1e-10)
    # better than the extended smoother on this record, and a handful of passes get there
    truth = pendulum_record
    assert float(estim.rmse(res, truth=truth)) < float(estim.rmse(first, truth=truth))
    two = ekf.smooth(Y, iterations=2)
    assert two.iterations == 2 and not two.converged


def test_what_does_not_apply_is_refused():
    with pytest.raises(ValueError, match="iterations must be"):
        estim.EKF(PEND, **TUNING, iterations=0)
    with pytest.raises(ValueError, match="covariance form"):
        estim.EKF(PEND, **TUNING, iterations=3, form="sqrt")
    with pytest.raises(ValueError, match="not with clip=True, a gate"):
        estim.EKF(PEND, **TUNING, gate=1e-6).smooth(np.zeros((5, 1)), iterations=3)
    with pytest.raises(ValueError, match="iterations must be"):
        estim.EKF(PEND, **TUNING).smooth(np.zeros((5, 1)), iterations=0)


@pytest.mark.skipif(compiler() is None, reason="no C compiler")
def test_the_exported_iterated_ekf_steps_as_python(pendulum_record, tmp_path):
    """The iterations are unrolled in the step's Function, so the C export carries them."""
    from test_codegen import CFilter, _close

    from estim import codegen

    ekf = estim.EKF(PEND, **TUNING, iterations=3)
    codegen.export(ekf, tmp_path, name="iekf")
    out = CFilter(ekf, tmp_path, "iekf").run(pendulum_record.y, None)
    log = estim.replay(ekf, pendulum_record.y)
    assert _close(out["x"], log.x_hat) <= 1e-12 and _close(out["P"], log.P) <= 1e-12


def test_the_command_line_takes_iterations(capsys):
    from estim import cli

    assert cli.main(["run", "sine_pendulum", "--steps", "60", "--seeds", "2", "--plot", "",
                     "-e", "ekf", "-e", "iekf=ekf:iterations=3"]) in (0, None)
    table = capsys.readouterr().out
    assert "iekf" in table


def test_a_one_sample_mhe_is_the_converged_iterated_ekf(pendulum_record):
    """MHE(horizon=1) with the filtering arrival cost solves each update's MAP problem,
    which the iterated EKF's Gauss-Newton iterations converge to: to 1e-10 with Ipopt's
    tight tolerance, and its covariance too; 1e-6 with the default Gauss-Newton stop."""
    Y = pendulum_record.y
    iekf = estim.replay(estim.EKF(PEND, **TUNING, iterations=60), Y)
    tight = estim.replay(estim.MHE(PEND, horizon=1, **TUNING, solver="ipopt",
                                   solver_options={"ipopt.tol": 1e-14}), Y)
    np.testing.assert_allclose(tight.x_hat, iekf.x_hat, rtol=0, atol=1e-10)
    np.testing.assert_allclose(tight.P, iekf.P, rtol=0, atol=1e-10)
    default = estim.replay(estim.MHE(PEND, horizon=1, **TUNING), Y)
    np.testing.assert_allclose(default.x_hat, iekf.x_hat, rtol=0, atol=1e-6)
    assert set(default.status) == {"ok"}


# ---------------------------------------------------- iterated posterior linearisation
@pytest.mark.parametrize("jit", [False, True])
def test_posterior_linearisation_on_a_linear_model_is_the_kalman_smoother(jit):
    """Statistical linear regression of a linear map is the map itself, with no added
    noise: the IPLF is the Kalman filter and the IPLS the RTS smoother (filterpy)."""
    if jit and compiler() is None:
        pytest.skip("no C compiler")
    from filterpy.kalman import rts_smoother
    from linear_gaussian import A

    Y = record(30, seed=5)
    x_kf, P_kf, _ = kalman(Y)
    xs, Ps, _, _ = rts_smoother(x_kf, P_kf, [A] * len(Y), [Q] * len(Y))
    for points in ("cubature", "gauss-hermite"):
        ukf = estim.UKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, points=points,
                        iterations=4, jit=jit)
        log = estim.replay(ukf, Y)
        np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-11)
        np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-11)
        res = ukf.smooth(Y)
        np.testing.assert_allclose(res.x, xs, rtol=0, atol=1e-10)
        np.testing.assert_allclose(res.P, Ps, rtol=0, atol=1e-10)
        assert res.converged and ukf.info.iterations == 4


def test_posterior_linearisation_once_is_the_ukf(pendulum_record):
    Y = pendulum_record.y
    plain = estim.replay(estim.UKF(PEND, **TUNING), Y)
    once = estim.replay(estim.UKF(PEND, **TUNING, iterations=1), Y)
    np.testing.assert_array_equal(once.x_hat, plain.x_hat)
    with pytest.raises(ValueError, match="covariance form on vector states"):
        estim.UKF(PEND, **TUNING, iterations=3, form="sqrt")


@pytest.mark.skipif(compiler() is None, reason="no C compiler")
def test_the_exported_iplf_steps_as_python(pendulum_record, tmp_path):
    from test_codegen import CFilter, _close

    from estim import codegen

    iplf = estim.UKF(PEND, **TUNING, points="gauss-hermite", order=3, iterations=3)
    codegen.export(iplf, tmp_path, name="iplf")
    out = CFilter(iplf, tmp_path, "iplf").run(pendulum_record.y, None)
    log = estim.replay(iplf, pendulum_record.y)
    assert _close(out["x"], log.x_hat) <= 1e-12 and _close(out["P"], log.P) <= 1e-12



# ------------------------------------------------------------- damped iterations
CUBE = estim.Model(states=["x"], outputs=["y"], dynamics=lambda x, u, p: x,
                   output=lambda x, u, p: x ** 3, name="cube sensor")
CUBE_PRIOR = {"Q": 1e-6, "R": 1e-4, "x0": [0.1], "P0": 1.0}


def _cube_map(y: float) -> float:
    """The update's MAP estimate from the prior 0.1 (variance 1) by ``y = x^3 + v``
    (variance 1e-4), by scipy's bounded scalar minimisation."""
    from scipy.optimize import minimize_scalar

    def cost(x):
        return (x - 0.1) ** 2 + (y - x ** 3) ** 2 / 1e-4

    return float(minimize_scalar(cost, bounds=(0.0, 4.0), method="bounded",
                                 options={"xatol": 1e-13}).x)


def test_damped_iterations_converge_where_the_plain_one_overshoots():
    """A cube-law sensor seen from a prior far from the state: the plain Gauss-Newton
    update jumps to x ~ 240 and creeps back (10 iterations: far from the MAP estimate,
    and said not converged); the line search and Levenberg-Marquardt reach scipy's MAP
    estimate; a damped update stopped short is a suspect step, never a silent iterate."""
    y, ref = 8.0, _cube_map(8.0)
    plain = estim.EKF(CUBE, **CUBE_PRIOR, iterations=10)
    assert abs(plain.step([y])[0] - ref) > 1.0
    assert plain.info.extra["converged"] is False
    for damping, K in (("line-search", 10), ("levenberg-marquardt", 30)):
        f = estim.EKF(CUBE, **CUBE_PRIOR, iterations=K, damping=damping)
        assert f.step([y])[0] == pytest.approx(ref, abs=1e-7)
        assert f.info.extra["converged"] is True
    short = estim.EKF(CUBE, **CUBE_PRIOR, iterations=10, damping="levenberg-marquardt")
    short.step([y])
    assert short.info.extra["converged"] is False
    assert short.info.status.startswith("suspect: the damped iterated update "
                                        "(levenberg-marquardt) did not converge in 10")


def test_a_record_reports_convergence_as_its_steps_do():
    """``FilterResult.converged`` and the statuses of the whole-record call are the step
    loop's, sample by sample, with the not-converged steps of a short damped update."""
    rng = np.random.default_rng(0)
    x = 2 + np.cumsum(rng.normal(0, 0.05, 40))
    Y = (x ** 3 + rng.normal(0, 0.01, 40))[:, None]
    tuning = dict(CUBE_PRIOR, Q=0.0025)
    for kw, n_converged in (({"iterations": 2, "damping": "levenberg-marquardt"}, 0),
                            ({"iterations": 3, "damping": "line-search"}, 40)):
        f = estim.EKF(CUBE, **tuning, **kw)
        res = f.filter(Y)
        log = estim.replay(f, Y, warn=False)
        assert res.status == tuple(log.status)
        assert res.converged.tolist() == [d["converged"] for d in log.diagnostics]
        assert res.converged.sum() == n_converged
    assert estim.EKF(CUBE, **tuning).filter(Y).converged is None  # no iterations


def test_damping_changes_nothing_where_the_iteration_converges(pendulum_record):
    """Where the plain iteration converges (20 iterations on the pendulum; with 10, the
    second sample's update is still moving by more than 1e-4 sd) the damped ones reach
    the same estimates."""
    Y = pendulum_record.y
    plain = estim.EKF(PEND, **TUNING, iterations=20).filter(Y)
    assert plain.converged.all()
    assert np.flatnonzero(~estim.EKF(PEND, **TUNING, iterations=10).filter(Y).converged
                          ).tolist() == [1]
    for damping in ("line-search", "levenberg-marquardt"):
        res = estim.EKF(PEND, **TUNING, iterations=20, damping=damping).filter(Y)
        assert res.converged.all() and set(res.status) == set(plain.status)
        # each converged to within tol = 1e-4 of its posterior sd: twice that apart at most
        bound = 2 * 1e-4 * np.sqrt(np.diagonal(plain.P, axis1=1, axis2=2))
        assert (np.abs(res.x - plain.x) <= bound).all()


def test_relaxed_posterior_linearisation_where_the_plain_one_oscillates():
    """Bearing-only triangulation (two bearings of 1 mrad from (0, 0) and (10, 0), the
    target at (5, 5)) from 60 priors drawn around it (sd 4 in each axis): the plain IPLF
    ends more than 0.1 away on several of them (measured on 200 priors: 13, with 10 or
    30 iterations), the relaxed one with 30 iterations on far fewer (2 of 200); neither
    says converged where it is wrong."""
    S = np.array([[0.0, 0.0], [10.0, 0.0]])
    m = estim.Model(states=["px", "py"], outputs=["b1", "b2"],
                    dynamics=lambda x, u, p: x,
                    output=lambda x, u, p: ca.vertcat(*[ca.atan2(x[1] - s[1], x[0] - s[0])
                                                        for s in S]))
    truth = np.array([5.0, 5.0])
    y = np.arctan2(truth[1] - S[:, 1], truth[0] - S[:, 0])
    tuning = {"Q": 1e-6, "R": 1e-6 * np.eye(2), "x0": truth, "P0": 16 * np.eye(2)}
    filters = {"plain": estim.UKF(m, **tuning, points="cubature", iterations=30),
               "relaxed": estim.UKF(m, **tuning, points="cubature", iterations=30,
                                    damping="relaxed")}
    wrong = dict.fromkeys(filters, 0)
    for x0 in truth + np.random.default_rng(1).normal(0, 4, (60, 2)):
        for name, f in filters.items():
            f.reset(x0=x0)
            far = np.linalg.norm(f.step(y) - truth) > 0.1
            wrong[name] += far
            assert not (far and f.info.extra["converged"])
    assert wrong["relaxed"] < wrong["plain"] and wrong["plain"] >= 3


def test_what_the_iterated_options_refuse():
    with pytest.raises(ValueError, match="damping must be None or one of 'line-search', "
                                         "'levenberg-marquardt'"):
        estim.EKF(PEND, **TUNING, iterations=3, damping="newton")
    with pytest.raises(ValueError, match="damping must be None or one of 'relaxed'"):
        estim.UKF(PEND, **TUNING, iterations=3, damping="levenberg-marquardt")
    with pytest.raises(ValueError, match="give iterations > 1"):
        estim.EKF(PEND, **TUNING, damping="line-search")
    with pytest.raises(ValueError, match="tol"):
        estim.EKF(PEND, **TUNING, iterations=3, tol=0.0)
    with pytest.raises(ValueError, match="iterations"):
        estim.EKF(PEND, **TUNING, iterations=0)
