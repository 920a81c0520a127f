"""The interacting multiple model filter against filterpy's IMMEstimator, and its checks."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import IMMEstimator, KalmanFilter

import estim
from estim.estimators.kalman.imm import IMM

F = np.array([[1.0, 1.0], [0.0, 1.0]])  # constant velocity, unit sample time
H = np.array([[1.0, 0.0]])
QS = {"quiet": np.diag([1e-4, 1e-4]), "manoeuvre": np.diag([0.5, 2.0])}
R = np.array([[1.0]])
X0, P0 = np.array([0.0, 1.0]), np.diag([4.0, 1.0])
PI = np.array([[0.95, 0.05], [0.1, 0.9]])
MU0 = np.array([0.6, 0.4])


def _dynamics(x, u, p):
    return F @ x


def _output(x, u, p):
    return H @ x


def target() -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"], dynamics=_dynamics, output=_output)


def record(T: int = 60, seed: int = 0) -> np.ndarray:
    """A target that cruises, turns hard between samples 20 and 30, and cruises again."""
    rng = np.random.default_rng(seed)
    x, Y = X0.copy(), []
    for k in range(T):
        if k:
            a = 1.5 if 20 <= k < 30 else 0.0
            x = F @ x + np.array([0.5 * a, a])
        Y.append(H @ x + rng.normal(0.0, 1.0, 1))
    return np.array(Y)


def reference(Y: np.ndarray):
    filters = []
    for Q in QS.values():
        kf = KalmanFilter(2, 1)
        kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = F, H, Q, R, X0.copy(), P0.copy()
        filters.append(kf)
    imm = IMMEstimator(filters, MU0.copy(), PI)
    xs, Ps, mus = [], [], []
    for k, y in enumerate(Y):
        if k:
            imm.predict()
        imm.update(y)
        xs.append(imm.x.copy())
        Ps.append(imm.P.copy())
        mus.append(imm.mu.copy())
    return np.array(xs), np.array(Ps), np.array(mus)


@pytest.mark.parametrize("form", ["covariance", "sqrt"])
@pytest.mark.parametrize("kind", ["EKF", "UKF"])
def test_equals_filterpy_imm_with_linear_modes(kind, form):
    """Linear modes: every state, covariance and mode probability equals filterpy's
    IMMEstimator over KalmanFilters to 1e-10 (the UKF is exact on a linear model)."""
    Y = record()
    xs, Ps, mus = reference(Y)
    m = target()
    cls = getattr(estim, kind)
    modes = {name: cls(m, Q=Q, R=R, x0=X0, P0=P0, form=form) for name, Q in QS.items()}
    imm = IMM(modes, transition=PI, mu0=MU0)
    for k, y in enumerate(Y):
        x = imm.step(y)
        mu = np.array(list(imm.info.extra["mode_probabilities"].values()))
        np.testing.assert_allclose(x, xs[k], rtol=0, atol=1e-10 * (1 + np.abs(xs[k]).max()))
        np.testing.assert_allclose(imm.info.P, Ps[k], rtol=0,
                                   atol=1e-10 * (1 + np.abs(Ps[k]).max()))
        np.testing.assert_allclose(mu, mus[k], rtol=0, atol=1e-10)
    # the manoeuvre is found: the manoeuvring mode dominates during the turn
    assert max(mus[22:30, 1]) > 0.9 and mus[5:15, 0].mean() > 0.8


def test_runs_in_the_loop_with_missing_outputs():
    m = target()
    modes = {name: estim.EKF(m, Q=Q, R=R, x0=X0, P0=P0) for name, Q in QS.items()}
    imm = IMM(modes, transition=PI)
    Y = record(40)
    Y[10:14] = np.nan
    log = estim.replay(imm, Y)
    assert np.isfinite(np.asarray(log.x_hat)).all() and all(log.success)
    assert set(imm.info.extra["modes"]) == set(QS)


def test_bad_arguments_are_named():
    m = target()
    ekf = estim.EKF(m, Q=QS["quiet"], R=R, x0=X0, P0=P0)
    other = estim.EKF(m, Q=QS["manoeuvre"], R=R, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="at least two"):
        IMM({"a": ekf}, transition=[[1.0]])
    with pytest.raises(TypeError, match=r"estimators\['b'\] must be an estim.EKF"):
        IMM({"a": ekf, "b": "filter"}, transition=PI)
    with pytest.raises(ValueError, match="transition must have shape"):
        IMM({"a": ekf, "b": other}, transition=np.eye(3))
    with pytest.raises(ValueError, match="row of transition must sum to 1"):
        IMM({"a": ekf, "b": other}, transition=[[0.9, 0.2], [0.1, 0.9]])
    with pytest.raises(ValueError, match="non-negative"):
        IMM({"a": ekf, "b": other}, transition=[[1.1, -0.1], [0.1, 0.9]])
    with pytest.raises(ValueError, match="mu0 must sum to 1"):
        IMM({"a": ekf, "b": other}, transition=PI, mu0=[0.5, 0.6])
    renamed = estim.Model(states=["q", "v"], outputs=["y"], dynamics=_dynamics,
                          output=_output)
    with pytest.raises(ValueError, match="other state names"):
        IMM({"a": ekf, "b": estim.EKF(renamed, Q=QS["quiet"], R=R, x0=X0, P0=P0)},
            transition=PI)
    with pytest.raises(ValueError, match="distinct"):
        IMM({"a": ekf, "b": ekf}, transition=PI)


def test_noise_levels_is_the_two_mode_imm():
    """``IMM.noise_levels`` (what ``estim run -e imm`` builds) equals the IMM written out:
    modes with Q and high * Q, switching with probability 1 - stay."""
    m = target()
    Y = record(30)
    quick = IMM.noise_levels(m, Q=QS["quiet"], R=R, x0=X0, P0=P0, high=50.0, stay=0.9)
    by_hand = IMM({"quiet": estim.EKF(m, Q=QS["quiet"], R=R, x0=X0, P0=P0),
                   "agile": estim.EKF(m, Q=50.0 * QS["quiet"], R=R, x0=X0, P0=P0)},
                  transition=[[0.9, 1 - 0.9], [1 - 0.9, 0.9]])
    a, b = estim.replay(quick, Y), estim.replay(by_hand, Y)
    np.testing.assert_array_equal(np.asarray(a.x_hat), np.asarray(b.x_hat))
    assert isinstance(IMM.noise_levels(m, Q=QS["quiet"], R=R, x0=X0, P0=P0,
                                       kind="ukf").estimators["agile"], estim.UKF)
    for kwargs, match in (({"stay": 1.0}, "stay"), ({"stay": 0.0}, "stay"),
                          ({"high": -1.0}, "high"), ({"kind": "pf"}, "kind")):
        with pytest.raises(ValueError, match=match):
            IMM.noise_levels(m, Q=QS["quiet"], R=R, x0=X0, P0=P0, **kwargs)
