"""Process noise on some directions only, in the windowed estimators: a singular ``Q``
makes the dynamics exact where there is no noise, a constrained problem
(:class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`). Checked against filterpy's Kalman
filter and Rauch-Tung-Striebel smoother (which take a singular Q) on a linear-Gaussian
model, and on the textbook pendulum against the EKF and its smoother."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from filterpy.kalman import rts_smoother
from linear_gaussian import P0, X0, A, R, kalman, linear_model, record

import estim

QS = np.diag([0.0, 1e-2])  # noise on the velocity only: the position integrates it


@pytest.fixture(scope="module")
def reference():
    Y = record(40, seed=2)
    x_kf, P_kf, _ = kalman(Y, Q=QS)
    xs, Ps, _, _ = rts_smoother(x_kf, P_kf, [A] * len(Y), [QS] * len(Y))
    return Y, x_kf, P_kf, xs, Ps


@pytest.mark.parametrize("solver", ["auto", "fatrop"])
def test_full_information_is_the_rts_smoother(reference, solver):
    """The MAP trajectory of a linear-Gaussian model with a prior is the smoother's
    mean, and its Laplace covariances the smoother's, with or without noise on every
    state; the position follows the velocity exactly."""
    Y, x_kf, P_kf, xs, Ps = reference
    res = estim.FullInformation(linear_model(), Q=QS, R=R, x0=X0, P0=P0,
                                solver=solver).fit(Y)
    assert res.success and res.solver == ("ipopt" if solver == "auto" else solver)
    np.testing.assert_allclose(res.x, xs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.P, Ps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.P_last, P_kf[-1], rtol=0, atol=1e-9)
    gap = res.x[1:, 0] - (res.x[:-1, 0] + 0.1 * res.x[:-1, 1])
    assert np.abs(gap).max() < 1e-12
    # the cost on the noise it estimated: sum |w|^2 / q over the velocity, no other term
    assert res.w[:, 0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("solver", ["auto", "fatrop"])
def test_mhe_with_a_filtering_arrival_is_the_kalman_filter(reference, solver):
    Y, x_kf, P_kf, _, _ = reference
    mhe = estim.MHE(linear_model(), horizon=10, Q=QS, R=R, x0=X0, P0=P0, solver=solver)
    log = estim.replay(mhe, Y)
    assert set(log.status) == {"ok"}
    np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-9)
    np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-9)


def test_what_does_not_apply_is_named():
    m = linear_model()
    kw = {"R": R, "x0": X0, "P0": P0}
    for solver in ("gauss-newton", "sqp"):
        with pytest.raises(ValueError, match=f"Q is singular \\(rank 1 of 2.*solver='{solver}'"):
            estim.MHE(m, horizon=5, Q=QS, solver=solver, **kw)
    with pytest.raises(ValueError, match="without a robust loss"):
        estim.FullInformation(m, Q=QS, loss="huber", **kw)
    with pytest.raises(ValueError, match="rti=False"):
        estim.MHE(m, horizon=5, Q=QS, rti=True, **kw)
    with pytest.raises(ValueError, match="Q is zero"):
        estim.FullInformation(m, Q=0.0, **kw)
    fie = estim.FullInformation(m, Q=QS, **kw)
    with pytest.raises(ValueError, match="keep the rank it had"):
        fie.set_tuning(Q=np.eye(2))
    with pytest.raises(ValueError, match="keep the rank it had"):
        estim.MHE(m, horizon=5, Q=np.eye(2), **kw).set_tuning(Q=QS)
    fie.set_tuning(Q=np.diag([0.0, 0.5]))  # the same rank: the noise is data
    angle = estim.Model(states=["theta", "omega"], outputs=["y"], angles=["theta"],
                        dynamics=lambda x, u, p: ca.vertcat(x[0] + 0.1 * x[1], x[1]),
                        output=lambda x, u, p: ca.sin(x[0]))
    with pytest.raises(ValueError, match="quaternions or angles"):
        estim.FullInformation(angle, Q=np.diag([0.0, 1e-4]), R=1e-4)


def test_the_pendulum_against_the_ekf_and_its_smoother():
    """The textbook pendulum with noise on the angular rate only (``Q = diag(0, 0.06)``),
    five records: MHE (N = 20, filtering arrival) is the EKF's equal, and full information
    started from the smoother's trajectory is no worse than the smoother (it is the MAP
    trajectory the smoother approximates by linearising). The medians over the records
    measured: EKF 0.62, MHE 0.62, RTS 0.32, FIE 0.32 (20 records; see
    docs/estimators.md)."""
    m = estim.models.sine_pendulum()
    Q = np.diag([0.0, 0.06])
    tuning = {"Q": Q, "R": 0.01, "x0": [1.2, 0.0], "P0": 0.09}
    scores: dict[str, list[float]] = {}
    for seed in range(5):
        log = estim.simulate(m, estim.EKF(m, **tuning), x0=[1.5, 0.0], n_steps=300, Q=Q,
                             R=0.01, seed=seed)
        smooth = estim.EKF(m, **tuning).smooth(log.y)
        fit = estim.FullInformation(m, **tuning).fit(log.y, guess=smooth.x)
        mhe = estim.replay(estim.MHE(m, horizon=20, **tuning), log.y)
        assert fit.success and set(mhe.status) == {"ok"}
        for name, result in (("EKF", log), ("RTS", smooth), ("FIE", fit), ("MHE", mhe)):
            scores.setdefault(name, []).append(float(estim.rmse(result, truth=log)))
    median = {k: float(np.median(v)) for k, v in scores.items()}
    assert median["FIE"] <= median["RTS"]
    assert median["RTS"] < median["EKF"]
    assert abs(median["MHE"] / median["EKF"] - 1.0) < 0.05, median
