"""The Gauss-Hermite rule of the UKF: exact moments, the points it draws, what it
refuses and what it warns about."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest
from linear_gaussian import P0, X0, Q, R, kalman, linear_model, record

import estim
from estim.estimators.kalman.ukf import gauss_hermite


@pytest.mark.parametrize("n,order", [(1, 1), (1, 4), (2, 3), (3, 5)])
def test_the_rule_integrates_polynomials_exactly(n, order):
    """E[prod x_i^a_i] under N(0, I) for every exponent up to 2p - 1 per coordinate:
    the product of the one-dimensional Gaussian moments (0 for odd, (a - 1)!! for even)."""
    unit, W = gauss_hermite(n, order)
    assert unit.shape == (n, order ** n) and W.shape == (order ** n,)
    assert W.sum() == pytest.approx(1.0, abs=1e-14) and (W > 0).all()

    def moment(a: int) -> float:
        return 0.0 if a % 2 else float(np.prod(np.arange(a - 1, 0, -2))) if a else 1.0

    for exps in itertools.product(range(2 * order), repeat=n):
        terms = W * np.prod(unit ** np.array(exps)[:, None], axis=0)
        exact = float(np.prod([moment(a) for a in exps]))
        # to rounding of the sum: relative to its largest term
        assert abs(float(terms.sum()) - exact) <= 1e-13 * max(1.0, np.abs(terms).sum()), exps


def test_on_a_linear_model_it_is_the_kalman_filter():
    Y = record(25, seed=4)
    x_kf, P_kf, _ = kalman(Y)
    ukf = estim.UKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, points="gauss-hermite", order=3)
    log = estim.replay(ukf, Y)
    np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-12)
    pts = ukf.sigma_points(X0, P0)
    assert pts.shape == (9, 2)
    np.testing.assert_allclose(ukf._Wm @ pts, X0, atol=1e-15)


def test_what_is_refused_and_warned():
    m = linear_model()
    kw = {"Q": Q, "R": R, "x0": X0, "P0": P0}
    with pytest.raises(ValueError, match="order must be"):
        estim.UKF(m, **kw, points="gauss-hermite", order=0)
    with pytest.raises(ValueError, match="points must be one of"):
        estim.UKF(m, **kw, points="hermite")
    seven = estim.Model(states=7, outputs=1, dynamics=lambda x, u, p: x,
                        output=lambda x, u, p: x[0])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(Exception):  # noqa: B017 - the warning is the point, not the build
            estim.UKF(seven, Q=1.0, R=1.0, x0=np.zeros(7), P0=1.0, points="gauss-hermite",
                      order=5, jit="no")
    assert any("5^7 = 78125 sigma points" in str(w.message) for w in caught)


def test_jit_and_the_c_export_carry_the_rule(tmp_path):
    from estim._compile import compiler

    if compiler() is None:
        pytest.skip("no C compiler")
    from test_codegen import CFilter, _close

    from estim import codegen

    sc = estim.scenarios.book_pendulum(n_steps=80)
    log = estim.simulate(sc, None, seed=0)
    ghkf = estim.UKF(sc.model, **sc.tuning, points="gauss-hermite", order=4)
    ref = estim.replay(ghkf, log.y)
    compiled = estim.replay(estim.UKF(sc.model, **sc.tuning, points="gauss-hermite", order=4,
                                      jit=True), log.y)
    np.testing.assert_array_equal(compiled.x_hat, ref.x_hat)
    codegen.export(ghkf, tmp_path, name="ghkf")
    out = CFilter(ghkf, tmp_path, "ghkf").run(log.y, None)
    assert _close(out["x"], ref.x_hat) <= 1e-12 and _close(out["P"], ref.P) <= 1e-12


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_the_fifth_degree_rule_integrates_every_quintic(n):
    """points="cubature5": 2n^2 + 1 points, exact for every monomial of total degree up
    to 5 (and not for every one of degree 6), negative axis weights beyond 4 states."""
    from estim.estimators.kalman.ukf import cubature5

    unit, W = cubature5(n)
    assert unit.shape == (n, 2 * n * n + 1) and W.sum() == pytest.approx(1.0, abs=1e-14)

    def moment(a: int) -> float:
        return 0.0 if a % 2 else float(np.prod(np.arange(a - 1, 0, -2))) if a else 1.0

    for exps in itertools.product(range(6), repeat=n):
        if sum(exps) > 5:
            continue
        terms = W * np.prod(unit ** np.array(exps)[:, None], axis=0)
        exact = float(np.prod([moment(a) for a in exps]))
        assert abs(float(terms.sum()) - exact) <= 1e-12 * max(1.0, np.abs(terms).sum()), exps
    sixth = float(np.sum(W * unit[0] ** 6))
    assert n == 1 or abs(sixth - 15.0) > 1e-6  # degree 6 is beyond the rule
    assert (W < 0).any() == (n > 4)


def test_the_fifth_degree_filter_on_a_linear_model_is_the_kalman_filter():
    Y = record(25, seed=6)
    x_kf, P_kf, _ = kalman(Y)
    log = estim.replay(estim.UKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0,
                                 points="cubature5"), Y)
    np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-12)


@pytest.mark.parametrize("points,order", [("gauss-hermite", 3), ("gauss-hermite", 4),
                                          ("cubature5", 3)])
def test_the_square_root_form_draws_the_same_rules(points, order):
    """The square-root UKF's points :math:`x + S \\xi_i` from the factor itself give the
    covariance form's estimates on van der Pol (to rounding), and the Kalman filter on
    the linear model."""
    vdp = estim.scenarios.van_der_pol(n_steps=150)
    Y = estim.simulate(vdp, None, seed=0, warn=False).y
    kw = {"points": points, "order": order}
    a = estim.UKF(vdp.model, **vdp.tuning, **kw).filter(Y)
    b = estim.UKF(vdp.model, **vdp.tuning, **kw, form="sqrt").filter(Y)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.P, a.P, rtol=0, atol=1e-12)
    assert set(b.status) == {"ok"}
    Yl = record(25, seed=6)
    x_kf, P_kf, _ = kalman(Yl)
    log = estim.replay(estim.UKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, form="sqrt",
                                 **kw), Yl)
    np.testing.assert_allclose(log.x_hat, x_kf, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.P, P_kf, rtol=0, atol=1e-12)


def test_the_rules_on_a_unit_quaternion():
    """Gauss-Hermite and fifth-degree points in the tangent space of a unit quaternion
    (the multiplicative UKF, ``x (+) S xi``), both forms: the whole-record call is the
    step loop, the two forms agree to rounding and track the attitude as the Merwe points
    do (mean error over the last 20 samples within 1 % of theirs)."""
    from test_attitude import scenario

    sc = scenario(T=80)
    truth = estim.simulate(sc, None, seed=0)
    err = {}
    for points in ("merwe", "gauss-hermite", "cubature5"):
        res = {}
        for form in ("covariance", "sqrt"):
            ukf = estim.UKF(sc.model, **sc.tuning, points=points, form=form)
            res[form] = ukf.filter(truth.y, sc.inputs)
            log = estim.replay(ukf, truth.y, sc.inputs)
            np.testing.assert_allclose(res[form].x, log.x_hat, rtol=0, atol=1e-12)
            assert set(res[form].status) == {"ok"}
        np.testing.assert_allclose(res["sqrt"].x, res["covariance"].x, rtol=0, atol=1e-10)
        angle = np.linalg.norm(estim.errors(res["covariance"], truth=truth), axis=1)
        err[points] = angle[-20:].mean()
    assert err["gauss-hermite"] == pytest.approx(err["merwe"], rel=0.01)
    assert err["cubature5"] == pytest.approx(err["merwe"], rel=0.01)
