"""estim.codegen.export: the generated C filter, built with its Makefile and loaded with
ctypes, steps as the Python filter does (estimates, covariances, statuses)."""

from __future__ import annotations

import ctypes
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest
from codegen_build import build
from models import two_tanks
from test_attitude import scenario as attitude_scenario

import estim
from estim import codegen
from estim._compile import compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")

TOL = 1e-12
CODES = {"ok": 0, "suspect": 1, "rejected": 2}


def _code(status: str) -> int:
    """The C status code of a Python status."""
    if status.startswith("failed"):
        return 4 if "re-anchored" in status else 3
    return CODES[status.split(":")[0]]


def _scenario_record(sc, seed=0):
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed, warn=False)
    return log.y.copy(), None


def _tanks_record(m):
    T = 60
    U = np.full((T, 1), 0.3)
    U[30:] = 0.2
    truth = estim.simulate(m, estim.EKF(m, Q=1e-4, R=1e-4, x0=[0.5, 0.5], P0=1.0),
                           x0=[0.5, 0.5], n_steps=T, Q=0.0, R=1e-4, inputs=U, seed=0,
                           warn=False)
    Y = truth.y.copy()
    Y[15] += 0.5  # suspect (or rejected)
    Y[20:30] = -0.3  # drives h2 below 0: failed updates, kept predictions, re-anchors
    return Y, U


def _root_record():
    """A square-root sensor of a tank emptied by a clipped update: a failed update of a
    trusted estimate (kept prediction), then re-anchored ones, a suspect one later."""
    m = estim.Model(states=["h"], outputs=["r"], inputs=["q"],
                    dynamics=lambda x, u, p: x + u[0], output=lambda x, u, p: ca.sqrt(x[0]),
                    lower=0.0, name="root sensor")
    T = 40
    Y, U = np.full((T, 1), 0.2), np.zeros((T, 1))
    U[8:] = 0.01
    Y[5] = 0.0  # an update below 0, clipped to the empty tank: dh/dx is infinite there
    Y[20] = -1.0  # suspect
    return m, Y, U


ITERATED = {
    "iekf_vdp": lambda m, **t: estim.EKF(m, **t, iterations=3, damping="line-search"),
    "lmekf_vdp": lambda m, **t: estim.EKF(m, **t, iterations=2,
                                          damping="levenberg-marquardt"),
    "iplf_vdp": lambda m, **t: estim.UKF(m, **t, points="gauss-hermite", order=3,
                                         iterations=2, damping="relaxed"),
    "ghsqrt_vdp": lambda m, **t: estim.UKF(m, **t, points="cubature5", form="sqrt")}


def _cubic_record():
    """A cube-law sensor seen from a prior far from the state: Levenberg-Marquardt with
    two iterations does not converge (every step suspect)."""
    m = estim.Model(states=["x"], outputs=["y"], dynamics=lambda x, u, p: x,
                    output=lambda x, u, p: x ** 3, name="cube sensor")
    rng = np.random.default_rng(0)
    x = 2 + np.cumsum(rng.normal(0, 0.05, 40))
    est = estim.EKF(m, Q=0.0025, R=1e-4, x0=[0.1], P0=1.0, iterations=2,
                    damping="levenberg-marquardt")
    return est, (x ** 3 + rng.normal(0, 0.01, 40))[:, None], None


def _configuration(key: str):
    """``(estimator, Y, U)`` of a configuration; ``U[k]`` acts after sample ``k``."""
    reactor = estim.scenarios.batch_reactor(n_steps=200)
    vdp = estim.scenarios.van_der_pol(n_steps=150)
    if key.endswith("reactor"):
        Y, U = _scenario_record(reactor)
        kind = key.split("_")[0]
        est = {"ekf": lambda: estim.EKF(reactor.model, **reactor.tuning),
               "ekfclip": lambda: estim.EKF(reactor.model, **reactor.tuning, clip=True),
               "merwe": lambda: estim.UKF(reactor.model, **reactor.tuning),
               "cubature": lambda: estim.UKF(reactor.model, **reactor.tuning,
                                             points="cubature")}[kind]()
        return est, Y, U
    if key == "lmekf_cubic":
        return _cubic_record()
    if key in ITERATED:  # iterated, damped and Gauss-Hermite updates
        Y, U = _scenario_record(vdp)
        return ITERATED[key](vdp.model, **vdp.tuning), Y, U
    if key.endswith("vdp"):
        Y, U = _scenario_record(vdp)
        F = estim.EKF if key.startswith("ekf") else estim.UKF
        if "gated" not in key:
            return F(vdp.model, **vdp.tuning), Y, U
        Y[10:14] = np.nan  # missing samples
        Y[30:40, 0] = np.nan  # one output missing
        Y[50] += 30.0  # outliers: rejected by the gate
        Y[80, 1] -= 20.0
        Y[100:103] += 8.0
        return F(vdp.model, **vdp.tuning, gate=1e-6), Y, U
    if key.endswith("attitude"):  # a unit quaternion: the multiplicative forms
        sc = attitude_scenario(T=80)
        log = estim.simulate(sc, None, seed=0)
        F = estim.EKF if key.startswith("ekf") else estim.UKF
        return F(sc.model, **sc.tuning), log.y.copy(), sc.inputs
    if key.endswith("root"):
        m, Y, U = _root_record()
        F = estim.EKF if key.startswith("ekf") else estim.UKF
        return F(m, Q=2e-3, R=0.01, x0=[0.04], P0=1e-3, clip=True), Y, U
    m = two_tanks("foh" if "foh" in key else "zoh")
    Y, U = _tanks_record(m)
    F = estim.EKF if key.startswith("ekf") else estim.UKF
    gate = 1e-6 if "gated" in key else None
    return F(m, Q=1e-4, R=1e-4, x0=[0.5, 0.5], P0=1.0, clip=True, gate=gate), Y, U


def _build(directory, name: str) -> ctypes.CDLL:
    """The library built (the driver with -Wall -Wextra -Werror) and loaded."""
    lib = ctypes.CDLL(str(build(directory, name)))
    d = ctypes.POINTER(ctypes.c_double)
    getattr(lib, f"{name}_step").argtypes = [ctypes.c_void_p, d, d, d, d]
    getattr(lib, f"{name}_nis").restype = ctypes.c_double
    getattr(lib, f"{name}_size").restype = ctypes.c_size_t
    return lib


class CFilter:
    """The exported filter, stepped through ctypes."""

    def __init__(self, est, directory, name):
        self.name, self.nx, self.nd = name, est.model.nx, est.model.ndx
        self.lib = _build(directory, name)
        size = int(getattr(self.lib, f"{name}_size")())
        self.memory = np.zeros(size // 8 + 1)  # 8-byte aligned
        self.f = self.memory.ctypes.data
        assert getattr(self.lib, f"{name}_init")(ctypes.c_void_p(self.f)) == 0

    def step(self, y, u):
        ptr = ctypes.POINTER(ctypes.c_double)
        y = np.ascontiguousarray(y, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        x, P = np.empty(self.nx), np.empty(self.nd * self.nd)
        status = getattr(self.lib, f"{self.name}_step")(
            ctypes.c_void_p(self.f), y.ctypes.data_as(ptr),
            u.ctypes.data_as(ptr) if u.size else None, x.ctypes.data_as(ptr),
            P.ctypes.data_as(ptr))
        return status, x, P.reshape(self.nd, self.nd, order="F")

    def nis(self) -> float:
        return getattr(self.lib, f"{self.name}_nis")(ctypes.c_void_p(self.f))

    def run(self, Y, U, sampled=False):
        assert getattr(self.lib, f"{self.name}_init")(ctypes.c_void_p(self.f)) == 0
        nu = U.shape[1] if U is not None else 0
        out = {"x": [], "P": [], "status": [], "nis": []}
        for k, y in enumerate(Y):
            u = np.zeros(nu) if U is None or (k == 0 and not sampled) else \
                U[k] if sampled else U[k - 1]
            status, x, P = self.step(y, u)
            out["x"].append(x)
            out["P"].append(P)
            out["status"].append(status)
            out["nis"].append(self.nis())
        return {k: np.array(v) for k, v in out.items()}


def _close(a, b):
    """Differences relative to the larger of 1 and the value: the largest one."""
    scale = np.maximum(1.0, np.abs(b))
    return float(np.max(np.abs(a - b) / scale))


CONFIGURATIONS = ["ekf_reactor", "ekfclip_reactor", "merwe_reactor", "cubature_reactor",
                  "ekf_vdp", "ukf_vdp", "ekf_gated_vdp", "ukf_gated_vdp", "ekf_tanks",
                  "ukf_tanks", "ekf_gated_tanks", "ukf_foh_tanks", "ekf_root", "ukf_root",
                  "ekf_attitude", "ukf_attitude", *ITERATED, "lmekf_cubic"]
#: Statuses each record must show (beyond "ok").
SHOWN = {"gated": {2}, "tanks": {4}, "root": {1, 3, 4}, "ekfclip": {1}, "cubic": {1}}


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """``key -> (estimator, Y, U, CFilter, directory)``, each exported and built once."""
    built = {}

    def get(key):
        if key not in built:
            est, Y, U = _configuration(key)
            directory = tmp_path_factory.mktemp(key)
            codegen.export(est, directory, name=key)
            built[key] = est, Y, U, CFilter(est, directory, key), directory
        return built[key]
    return get


def check_c_step(est, Y, U, cf, key: str, name: str, shown_by_part: dict) -> None:
    """The exported filter ``cf`` (library name ``name``) steps as ``est`` over ``(Y, U)``:
    the same statuses, estimates and covariances to ``TOL``, NIS; the statuses each part
    of ``key`` is there to show; the size C reports is :func:`codegen.memory`'s."""
    log = estim.replay(est, Y, U, warn=False)
    out = cf.run(Y, U, sampled=est.model.sampled)
    assert out["status"].tolist() == [_code(s) for s in log.status]
    assert _close(out["x"], log.x_hat) <= TOL
    assert _close(out["P"], log.P) <= TOL
    np.testing.assert_allclose(out["nis"], log.nis, rtol=TOL, atol=TOL)  # NaN where NaN
    codes = set(out["status"].tolist())
    for part, shown in shown_by_part.items():
        if part in key.split("_"):
            assert shown <= codes
    assert int(getattr(cf.lib, f"{name}_size")()) == codegen.memory(est)


@pytest.mark.parametrize("key", CONFIGURATIONS)
def test_the_c_step_is_the_python_step(exports, key):
    est, Y, U, cf, _ = exports(key)
    check_c_step(est, Y, U, cf, key, key, SHOWN)


def test_inf_in_y_is_refused_and_changes_nothing(exports):
    key = "ekf_tanks"
    est, Y, U, cf, _ = exports(key)
    getattr(cf.lib, f"{key}_init")(ctypes.c_void_p(cf.f))
    _, x1, _ = cf.step(Y[0], U[0])
    before = cf.memory.copy()
    status, _, _ = cf.step(np.array([np.inf]), U[0])
    assert status == -1
    np.testing.assert_array_equal(cf.memory, before)
    status, _, _ = cf.step(Y[1], np.array([np.nan]))
    assert status == -1
    est.reset()
    est.step(Y[0], U[0])
    with pytest.raises(ValueError, match="inf"):
        est.step(np.array([np.inf]), U[0])


def test_tuning_set_in_c_is_set_tuning(exports):
    key = "ekf_gated_vdp"
    est, Y, U, cf, _ = exports(key)
    Q, P0 = 2 * np.asarray(est.Q), 3 * np.asarray(est.P0)
    ptr = ctypes.POINTER(ctypes.c_double)
    Qf, P0f = (np.asfortranarray(a).ravel(order="F") for a in (Q, P0))
    set_tuning = getattr(cf.lib, f"{key}_set_tuning")
    set_tuning.argtypes = [ctypes.c_void_p, ptr, ptr, ptr, ptr]
    getattr(cf.lib, f"{key}_init")(ctypes.c_void_p(cf.f))
    assert set_tuning(ctypes.c_void_p(cf.f), Qf.ctypes.data_as(ptr), None, None,
                      P0f.ctypes.data_as(ptr)) == 0
    assert getattr(cf.lib, f"{key}_reset")(ctypes.c_void_p(cf.f)) == 0
    x, P, status = [], [], []
    for y in Y:
        s, xk, Pk = cf.step(y, np.zeros(0))
        x.append(xk)
        P.append(Pk)
        status.append(s)
    Q0, P00 = est.Q.copy(), est.P0.copy()
    try:
        est.set_tuning(Q=Q, P0=P0)
        log = estim.replay(est, Y, warn=False)
    finally:
        est.set_tuning(Q=Q0, P0=P00)
    assert status == [_code(s) for s in log.status]
    assert _close(np.array(x), log.x_hat) <= TOL and _close(np.array(P), log.P) <= TOL


@pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")
def test_a_loop_in_c(exports, tmp_path):
    """A C program linked with the static library runs the record (the timing loop)."""
    key = "ekf_reactor"
    est, Y, U, cf, directory = exports(key)
    subprocess.run(["make", f"CC={compiler()[0]}", f"lib{key}.a"], cwd=directory,
                   check=True, capture_output=True)
    rows = ",\n".join("{" + ", ".join(repr(float(v)) for v in y) + "}" for y in Y)
    (tmp_path / "loop.c").write_text(f"""
#include <stdio.h>
#include <time.h>
#include "{key}.h"
static const double Y[{len(Y)}][{est.model.ny}] = {{{rows}}};
int main(void) {{
    {key}_t f;
    double x[{est.model.nx}], P[{est.model.nx ** 2}];
    struct timespec t0, t1;
    int r, k, repeats = 50;
    clock_gettime(CLOCK_MONOTONIC, &t0);
    for (r = 0; r < repeats; ++r) {{
        {key}_init(&f);
        for (k = 0; k < {len(Y)}; ++k) {key}_step(&f, Y[k], NULL, x, P);
    }}
    clock_gettime(CLOCK_MONOTONIC, &t1);
    printf("%.17g %.17g\\n", x[0], ((t1.tv_sec - t0.tv_sec) * 1e9 +
           (t1.tv_nsec - t0.tv_nsec)) / (repeats * {len(Y)}.0));
    return 0;
}}
""")
    cc = compiler()[0]
    subprocess.run([cc, "-O2", "-I", directory, "loop.c", f"{directory}/lib{key}.a", "-lm",
                    "-o", "loop"], cwd=tmp_path, check=True, capture_output=True)
    run = subprocess.run([str(tmp_path / "loop")], check=True, capture_output=True, text=True)
    x_last, ns_per_step = map(float, run.stdout.split())
    log = estim.replay(est, Y, warn=False)
    assert abs(x_last - log.x_hat[-1, 0]) <= TOL * max(1.0, abs(log.x_hat[-1, 0]))
    assert 0 < ns_per_step < 1e6


@pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")
@pytest.mark.parametrize("key", ["ekf_tanks", "cubature_reactor"])
def test_the_example_program_runs_a_csv_record(exports, key, tmp_path):
    """``make example`` builds ``<name>_example``, which reads a record as CSV (a header,
    the outputs, ``nan`` for a missing one, then the input that acted since the previous
    sample) and writes Python's statuses, estimates and standard deviations."""
    est, Y, U, cf, directory = exports(key)
    m = est.model
    run = subprocess.run(["make", f"CC={compiler()[0]}", "example"], cwd=directory,
                         capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    Y = Y.copy()
    Y[3] = np.nan  # a missing sample
    given = np.zeros((len(Y), m.nu)) if U is None else \
        np.vstack([np.zeros((1, m.nu)), U[:-1]])  # the input since the previous sample
    rows = [",".join(m.output_names + m.input_names)]
    rows += [",".join(f"{v:.17g}" for v in [*y, *u]) for y, u in zip(Y, given, strict=True)]
    (tmp_path / "record.csv").write_text("\n".join(rows) + "\n")
    program = directory / f"{key}_example"
    subprocess.run([str(program), "record.csv", "estimates.csv"], cwd=tmp_path, check=True)
    lines = (tmp_path / "estimates.csv").read_text().splitlines()
    assert lines[0] == ",".join(["status", *m.state_names,
                                 *(f"sd_{n}" for n in m.state_names)])
    out = np.loadtxt(tmp_path / "estimates.csv", delimiter=",", skiprows=1, ndmin=2)
    log = estim.replay(est, Y, U, warn=False)
    assert out[:, 0].astype(int).tolist() == [_code(s) for s in log.status]
    assert _close(out[:, 1:1 + m.nx], log.x_hat) <= TOL
    sd = np.sqrt(np.diagonal(log.P, axis1=1, axis2=2))
    assert _close(out[:, 1 + m.nx:], sd) <= TOL
    # a malformed line is named, with what was expected
    (tmp_path / "bad.csv").write_text(rows[0] + "\n" + rows[1] + "\n1,2,x\n")
    bad = subprocess.run([str(program), "bad.csv", "out.csv"], cwd=tmp_path,
                         capture_output=True, text=True, check=False)
    assert bad.returncode == 1 and "bad.csv:3: expected" in bad.stderr


def test_optimizing_for_size_gives_the_same_doubles(tmp_path):
    """``optimize="size"`` (-Os) writes a smaller library that steps to the same
    numbers; anything else is refused."""
    sc = estim.scenarios.batch_reactor(n_steps=60)
    est = estim.UKF(sc.model, **sc.tuning)
    Y, U = _scenario_record(sc)
    runs = {}
    for optimize in ("speed", "size"):
        directory = tmp_path / optimize
        name = f"ukf_{optimize}"
        paths = codegen.export(est, directory, name=name, optimize=optimize)
        flags = "-Os" if optimize == "size" else "-O2"
        assert f"CFLAGS ?= {flags} " in paths["makefile"].read_text()
        cf = CFilter(est, directory, name)
        runs[optimize] = cf.run(Y, U)
    for field in ("x", "P", "status"):
        assert np.array_equal(runs["speed"][field], runs["size"][field])
    with pytest.raises(ValueError, match="optimize must be one of"):
        codegen.export(est, tmp_path / "x", optimize="fast")


def test_what_export_refuses(tmp_path):
    sc = estim.scenarios.van_der_pol(n_steps=10)
    with pytest.raises(ValueError, match="rti=True"):
        codegen.export(estim.MHE(sc.model, **sc.tuning, horizon=5), tmp_path)
    with pytest.raises(TypeError, match="estimator"):
        codegen.export("ekf", tmp_path)
    m = estim.models.van_der_pol()
    cvodes = estim.Model(states=["a"], outputs=["a"], ode=lambda x, u, p: -x,
                         output=lambda x, u, p: x, dt=0.1, integrator="cvodes")
    with pytest.raises(ValueError, match="CVODES"):
        codegen.export(estim.EKF(cvodes, Q=1.0, R=1.0, x0=[0.0], P0=1.0), tmp_path)
    est = estim.EKF(m, **sc.tuning)
    with pytest.raises(ValueError, match="identifier"):
        codegen.export(est, tmp_path, name="2 filters")
    paths = codegen.export(est, tmp_path / "out")
    assert paths["h"].name == "ekf_van_der_pol.h" and paths["makefile"].exists()
    with pytest.raises(FileExistsError, match="overwrite"):
        codegen.export(est, tmp_path / "out")
    codegen.export(est, tmp_path / "out", overwrite=True)
