"""Inputs between samples: hold="foh" integrates with the input linear between samples,
in the model, the simulation and every estimator."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import estim

W, ZETA, B, DT = 7.0, 0.1, 3.0, 0.05


def oscillator(hold="foh", integrator="rk4", substeps=1, inputs=("u",), **kw):
    """A lightly damped oscillator driven by ``u`` (and ``v``, a constant offset)."""
    def ode(x, u, p):
        force = B * u[0] + (u[1] if u.numel() > 1 else 0)
        return ca.vertcat(x[1], -W**2 * x[0] - 2 * ZETA * W * x[1] + force)

    return estim.Model(states=["q", "v"], outputs=["q"], inputs=list(inputs), ode=ode,
                       output=lambda x, u, p: x[0], dt=DT, hold=hold, integrator=integrator,
                       substeps=substeps, **kw)


def exact(x0, u0, u1, ramp=(1.0,)):
    """solve_ivp with the input linear from u0 to u1 over one sample (1e-12)."""
    u0, u1, ramp = (np.atleast_1d(np.asarray(a, float)) for a in (u0, u1, ramp))

    def rhs(t, x):
        u = u0 + ramp * (t / DT) * (u1 - u0)
        force = B * u[0] + (u[1] if len(u) > 1 else 0)
        return [x[1], -W**2 * x[0] - 2 * ZETA * W * x[1] + force]

    return solve_ivp(rhs, (0, DT), x0, method="DOP853", rtol=1e-13, atol=1e-14).y[:, -1]


@pytest.mark.parametrize("integrator, substeps, tol", [("rk4", 128, 1e-11), ("cvodes", 1, 1e-8)])
def test_a_first_order_hold_integrates_the_interpolated_input(integrator, substeps, tol):
    m = oscillator(integrator=integrator, substeps=substeps)
    assert m.sampled and m.nw == 2
    rng = np.random.default_rng(0)
    for _ in range(5):
        x0, (u0, u1) = rng.standard_normal(2), rng.standard_normal(2)
        np.testing.assert_allclose(m.f(x0, [u0], [u1]), exact(x0, u0, u1), rtol=0, atol=tol)
    # RK4 is fourth order over the sample: doubling the substeps divides the error by 16
    # (an error in the interpolation would leave a first-order term)
    x0 = np.array([0.3, -1.0])
    err = [np.abs(oscillator(substeps=s).f(x0, [1.0], [-2.0]) - exact(x0, 1.0, -2.0)).max()
           for s in (4, 8)]
    assert 13 < err[0] / err[1] < 19
    # held input: the zero-order hold's map
    np.testing.assert_allclose(m.f(x0, [0.7]), oscillator(hold="zoh", integrator=integrator,
                                                          substeps=substeps).f(x0, [0.7]),
                               atol=tol)


def test_a_hold_per_input():
    m = oscillator(hold={"u": "foh", "v": "zoh"}, substeps=16, inputs=("u", "v"))
    x0 = np.array([0.1, 0.2])
    got = m.f(x0, [1.0, 0.5], [-1.0, 3.0])  # v held at its value at the start, 0.5
    np.testing.assert_allclose(got, exact(x0, [1.0, 0.5], [-1.0, 3.0], ramp=(1.0, 0.0)),
                               atol=1e-11)
    with pytest.raises(ValueError, match="hold names unknown inputs"):
        oscillator(hold={"w": "foh"})
    with pytest.raises(ValueError, match="hold must be one of"):
        oscillator(hold="linear")
    with pytest.raises(ValueError, match="needs a continuous model"):
        estim.Model(states=1, outputs=1, inputs=1, dynamics=lambda x, u, p: x + u,
                    output=lambda x, u, p: x, hold="foh")


def test_simulate_moves_the_plant_with_the_ramp():
    m = oscillator()
    T = 40
    U = np.sin(np.arange(T) * 0.3)[:, None]
    log = estim.simulate(m, estim.EKF(m, Q=1e-4, R=1e-2, x0=[0, 0], P0=1.0), x0=[0.2, 0.0],
                         n_steps=T, Q=0.0, R=1e-2, inputs=U, seed=0)
    x = np.array([0.2, 0.0])
    for k in range(T - 1):
        np.testing.assert_allclose(log.x[k], x, atol=1e-12)
        x = m.f(x, U[k], U[k + 1])
    with pytest.raises(ValueError, match="needs them in advance"):
        estim.simulate(m, estim.EKF(m, Q=1e-4, R=1e-2, x0=[0, 0], P0=1.0), x0=[0, 0],
                       n_steps=5, Q=0.0, R=1e-2, controller=lambda t, x: [0.0])


def _discrete_twin(m):
    """The same transitions written by hand as a discrete map with the inputs of both
    ends ((u_k, u_{k+1}) as two held inputs): the workaround before hold="foh"."""
    F = m.F
    return estim.Model(states=m.state_names, outputs=m.output_names, inputs=["u0", "u1"],
                       dynamics=lambda x, w, p: F(x, w, m.p), output=lambda x, w, p: x[0],
                       dt=m.dt)


MAKERS = {
    "ekf": lambda m: estim.EKF(m, Q=1e-4, R=1e-2, x0=[0.0, 0.0], P0=1.0),
    "ukf": lambda m: estim.UKF(m, Q=1e-4, R=1e-2, x0=[0.0, 0.0], P0=1.0),
    "mhe": lambda m: estim.MHE(m, horizon=6, solver="gauss-newton", Q=1e-4, R=1e-2,
                               x0=[0.0, 0.0], P0=1.0),
    "mhe ipopt": lambda m: estim.MHE(m, horizon=6, solver="ipopt", Q=1e-4, R=1e-2,
                                     x0=[0.0, 0.0], P0=1.0),
    "fie": lambda m: estim.FullInformation(m, Q=1e-4, R=1e-2, x0=[0.0, 0.0], P0=1.0),
    "shooting": lambda m: estim.ShootingObserver(m, window=5, every=2, R=1e-2, x0=[0.0, 0.0],
                                                 derivative_weight=0.0, method="lbfgsb"),
}


@pytest.mark.parametrize("name", list(MAKERS))
def test_every_estimator_sees_the_ramp(name):
    """Each estimator on the hold="foh" model, given the inputs at the samples, equals the
    same estimator on the hand-written twin given the pairs of inputs."""
    m = oscillator()
    twin = _discrete_twin(m)
    T = 30
    U = np.cos(np.arange(T) * 0.4)[:, None]
    truth = estim.simulate(m, MAKERS["ekf"](m), x0=[0.3, 0.0], n_steps=T, Q=1e-6, R=1e-2,
                           inputs=U, seed=1)
    pairs = np.hstack([U, np.vstack([U[1:], U[-1:]])])  # pairs[k] acts from k to k+1
    foh = estim.replay(MAKERS[name](m), truth.y, U)
    ref = estim.replay(MAKERS[name](twin), truth.y, pairs)
    np.testing.assert_allclose(foh.x_hat, ref.x_hat, rtol=0, atol=1e-9)
    if name == "fie":
        fit = MAKERS[name](m).fit(truth.y, U)
        np.testing.assert_allclose(fit.x, MAKERS[name](twin).fit(truth.y, pairs[:-1]).x,
                                   atol=1e-9)
        with pytest.raises(ValueError, match=r"U must have shape \(30, 1\), the input at each"):
            MAKERS[name](m).fit(truth.y, U[:-1])


def test_the_shooting_observer_keeps_its_derivative_term_and_backward_mode():
    m = oscillator()
    T = 60
    U = np.sin(np.arange(T) * 0.25)[:, None]
    truth = estim.simulate(m, MAKERS["ekf"](m), x0=[0.5, 0.0], n_steps=T, Q=0.0, R=1e-4,
                           inputs=U, seed=2)
    held = oscillator(hold="zoh")  # the same equations, the input held instead
    for direction in ("forward", "backward"):
        rms = {}
        for name, model, inputs in (("foh", m, U), ("zoh", held, np.vstack([U[1:], U[-1:]]))):
            obs = estim.ShootingObserver(model, window=6, every=3, R=1e-4, x0=[0.0, 0.0],
                                         direction=direction)
            log = estim.replay(obs, truth.y, inputs, truth.x)
            rms[name] = np.sqrt(np.mean((log.x_hat[-30:] - truth.x[-30:]) ** 2))
            assert any(h["derivative_weight"] > 0 for h in obs.history)
        assert rms["foh"] < 0.5 * rms["zoh"], rms  # measured 0.019 against 0.050
