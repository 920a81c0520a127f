"""Fault injection: every estimator and solver survives bad data and recovers in time.

The matrix of ``benchmarks/faults.py`` (van der Pol, 200 samples, faults from sample 80:
a burst of missing outputs, one and five 100-sigma outliers, a model that is not
finite over one step, a solver capped at one or two iterations), asserted: no estimate
is ever non-finite, no corrupted sample is reported ``"ok"``, a model fault is reported
as a failure, and the error returns to the clean run's error level within the bound
(30 samples for the filters, 2 N for MHE and full information, 2 w for the shooting
observer).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

import estim

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "faults.py"


def _load():
    spec = importlib.util.spec_from_file_location("estim_bench_faults", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


faults = _load()
NAMES = list(faults.estimators(faults.faulty_van_der_pol()))


@pytest.fixture(scope="module")
def matrix():
    return faults.fault_matrix()


@pytest.mark.parametrize("name", NAMES)
def test_recovers_within_the_bound(matrix, name):
    cells = {f: c for (n, f), c in matrix.items() if n == name}
    assert cells, name
    for fault, c in cells.items():
        assert c.finite, (name, fault)
        assert c.ok_while_corrupt == 0, (name, fault, c)
        if c.bound is not None:
            assert c.recover <= c.bound, (name, fault, c)
    # a model that is not finite for one step is a failure, and reported as one
    assert cells["model_nan"].failed >= 1
    if "capped" in cells:  # early stops are used, and said to be inexact
        assert cells["capped"].failed == 0 and cells["capped"].flagged > 0


def test_textbook_filter_absorbs_an_outlier_and_flags_it(matrix):
    """Without a gate the filters use every measurement (they equal filterpy's), flag
    the outlier "suspect", and come back at the pace of their gain; the gated ones
    reject it and are back within a few samples."""
    for name in ("ekf", "ukf"):
        c, gated = matrix[name, "outlier"], matrix[f"{name} gate=1e-9", "outlier"]
        assert c.flagged >= 1 and c.failed == 0
        assert c.recover < faults.T - faults.START  # it does come back
        assert gated.recover < c.recover


def test_outlier_steps_are_flagged_not_ok():
    model = faults.faulty_van_der_pol()
    X, Y = faults.record(model)
    Yf, U, _ = faults.inject("outlier", Y)
    for est in (estim.EKF(model, **faults.TUNING),
                estim.MHE(model, horizon=15, solver="gauss-newton", **faults.TUNING)):
        log = estim.replay(est, Yf, U, X, warn=False)
        assert log.status[faults.START] != "ok"
        assert np.isfinite(log.x_hat).all()
