"""Observability rank condition, symmetries and classification on PyNOA's and seed examples."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim
from estim.observability import analyze, window


def martinelli_simple():
    """Martinelli 2010, simple localisation: (D, phi_R, theta_R), inputs (v, omega)."""
    return estim.Model(
        states=["D", "phi_R", "theta_R"], outputs=["beta"], inputs=["v", "omega"],
        ode=lambda x, u, p: ca.vertcat(u[0] * ca.cos(x[2] - x[1]),
                                       u[0] * ca.sin(x[2] - x[1]) / x[0], u[1]),
        output=lambda x, u, p: ca.pi - x[2] + x[1], dt=0.1,
        lower=[0.5, -np.inf, -np.inf], upper=[5.0, np.inf, np.inf], name="martinelli_simple")


@pytest.mark.parametrize("method", ["numeric", "symbolic"])
@pytest.mark.parametrize("arrangement", [None, "combination", "permutation", "drift2ndOrder"])
def test_martinelli_simple_localisation(method, arrangement):
    rep = analyze(martinelli_simple(), method=method, arrangement=arrangement,
                  order=None if arrangement is None else 2)
    assert rep.rank == 2 and rep.n == 3 and not rep.is_observable
    assert rep.observable == ["D"]
    assert rep.jointly_observable == [["phi_R", "theta_R"]]
    assert rep.unobservable == []
    np.testing.assert_allclose(rep.symmetries, [[0.0, 1.0, 1.0]], atol=1e-9)
    assert rep.gap > 1e10
    assert "jointly observable: (phi_R, theta_R)" in str(rep)


def odometry_noncircular():
    """Martinelli 2010 odometry calibration (PyNOA notebook), wheel speeds as inputs."""
    def ode(x, u, p):
        mu, g, phi, psi, eta, delta, xi = (x[i] for i in range(7))
        f1 = ca.vertcat(-mu**2 * eta * ca.cos(g - phi), xi - mu * eta * ca.sin(g - phi),
                        0, 0, 0, 0, 0)
        f2 = ca.vertcat(-mu**2 * eta * delta * ca.cos(g - phi),
                        -xi * delta - mu * eta * delta * ca.sin(g - phi), 0, 0, 0, 0, 0)
        return f1 * u[0] + f2 * u[1]

    return estim.Model(
        states=["mu", "gamma", "phi", "psi", "eta", "delta", "xi"], outputs=["beta"],
        inputs=["omega_R", "omega_L"], ode=ode, dt=0.1, name="odometry_noncircular",
        output=lambda x, u, p: -ca.atan2(ca.sin(x[1]), x[0] + ca.cos(x[1])) - x[3],
        lower=[0.2, -np.inf, -np.inf, -np.inf, 0.2, 0.2, 0.2], upper=[3, np.inf, np.inf,
                                                                       np.inf, 3, 3, 3])


def odometry_circular():
    """The same robot on a circular trajectory (PyNOA notebook's 5-state model)."""
    def ode(x, u, p):
        mu, g, eta, xi, phi = (x[i] for i in range(5))
        return ca.vertcat(-mu**2 * eta * ca.cos(g - phi), xi - mu * eta * ca.sin(g - phi),
                          0, 0, 0) * u[0]

    return estim.Model(
        states=["mu", "gamma", "eta_q", "xi_q", "phi"], outputs=["y"], inputs=["nu"], ode=ode,
        output=lambda x, u, p: ca.sin(x[1]) / (x[0] + ca.cos(x[1])), dt=0.1,
        lower=[0.2, -np.inf, 0.2, 0.2, -np.inf], upper=[3, np.inf, 3, 3, np.inf],
        name="odometry_circular")


def test_odometry_calibration_noncircular_is_observable():
    rep = analyze(odometry_noncircular())
    assert rep.rank == 7 and rep.is_observable and not rep.point_dependent


def test_odometry_calibration_circular_has_martinelli_symmetry():
    """Rank 4 of 5 (PyNOA prints 5 with floating-point primes), only xi_q observable,
    and the null space is Martinelli's symmetry
    [mu cos g + 1, sin g, (xi_q sin phi - eta_q) / mu, 0, xi_q cos phi / (eta_q mu)]."""
    x = np.array([1.3, 0.7, 1.1, 0.8, -0.4])
    rep = analyze(odometry_circular(), at=x)
    assert rep.rank == 4 and rep.observable == ["xi_q"] and rep.gap > 1e10
    assert rep.jointly_observable == [["mu", "gamma", "eta_q", "phi"]]
    mu, g, eta, xi, phi = x
    v = np.array([mu * np.cos(g) + 1, np.sin(g), (xi * np.sin(phi) - eta) / mu, 0,
                  xi * np.cos(phi) / (eta * mu)])
    np.testing.assert_allclose(rep.symmetries[0], v / v[0], atol=1e-8)


def test_lorenz_with_x3_is_locally_weakly_observable_only():
    """The rank test passes; the report says it cannot see (x1, x2) -> (-x1, -x2)."""
    m = estim.Model(states=3, outputs=1, dt=0.02, name="lorenz_x3",
                    ode=lambda x, u, p: ca.vertcat(10 * (x[1] - x[0]), x[0] * (28 - x[2]) - x[1],
                                                   x[0] * x[1] - 8 / 3 * x[2]),
                    output=lambda x, u, p: x[2])
    rep = analyze(m)
    assert rep.rank == 3 and rep.is_observable and rep.order == 2
    assert any("discrete symmetries" in n for n in rep.notes)
    # the discrete symmetry is real: the output is unchanged under (x1, x2) -> (-x1, -x2)
    x = np.array([1.0, -2.0, 20.0])
    xm = np.array([-1.0, 2.0, 20.0])
    for _ in range(50):
        x = x + 0.01 * np.array([10 * (x[1] - x[0]), x[0] * (28 - x[2]) - x[1],
                                 x[0] * x[1] - 8 / 3 * x[2]])
        xm = xm + 0.01 * np.array([10 * (xm[1] - xm[0]), xm[0] * (28 - xm[2]) - xm[1],
                                   xm[0] * xm[1] - 8 / 3 * xm[2]])
        assert x[2] == pytest.approx(xm[2], abs=1e-9)


def test_satellite_scale_symmetry_without_torque_only():
    """omega measured, inertias unknown: with zero torque I -> cI is a symmetry
    (gravity gradient included); a known varying torque removes it."""
    sat = estim.models.satellite_rates().augment("I1", "I2", "I3", lower=0.1, upper=1.0)
    at = np.array([0.02, -0.015, 0.01, 0.5, 0.4, 0.26])
    rep = analyze(sat, inputs={"tau_x": 0.0, "tau_y": 0.0, "tau_z": 0.0}, at=at)
    assert rep.rank == 5
    assert rep.observable == ["wx", "wy", "wz"]
    assert rep.jointly_observable == [["I1", "I2", "I3"]]
    np.testing.assert_allclose(rep.symmetries[0], [0, 0, 0, 1.0, 0.8, 0.52], atol=1e-8)
    assert analyze(sat, at=at).rank == 6


def test_unobservable_state_is_classified():
    """A state that enters neither the output nor the others' dynamics."""
    m = estim.Model(states=["a", "b", "c"], outputs=1, dt=0.1,
                    ode=lambda x, u, p: ca.vertcat(x[1], -x[0], -x[2]),
                    output=lambda x, u, p: x[0])
    rep = analyze(m)
    assert rep.rank == 2 and rep.unobservable == ["c"] and rep.observable == ["a", "b"]


def test_discrete_model_and_window_sensitivity():
    """A discrete rotation observed through one coordinate is observable in two samples;
    the window's Fisher information gives the Cramer-Rao bound."""
    c, s = np.cos(0.3), np.sin(0.3)
    m = estim.Model(states=2, outputs=1, dynamics=lambda x, u, p: ca.vertcat(
        c * x[0] - s * x[1], s * x[0] + c * x[1]), output=lambda x, u, p: x[0])
    rep = analyze(m)
    assert rep.rank == 2 and rep.order == 1
    w = window(m, [1.0, 0.0], n_steps=4, R=0.01)
    S = np.array([[np.cos(0.3 * k), -np.sin(0.3 * k)] for k in range(5)]) / 0.1
    np.testing.assert_allclose(w.sensitivity, S, atol=1e-12)
    np.testing.assert_allclose(w.crb_std, np.sqrt(np.diag(np.linalg.inv(S.T @ S))), rtol=1e-12)
    assert w.rank == 2


def test_bad_input():
    m = martinelli_simple()
    with pytest.raises(ValueError, match="inputs must be"):
        analyze(m, inputs="random")
    with pytest.raises(ValueError, match="method must be"):
        analyze(m, method="exact")
    with pytest.raises(ValueError, match="arrangement must be one of"):
        analyze(m, arrangement="all")
    with pytest.raises(ValueError, match="unknown inputs"):
        analyze(m, inputs={"thrust": 0.0})
    with pytest.raises(ValueError, match="order must be"):
        analyze(m, order=-1)
    with pytest.raises(TypeError, match="model must be an estim.Model"):
        analyze("robot")
