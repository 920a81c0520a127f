"""Autocovariance least squares: Q and R recovered from simulated records, within their
standard errors, at the 1/sqrt(T) rate, positive semidefinite, and on a nonlinear model."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize

import estim
from estim.tuning import TuningResult, als


def linear_model(A, C) -> estim.Model:
    A, C = np.asarray(A, float), np.asarray(C, float)
    return estim.Model(states=[f"x{i}" for i in range(A.shape[0])],
                       outputs=[f"y{i}" for i in range(C.shape[0])],
                       dynamics=lambda x, u, p: ca.mtimes(ca.DM(A), x),
                       output=lambda x, u, p: ca.mtimes(ca.DM(C), x), dt=1.0)


def record(A, C, Q, R, T, seed):
    """y_k = C x_k + v_k, x_{k+1} = A x_k + w_k from x_0 = 0, w ~ N(0, Q), v ~ N(0, R)."""
    rng = np.random.default_rng(seed)
    nx, ny = len(A), len(C)
    lam, V = np.linalg.eigh(Q)  # Q may be singular
    W = rng.standard_normal((T, nx)) @ (V * np.sqrt(np.maximum(lam, 0.0))).T
    E = rng.standard_normal((T, ny)) @ np.linalg.cholesky(R).T
    x = np.zeros(nx)
    Y = np.empty((T, ny))
    for k in range(T):
        Y[k] = C @ x + E[k]
        x = A @ x + W[k]
    return Y


# three states, two outputs: a diagonal Q and a full R
A3 = np.array([[0.9, 0.2, 0.0], [0.0, 0.7, 0.1], [0.1, 0.0, 0.8]])
C3 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
Q3 = np.diag([0.5, 0.2, 0.1])
R3 = np.array([[1.0, 0.3], [0.3, 0.5]])
# two states, both measured
A2 = np.array([[0.9, 0.3], [-0.2, 0.8]])
C2 = np.eye(2)
Q2 = np.diag([0.2, 0.1])
R2 = np.diag([0.5, 0.3])


def free(res: TuningResult):
    """Estimates and standard errors of the entries the structure leaves free."""
    est = np.r_[res.Q[~np.isnan(res.stderr["Q"])], res.R[~np.isnan(res.stderr["R"])]]
    se = np.r_[res.stderr["Q"][~np.isnan(res.stderr["Q"])],
               res.stderr["R"][~np.isnan(res.stderr["R"])]]
    return est, se


@pytest.mark.parametrize("weighting", ["identity", "optimal"])
def test_als_recovers_a_diagonal_q_and_a_full_r_within_its_standard_errors(weighting):
    model = linear_model(A3, C3)
    Y = record(A3, C3, Q3, R3, 8000, seed=1)
    res = als(model, Y, structure={"Q": "diagonal", "R": "full"}, weighting=weighting)
    assert res.method == "als" and res.success
    assert res.details["linearization"] == "time-invariant"
    est, se = free(res)
    truth = np.r_[np.diag(Q3), R3[0, 0], R3[0, 1], R3[1, 0], R3[1, 1]]
    assert est.shape == truth.shape
    # asymptotically normal estimates: 3 standard errors (a Monte Carlo of 30 records
    # gave standard errors 1.0-1.3 times the spread of the estimates)
    assert np.all(np.abs(est - truth) < 3 * se), (est, truth, se)
    np.testing.assert_allclose(res.Q, np.diag(np.diag(res.Q)))  # the structure holds
    assert np.isnan(res.stderr["Q"][0, 1]) and res.stderr["R"][0, 1] > 0
    assert res.check.white and res.check.nis_bounds[0] < res.check.nis_mean < \
        res.check.nis_bounds[1]
    if weighting == "optimal":
        stat, dof, p = res.details["overidentification"]
        assert dof == res.details["equations"][0].shape[0] - 6 and p > 1e-3


def test_als_error_shrinks_like_one_over_sqrt_t():
    """The estimates from the first T = 1000, 4000, 16000 samples of 12 seeded records.

    The standard errors halve per x4 samples (to 10 %), and the errors are of their size
    (RMS of error / standard error within [0.5, 1.6], for 144 numbers). The errors'
    RMS over the records and entries is noisy: over 10 sets of 4 records the log of the
    ratio between T = 1000 and 16000 (expected 4) had a spread of 0.5, so 0.29 for 12
    records, and the ratio is checked within 4 exp(±0.7), [2, 8], about 2.4 sigma; the
    per-x4 ratios (expected 2) within [1, 4]."""
    model = linear_model(A2, C2)
    truth = np.r_[np.diag(Q2), np.diag(R2)]
    sizes = (1000, 4000, 16000)
    err = {T: [] for T in sizes}
    se = {T: [] for T in sizes}
    for seed in range(12):
        Y = record(A2, C2, Q2, R2, sizes[-1], seed=10 + seed)
        for T in sizes:
            res = als(model, Y[:T])
            est = np.r_[np.diag(res.Q), np.diag(res.R)]
            err[T].append((est - truth) / truth)
            se[T].append(np.r_[np.diag(res.stderr["Q"]), np.diag(res.stderr["R"])] / truth)
    rms = {T: np.sqrt(np.mean(np.square(err[T]))) for T in sizes}
    srms = {T: np.sqrt(np.mean(np.square(se[T]))) for T in sizes}
    assert 2 < rms[1000] / rms[16000] < 8, rms
    assert 1 < rms[1000] / rms[4000] < 4 and 1 < rms[4000] / rms[16000] < 4, rms
    for small, large in zip(sizes, sizes[1:], strict=False):
        assert srms[small] / srms[large] == pytest.approx(2.0, rel=0.1)
    # and the errors are of the size the standard errors say
    z = np.concatenate([np.divide(err[T], se[T]) for T in sizes])
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6


@pytest.mark.parametrize("structure", ["diagonal", "full"])
def test_als_enforces_positive_semidefinite_covariances(structure):
    """A short record and a tiny true Q: the unconstrained least squares is indefinite,
    the constrained one is PSD and at least as good as any PSD point tried."""
    model = linear_model(A2, C2)
    Qt = 1e-6 * np.eye(2)
    Y = record(A2, C2, Qt, R2, 300, seed=3)
    res = als(model, Y, structure={"Q": structure, "R": "diagonal"}, burn_in=20)
    un = res.details["unconstrained"]
    assert np.linalg.eigvalsh(un["Q"]).min() < 0  # the case this test is about
    assert res.details["constraint_active"]
    assert np.linalg.eigvalsh(res.Q).min() > -1e-12
    assert np.linalg.eigvalsh(res.R).min() > 0
    # the same problem solved another way: a Cholesky factor of Q, from several starts
    A_als, b = res.details["equations"]
    theta = res.details["theta"]
    assert res.objective == pytest.approx(float(np.sum((A_als @ theta - b) ** 2)))

    def cost(z):
        if structure == "diagonal":
            th = np.r_[z[:2] ** 2, z[2:]]
        else:
            Lq = np.array([[z[0], 0.0], [z[1], z[2]]])
            Qz = Lq @ Lq.T
            th = np.r_[Qz[0, 0], Qz[0, 1], Qz[1, 1], z[3:]]
        return float(np.sum((A_als @ th - b) ** 2))

    n = 4 if structure == "diagonal" else 5
    rng = np.random.default_rng(0)
    best = min(minimize(cost, np.r_[0.1 * rng.random(n - 2), 0.5, 0.3], method="Nelder-Mead",
                        options={"xatol": 1e-12, "fatol": 1e-16, "maxiter": 20000}).fun
               for _ in range(4))
    assert res.objective <= best * (1 + 1e-6) + 1e-14


def test_als_on_van_der_pol_tunes_an_ekf_as_well_as_the_true_covariances():
    """Time-varying ALS along the EKF's estimates (an approximation for a nonlinear model):
    Q = 0.1² I and R = I recovered, and an EKF with the estimates tracks new records as
    well as one with the true covariances."""
    sc = estim.scenarios.van_der_pol(n_steps=10000)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    # a poor starting filter: Q0 ten times too large, R0 four times too small
    res = als(sc.model, log.y, Q0=0.1, R0=0.25, x0=sc.tuning["x0"], P0=sc.tuning["P0"])
    assert res.details["linearization"] == "time-varying"
    est, se = free(res)
    truth = np.array([0.01, 0.01, 1.0, 1.0])
    assert np.all(np.abs(est - truth) < 3 * se), (est, se)
    np.testing.assert_allclose(np.diag(res.R), 1.0, atol=0.1)
    assert np.all((np.diag(res.Q) > 0.003) & (np.diag(res.Q) < 0.03))
    test = estim.scenarios.van_der_pol(n_steps=1000)
    tuned = {**sc.tuning, "Q": res.Q, "R": res.R}
    rmse_true = np.mean([float(estim.rmse(estim.simulate(test, estim.EKF(test.model, **sc.tuning),
                                                   seed=s))) for s in range(100, 106)])
    rmse_tuned = np.mean([float(estim.rmse(estim.simulate(test, estim.EKF(test.model, **tuned),
                                                    seed=s))) for s in range(100, 106)])
    assert rmse_tuned < 1.05 * rmse_true, (rmse_tuned, rmse_true)


def test_als_gains_and_shaping():
    model = linear_model(A2, C2)
    Y = record(A2, C2, Q2, R2, 4000, seed=5)
    ref = als(model, Y)
    # a fixed gain given as an array: the same time-invariant equations
    L = np.array([[0.4, 0.1], [0.0, 0.3]])
    fixed = als(model, Y, gain=L)
    assert fixed.details["gain"] == "fixed gain"
    # an EKF replayed with its own tuning: time-varying (its gain converges)
    ekf = estim.EKF(model, Q=0.05, R=1.0, x0=[0, 0], P0=1.0)
    tv = als(model, Y, gain=ekf)
    assert tv.details["linearization"] == "time-varying"
    for res in (fixed, tv):
        est, se = free(res)
        assert np.all(np.abs(est - free(ref)[0]) < 3 * se)
    # Q = G q G^T with a known shape
    G = np.array([[1.0], [0.5]])
    shaped = als(model, record(A2, C2, 0.2 * G @ G.T, R2, 4000, seed=6), G=G)
    assert shaped.details["Q_w"].shape == (1, 1)
    np.testing.assert_allclose(shaped.Q, shaped.details["Q_w"][0, 0] * G @ G.T)
    assert abs(shaped.details["Q_w"][0, 0] - 0.2) < 3 * shaped.stderr["Q"][0, 0]


def test_als_summary_and_plot(tmp_path):
    res = als(linear_model(A2, C2), record(A2, C2, Q2, R2, 1000, seed=0))
    assert "Q[0,0]" in res.summary() and "Ljung-Box" in res.summary()
    res.plot(tmp_path / "acf.png")
    assert (tmp_path / "acf.png").stat().st_size > 10_000


def test_als_refuses_bad_input():
    model = linear_model(A2, C2)
    Y = record(A2, C2, Q2, R2, 500, seed=0)
    bad = Y.copy()
    bad[3, 0] = np.nan
    with pytest.raises(ValueError, match="Y must be finite"):
        als(model, bad)
    with pytest.raises(ValueError, match="gain must be a finite"):
        als(model, Y, gain=np.ones((3, 2)))
    with pytest.raises(TypeError, match="gain must be None"):
        als(model, Y, gain=estim.UKF(model, Q=0.1, R=1.0, x0=[0, 0], P0=1.0))
    with pytest.raises(ValueError, match="unstable"):
        als(model, Y, gain=-3 * np.eye(2))
    with pytest.raises(ValueError, match="structure"):
        als(model, Y, structure="diagonl")
    with pytest.raises(ValueError, match="weighting"):
        als(model, Y, weighting="best")
    with pytest.raises(ValueError, match="too few samples"):
        als(model, Y[:40])
    # two states, one output: a full Q is not identifiable
    one = linear_model(A2, C2[:1])
    with pytest.raises(ValueError, match="not identifiable"):
        als(one, Y[:, :1], structure={"Q": "full"})
    with pytest.raises(ValueError, match="lags"):
        als(model, Y, lags=0)
    with pytest.raises(ValueError, match="give gain=None"):
        als(model, Y, gain=np.eye(2) * 0.5, iterations=2)


def test_als_second_pass_from_a_bad_filter_is_more_precise():
    """ALS is consistent for any stable gain, but a gain far from the optimal one gives
    imprecise estimates; a second pass from the filter of the first estimate fixes it."""
    model = linear_model(A2, C2)
    Y = record(A2, C2, Q2, R2, 4000, seed=7)
    one = als(model, Y, Q0=10.0, R0=0.01)
    two = als(model, Y, Q0=10.0, R0=0.01, iterations=2)
    assert two.details["iterations"] == 2
    assert np.all(two.stderr["Q"].diagonal() < 0.7 * one.stderr["Q"].diagonal())
    est, se = free(two)
    assert np.all(np.abs(est - np.r_[np.diag(Q2), np.diag(R2)]) < 3 * se)


def test_als_says_when_a_variance_is_poorly_determined():
    """A state seen through a gain of 0.02: its process noise is all but invisible."""
    A = np.diag([0.9, 0.5])
    C = np.array([[1.0, 0.02]])
    Y = record(A, C, np.diag([0.2, 0.2]), np.array([[0.5]]), 2000, seed=0)
    res = als(linear_model(A, C), Y)
    assert res.status.startswith("poorly determined: Q[1,1]") and "R[0,0]" not in res.status
    assert abs(res.Q[0, 0] - 0.2) < 3 * res.stderr["Q"][0, 0]
    assert als(linear_model(A2, C2), record(A2, C2, Q2, R2, 2000, seed=0)).status == "ok"
