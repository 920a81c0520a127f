"""Moving horizon estimation: exact references, the seeds, failures and bad input."""

from __future__ import annotations

import warnings

import casadi as ca
import numpy as np
import pytest
from conftest import make_linear
from scipy.optimize import least_squares
from test_kalman import _kalman, _record

import estim
from estim.solvers.least_squares.solution import Solution

SOLVERS = ["gauss-newton", "ipopt", "sqp", "fatrop"]


@pytest.mark.parametrize("solver", SOLVERS)
def test_filtering_arrival_cost_equals_kalman_filter(solver):
    """Linear-Gaussian, no bounds: MHE with the filtering prior is the Kalman filter."""
    sys = make_linear(0)
    Y, U = _record(sys, T=30, seed=3)
    x_ref, P_ref = _kalman(sys, Y, U)
    mhe = estim.MHE(sys.model, horizon=6, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                    arrival_cost="filtering", solver=solver)
    for k, y in enumerate(Y):
        x = mhe.step(y, U[k - 1] if k else None)
        np.testing.assert_allclose(x, x_ref[k], atol=1e-6)
        np.testing.assert_allclose(mhe.info.P, P_ref[k], atol=1e-9)
        assert mhe.info.success


def test_missing_outputs_drop_their_residuals():
    """With NaN entries the filtering MHE still equals the Kalman filter that
    skips those rows (the reduced update of test_kalman)."""
    sys = make_linear(1)
    Y, U = _record(sys, T=20, seed=4)
    Y[3, 0] = np.nan
    Y[7] = np.nan
    Y[12, 1] = np.nan
    ekf = estim.EKF(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)  # = KF, tested
    mhe = estim.MHE(sys.model, horizon=4, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    for k, y in enumerate(Y):
        u = U[k - 1] if k else None
        np.testing.assert_allclose(mhe.step(y, u), ekf.step(y, u), atol=1e-6)


def _vdp_batch_reference(model, Y, x0, P0, Q, R):
    """The whole-record problem written in numpy, solved by scipy's least_squares."""
    mu, dt = model.params["mu"], model.dt

    def f(x):
        return np.array([x[1], mu * (1 - x[0] ** 2) * x[1] - x[0]])

    def F(x):
        k1 = f(x)
        k2 = f(x + dt / 2 * k1)
        k3 = f(x + dt / 2 * k2)
        k4 = f(x + dt * k3)
        return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    Wq = np.linalg.cholesky(np.linalg.inv(Q)).T
    Wr = np.linalg.cholesky(np.linalg.inv(R)).T
    W0 = np.linalg.cholesky(np.linalg.inv(P0)).T
    T = len(Y)

    def residual(z):
        X = z.reshape(T, 2)
        r = [W0 @ (X[0] - x0)]
        r += [Wq @ (X[k + 1] - F(X[k])) for k in range(T - 1)]
        r += [Wr @ (Y[k] - X[k]) for k in range(T)]
        return np.concatenate(r)

    z0 = np.tile(x0, T)
    sol = least_squares(residual, z0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.x.reshape(T, 2)


@pytest.mark.parametrize("solver", SOLVERS)
def test_horizon_covering_all_data_equals_batch_solve(solver):
    """Before the window is full, MHE is full-information estimation over all data
    (no padding): each estimate is the last state of the batch solution."""
    sc = estim.scenarios.van_der_pol()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2, n_steps=25)
    Q, R, x0, P0 = np.eye(2) * 0.01, np.eye(2), np.zeros(2), np.eye(2)
    mhe = estim.MHE(sc.model, horizon=40, Q=Q, R=R, x0=x0, P0=P0, arrival_cost="fixed",
                    solver=solver)
    for k in range(25):
        x = mhe.step(log.y[k])
        if k in (0, 4, 24):
            ref = _vdp_batch_reference(sc.model, log.y[: k + 1], x0, P0, Q, R)
            np.testing.assert_allclose(x, ref[-1], atol=1e-6)
            np.testing.assert_allclose(mhe.info.extra["window"], ref, atol=1e-6)


def test_long_window_mapped_graph_equals_unrolled():
    """A 70-slot window (a 64-slot chunk and a remainder in the mapped graph), through
    the start-up windows with unused slots and into the full ones."""
    sc = estim.scenarios.van_der_pol(n_steps=90)
    logs = [estim.simulate(sc, estim.MHE(sc.model, horizon=70, arrival_cost="filtering",
                                         solver="gauss-newton",
                                         solver_options={"mode": mode}, **sc.tuning), seed=2)
            for mode in ("unrolled", "mapped")]
    assert all(lg.success.all() for lg in logs)
    np.testing.assert_allclose(logs[0].x_hat, logs[1].x_hat, atol=1e-8)


def test_solvers_agree_on_the_benchmark_problems():
    for name, N, ac in (("van_der_pol", 15, "filtering"), ("batch_reactor", 10, "none")):
        sc = estim.scenarios.get(name).replace(n_steps=60)
        logs = [estim.simulate(sc, estim.MHE(sc.model, horizon=N, arrival_cost=ac,
                                             solver=s, **sc.tuning), seed=1)
                for s in SOLVERS]
        burn = 5 if ac == "none" else 0  # the first windows alone do not determine x
        for other in logs[1:]:
            np.testing.assert_allclose(other.x_hat[burn:], logs[0].x_hat[burn:], atol=1e-6)
        assert all(lg.success.all() for lg in logs)


def test_batch_reactor_mhe_beats_ekf_and_longer_horizon_is_better():
    """Seed 002, exercises 5-6: zero prior, x in [0, 10]."""
    sc = estim.scenarios.batch_reactor()
    ekf = float(estim.rmse(estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)))
    res = {}
    for N in (10, 25):
        mhe = estim.MHE(sc.model, horizon=N, arrival_cost="none", upper=10.0,
                        solver="fatrop", **sc.tuning)
        log = estim.simulate(sc, mhe, seed=0)
        assert log.x_hat.min() >= -1e-8 and log.x_hat.max() <= 10 + 1e-8
        assert log.success.all()
        res[N] = float(estim.rmse(log))
    assert res[10] < 0.5 * ekf
    assert res[25] < 0.5 * res[10]


def test_van_der_pol_filtering_mhe_as_accurate_as_ekf():
    """Seed 001: over 10 seeds the filtering MHE is within 2 % of the EKF."""
    sc = estim.scenarios.van_der_pol()
    mean = {}
    for name, est in (("ekf", estim.EKF(sc.model, **sc.tuning)),
                      ("mhe", estim.MHE(sc.model, horizon=15, solver="fatrop", **sc.tuning))):
        mean[name] = np.mean([float(estim.rmse(estim.simulate(sc, est, seed=s)))
                              for s in range(10)])
    assert mean["mhe"] <= 1.02 * mean["ekf"]


def test_parameter_estimation_on_augmented_model():
    """The reactor's rate constant k1 as an unknown, bounded state."""
    m = estim.models.batch_reactor().augment("k1", lower=0.0, upper=5.0)
    sc = estim.scenarios.batch_reactor()
    x0_true = np.r_[sc.x0, 0.5]
    mhe = estim.MHE(m, horizon=20, Q=[0.002**2] * 3 + [1e-8], R=0.25**2,
                    x0=[0.6, 0.1, 0.1, 0.3], P0=[0.1, 0.1, 0.1, 0.1], solver="fatrop")
    log = estim.simulate(m, mhe, x0=x0_true, n_steps=80, Q=[0.002**2] * 3 + [0.0],
                         R=0.25**2, seed=0, clip=True)
    assert log.success.all()
    # k1 is identifiable from the transient: after it the estimate is close
    assert abs(log.x_hat[-1, 3] - 0.5) < 0.05
    assert float(estim.rmse(log, burn_in=40, states=["C_A", "C_B", "C_C"])) < 0.05


def test_failed_solve_reanchors_and_recovers(monkeypatch):
    """A failed solve restarts the window from the last trusted estimate: the arrival
    cost there with P + P0, and this measurement. With y = x that is the Kalman update
    x_a + P_a (P_a + R)^-1 (y - x_a); afterwards the windows grow again and the estimates
    return to those of the run without the failure."""
    sc = estim.scenarios.van_der_pol()
    mhe = estim.MHE(sc.model, horizon=5, solver="ipopt", **sc.tuning)
    log = estim.simulate(sc, mhe, seed=0, n_steps=120)
    mhe.reset()
    real = mhe._nlp.solve
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        sol = real(*args, **kwargs)
        if calls["n"] == 8:
            return Solution(sol.X * np.nan, False, "Invalid_Number_Detected", 3, np.nan, 0.0)
        return sol

    monkeypatch.setattr(mhe._nlp, "solve", flaky)
    xs, statuses, covs = [], [], []
    for y, u in zip(log.y, [None, *log.u[:-1]], strict=True):
        xs.append(mhe.step(y, u))
        statuses.append(mhe.info.status)
        covs.append(mhe.info.P)
    assert all(np.isfinite(x).all() for x in xs)
    assert statuses[7] == ("failed: Invalid_Number_Detected; re-anchored on the last trusted "
                           "estimate")
    Pa = covs[6] + mhe.P0
    expected = xs[6] + Pa @ np.linalg.solve(Pa + mhe.R, log.y[7] - xs[6])
    np.testing.assert_allclose(xs[7], expected, atol=1e-8)
    assert set(statuses[8:]) == {"ok"}  # the next steps solve again
    # and forget the failure as the filtering arrival cost forgets its prior
    gap = np.abs(np.array(xs) - log.x_hat).max(axis=1)
    assert gap[-1] < 1e-3 * gap.max()


def test_all_failures_keep_the_loop_running():
    """Ipopt allowed no iteration returns its start: used as an inexact estimate, never
    a failure that stops the estimator from following the data."""
    sc = estim.scenarios.van_der_pol()
    mhe = estim.MHE(sc.model, horizon=5, solver="ipopt", solver_options={"ipopt.max_iter": 0},
                    **sc.tuning)
    log = estim.simulate(sc, mhe, seed=0, n_steps=20)
    assert log.success.all()
    assert all(s.startswith("inexact: Maximum_Iterations_Exceeded") for s in log.status)
    assert np.isfinite(log.x_hat).all()


def test_bad_input():
    sc = estim.scenarios.van_der_pol()
    with pytest.raises(ValueError, match="horizon must be"):
        estim.MHE(sc.model, horizon=0, **sc.tuning)
    with pytest.raises(ValueError, match="rti=True needs horizon >= 2"):
        estim.MHE(sc.model, horizon=1, rti=True, **sc.tuning)
    with pytest.raises(ValueError, match=r"\['mode'\] apply to solver='gauss-newton' only"):
        estim.MHE(sc.model, horizon=5, solver="ipopt", solver_options={"mode": "mapped"},
                  **sc.tuning)
    with pytest.raises(ValueError, match="arrival_cost must be one of"):
        estim.MHE(sc.model, horizon=5, arrival_cost="ekf", **sc.tuning)
    with pytest.raises(ValueError, match="solver must be one of"):
        estim.MHE(sc.model, horizon=5, solver="snopt", **sc.tuning)
    with pytest.raises(ValueError, match="Q is singular.*rti=True"):
        estim.MHE(sc.model, horizon=5, rti=True, **{**sc.tuning, "Q": [0.01, 0.0]})
    with pytest.raises(ValueError, match="P0 is required"):
        estim.MHE(sc.model, horizon=5, arrival_cost="filtering", Q=0.01, R=1.0, x0=[0, 0])
    estim.MHE(sc.model, horizon=5, arrival_cost="none", Q=0.01, R=1.0, x0=[0, 0])
    with pytest.raises(TypeError, match="unknown option"):
        estim.MHE(sc.model, horizon=5, window=3, **sc.tuning)


def test_default_solver_is_the_fastest_and_is_recorded():
    """``solver="auto"`` (the default) is the structured Gauss-Newton solver for MHE and
    full information; it reaches Ipopt's optimum, and the choice is recorded."""
    from estim.cli import parse_estimator

    sc = estim.scenarios.van_der_pol()
    sc = sc.replace(n_steps=40)
    auto = estim.MHE(sc.model, horizon=15, **sc.tuning)
    ipopt = estim.MHE(sc.model, horizon=15, solver="ipopt", **sc.tuning)
    assert auto.solver == "gauss-newton" and ipopt.solver == "ipopt"
    la, li = estim.simulate(sc, auto, seed=1), estim.simulate(sc, ipopt, seed=1)
    assert auto.info.extra["solver"] == "gauss-newton"
    assert ipopt.info.extra["solver"] == "ipopt"
    assert (la.status == "ok").all() and (li.status == "ok").all()
    np.testing.assert_allclose(la.x_hat, li.x_hat, atol=1e-6)
    # full information: the same choice, recorded in the fit and the step
    fie = estim.FullInformation(sc.model, **sc.tuning)
    res = fie.fit(la.y)
    assert fie.solver == res.solver == "gauss-newton"
    fie.step(la.y[0])
    assert fie.info.extra["solver"] == "gauss-newton"
    # the command line follows the same default
    _, cls, kwargs = parse_estimator("mhe:horizon=15")
    assert cls(sc.model, **kwargs, **sc.tuning).solver == "gauss-newton"


def test_auto_solver_refuses_another_solvers_options():
    sc = estim.scenarios.van_der_pol()
    with pytest.raises(ValueError, match=r"solver='auto'.*'ipopt.tol'.*solver='ipopt'"):
        estim.MHE(sc.model, horizon=5, solver_options={"ipopt.tol": 1e-8}, **sc.tuning)
    with pytest.raises(ValueError, match=r"solver must be one of"):
        estim.FullInformation(sc.model, solver="newton", **sc.tuning)
    # Gauss-Newton's own options are fine with "auto"
    mhe = estim.MHE(sc.model, horizon=5, solver_options={"max_iter": 5}, **sc.tuning)
    assert mhe.solver == "gauss-newton"


def test_solver_warnings_are_kept_not_printed(capsys):
    """Ipopt at a square root's bound: CasADi's "Failed to calculate multipliers"
    warnings go to the step's diagnostics, not to stderr."""
    m = estim.Model(states=["h1", "h2"], inputs=["q"], outputs=["y"],
                    ode=lambda x, u, p: ca.vertcat(u[0] - 0.5 * ca.sqrt(ca.fmax(x[0], 0)),
                                                   0.5 * ca.sqrt(ca.fmax(x[0], 0))
                                                   - 0.4 * ca.sqrt(ca.fmax(x[1], 0))),
                    output=lambda x, u, p: x[1], dt=0.5, lower=0.0, name="tanks")
    U = np.zeros((40, 1))
    U[:20] = 0.3
    sc = estim.Scenario("tanks", m, x0=[0.3, 0.3], n_steps=40, Q=0.0, R=1e-4, inputs=U,
                        clip=True, tuning=dict(Q=1e-5, R=1e-4, x0=[0.3, 0.3], P0=0.01))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", estim.EstimationWarning)  # (the fmax advice)
        log = estim.simulate(sc, estim.MHE(m, horizon=10, solver="ipopt", **sc.tuning),
                             seed=0, warn=False)
    kept = [d["solver_messages"] for d in log.diagnostics if "solver_messages" in d]
    assert kept and "Failed to calculate multipliers" in kept[0]
    assert "Failed to calculate" not in capsys.readouterr().err
