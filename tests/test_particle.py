"""The bootstrap particle filter against the exact Kalman filter (filterpy), and its
resampling, seeding, recovery and argument checks: interpreted and compiled
(``jit=True``) alike, through the ``PF`` fixture."""

from __future__ import annotations

import functools
import pickle

import casadi as ca
import numpy as np
import pytest
from linear_gaussian import P0, X0, A, Q, R, kalman, linear_model, record

import estim
from estim._compile import compiler
from estim.solvers.sampling.resampling import RESAMPLING, effective_sample_size, resample


@pytest.fixture(params=[False, True], ids=["interpreted", "compiled"])
def PF(request):
    """``estim.ParticleFilter`` interpreted, and compiled (``jit=True``)."""
    if request.param and compiler() is None:
        pytest.skip("no C compiler")
    return functools.partial(estim.ParticleFilter, jit=request.param)


def test_means_agree_with_the_kalman_filter_within_monte_carlo_error(PF):
    """Over independent seeds, the particle filter's mean at every sample equals the
    exact posterior mean within 3 standard errors of the seeds' average."""
    Y = record(20)
    x_kf, P_kf, _ = kalman(Y)
    m = linear_model()
    runs = np.array([PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=500,
                                          seed=s).filter(Y).x for s in range(40)])
    se = runs.std(axis=0, ddof=1) / np.sqrt(len(runs))
    z = (runs.mean(axis=0) - x_kf) / se
    # 40 comparisons: the largest |z| of 40 standard normals is below 3.5 in 98 % of
    # cases; the seeds are fixed, so the test is deterministic
    assert np.abs(z).max() < 3.5, np.abs(z).max()
    # and each run's mean is close to the posterior mean for its particle count:
    # the spread over seeds is of the order of sqrt(P / N)
    ratio = runs.std(axis=0, ddof=1) / np.sqrt(np.diagonal(P_kf, axis1=1, axis2=2) / 500)
    assert 0.5 < np.median(ratio) < 3.0


def test_likelihood_estimate_is_unbiased(PF):
    """E[exp(log L_hat - log L)] = 1 (Del Moral 2004): the mean over 200 seeds within
    3 standard errors of 1."""
    Y = record(15, seed=4)
    _, _, ll = kalman(Y)
    m = linear_model()
    ratios = np.array([np.exp(PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=200,
                                                   seed=s).filter(Y).log_likelihood - ll)
                       for s in range(200)])
    se = ratios.std(ddof=1) / np.sqrt(len(ratios))
    assert abs(ratios.mean() - 1.0) < 3 * se, (ratios.mean(), se)


def test_seeded_runs_are_identical_and_reset_restarts_the_stream(PF):
    m, Y = linear_model(), record(10)
    a = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, seed=7)
    b = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, seed=7)
    ra, rb = a.filter(Y), b.filter(Y)
    assert np.array_equal(ra.x, rb.x) and np.array_equal(ra.P, rb.P)
    assert np.array_equal(a.filter(Y).x, ra.x)  # filter resets
    c = pickle.loads(pickle.dumps(a))
    assert np.array_equal(c.filter(Y).x, ra.x)
    other = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, seed=8)
    assert not np.array_equal(other.filter(Y).x, ra.x)
    # step by step (replay) gives what filter gives
    log = estim.replay(a, Y)
    assert np.array_equal(np.asarray(log.x_hat), ra.x)


def test_step_reports_ess_likelihood_and_missing_outputs(PF):
    m = linear_model()
    pf = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=400, seed=0)
    pf.step(np.array([0.3]))
    info = pf.info
    assert info.status == "ok" and 1.0 <= info.extra["ess"] <= 400
    assert np.isfinite(info.extra["log_likelihood"]) and np.isfinite(info.nis)
    assert info.P.shape == (2, 2) and np.all(np.linalg.eigvalsh(info.P) > 0)
    x = pf.step(np.array([np.nan]))  # nothing measured: the weights do not change
    assert np.isfinite(x).all() and pf.info.extra["log_likelihood"] == 0.0
    assert np.isnan(pf.info.nis) and pf.info.status == "ok"


def test_collapse_is_suspect_and_nonfinite_weights_reanchor(PF):
    m = linear_model()
    pf = PF(m, Q=Q, R=1e-10, x0=X0, P0=P0, n_particles=50, seed=0)
    pf.step(np.array([0.5]))
    assert pf.info.status.startswith("suspect: effective sample size")
    assert pf.info.success

    def capped(y, yhat, p):  # a log-density with bounded support: |y - yhat| < 5
        return ca.if_else(ca.fabs(y[0] - yhat[0]) < 5, -0.5 * (y[0] - yhat[0]) ** 2, -ca.inf)

    pf = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=200, loglik=capped)
    pf.step(np.array([0.1]))
    x = pf.step(np.array([1e3]))  # no particle, and no re-anchored one, can explain it
    assert pf.info.status.startswith("failed: every particle weight is zero")
    assert not pf.info.success and np.isfinite(x).all()
    pf.step(np.array([0.2]))
    assert pf.info.success


def test_custom_log_densities(PF):
    """Student-t and Laplace measurement noise (the docstring's examples) run and give
    finite estimates; a Gaussian written by hand equals the built-in one."""
    m, Y = linear_model(), record(10)

    def student(y, yhat, p, nu=3.0, s=0.3):
        e = (y[0] - yhat[0]) / s
        return -(nu + 1) / 2 * ca.log1p(e ** 2 / nu)

    def laplace(y, yhat, p, b=0.3):
        return -ca.fabs(y[0] - yhat[0]) / b

    for ll in (student, laplace):
        r = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300,
                                 loglik=ll).filter(Y)
        assert r.success and np.isfinite(r.x).all()

    def gauss(y, yhat, p):
        return -0.5 * (y[0] - yhat[0]) ** 2 / R[0, 0] - 0.5 * np.log(2 * np.pi * R[0, 0])

    a = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, loglik=gauss)
    b = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300)
    ra, rb = a.filter(Y), b.filter(Y)
    assert np.allclose(ra.x, rb.x, rtol=0, atol=1e-10)
    assert ra.log_likelihood == pytest.approx(rb.log_likelihood, abs=1e-9)


@pytest.mark.parametrize("scheme", RESAMPLING)
def test_resampling_is_unbiased_and_skips_zero_weights(scheme):
    rng = np.random.default_rng(0)
    W = np.array([0.0, 0.5, 0.05, 0.0, 0.3, 0.15])
    counts = np.zeros(len(W))
    n_draws = 4000
    for _ in range(n_draws):
        idx = resample(W, scheme, rng, n=20)
        assert idx.shape == (20,) and idx.min() >= 0 and idx.max() < len(W)
        counts += np.bincount(idx, minlength=len(W))
    assert counts[0] == counts[3] == 0
    mean = counts / n_draws
    # each count has variance at most 20 W (1 - W) (multinomial, the largest)
    se = np.sqrt(20 * W * (1 - W) / n_draws)
    assert np.all(np.abs(mean - 20 * W) <= 4 * se + 1e-12)
    if scheme in ("systematic", "residual"):  # at least floor(n W) copies
        idx = resample(W, scheme, rng, n=20)
        assert np.all(np.bincount(idx, minlength=len(W)) >= np.floor(20 * W))
    assert effective_sample_size(np.full(8, 1 / 8)) == pytest.approx(8.0)


def test_bad_arguments_are_named():
    m = linear_model()
    kw = dict(Q=Q, R=R, x0=X0, P0=P0)
    with pytest.raises(ValueError, match="n_particles"):
        estim.ParticleFilter(m, n_particles=1, **kw)
    for bad in (2.5, True, "100"):
        with pytest.raises(TypeError, match="n_particles"):
            estim.ParticleFilter(m, n_particles=bad, **kw)
    with pytest.raises(ValueError, match="did you mean 'systematic'"):
        estim.ParticleFilter(m, resampling="systematc", **kw)
    for bad in (0.0, 1.5, -0.1):
        with pytest.raises(ValueError, match="ess_threshold"):
            estim.ParticleFilter(m, ess_threshold=bad, **kw)
    with pytest.raises(TypeError, match="loglik"):
        estim.ParticleFilter(m, loglik="gaussian", **kw)
    with pytest.raises(ValueError, match="scalar"):
        estim.ParticleFilter(m, loglik=lambda y, yhat, p: ca.vertcat(y, yhat), **kw)
    with pytest.raises(TypeError, match="seed"):
        estim.ParticleFilter(m, seed=1.5, **kw)
    with pytest.raises(ValueError, match="P0"):
        estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=None)


def _smoothed_like_rts(PF, Q_, Y):
    """20 seeds of ``PF.smooth`` (1000 particles, 300 paths) on the linear model with
    process noise ``Q_``, checked against filterpy's Rauch-Tung-Striebel smoother: the
    seeds' mean within 3.5 standard errors at every sample and state (40 comparisons: a
    false alarm for about 2 % of seed sets), the paths' spread of the smoother's size.
    Returns the runs."""
    from filterpy.kalman import rts_smoother

    x_kf, P_kf, _ = kalman(Y, Q=Q_)
    # filterpy's smoother takes the filtered means and covariances of its own filter
    xs, Ps, _, _ = rts_smoother(x_kf, P_kf, [A] * len(Y), [Q_] * len(Y))
    runs = [PF(linear_model(), Q=Q_, R=R, x0=X0, P0=P0, n_particles=1000,
               seed=s).smooth(Y, n_paths=300) for s in range(20)]
    means = np.array([r.x for r in runs])
    se = means.std(axis=0, ddof=1) / np.sqrt(len(means))
    assert np.abs((means.mean(axis=0) - xs) / se).max() < 3.5
    spread = np.median([np.diagonal(r.P, axis1=1, axis2=2) / np.diagonal(Ps, axis1=1, axis2=2)
                        for r in runs])
    assert 0.5 < spread < 2.0, spread
    return runs


def test_backward_simulation_matches_the_rts_smoother(PF):
    """Forward-filtering backward-simulation: over 20 seeds, the smoothed means equal
    filterpy's Rauch-Tung-Striebel smoother within 3.5 standard errors of the seeds'
    average (40 comparisons), and the paths' covariance is of the smoother's size."""
    Y = record(20, seed=2)
    runs = _smoothed_like_rts(PF, Q, Y)
    assert runs[0].paths.shape == (300, 20, 2)
    with pytest.raises(ValueError, match="n_paths"):
        PF(linear_model(), Q=Q, R=R, x0=X0, P0=P0).smooth(Y, n_paths=0)


def test_backward_simulation_with_noise_on_one_state_is_exact(PF):
    """Process noise on the velocity only (``Q = diag(0, 1e-2)``, the position integrates
    it exactly): the transition density is degenerate, and every smoothed path obeys
    :math:`p_{k+1} = p_k + 0.1 v_k` to the last bit; over 20 seeds the means equal
    filterpy's Rauch-Tung-Striebel smoother (which takes a singular Q) within 3.5
    standard errors (40 comparisons: a false alarm about 2 % of seeds sets), and the
    paths' spread is of the smoother's size."""
    Qs = np.diag([0.0, 1e-2])
    Y = record(20, seed=2)
    runs = _smoothed_like_rts(PF, Qs, Y)
    for r in runs:
        p = r.paths
        assert np.array_equal(p[:, 1:, 0], p[:, :-1, 0] + 0.1 * p[:, :-1, 1])
    m = linear_model()
    # the filter's forward pass is kept, with the record's times and the state names
    assert np.array_equal(runs[0].x_filtered, PF(m, Q=Qs, R=R, x0=X0, P0=P0, n_particles=1000,
                                                 seed=0).filter(Y).x)
    assert runs[0].state_names == ("p", "v") and runs[0].t[1] == m.dt


def test_linearised_proposal_is_exact_on_a_linear_output(PF):
    """With a linear output the "ekf" proposal is the optimal one: the means still agree
    with the Kalman filter within Monte Carlo error, and with precise measurements
    (R = 1e-3) the likelihood estimate varies far less than the bootstrap filter's."""
    Y = record(15, seed=5)
    m = linear_model()
    x_kf, _, _ = kalman(Y)
    runs = np.array([PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300,
                                          proposal="ekf", seed=s).filter(Y).x
                     for s in range(30)])
    se = runs.std(axis=0, ddof=1) / np.sqrt(len(runs))
    assert np.abs((runs.mean(axis=0) - x_kf) / se).max() < 3.5
    Rp = np.array([[1e-3]])
    Yp = record(15, seed=5, r=Rp[0, 0])
    lls = {prop: np.array([PF(m, Q=Q, R=Rp, x0=X0, P0=P0, n_particles=200,
                                                proposal=prop, seed=s).filter(Yp).log_likelihood
                           for s in range(30)]) for prop in ("bootstrap", "ekf")}
    # an F-test at the 0.1 % level: the linearised proposal's variance is smaller
    from scipy import stats
    ratio = lls["ekf"].var(ddof=1) / lls["bootstrap"].var(ddof=1)
    assert ratio < stats.f.ppf(0.001, 29, 29), ratio
    with pytest.raises(ValueError, match="Q must be positive definite"):
        PF(m, Q=np.diag([0.0, 1e-2]), R=R, x0=X0, P0=P0, proposal="ekf")
    with pytest.raises(ValueError, match="did you mean 'ekf'"):
        PF(m, Q=Q, R=R, x0=X0, P0=P0, proposal="ekff")


def test_compare_is_deterministic_in_any_number_of_jobs(PF):
    """The same seeds give the same particle filter runs in one process or two workers."""
    sc = estim.scenarios.van_der_pol(n_steps=40)

    def pf(model, tuning):
        return PF(model, n_particles=200, seed=3, **tuning)

    one = estim.compare(sc, {"pf": pf}, seeds=range(3), n_jobs=1)
    two = estim.compare(sc, {"pf": pf}, seeds=range(3), n_jobs=2)
    assert np.array_equal(one.rmse["pf"], two.rmse["pf"])
    assert one.rows[0].failures == 0 and 0.3 < one.rows[0].nees_mean < 3.0


def test_particles_outside_the_bounds_get_no_weight(PF):
    """The model's bounds are the state's support: on the batch reactor (concentrations
    that cannot be negative, a guess far off and tiny process noise) every estimate stays
    inside them and the run neither fails nor raises, where without them the cloud follows
    a negative concentration whose dynamics diverge (estimates beyond 1e100)."""
    sc = estim.scenarios.batch_reactor()
    pf = PF(sc.model, n_particles=300, **sc.tuning)
    log = estim.simulate(sc, pf, seed=0)
    x_hat = np.asarray(log.x_hat)
    assert np.all(x_hat >= 0.0) and np.isfinite(x_hat).all()
    assert pf.lower.tolist() == [0.0, 0.0, 0.0]
    free = PF(sc.model, n_particles=300, lower=-np.inf, **sc.tuning)
    assert np.isinf(free.lower).all()
    with pytest.raises(ValueError, match="lower must not exceed upper"):
        PF(sc.model, lower=1.0, upper=0.0, **sc.tuning)
    # a collapsed cloud's covariance is singular: its NEES is infinite, not an error
    from estim.metrics import nees_values
    assert np.isinf(nees_values(np.ones((1, 3)), np.zeros((1, 3, 3))))[0]


def test_unscented_proposal(PF):
    """The "ukf" proposal (spherical-cubature moments of the output over N(F(x), Q)) is
    the "ekf" one when the output is linear: the same particles and weights from the
    same seed, to rounding. On the growth model's quadratic output y = x^2/20 it is a
    valid importance sampler (its likelihood estimates agree with the bootstrap
    filter's within their Monte Carlo error) that keeps more effective particles."""
    Y = record(15, seed=5)
    m = linear_model()
    kw = dict(Q=Q, R=R, x0=X0, P0=P0, n_particles=200, seed=3)
    ekf = PF(m, proposal="ekf", **kw).filter(Y)
    for rule in ({}, {"points": "gauss-hermite", "order": 3}, {"points": "cubature5"}):
        ukf = PF(m, proposal="ukf", **kw, **rule).filter(Y)  # every rule: the same moments
        np.testing.assert_allclose(ukf.x, ekf.x, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ukf.log_likelihood, ekf.log_likelihood, rtol=1e-9)
    g = estim.Model(states=["x"], inputs=["t"], outputs=["y"],
                    dynamics=lambda x, u, p: x / 2 + 25 * x / (1 + x**2) + 8 * ca.cos(1.2 * u[0]),
                    output=lambda x, u, p: x**2 / 20)
    rng = np.random.default_rng(7)
    x, ys = rng.normal(0.0, 2.0), []
    for t in range(30):
        if t:
            x = x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * (t - 1)) + rng.normal(0, 10**0.5)
        ys.append(x**2 / 20 + rng.normal())
    Yg, Ug = np.array(ys)[:, None], np.arange(29.0)[:, None]
    rules = {"bootstrap": {"proposal": "bootstrap"}, "ukf": {"proposal": "ukf"},
             "gh5": {"proposal": "ukf", "points": "gauss-hermite", "order": 5}}
    out = {name: [PF(g, Q=10.0, R=1.0, x0=[0.0], P0=4.0, n_particles=500, seed=s,
                     **rule).filter(Yg, Ug) for s in range(20)]
           for name, rule in rules.items()}
    ll = {k: np.array([r.log_likelihood for r in v]) for k, v in out.items()}
    assert all(r.success for v in out.values() for r in v)
    for name in ("ukf", "gh5"):  # each a valid importance sampler (3 se of the difference)
        se = np.sqrt(ll["bootstrap"].var(ddof=1) / 20 + ll[name].var(ddof=1) / 20)
        assert abs(ll[name].mean() - ll["bootstrap"].mean()) < 3 * se
    # the proposal follows the measurement: more effective particles (measured: 276
    # against 192 of 500 on average)
    ess = {k: np.mean([r.ess.mean() for r in v]) for k, v in out.items()}
    assert ess["ukf"] > 1.2 * ess["bootstrap"], ess
    with pytest.raises(ValueError, match="Q must be positive definite"):
        PF(m, Q=np.diag([0.0, 1e-2]), R=R, x0=X0, P0=P0, proposal="ukf")
    with pytest.raises(ValueError, match="give proposal='ukf'"):
        PF(m, Q=Q, R=R, x0=X0, P0=P0, points="gauss-hermite")
    with pytest.raises(ValueError, match=r"\(rules of positive weights\), got 'merwe'"):
        PF(m, Q=Q, R=R, x0=X0, P0=P0, proposal="ukf", points="merwe")
    five = estim.Model(states=5, outputs=1, dynamics=lambda x, u, p: x,
                       output=lambda x, u, p: x[0])
    with pytest.raises(ValueError, match="negative weights beyond four states"):
        PF(five, Q=1.0, R=1.0, x0=np.zeros(5), P0=1.0, proposal="ukf", points="cubature5")


def test_particles_whose_state_is_lost_get_no_weight(PF):
    """A transition that is not finite for part of the cloud (the square root of a
    negative state) zeroes those particles' weights: the estimates stay finite and every
    step succeeds, with all the weight on particles whose state is a number."""
    m = estim.Model(states=["x"], outputs=["y"], dynamics=lambda x, u, p: ca.sqrt(x) + 1.0,
                    output=lambda x, u, p: x)
    Y = np.array([[np.nan], [2.4], [2.5], [2.6], [2.6]])  # (half the cloud below 0 first)
    pf = PF(m, Q=0.01, R=0.04, x0=[0.0], P0=4.0, n_particles=400, seed=1)
    res = pf.filter(Y)
    assert res.success and np.isfinite(res.x).all() and np.isfinite(res.P).all()
    X, W = pf.particles
    assert np.isfinite(X).all() and np.isclose(W.sum(), 1.0)
    assert abs(res.x[-1, 0] - 2.6) < 0.2


def test_a_seed_per_call(PF):
    """``filter(Y, seed=k)`` and ``smooth(..., seed=k)``: independent runs of one record
    without touching the constructor's seed (the next reset starts its stream again);
    the same seed, the same run; ``smooth`` keeps the forward pass's whole result."""
    m, Y = linear_model(), record(30)
    pf = PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, seed=7)
    base = pf.filter(Y)
    runs = [pf.filter(Y, seed=k) for k in (11, 12, 11)]
    assert np.array_equal(runs[0].x, runs[2].x)
    assert not np.array_equal(runs[0].x, runs[1].x)
    assert not np.array_equal(runs[0].x, base.x)
    assert pf.seed == 7 and np.array_equal(pf.filter(Y).x, base.x)
    assert PF(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, seed=11).filter(Y).log_likelihood \
        == runs[0].log_likelihood
    sm = pf.smooth(Y, n_paths=20, seed=11)
    assert sm.filtered.log_likelihood == runs[0].log_likelihood
    assert np.array_equal(sm.filtered.x, sm.x_filtered)
    with pytest.raises(TypeError, match="seed"):
        pf.filter(Y, seed="one")


def test_rejection_draws_the_backward_distribution():
    """The backward draws by rejection (candidates from the weights, accepted with the
    transition density over its maximum) have the direct draw's distribution
    :math:`P(i) \\propto W_i N(x_{t+1}; F(x^i), Q)`: 40 000 draws for one successor
    against the exact probabilities, a chi-square test at 1e-3 (false alarm 0.1 %)."""
    from scipy import stats

    from estim.estimators.sampling.particle_smoothing import _rejection

    rng = np.random.default_rng(3)
    N, n = 12, 40_000
    X = rng.normal(size=(1, N))
    W = rng.random(N)
    W /= W.sum()
    LQ_inv = np.array([[1 / 0.7]])
    Z = LQ_inv @ X  # predictions F(x) = x
    paths = np.zeros((n, 2, 1))
    paths[:, 1] = 0.3  # the successor
    pending = _rejection(paths, 0, X, W, Z, LQ_inv, rng)
    assert pending.size < 0.01 * n
    picks = paths[np.setdiff1d(np.arange(n), pending), 0, 0]
    p = W * np.exp(-0.5 * ((0.3 - X[0]) / 0.7) ** 2)
    p /= p.sum()
    counts = np.array([(picks == x).sum() for x in X[0]])
    assert stats.chisquare(counts, p * counts.sum()).pvalue > 1e-3
