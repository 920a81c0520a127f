"""Grading the course's EKF with pytest: a student's ``EKF`` (from ``solution.py``, or the
module named by ``ESTIM_COURSE_STUDENT``, e.g. ``template``) against ``estim.EKF`` on the
seeded batch-reactor run, with :mod:`estim.testing`. Run from this folder::

    pytest test_grade.py                               # the reference solution
    ESTIM_COURSE_STUDENT=template pytest test_grade.py # a student's file

The course's observer ``ekf(y, log)`` is put in estim's loop by
``estim.adapters.from_function``; its estimates must equal estim's filter of the same
equations to 1e-8 (the course's covariance update ``P - L C P`` and estim's Joseph form
agree to rounding), unclipped and clipped, and over five seeds the two are equivalent
in RMSE (two one-sided tests within 1e-6).
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest

import estim
from estim import adapters, testing

sys.path.insert(0, str(Path(__file__).parent))
student = importlib.import_module(os.environ.get("ESTIM_COURSE_STUDENT", "solution"))
SC, MODEL = student.SC, student.MODEL
TUNING = {"x0": student.GUESS, "P0": student.SIG_P**2 * np.eye(3),
          "Q": student.SIG_W**2 * np.eye(3), "R": student.SIG_V**2 * np.eye(1)}


def graded(clipping: bool = False) -> estim.Estimator:
    """The student's EKF as an estim estimator (a new course EKF at every reset)."""
    held: dict = {}

    def reset():
        held["ekf"], held["log"] = student.EKF(MODEL, **TUNING, clipping=clipping), estim.Log()

    def step(y, u):
        held["ekf"](y, held["log"])
        return held["log"].x_hat[-1]

    reset()
    return adapters.from_function(step, MODEL, name="student EKF", reset=reset)


@pytest.mark.parametrize("clipping", [False, True])
def test_the_estimates_are_estims(clipping):
    log = estim.simulate(SC, None, seed=0)
    testing.assert_close(graded(clipping), estim.EKF(MODEL, **TUNING, clip=clipping),
                         (log.y, None), atol=1e-8, rtol=1e-8)


def test_equivalent_over_seeds():
    res = estim.compare(SC.replace(n_steps=100),
                        {"student": graded(), "estim": lambda m, t: estim.EKF(m, **TUNING)},
                        seeds=range(5))
    testing.assert_equivalent(res, "student", "estim", tolerance=1e-6)
