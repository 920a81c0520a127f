"""The square-root forms of the EKF and the UKF (``form="sqrt"``): the same estimates
as the covariance form and as filterpy's Kalman filter, and no failed step where the
covariance form loses definiteness."""

from __future__ import annotations

import copy
import warnings

import casadi as ca
import numpy as np
import pytest
from conftest import make_linear
from filterpy.kalman import KalmanFilter
from models import two_tanks
from sqrt_cases import cases, nees_band, run
from test_kalman import _record

import estim

FILTERS = {
    "EKF": lambda m, **kw: estim.EKF(m, **kw),
    "UKF merwe": lambda m, **kw: estim.UKF(m, **kw),
    "UKF julier": lambda m, **kw: estim.UKF(m, points="julier", kappa=1.0, **kw),
    "UKF cubature": lambda m, **kw: estim.UKF(m, points="cubature", **kw),
}
TOL = 1e-10


def _with_gaps(Y: np.ndarray) -> np.ndarray:
    """``Y`` with single outputs and whole samples missing (NaN)."""
    Y = Y.copy()
    Y[3, 0] = np.nan
    Y[7, :] = np.nan
    Y[12, -1] = np.nan
    return Y


def _steps(est, Y, U=None):
    """x, P of every sample by ``step`` after a reset; ``U[k]`` acts from k to k+1."""
    est.reset()
    xs, Ps = [], []
    for k, y in enumerate(Y):
        xs.append(est.step(y, None if U is None or k == 0 else U[k - 1]))
        assert est.info.success, est.info.status
        Ps.append(est.info.P)
        np.testing.assert_array_equal(est.P, est.info.P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("form", ["Sqrt", "square-root", None, 1])
def test_an_unknown_form_is_refused(form):
    m = make_linear(0).model
    for cls in (estim.EKF, estim.UKF):
        with pytest.raises(ValueError, match=r"form must be one of 'covariance', 'sqrt'"):
            cls(m, Q=1.0, R=1.0, x0=np.zeros(m.nx), P0=1.0, form=form)


@pytest.mark.parametrize("kind", list(FILTERS))
@pytest.mark.parametrize("name", ["van_der_pol", "batch_reactor"])
def test_sqrt_equals_the_covariance_form_on_the_scenarios(kind, name):
    sc = estim.scenarios.get(name).replace(n_steps=80)
    cov = FILTERS[kind](sc.model, **sc.tuning)
    sqrt = FILTERS[kind](sc.model, **sc.tuning, form="sqrt")
    assert (cov.form, sqrt.form) == ("covariance", "sqrt")
    Y = _with_gaps(estim.simulate(sc, cov, seed=1).y)
    x_c, P_c = _steps(cov, Y)
    x_s, P_s = _steps(sqrt, Y)
    np.testing.assert_allclose(x_s, x_c, rtol=0, atol=TOL)
    np.testing.assert_allclose(P_s, P_c, rtol=0, atol=TOL)
    res = sqrt.filter(Y)
    assert res.success
    np.testing.assert_allclose(res.x, x_c, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.P, P_c, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.nis, cov.filter(Y).nis, rtol=1e-9, atol=TOL)


def _filterpy(sys, Y, U):
    """filterpy's KalmanFilter, the update on the measured rows of each sample only."""
    kf = KalmanFilter(dim_x=sys.A.shape[0], dim_z=sys.C.shape[0], dim_u=sys.B.shape[1])
    kf.F, kf.B, kf.Q = sys.A, sys.B, sys.Q
    kf.x, kf.P = sys.x0.copy(), sys.P0.copy()
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            kf.predict(u=U[k - 1])
        rows = np.isfinite(y)
        if rows.any():
            kf.dim_z = int(rows.sum())
            kf.update(y[rows], R=sys.R[np.ix_(rows, rows)], H=sys.C[rows])
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("kind", list(FILTERS))
@pytest.mark.parametrize("seed", [0, 1])
def test_sqrt_equals_filterpy_on_linear_gaussian(kind, seed):
    """Full Q, R and P0, inputs, and missing outputs."""
    sys = make_linear(seed, nx=4, nu=2, ny=3)
    Y, U = _record(sys, T=40, seed=seed + 20)
    Y = _with_gaps(Y)
    x_ref, P_ref = _filterpy(sys, Y, U)
    est = FILTERS[kind](sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0, form="sqrt")
    x, P = _steps(est, Y, U)
    np.testing.assert_allclose(x, x_ref, rtol=0, atol=TOL)
    np.testing.assert_allclose(P, P_ref, rtol=0, atol=TOL)
    res = est.filter(Y, U[:-1])
    np.testing.assert_allclose(res.x, x_ref, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.P, P_ref, rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", ["EKF", "UKF merwe"])
def test_gate_recovery_and_smoother_in_the_sqrt_form(kind):
    """A gated step (the prediction with P0 added) is the same in the step loop, in the
    whole-record scan and in the covariance form; so are the smoother and a recovery."""
    sc = estim.scenarios.van_der_pol(n_steps=60)
    Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=2).y
    Y[20] += 40.0  # outliers
    Y[35, 0] -= 25.0
    cov = FILTERS[kind](sc.model, **sc.tuning, gate=1e-6)
    sqrt = FILTERS[kind](sc.model, **sc.tuning, gate=1e-6, form="sqrt")
    x_c, P_c = _steps(cov, Y)
    x_s, P_s = _steps(sqrt, Y)
    assert sqrt.info.status == cov.info.status
    np.testing.assert_allclose(x_s, x_c, rtol=0, atol=TOL)
    np.testing.assert_allclose(P_s, P_c, rtol=0, atol=TOL)
    res = sqrt.filter(Y)
    assert res.status[20].startswith("rejected") and res.status == cov.filter(Y).status
    np.testing.assert_array_equal(res.x, x_s)  # the scan's gate is the step's
    np.testing.assert_array_equal(res.P, P_s)
    sm_c, sm_s = cov.smooth(Y), sqrt.smooth(Y)
    np.testing.assert_allclose(sm_s.x, sm_c.x, rtol=0, atol=TOL)
    np.testing.assert_allclose(sm_s.P, sm_c.P, rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", ["EKF", "UKF merwe"])
def test_failed_steps_recover_as_in_the_covariance_form(kind):
    """Clipping to an empty tank makes the update non-finite on seed 3: the kept
    prediction and the re-anchoring with P + P0 are those of the covariance form."""
    m = two_tanks()
    tuning = dict(Q=1e-4, R=0.01, x0=[0.5, 0.05], P0=1.0)
    sc = estim.Scenario("tanks", m, x0=[0.5, 0.5], n_steps=60, Q=1e-4, R=0.01,
                        inputs=lambda t: [0.3], clip=True, tuning=tuning)
    logs = [estim.simulate(sc, FILTERS[kind](m, **tuning, clip=True, form=form), seed=3,
                           warn=False) for form in ("covariance", "sqrt")]
    assert not logs[0].success.all()
    assert list(logs[1].status) == list(logs[0].status)
    np.testing.assert_allclose(logs[1].x_hat, logs[0].x_hat, rtol=0, atol=TOL)
    np.testing.assert_allclose(logs[1].P, logs[0].P, rtol=0, atol=TOL)


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_clip_and_inputs_in_the_output(hold):
    """Clipping (active: the spring swings below its bound) and an input in the output,
    held or sampled, as in the covariance form, after a deep copy of the filter."""
    sc = _spring(hold)
    Y = _with_gaps(estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0).y)
    U = np.asarray(sc.inputs)
    U = U if sc.model.sampled else U[:-1]
    for kind in ("EKF", "UKF merwe"):
        ests = [FILTERS[kind](sc.model, **sc.tuning, clip=True, form=form)
                for form in ("covariance", "sqrt")]
        ests[1] = copy.deepcopy(ests[1])
        ref, res = (est.filter(Y, U) for est in ests)
        np.testing.assert_allclose(res.x, ref.x, rtol=0, atol=TOL)
        np.testing.assert_allclose(res.P, ref.P, rtol=0, atol=TOL)


@pytest.mark.parametrize("kind", ["EKF", "UKF merwe"])
@pytest.mark.parametrize("case", cases(), ids=lambda c: c.name)
def test_sqrt_form_never_fails_where_the_covariance_form_breaks(kind, case):
    """Eight runs: the covariance form fails steps or loses definiteness, the
    square-root form fails none and its NEES, summed over the runs, stays at every
    sample inside the band that holds with 95 % probability over the whole run."""
    seeds = range(8)
    broken = 0
    for seed in seeds:
        r = run(case, FILTERS[kind], "covariance", seed)
        broken += r["failed"] + r["indefinite"]
    assert broken > 0  # the case is hard for the covariance form
    runs = [run(case, FILTERS[kind], "sqrt", seed) for seed in seeds]
    assert sum(r["failed"] for r in runs) == 0
    assert sum(r["indefinite"] for r in runs) == 0
    lo, hi = nees_band(len(seeds), len(case.A), case.T)
    nees = np.sum([r["nees"] for r in runs], axis=0)
    assert np.all((nees >= lo) & (nees <= hi)), (nees.min(), nees.max(), lo, hi)


def _spring(hold: str = "zoh") -> estim.Scenario:
    """A spring whose output sees the input, which is held or sampled."""
    m = estim.Model(states=["q", "v"], outputs=["q"], inputs=["u"],
                    ode=lambda x, u, p: ca.vertcat(x[1], -49.0 * x[0] - 1.4 * x[1] + 3 * u[0]),
                    output=lambda x, u, p: x[0] + 0.1 * u[0], dt=0.05, hold=hold,
                    lower={"q": -0.02}, name="spring")
    T = 100
    return estim.Scenario("spring", m, x0=[0.0, 0.0], n_steps=T, Q=1e-4, R=1e-3,
                          inputs=np.sin(0.3 * np.arange(T))[:, None],
                          tuning=dict(Q=1e-4, R=1e-3, x0=[0.2, 0.0], P0=0.5))


@pytest.mark.parametrize("scenario", [lambda: estim.scenarios.van_der_pol(n_steps=100),
                                      _spring], ids=["van_der_pol", "spring"])
def test_simulate_and_compare_with_sqrt_filters(scenario):
    sc = scenario()
    specs = {"EKF": lambda m, t: estim.EKF(m, **t, form="sqrt"),
             "UKF": lambda m, t: estim.UKF(m, **t, form="sqrt", gate=1e-4)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", estim.EstimationWarning)
        batched = estim.compare(sc, specs, seeds=range(3), keep_logs=True)
        per_run = estim.compare(sc, specs, seeds=range(3), keep_logs=True, batch=False)
    assert batched.batched and not per_run.batched
    for name in specs:
        for a, b in zip(batched.logs[name], per_run.logs[name], strict=True):
            np.testing.assert_array_equal(a.x_hat, b.x_hat)
            np.testing.assert_array_equal(a.P, b.P)
            assert list(a.status) == list(b.status)
    log_s = estim.simulate(sc, estim.UKF(sc.model, **sc.tuning, form="sqrt"), seed=4)
    log_c = estim.simulate(sc, estim.UKF(sc.model, **sc.tuning), seed=4)
    np.testing.assert_allclose(log_s.x_hat, log_c.x_hat, rtol=0, atol=TOL)
    np.testing.assert_allclose(log_s.P, log_c.P, rtol=0, atol=TOL)


def test_a_singular_process_noise_and_new_tuning():
    """Q = 0 and a rank-one Q have factors; set_tuning rewrites them."""
    sys = make_linear(3)
    Y, U = _record(sys, T=30, seed=5)
    for Q in (np.zeros_like(sys.Q), np.outer(np.ones(4), np.ones(4)) * 0.01):
        ref = _filterpy(sys.__class__(**{**sys.__dict__, "Q": Q}), Y, U)
        for kind in ("EKF", "UKF merwe"):
            est = FILTERS[kind](sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                                form="sqrt")
            est.set_tuning(Q=Q)
            x, P = _steps(est, Y, U)
            np.testing.assert_allclose(x, ref[0], rtol=0, atol=TOL)
            np.testing.assert_allclose(P, ref[1], rtol=0, atol=TOL)
