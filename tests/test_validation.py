"""Bad input fails early with a message naming the argument."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim


def vdp(**kwargs):
    base = dict(states=["x1", "x2"], outputs=["y"],
                ode=lambda x, u, p: ca.vertcat(x[1], -x[0]), output=lambda x, u, p: x[0],
                dt=0.1)
    base.update(kwargs)
    return estim.Model(**base)


@pytest.fixture
def ekf():
    return estim.EKF(vdp(), Q=0.01, R=0.1, x0=[0, 0], P0=1.0)


@pytest.mark.parametrize("cls", [estim.EKF, estim.UKF])
@pytest.mark.parametrize("y", [[1.0, 2.0], np.zeros((2, 2)), []])
def test_wrong_y_shape(cls, y):
    est = cls(vdp(), Q=0.01, R=0.1, x0=[0, 0], P0=1.0)
    with pytest.raises(ValueError, match=r"y must have shape \(1,\)"):
        est.step(y)


def test_non_numeric_y(ekf):
    with pytest.raises(TypeError, match="y must be numeric"):
        ekf.step("abc")


def test_inf_in_y(ekf):
    with pytest.raises(ValueError, match="y must not contain inf"):
        ekf.step(np.array([np.inf]))


@pytest.mark.parametrize("P0", [-1.0, [1.0, 0.0], [[1.0, 2.0], [2.0, 1.0]], [[1, 0.5], [0, 1]]])
def test_non_positive_definite_or_asymmetric_P0(P0):
    with pytest.raises(ValueError, match="P0 must be"):
        estim.EKF(vdp(), Q=0.01, R=0.1, x0=[0, 0], P0=P0)


def test_bad_covariance_shapes_and_values():
    m = vdp()
    with pytest.raises(ValueError, match="R must be positive definite"):
        estim.EKF(m, Q=0.01, R=0.0, x0=[0, 0], P0=1.0)
    with pytest.raises(ValueError, match="Q must be positive semi-definite"):
        estim.EKF(m, Q=-0.1, R=0.1, x0=[0, 0], P0=1.0)
    with pytest.raises(ValueError, match=r"Q must be a scalar, a \(2,\) vector"):
        estim.EKF(m, Q=np.eye(3), R=0.1, x0=[0, 0], P0=1.0)
    with pytest.raises(ValueError, match="P0 is required"):
        estim.EKF(m, Q=0.01, R=0.1, x0=[0, 0], P0=None)


@pytest.mark.parametrize("x0", [[np.nan, 0.0], [0.0, np.inf]])
def test_nan_in_x0(x0):
    with pytest.raises(ValueError, match="x0 must be finite"):
        estim.EKF(vdp(), Q=0.01, R=0.1, x0=x0, P0=1.0)
    with pytest.raises(ValueError, match="x0 must be finite"):
        estim.UKF(vdp(), Q=0.01, R=0.1, x0=x0, P0=1.0)


def test_x0_wrong_length():
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\)"):
        estim.EKF(vdp(), Q=0.01, R=0.1, x0=[0, 0, 0], P0=1.0)


def test_unknown_integrator():
    with pytest.raises(ValueError, match="integrator must be one of"):
        vdp(integrator="rk45")


def test_unknown_option():
    with pytest.raises(TypeError, match="unknown option.*horizon"):
        estim.EKF(vdp(), Q=0.01, R=0.1, x0=[0, 0], P0=1.0, horizon=10)


@pytest.mark.parametrize("arg", ["ode", "output"])
def test_equation_returning_the_wrong_size(arg):
    bad = {"ode": lambda x, u, p: ca.vertcat(x[1], -x[0], 0),
           "output": lambda x, u, p: x}[arg]
    with pytest.raises(ValueError, match=f"{arg} must return"):
        vdp(**{arg: bad})
    with pytest.raises(ValueError, match="dynamics must return"):
        estim.Model(states=2, outputs=1, dynamics=lambda x, u, p: x[0],
                    output=lambda x, u, p: x[0])


def test_equation_returning_garbage():
    with pytest.raises(TypeError, match="ode must return a CasADi expression"):
        vdp(ode=lambda x, u, p: "x")


def test_model_definition_errors():
    with pytest.raises(ValueError, match="exactly one of ode"):
        estim.Model(states=1, outputs=1, output=lambda x, u, p: x)
    with pytest.raises(ValueError, match="dt is required"):
        estim.Model(states=1, outputs=1, ode=lambda x, u, p: -x, output=lambda x, u, p: x)
    with pytest.raises(ValueError, match="dt must be a positive"):
        vdp(dt=-0.1)
    with pytest.raises(TypeError, match="ode must be callable"):
        vdp(ode=3)
    with pytest.raises(ValueError, match="duplicate"):
        vdp(states=["a", "a"])
    with pytest.raises(ValueError, match=r"params\['k'\] must be a finite number"):
        vdp(params={"k": np.nan})
    with pytest.raises(ValueError, match="lower names unknown state"):
        vdp(lower={"z": 0})
    with pytest.raises(ValueError, match="lower must not exceed upper"):
        vdp(lower=1.0, upper=0.0)
    with pytest.raises(ValueError, match="substeps must be a positive integer"):
        vdp(substeps=0)


def test_model_numeric_shapes():
    m = vdp(inputs=["u"])
    with pytest.raises(ValueError, match=r"x must have shape \(2,\)"):
        m.f([1.0])
    with pytest.raises(ValueError, match=r"u must have shape \(1,\)"):
        m.f([1.0, 2.0], [1.0, 2.0])
    assert m.f([1.0, 2.0]).shape == (2,) and m.h([1.0, 2.0]).shape == (1,)


def test_augment_errors():
    m = estim.models.van_der_pol()
    with pytest.raises(ValueError, match="unknown parameter 'nu'"):
        m.augment("nu")
    with pytest.raises(ValueError, match="at least one"):
        m.augment()
    with pytest.raises(ValueError, match="unknown parameter"):
        m.with_params(nu=1.0)


def test_simulate_argument_errors():
    sc = estim.scenarios.van_der_pol()
    ekf = estim.EKF(sc.model, **sc.tuning)
    with pytest.raises(TypeError, match="estimator must be"):
        estim.simulate(sc, object())
    with pytest.raises(TypeError, match="target must be a Scenario or a Model"):
        estim.simulate("vdp", ekf)
    with pytest.raises(ValueError, match="n_steps must be a positive integer"):
        estim.simulate(sc, ekf, n_steps=0)
    with pytest.raises(ValueError, match=r"inputs must have shape"):
        estim.simulate(estim.models.satellite(), estim.EKF(
            estim.models.satellite(), Q=1e-8, R=1e-6, x0=np.r_[1, np.zeros(7)], P0=1e-4),
            x0=np.r_[1, np.zeros(7)], n_steps=5, Q=0, R=1e-6, inputs=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="missing as a probability"):
        estim.simulate(sc, ekf, missing=1.5)
    with pytest.raises(ValueError, match="other dimensions"):
        estim.simulate(estim.scenarios.lorenz(), ekf)
    with pytest.raises(ValueError, match="unknown scenario"):
        estim.scenarios.get("double_pendulum")


def test_inputs_are_never_silently_zero():
    """A model with inputs refuses a record without U in fit, filter, smooth, replay and
    the tuning functions (naming U and nu); U=0 runs with zero inputs on purpose."""
    m = estim.Model(states=["h"], inputs=["q"], outputs=["y"],
                    ode=lambda x, u, p: -0.5 * x + u, output=lambda x, u, p: x, dt=0.1)
    Y = np.full((20, 1), 0.3)
    tuning = dict(Q=1e-4, R=1e-2, x0=[0.3], P0=0.1)
    calls = [lambda: estim.FullInformation(m, Q=1e-4, R=1e-2).fit(Y),
             lambda: estim.EKF(m, **tuning).filter(Y),
             lambda: estim.UKF(m, **tuning).smooth(Y),
             lambda: estim.EnKF(m, **tuning).filter(Y),
             lambda: estim.tuning.als(m, Y, x0=[0.3], P0=0.1)]
    for call in calls:
        with pytest.raises(ValueError, match=r"U is required: model has nu = 1 input\(s\) "
                                             r"\['q'\].* or U=0 to run with zero inputs"):
            call()
    with pytest.raises(ValueError, match=r"u is required: .* or u=0 to replay"):
        estim.replay(estim.EKF(m, **tuning), Y)
    zero = estim.EKF(m, **tuning).filter(Y, 0)
    np.testing.assert_allclose(zero.x, estim.EKF(m, **tuning).filter(Y, np.zeros((19, 1))).x)
    np.testing.assert_allclose(estim.replay(estim.EKF(m, **tuning), Y, u=0).x_hat, zero.x)
    assert estim.FullInformation(m, Q=1e-4, R=1e-2).fit(Y, 0).success


def test_corners_are_refused():
    """codegen.memory refuses what export refuses; compare checks the backend's name; a
    first-order hold on a model without inputs is refused."""
    sc = estim.scenarios.get("van_der_pol")
    for bad in (None, estim.FullInformation(sc.model, Q=0.01, R=1.0)):
        with pytest.raises(TypeError, match="estimator must be an estim.EKF, estim.UKF or "
                                            "estim.MHE with rti=True"):
            estim.codegen.memory(bad)
    with pytest.raises(ValueError, match=r"backend must be one of .* got 'lokky'; did you "
                                         r"mean 'loky'"):
        estim.compare(sc, {"ekf": estim.EKF}, backend="lokky")
    with pytest.raises(ValueError, match="hold='foh' .* the model has none"):
        estim.Model(states=["x"], outputs=["y"], ode=lambda x, u, p: -x,
                    output=lambda x, u, p: x, dt=0.1, hold="foh")


@pytest.mark.parametrize("ode, error, hint", [
    (lambda x, u, p: x[0] if x[0] > 0 else -x[0], RuntimeError, "ca.if_else"),
    (lambda x, u, p: ca.vertcat(x[0], None), NotImplementedError, "None?"),
    (lambda x, u, p: ca.vertcat(x[5], x[0]), RuntimeError, "an index beyond a vector"),
])
def test_errors_inside_user_equations_name_the_model_and_equation(ode, error, hint):
    with pytest.raises(error, match=r"^mine: building the equation ode= failed: .*" + hint):
        estim.Model(states=["a", "b"], outputs=["y"], ode=ode, output=lambda x, u, p: x[0],
                    dt=0.1, name="mine")


def test_a_failed_step_says_what_is_not_finite():
    """The EKF's status at a square root of a negative state names the entry and the
    operation; the run's warning does the same for estimators whose status does not."""
    from estim.simulate import _located

    m = estim.Model(states=["h1", "h2"], inputs=["q"], outputs=["y"],
                    ode=lambda x, u, p: ca.vertcat(u[0] - 0.5 * ca.sqrt(x[0]),
                                                   0.5 * ca.sqrt(x[0]) - 0.4 * ca.sqrt(x[1])),
                    output=lambda x, u, p: x[1], dt=0.5, name="tanks")
    Y = np.full((10, 1), 0.5)
    log = estim.replay(estim.EKF(m, Q=1e-4, R=1e-4, x0=[0.01, 0.5], P0=1.0), Y, u=0,
                       warn=False)
    assert "(not finite: F entry 'h1' is nan: sqrt of -0.0025 at [0.01, 0.5])" in \
        log.status[1]
    assert _located(m, log, 1) == "F entry 'h1' is nan: sqrt of -0.0025 at [0.01, 0.5]"


def test_a_size_mismatch_gives_the_sizes_and_the_fix():
    sc = estim.scenarios.get("van_der_pol")
    ekf = estim.EKF(sc.model.augment("mu"), Q=0.01, R=1.0, x0=[0, 0, 1.0], P0=1.0)
    with pytest.raises(ValueError, match=r"nx=3 \['x1', 'x2', 'mu'\], ny=2, nu=0 against the "
                                         r"plant's nx=2 .* the states \['mu'\] the plant lacks"):
        estim.simulate(sc, ekf)
    with pytest.raises(ValueError, match=r"estimators\['ekf'\] was built .* \['mu'\]"):
        estim.compare(sc, {"ekf": ekf})
