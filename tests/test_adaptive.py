"""Measurement noise learnt online: ``EKF/UKF(adapt="R", forgetting=rho)``, the variational
Bayes adaptive filter of Särkkä & Hartikainen (2013), against a plain numpy transcription
of the paper's algorithm, on a switching noise, over a long gap, and what it refuses."""

from __future__ import annotations

import numpy as np
import pytest
from test_student_t import A, H, Q, linear_model
from test_student_t import R as R0

import estim
from estim.estimators.kalman.heavy_tails import ITERATIONS


def switching_record(T: int = 400, seed: int = 0):
    """R = R0 for the first half, 9 R0 after; a sample with one output missing."""
    rng = np.random.default_rng(seed)
    x, Y = np.zeros(2), []
    for k in range(T):
        if k:
            x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        Y.append(H @ x + rng.multivariate_normal(np.zeros(2), R0 * (1 if k < T // 2 else 9)))
    Y = np.array(Y)
    Y[100, 1] = np.nan
    return Y


def vb_akf(Y, rho):
    """The paper's algorithm, per sample (numpy): the statistics' prediction by the
    forgetting, then ITERATIONS fixed-point updates; a sample with a missing output
    updated with the predicted noise, the statistics left at their prediction."""
    d = 2
    x, P = np.zeros(2), np.eye(2)
    nu, V = 1 / (1 - rho) + d + 1, R0 / (1 - rho)
    xs, Rs = [], []
    for k, y in enumerate(Y):
        if k:
            x, P = A @ x, A @ P @ A.T + Q
            nu, V = rho * (nu - d - 1) + d + 1, rho * V
        rows = np.isfinite(y)
        if rows.all():
            nu, V0, xb, Pb = nu + 1, V.copy(), x, P
            for _ in range(ITERATIONS):
                S = H @ Pb @ H.T + V / (nu - d - 1)
                K = Pb @ H.T @ np.linalg.inv(S)
                x, P = xb + K @ (y - H @ xb), Pb - K @ S @ K.T
                r = y - H @ x
                V = V0 + np.outer(r, r) + H @ P @ H.T
        else:
            Hm, Rm = H[rows], (V / (nu - d - 1))[np.ix_(rows, rows)]
            S = Hm @ P @ Hm.T + Rm
            K = P @ Hm.T @ np.linalg.inv(S)
            x, P = x + K @ (y[rows] - Hm @ x), P - K @ S @ K.T
        xs.append(x)
        Rs.append(V / (nu - d - 1))
    return np.array(xs), np.array(Rs)


@pytest.mark.parametrize("F", [estim.EKF, estim.UKF])
def test_the_adaptive_filter_is_the_papers(F):
    """A full R that jumps ninefold halfway, a missing output: ``filter``, ``replay`` and
    ``info.extra["R"]`` are the numpy transcription to 1e-12 (measured 1.8e-14 for the
    EKF, 4.3e-14 for the UKF, whose statistical linear regression is exact here), and the
    learnt R follows the jump (its trace within 30 % of the truth's at the end)."""
    Y = switching_record()
    want_x, want_R = vb_akf(Y, 0.98)
    f = F(linear_model(), Q=Q, R=R0, x0=np.zeros(2), P0=np.eye(2), adapt="R",
          forgetting=0.98)
    res = f.filter(Y)
    np.testing.assert_allclose(res.x, want_x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.R, want_R, rtol=0, atol=1e-12)
    log = estim.replay(f, Y)
    np.testing.assert_allclose(log.x_hat, want_x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.diagnostic("R"), want_R, rtol=0, atol=1e-12)
    assert abs(np.trace(res.R[-1]) / np.trace(9 * R0) - 1) < 0.3
    assert abs(np.trace(res.R[190]) / np.trace(R0) - 1) < 0.3


def test_a_long_gap_keeps_the_learnt_noise_and_fades_its_weight():
    """Every output missing for 100 samples: the learnt R stays where it was (its mean
    is unchanged by the forgetting) while its weight fades, so the first measurements
    after the gap move it more than before; the filter predicts through the gap."""
    Y = switching_record()
    Y[250:350] = np.nan
    f = estim.EKF(linear_model(), Q=Q, R=R0, x0=np.zeros(2), P0=np.eye(2), adapt="R")
    res = f.filter(Y)
    np.testing.assert_allclose(res.R[250:350], np.broadcast_to(res.R[249], (100, 2, 2)),
                               rtol=1e-12)
    assert set(res.status) == {"ok"}
    # a sample's pull on R: about 1/(weight + 1), the weight 50 before the gap and
    # 50 * 0.98^100 = 6.6 after it (measured: a mean step 0.065 after, 0.015 before)
    step = np.abs(np.diff(res.R, axis=0)).max(axis=(1, 2))
    assert step[349:354].mean() > 3 * step[244:249].mean()


def test_what_the_adaptive_filters_refuse():
    m = linear_model()
    kw = {"Q": Q, "R": R0, "x0": np.zeros(2), "P0": np.eye(2)}
    for bad in (0.0, -0.5, 1.01, 2.0):
        with pytest.raises(ValueError, match=r"forgetting must be in \(0, 1\]"):
            estim.EKF(m, **kw, adapt="R", forgetting=bad)
    with pytest.raises(ValueError, match="forgetting must be a finite number"):
        estim.UKF(m, **kw, adapt="R", forgetting=np.nan)
    with pytest.raises(ValueError, match="adapt must be one of"):
        estim.EKF(m, **kw, adapt="P")
    for bad in ({"iterations": 3}, {"noise": "student-t", "dof": 4}):
        with pytest.raises(ValueError, match="with iterations=1 and a Gaussian noise"):
            estim.EKF(m, **kw, adapt="R", **bad)
    with pytest.raises(ValueError, match="adapt='QR' in the covariance form"):
        estim.UKF(m, **kw, adapt="QR", form="sqrt")
    f = estim.EKF(m, **kw, adapt="R")
    with pytest.raises(ValueError, match="adapts its noise"):
        estim.IMM({"a": f, "b": estim.EKF(m, **kw)},
                  transition=np.array([[0.95, 0.05], [0.05, 0.95]]))
    assert estim.EKF(m, **kw).filter(switching_record()).R is None


def test_a_switching_noise_is_tracked_near_the_oracle():
    """The resonator of benchmarks/adaptive.py (R 1, 4, 1, then drifting), 5 seeds: the
    adaptive EKF (forgetting 0.95) is within 5 % of filterpy's Kalman filter told the true
    R_k at every sample (measured over 50 seeds: 1.009 in the median, 1.044 at worst), and
    better than the EKF with the record's mean R on average."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parents[1] / "benchmarks"))
    from adaptive import discretised, model, oracle, record

    F, Qd = discretised()
    m = model(F)
    tun = {"Q": Qd, "x0": [0.0, 0.0], "P0": np.eye(2)}
    vb = estim.EKF(m, **tun, R=1.0, adapt="R", forgetting=0.95)
    fixed = estim.EKF(m, **tun, R=1.5)
    ratios, gains = [], []
    for seed in range(5):
        X, Y, Rk = record(seed, F, Qd, False)
        best = np.sqrt(np.mean((oracle(F, Qd, Y, Rk) - X) ** 2))
        ratios.append(np.sqrt(np.mean((vb.filter(Y).x - X) ** 2)) / best)
        gains.append(np.sqrt(np.mean((fixed.filter(Y).x - X) ** 2)) / best - ratios[-1])
    assert max(ratios) < 1.05 and np.mean(gains) > 0


def definite(M):
    """Every Cholesky pivot above DEFINITE times the largest variance."""
    from estim.estimators.kalman.adaptive import DEFINITE

    p0 = M[0, 0]
    p1 = M[1, 1] - M[1, 0] ** 2 / p0 if p0 > 0 else -1.0
    return min(p0, p1) > DEFINITE * max(M[0, 0], M[1, 1])


def sage_husa(Y, b):
    """Sage and Husa's fading-memory estimate, per sample (numpy): the Kalman update with
    the current estimate, then the estimate moved towards e e^T - H Pbar H^T, a candidate
    that is not positive definite replaced by the one without the subtraction, or the
    estimate kept."""
    x, P, Rh, j = np.zeros(2), np.eye(2), R0.copy(), 0
    xs, Rs, fallbacks = [], [], 0
    for k, y in enumerate(Y):
        if k:
            x, P = A @ x, A @ P @ A.T + Q
        rows = np.isfinite(y)
        Hm, Rm = H[rows], Rh[np.ix_(rows, rows)]
        S = Hm @ P @ Hm.T + Rm
        K = P @ Hm.T @ np.linalg.inv(S)
        e = y[rows] - Hm @ x
        Pzz = Hm @ P @ Hm.T
        x, P = x + K @ e, P - K @ S @ K.T
        if rows.all():
            d = (1 - b) / (1 - b ** (j + 1))
            first = (1 - d) * Rh + d * (np.outer(e, e) - Pzz)
            second = (1 - d) * Rh + d * np.outer(e, e)
            if definite(first):
                Rh = first
            else:
                fallbacks += 1
                Rh = second if definite(second) else Rh
            j += 1
        xs.append(x)
        Rs.append(Rh)
    return np.array(xs), np.array(Rs), fallbacks


@pytest.mark.parametrize("F", [estim.EKF, estim.UKF])
def test_sage_husa_is_the_classical_estimate_with_its_guard(F):
    """``adapt="sage-husa"``: the numpy transcription to 1e-10 on the switching record,
    whose first samples' estimates are not positive definite (the classical failure,
    guarded: every learnt R is positive definite)."""
    Y = switching_record()
    want_x, want_R, fallbacks = sage_husa(Y, 0.97)
    assert fallbacks > 0  # the guard is exercised
    res = F(linear_model(), Q=Q, R=R0, x0=np.zeros(2), P0=np.eye(2), adapt="sage-husa",
            forgetting=0.97).filter(Y)
    np.testing.assert_allclose(res.x, want_x, rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.R, want_R, rtol=0, atol=1e-10)
    assert np.linalg.eigvalsh(res.R).min() > 0


@pytest.mark.parametrize("adapt, F, form", [
    ("R", estim.EKF, "covariance"), ("R", estim.UKF, "covariance"),
    ("sage-husa", estim.EKF, "covariance"), ("QR", estim.EKF, "covariance"),
    ("R", estim.UKF, "sqrt")])
def test_the_exported_adaptive_filter_is_pythons(adapt, F, form, tmp_path):
    """The C export carries the learnt noise in its filter state: the same estimates,
    covariances and learnt R (``<name>_noise``) as Python to 1e-12 over the switching
    record with its missing output, and a reset starts the noise at R again."""
    import ctypes

    from codegen_build import build

    from estim._compile import compiler

    if compiler() is None:
        pytest.skip("no C compiler")
    Y = switching_record(200)
    f = F(linear_model(), Q=Q, R=R0, x0=np.zeros(2), P0=np.eye(2), adapt=adapt,
          forgetting=0.97, form=form)
    estim.codegen.export(f, tmp_path, name="vb")
    lib = ctypes.CDLL(str(build(tmp_path, "vb")))
    d = ctypes.POINTER(ctypes.c_double)
    lib.vb_step.argtypes = [ctypes.c_void_p, d, d, d, d]
    lib.vb_noise.argtypes = [ctypes.c_void_p, d]
    lib.vb_size.restype = ctypes.c_size_t
    memory = np.zeros(int(lib.vb_size()) // 8 + 1)
    e = ctypes.c_void_p(memory.ctypes.data)
    assert lib.vb_init(e) == 0
    res = f.filter(Y)
    xs, Ps, Rs = [], [], []
    for y in Y:
        y = np.ascontiguousarray(y, dtype=float)
        x, P, R = np.empty(2), np.empty(4), np.empty(4)
        lib.vb_step(e, y.ctypes.data_as(d), None, x.ctypes.data_as(d), P.ctypes.data_as(d))
        assert lib.vb_noise(e, R.ctypes.data_as(d)) == 0
        xs.append(x)
        Ps.append(P.reshape(2, 2, order="F"))
        Rs.append(R.reshape(2, 2, order="F"))
    np.testing.assert_allclose(np.array(xs), res.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.array(Ps), res.P, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.array(Rs), res.R, rtol=0, atol=1e-12)
    if adapt == "QR":
        Qh = np.empty(4)
        lib.vb_process_noise.argtypes = [ctypes.c_void_p, d]
        assert lib.vb_process_noise(e, Qh.ctypes.data_as(d)) == 0
        np.testing.assert_allclose(Qh.reshape(2, 2, order="F"), res.Q[-1], rtol=0, atol=1e-12)
    assert lib.vb_reset(e) == 0
    R = np.empty(4)
    lib.vb_noise(e, R.ctypes.data_as(d))
    np.testing.assert_allclose(R.reshape(2, 2, order="F"), R0, rtol=1e-15)


def huang(Y, rho, tau=3.0):
    """Huang et al. (2018), Algorithm 1, per sample (numpy): the predicted covariance's
    inverse Wishart about A P A^T + Q with weight tau, the measurement noise's as in
    vb_akf; an output missing: the plain update with the predicted noise, Q as given."""
    n = m = 2
    x, P = np.zeros(2), np.eye(2)
    u, U = 1 / (1 - rho) + m + 1, R0 / (1 - rho)
    xs, Rs, Qs = [], [], []
    for k, y in enumerate(Y):
        Pt = P
        if k:
            x, Pt = A @ x, A @ P @ A.T + Q
            u, U = rho * (u - m - 1) + m + 1, rho * U
        rows = np.isfinite(y)
        if rows.all():
            xb, t, u = x, n + tau + 2, u + 1
            T0, U0 = tau * Pt, U
            xi, Pi = xb, Pt  # x^(0), P^(0)
            for _ in range(ITERATIONS):  # steps 4-12
                dx = xi - xb
                Pbar = (Pi + np.outer(dx, dx) + T0) / (t - n - 1)
                U = np.outer(y - H @ xi, y - H @ xi) + H @ Pi @ H.T + U0
                K = Pbar @ H.T @ np.linalg.inv(H @ Pbar @ H.T + U / (u - m - 1))
                xi, Pi = xb + K @ (y - H @ xb), Pbar - K @ H @ Pbar
            x, P = xi, Pi  # step 13: x^(N), P^(N), U^(N)
            Qh = Q + Pbar - Pt
        else:
            Hm, Rm = H[rows], (U / (u - m - 1))[np.ix_(rows, rows)]
            S = Hm @ Pt @ Hm.T + Rm
            K = Pt @ Hm.T @ np.linalg.inv(S)
            x, P, Qh = x + K @ (y[rows] - Hm @ x), Pt - K @ S @ K.T, Q
        xs.append(x)
        Rs.append(U / (u - m - 1))
        Qs.append(Qh)
    return np.array(xs), np.array(Rs), np.array(Qs)


@pytest.mark.parametrize("F", [estim.EKF, estim.UKF])
def test_adapting_q_and_r_is_huangs_algorithm(F):
    """``adapt="QR"``: the numpy transcription of Huang et al.'s algorithm to 1e-12 on
    the switching record (measured 4.7e-14 and 8.9e-14 in the means), the learnt R and the
    process noise it implies in ``FilterResult.R`` and ``.Q``."""
    Y = switching_record()
    want_x, want_R, want_Q = huang(Y, 0.97)
    res = F(linear_model(), Q=Q, R=R0, x0=np.zeros(2), P0=np.eye(2), adapt="QR",
            forgetting=0.97).filter(Y)
    np.testing.assert_allclose(res.x, want_x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.R, want_R, rtol=0, atol=1e-12)
    np.testing.assert_allclose(res.Q, want_Q, rtol=0, atol=1e-12)
    assert res.Q.shape == (len(Y), 2, 2)


@pytest.mark.parametrize("F", [estim.EKF, estim.UKF])
@pytest.mark.parametrize("adapt", ["R", "sage-husa"])
def test_the_square_root_forms_adapt_as_the_covariance_forms(F, adapt):
    """``form="sqrt"``: the noise of the final update (its factor) from the same
    statistics, the factor's update with it: the covariance form's estimates,
    covariances and learnt R to 1e-12 (measured 4.3e-14 at most)."""
    Y = switching_record()
    kw = {"Q": Q, "R": R0, "x0": np.zeros(2), "P0": np.eye(2), "adapt": adapt,
          "forgetting": 0.97}
    a = F(linear_model(), **kw).filter(Y)
    b = F(linear_model(), **kw, form="sqrt").filter(Y)
    for k in ("x", "P", "R"):
        np.testing.assert_allclose(getattr(b, k), getattr(a, k), rtol=0, atol=1e-12)
