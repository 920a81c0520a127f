"""Shooting observer: a zero start is no obstacle, and a step is "ok" only when it converged.

Van der Pol with ``mu`` augmented (``model.augment("mu")``), every state and the parameter
starting at 0 (where the origin is an equilibrium and ``mu`` has no effect on the outputs),
both states measured with noise std 0.1, no process noise, windows of 20 samples every 2
steps. The reference is scipy's ``least_squares`` on the same window (an independent
propagation with ``model.f``); its Jacobian gives the standard errors.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from scipy.optimize import least_squares

import estim
from estim.estimators.window import shooting

W, N, R = 20, 2, 0.1**2
TRUTH = [1.5, 1.5, 1.0]


@cache
def _model():
    return estim.models.van_der_pol().augment("mu")


def _observer(**kw):
    base = dict(window=W, every=N, R=R, x0=[0.0, 0.0, 0.0], derivative_weight=0.0)
    base.update(kw)
    return estim.ShootingObserver(_model(), **base)


@cache
def _simulated(seed: int):
    log = estim.simulate(_model(), _observer(), x0=TRUTH, n_steps=80, Q=0.0, R=R, seed=seed)
    return log.y.copy(), log.x.copy()


def _record(seed: int):
    return _simulated(seed)[0]


def _run(obs, y):
    """Step through ``y``; the (status, iterations, window start) of every optimisation."""
    out = []
    obs.reset()
    for yk in y:
        obs.step(yk)
        if obs.info.extra.get("optimised"):
            out.append((obs.info.status, obs.info.iterations,
                        obs.info.extra["window_start"].copy()))
    return out


def _least_squares(y, k, start):
    """The window ending at sample k fitted by scipy: (optimum, standard errors)."""
    model, span = _model(), (W - 1) * N
    Y = y[k - span:k + 1:N]

    def residuals(xi):
        x, out = xi.copy(), []
        for j in range(span + 1):
            if j % N == 0:
                out.append((Y[j // N] - model.h(x)) / np.sqrt(R))
            if j < span:
                x = model.f(x)
        return np.concatenate(out)

    fit = least_squares(residuals, start, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return fit.x, np.sqrt(np.diag(np.linalg.inv(fit.jac.T @ fit.jac)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_parameter_starting_at_zero_reaches_the_window_optimum(seed):
    """Defaults (BFGS, resolution=None): from (0, 0, 0) the last window's optimum is
    reached. Tolerance from the stopping rule, not tuned: BFGS stops when the gradient
    in the whitened coordinates z (Hessian I, so a unit of z is one standard error
    over sqrt 2) is below sqrt(2 tol) in every component; the distance left is then at
    most sqrt(n) sqrt(2 tol) in z, i.e. sqrt(n tol) standard errors in each component."""
    y = _record(seed)
    obs = _observer()
    runs = _run(obs, y)
    k = obs.history[-1]["k"]
    status, _, start = runs[-1]
    assert status == "ok"
    optimum, sd = _least_squares(y, k, _simulated(seed)[1][k - (W - 1) * N])
    assert abs(optimum[2]) > 10 * sd[2]  # mu is far from its start of 0 in noise units
    tol = np.sqrt(3 * obs.tol) * sd
    np.testing.assert_array_less(np.abs(start - optimum), tol)


def test_zero_start_is_judged_on_the_windows_own_estimate():
    """With a resolution, a component starting at 0 has no magnitude of its own; its
    scale is the window's Gauss-Newton estimate, so mu (determined to ~5 %) moves with
    resolution=0.1 (before: it was never optimised). A direction left out is said."""
    y, x = _simulated(0)
    obs = _observer(resolution=0.1)
    runs = _run(obs, y)
    status, _, start = runs[-1]
    k = obs.history[-1]["k"]
    optimum, sd = _least_squares(y, k, x[k - (W - 1) * N])
    assert abs(start[2] - optimum[2]) < sd[2]  # as good as the window can tell
    for status, _, _ in runs:
        assert status == "ok" or status.startswith("inexact: "), status
        if "left out" in status:
            assert "of 3 directions left out (not determined to the resolution 0.1)" in status


def test_nothing_determined_is_inexact_and_keeps_the_estimate():
    """resolution=0.01: mu is determined to ~5 %, the states to a few %, so no direction
    passes; the estimate stays at the (equilibrium) start and every step says so."""
    y = _record(0)
    runs = _run(_observer(resolution=0.01), y)
    assert runs
    for status, iterations, start in runs:
        assert status.startswith(
            "inexact: no direction determined to the resolution 0.01 (0 of 3)"), status
        assert iterations == 0 and not start.any()


@pytest.mark.parametrize("method", shooting.METHODS)
def test_a_capped_optimisation_is_never_ok(method):
    """One iteration from (0, 0, 0) cannot reach the optimum: the step is usable but
    "inexact", for every method."""
    runs = _run(_observer(method=method, max_iter=1), _record(0)[:(W - 1) * N + 1])
    (status, _, _), = runs
    assert status.startswith("inexact: "), status
    assert "max_iter" in status or "Maximum" in status


def test_every_ok_step_passed_the_gradient_test():
    """At every step reported "ok" the decrease the Gauss-Newton model still predicts,
    g' H^-1 g / 2, is below the n tol that the gradient test allows."""
    y = _record(1)
    obs = _observer()
    ok = 0
    obs.reset()
    for yk in y:
        obs.step(yk)
        if obs.info.extra.get("optimised") and obs.info.status == "ok":
            Y, Yd, U, WY = obs._window_data()
            args = (U, Y, np.zeros_like(Yd), 0.0, np.zeros(3), np.zeros(9), WY)
            x = obs.info.extra["window_start"]
            g = obs._J(x, *args)[1]
            assert 0.5 * g @ np.linalg.solve(obs._hessian(x, args), g) <= 3 * obs.tol
            ok += 1
    assert ok > 10


def _fake_minimize(status, x=None):
    """scipy's minimize, with its result's status (and optionally x) replaced."""
    real = shooting.scipy_minimize

    def minimize(fun, x0, **kw):
        res = real(fun, x0, **kw)
        res.status = status
        if x is not None:
            res.x = np.full_like(res.x, x)
            res.fun, res.jac = fun(res.x) if kw.get("jac") else (fun(res.x), None)
        return res
    return minimize


@pytest.mark.parametrize(("method", "status", "x", "expected"), [
    ("bfgs", 1, None, "inexact: max_iter (100) reached"),
    ("bfgs", 2, None, "inexact: line search stalled (precision loss) before the gradient test"),
    ("lbfgsb", 2, 0.0, "inexact: line search stalled before the gradient test"),
    ("bfgs", 2, np.nan, "failed: non-finite cost at the method's point"),
])
def test_scipy_stops_before_the_gradient_test_are_not_ok(monkeypatch, method, status, x,
                                                          expected):
    """BFGS's precision loss (status 2) or max_iter (1), L-BFGS-B stopping where it started:
    usable, so "inexact"; a non-finite point: "failed", and the estimate is kept."""
    y = _record(0)[:(W - 1) * N + 1]
    monkeypatch.setattr(shooting, "scipy_minimize", _fake_minimize(status, x))
    obs = _observer(method=method, x0=[1.0, 1.0, 0.5])
    runs = _run(obs, y)
    (got, _, _), = runs
    assert got.startswith(expected), got
    assert obs.info.success == (not expected.startswith("failed"))
