"""EKF and UKF with jit=True: the steps and the whole-record scans compiled to C through
the per-machine cache give the interpreted filter's numbers."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

import estim
from estim import _fast
from estim._compile import compiler
from estim.solvers import seeds

needs_cc = pytest.mark.skipif(compiler() is None, reason="jit needs a C compiler")


def _record(T: int = 120):
    sc = estim.scenarios.van_der_pol(n_steps=T)
    Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=3).y
    Y[7, 1] = Y[T // 3] = np.nan  # missing outputs
    Y[2 * T // 3, 0] += 40.0  # an outlier beyond the gate
    return sc, Y


def _same(a, b, atol=1e-12):
    for key in ("x", "P", "innovation", "nis"):
        np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=0, atol=atol,
                                   err_msg=key)
    assert a.status == b.status and a.success == b.success


@needs_cc
@pytest.mark.parametrize("form", ["covariance", "sqrt"])
@pytest.mark.parametrize("kind", ["EKF", "UKF"])
def test_the_compiled_filter_is_the_interpreted_one(fresh_cache, kind, form):
    """filter(), the step loop, reset and set_tuning: compiled as interpreted."""
    sc, Y = _record()
    make = getattr(estim, kind)
    plain = make(sc.model, form=form, gate=1e-6, **sc.tuning)
    fast = make(sc.model, form=form, gate=1e-6, jit=True, **sc.tuning)
    assert fast.jit and fast._update.compiled and fast._predict_update.compiled
    assert fast._whole_record(len(Y)).compiled
    ref = plain.filter(Y)
    assert any(s.startswith("rejected") for s in ref.status)  # the gate acted
    _same(fast.filter(Y), ref)
    fast.reset()
    np.testing.assert_allclose(np.array([fast.step(y) for y in Y]), ref.x, rtol=0,
                               atol=1e-12)
    for est in (plain, fast):  # the tuning is data: nothing is rebuilt
        est.set_tuning(Q=0.05 * np.eye(2), R=2.0 * np.eye(2))
    _same(fast.filter(Y), plain.filter(Y))
    again = copy.deepcopy(fast)  # copies compile again (here: load from the cache)
    assert again._update.compiled
    _same(again.filter(Y), fast.filter(Y))


@needs_cc
def test_compare_with_jit_is_compare_without(fresh_cache):
    sc = estim.scenarios.van_der_pol(n_steps=80)
    est = {"EKF": lambda m, tun: estim.EKF(m, jit=True, **tun),
           "UKF": lambda m, tun: estim.UKF(m, form="sqrt", jit=True, **tun)}
    ref = {"EKF": estim.EKF, "UKF": lambda m, tun: estim.UKF(m, form="sqrt", **tun)}
    fast, plain = (estim.compare(sc, e, seeds=range(3)) for e in (est, ref))
    assert fast.batched.count("compiled") == 2 and "compiled" not in plain.batched
    for name in est:
        np.testing.assert_array_equal(fast.rmse[name], plain.rmse[name])
    for a, b in zip(fast.rows, plain.rows, strict=True):
        assert (a.rmse_mean, a.nees_mean, a.flagged) == (b.rmse_mean, b.nees_mean, b.flagged)


def test_jit_must_be_a_bool():
    sc = estim.scenarios.van_der_pol(n_steps=10)
    for make in (estim.EKF, estim.UKF):
        with pytest.raises(TypeError, match="jit must be True or False"):
            make(sc.model, jit="yes", **sc.tuning)
        assert make(sc.model, **sc.tuning).jit is False


def test_without_a_compiler_jit_warns_and_interprets(monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setattr(_fast, "_WARNED", set())
    monkeypatch.setattr(seeds, "_MAPPED", type(seeds._MAPPED)())
    sc, Y = _record(40)
    with pytest.warns(estim.EstimationWarning, match="jit=True: no C compiler found"):
        fast = estim.EKF(sc.model, jit=True, **sc.tuning)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # one warning per process, not one per Function
        res = fast.filter(Y)
    assert not fast._update.compiled
    assert not fast._whole_record(len(Y)).fun.is_a("External")
    _same(res, estim.EKF(sc.model, **sc.tuning).filter(Y), atol=0)
