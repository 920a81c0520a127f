"""Full-information estimation: RTS smoother equality, Ipopt agreement, bounds, bad input."""

from __future__ import annotations

import shutil

import casadi as ca
import numpy as np
import pytest
from conftest import make_linear
from filterpy.kalman import KalmanFilter
from test_kalman import _record

import estim


def _rts_reference(sys, Y):
    """Kalman filter (update first: x0, P0 is the prior of x_0) then filterpy's RTS smoother.

    filterpy's ``batch_filter`` predicts before its first update, so the
    filtered means and covariances are produced here and handed to
    ``KalmanFilter.rts_smoother``. Missing rows (NaN) are skipped in the update.
    """
    nx = sys.A.shape[0]
    kf = KalmanFilter(dim_x=nx, dim_z=sys.C.shape[0])
    kf.F, kf.H, kf.Q, kf.R = sys.A, sys.C, sys.Q, sys.R
    kf.x, kf.P = sys.x0.copy(), sys.P0.copy()
    xs, Ps = [], []
    for k, y in enumerate(Y):
        if k:
            kf.predict()
        rows = np.isfinite(y)
        if rows.all():
            kf.update(y)
        elif rows.any():
            kf.update(y[rows], R=sys.R[np.ix_(rows, rows)], H=sys.C[rows])
        xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    xs, Ps = np.array(xs), np.array(Ps)
    Fs = np.array([sys.A] * len(Y))
    Qs = np.array([sys.Q] * len(Y))
    x_smooth, P_smooth, _, _ = kf.rts_smoother(xs, Ps, Fs, Qs)
    return x_smooth, P_smooth, Ps


@pytest.mark.parametrize("solver", ["gauss-newton", "ipopt"])
@pytest.mark.parametrize("seed", [0, 1])
def test_fit_equals_rts_smoother(solver, seed):
    sys = make_linear(seed)
    Y, _ = _record(sys, T=40, seed=seed + 7)
    x_ref, _, P_filt = _rts_reference(sys, Y)
    fie = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                                solver=solver, solver_options={} if solver != "ipopt"
                                else {"ipopt.tol": 1e-12})
    res = fie.fit(Y, np.zeros((len(Y) - 1, 1)))
    assert res.success and res.status == "ok"
    np.testing.assert_allclose(res.x, x_ref, atol=1e-8)
    # the smoother's last state is the filter's: same covariance
    np.testing.assert_allclose(res.P_last, P_filt[-1], atol=1e-10)
    assert res.w.shape == (39, 4) and res.v.shape == (40, 2)


def test_missing_rows_are_dropped_exactly():
    sys = make_linear(2)
    Y, _ = _record(sys, T=30, seed=5)
    Y[4] = np.nan
    Y[10, 0] = np.nan
    x_ref, _, _ = _rts_reference(sys, Y)
    fie = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    res = fie.fit(Y, 0)
    np.testing.assert_allclose(res.x, x_ref, atol=1e-8)
    assert np.isnan(res.v[4]).all() and np.isnan(res.v[10, 0])


def _lorenz_record(T, seed=0):
    m = estim.models.lorenz()
    ekf = estim.EKF(m, Q=0.02**2, R=0.1**2, x0=[-10, -12, 27], P0=1.0)
    return estim.simulate(m, ekf, x0=[-10.0, -12.0, 27.0], n_steps=T, Q=0.02**2, R=0.1**2,
                          seed=seed)


def test_lorenz_gauss_newton_and_ipopt_reach_the_same_optimum():
    """Seed 000: weights 20 / 1, no prior, from zeros."""
    log = _lorenz_record(100)
    m = estim.models.lorenz()
    res = {s: estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3), solver=s,
                                    solver_options={"ipopt.tol": 1e-12} if s == "ipopt" else {}
                                    ).fit(log.y)
           for s in ("gauss-newton", "ipopt")}
    assert all(r.success for r in res.values())
    np.testing.assert_allclose(res["gauss-newton"].x, res["ipopt"].x, atol=1e-6)
    assert res["gauss-newton"].cost == pytest.approx(res["ipopt"].cost, rel=1e-9)
    # the estimate is far better than inverting the output sample by sample
    assert np.sqrt(np.mean((res["gauss-newton"].x - log.x) ** 2)) < 0.1


def test_chunk_length_leaves_fewest_slots_over():
    """The mapped mode's chunk length stays within a quarter of sqrt(n/5) (between 16 and
    64 slots, at most 1024 chunks) and, within that, leaves the fewest single slots."""
    from estim.solvers.least_squares.gauss_newton import chunk_slots
    for n in (5, 98, 148, 1998, 2000, 9998, 10000, 40000, 123457):
        L = chunk_slots(n)
        base = max(min(64, max(16, round((n / 5) ** 0.5))), -(-n // 1024))
        near = range(base - base // 4, base + base // 4 + 1)
        assert L in near
        assert n % L == min(n % k for k in near)
    assert chunk_slots(1998) == 18 and chunk_slots(2000) == 20  # 111 and 100 chunks


def test_mapped_and_unrolled_modes_agree():
    """The chunked mapped graph (chunks of 16 slots plus 4 single ones on the Lorenz
    record, of 16 alone on the reactor's) solves the same problem: complete data, missing
    outputs, and active bounds."""
    log = _lorenz_record(150, seed=1)
    m = estim.models.lorenz()
    Y = log.y.copy()
    for data in (log.y, Y):
        xs = [estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3),
                                    solver_options={"mode": mode}).fit(data).x
              for mode in ("unrolled", "mapped")]
        np.testing.assert_allclose(xs[0], xs[1], atol=1e-9)
        Y[[3, 70, 140]] = np.nan  # the second pass: missing outputs
        Y[100, 1] = np.nan
    sc = estim.scenarios.batch_reactor()
    rlog = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    kw = dict(Q=0.002**2, R=0.25**2, x0=[0.1, 0.2, 0.6])
    fits = [estim.FullInformation(sc.model, solver_options={"mode": mode}, **kw).fit(
        rlog.y[300:430]) for mode in ("unrolled", "mapped")]
    assert (fits[0].x <= 1e-12).any()  # a bound is active
    np.testing.assert_allclose(fits[0].x, fits[1].x, atol=1e-8)


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                    reason="jit needs a C compiler")
def test_jit_compiled_graph_gives_the_same_fit(tmp_path, monkeypatch):
    """Same fit compiled; the libraries go to the per-machine cache (here
    $ESTIM_CACHE_DIR), not the current directory, and a second estimator, asking by
    ``jit=True``, loads them."""
    cwd, cache = tmp_path / "cwd", tmp_path / "cache"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(cache))
    log = _lorenz_record(40, seed=2)
    m = estim.models.lorenz()
    fits = [estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3), solver_options=opts).fit(
        log.y) for opts in ({}, {"jit": True})]
    assert fits[1].success
    np.testing.assert_allclose(fits[0].x, fits[1].x, atol=1e-9)
    np.testing.assert_allclose(fits[0].P_last, fits[1].P_last, rtol=1e-9)
    assert list(cwd.iterdir()) == []
    libraries = sorted(cache.glob("*.so"))
    assert libraries
    stamps = [lib.stat().st_mtime_ns for lib in libraries]
    # jit=True, the filters' spelling, is the same compiled code (loaded, not rebuilt)
    fie = estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3), jit=True)
    assert fie.jit and fie.solver_options == {"jit": True}
    again = fie.fit(log.y)
    np.testing.assert_array_equal(again.x, fits[1].x)
    assert [lib.stat().st_mtime_ns for lib in sorted(cache.glob("*.so"))] == stamps


def test_singular_system_falls_back_to_the_ridge():
    """No prior and a state that no output sees: J^T J is singular. The first
    direction is not finite; the solver continues with the ridge and still finds
    the optimum of the observable part (the one-state problem's)."""
    A, Ad = np.array([[0.9, 0.0], [0.0, 1.0]]), ca.DM([[0.9, 0.0], [0.0, 1.0]])
    two = estim.Model(states=2, outputs=1, dynamics=lambda x, u, p: Ad @ x,
                      output=lambda x, u, p: x[0], name="hidden")
    one = estim.Model(states=1, outputs=1, dynamics=lambda x, u, p: 0.9 * x,
                      output=lambda x, u, p: x, name="seen")
    rng = np.random.default_rng(3)
    x, Y = np.array([1.0, 2.0]), []
    for _ in range(30):
        Y.append(x[:1] + 0.1 * rng.standard_normal(1))
        x = A @ x + 0.05 * rng.standard_normal(2)
    Y = np.array(Y)
    fie = estim.FullInformation(two, Q=0.05**2, R=0.1**2)
    res = fie.fit(Y, 0)
    ref = estim.FullInformation(one, Q=0.05**2, R=0.1**2).fit(Y)
    assert res.success and fie._problem(30, full=True).gn._ridge
    assert np.isfinite(res.x).all()
    np.testing.assert_allclose(res.x[:, 0], ref.x[:, 0], atol=1e-8)
    np.testing.assert_allclose(res.x[:, 1], 0.0, atol=1e-8)  # not moved from the guess
    assert res.cost == pytest.approx(ref.cost, rel=1e-10)


def test_residuals_are_snapshots():
    """w and v are computed on first access, from the data of the fit."""
    log = _lorenz_record(50)
    m = estim.models.lorenz()
    Y = log.y.copy()
    res = estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3)).fit(Y)
    Y[:] = 0.0  # the caller reuses its array before reading the residuals
    F = np.array([np.asarray(m.F(x, [], m.p)).ravel() for x in res.x[:-1]])
    H = np.array([np.asarray(m.H(x, [], m.p)).ravel() for x in res.x])
    np.testing.assert_allclose(res.w, res.x[1:] - F, atol=1e-12)
    np.testing.assert_allclose(res.v, log.y - H, atol=1e-12)
    np.testing.assert_allclose(res.cost, 20 * np.sum(res.w**2) + np.sum(res.v**2), rtol=1e-12)


def test_bounds_gauss_newton_matches_ipopt():
    """The reactor near equilibrium (C_A ~ 0.01), 25 samples, no prior: x >= 0 is
    active at the optimum and the projection reaches Ipopt's constrained optimum."""
    sc = estim.scenarios.batch_reactor()
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    Y = log.y[300:325]
    kw = dict(Q=0.002**2, R=0.25**2, x0=[0.1, 0.2, 0.6])
    gn = estim.FullInformation(sc.model, **kw).fit(Y)
    ip = estim.FullInformation(sc.model, solver="ipopt", solver_options={"ipopt.tol": 1e-12},
                               **kw).fit(Y)
    assert gn.success and ip.success
    assert gn.x.min() >= 0.0
    assert (gn.x <= 1e-12).any()  # a bound is active at the optimum
    np.testing.assert_allclose(gn.x, ip.x, atol=1e-6)
    assert gn.cost == pytest.approx(ip.cost, rel=1e-7)


def test_step_resolves_the_growing_record():
    sc = estim.scenarios.van_der_pol(n_steps=20)
    fie = estim.FullInformation(sc.model, **sc.tuning)
    log = estim.simulate(sc, fie, seed=0)
    assert log.success.all()
    for k in (0, 5, 19):
        res = estim.FullInformation(sc.model, **sc.tuning).fit(log.y[: k + 1])
        np.testing.assert_allclose(log.x_hat[k], res.x[-1], atol=1e-7)


def test_bad_input():
    m = estim.models.lorenz()
    fie = estim.FullInformation(m, Q=np.eye(3) / 20, R=np.eye(3))
    with pytest.raises(ValueError, match=r"Y must have shape \(T, 3\)"):
        fie.fit(np.zeros((10, 2)))
    with pytest.raises(ValueError, match="at least one sample"):
        fie.fit(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="no measured value"):
        fie.fit(np.full((5, 3), np.nan))
    with pytest.raises(ValueError, match="must not contain inf"):
        fie.fit(np.full((5, 3), np.inf))
    with pytest.raises(TypeError, match="Y must be numeric"):
        fie.fit([["a", "b", "c"]])
    with pytest.raises(ValueError, match=r"U must have shape"):
        estim.FullInformation(estim.models.satellite(), Q=1e-6, R=1e-6).fit(
            np.zeros((5, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"guess must have shape"):
        fie.fit(np.zeros((5, 3)), guess=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="P0 must be positive definite"):
        estim.FullInformation(m, Q=0.05, R=1.0, x0=[0, 0, 0], P0=np.diag([1.0, 1.0, 0.0]))
    with pytest.raises(ValueError, match="P0 was given without x0"):
        estim.FullInformation(m, Q=0.05, R=1.0, P0=1.0)
    # a singular Q is a constrained problem (tests/test_singular_noise.py), not for every
    # solver
    with pytest.raises(ValueError, match="Q is singular.*solver='gauss-newton' does not"):
        estim.FullInformation(m, Q=[0.05, 0.05, 0.0], R=1.0, solver="gauss-newton")
    with pytest.raises(ValueError, match="solver must be one of"):
        estim.FullInformation(m, Q=0.05, R=1.0, solver="panoc")


def test_reset_with_new_prior_uses_it():
    """reset(P0=...) must refactor the prior weight (it is cached per reset)."""
    sys = make_linear(0)
    Y, _ = _record(sys, T=10, seed=2)
    fie = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0)
    tight = estim.FullInformation(sys.model, Q=sys.Q, R=sys.R, x0=sys.x0, P0=1e-6)
    fie.reset(P0=1e-6)
    np.testing.assert_allclose(fie.fit(Y, 0).x, tight.fit(Y, 0).x, atol=1e-10)
    mhe = estim.MHE(sys.model, horizon=4, Q=sys.Q, R=sys.R, x0=sys.x0, P0=sys.P0,
                    arrival_cost="fixed", solver="gauss-newton")
    ref = estim.MHE(sys.model, horizon=4, Q=sys.Q, R=sys.R, x0=sys.x0, P0=1e-6,
                    arrival_cost="fixed", solver="gauss-newton")
    mhe.reset(P0=1e-6)
    for y in Y:
        np.testing.assert_allclose(mhe.step(y), ref.step(y), atol=1e-8)
