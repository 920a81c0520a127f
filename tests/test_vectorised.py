"""SX Functions evaluated over many points by numpy operations (estim._vectorised) give
CasADi's own values."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim
from estim._vectorised import vectorised


@pytest.mark.parametrize("name", ["lorenz", "van_der_pol", "batch_reactor", "satellite"])
def test_model_maps_equal_casadi(name):
    m = getattr(estim.models, name)()
    rng = np.random.default_rng(0)
    n = 64
    X = np.abs(rng.standard_normal((m.nx, n))) + 0.1  # positive: square roots, logs
    W = rng.standard_normal((m.nw, n)) if m.nw else np.zeros((0, n))
    p = np.asarray(m.p, float).ravel()
    for fun, args in ((m.F, (X, W, p)), (m.H, (X, W[:m.nu], p)), (m.F_x, (X, W, p))):
        g = vectorised(fun)
        assert g is not None, fun.name()
        ours = g(*args, n=n)[0]
        ref = np.column_stack([fun(X[:, i], args[1][:, i], p).nonzeros()  # (sparse F_x)
                               for i in range(n)])
        assert ours.shape == ref.shape
        np.testing.assert_allclose(ours, ref, rtol=1e-13, atol=1e-13)


def test_operations_and_broadcasting():
    x, y = ca.SX.sym("x"), ca.SX.sym("y", 2)
    outs = [x + y[0], x - y[1], x * y[0], x / y[1], -x, 2 * x, x ** 2, 1 / x, ca.sqrt(x),
            ca.exp(x), ca.log(x), x ** y[0], x ** 3, ca.sin(x), ca.cos(x), ca.tan(x),
            ca.atan2(x, y[0]), ca.fabs(y[0]), ca.sign(y[0]), ca.fmin(x, y[0]),
            ca.fmax(x, y[0]), ca.floor(y[0]), ca.ceil(y[0]), ca.fmod(y[0], x),
            x < y[0], x <= y[0], x == y[0], x != y[0], ca.logic_not(y[0] > 0),
            ca.logic_and(x > 0.5, y[0] > 0), ca.logic_or(x > 0.5, y[0] > 0),
            ca.if_else(y[0] > 0, x, y[1]), ca.erf(x), ca.tanh(x), ca.log1p(x), ca.expm1(x),
            ca.hypot(x, y[0]), ca.copysign(x, y[0]), ca.SX(3.5), ca.SX(np.inf)]
    f = ca.Function("f", [x, y], [ca.vertcat(*outs), ca.SX(2, 1)])
    g = vectorised(f)
    assert g is not None
    rng = np.random.default_rng(1)
    n = 50
    X = np.abs(rng.standard_normal((1, n))) + 0.2
    Y = np.array([1.0, -2.0])  # the same at every point
    got = g(X, Y, n=n)
    ref = np.column_stack([np.asarray(f(X[:, i], Y)[0]).ravel() for i in range(n)])
    np.testing.assert_allclose(got[0], ref, rtol=1e-14, atol=1e-15)
    assert got[1].shape == (0, n)  # an output without nonzeros


def test_unsupported_functions_give_none():
    x = ca.MX.sym("x")
    assert vectorised(ca.Function("m", [x], [ca.sin(x)])) is None  # an MX Function
    s = ca.SX.sym("s")
    inner = ca.Function("inner", [s], [s ** 2], {"never_inline": True})
    outer = ca.Function("outer", [s], [inner(s) + 1])
    assert vectorised(outer) is None  # a call of another Function
