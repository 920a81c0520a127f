"""estim.grading: a hand-written Kalman filter graded against estim's, and what the
messages say when it is wrong on purpose."""

from __future__ import annotations

import numpy as np
import pytest

import estim
from estim.adapters import from_function
from estim.grading import check_consistent, check_filter, check_over_seeds

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
