"""Observability rank condition, symmetries and classification on PyNOA's and seed examples."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim
from estim.models.localization import martinelli_simple, odometry_circular, odometry_noncircular
from estim.observability import analyze, window


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


def _in_null_space(rep, v):
    Q, _ = np.linalg.qr(rep.symmetries.T)
    v = v / np.linalg.norm(v)
    return np.linalg.norm(v - Q @ (Q.T @ v))


def test_quadrotor_parameters_have_two_scale_symmetries():
    """Ko 2019 with IMU, GNSS and barometer (33 states): rank 31, not 33 as PyNOA
    prints. IMU specific force and dynamics are unchanged by scaling (m, lambda, k_f,
    I, k_m) together, and by scaling (I, d, k_m) together; these span the null space.
    (PyNOA holds the rotor speeds in h at constant values while differentiating along
    the input fields, which adds rows that do not belong to the system.)"""
    m = estim.models.quadrotor_ko2019("imu_gnss_baro")
    x = np.random.default_rng(3).uniform(0.5, 2.0, m.nx)
    rep = analyze(m, order=2, at=x)
    assert rep.rank == 31 and rep.gap > 1e8

    def direction(names):
        v = np.zeros(m.nx)
        for n in names:
            v[m.state_names.index(n)] = x[m.state_names.index(n)]
        return v

    mass = direction(["m", "lambda_l", "k_f1", "k_f2", "k_f3", "k_f4", "i_xx", "i_yy", "i_zz",
                      "k_m1", "k_m2", "k_m3", "k_m4"])
    inertia = direction(["i_xx", "i_yy", "i_zz", "d_12", "d_23", "d_34", "d_14",
                         "k_m1", "k_m2", "k_m3", "k_m4"])
    assert _in_null_space(rep, mass) < 1e-8 and _in_null_space(rep, inertia) < 1e-8
    assert {"r_x", "r_y", "r_z", "v_x", "q_w", "w_x", "g_z"} <= set(rep.observable)


def test_quadrotor_navigation_yaw_is_unobservable():
    """IMU and barometer, parameters known (13 states): horizontal position and the
    rotation of the world about gravity (yaw) are symmetries: rank 10 (PyNOA: 11)."""
    m = estim.models.quadrotor_ko2019("imu_baro")
    x = np.random.default_rng(4).uniform(-1.0, 1.0, 13)
    rep = analyze(m, order=2, at=x)
    assert rep.rank == 10 and rep.unobservable == ["r_x", "r_y"]
    r, v, q = x[0:3], x[3:6], x[6:10]
    yaw = np.concatenate([[-r[1], r[0], 0], [-v[1], v[0], 0],
                          0.5 * np.array([-q[3], -q[2], q[1], q[0]]), np.zeros(3)])
    assert _in_null_space(rep, yaw) < 1e-8


def test_the_matrix_and_its_conditioning_against_closed_forms(tmp_path):
    """The observability matrix at given states. The pendulum seen through sin(theta):
    grad h = (cos th, 0) and grad L_f h = (-w sin th, cos th) in closed form, grad L_f^2 h
    by central differences of the closed-form L_f^2 h. The constant-velocity target
    (discrete): H, H A, H A^2. The conditioning map finds the pendulum's two singular
    points, theta = +-pi/2 with omega = 0."""
    from estim.observability import conditioning, matrix

    m = estim.models.sine_pendulum(g=9.81, dt=0.01, integrator="euler")
    X = np.random.default_rng(3).uniform(-3, 3, size=(7, 2))
    obs = matrix(m, X, 1)
    th, om = X[:, 0], X[:, 1]
    exact = np.stack([np.stack([np.cos(th), 0 * th], 1),
                      np.stack([-om * np.sin(th), np.cos(th)], 1)], 1)
    np.testing.assert_allclose(obs, exact, rtol=0, atol=1e-12)

    def lf2(x):  # L_f^2 h = d/dt (w cos th) = -w^2 sin th - g sin th cos th
        return -x[1] ** 2 * np.sin(x[0]) - 9.81 * np.sin(x[0]) * np.cos(x[0])
    eps = 1e-6
    for x, row in zip(X, matrix(m, X, 2)[:, 2], strict=True):
        fd = [(lf2(x + eps * e) - lf2(x - eps * e)) / (2 * eps) for e in np.eye(2)]
        np.testing.assert_allclose(row, fd, rtol=1e-6, atol=1e-6)
    cv = estim.models.constant_velocity(dt=0.1)
    A = np.block([[np.eye(2), 0.1 * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    H = np.eye(2, 4)
    np.testing.assert_allclose(matrix(cv, np.ones(4), 2), np.vstack([H, H @ A, H @ A @ A]),
                               rtol=0, atol=1e-14)
    c = conditioning(m, {"theta": np.linspace(-np.pi, np.pi, 61),
                         "omega": np.linspace(-4, 4, 41)}, 2)
    B, A_ = np.nonzero(c.rank < 2)
    np.testing.assert_allclose(np.sort(c.grid[0][A_]), [-np.pi / 2, np.pi / 2], atol=1e-12)
    np.testing.assert_allclose(c.grid[1][B], 0.0, atol=1e-12)
    assert c.values.shape == (41, 61) and c.values[B, A_].max() == 0.0
    assert np.all((c.values >= 0) & (c.values <= 1))
    pytest.importorskip("matplotlib")
    c.plot(tmp_path / "map.png")
    assert (tmp_path / "map.png").stat().st_size > 0
    with pytest.raises(ValueError, match="'phi' is not a state"):
        conditioning(m, {"theta": [0, 1], "phi": [0, 1]}, 2)
    with pytest.raises(ValueError, match=r"x must have shape \(2,\) or \(m, 2\)"):
        matrix(m, np.zeros(3), 1)
