"""Semi-explicit index-1 DAE models (``Model(algebraic=..., alg=...)``): every estimator on
a DAE equals the same estimator on the model reduced by hand; the integrators against
``solve_ivp`` (Radau); what is not index 1 is refused."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import estim
import estim._dae

K, KR = 2.0, 0.3  # fast equilibrium B = K A, slow reaction B -> C
G = 9.81


def reactor(dae: bool = True, squared: bool = False, **kw) -> estim.Model:
    """A <-> B at equilibrium (c_B = K c_A), B -> C at rate KR c_B, A fed by ``feed``;
    states the total n = c_A + c_B and c_C; measured c_B + 2 c_C. With ``dae`` c_A is an
    algebraic state, else it is eliminated by hand (c_A = n / (1 + K)). The equilibrium
    is linear in c_A (solved in the graph), or with ``squared`` written as
    c_B^2 = K^2 c_A^2 (Newton's method from z0 = 0.2 finds the positive root)."""
    if dae:
        def alg(x, z, u, p):
            cB = x[0] - z[0]
            return cB**2 - K**2 * z[0] ** 2 if squared else cB - K * z[0]
        return estim.Model(
            states=["n", "cC"], algebraic=["cA"], inputs=["feed"], outputs=["y"],
            ode=lambda x, z, u, p: ca.vertcat(-KR * (x[0] - z[0]) + u[0], KR * (x[0] - z[0])),
            alg=alg, output=lambda x, z, u, p: x[0] - z[0] + 2 * x[1], dt=0.1,
            z0=[0.2] if squared else None, **kw)
    b = K / (1 + K)
    return estim.Model(states=["n", "cC"], inputs=["feed"], outputs=["y"],
                       ode=lambda x, u, p: ca.vertcat(-KR * b * x[0] + u[0], KR * b * x[0]),
                       output=lambda x, u, p: b * x[0] + 2 * x[1], dt=0.1, **kw)


def pendulum(dae: bool = True, **kw) -> estim.Model:
    """A pendulum in Cartesian coordinates (unit mass, length 1), the tension ``lam`` from
    the constraint differentiated twice (index 1): lam (x^2 + y^2) = vx^2 + vy^2 - g y;
    measured x and y. Without ``dae`` lam is substituted by hand."""
    def lam(s):
        return (s[2] ** 2 + s[3] ** 2 - G * s[1]) / (s[0] ** 2 + s[1] ** 2)

    def acc(s, la):
        return ca.vertcat(s[2], s[3], -la * s[0], -la * s[1] - G)

    common = dict(states=["x", "y", "vx", "vy"], outputs=["x_m", "y_m"], dt=0.05, **kw)
    if dae:
        return estim.Model(algebraic=["lam"], ode=lambda s, z, u, p: acc(s, z[0]),
                           alg=lambda s, z, u, p: z[0] * (s[0] ** 2 + s[1] ** 2)
                           - (s[2] ** 2 + s[3] ** 2) + G * s[1],
                           output=lambda s, z, u, p: s[:2], z0=[G], **common)
    return estim.Model(ode=lambda s, u, p: acc(s, lam(s)), output=lambda s, u, p: s[:2],
                       **common)


@pytest.mark.parametrize("squared", [False, True])
def test_model_and_consistent_algebraic_state(squared):
    m = reactor(squared=squared)
    assert m.nz == 1 and m.algebraic_names == ["cA"] and m.Z is not None
    # linear in z: all in the SX graph; squared: a Newton solve the graphs call
    assert m.F.is_a("SXFunction") != squared
    np.testing.assert_allclose(m.z([0.9, 0.0]), [0.3], rtol=1e-14)
    red = reactor(dae=False)
    x, u = np.array([0.9, 0.2]), np.array([0.05])
    np.testing.assert_allclose(m.f(x, u), red.f(x, u), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(m.h(x, u), red.h(x, u), rtol=1e-14)
    for a, b in zip(m.jacobians(x, u), red.jacobians(x, u), strict=True):  # through the IFT
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("integrator, substeps, tol", [("rk4", 4, 1e-7), ("collocation", 4, 1e-9),
                                                       ("idas", 1, 1e-8)])
def test_integrators_against_radau(integrator, substeps, tol):
    """One sample of the pendulum from a consistent state against solve_ivp's Radau
    (rtol 1e-12) on the hand-reduced ODE."""
    m = pendulum(integrator=integrator, substeps=substeps)
    red = pendulum(dae=False)
    s0 = np.array([0.6, -0.8, 1.0, 0.75])  # on the circle, velocity tangent
    ref = solve_ivp(lambda t, s: np.asarray(red.f_c(s, [], [])).ravel(), (0, 0.05), s0,
                    method="Radau", rtol=1e-12, atol=1e-14).y[:, -1]
    np.testing.assert_allclose(m.f(s0), ref, atol=tol)


@pytest.mark.parametrize("make, x, u", [
    (lambda: reactor(integrator="collocation", substeps=2), [0.9, 0.2], [0.05]),
    (lambda: reactor(squared=True, integrator="collocation", substeps=3), [0.9, 0.2], [0.05]),
    (lambda: pendulum(integrator="collocation", substeps=2), [0.6, -0.8, 1.0, 0.75], []),
])
def test_collocation_equals_casadis_collocation_integrator(make, x, u):
    """estim's Radau IIA collocation (stage equations solved in the graph for the linear
    reactor, by Newton's method otherwise) is the discretisation of CasADi's
    ``collocation`` integrator with Radau points: the same state, and the same
    Jacobian, after one sample; the Butcher tableau is Radau IIA's (Hairer-Wanner)."""
    m = make()
    assert m.F.is_a("SXFunction") == (m.nx == 2 and m.substeps == 2)  # linear: in the graph
    xs, zs, us = ca.SX.sym("x", m.nx), ca.SX.sym("z", m.nz), ca.SX.sym("u", m.nu)
    dae = {"x": xs, "z": zs, "p": us, "ode": m._ode(xs, zs, us, {}),
           "alg": m._alg(xs, zs, us, {})}
    ref = ca.integrator("ref", "collocation", dae, 0.0, m.dt,
                        {"number_of_finite_elements": m.substeps, "interpolation_order": 3,
                         "collocation_scheme": "radau",
                         "rootfinder_options": {"abstol": 1e-14}})
    x0 = ca.MX.sym("x0", m.nx)
    xf = ref(x0=x0, z0=m.z(x, u), p=u)["xf"]
    ref_x = ca.Function("ref_x", [x0], [xf, ca.jacobian(xf, x0)])
    x_ref, A_ref = (np.asarray(v) for v in ref_x(x))
    np.testing.assert_allclose(m.f(x, u), x_ref.ravel(), atol=1e-13)
    np.testing.assert_allclose(np.asarray(m.F_x(x, u, [])), A_ref, atol=1e-10)
    A, b, c = estim._dae.radau_tableau()
    s6 = np.sqrt(6)
    np.testing.assert_allclose(c, [(4 - s6) / 10, (4 + s6) / 10, 1], rtol=1e-15)
    np.testing.assert_allclose(A[0], [(88 - 7 * s6) / 360, (296 - 169 * s6) / 1800,
                                      (-2 + 3 * s6) / 225], rtol=1e-13)
    np.testing.assert_allclose(b, [(16 - s6) / 36, (16 + s6) / 36, 1 / 9], rtol=1e-14)


@pytest.mark.parametrize("squared", [False, True])
def test_estimators_equal_the_hand_reduced_model(squared):
    """simulate, EKF, UKF, MHE (Gauss-Newton and Ipopt), the EnKF, the particle filter and
    full information on the DAE equal the same on the reduced ODE to 1e-8; the log has
    the algebraic states of the truth and of the estimates."""
    U = 0.1 * (1 + np.sin(0.1 * np.arange(40)))[:, None]
    tuning = dict(Q=1e-4, R=1e-2, x0=[1.0, 0.0], P0=0.1)
    sc = estim.Scenario("dae", reactor(squared=squared), x0=[1.0, 0.0], n_steps=40, Q=1e-4,
                        R=1e-2,
                        tuning=tuning, inputs=U)
    scr = sc.replace(model=reactor(dae=False))
    makers = [lambda m: estim.EKF(m, **tuning), lambda m: estim.UKF(m, **tuning),
              lambda m: estim.MHE(m, horizon=8, solver="gauss-newton", **tuning),
              lambda m: estim.MHE(m, horizon=8, **tuning),
              lambda m: estim.EnKF(m, n_ensemble=10, **tuning),
              lambda m: estim.ParticleFilter(m, n_particles=50, **tuning)]
    for make in makers:
        a, b = estim.simulate(sc, make(sc.model), seed=0), estim.simulate(scr, make(scr.model),
                                                                          seed=0)
        np.testing.assert_allclose(a.x, b.x, atol=1e-12)
        np.testing.assert_allclose(a.x_hat, b.x_hat, atol=1e-8, err_msg=a.estimator)
        assert np.all(a.success)
    # exact when solved in the graph; to the Newton solve's tolerance (residual 1e-13)
    tol = 1e-10 if squared else 1e-13
    np.testing.assert_allclose(a.z[:, 0], a.x[:, 0] / (1 + K), rtol=tol)
    np.testing.assert_allclose(a.z_hat[:, 0], a.x_hat[:, 0] / (1 + K), rtol=tol)
    # the squared equilibrium has a second root, c_A = -n, which Newton's method finds
    # from z0 where n < 0: from the zero trajectory the fit would cross into it, so it
    # starts from the filter's estimates there (the linear form from zero)
    guess = np.asarray(a.x_hat) if squared else None
    for solver in ("gauss-newton", "ipopt"):
        fa = estim.FullInformation(sc.model, Q=1e-4, R=1e-2, solver=solver).fit(a.y, U,
                                                                                guess=guess)
        fb = estim.FullInformation(scr.model, Q=1e-4, R=1e-2, solver=solver).fit(a.y, U)
        assert fa.success
        np.testing.assert_allclose(fa.x, fb.x, atol=1e-8)


def test_pendulum_filters_equal_the_reduced_model():
    sc = estim.Scenario("pendulum", pendulum(), x0=[0.6, -0.8, 1.0, 0.75], n_steps=60,
                        Q=np.diag([0, 0, 1e-4, 1e-4]), R=1e-4,
                        tuning=dict(Q=np.diag([1e-8, 1e-8, 1e-4, 1e-4]), R=1e-4,
                                    x0=[0.6, -0.8, 1.0, 0.75], P0=1e-3))
    scr = sc.replace(model=pendulum(dae=False))
    makers = [estim.EKF, estim.UKF,
              lambda m, **kw: estim.MHE(m, horizon=6, solver="gauss-newton", **kw)]
    for make in makers:
        a = estim.simulate(sc, make(sc.model, **sc.tuning), seed=1)
        b = estim.simulate(scr, make(scr.model, **scr.tuning), seed=1)
        np.testing.assert_allclose(a.x_hat, b.x_hat, atol=1e-8)
        assert np.all(np.isfinite(a.z_hat)) and np.all(a.success)
    fits = [estim.FullInformation(s.model, Q=s.tuning["Q"], R=1e-4, x0=s.tuning["x0"],
                                  P0=1e-3).fit(a.y) for s in (sc, scr)]
    assert fits[0].success and fits[1].success
    np.testing.assert_allclose(fits[0].x, fits[1].x, atol=1e-8)


def test_augment_and_disturbances_keep_the_algebraic_states():
    m = estim.Model(states=["n", "cC"], algebraic=["cA"], inputs=["feed"], outputs=["y"],
                    ode=lambda x, z, u, p: ca.vertcat(-p["k"] * (x[0] - z[0]) + u[0],
                                                      p["k"] * (x[0] - z[0])),
                    alg=lambda x, z, u, p: (x[0] - z[0]) - K * z[0],
                    output=lambda x, z, u, p: x[0] - z[0] + 2 * x[1], dt=0.1,
                    params={"k": KR})
    a = m.augment("k")
    assert a.algebraic_names == ["cA"]
    np.testing.assert_allclose(a.f([1.0, 0.0, KR], [0.1])[:2], m.f([1.0, 0.0], [0.1]),
                               rtol=1e-14)
    d = m.with_disturbances(inputs=["feed"], at=([1.0, 0.0], [0.1]))
    np.testing.assert_allclose(d.f([1.0, 0.0, 0.05], [0.1])[:2], m.f([1.0, 0.0], [0.15]),
                               rtol=1e-14)


def test_not_index_one_and_bad_input_are_refused():
    def ode(s, z, u, p):
        return ca.vertcat(s[2], s[3], -z[0] * s[0], -z[0] * s[1] - G)

    common = dict(states=["x", "y", "vx", "vy"], outputs=["x_m"], ode=ode, dt=0.05,
                  output=lambda s, z, u, p: s[0], algebraic=["lam"])
    with pytest.raises(ValueError, match=r"structurally singular .* no equation contains "
                                         r"\['lam'\].*not index 1"):
        estim.Model(alg=lambda s, z, u, p: s[0] ** 2 + s[1] ** 2 - 1, **common)  # index 3
    with pytest.raises(ValueError, match=r"alg must return 1 entries .* got shape \(2, 1\)"):
        estim.Model(alg=lambda s, z, u, p: ca.vertcat(z[0], z[0]), **common)
    with pytest.raises(ValueError, match="z0"):
        estim.Model(alg=lambda s, z, u, p: z[0] - 1, z0=[1.0, 2.0], **common)
    with pytest.raises(TypeError, match="alg="):
        estim.Model(**common)
    with pytest.raises(ValueError, match="'cvodes' integrates ODEs only"):
        estim.Model(alg=lambda s, z, u, p: z[0] - 1, integrator="cvodes", **common)
    with pytest.raises(ValueError, match="algebraic=, alg="):
        reactor(dae=False, integrator="idas")
    with pytest.raises(ValueError, match="need algebraic="):
        estim.Model(states=["x"], outputs=["y"], ode=lambda x, u, p: -x,
                    output=lambda x, u, p: x, dt=0.1, alg=lambda x, z, u, p: z)


def test_no_algebraic_solution_fails_a_step_not_the_loop():
    """z^2 = x - 1 has no real root for x < 1: model.z says so, and a filter whose
    estimate goes there fails the step (NaN from the Newton solve) and re-anchors."""
    m = estim.Model(states=["x"], algebraic=["z"], outputs=["y"], ode=lambda x, z, u, p: -0.1 * x,
                    alg=lambda x, z, u, p: z[0] ** 2 - (x[0] - 1), z0=[1.0],
                    output=lambda x, z, u, p: z[0], dt=0.1)
    np.testing.assert_allclose(m.z([5.0]), [2.0])
    with pytest.raises(ValueError, match="no consistent algebraic state at x = \\[0.5\\]"):
        m.z([0.5])
    ekf = estim.EKF(m, Q=1e-4, R=1e-2, x0=[0.5], P0=0.01)
    ekf.step([1.0])
    assert not ekf.info.success and "failed" in ekf.info.status


def test_pendulum_scenario():
    """``estim.scenarios.get("pendulum")``: the plant (Radau IIA collocation) stays on its
    circle, and the EKF from the wrong guess tracks the state and the rod's tension."""
    sc = estim.scenarios.get("pendulum", n_steps=80)
    assert sc.model.algebraic_names == ["tension"] and "pendulum" in estim.scenarios.SCENARIOS
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    assert np.abs(np.hypot(log.x[:, 0], log.x[:, 1]) - 1).max() < 1e-6
    assert np.all(log.success)
    late = slice(40, None)
    assert np.abs(log.x_hat[late, :2] - log.x[late, :2]).max() < 0.05
    # the tension (about g at the bottom) against the truth's
    assert np.abs(log.z_hat[late, 0] - log.z[late, 0]).max() < 0.1 * np.abs(log.z).max()


def test_code_generation_refuses_algebraic_states(tmp_path):
    m = estim.models.pendulum()
    ekf = estim.EKF(m, Q=1e-6, R=1e-4, x0=[0.5, -0.866, 0.0, 0.0], P0=0.01)
    with pytest.raises(ValueError, match=r"algebraic states \['tension'\]"):
        estim.codegen.export(ekf, tmp_path)


def test_shooting_observer_and_observability_on_a_dae():
    """The shooting observer on the DAE equals it on the reduced ODE; the observability
    analysis of the DAE finds what it finds of the reduced model (both states observable
    from y = c_B + 2 c_C with the feed varying)."""
    U = np.full((120, 1), 0.1)
    logs = []
    for dae in (True, False):
        m = reactor(dae)
        sc = estim.Scenario("dae", m, x0=[1.0, 0.0], n_steps=120, Q=0.0, R=1e-3,
                            tuning=dict(Q=1e-5, R=1e-3, x0=[1.2, 0.1], P0=0.1), inputs=U)
        logs.append(estim.simulate(sc, estim.ShootingObserver(m, window=10, every=5, R=1e-3,
                                                              x0=[1.2, 0.1]), seed=0))
    np.testing.assert_allclose(logs[0].x_hat, logs[1].x_hat, atol=1e-10, equal_nan=True)
    reports = [estim.observability.analyze(reactor(dae)) for dae in (True, False)]
    assert [r.observable for r in reports] == [["n", "cC"], ["n", "cC"]]
