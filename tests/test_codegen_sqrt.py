"""estim.codegen.export of the square-root filters (form="sqrt"): the generated C filter,
built with its Makefile and loaded with ctypes, steps as the Python square-root filter
does (estimates, covariances, statuses), on the records of tests/test_codegen.py."""

from __future__ import annotations

import ctypes

import numpy as np
import pytest
from test_codegen import TOL, CFilter, _close, _code, _configuration, check_c_step

import estim
from estim import codegen
from estim._compile import compiler
from estim.codegen.files import sections

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")

#: The covariance form's configurations (the multiplicative forms of the attitude records
#: included), and van der Pol with a full Q, R and P0 (the generated Cholesky factors
#: instead of the square roots of a diagonal).
CONFIGURATIONS = ["ekf_reactor", "ekfclip_reactor", "merwe_reactor", "cubature_reactor",
                  "ekf_vdp", "ukf_vdp", "ekf_gated_vdp", "ukf_gated_vdp", "ekf_tanks",
                  "ukf_tanks", "ekf_gated_tanks", "ukf_foh_tanks", "ekf_root", "ukf_root",
                  "ekf_full_vdp", "ukf_full_vdp", "ekf_attitude", "ukf_attitude"]
#: Statuses each record must show (beyond "ok").
SHOWN = {"gated": {2}, "tanks": {4}, "root": {1, 3, 4}, "full": {2}}


def _sqrt(est, **tuning):
    """The square-root form of a covariance-form filter, with the same options."""
    options = {"Q": est.Q, "R": est.R, "x0": est.x0, "P0": est.P0, "clip": est.clip,
               "gate": est.gate, **tuning}
    if isinstance(est, estim.UKF):
        options.update(points=est.points, alpha=est.alpha, beta=est.beta, kappa=est.kappa)
    return type(est)(est.model, **options, form="sqrt")


def _sqrt_configuration(key: str):
    """``(square-root estimator, Y, U)`` of a configuration."""
    if "full" not in key:
        est, Y, U = _configuration(key)
        return _sqrt(est), Y, U
    est, Y, U = _configuration(key.replace("full", "gated"))
    return _sqrt(est, Q=[[0.01, 0.004], [0.004, 0.01]], R=[[1.0, 0.3], [0.3, 1.0]],
                 P0=[[1.0, 0.2], [0.2, 0.5]]), Y, U


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """``key -> (estimator, Y, U, CFilter)``, each exported and built once."""
    built = {}

    def get(key):
        if key not in built:
            est, Y, U = _sqrt_configuration(key)
            directory = tmp_path_factory.mktemp(f"sqrt_{key}")
            codegen.export(est, directory, name=f"sqrt_{key}")
            built[key] = est, Y, U, CFilter(est, directory, f"sqrt_{key}")
        return built[key]
    return get


@pytest.mark.parametrize("key", CONFIGURATIONS)
def test_the_c_step_is_the_python_step(exports, key):
    est, Y, U, cf = exports(key)
    assert est.form == "sqrt"
    check_c_step(est, Y, U, cf, key, f"sqrt_{key}", SHOWN)


def test_a_gated_step_and_a_recovery_are_exported():
    """The records cover the sums with P0 of the square-root form: the gate's and the
    recovery's."""
    seen = set()
    for key in ("ekf_gated_vdp", "ukf_gated_vdp", "ekf_tanks", "ukf_root"):
        est, Y, U = _sqrt_configuration(key)
        seen |= {_code(s) for s in estim.replay(est, Y, U, warn=False).status}
    assert {2, 3, 4} <= seen


def test_the_struct_holds_the_factor(exports):
    """The filter state in the struct is [x; vec(S)] with P = S S^T, S lower."""
    key = "ekf_full_vdp"
    est, Y, U, cf = exports(key)
    assert getattr(cf.lib, f"sqrt_{key}_init")(ctypes.c_void_p(cf.f)) == 0
    nx = est.model.nx
    _, x, P = cf.step(Y[0], np.zeros(0))
    ny = est.model.ny
    s = cf.memory[2 * nx * nx + ny * ny + nx:][:nx + nx * nx]  # after Q, R, x0, P0
    S = s[nx:].reshape(nx, nx, order="F")
    np.testing.assert_array_equal(s[:nx], x)
    assert np.allclose(np.triu(S, 1), 0.0) and (np.diag(S) > 0).all()
    np.testing.assert_allclose(S @ S.T, P, rtol=1e-14, atol=1e-15)
    assert codegen.memory(est) > codegen.memory(_configuration("ekf_gated_vdp")[0])


def test_tuning_set_in_c_is_set_tuning(exports):
    key = "ukf_full_vdp"
    est, Y, U, cf = exports(key)
    Q, R, P0 = 2 * np.asarray(est.Q), 0.5 * np.asarray(est.R), 3 * np.asarray(est.P0)
    ptr = ctypes.POINTER(ctypes.c_double)
    Qf, Rf, P0f = (np.asfortranarray(a).ravel(order="F") for a in (Q, R, P0))
    set_tuning = getattr(cf.lib, f"sqrt_{key}_set_tuning")
    set_tuning.argtypes = [ctypes.c_void_p, ptr, ptr, ptr, ptr]
    getattr(cf.lib, f"sqrt_{key}_init")(ctypes.c_void_p(cf.f))
    assert set_tuning(ctypes.c_void_p(cf.f), Qf.ctypes.data_as(ptr), Rf.ctypes.data_as(ptr),
                      None, P0f.ctypes.data_as(ptr)) == 0
    assert getattr(cf.lib, f"sqrt_{key}_reset")(ctypes.c_void_p(cf.f)) == 0
    x, P, status = [], [], []
    for y in Y:
        s, xk, Pk = cf.step(y, np.zeros(0))
        x.append(xk)
        P.append(Pk)
        status.append(s)
    Q0, R0, P00 = est.Q.copy(), est.R.copy(), est.P0.copy()
    try:
        est.set_tuning(Q=Q, R=R, P0=P0)
        log = estim.replay(est, Y, warn=False)
    finally:
        est.set_tuning(Q=Q0, R=R0, P0=P00)
    assert status == [_code(s) for s in log.status]
    assert _close(np.array(x), log.x_hat) <= TOL and _close(np.array(P), log.P) <= TOL


def test_the_files_say_the_form(tmp_path):
    sc = estim.scenarios.van_der_pol(n_steps=10)
    paths = codegen.export(estim.UKF(sc.model, **sc.tuning, form="sqrt"), tmp_path)
    assert paths["c"].name == "ukf_van_der_pol.c"
    for kind in ("c", "h", "readme"):
        text = paths[kind].read_text()
        assert "form='sqrt'" in text and "@" not in text.replace("@name@", "")
    assert "ukf_van_der_pol_add_P0" in paths["functions_h"].read_text()


def test_template_sections():
    text = "a\n@if on@\nb\n@if off@\nc\n@else@\nd\n@end@\n@else@\ne\n@end@\nf\n"
    assert sections(text, {"on": True, "off": False}) == "a\nb\nd\nf\n"
    assert sections(text, {"on": False, "off": True}) == "a\ne\nf\n"
    assert sections("a\n@x@\n", {}) == "a\n@x@\n"
    with pytest.raises(ValueError, match="@end"):
        sections("@if on@\nb\n", {"on": True})
    with pytest.raises(ValueError, match="without @if"):
        sections("@if on@\n@end@\n@end@\n", {"on": True})
