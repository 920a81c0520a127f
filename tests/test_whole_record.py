"""EKF.filter and UKF.filter: a whole record in one compiled call gives what the step
loop (replay) gives."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from models import two_tanks

import estim
from estim.estimators.kalman import fused_calls

TOL = 1e-12
FILTERS = pytest.mark.parametrize("F", [estim.EKF, estim.UKF], ids=["ekf", "ukf"])


@pytest.fixture(params=[None, 7], ids=["one-call", "windows-of-7"])
def window(request, monkeypatch):
    """The record in one Function, or in windows of 7 samples (the last one padded)."""
    if request.param is not None:
        monkeypatch.setattr(fused_calls, "RECORD_WINDOW", request.param)
    return request.param


def _same(est, Y, U=None, t=None):
    """``est.filter`` equals ``replay`` (the step loop) to TOL, status by status; the
    filter is left where the step loop leaves it."""
    U_loop = U
    if U is not None and len(U) == len(Y) - 1:  # replay reads (T, nu), its last row unused
        U_loop = np.vstack([U, np.zeros((1, est.model.nu))])
    log = estim.replay(est, Y, U_loop, t=t, warn=False)
    x_loop, P_loop = est.x.copy(), est.P.copy()
    res = est.filter(Y, U, t=t)
    assert res.status == tuple(log.status)
    assert res.success == bool(log.success.all())
    np.testing.assert_allclose(res.x, log.x_hat, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.P, log.P, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.nis, log.nis, rtol=0, atol=TOL)  # NaN where NaN
    assert res.x.shape == (len(Y), est.model.nx) and res.innovation.shape == Y.shape
    np.testing.assert_allclose(est.x, x_loop, rtol=0, atol=TOL)
    np.testing.assert_allclose(est.P, P_loop, rtol=0, atol=TOL)
    # innovations against the steps' own
    est.reset()
    for k, y in enumerate(Y):
        u = _step_input(est.model, U, k)
        dt = None if t is None or k == 0 else t[k] - t[k - 1]
        est.step(y.copy(), u, dt=dt)
        if est.info.innovation is not None:
            np.testing.assert_allclose(res.innovation[k], est.info.innovation, rtol=0, atol=TOL)
        else:
            assert np.isnan(res.innovation[k]).all()
    return res


def _step_input(model, U, k):
    if U is None or model.nu == 0:
        return None
    U = np.asarray(U, float).reshape(-1, model.nu)
    return U[k] if model.sampled else U[k - 1] if k else np.zeros(model.nu)


def _missing(Y, rows=(3, 17, 18), single=(8, 25)):
    Y = Y.copy()
    Y[list(rows)] = np.nan
    Y[list(single), 0] = np.nan
    return Y


@pytest.mark.parametrize("name, n_steps", [("van_der_pol", 200), ("batch_reactor", 400)])
@pytest.mark.parametrize("clip", [False, True])
@FILTERS
def test_scenarios_equal_the_step_loop(name, n_steps, clip, F):
    sc = getattr(estim.scenarios, name)(n_steps=n_steps)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=1, warn=False)
    est = F(sc.model, **sc.tuning, clip=clip)
    _same(est, log.y, log.u)
    _same(est, _missing(log.y), log.u)


@FILTERS
def test_a_record_of_one_sample_and_all_missing(F):
    sc = estim.scenarios.van_der_pol(n_steps=20)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    est = F(sc.model, **sc.tuning)
    _same(est, log.y[:1])
    res = _same(est, np.full((20, sc.model.ny), np.nan))
    assert np.isnan(res.nis).all() and (res.innovation == 0).all()


@pytest.mark.parametrize("hold", ["zoh", "foh"])
@FILTERS
def test_a_model_with_inputs(hold, F, window):
    m = estim.Model(states=["q", "v"], outputs=["q"], inputs=["u"],
                    ode=lambda x, u, p: ca.vertcat(x[1], -49 * x[0] - 1.4 * x[1] + 3 * u[0]),
                    output=lambda x, u, p: x[0] + 0.1 * u[0], dt=0.05, hold=hold)
    T = 150
    U = np.sin(0.3 * np.arange(T))[:, None]
    tuning = dict(Q=1e-4, R=1e-3, x0=[0.2, 0.0], P0=0.5)
    truth = estim.simulate(m, estim.EKF(m, **tuning), x0=[0.0, 0.0], n_steps=T, Q=1e-4,
                           R=1e-3, inputs=U, seed=0)
    est = F(m, **tuning)
    _same(est, truth.y, U if hold == "foh" else U[:-1])
    _same(est, _missing(truth.y), U if hold == "foh" else U[:-1])


@FILTERS
def test_irregular_time_stamps(F, window):
    m = estim.Model(states=["x1", "x2"], outputs=["y"], inputs=["u"],
                    ode=lambda x, u, p: ca.vertcat(x[1], (1 - x[0] ** 2) * x[1] - x[0] + u[0]),
                    output=lambda x, u, p: x[0], dt=0.1, variable_dt=True)
    rng = np.random.default_rng(0)
    T = 80
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.02, 0.3, T - 1))])
    Y = np.sin(t)[:, None] + 0.05 * rng.standard_normal((T, 1))
    U = 0.1 * rng.standard_normal((T - 1, 1))
    _same(F(m, Q=1e-3, R=1e-2, x0=[0.0, 1.0], P0=1.0), Y, U, t)


@pytest.mark.parametrize("gate", [None, 1e-6])
@FILTERS
def test_outliers_suspect_and_gated(gate, F, window):
    sc = estim.scenarios.van_der_pol(n_steps=120)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    Y = _missing(log.y)
    Y[30] += 50.0  # beyond both tails
    Y[31:34, 1] += 50.0  # one output: the NIS with one degree of freedom
    est = F(sc.model, **sc.tuning, gate=gate)
    res = _same(est, Y)
    word = "suspect" if gate is None else "rejected"
    assert res.status[30].startswith(word) and res.status[31].startswith(word)
    assert res.success


@pytest.mark.parametrize("gate", [None, 1e-6])
@FILTERS
def test_non_finite_updates_finish_with_the_step_loop(gate, F, window):
    """Suspect or gated steps, then an estimate clipped to an empty tank: the recovery
    (re-anchoring on the last trusted estimate) is the step loop's."""
    m = two_tanks()
    T = 60
    U = np.full((T, 1), 0.3)
    tuning = dict(Q=1e-4, R=1e-4, x0=[0.5, 0.5], P0=1.0)
    truth = estim.simulate(m, estim.EKF(m, **tuning), x0=[0.5, 0.5], n_steps=T, Q=0.0,
                           R=1e-4, inputs=U, seed=0, warn=False)
    Y = truth.y.copy()
    Y[15] += 0.5  # suspect (or rejected)
    Y[20:23] = -5.0  # drives h2 below 0: clipped to the empty tank (the EKF)
    _same(F(m, **tuning, clip=True, gate=gate), Y, U[:-1])
    Y[20:30] = -0.3  # within reach of the gate too: the UKF fails as well
    # (the UKF with points near the mean, alpha = 0.1: the default's reach sqrt(2) sd of
    # P0 = 1 below the levels of 0.5 and fail from the first prediction on)
    narrow = {"alpha": 0.1} if F is estim.UKF else {}
    res = _same(F(m, **tuning, clip=True, gate=gate, **narrow), Y, U[:-1])
    failed = [k for k, s in enumerate(res.status) if s.startswith("failed")]
    assert failed and not res.success
    assert any(s.startswith("suspect" if gate is None else "rejected")
               for s in res.status[:failed[0]])
    # from the first sample on
    _same(F(m, Q=1e-4, R=1e-4, x0=[0.0, 0.0], P0=1.0, clip=True), Y, U[:-1])


@FILTERS
def test_tuning_is_data(F, window):
    sc = estim.scenarios.van_der_pol(n_steps=60)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    est = F(sc.model, **sc.tuning, gate=1e-6)
    est.filter(log.y)
    est.set_tuning(Q=2 * np.asarray(sc.tuning["Q"]), P0=3 * np.asarray(sc.tuning["P0"]))
    Y = log.y.copy()
    Y[20] += 50.0
    _same(est, Y)


@FILTERS
def test_a_few_record_lengths_are_kept(F):
    sc = estim.scenarios.van_der_pol(n_steps=40)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    est = F(sc.model, **sc.tuning)
    for T in range(5, 40, 3):
        _same(est, log.y[:T])
    assert len(est._whole_records) == 8 and (38, True, True) in est._whole_records


@pytest.mark.parametrize("form", ["covariance", "sqrt"])
@FILTERS
def test_long_records_in_windows_equal_one_call(F, form, monkeypatch):
    """Windows continued one from the other give the single Function's numbers bit for
    bit, whatever the record's length, from two Functions (the first window and a
    continued one)."""
    sc = estim.scenarios.van_der_pol(n_steps=100)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    Y = _missing(log.y)
    whole = [F(sc.model, **sc.tuning, form=form).filter(Y[:T]) for T in (23, 100)]
    monkeypatch.setattr(fused_calls, "RECORD_WINDOW", 8)
    est = F(sc.model, **sc.tuning, form=form)
    for T, ref in zip((23, 100), whole, strict=True):
        res = est.filter(Y[:T])
        for a, b in ((res.x, ref.x), (res.P, ref.P), (res.nis, ref.nis),
                     (res.innovation, ref.innovation)):
            assert np.array_equal(a, b, equal_nan=True)
        assert res.status == ref.status
    assert set(est._whole_records) == {(8, True, True), (8, True, False)}
