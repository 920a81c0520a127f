"""Standard errors, correlations and intervals of identified parameters (estim.uncertainty).

References: the Fisher information of ``estim.observability.window`` (an independent
computation of the same matrix), exact definitions (residual scaling, quantiles), and a
seeded Monte Carlo coverage study whose tolerances come from the binomial distribution.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from scipy import stats

import estim
from estim.observability import window

T = 100
SIGMA = 0.05
TRUTH = np.array([0.0, 1.0, 2.0])           # x0, tau, K
Q_THETA = 1e-12                              # a constant parameter (see the docs)
Q = Q_THETA * np.array([1.0, 1.0, 4.0])


def first_order(**kwargs) -> estim.Model:
    """dx/dt = (K u - x) / tau, y = x, with tau and K as states."""
    m = estim.Model(states=["x"], outputs=["y"], inputs=["u"],
                    ode=lambda x, u, p: (p["K"] * u[0] - x[0]) / p["tau"],
                    output=lambda x, u, p: x[0], params={"tau": 1.0, "K": 2.0}, dt=0.1,
                    name="first_order")
    return m.augment("tau", "K", **kwargs)


@pytest.fixture(scope="module")
def setup():
    aug = first_order()
    U = np.where((np.arange(T - 1) // 25) % 2 == 0, 1.0, -1.0)[:, None]
    x, X = TRUTH.copy(), []
    for k in range(T):
        X.append(x)
        if k < T - 1:
            x = aug.f(x, U[k])
    y_true = np.array(X)[:, :1]
    fie = estim.FullInformation(aug, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4])
    return aug, U, y_true, fie


def _record(y_true, seed):
    return y_true + SIGMA * np.random.default_rng(seed).standard_normal(y_true.shape)


def test_the_parameters_block_of_the_last_covariance(setup):
    aug, U, y_true, fie = setup
    res = fie.fit(_record(y_true, 0), U)
    pe = res.parameters()
    assert pe.names == ("tau", "K") and pe.scale == "none" and pe.dof is None
    np.testing.assert_array_equal(pe.value, res.x[-1, 1:])
    np.testing.assert_allclose(pe.covariance, res.P_last[1:, 1:], rtol=1e-12)
    s = np.sqrt(np.diag(res.P_last)[1:])
    np.testing.assert_allclose(pe.stderr, s, rtol=1e-12)
    assert pe.correlation[0, 1] == pytest.approx(res.P_last[1, 2] / (s[0] * s[1]))
    np.testing.assert_allclose(pe.interval(0.95), np.column_stack(
        [pe.value - 1.959963984540054 * s, pe.value + 1.959963984540054 * s]), rtol=1e-12)
    assert pe.issues == ()
    # the shortcuts of FitResult and the function say the same
    assert res.params == pe.params == {"tau": pe.value[0], "K": pe.value[1]}
    assert res.stderr == {"tau": s[0], "K": s[1]}
    assert res.confidence(0.9)["K"] == pytest.approx(tuple(pe.interval(0.9)[1]))
    np.testing.assert_array_equal(estim.parameter_uncertainty(res).covariance, pe.covariance)
    table = pe.summary()
    assert "tau" in table and "correlation" in table and repr(pe) == table
    df = pe.to_pandas(0.9)
    assert list(df.index) == ["tau", "K"]
    np.testing.assert_allclose(df[["lower", "upper"]].to_numpy(), pe.interval(0.9))


def test_agrees_with_the_fisher_information_of_the_window(setup):
    """As q -> 0 the fit's Laplace covariance of the constant parameters is the inverse
    Fisher information of (x0, theta) from observability.window (an independent
    computation: the sensitivities of the noise-free simulation from the fitted x0),
    reduced to theta; with a prior, of F + P0^-1. The random walk allowed to the
    parameter states adds a little, less than its unobserved growth (T-1) q."""
    aug, U, y_true, _ = setup
    Y = _record(y_true, 1)
    P0 = np.array([1.0, 0.25, 1.0])
    for q in (1e-10, 1e-12):
        for prior in (None, P0):
            fie = estim.FullInformation(aug, Q=q * Q / Q_THETA, R=SIGMA**2,
                                        x0=[0.0, 0.7, 1.4], P0=prior)
            res = fie.fit(Y, U)
            F = window(aug, x0=res.x[0], n_steps=T - 1, inputs=U, R=SIGMA**2).fisher
            if prior is not None:
                F = F + np.diag(1 / prior)
            expected = np.linalg.inv(F)[1:, 1:]
            excess = np.diag(res.parameters().covariance - expected) \
                / ((T - 1) * q * Q[1:] / Q_THETA)
            assert np.all((excess > 0) & (excess < 1)), (q, excess)
            if q == 1e-12:
                np.testing.assert_allclose(res.parameters().covariance, expected, rtol=2e-6)


def test_residual_scaling(setup):
    aug, U, y_true, fie = setup
    res = fie.fit(_record(y_true, 2), U)
    known, scaled = res.parameters(), res.parameters(scale="residual")
    nu = T - aug.nx                     # measured values minus the unknown x0
    s2 = res.cost / nu
    assert scaled.dof == nu and scaled.residual_variance == pytest.approx(s2)
    assert known.residual_variance == pytest.approx(s2)
    np.testing.assert_allclose(scaled.covariance, s2 * known.covariance, rtol=1e-12)
    half = stats.t.ppf(0.975, nu) * scaled.stderr
    np.testing.assert_allclose(scaled.interval(), np.column_stack(
        [scaled.value - half, scaled.value + half]), rtol=1e-12)
    # with the right R the residual variance is about 1: chi-square(nu)/nu
    assert abs(s2 - 1) < 4 * np.sqrt(2 / nu)


def test_poorly_determined_parameters_warn(setup):
    aug, U, y_true, fie = setup
    res = fie.fit(_record(y_true, 0)[:4], U[:3])      # four samples of a slow response
    with pytest.warns(estim.EstimationWarning, match="observability.window") as record:
        pe = res.parameters()
    message = str(record[0].message)
    assert "tau" in message and "K" in message and "correlation" in message
    assert record[0].filename == __file__
    assert any("relative standard error" in i for i in pe.issues)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        quiet = res.parameters(warn=False)
        assert quiet.issues == pe.issues
        fie.fit(_record(y_true, 0), U).parameters()    # the whole record: no warning
    with pytest.warns(estim.EstimationWarning) as record:
        estim.parameter_uncertainty(res)
    assert record[0].filename == __file__


def test_a_combination_the_data_do_not_fix_is_named():
    """Three parameters, each pair correlated below 0.99, whose sum is nearly fixed: the
    near-singular block names the combination (in standard errors) that the data
    determine far better than each parameter."""
    from estim.uncertainty import _issues

    v = np.array([1.0, 1.0, 1.0]) / np.sqrt(3)
    C = np.eye(3) - (1 - 1e-5) * np.outer(v, v)      # correlations -0.5, eigenvalue 1e-5
    issues = _issues(("a", "b", "c"), np.array([10.0, 20.0, 30.0]), C, [-np.inf] * 3,
                     [np.inf] * 3)
    assert len(issues) == 1 and "near-singular" in issues[0], issues
    assert "+1.00·a +1.00·b +1.00·c" in issues[0].replace("-", "+")
    assert _issues(("a",), np.array([1.0]), np.array([[np.nan]]), [0.0], [2.0])[0].startswith(
        "the covariance is not finite")


def test_a_parameter_at_its_bound_is_reported(setup):
    aug, U, y_true, _ = setup
    bounded = first_order(upper={"tau": 0.9})
    res = estim.FullInformation(bounded, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4]).fit(
        _record(y_true, 0), U)
    assert res.x[-1, 1] == pytest.approx(0.9)
    with pytest.warns(estim.EstimationWarning, match="at a bound"):
        res.parameters()


def test_mhe_and_filters(setup):
    aug, U, y_true, _ = setup
    Y = _record(y_true, 3)
    mhe = estim.MHE(aug, horizon=20, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4], P0=[1.0, 1.0, 1.0])
    for k in range(T):
        x_hat = mhe.step(Y[k], U[k - 1] if k else None)
    pe = estim.parameter_uncertainty(mhe)
    np.testing.assert_array_equal(pe.value, x_hat[1:])
    np.testing.assert_array_equal(pe.covariance, mhe.info.P[1:, 1:])
    assert np.all(np.abs(pe.value - TRUTH[1:]) < 4 * pe.stderr)
    # any estimator's record, through the model
    ekf = estim.EKF(aug, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4], P0=[1.0, 1.0, 1.0])
    for k in range(T):
        x_hat = ekf.step(Y[k], U[k - 1] if k else None)
    pe = estim.parameter_uncertainty(aug, x_hat, ekf.info.P)
    np.testing.assert_array_equal(pe.stderr, np.sqrt(np.diag(ekf.info.P)[1:]))
    with pytest.raises(ValueError, match="pass x"):
        estim.parameter_uncertainty(ekf)
    # full information run step by step: its last estimate and info.P
    fie = estim.FullInformation(aug, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4])
    for k in range(30):
        x_hat = fie.step(Y[k], U[k - 1] if k else None)
    pe = estim.parameter_uncertainty(fie, warn=False)
    np.testing.assert_array_equal(pe.value, x_hat[1:])
    np.testing.assert_array_equal(pe.covariance, fie.info.P[1:, 1:])
    with pytest.raises(ValueError, match="scale='residual' needs a FitResult"):
        estim.parameter_uncertainty(mhe, scale="residual")


def test_bad_input(setup):
    aug, U, y_true, fie = setup
    res = fie.fit(_record(y_true, 0), U)
    with pytest.raises(ValueError, match="scale"):
        res.parameters(scale="relative")
    with pytest.raises(ValueError, match="level"):
        res.parameters().interval(1.5)
    with pytest.raises(ValueError, match="level"):
        res.confidence(0)
    with pytest.raises(TypeError, match="source"):
        estim.parameter_uncertainty(res.x)
    with pytest.raises(ValueError, match="x .* and P .* are required"):
        estim.parameter_uncertainty(aug)
    with pytest.raises(ValueError, match="P must have shape"):
        estim.parameter_uncertainty(aug, res.x[-1], np.eye(2))
    with pytest.raises(ValueError, match="x"):
        estim.parameter_uncertainty(aug, [1.0, 2.0], np.eye(3))
    with pytest.raises(TypeError, match="scal"):
        estim.parameter_uncertainty(res, scal="residual")
    plain = estim.Model(states=["x"], outputs=["y"], ode=lambda x, u, p: -x,
                        output=lambda x, u, p: x, dt=0.1)
    fit = estim.FullInformation(plain, Q=1e-6, R=1.0).fit(np.ones((5, 1)))
    with pytest.raises(ValueError, match="no augmented parameters"):
        fit.parameters()
    with pytest.raises(ValueError, match="no augmented parameters"):
        _ = fit.params
    mhe = estim.MHE(aug, horizon=5, Q=Q, R=SIGMA**2, x0=[0.0, 0.7, 1.4], P0=1.0)
    with pytest.raises(ValueError, match="no covariance"):
        estim.parameter_uncertainty(mhe, x=np.zeros(3))    # no step yet


def test_monte_carlo_coverage(setup):
    """95 % intervals over 1000 seeds of the first-order model (a fit and its covariance
    take about 1 ms).

    Tolerances: a correct interval covers the truth in a Binomial(n, 0.95) number of
    seeds, of standard error sqrt(0.95 * 0.05 / n) = 0.69 % at n = 1000; the required
    95 ± 3 % is then 4.4 standard errors wide (a correct method fails it with
    probability 1e-5). It misses standard errors too large by up to 15 % (coverage
    97.6 %); the second check does not: the empirical standard deviation of n estimates
    has a relative standard error 1/sqrt(2(n-1)) = 2.2 %, and the mean standard error
    must match it within 10 % (4.5 of those). The joint 95 % ellipsoid of (tau, K) checks
    the correlation too, with the coverage's tolerance.
    """
    aug, U, y_true, fie = setup
    n, theta = 1000, TRUTH[1:]
    chi2 = stats.chi2.ppf(0.95, 2)
    hits, joint, values, stderrs = [], [], [], []
    for seed in range(n):
        res = fie.fit(_record(y_true, seed), U)
        assert res.success
        pe = res.parameters()
        lo, hi = pe.interval(0.95).T
        hits.append((lo <= theta) & (theta <= hi))
        err = pe.value - theta
        joint.append(err @ np.linalg.solve(pe.covariance, err) <= chi2)
        values.append(pe.value)
        stderrs.append(pe.stderr)
    coverage = np.mean(hits, axis=0)
    assert np.all(np.abs(coverage - 0.95) <= 0.03), coverage
    assert abs(np.mean(joint) - 0.95) <= 0.03, np.mean(joint)
    ratio = np.mean(stderrs, axis=0) / np.std(values, axis=0, ddof=1)
    assert np.all(np.abs(ratio - 1) <= 0.10), ratio
