"""The five benchmark models against references nobody here wrote.

References: the equations of ``/work/shared/models.md`` re-typed below in plain
numpy (not through ``estim``), SciPy's DOP853 at tight tolerances for the exact
flow, closed forms (equilibria, gravity-gradient offset, linear tracking
error), conservation laws and the scale symmetry of Euler's equations.
Every tolerance is derived in the comment next to it; the numbers measured
when the file was written are quoted as "measured".
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import fsolve
from scipy.signal import find_peaks
from scipy.spatial.transform import Rotation

from estim.models import (
    PDAttitudeController,
    batch_reactor,
    lorenz,
    reference_attitude,
    runaway,
    satellite,
    van_der_pol,
)

TIGHT = {"method": "DOP853", "rtol": 1e-12, "atol": 1e-12}
MU_EARTH = 3.986004418e14
R_ORBIT = 7.0e6
EPS = np.finfo(float).eps


# --------------------------------------------------------------------------------------
# Independent right-hand sides, typed from models.md (column-wise: x may be (n,) or (n, N)).
# --------------------------------------------------------------------------------------
def vdp_rhs(x, u=None, mu=1.0):
    x1, x2 = x
    return np.array([x2, mu * (1 - x1**2) * x2 - x1])


def reactor_rhs(x, u=None, k1=0.5, km1=0.05, k2=0.2, km2=0.01):
    ca_, cb, cc = x
    r1 = k1 * ca_ - km1 * cb * cc
    r2 = k2 * cb**2 - km2 * cc
    return np.array([-r1, r1 - 2 * r2, r1 + r2])


def runaway_rhs(x, u=None, gamma=0.5, gamma1=2.5, nu=0.5, source=1.0, S=0.0, W_t=0.1,
                eps=50.0):
    x1, x2 = x
    return np.array([eps * (-2 * x1 * x2 - 2 * S + source),
                     eps * (-nu * x2 + gamma * (x1 * x2 + S) - gamma1 * x2 / (1 + x2 / W_t))])


def lorenz_rhs(x, u=None, sigma=10.0, rho=28.0, beta=8.0 / 3.0):
    x1, x2, x3 = x
    return np.array([sigma * (x2 - x1), x1 * (rho - x3) - x2, x1 * x2 - beta * x3])


def rotation(q):
    """Body-to-inertial rotation matrix of a unit quaternion (scalar first, Shuster 1993)."""
    q0, v = q[0], np.asarray(q[1:4])
    skew = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return (q0**2 - v @ v) * np.eye(3) + 2 * np.outer(v, v) + 2 * q0 * skew


def omega_matrix(w):
    """``Omega(w)`` with ``q' = 0.5 Omega(w) q`` for body rates ``w``."""
    wx, wy, wz = w
    return np.array([[0, -wx, -wy, -wz],
                     [wx, 0, wz, -wy],
                     [wy, -wz, 0, wx],
                     [wz, wy, -wx, 0]])


def satellite_rhs(x, u=None, inertia=(0.50, 0.40, 0.26), mu=MU_EARTH, r=R_ORBIT):
    q, w, theta = x[0:4], x[4:7], x[7]
    inertia = np.asarray(inertia)
    tau = np.zeros(3) if u is None else np.asarray(u)
    n2 = mu / r**3
    n_b = rotation(q).T @ np.array([-np.cos(theta), -np.sin(theta), 0.0])
    w_dot = (-np.cross(w, inertia * w) + 3 * n2 * np.cross(n_b, inertia * n_b) + tau) / inertia
    return np.concatenate([0.5 * omega_matrix(w) @ q, w_dot, [np.sqrt(n2)]])


def flow(rhs, x, u, dt, **tol):
    """The exact one-sample map, by DOP853 at tight tolerances."""
    sol = solve_ivp(lambda t, z: rhs(z, u), (0.0, dt), np.asarray(x, float), **(tol or TIGHT))
    assert sol.success
    return sol.y[:, -1]


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@lru_cache(maxsize=1)
def runaway_orbit():
    """``runaway().f`` from (0, 0.001) for 3 s (6000 samples): times, states, burst indices."""
    model = runaway()
    X = np.empty((6001, 2))
    X[0] = (0.0, 1e-3)
    for k in range(6000):
        X[k + 1] = model.f(X[k])
    t = np.arange(6001) * model.dt
    peaks, _ = find_peaks(X[:, 1], height=0.5)
    return t, X, peaks


def runaway_point(phase):
    """A state on the limit cycle: at the 2nd burst peak, or half a period later (quiet)."""
    _, X, peaks = runaway_orbit()
    if phase == "burst":
        return X[peaks[1]]
    return X[(peaks[1] + peaks[2]) // 2]


SAT_X = np.concatenate([unit([0.9, 0.1, -0.3, 0.2]), [0.1, -0.08, 0.12], [0.7]])
SAT_U = np.array([2e-3, -3e-3, 1e-3])  # PD torques in the experiment stay below 3.1e-3 N m


def continuous_case(name):
    """(factory, factory kwargs, x, u, numpy rhs, experiment noise std from models.md)."""
    if name == "van_der_pol":
        return van_der_pol, {}, np.array([1.5, 1.5]), None, vdp_rhs, 0.1
    if name == "batch_reactor":
        return batch_reactor, {}, np.array([0.5, 0.05, 0.0]), None, reactor_rhs, 0.002
    if name.startswith("runaway"):
        # no process noise in the experiment: measurement noise 1e-4
        return runaway, {}, runaway_point(name.split("-")[1]), None, runaway_rhs, 1e-4
    if name == "satellite":
        # no process noise given: gyro noise 1e-3 rad/s
        return satellite, {}, SAT_X, SAT_U, satellite_rhs, 1e-3
    if name == "lorenz_rk4":
        return lorenz, {"integrator": "rk4"}, np.array([-10.0, -12.0, 27.0]), None, lorenz_rhs, 0.02
    raise KeyError(name)


CONTINUOUS = ["van_der_pol", "batch_reactor", "runaway-burst", "runaway-quiet", "satellite",
              "lorenz_rk4"]


# --------------------------------------------------------------------------------------
# The equations themselves
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("factory", "kwargs", "rhs", "rhs_kwargs", "nu", "lo", "hi"),
    [
        (van_der_pol, {}, vdp_rhs, {}, 0, -3, 3),
        (van_der_pol, {"mu": 2.5}, vdp_rhs, {"mu": 2.5}, 0, -3, 3),
        (batch_reactor, {}, reactor_rhs, {}, 0, 0, 2),
        (batch_reactor, {"k1": 0.6, "km2": 0.03}, reactor_rhs, {"k1": 0.6, "km2": 0.03}, 0, 0, 2),
        (runaway, {}, runaway_rhs, {}, 0, 0, 3),
        (runaway, {"gamma": 0.6, "W_t": 0.2, "S": 0.01}, runaway_rhs,
         {"gamma": 0.6, "W_t": 0.2, "S": 0.01}, 0, 0, 3),
        (lorenz, {}, lorenz_rhs, {}, 0, -20, 40),
        (lorenz, {"rho": 20.0, "beta": 2.0}, lorenz_rhs, {"rho": 20.0, "beta": 2.0}, 0, -20, 40),
        (satellite, {}, satellite_rhs, {}, 3, -1, 1),
        (satellite, {"I1": 0.6, "r": 6.8e6}, satellite_rhs,
         {"inertia": (0.6, 0.4, 0.26), "r": 6.8e6}, 3, -1, 1),
    ],
)
def test_rhs_is_the_documented_equation(factory, kwargs, rhs, rhs_kwargs, nu, lo, hi):
    """``model.f_c`` is the models.md right-hand side, with factory parameters honoured."""
    model = factory(**kwargs)
    rng = np.random.default_rng(0)
    for _ in range(20):
        x = rng.uniform(lo, hi, model.nx)
        if model.name == "satellite":
            x[:4] = unit(x[:4])
        u = rng.uniform(-1e-2, 1e-2, nu)
        expected = rhs(x, u, **rhs_kwargs)
        got = model.f_c(x, u, model.p).full().ravel()
        # same arithmetic in another order: a few ulps of the largest term
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def test_outputs_are_the_documented_ones():
    rng = np.random.default_rng(1)
    x2, x3 = rng.uniform(0, 2, 2), rng.uniform(0, 2, 3)
    np.testing.assert_array_equal(van_der_pol().h(x2), x2)
    assert batch_reactor().h(x3)[0] == pytest.approx(32.84 * x3.sum(), rel=1e-14)
    assert batch_reactor(gain=32.83).h(x3)[0] == pytest.approx(32.83 * x3.sum(), rel=1e-14)
    assert runaway().h(x2)[0] == x2[1]
    xs = np.concatenate([unit(rng.standard_normal(4)), rng.standard_normal(3), [0.4]])
    np.testing.assert_array_equal(satellite().h(xs, SAT_U), xs[4:7])
    assert (van_der_pol().dt, batch_reactor().dt, runaway().dt, satellite().dt, lorenz().dt) \
        == (0.1, 0.25, 5e-4, 1.0, 0.02)
    np.testing.assert_array_equal(batch_reactor().lower, 0.0)
    np.testing.assert_array_equal(runaway().lower, 0.0)


# --------------------------------------------------------------------------------------
# 1. One RK4 sample against the exact flow
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", CONTINUOUS)
def test_rk4_step_matches_exact_flow_to_local_error(name):
    """``model.f`` is one RK4 step: its error against DOP853 is the RK4 local error.

    Three checks.  (i) Halving dt divides the error by ~2^5 = 32 (local error
    C h^5 + O(h^6)); accepted 20..45.  Measured: van der Pol 34.2, reactor 32.1,
    runaway burst 31.9 / quiet 31.9, satellite 32.7, Lorenz 33.1.  A wrong
    coefficient in the right-hand side would give an O(h) error, ratio ~2.
    (ii) The error equals Richardson's estimate (16/15)(F_h - F_{h/2}(F_{h/2}))
    computed from the model alone, to 10 % (the estimate neglects the relative
    O(h) term; measured <= 1 %).  (iii) The error is at most 1 % of the
    experiment's noise std (models.md), so the discretisation is invisible to
    the estimators.  Measured |err|_inf: 9.2e-6, 3.7e-7, 9.2e-9, 3.5e-12,
    1.5e-7, 2.6e-5 (at most 0.13 % of the noise std).
    """
    factory, kwargs, x, u, rhs, noise = continuous_case(name)
    model = factory(**kwargs)
    half = factory(dt=model.dt / 2, **kwargs)
    assert model.integrator == "rk4" and model.substeps == 1
    uu = np.zeros(model.nu) if u is None else u

    step = model.f(x, u)
    err = step - flow(rhs, x, uu, model.dt)
    err_half = half.f(x, u) - flow(rhs, x, uu, model.dt / 2)
    ratio = np.linalg.norm(err) / np.linalg.norm(err_half)
    assert 20 < ratio < 45, f"RK4 local error ratio {ratio:.1f}, expected ~32"

    richardson = 16 / 15 * (step - half.f(half.f(x, u), u))
    assert np.linalg.norm(err - richardson) <= 0.1 * np.linalg.norm(richardson)

    assert np.abs(err).max() <= 0.01 * noise
    # and the step itself is not trivially small: the error is relative to real motion
    assert np.abs(err).max() < 1e-3 * np.abs(step - x).max()


# --------------------------------------------------------------------------------------
# 2. Lorenz: the seed's Euler map, exactly
# --------------------------------------------------------------------------------------
def test_lorenz_is_the_seed_euler_map():
    model = lorenz()
    assert model.integrator == "euler" and model.dt == 0.02
    rng = np.random.default_rng(2)
    X = np.column_stack([rng.uniform(-20, 20, (200, 2)), rng.uniform(0, 50, 200)]).T  # (3, N)
    ts, sigma, rho, beta = 0.02, 10.0, 28.0, 8.0 / 3.0
    x1, x2, x3 = X
    seed_next = X + ts * np.array([sigma * (x2 - x1), x1 * (rho - x3) - x2,
                                   x1 * x2 - beta * x3])
    seed_y = np.array([2 * x1, x2 + x3, x3**2 / 10 - x1])
    got_next = np.array([model.f(x) for x in X.T]).T
    got_y = np.array([model.h(x) for x in X.T]).T
    # identical formula, evaluation order may differ: a few ulps of values up to ~300
    np.testing.assert_allclose(got_next, seed_next, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got_y, seed_y, rtol=1e-12, atol=1e-12)
    # the seed's experiment starts at (-10, -12, 27): first step by hand
    np.testing.assert_allclose(model.f([-10, -12, 27]),
                               [-10 + 0.02 * 10 * (-2), -12 + 0.02 * (-10 * 1 + 12),
                                27 + 0.02 * (120 - 72)], rtol=1e-14)


# --------------------------------------------------------------------------------------
# 3. CVODES discretisation
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["van_der_pol", "batch_reactor", "runaway-burst"])
def test_cvodes_matches_exact_flow_and_its_jacobian(name):
    """CVODES (tolerances 1e-10) is the exact flow to 1e-7; its AD Jacobian is the flow's.

    Measured: flow error <= 4e-9; Jacobian vs central differences <= 2.5e-9.
    The difference step d = 1e-4 gives truncation ~d^2 |Phi'''| / 6 ~ 1e-8 and
    reference noise ~1e-12 / d = 1e-8, far below the 1e-5 tolerance.
    """
    factory, kwargs, x, u, rhs, _ = continuous_case(name)
    model = factory(integrator="cvodes", **kwargs)
    assert model.integrator == "cvodes"
    uu = np.zeros(model.nu)
    exact = flow(rhs, x, uu, model.dt)
    np.testing.assert_allclose(model.f(x), exact, rtol=0, atol=1e-7)

    d = 1e-4
    fd = np.column_stack([(flow(rhs, x + d * e, uu, model.dt) - flow(rhs, x - d * e, uu, model.dt))
                          / (2 * d) for e in np.eye(model.nx)])
    A = model.F_x(x, uu, model.p).full()
    np.testing.assert_allclose(A, fd, rtol=0, atol=1e-5)
    np.testing.assert_allclose(model.jacobians(x)[0], A, rtol=0, atol=0)


# --------------------------------------------------------------------------------------
# 4. Jacobians against central differences
# --------------------------------------------------------------------------------------
def jacobian_case(name):
    rng = np.random.default_rng(3)
    if name == "van_der_pol":
        return van_der_pol(), np.array([1.5, 1.5]), None
    if name == "batch_reactor":
        return batch_reactor(), np.array([0.5, 0.05, 0.01]), None
    if name == "runaway":
        return runaway(), runaway_point("burst"), None
    if name == "runaway_augmented":
        return runaway().augment("gamma", "gamma1"), np.r_[runaway_point("burst"), 0.5, 2.5], None
    if name == "satellite":
        x = np.concatenate([unit(rng.standard_normal(4)), [0.02, -0.015, 0.01], [0.3]])
        return satellite(), x, SAT_U
    if name == "lorenz":
        return lorenz(), np.array([-10.0, -12.0, 27.0]), None
    if name == "lorenz_rk4":
        return lorenz(integrator="rk4"), np.array([-10.0, -12.0, 27.0]), None
    raise KeyError(name)


@pytest.mark.parametrize("name", ["van_der_pol", "batch_reactor", "runaway", "runaway_augmented",
                                  "satellite", "lorenz", "lorenz_rk4"])
def test_jacobians_match_central_differences(name):
    """``F_x``, ``H_x`` (CasADi AD) against central differences of ``model.f`` / ``model.h``.

    Step d_i = 1e-5 max(1, |x_i|): truncation d^2 |F'''| / 6 ~ 1e-10 and rounding
    eps |F| / d ~ 1e-10 (|F| <= 30 here); tolerance 1e-7, measured <= 3e-10.
    """
    model, x, u = jacobian_case(name)
    uu = np.zeros(model.nu) if u is None else u
    A, C = model.jacobians(x, u)
    np.testing.assert_array_equal(A, model.F_x(x, uu, model.p).full())
    np.testing.assert_array_equal(C, model.H_x(x, uu, model.p).full())
    assert A.shape == (model.nx, model.nx) and C.shape == (model.ny, model.nx)

    steps = 1e-5 * np.maximum(1.0, np.abs(x))
    A_fd = np.empty_like(A)
    C_fd = np.empty_like(C)
    for i, d in enumerate(steps):
        e = np.zeros(model.nx)
        e[i] = d
        A_fd[:, i] = (model.f(x + e, u) - model.f(x - e, u)) / (2 * d)
        C_fd[:, i] = (model.h(x + e, u) - model.h(x - e, u)) / (2 * d)
    np.testing.assert_allclose(A, A_fd, rtol=0, atol=1e-7)
    np.testing.assert_allclose(C, C_fd, rtol=0, atol=1e-7)


# --------------------------------------------------------------------------------------
# 5. Runaway electrons: bursts and the unstable equilibrium
# --------------------------------------------------------------------------------------
def test_runaway_bursts_as_documented():
    """models.md: bursts every 0.2865 s, peak 1.38, first 2.36 at 0.287 s, ~0.05 s wide.

    Measured (dt = 5e-4): first burst 2.3558 at 0.2870 s, then periods
    0.2865 s (all eight, to the sample), peaks 1.3860 then 1.3805-1.3807,
    widths at half prominence 0.0498-0.0499 s.
    """
    t, X, peaks = runaway_orbit()
    assert np.all(np.isfinite(X)) and X.min() >= 0.0  # positive system: states stay >= 0
    assert len(peaks) >= 9  # ~10 bursts in 3 s
    assert X[peaks[0], 1] == pytest.approx(2.36, rel=0.01)
    assert t[peaks[0]] == pytest.approx(0.287, abs=2 * 5e-4)  # two samples
    periods = np.diff(t[peaks[1:]])
    np.testing.assert_allclose(periods, 0.2865, rtol=0.01)
    np.testing.assert_allclose(X[peaks[1:], 1], 1.38, rtol=0.02)
    widths = find_peaks(X[:, 1], height=0.5, width=0)[1]["widths"] * 5e-4
    np.testing.assert_allclose(widths[1:-1], 0.05, rtol=0.1)  # "about 0.05 s"
    # quiet phase between bursts: x2 falls two orders of magnitude below the peak
    assert X[peaks[1]:peaks[2], 1].min() < 0.01


def test_runaway_discrete_orbit_follows_continuous_system():
    """The RK4 orbit stays within 3e-5 of the exact one for 3 s (models.md) and bursts together.

    Reference: DOP853 of the numpy rhs at 1e-12 (its own error ~1e-6: two
    tight references differ by 8e-7 on this relaxation cycle).  Measured
    global RK4 error 2.74e-5 in x1, 5.5e-6 in x2.
    """
    t, X, peaks = runaway_orbit()
    ref = solve_ivp(lambda s, z: runaway_rhs(z), (0.0, t[-1]), X[0], t_eval=t, **TIGHT)
    assert ref.success
    assert np.abs(ref.y.T - X).max() < 3e-5
    ref_peaks, _ = find_peaks(ref.y[1], height=0.5)
    np.testing.assert_array_equal(ref_peaks, peaks)


def test_runaway_equilibrium_is_unstable():
    """(2.79, 0.179) solves rhs = 0 and has an eigenvalue with positive real part.

    Closed form: x1 x2 = Q/2 = 1/2 and 5 x2^2 + x2/2 - 1/4 = 0, so
    x2* = (sqrt(5.25) - 0.5)/10 = 0.17913, x1* = 2.7913.
    """
    root, info, ier, msg = fsolve(runaway_rhs, [2.79, 0.179], full_output=True, xtol=1e-14)
    assert ier == 1, msg
    x2s = (np.sqrt(5.25) - 0.5) / 10
    np.testing.assert_allclose(root, [0.5 / x2s, x2s], rtol=1e-12)
    # models.md quotes three significant digits: half a unit in the last place
    assert abs(root[0] - 2.79) <= 0.005 and abs(root[1] - 0.179) <= 0.0005

    model = runaway()
    assert np.abs(model.f_c(root, [], model.p).full()).max() < 1e-10
    # analytic Jacobian of the numpy rhs (eps = 50, nu = 0.5, gamma = 0.5, gamma1 = 2.5, W_t = 0.1)
    x1, x2 = root
    J = 50 * np.array([[-2 * x2, -2 * x1],
                       [0.5 * x2, -0.5 + 0.5 * x1 - 2.5 / (1 + x2 / 0.1) ** 2]])
    eig = np.linalg.eigvals(J)
    assert eig.real.max() > 0
    # the model's own linearisation agrees, and the sampled map is unstable there too
    Jc = model.f_c.jacobian()(root, [], model.p, 0)[0].full()  # d xdot / d x
    np.testing.assert_allclose(Jc, J, rtol=1e-12, atol=1e-12)
    A = model.jacobians(root)[0]
    assert np.abs(np.linalg.eigvals(A)).max() > 1


# --------------------------------------------------------------------------------------
# 6. Satellite
# --------------------------------------------------------------------------------------
SAT_I = np.array([0.50, 0.40, 0.26])
KP, KD = 0.01, 0.09


def quat_error_angle(q, q_ref):
    """Rotation angle of q_ref^* (x) q, computed with numpy only (robust near 0)."""
    q_e0 = q_ref @ q  # scalar part of q_ref^* (x) q
    return 2 * np.arctan2(np.sqrt(max(0.0, 1 - q_e0**2)), abs(q_e0))


def scipy_quat(q):
    """Scalar-first (ours) to SciPy's scalar-last quaternion."""
    return np.r_[q[1:4], q[0]]


def test_attitude_helpers_match_scipy_rotations():
    """The test's rotation matrix, ``reference_attitude`` and the PD law against SciPy.

    SciPy's ``Rotation`` (Hamilton, active, scalar last) is the independent
    reference: ``rotation(q)`` is its matrix, ``reference_attitude(t)`` is
    ``Rotation.from_rotvec(phi(t))`` up to the quaternion sign, and the PD
    torque is -Kp sign(q_e0) vec(q_e) - Kd omega with q_e the quaternion of
    R_ref^T R -- the same for q and -q (one attitude, two quaternions).
    """
    rng = np.random.default_rng(6)
    ctrl = PDAttitudeController(excitation=True)
    P, c = np.array([100.0, 73.0, 131.0]), np.array([0.0, 1.0, 2.0])
    for t in rng.uniform(0, 400, 10):
        q = unit(rng.standard_normal(4))
        np.testing.assert_allclose(rotation(q), Rotation.from_quat(scipy_quat(q)).as_matrix(),
                                   atol=1e-14)
        phi = 0.4 * np.sin(2 * np.pi * t / P + c)
        q_ref = reference_attitude(t)
        np.testing.assert_allclose(scipy_quat(q_ref), Rotation.from_rotvec(phi).as_quat(
            canonical=True), atol=1e-14)
        assert np.linalg.norm(q_ref) == pytest.approx(1.0, abs=1e-15)

        w = rng.uniform(-0.05, 0.05, 3)
        r_err = Rotation.from_rotvec(phi).inv() * Rotation.from_quat(scipy_quat(q))
        q_e = r_err.as_quat(canonical=True)  # scalar part >= 0: the sign(q_e0) choice
        expected = -KP * q_e[:3] - KD * w
        for sign in (1.0, -1.0):
            tau = ctrl(t, np.r_[sign * q, w, 0.0])
            np.testing.assert_allclose(tau, expected, atol=1e-15)
    # without excitation the target is the identity: a rotation a about x gives -Kp sin(a/2) e_x
    a = 0.3
    tau = PDAttitudeController(excitation=False)(123.0, np.r_[np.cos(a / 2), np.sin(a / 2), 0, 0,
                                                              0, 0, 0, 0])
    np.testing.assert_allclose(tau, [-KP * np.sin(a / 2), 0, 0], atol=1e-16)


def closed_loop(excitation, fault, T=400):
    """PD on the true state, dt = 1, from q0 = (1,0,0,0), omega0 = (0.02, -0.015, 0.01)."""
    model = satellite()
    faulty = model.with_params(I1=0.2, I2=0.16, I3=0.104)  # 0.4 I
    ctrl = PDAttitudeController(excitation=excitation)
    X = np.empty((T + 1, 8))
    X[0] = [1, 0, 0, 0, 0.02, -0.015, 0.01, 0.0]
    U = np.empty((T, 3))
    for k in range(T):
        t = k * model.dt
        U[k] = ctrl(t, X[k])
        X[k + 1] = (faulty if fault and t >= 200 else model).f(X[k], U[k])
    return np.arange(T + 1) * model.dt, X, U


@pytest.mark.parametrize("fault", [False, True], ids=["nominal", "fault_at_200s"])
def test_satellite_closed_loop_tracks_exciting_reference(fault):
    """Closed loop with the persistently exciting target stays stable, before and after the fault.

    - Quaternion norm: models.md claims drift < 1e-8 over 400 s; measured 4.6e-9.
    - |omega| < 0.05 rad/s; measured max 0.033 (0.032 with the fault).
    - Attitude error vs reference_attitude(t) after a 60 s transient (closed-loop
      time constants 11-14 s): the PD law has no rate feed-forward, so it lags.
      Linearised per axis, I phi'' + Kd phi' + Kp/2 phi = Kp/2 phi_ref, the error
      amplitude is 0.4 |I s^2 + Kd s| / |I s^2 + Kd s + Kp/2| at s = 2 pi i / P.
      The sum over the three axes (worst alignment) is 1.07 rad; measured max
      0.627 rad (0.620 with the fault, where the smaller inertia lags less).
    """
    t, X, U = closed_loop(excitation=True, fault=fault)
    assert np.abs(np.linalg.norm(X[:, :4], axis=1) - 1).max() < 1e-8
    assert np.linalg.norm(X[:, 4:7], axis=1).max() < 0.05
    assert np.abs(U).max() < 0.01  # torques of a small satellite: measured 3.0e-3 N m

    s = 2j * np.pi / np.array([100.0, 73.0, 131.0])
    lag = np.abs(SAT_I * s**2 + KD * s) / np.abs(SAT_I * s**2 + KD * s + KP / 2)
    bound = 0.4 * lag.sum()
    assert 1.0 < bound < 1.1
    err = np.array([quat_error_angle(x[:4], reference_attitude(tk))
                    for tk, x in zip(t, X, strict=True)])
    assert err[t >= 60].max() < bound
    # the reference moves by up to 0.67 rad: the loop is really following it, not sitting
    ref_angle = np.array([quat_error_angle(reference_attitude(tk), np.array([1.0, 0, 0, 0]))
                          for tk in t])
    assert ref_angle.max() > 0.6


@pytest.mark.parametrize("fault", [False, True], ids=["nominal", "fault_at_200s"])
def test_satellite_regulation_settles_at_gravity_gradient_offset(fault):
    """Without excitation the PD law holds the identity attitude up to the gravity-gradient offset.

    Near identity n_B ~ (-cos th, -sin th, 0), so the gravity-gradient torque is
    3 n^2 (I2 - I1) cos th sin th e_z, at most 3 n^2 |I1 - I2| / 2.  At rest it is
    balanced by Kp sin(alpha/2) ~ Kp alpha / 2: alpha <= 3 n^2 |I1 - I2| / Kp =
    3.49e-5 rad (the fault only shrinks |I1 - I2|).  Measured after 150 s:
    alpha <= 2.56e-5 rad (theta reaches only 0.43 rad), |omega| <= 1.6e-7 rad/s
    (4.0e-7 with the fault, its transient at 200 s); |q| drift 3.5e-10.
    """
    _, X, _ = closed_loop(excitation=False, fault=fault)
    n2 = MU_EARTH / R_ORBIT**3
    alpha_bound = 3 * n2 * abs(SAT_I[0] - SAT_I[1]) / KP
    alpha = 2 * np.arctan2(np.linalg.norm(X[:, 1:4], axis=1), np.abs(X[:, 0]))
    assert alpha[150:].max() < alpha_bound
    # |omega| a 1e5-fold smaller than at start: the loop converged
    assert np.linalg.norm(X[150:, 4:7], axis=1).max() < 1e-6
    assert np.abs(np.linalg.norm(X[:, :4], axis=1) - 1).max() < 1e-8


def simulate(model, x0, steps, u=None):
    X = np.empty((steps + 1, model.nx))
    X[0] = x0
    for k in range(steps):
        X[k + 1] = model.f(X[k], u)
    return X


def test_satellite_gyro_signal_invariant_under_inertia_scaling():
    """Zero torque: I -> 2.5 I leaves the gyro signal unchanged (gravity gradient included).

    Both Euler's equations and the gravity-gradient torque are homogeneous of
    degree one in I, so omega' is unchanged; RK4 preserves this step by step.
    Measured relative difference 1.5e-16 (rounding).  The gravity gradient
    matters on this run (changes omega by 4.6e-5 vs mu = 0), and a known
    torque breaks the symmetry (which is what makes the inertia identifiable).
    """
    rng = np.random.default_rng(4)
    x0 = np.concatenate([unit(rng.standard_normal(4)), [0.02, -0.015, 0.01], [0.3]])
    base = satellite()
    c = 2.5
    for scaled in (satellite(I1=c * 0.5, I2=c * 0.4, I3=c * 0.26),
                   base.with_params(I1=c * 0.5, I2=c * 0.4, I3=c * 0.26)):
        Y = np.array([base.h(x) for x in simulate(base, x0, 400)])
        Ys = np.array([scaled.h(x) for x in simulate(scaled, x0, 400)])
        assert np.abs(Ys - Y).max() <= 1e-9 * np.abs(Y).max()

    no_gg = simulate(satellite(mu=0.0), x0, 400)[:, 4:7]
    assert np.abs(no_gg - Y).max() > 1e-6  # >> 1e-9: the symmetry check is not vacuous

    tau = np.array([1e-4, -1e-4, 5e-5])
    W = simulate(base, x0, 100, tau)[:, 4:7]
    Ws = simulate(satellite(I1=c * 0.5, I2=c * 0.4, I3=c * 0.26), x0, 100, tau)[:, 4:7]
    assert np.abs(W - Ws).max() > 1e-3 * np.abs(W).max()


def test_satellite_torque_free_conservation():
    """mu = 0, zero torque: kinetic energy and inertial angular momentum R(q) I omega conserved.

    Momentum in the inertial frame also checks the kinematics convention
    (q' = q (x) (0, omega)/2, body to inertial): a wrong one drifts O(1).
    RK4 on q' = Omega q / 2 drops (|omega| h / 2)^5 / 5! per step relative;
    over N = 400 steps at |omega| = 0.14 rad/s that is <= 5e-6, doubled for
    rotating I omega: bound 1e-5 on ||L - L0|| / ||L0||.  Energy depends on
    omega only (Euler's equations decouple at mu = 0).  Halving dt must shrink
    both drifts at least 12-fold (4th order: 16).
    Measured: L drift 1.1e-6 (h = 1) -> 5.9e-8 (h = 0.5), ratio 19;
    energy 2.8e-8 -> 9.8e-10, ratio 29; |q| drift 3.4e-7.
    """
    rng = np.random.default_rng(5)
    w0 = np.array([0.05, -0.08, 0.1])
    x0 = np.concatenate([unit(rng.standard_normal(4)), w0, [0.0]])
    drifts = []
    for dt in (1.0, 0.5):
        X = simulate(satellite(mu=0.0, dt=dt), x0, int(round(400 / dt)))
        W = X[:, 4:7]
        energy = 0.5 * np.sum(SAT_I * W**2, axis=1)
        L = np.array([rotation(x[:4]) @ (SAT_I * x[4:7]) for x in X])
        dL = np.linalg.norm(L - L[0], axis=1).max() / np.linalg.norm(L[0])
        dT = np.abs(energy / energy[0] - 1).max()
        drifts.append((dL, dT))
        if dt == 1.0:
            step_err = (np.linalg.norm(w0) * dt / 2) ** 5 / 120
            assert dL < 2 * 400 * step_err
            assert dL < 1e-5 and dT < 1e-5
            assert np.abs(np.linalg.norm(X[:, :4], axis=1) - 1).max() < 400 * step_err
            # momentum norm too (the quantity asked for)
            assert np.abs(np.linalg.norm(L, axis=1) / np.linalg.norm(L[0]) - 1).max() < 1e-5
    (dL1, dT1), (dL2, dT2) = drifts
    assert dL1 / dL2 > 12 and dT1 / dT2 > 12


# --------------------------------------------------------------------------------------
# 7. Augmentation and factory parameters
# --------------------------------------------------------------------------------------
def test_augment_appends_constant_parameters():
    base = runaway()
    aug = base.augment("gamma", "gamma1")
    assert aug.state_names == ["x1", "x2", "gamma", "gamma1"]
    assert aug.augmented == {"gamma": 0.5, "gamma1": 2.5}
    assert "gamma" not in aug.param_names and "gamma1" not in aug.param_names
    assert aug.dt == base.dt and aug.integrator == base.integrator

    for x in (runaway_point("burst"), runaway_point("quiet"), np.array([0.0, 1e-3])):
        xa = np.r_[x, 0.5, 2.5]
        nxt = aug.f(xa)
        np.testing.assert_allclose(nxt[:2], base.f(x), rtol=1e-14, atol=1e-16)
        np.testing.assert_array_equal(nxt[2:], [0.5, 2.5])
        assert aug.h(xa)[0] == base.h(x)[0]
        A, C = aug.jacobians(xa)
        np.testing.assert_allclose(A[:2, :2], base.jacobians(x)[0], rtol=1e-13, atol=1e-16)
        np.testing.assert_array_equal(A[2:], np.c_[np.zeros((2, 2)), np.eye(2)])
        np.testing.assert_array_equal(C, [[0, 1, 0, 0]])
        # d x+/d gamma is nonzero: the parameters do enter the dynamics
        assert np.abs(A[1, 2:]).min() > 0

    # other parameter values in the state = the model built with those values
    x = runaway_point("burst")
    np.testing.assert_allclose(aug.f(np.r_[x, 0.6, 2.0])[:2], runaway(gamma=0.6, gamma1=2.0).f(x),
                               rtol=1e-14, atol=1e-16)


def test_factory_parameters_change_the_dynamics():
    """batch_reactor(k1=0.6) is the reactor with k1 = 0.6: the exact flow agrees to RK4 error."""
    x = np.array([0.5, 0.05, 0.0])
    nominal, changed = batch_reactor(), batch_reactor(k1=0.6)
    assert changed.params["k1"] == 0.6
    step = changed.f(x)
    # k1 moves C_A by ~ -dt * 0.1 * 0.5 = -0.0125 in one step, vs RK4 errors ~4e-7
    assert np.abs(step - nominal.f(x)).max() > 1e-3
    exact = flow(lambda z, u: reactor_rhs(z, k1=0.6), x, None, changed.dt)
    assert np.abs(step - exact).max() < 1e-5  # 0.5 % of sigma_w; nominal measured 3.7e-7
    np.testing.assert_array_equal(nominal.with_params(k1=0.6).f(x), step)
    np.testing.assert_array_equal(nominal.f(x), batch_reactor().f(x))  # with_params copies
