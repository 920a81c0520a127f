"""Testing estimators with pytest: what a research group or a course keeps in its CI.

Run with ``pytest examples/test_estimators.py`` (estim's pytest plugin is active wherever
estim is installed). Each comparison uses the same noise for every estimator of a seed,
so the assertions are paired tests over seeds with stated error rates
(:mod:`estim.testing`); ``--estim-seeds 200`` makes a nightly run stricter,
``--estim-baseline baselines/`` stores the per-seed metrics and fails a later run whose
estimators got worse, ``--estim-report report.html`` writes the tables and plots, and
``-n 4`` (pytest-xdist) spreads the tests over processes with the same results.
"""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

import estim
from estim import adapters, testing

VDP = estim.scenarios.get("van_der_pol")


def test_mhe_beats_the_ekf_on_the_batch_reactor(estim_compare):
    """From the course's bad guess the EKF settles on a wrong, partly negative state; the
    MHE with the bound x >= 0 does not: lower RMSE at 95 %, by at least half."""
    reactor = estim.scenarios.get("batch_reactor", n_steps=100)
    res = estim_compare(reactor, {"ekf": estim.EKF,
                                  "mhe": lambda m, t: estim.MHE(m, horizon=25,
                                                                arrival_cost="none", **t)},
                        seeds=range(5), name="reactor_mhe_ekf")
    testing.assert_better(res, "mhe", "ekf", confidence=0.95, margin=0.5)


def test_compiling_changes_nothing(estim_compare):
    """jit=True gives the same numbers: equivalent within 0.1 % (two one-sided tests)."""
    res = estim_compare(VDP, {"ekf": estim.EKF,
                              "ekf_jit": lambda m, t: estim.EKF(m, **t, jit=True)},
                        seeds=range(10))
    testing.assert_equivalent(res, "ekf_jit", "ekf", tolerance=1e-3)


def test_the_tuned_ekf_is_consistent(estim_compare):
    res = estim_compare(VDP, {"ekf": estim.EKF}, seeds=range(20), keep_logs=True,
                        burn_in=12)
    testing.assert_consistent(res, level=0.99)


def test_a_filterpy_filter_in_the_loop():
    """A filterpy KalmanFilter equals estim's filter of the same linear model."""
    A, C = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[1.0, 0.0]])
    model = estim.Model(states=["p", "v"], outputs=["y"], dynamics=lambda x, u, p: A @ x,
                        output=lambda x, u, p: C @ x)
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.H, kf.Q, kf.R, kf.P = A, C, np.diag([1e-3, 1e-2]), np.eye(1) * 0.1, np.eye(2)
    record = (np.sin(0.1 * np.arange(50))[:, None], None)
    testing.assert_close(adapters.from_filterpy(kf, model),
                         estim.EKF(model, Q=kf.Q, R=kf.R, x0=[0.0, 0.0], P0=np.eye(2)),
                         record, atol=1e-12)


@pytest.mark.parametrize("estim_scenario", ["van_der_pol", "lorenz"], indirect=True)
def test_the_ukf_is_no_worse_than_the_ekf(estim_compare, estim_scenario):
    res = estim_compare(estim_scenario.replace(n_steps=60), {"ekf": estim.EKF, "ukf": estim.UKF},
                        seeds=range(10))
    # non-inferiority: better than the EKF less 20 % of its median (a negative margin)
    testing.assert_better(res, "ukf", "ekf", margin=-0.2)
