"""Tuning is data: changing Q, R, P0 never rebuilds a compiled graph, and gives what a
freshly built estimator gives."""

from __future__ import annotations

import numpy as np
import pytest

import estim

SC = estim.scenarios.van_der_pol(n_steps=60)
NEW = {"Q": [0.02, 0.005], "R": [0.5, 2.0]}


def _built(est):
    """The compiled functions an estimator holds (to see that none is rebuilt)."""
    if isinstance(est, (estim.EKF, estim.UKF)):
        return [est._update, est._predict_update]
    if isinstance(est, estim.MHE):
        return [est._nlp, est._cov_step] + list(est._nlp.gn._funs.values())
    if isinstance(est, estim.FullInformation):
        return list(est._nlps.values())
    if isinstance(est, estim.ShootingObserver):
        return [est._J, est._terms, est._sens]
    return [est._F, est._H]


MAKERS = {
    "ekf": lambda **t: estim.EKF(SC.model, **t),
    "ukf": lambda **t: estim.UKF(SC.model, **t),
    "mhe gauss-newton": lambda **t: estim.MHE(SC.model, horizon=8, solver="gauss-newton", **t),
    "mhe ipopt": lambda **t: estim.MHE(SC.model, horizon=8, solver="ipopt", **t),
    "mhe fixed": lambda **t: estim.MHE(SC.model, horizon=8, solver="gauss-newton",
                                       arrival_cost="fixed", **t),
    "fie": lambda **t: estim.FullInformation(SC.model, **t),
    "shooting": lambda **t: estim.ShootingObserver(SC.model, window=6, every=1, R=t["R"],
                                                   x0=t["x0"], P0=t["P0"]),
}


@pytest.mark.parametrize("name", list(MAKERS))
def test_set_tuning_equals_a_fresh_estimator_and_rebuilds_nothing(name):
    make = MAKERS[name]
    est = make(**SC.tuning)
    estim.simulate(SC, est, seed=0)
    before = _built(est)
    est.set_tuning(**NEW, P0=[2.0, 0.5])
    after = estim.simulate(SC, est, seed=1)
    assert all(a is b for a, b in zip(before, _built(est), strict=False))
    fresh = estim.simulate(SC, make(**{**SC.tuning, **NEW, "P0": [2.0, 0.5]}), seed=1)
    np.testing.assert_allclose(after.x_hat, fresh.x_hat, rtol=0, atol=1e-12)


def test_fit_takes_the_tuning_per_call():
    log = estim.simulate(SC, estim.EKF(SC.model, **SC.tuning), seed=0)
    fie = estim.FullInformation(SC.model, **SC.tuning)
    fie.fit(log.y)
    problems = dict(fie._nlps)
    per_call = fie.fit(log.y, Q=NEW["Q"], R=NEW["R"])
    fresh = estim.FullInformation(SC.model, **{**SC.tuning, **NEW}).fit(log.y)
    np.testing.assert_allclose(per_call.x, fresh.x, rtol=0, atol=1e-10)
    assert per_call.cost == pytest.approx(fresh.cost, rel=1e-12)
    assert all(fie._nlps[k] is v for k, v in problems.items())
    # the estimator's own tuning is unchanged
    np.testing.assert_array_equal(fie.Q, SC.tuning["Q"] * np.eye(2))
    np.testing.assert_allclose(fie.fit(log.y).x, fie.fit(log.y).x)


def test_set_tuning_adds_a_prior_to_full_information():
    log = estim.simulate(SC, estim.EKF(SC.model, **SC.tuning), seed=0)
    fie = estim.FullInformation(SC.model, Q=0.01, R=1.0)
    with pytest.raises(ValueError, match="P0 was given without x0"):
        fie.set_tuning(P0=1.0)
    fie.set_tuning(x0=[0.0, 0.0], P0=1.0)
    ref = estim.FullInformation(SC.model, Q=0.01, R=1.0, x0=[0.0, 0.0], P0=1.0).fit(log.y)
    np.testing.assert_allclose(fie.fit(log.y).x, ref.x, rtol=0, atol=1e-10)


def test_a_diagonal_estimator_takes_a_diagonal_tuning_only():
    est = estim.MHE(SC.model, horizon=5, solver="gauss-newton", **SC.tuning)
    with pytest.raises(ValueError, match="Q must be diagonal: MHE was built with a diagonal Q"):
        est.set_tuning(Q=[[0.01, 0.001], [0.001, 0.01]])
    full = estim.EKF(SC.model, **{**SC.tuning, "R": [[1.0, 0.1], [0.1, 1.0]]})
    full.set_tuning(R=[[1.0, 0.3], [0.3, 1.0]])  # built full: any structure
    with pytest.raises(ValueError, match="Q must keep the rank it had when MHE was built"):
        est.set_tuning(Q=[0.01, 0.0])
    with pytest.raises(TypeError, match="R must be numeric"):
        est.set_tuning(R="large")


def test_tuning_corners_are_reported():
    """ALS reports a filter that diverges on the record as a failed status and refuses a
    constant record; maximum likelihood names kappa when the UKF's sigma points break and
    refuses a record with fewer values than free parameters."""
    from estim.tuning import als, maximum_likelihood

    sc = estim.scenarios.get("van_der_pol", n_steps=400)
    log = estim.simulate(sc, None, seed=0)
    guess = dict(x0=sc.tuning["x0"], P0=sc.tuning["P0"])
    Y = log.y.copy()
    Y[200:] = 1e150
    res = als(sc.model, Y, Q0=0.01, R0=1.0, **guess)
    assert not res.success and res.status.startswith("failed: the filter with Q0, R0 diverged")
    with pytest.raises(ValueError, match=r"Y is constant in every output \['y1', 'y2'\]"):
        als(sc.model, np.ones((400, 2)), **guess)
    with pytest.raises(ValueError, match="kappa must make nx \\+ kappa positive .* got -5"):
        maximum_likelihood(sc.model, log.y, estimator="ukf", kappa=-5, **guess)
    with pytest.raises(ValueError, match="Y has 4 measured values after the burn-in for 4 "
                                         "free parameters"):
        maximum_likelihood(sc.model, log.y[:2], **guess)


def test_maximum_likelihood_says_when_starts_end_at_different_optima():
    """A rotation's frequency from 300 noisy samples of its cosine: the likelihood in the
    frequency is a comb of local optima, and starts spread from a wrong guess end at
    several of them (none at the truth, 0.5). The result says so in ``status`` and lists
    them in ``details["optima"]``, where one start alone would report a confident "ok";
    starts within the truth's own basin (the comb's teeth are about 2 pi / 300 = 0.02
    apart) agree and the status stays "ok"."""
    import casadi as ca

    def rotation(x, u, p):
        w = p["omega"]
        return ca.vertcat(ca.cos(w) * x[0] - ca.sin(w) * x[1],
                          ca.sin(w) * x[0] + ca.cos(w) * x[1])

    m = estim.Model(states=2, outputs=1, dynamics=rotation, output=lambda x, u, p: x[0],
                    params={"omega": 0.5})
    rng = np.random.default_rng(0)
    Y = (np.cos(0.3 + 0.5 * np.arange(300)) + rng.normal(0, 0.3, 300))[:, None]
    kw = dict(Q0=1e-6 * np.eye(2), R0=0.09, structure={"Q": "fixed", "R": "fixed"},
              x0=[1.0, 0.0], P0=np.eye(2))
    res = estim.tuning.maximum_likelihood(m, Y, params={"omega": 1.3}, starts=6,
                                          param_spread=0.5, **kw)
    assert len(res.details["optima"]) >= 2 and "multimodal" in res.status
    assert res.details["optima"][0] == pytest.approx(res.objective)
    near = estim.tuning.maximum_likelihood(m, Y, params={"omega": 0.505}, starts=4,
                                           param_spread=0.002, **kw)
    assert near.status == "ok" and len(near.details["optima"]) == 1
    # (the cosine of a rotation by -omega is the same output: the sign is not identified)
    assert abs(abs(near.params["omega"]) - 0.5) < 3 * near.stderr["params"]["omega"]
