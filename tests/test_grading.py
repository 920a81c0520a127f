"""estim.grading: a hand-written Kalman filter graded against estim's, and what the
messages say when it is wrong on purpose."""

from __future__ import annotations

import numpy as np
import pytest

import estim
from estim.adapters import from_function
from estim.grading import (
    as_log,
    check_arrays,
    check_consistent,
    check_filter,
    check_over_seeds,
    from_steps,
)

F = np.array([[1.0, 0.1], [0.0, 1.0]])
H = np.array([[1.0, 0.0]])
Q, R = np.diag([1e-3, 1e-2]), np.array([[0.1]])
X0, P0 = np.zeros(2), np.eye(2)
EQUATIONS = {"P": "the prediction P = F P Fᵀ + Q (eq. 2) and the update P = (I - K H) P "
                  "(eq. 5)",
             "x": "the update x̂ = x̄ + K (y - H x̄) (eq. 4)"}


def model() -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"],
                       dynamics=lambda x, u, p: F @ x, output=lambda x, u, p: H @ x)


def student(mistake: str | None = None) -> estim.Estimator:
    """A student's numpy Kalman filter (update at the first sample, then predict-update),
    with an optional mistake."""
    held: dict = {}

    def reset():
        held["x"], held["P"], held["k"] = X0.copy(), P0.copy(), 0

    def step(y, u):
        x, P = held["x"], held["P"]
        if held["k"]:
            x = F @ x
            P = F @ P @ F.T + (0 if mistake == "no Q" else Q)
        if mistake == "raises" and held["k"] == 3:
            raise ValueError("matrices not aligned")
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        e = y - H @ x
        x = x + K @ (-e if mistake == "sign" else e)
        P = (np.eye(2) - K @ H) @ P
        if mistake == "half P":
            P = 0.5 * P
        held["x"], held["P"], held["k"] = x, P, held["k"] + 1
        return x, P

    reset()
    return from_function(step, model(), name="your filter", reset=reset)


def scenario() -> estim.Scenario:
    return estim.Scenario("tracking", model(), x0=[0.0, 1.0], n_steps=60, Q=Q, R=R,
                          tuning={"Q": Q, "R": R, "x0": X0, "P0": P0})


def reference() -> estim.Estimator:
    return estim.EKF(model(), Q=Q, R=R, x0=X0, P0=P0)


@pytest.fixture(scope="module")
def record():
    log = estim.simulate(scenario(), None, seed=0)
    return log.y, None


def test_a_right_filter_passes(record):
    text = check_filter(student(), reference(), record, equations=EQUATIONS)
    assert "equals the reference on all 60 samples" in text


@pytest.mark.parametrize("mistake, quantity, sample, hint", [
    ("no Q", "the covariance P", 1, "eq. 2"),
    ("sign", "the estimate x̂", 0, "eq. 4"),
    ("half P", "the covariance P", 0, "eq. 5")])
def test_a_wrong_filter_is_told_where_and_what(record, mistake, quantity, sample, hint):
    with pytest.raises(AssertionError) as info:
        check_filter(student(mistake), reference(), record, equations=EQUATIONS)
    text = str(info.value)
    assert f"{quantity} differs first at sample {sample}" in text and hint in text
    if mistake == "sign":
        assert "the covariance P is right at every sample" in text


def test_a_filter_without_covariance_is_told_of_its_estimate_only(record):
    est = student("sign")
    mine = from_function(lambda y, u: np.asarray(est.step(y, u))[:2], model(),
                         name="your filter", reset=est.reset)
    with pytest.raises(AssertionError) as info:
        check_filter(mine, reference(), record, equations=EQUATIONS)
    text = str(info.value)
    assert "the estimate x̂ differs first at sample 0" in text and "covariance" not in text


def test_an_exception_is_reported_with_its_sample(record):
    with pytest.raises(AssertionError, match="raised ValueError at sample 3: matrices"):
        check_filter(student("raises"), reference(), record)


def test_over_seeds_and_consistency():
    sc = scenario()
    assert "as accurate as the reference" in check_over_seeds(
        student(), reference(), sc, seeds=range(10))
    assert "matches its errors" in check_consistent(student(), sc, seeds=range(20))
    with pytest.raises(AssertionError, match="too small for its errors"):
        check_consistent(student("half P"), sc, seeds=range(20))


def test_from_steps_is_the_textbook_loop(record):
    """Two functions (predict, update) in estim's loop equal the Kalman filter, with the
    prior one step before the first measurement (a NaN first row) and a missing sample."""
    Y = np.vstack([[np.nan], record[0]])
    Y[7] = np.nan
    mine = from_steps(model(), lambda x, P: (F @ x, F @ P @ F.T + Q),
                      lambda x, P, y: _update(x, P, y), X0, P0)
    ref = reference().filter(Y)
    log = estim.replay(mine, Y)
    np.testing.assert_allclose(log.x_hat, ref.x, rtol=0, atol=1e-12)
    np.testing.assert_allclose(log.P, ref.P, rtol=0, atol=1e-12)
    assert "equals the reference on all 61 samples" in check_filter(
        mine, reference(), (Y, None))
    # a predict that returns nothing yet is told as such, with its sample
    blank = from_steps(model(), lambda x, P: None, _update, X0, P0)
    with pytest.raises(AssertionError, match="at sample 1: predict must return the pair "
                                             r"\(x, P\), got nothing \(not answered yet"):
        check_filter(blank, reference(), (Y, None))
    with pytest.raises(TypeError, match="predict must be callable"):
        from_steps(model(), None, _update, X0, P0)
    with pytest.raises(ValueError, match="P0 must be 2 x 2"):
        from_steps(model(), _update, _update, X0, np.eye(3))


def _update(x, P, y):
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    return x + K @ (y - H @ x), P - K @ S @ K.T


def test_check_arrays_names_the_first_entry_and_the_equation():
    ref = np.arange(12.0).reshape(3, 2, 2)
    assert "equals the reference" in check_arrays(ref + 1e-10, ref, quantity="the gains")
    wrong = ref.copy()
    wrong[1, 0, 1] += 0.5
    wrong[2, 1, 1] -= 1.0
    with pytest.raises(AssertionError) as info:
        check_arrays(wrong, ref, quantity="the gains", equation="eq. (7)", index="sample")
    assert str(info.value).startswith("the gains differs first at sample 1, entry (0, 1): "
                                      "yours 5.5, the reference 5. Look at eq. (7). (2 of "
                                      "12 entries differ")
    with pytest.raises(AssertionError, match=r"differs first at entry \(1, 0, 1\): yours 5.5"):
        check_arrays(wrong, ref, quantity="the gains")
    with pytest.raises(AssertionError, match=r"has shape \(3, 4\), expected \(3, 2, 2\)"):
        check_arrays(ref.reshape(3, 4), ref, quantity="the gains")
    for blank in (None, ...):
        with pytest.raises(AssertionError, match="not answered yet"):
            check_arrays(blank, ref, quantity="the gains")
    with pytest.raises(AssertionError, match="expected numbers, got str"):
        check_arrays("gains", ref, quantity="the gains")


def test_as_log_draws_a_students_arrays(tmp_path):
    """A student's means and covariances as a log: estim's metrics and figures take it."""
    pytest.importorskip("matplotlib")
    from estim.plotting import plot_errors, plot_particles

    sc = scenario()
    truth = estim.simulate(sc, reference(), seed=1)
    log = as_log(truth.x_hat, truth.P, truth=truth.x, model=model())
    np.testing.assert_allclose(estim.nees(log), estim.nees(truth), rtol=1e-12)
    np.testing.assert_allclose(log.t, truth.t)
    plot_errors(log, tmp_path / "errors.png")
    assert (tmp_path / "errors.png").stat().st_size > 0
    with pytest.raises(ValueError, match="truth must have the estimates' shape"):
        as_log(truth.x_hat, truth.P, truth=truth.x[:-1])
    # a particle cloud: (T, N, nx), its weights and the truth
    rng = np.random.default_rng(0)
    cloud = truth.x[:, None, :] + rng.normal(size=(60, 300, 2))
    w = rng.random((60, 300))
    fig = plot_particles(cloud, tmp_path / "cloud.png", weights=w / w.sum(1, keepdims=True),
                         truth=truth.x, t=truth.t, state=1, name="v")
    assert fig.axes[0].get_ylabel() == "v" and (tmp_path / "cloud.png").stat().st_size > 0
    with pytest.raises(ValueError, match=r"weights must be \(T, N\)"):
        plot_particles(cloud, weights=w[:, :10])
    with pytest.raises(ValueError, match="state must be in 0..1"):
        plot_particles(cloud, state=2)


def test_a_filter_that_fails_on_most_seeds_is_told_so():
    """A filter whose estimates are NaN (a transposed Jacobian blows up) is not a
    ValueError of the paired test but an answer that says so."""
    def broken(model, tuning):
        return from_function(lambda y, u: np.full(2, np.nan), model, name="your filter")

    with pytest.raises(AssertionError, match="has no finite estimates on 10 of 10 seeds"):
        check_over_seeds(broken, reference(), scenario(), seeds=range(10))
    with pytest.raises(AssertionError, match=r"median RMSE \S+ against the reference's "
                                             r"\S+: \d+% worse\)"):
        check_over_seeds(student("sign"), reference(), scenario(), seeds=range(10))
    text = check_over_seeds(student(), reference(), scenario(), seeds=range(10),
                            tolerance=1e-6)
    assert "within 1e-06 × the reference's median over 10 seeds" in text


def test_the_students_own_loop_is_checked_against_the_same_run(record):
    """``loop=``: the arrays of the student's whole-record function, checked once the
    steps are right, against the reference's samples after the prior's row."""
    Y = np.vstack([[np.nan], record[0]])
    ref = reference().filter(Y)
    mine = from_steps(model(), lambda x, P: (F @ x, F @ P @ F.T + Q), _update, X0, P0)
    assert "so does your loop" in check_filter(mine, reference(), (Y, None),
                                               loop=(ref.x[1:], ref.P[1:]))
    late = ref.x[1:].copy()
    late[5:] = ref.x[5:-1]  # a loop that keeps the estimate of the sample before
    with pytest.raises(AssertionError, match="your loop's means differs first at sample 5"):
        check_filter(mine, reference(), (Y, None), loop=(late, ref.P[1:]))
    with pytest.raises(AssertionError, match="your loop's means: not answered yet"):
        check_filter(mine, reference(), (Y, None), loop=(None, None))
