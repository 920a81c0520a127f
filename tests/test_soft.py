"""estim.soft (smooth replacements for switches) and the non-smoothness diagnostic.

The helpers are checked against their closed forms, their deviation bounds, their
algorithmic derivatives against central differences (first and second order, at the
corner too), numpy against CasADi, and far into the tails. The diagnostic is checked on
small tank models with ``fmin``/``if_else`` switches and their smooth rewrites, and on
every model of ``estim.models``; a full-information fit shows the measured problem (an
``if_else`` threshold that never moves) and the fix.
"""

from __future__ import annotations

import doctest
import warnings

import casadi as ca
import numpy as np
import pytest

import estim
from estim import soft
from estim._smoothness import (
    NonSmoothOperation,
    _scan,
    advice,
    nonsmooth_operations,
    zero_derivative_parameters,
)

LOG2 = np.log(2.0)
WIDTHS = [1e-3, 1.0, 250.0]


def _softplus(z):
    return np.logaddexp(0.0, z)


def _logistic(z):
    return np.exp(-np.logaddexp(0.0, -z))


# every helper as a function of one argument, with its exact non-smooth counterpart
# and its reference closed form (numpy, independent of estim.soft)
CASES = {
    "relu": (lambda x, w: soft.relu(x, w), lambda x, w: np.maximum(x, 0),
             lambda x, w: w * _softplus(x / w)),
    "max": (lambda x, w: soft.max(x, 0.3 * w, w), lambda x, w: np.maximum(x, 0.3 * w),
            None),
    "min": (lambda x, w: soft.min(x, -0.3 * w, w), lambda x, w: np.minimum(x, -0.3 * w),
            None),
    "abs": (lambda x, w: soft.abs(x, w), lambda x, w: np.abs(x),
            lambda x, w: np.sqrt(x**2 + w**2) - w),
    "step": (lambda x, w: soft.step(x, w), lambda x, w: (x > 0).astype(float),
             lambda x, w: _logistic(x / w)),
    "clip": (lambda x, w: soft.clip(x, -2 * w, 3 * w, w),
             lambda x, w: np.clip(x, -2 * w, 3 * w), None),
}

# each helper called with a given width (for the argument checks)
CALLS = [lambda w: soft.relu(1.0, w), lambda w: soft.max(1.0, 0.0, w),
         lambda w: soft.min(1.0, 0.0, w), lambda w: soft.abs(1.0, w),
         lambda w: soft.step(1.0, w), lambda w: soft.clip(1.0, 0.0, 2.0, w)]


def _grid(w, n=4001, span=40.0):
    return w * np.concatenate([np.linspace(-span, span, n), [0.0, 1e-12, -1e-12]])


def _derivatives(name, w):
    """A CasADi Function x -> (value, first, second derivative) of helper ``name``."""
    x = ca.SX.sym("x")
    e = CASES[name][0](x, w)
    d1 = ca.jacobian(e, x)
    return ca.Function("d", [x], [e, d1, ca.jacobian(d1, x)])


def _eval(fun, xs):
    return [np.asarray(v).ravel() for v in fun.map(len(xs))(xs)]


# --------------------------------------------------------------------- values
@pytest.mark.parametrize("w", WIDTHS)
@pytest.mark.parametrize("name", ["relu", "abs", "step"])
def test_closed_forms(name, w):
    x = _grid(w)
    got = CASES[name][0](x, w)
    ref = CASES[name][2](x, w)
    scale = 1.0 if name == "step" else w        # step is dimensionless
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-15 * scale)


@pytest.mark.parametrize("w", WIDTHS)
def test_max_min_clip_identities(w):
    rng = np.random.default_rng(0)
    a, b = rng.normal(scale=5 * w, size=(2, 500))
    sp = w * _softplus((a - b) / w)
    np.testing.assert_allclose(soft.max(a, b, w), b + sp, rtol=1e-13, atol=1e-13 * w)
    np.testing.assert_allclose(soft.max(a, b, w), soft.max(b, a, w), rtol=1e-13,
                               atol=1e-13 * w)
    np.testing.assert_allclose(soft.min(a, b, w), -soft.max(-a, -b, w), rtol=1e-13,
                               atol=1e-13 * w)
    lo, up = -w, 2 * w
    ref = lo + w * _softplus((a - lo) / w) - w * _softplus((a - up) / w)
    np.testing.assert_allclose(soft.clip(a, lo, up, w), ref, rtol=1e-13, atol=1e-13 * w)


@pytest.mark.parametrize("w", WIDTHS)
def test_deviation_bounds(w):
    x = _grid(w)
    tol = 1e-12 * w
    gap = soft.relu(x, w) - np.maximum(x, 0)
    assert np.all(gap >= 0) and np.all(gap <= w * LOG2 + tol)
    assert np.all(soft.relu(x[x > -700 * w], w) > 0)      # positive until it underflows
    assert soft.relu(0.0, w) == pytest.approx(w * LOG2, rel=1e-15)
    far = np.abs(x) > 5 * w     # exponentially close (up to the rounding of x + gap)
    assert np.all(gap[far] <= w * np.exp(-np.abs(x[far]) / w) + 1e-15 * np.abs(x[far]))
    rounding = 1e-15 * np.abs(x)        # b + (a - b) is a only up to rounding
    gap = soft.max(x, 0.3 * w, w) - np.maximum(x, 0.3 * w)
    assert np.all(gap >= -rounding) and np.all(gap <= w * LOG2 + tol)
    gap = np.minimum(x, -0.3 * w) - soft.min(x, -0.3 * w, w)
    assert np.all(gap >= -rounding) and np.all(gap <= w * LOG2 + tol)
    gap = np.abs(x) - soft.abs(x, w)
    assert np.all(gap >= 0) and np.all(gap < w)
    assert soft.abs(0.0, w) == 0.0 and np.all(soft.abs(x, w) >= 0)
    s = soft.step(x, w)
    assert np.all((s >= 0) & (s <= 1)) and soft.step(0.0, w) == 0.5
    far = np.abs(x) > w
    assert np.all(np.abs(s - (x > 0))[far] <= np.exp(-np.abs(x[far]) / w) + 3e-16)
    c = soft.clip(x, -2 * w, 3 * w, w)
    assert np.all(np.abs(c - np.clip(x, -2 * w, 3 * w)) <= w * LOG2 + tol)
    rounding = 1e-15 * np.max(np.abs(x))     # l + (x - l) - (x - u) = u up to rounding
    assert np.all((c >= -2 * w - rounding) & (c <= 3 * w + rounding))
    assert np.all(np.diff(soft.clip(np.sort(x), -2 * w, 3 * w, w)) >= -rounding)


# ----------------------------------------------------------------- derivatives
@pytest.mark.parametrize("w", WIDTHS)
@pytest.mark.parametrize("name", list(CASES))
def test_derivatives_match_central_differences(name, w):
    fun = _derivatives(name, w)
    xs = w * np.array([-30.0, -10.0, -3.0, -1.0, -0.25, 0.0, 0.1, 0.5, 1.0, 2.5, 10.0, 30.0])
    v, d1, d2 = _eval(fun, xs)
    h = 1e-4 * w
    vp, d1p, _ = _eval(fun, xs + h)
    vm, d1m, _ = _eval(fun, xs - h)
    np.testing.assert_allclose(d1, (vp - vm) / (2 * h), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(d2, (d1p - d1m) / (2 * h), rtol=1e-6, atol=1e-7 / w)
    # the numpy value agrees with the CasADi one
    np.testing.assert_allclose(CASES[name][0](xs, w), v, rtol=1e-14, atol=1e-15 * w)


@pytest.mark.parametrize("name", list(CASES))
def test_derivatives_are_continuous(name):
    """On a fine grid, the first and second derivatives change by no more than their
    bounded slopes allow: no jump anywhere, the corner included."""
    w = 0.5
    fun = _derivatives(name, w)
    xs = np.linspace(-20 * w, 20 * w, 40001)
    _, d1, d2 = _eval(fun, xs)
    dx = xs[1] - xs[0]
    assert np.max(np.abs(np.diff(d1))) <= np.max(np.abs(d2)) * dx * 1.01
    h = 1e-5 * w
    d3 = (_eval(fun, xs + h)[2] - _eval(fun, xs - h)[2]) / (2 * h)
    assert np.max(np.abs(np.diff(d2))) <= np.max(np.abs(d3)) * dx * 1.01 + 1e-9 / w**2


def test_exact_derivatives_at_the_corner():
    """The algorithmic derivatives at the corner are the smooth function's: the textbook
    stable form max(x, 0) + w log1p(exp(-|x|/w)) gives relu'' = 0 there instead."""
    w = 0.2
    x = ca.SX.sym("x")
    for expr, d1, d2 in [(soft.relu(x, w), 0.5, 1 / (4 * w)),
                         (soft.abs(x, w), 0.0, 1 / w),
                         (soft.step(x, w), 1 / (4 * w), 0.0),
                         (soft.max(x, 0, w), 0.5, 1 / (4 * w)),
                         (soft.min(x, 0, w), 0.5, -1 / (4 * w))]:
        g = ca.jacobian(expr, x)
        f = ca.Function("f", [x], [g, ca.jacobian(g, x)])
        got = [float(v) for v in f(0.0)]
        assert got == pytest.approx([d1, d2], abs=1e-15)
    naive = ca.fmax(x, 0) + w * ca.log1p(ca.exp(-ca.fabs(x) / w))
    g = ca.jacobian(naive, x)
    assert float(ca.Function("f", [x], [ca.jacobian(g, x)])(0.0)) == 0.0


# -------------------------------------------------------------- tails, types
@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("w", WIDTHS)
def test_far_tails_are_finite(name, w):
    xs = np.concatenate([[-1e300], w * np.array([-1e6, -1e3, 1e3, 1e6]), [1e300]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        values = CASES[name][0](xs, w)
    assert np.all(np.isfinite(values))
    exact = CASES[name][1](xs, w)
    np.testing.assert_allclose(values[1:-1], exact[1:-1], rtol=1e-12, atol=w)
    v, d1, d2 = _eval(_derivatives(name, w), xs)
    assert np.all(np.isfinite(v)) and np.all(np.isfinite(d1)) and np.all(np.isfinite(d2))
    np.testing.assert_allclose(v, values, rtol=1e-14)
    # far from the corner the derivative is the exact function's slope
    slope = {"relu": xs > 0, "max": xs > 0, "min": xs < 0, "abs": np.sign(xs),
             "step": 0 * xs, "clip": 0 * xs}[name]
    np.testing.assert_allclose(d1[1:-1], slope[1:-1], atol=1e-6)


def test_relu_tails_exact():
    assert soft.relu(-50.0, 1.0) == pytest.approx(np.exp(-50.0), rel=1e-12)
    assert soft.relu(-1e6, 1.0) == 0.0
    assert soft.relu(1e6, 1.0) == 1e6
    assert soft.relu(40.0, 1.0) == pytest.approx(40.0 + np.exp(-40.0), rel=1e-15)


def test_types_follow_the_argument():
    w = 0.1
    sx, mx = ca.SX.sym("x", 3), ca.MX.sym("x", 3)
    for name, (f, _, _) in CASES.items():
        assert isinstance(f(sx, w), ca.SX), name
        assert isinstance(f(mx, w), ca.MX), name
        assert isinstance(f(ca.DM([0.1, 0.2, 0.3]), w), ca.DM), name
        assert isinstance(f(0.25, w), np.floating), name
        assert f(np.zeros((2, 3)), w).shape == (2, 3), name
        assert f([0.0, 1.0], w).shape == (2,), name
    # CasADi and numpy arguments together: a CasADi expression
    out = soft.max(sx, np.array([0.0, 1.0, 2.0]), w)
    assert isinstance(out, ca.SX) and out.shape == (3, 1)
    got = ca.Function("f", [sx], [out])([0.5, 0.5, 0.5]).full().ravel()
    np.testing.assert_allclose(got, soft.max(0.5, [0.0, 1.0, 2.0], w), rtol=1e-15)
    # broadcasting as numpy does
    assert soft.clip(np.zeros((4, 1)), np.zeros(3) - 1, 1.0, w).shape == (4, 3)


def test_sx_and_mx_give_the_numpy_numbers():
    w = 0.3
    xs = np.linspace(-5, 5, 101)
    for name, (f, _, _) in CASES.items():
        ref = f(xs, w)
        for sym in (ca.SX.sym("x", 101), ca.MX.sym("x", 101)):
            got = ca.Function("f", [sym], [f(sym, w)])(xs).full().ravel()
            np.testing.assert_allclose(got, ref, rtol=1e-14, atol=1e-15, err_msg=name)
        np.testing.assert_allclose(f(ca.DM(xs), w).full().ravel(), ref, rtol=1e-14,
                                   atol=1e-15, err_msg=name)


@pytest.mark.parametrize("width", [0, -1.0, float("nan"), float("inf")])
def test_width_must_be_positive(width):
    for call in CALLS:
        with pytest.raises(ValueError, match="width must be a positive number"):
            call(width)


@pytest.mark.parametrize("width", ["0.1", None, True, ca.SX.sym("w"), [0.1]])
def test_width_must_be_a_number(width):
    for call in CALLS:
        with pytest.raises(TypeError, match="width must be a positive number"):
            call(width)


def test_bad_arguments_are_named():
    with pytest.raises(TypeError, match="x must be numeric"):
        soft.relu("a", 0.1)
    with pytest.raises(TypeError, match="b must be numeric"):
        soft.max(1.0, None, 0.1)
    with pytest.raises(ValueError, match="lower must be less than upper"):
        soft.clip(0.0, 1.0, 1.0, 0.1)
    with pytest.raises(ValueError, match="lower must be less than upper"):
        soft.clip(0.0, [0.0, 2.0], [1.0, 1.0], 0.1)
    with pytest.raises(ValueError, match="upper must be finite"):
        soft.clip(0.0, 0.0, np.inf, 0.1)
    with pytest.raises(ValueError, match="lower must be finite"):
        soft.clip(ca.SX.sym("x"), -np.inf, 1.0, 0.1)
    # symbolic bounds are not checked (a parameter may be a bound)
    p = ca.SX.sym("p")
    assert isinstance(soft.clip(ca.SX.sym("x"), p, p + 1, 0.1), ca.SX)


def test_docstring_examples():
    result = doctest.testmod(soft, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 5 and result.failed == 0


@pytest.mark.parametrize("name", list(CASES))
def test_helpers_raise_no_nonsmoothness_report(name):
    x = ca.SX.sym("x")
    assert _scan(ca.Function("f", [x], [CASES[name][0](x, 0.1)])) == []


# ------------------------------------------------------------------ diagnostic
def _tank(switch: str, width: float = 0.02, integrator: str = "rk4") -> estim.Model:
    """Two tanks in series; tank 1 loses water through a valve that opens at ``h_crit``
    (``if_else``/``step``), an overflow (``fmax``/``relu``) or a capped outlet (``fmin``
    / ``min``)."""
    def ode(x, u, p):
        h1, h2 = x[0], x[1]
        loss = {
            "if_else": lambda: ca.if_else(h1 > p["h_crit"], p["k_v"], 0),
            "step": lambda: p["k_v"] * soft.step(h1 - p["h_crit"], width),
            "fmax": lambda: 2.0 * ca.fmax(h1 - p["h_crit"], 0),
            "relu": lambda: 2.0 * soft.relu(h1 - p["h_crit"], width),
            "fmin": lambda: 0.3 * ca.fmin(h1, p["h_crit"]),
            "min": lambda: 0.3 * soft.min(h1, p["h_crit"], width),
            "input": lambda: ca.if_else(u[0] > 0.6, p["k_v"], 0) * h1,
        }[switch]()
        q12 = 0.5 * ca.sqrt(h1)
        return ca.vertcat(u[0] - q12 - loss, q12 - 0.4 * ca.sqrt(h2))

    return estim.Model(states=["h1", "h2"], outputs=["y1", "y2"], inputs=["q_in"], ode=ode,
                       output=lambda x, u, p: x, params={"h_crit": 1.0, "k_v": 0.3},
                       dt=0.5, lower=[1e-3, 1e-3], integrator=integrator, name=switch)


def _record(model, T=200, seed=1):
    t = np.arange(T) * model.dt
    U = (0.55 + 0.25 * np.sin(2 * np.pi * t / 40))[:, None]
    x, X = np.array([0.8, 1.0]), []
    for k in range(T):
        X.append(x)
        x = model.f(x, U[k])
    X = np.array(X)
    rng = np.random.default_rng(seed)
    return X, U, X + 0.01 * rng.standard_normal(X.shape)


@pytest.mark.parametrize("switch, op, kind", [("fmin", "fmin", "kink"),
                                              ("fmax", "fmax", "kink"),
                                              ("if_else", "if_else", "switch")])
def test_switch_on_a_state_is_reported(switch, op, kind):
    found = nonsmooth_operations(_tank(switch))
    assert found == [NonSmoothOperation(op, "dynamics", kind, ("h1",), (), ("h_crit",), 1)]
    assert found[0].affects_gradient
    assert str(found[0]).startswith(f"{op} in the dynamics ")
    text = advice(found)
    assert f"{op} in the dynamics" in text and "h1" in text
    helper = {"fmin": "estim.soft.min(a, b, width)", "fmax": "estim.soft.max(a, b, width)",
              "if_else": "estim.soft.step(s, width)"}[switch]
    assert helper in text
    # augmented: the estimated threshold is a state now
    aug = nonsmooth_operations(_tank(switch).augment("h_crit"))
    assert [o.states for o in aug] == [("h1", "h_crit")] and aug[0].params == ()


@pytest.mark.parametrize("switch", ["step", "relu", "min"])
def test_smooth_rewrite_reports_nothing(switch):
    model = _tank(switch)
    assert nonsmooth_operations(model) == []
    X, U, _ = _record(model)
    aug = model.augment("h_crit")
    assert nonsmooth_operations(aug) == []
    assert zero_derivative_parameters(aug, np.column_stack([X, np.ones(len(X))]), U) == []
    assert advice(nonsmooth_operations(aug)) == ""


def test_switch_on_an_input_is_harmless():
    found = nonsmooth_operations(_tank("input"))
    assert [(o.operation, o.states, o.inputs) for o in found] == [("if_else", (), ("q_in",))]
    assert not found[0].affects_gradient
    assert str(found[0]) == "if_else in the dynamics switches only on q_in"
    assert advice(found) == ""


def test_comparisons_and_constants():
    def dynamics(x, u, p):
        return ca.vertcat(x[0] + (x[1] > 0) * x[1],           # a comparison used as a number
                          x[1] + ca.fabs(p["c"]) + ca.fabs(-2.0) * ca.floor(u[0]),
                          ca.if_else(ca.logic_and(x[0] > 0, x[1] < 1), x[2], -x[2]))
    model = estim.Model(states=3, outputs=1, inputs=1, dynamics=dynamics,
                        output=lambda x, u, p: ca.sign(x[2]) * x[0], params={"c": -1.0})
    found = {(o.operation, o.where): o for o in nonsmooth_operations(model)}
    assert set(found) == {("comparison", "dynamics"), ("fabs", "dynamics"),
                          ("floor", "dynamics"), ("if_else", "dynamics"), ("sign", "output")}
    assert found["comparison", "dynamics"].states == ("x2",)       # (x[1] > 0) * x[1]
    assert found["fabs", "dynamics"].params == ("c",)               # fabs(-2.0) folded away
    assert not found["fabs", "dynamics"].affects_gradient
    assert found["floor", "dynamics"].inputs == ("u1",)
    # the comparisons inside the if_else condition are reported as the if_else
    assert found["if_else", "dynamics"].states == ("x1", "x2")
    assert found["if_else", "dynamics"].count == 2                   # c ? a : 0 and !c ? b : 0
    assert found["sign", "output"].states == ("x3",)
    text = advice(found.values())
    assert "sign in the output depends on x3" in text
    assert "fabs" not in text and "floor" not in text


def test_cvodes_model_uses_the_continuous_right_hand_side():
    model = _tank("fmin", integrator="cvodes")
    assert not model.F.is_a("SXFunction")
    assert [o.operation for o in nonsmooth_operations(model)] == ["fmin"]


def test_uninspectable_functions_are_skipped():
    cvodes = _tank("fmin", integrator="cvodes")

    class Opaque:   # a discrete model whose map is an integrator call (no SX form)
        state_names, input_names, param_names = cvodes.state_names, ["q_in"], ["h_crit", "k_v"]
        nx, nu = 2, 1
        f_c, F, H = None, cvodes.F, cvodes.H

    assert nonsmooth_operations(Opaque()) == []


MODELS = ["batch_reactor", "lorenz", "martinelli_simple", "odometry_circular",
          "odometry_noncircular", "quadrotor_ko2019", "runaway", "satellite", "satellite_rates",
          "van_der_pol"]


@pytest.mark.parametrize("name", MODELS)
def test_every_library_model_is_smooth(name):
    assert set(MODELS) <= set(estim.models.__all__)
    model = getattr(estim.models, name)()
    assert nonsmooth_operations(model) == []
    if model.param_names:
        assert nonsmooth_operations(model.augment(*model.param_names)) == []


@pytest.mark.parametrize("sensors", ["baro_gnss", "imu", "imu_baro"])
def test_quadrotor_sensor_sets_are_smooth(sensors):
    assert nonsmooth_operations(estim.models.quadrotor_ko2019(sensors)) == []


def test_cvodes_library_model_is_smooth():
    model = estim.models.runaway(integrator="cvodes")
    assert nonsmooth_operations(model.augment(*model.param_names)) == []


def test_library_records_have_no_frozen_parameter():
    rec = estim.scenarios.satellite_inertia()
    assert list(rec.model.augmented) == ["I1", "I2", "I3"]
    assert zero_derivative_parameters(rec.model, rec.x, rec.u) == []
    sc = estim.scenarios.runaway(n_steps=1200)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    assert list(sc.model.augmented) == ["gamma", "gamma1"]
    assert zero_derivative_parameters(sc.model, log.x, log.u) == []


# ------------------------------------------------------------- zero derivative
def _augmented_record(switch):
    model = _tank(switch)
    X, U, Y = _record(_tank("if_else"))
    aug = model.augment("h_crit", "k_v")
    Xa = np.column_stack([X, np.full(len(X), 1.2), np.full(len(X), 0.3)])
    return aug, Xa, U, Y


def test_threshold_inside_if_else_has_zero_derivative():
    aug, Xa, U, _ = _augmented_record("if_else")
    assert Xa[:, 0].max() > 1.0 and Xa[:, 0].min() < 1.0     # the valve opens and closes
    assert zero_derivative_parameters(aug, Xa, U) == ["h_crit"]
    assert zero_derivative_parameters(aug, Xa, U, names=["k_v"]) == []
    assert zero_derivative_parameters(aug, Xa, U[:-1]) == ["h_crit"]      # (T-1, nu) inputs
    # one sample: no transition, so only the output counts (it involves neither)
    assert zero_derivative_parameters(aug, Xa[:1], U[:1]) == ["h_crit", "k_v"]
    text = advice(nonsmooth_operations(aug), ["h_crit"])
    assert "h_crit has a zero derivative" in text
    assert "it sets where if_else in the dynamics switches" in text


def test_smooth_threshold_moves():
    aug, Xa, U, _ = _augmented_record("step")
    assert zero_derivative_parameters(aug, Xa, U) == []


def test_zero_derivative_through_the_output_and_inputs():
    # gain only multiplies an input that is zero on this record: cannot move either
    model = estim.Model(states=["x"], outputs=["y"], inputs=["u"],
                        ode=lambda x, u, p: -x + p["b"] * u[0],
                        output=lambda x, u, p: p["c"] * x, params={"b": 1.0, "c": 2.0}, dt=0.1)
    aug = model.augment("b", "c")
    X = np.column_stack([np.linspace(1, 0.5, 30), np.ones(30), np.full(30, 2.0)])
    assert zero_derivative_parameters(aug, X) == ["b"]
    assert zero_derivative_parameters(aug, X, np.ones(30)) == []
    assert advice([], ["b"]).startswith("some estimated parameters cannot move")


def test_zero_derivative_arguments():
    aug, Xa, U, _ = _augmented_record("if_else")
    with pytest.raises(ValueError, match="names must be augmented parameters"):
        zero_derivative_parameters(aug, Xa, U, names=["h1"])
    with pytest.raises(ValueError, match=r"X must have shape \(T, 4\)"):
        zero_derivative_parameters(aug, Xa[:, :2], U)
    with pytest.raises(ValueError, match="U must have shape"):
        zero_derivative_parameters(aug, Xa, U[:5])
    with pytest.raises(ValueError, match="X must be finite"):
        zero_derivative_parameters(aug, np.full_like(Xa, np.nan), U)
    assert zero_derivative_parameters(_tank("if_else"), Xa[:, :2], U) == []   # not augmented


def test_zero_derivative_is_chunked_not_per_sample(monkeypatch):
    """Long records are mapped in a few calls (bounded memory), with the same answer."""
    import estim._smoothness as mod

    aug, Xa, U, _ = _augmented_record("if_else")
    calls = []
    real = ca.Function.map

    def counting_map(self, *args):
        calls.append(args[0])
        return real(self, *args)

    monkeypatch.setattr(mod, "_CHUNK", 4 * 4 * 64)
    monkeypatch.setattr(ca.Function, "map", counting_map)
    assert zero_derivative_parameters(aug, Xa, U) == ["h_crit"]
    # dF/dx (4 x 4) over 199 samples: a head of 32, then 64 + 64 + 39 (one map of each
    # size); dh/dx (2 x 4) for h_crit, still zero, over 200: 32, then 128 + 40
    assert sorted(calls) == [32, 32, 39, 40, 64, 128]


def test_zero_derivative_stops_when_every_parameter_moved(monkeypatch):
    """A parameter that matters is seen at the first samples: the rest is not evaluated."""
    import estim._smoothness as mod

    aug, Xa, U, _ = _augmented_record("step")   # smooth: h_crit moves everywhere
    calls = []
    real = ca.Function.map

    def counting_map(self, *args):
        calls.append(args[0])
        return real(self, *args)

    monkeypatch.setattr(ca.Function, "map", counting_map)
    assert zero_derivative_parameters(aug, Xa, U) == []
    assert calls == [mod._HEAD]


def test_fit_with_a_threshold_inside_if_else():
    """The measured problem: from the if_else plant's data, the if_else model's threshold
    stays at its guess (zero derivative); the smooth rewrite recovers it."""
    X, U, Y = _record(_tank("if_else"))
    guess = np.column_stack([Y, np.full(len(Y), 1.2)])
    got = {}
    for switch in ("if_else", "step"):
        aug = _tank(switch, width=0.02).augment("h_crit", lower=0.1)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            fie = estim.FullInformation(aug, Q=[1e-6, 1e-6, 1e-10], R=1e-4)
            res = fie.fit(Y, U, guess=guess)
        got[switch] = res.x[0, 2]
        texts = [str(w.message) for w in caught if w.category is estim.EstimationWarning]
        expected = ["h_crit"] if switch == "if_else" else []
        assert zero_derivative_parameters(aug, guess, U) == expected
        if switch == "if_else":
            # at construction: the switch; after the fit: the parameter that never moved
            assert len(texts) == 2 and texts[0].startswith("FullInformation on if_else:")
            assert "estim.soft.step(s, width)" in texts[0]
            assert texts[1].startswith("FullInformation.fit on if_else:") and "h_crit" in texts[1]
            assert res.status == ("inexact: h_crit has a zero derivative over the record "
                                  "and kept the initial value")
        else:
            assert texts == [] and res.status == "ok"
    assert got["if_else"] == 1.2
    assert abs(got["step"] - 1.0) < 0.02


@pytest.mark.parametrize("make", ["MHE", "FullInformation", "ShootingObserver"])
def test_optimisation_estimators_warn_at_construction(make):
    """The warning points at the user's line, names the switch and the smooth form."""
    kwargs = {"MHE": dict(horizon=5, Q=1e-4, R=1e-4, x0=[1.0, 1.0], P0=1.0),
              "FullInformation": dict(Q=1e-4, R=1e-4),
              "ShootingObserver": dict(window=5, every=1, R=1e-4, x0=[1.0, 1.0])}[make]
    with pytest.warns(estim.EstimationWarning,
                      match=f"(?s)^{make} on fmin: .*fmin in the dynamics") as caught:
        getattr(estim, make)(_tank("fmin"), **kwargs)
    assert caught[0].filename == __file__
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        getattr(estim, make)(_tank("min"), **kwargs)   # the smooth rewrite is silent


@pytest.mark.parametrize("name", ["lorenz", "van_der_pol", "batch_reactor",
                                  "runaway", "satellite"])
def test_library_models_raise_no_warning(name):
    model = getattr(estim.models, name)()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        estim.FullInformation(model, Q=np.eye(model.nx) * 1e-3, R=np.eye(model.ny) * 1e-2)


def test_smooth_sqrt_has_a_bounded_slope_and_error():
    """sqrt(x, w): within 0.53 sqrt(w) of sqrt(max(x, 0)), below it for x >= w, its
    derivative finite (at most 0.35 / sqrt(w)) where the exact one is infinite; the same
    numbers on CasADi symbols as on numpy arrays."""
    from estim import soft

    for w in (1e-2, 1e-4):
        x = np.linspace(-1.0, 10.0, 200_001)
        exact = np.sqrt(np.maximum(x, 0.0))
        approx = soft.sqrt(x, w)
        assert np.abs(approx - exact).max() < 0.533 * np.sqrt(w)
        assert (approx[x >= w] <= exact[x >= w]).all()
        assert np.gradient(approx, x).max() < 0.35 / np.sqrt(w)
        h = ca.SX.sym("h")
        f = ca.Function("f", [h], [soft.sqrt(h, w), ca.jacobian(soft.sqrt(h, w), h)])
        value, slope = (float(v) for v in f(0.0))
        assert value == pytest.approx(float(soft.sqrt(0.0, w)), rel=1e-14)
        assert np.isfinite(slope) and slope < 0.35 / np.sqrt(w)
