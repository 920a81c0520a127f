"""Disturbance models (``Model.with_disturbances``): offset-free estimation and the
detectability condition of Pannocchia and Rawlings (2003)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import estim

A = np.array([[0.9, 0.1], [0.0, 0.8]])
B = np.array([[0.0], [0.5]])


def plant(bias_u: float = 0.0, bias_y: float = 0.0, T: int = 300):
    """The linear plant's noise-free record under a known input plus ``bias_u``, seen
    through ``y = x1 + bias_y``: (Y, U), ``U[k]`` acting from sample k to k+1."""
    U = np.sin(0.05 * np.arange(T))[:, None]
    x, Y = np.zeros(2), []
    for k in range(T):
        if k:
            x = A @ x + B @ (U[k - 1] + bias_u)
        Y.append([x[0] + bias_y])
    return np.array(Y), U


def linear(ny: int = 1) -> estim.Model:
    return estim.Model(states=["x1", "x2"], inputs=["u"], outputs=["y", "y2"][:ny],
                       dynamics=lambda x, u, p: A @ x + B @ u,
                       output=lambda x, u, p: x[:ny])


def output_errors(model, log, U):
    xh = np.asarray(log.x_hat)
    return np.array([np.asarray(model.H(xh[k], U[k], model.p)).ravel()
                     for k in range(len(xh))])


@pytest.mark.parametrize("where", ["input", "output"])
def test_integrating_disturbance_removes_the_offset(where):
    """A constant unmeasured input load (or sensor bias): the EKF on the model is biased
    at steady state, the EKF on the model with an integrating disturbance follows the
    output to rounding and estimates the disturbance itself."""
    kw = {"bias_u": 0.3} if where == "input" else {"bias_y": 0.2}
    Y, U = plant(**kw)
    m = linear()
    aug = m.with_disturbances(**({"inputs": ["u"]} if where == "input" else {"outputs": ["y"]}))
    assert aug.state_names == ["x1", "x2", "d_u" if where == "input" else "d_y"]
    plain = estim.replay(estim.EKF(m, Q=1e-4, R=1e-2, x0=np.zeros(2), P0=1.0), Y, U)
    log = estim.replay(estim.EKF(aug, Q=[1e-4, 1e-4, 1e-3], R=1e-2, x0=np.zeros(3), P0=1.0),
                       Y, U)
    e_plain = Y[-50:, 0] - np.asarray(plain.x_hat)[-50:, 0]
    e_aug = (Y - output_errors(aug, log, U))[-50:, 0]
    assert np.abs(e_plain).max() > 0.1
    assert np.abs(e_aug).max() <= 1e-8
    np.testing.assert_allclose(np.asarray(log.x_hat)[-1, 2], 0.3 if where == "input" else 0.2,
                               atol=1e-8)


def test_reactor_feed_disturbance():
    """The semi-batch reactor fed an unknown extra 0.01: the EKF on the reactor model
    keeps an offset of 0.44 in the pressure; with the disturbance on ``feed`` it is
    gone (noise-free record) and ``d_feed`` is the extra feed."""
    r = estim.models.batch_reactor(feed=True)
    x, Y = np.array([0.5, 0.05, 0.0]), []
    for k in range(400):
        if k:
            x = np.asarray(r.F(x, [0.01], r.p)).ravel()
        Y.append([32.84 * x.sum()])
    Y, U = np.array(Y), np.zeros((400, 1))
    aug = r.with_disturbances(inputs=["feed"], at=([0.5, 0.05, 0.0], [0.0]))
    out = {}
    for name, model, Q in (("plain", r, 1e-6), ("augmented", aug, 1e-6)):
        x0 = np.r_[[0.5, 0.05, 0.0], np.zeros(model.nx - 3)]
        log = estim.replay(estim.EKF(model, Q=Q, R=0.25**2, x0=x0, P0=0.01), Y, U)
        out[name] = (Y - output_errors(model, log, U))[-50:, 0], np.asarray(log.x_hat)[-1]
    assert np.abs(out["plain"][0]).max() > 0.1
    assert np.abs(out["augmented"][0]).max() <= 1e-8
    assert out["augmented"][1][3] == pytest.approx(0.01, abs=1e-6)


def test_scenario_estimates_the_disturbance():
    """``reactor_feed``: from ``d_feed = 0`` the EKF's estimate of the extra feed settles
    around the truth (0.01) within the standard deviation it reports (about 0.0036:
    the disturbance's random walk keeps it from shrinking)."""
    sc = estim.scenarios.get("reactor_feed", n_steps=200)
    assert sc.model.state_names[-1] == "d_feed" and "reactor_feed" in estim.scenarios.SCENARIOS
    means = []
    for seed in range(3):
        log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed)
        d, P = np.asarray(log.x_hat)[100:, 3], np.asarray(log.P)[100:, 3, 3]
        assert np.abs((d - 0.01) / np.sqrt(P)).max() < 3.5
        means.append(d.mean())
    assert abs(np.mean(means) - 0.01) < 0.0036


def test_equations_of_the_augmented_model():
    m = linear(2)
    aug = m.with_disturbances(inputs=["u"], outputs=["y2"])
    x, u = np.array([0.3, -0.2]), np.array([0.7])
    z = np.r_[x, 0.1, 0.05]
    np.testing.assert_allclose(aug.f(z, u)[:2], A @ x + B @ (u + 0.1), atol=1e-15)
    np.testing.assert_allclose(aug.f(z, u)[2:], [0.1, 0.05])
    np.testing.assert_allclose(np.asarray(aug.H(z, u, aug.p)).ravel(), [0.3, -0.15])
    assert aug.disturbances == {"inputs": {"u": "d_u"}, "outputs": {"y2": "d_y2"},
                                "kind": "integrating"}
    same = estim.Model(states=["x1", "x2"], inputs=["y"], outputs=["y"],
                       dynamics=lambda x, u, p: A @ x + B @ u, output=lambda x, u, p: x[0])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # two disturbances, one output
        both = same.with_disturbances(inputs=["y"], outputs=["y"], check=False)
    assert both.state_names[2:] == ["d_u_y", "d_y_y"]


def test_undetectable_disturbances_are_refused_by_name():
    """More disturbances than outputs, and the classic case: an output disturbance on
    an integrating plant (a constant bias and a constant position look alike)."""
    with pytest.raises(ValueError, match=r"2 disturbances \['d_u', 'd_y'\] but 1 output"):
        linear().with_disturbances(inputs=["u"], outputs=["y"])
    integ = estim.Model(states=["p", "v"], inputs=["u"], outputs=["y"],
                        dynamics=lambda x, u, p: np.array([[1.0, 0.1], [0.0, 1.0]]) @ x
                        + B @ u, output=lambda x, u, p: x[0])
    with pytest.raises(ValueError, match=r"disturbances \['d_y'\] are not detectable: "
                                         r"rank .* = 2 < n_x \+ n_d = 3"):
        integ.with_disturbances(outputs=["y"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        kept = integ.with_disturbances(outputs=["y"], check=False)
    assert kept.nx == 3 and "not detectable" in str(caught[0].message)
    assert integ.with_disturbances(inputs=["u"]).nx == 3  # an input load is detectable


@pytest.mark.parametrize("kwargs, error, match", [
    ({"inputs": ["q"]}, ValueError, r"inputs: 'q' is not an input"),
    ({"outputs": ["z"]}, ValueError, r"outputs: 'z' is not an output"),
    ({}, ValueError, "at least one input or output"),
    ({"inputs": ["u", "u"]}, ValueError, "twice"),
    ({"inputs": [1]}, TypeError, "inputs must be a list"),
    ({"inputs": ["u"], "kind": "step"}, ValueError, "kind"),
    ({"inputs": ["u"], "at": (1.0, 2.0)}, ValueError, r"at\[0\]"),
    ({"inputs": ["u"], "at": [0.0]}, TypeError, "at must be a pair"),
    ({"inputs": ["u"], "check": "yes"}, TypeError, "check"),
])
def test_bad_input(kwargs, error, match):
    with pytest.raises(error, match=match):
        linear().with_disturbances(**kwargs)
