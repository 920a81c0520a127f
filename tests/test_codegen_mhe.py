"""estim.codegen.export of the real-time iteration MHE: the generated C estimator, built
and loaded with ctypes, steps as the Python MHE does (estimates, covariances, statuses),
with and without the preparation phase; and its timing in a small C program."""

from __future__ import annotations

import ctypes
import shutil
import subprocess
from concurrent.futures import ThreadPoolExecutor

import casadi as ca
import numpy as np
import pytest
from codegen_build import build
from test_attitude import scenario as attitude_scenario
from test_attitude_windows import circling

import estim
from estim import codegen
from estim._compile import compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")

TOL = 1e-12


def _code(status: str) -> int:
    """The C status code of a Python status."""
    return {"ok": 0, "inexact": 1, "suspect": 2, "failed": 3}[status.split(":")[0]]


def _vdp_record(n: int, missing: bool = False, outlier: bool = False):
    sc = estim.scenarios.van_der_pol()
    Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0, warn=False).y[:n].copy()
    if outlier:  # a million standard deviations: solved, then re-anchored
        Y[60, 0] += 1e6
    if missing:
        Y[3, 0] = np.nan  # while the window fills
        Y[20:23] = np.nan  # whole samples, newest slot included
        Y[40:50, 1] = np.nan  # one output
        Y[n - 1, 0] = np.nan
    return sc, Y


def _oscillator(hold: str = "zoh"):
    """A damped linear oscillator driven by a force."""
    return estim.Model(
        states=["p", "v"], outputs=["p"], inputs=["u"],
        ode=lambda x, u, p: ca.vertcat(x[1], -x[0] - 0.2 * x[1] + u[0]),
        output=lambda x, u, p: x[0], dt=0.1, hold=hold, name="oscillator")


def _configuration(key: str):
    """``(estimator, Y, U)``; ``U[k]`` acts after sample ``k`` (at sample ``k`` if sampled)."""
    if key.startswith("vdp"):
        parts = key.split("_")
        data = ("missing", "outlier")
        arrival = parts[1] if len(parts) > 1 and parts[1] not in data else "filtering"
        n, N = (120, 15) if arrival == "filtering" else (50, 8)
        sc, Y = _vdp_record(n, missing="missing" in parts, outlier="outlier" in parts)
        return estim.MHE(sc.model, **sc.tuning, horizon=N, rti=True,
                         arrival_cost=arrival), Y, None
    if key == "reactor":
        sc = estim.scenarios.batch_reactor()
        Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0, warn=False).y.copy()
        return estim.MHE(sc.model, **sc.tuning, horizon=25, rti=True), Y, None
    if key == "attitude":  # a unit quaternion: the moves are retractions
        sc = attitude_scenario(T=60)
        Y = estim.simulate(sc, None, seed=0).y.copy()
        Y[12:14] = np.nan  # missing samples
        Y[30, :3] += 0.5  # an outlier (50 sigma): a suspect step, solved to convergence
        return estim.MHE(sc.model, horizon=4, rti=True, **sc.tuning), Y, sc.inputs
    if key == "circling":  # angles (the heading, the bearing) and a bound on the speed
        m, tuning, sc = circling(120)
        Y = estim.simulate(sc, estim.EKF(m, **tuning), seed=0, warn=False).y
        return estim.MHE(m, horizon=4, rti=True, lower={"speed": 1.995}, **tuning), Y, None
    if key == "square":  # negative values of a square: windows that do not converge
        m = estim.Model(states=["x"], outputs=["y"], dynamics=lambda x, u, p: x,
                        output=lambda x, u, p: x[0] ** 2, name="square sensor")
        Y = np.concatenate([[-1.0] * 3, [-8.0] * 3, 1.0 + 0.1 * np.sin(np.arange(24))])
        return estim.MHE(m, Q=1e-2, R=0.1, x0=[1.0], P0=10.0, horizon=4, rti=True), \
            Y[:, None], None
    m = _oscillator("foh" if key.endswith("foh") else "zoh")
    T = 80
    U = np.sin(0.15 * np.arange(T))[:, None]
    truth = estim.simulate(m, estim.EKF(m, Q=1e-4, R=1e-2, x0=[1.0, 0.0], P0=1.0),
                           x0=[1.0, 0.0], n_steps=T, Q=1e-4, R=1e-2, inputs=U, seed=1,
                           warn=False)
    est = estim.MHE(m, Q=1e-4, R=1e-2, x0=[0.5, 0.0], P0=1.0, horizon=10, rti=True)
    return est, truth.y.copy(), U


def _load(directory, name: str) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(directory / f"lib{name}.so"))
    d = ctypes.POINTER(ctypes.c_double)
    getattr(lib, f"{name}_step").argtypes = [ctypes.c_void_p, d, d, d, d]
    getattr(lib, f"{name}_prepare").argtypes = [ctypes.c_void_p, d]
    getattr(lib, f"{name}_size").restype = ctypes.c_size_t
    return lib


class CMHE:
    """The exported MHE, stepped through ctypes."""

    def __init__(self, est, directory, name):
        self.name, self.nx, self.nd = name, est.model.nx, est.model.ndx
        self.lib = _load(directory, name)
        size = int(getattr(self.lib, f"{name}_size")())
        self.memory = np.zeros(size // 8 + 1)  # 8-byte aligned
        self.e = ctypes.c_void_p(self.memory.ctypes.data)
        self.init()

    def init(self):
        assert getattr(self.lib, f"{self.name}_init")(self.e) == 0

    @staticmethod
    def _ptr(a):
        return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double)) if a.size else None

    def prepare(self, u):
        u = np.ascontiguousarray(u, dtype=float)
        return getattr(self.lib, f"{self.name}_prepare")(self.e, self._ptr(u))

    def step(self, y, u):
        y = np.ascontiguousarray(y, dtype=float)
        u = np.ascontiguousarray(u, dtype=float)
        x, P = np.empty(self.nx), np.empty(self.nd * self.nd)
        status = getattr(self.lib, f"{self.name}_step")(self.e, self._ptr(y), self._ptr(u),
                                                        self._ptr(x), self._ptr(P))
        return status, x, P.reshape(self.nd, self.nd, order="F")

    def run(self, Y, U, sampled=False, prepare=False):
        self.init()
        nu = U.shape[1] if U is not None else 0
        out = {"x": [], "P": [], "status": []}
        for k, y in enumerate(Y):
            u = _input(U, k, nu, sampled)
            if prepare and k > 0:
                assert self.prepare(u) == 0
            status, x, P = self.step(y, u)
            out["x"].append(x)
            out["P"].append(P)
            out["status"].append(status)
        return {k: np.array(v) for k, v in out.items()}


def _input(U, k, nu, sampled):
    if U is None or (k == 0 and not sampled):
        return np.zeros(nu)
    return U[k] if sampled else U[k - 1]


def _python(est, Y, U, prepare=False):
    """The Python MHE's step loop (with ``prepare`` before every step after the first)."""
    est.reset()
    nu = est.model.nu
    x, P, status = [], [], []
    for k, y in enumerate(Y):
        u = _input(U, k, nu, est.model.sampled)
        if prepare and k > 0:
            est.prepare(u)
        x.append(est.step(y, u))
        P.append(est.info.P)
        status.append(est.info.status)
    return np.array(x), np.array(P), status


CONFIGURATIONS = ["vdp", "vdp_missing", "vdp_outlier", "reactor", "vdp_smoothing",
                  "vdp_fixed", "vdp_none", "oscillator", "oscillator_foh", "square",
                  "attitude", "circling"]


#: Configurations that differ from another one in their data only share its build.
SHARED = {"vdp_missing": "vdp", "vdp_outlier": "vdp"}


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """``key -> (estimator, Y, U, CMHE, directory)``: every configuration exported and
    built once, the builds side by side."""
    data, directories = {}, {}
    for key in CONFIGURATIONS:
        est, Y, U = _configuration(key)
        data[key] = est, Y, U
        if key not in SHARED:
            directories[key] = tmp_path_factory.mktemp(key)
            codegen.export(est, directories[key], name=key)
    with ThreadPoolExecutor() as pool:  # the builds (the driver with -Werror) side by side
        for done in [pool.submit(build, directory, key)
                     for key, directory in directories.items()]:
            done.result()
    loaded = {key: (CMHE(data[key][0], directory, key), directory)
              for key, directory in directories.items()}
    return lambda key: (*data[key], *loaded[SHARED.get(key, key)])


@pytest.mark.parametrize("key", CONFIGURATIONS)
def test_the_c_mhe_is_the_python_mhe(exports, key):
    est, Y, U, cm, _ = exports(key)
    log = estim.replay(est, Y, U, warn=False)
    out = cm.run(Y, U, sampled=est.model.sampled)
    assert out["status"].tolist() == [_code(s) for s in log.status]
    difference = max(float(np.abs(out["x"] - log.x_hat).max()),
                     float(np.abs(out["P"] - log.P).max()))
    print(f"{key}: largest difference {difference:.3g}")
    assert difference <= TOL
    if key == "square":  # inexact; suspect after a converged solve; re-anchored
        assert {1, 2, 3} <= set(out["status"][:10].tolist())
    if key == "vdp_outlier":  # the outlier's window and the next are re-anchored
        assert out["status"][60:62].tolist() == [3, 3] and (out["status"][62:] == 0).all()
    if key == "attitude":  # on the sphere; the outlier's step not taken as it is
        assert np.abs(np.linalg.norm(out["x"], axis=1) - 1).max() < 1e-12
        assert out["P"].shape == (60, 3, 3) and set(out["status"][30:32]) - {0}
    if key == "reactor":
        assert 2 in out["status"]  # windows whose cost is beyond the chi-square tail
    assert int(getattr(cm.lib, f"{cm.name}_size")()) == codegen.memory(est)


@pytest.mark.parametrize("key", ["vdp_missing", "reactor", "oscillator_foh"])
def test_prepare_then_step_is_step(exports, key):
    est, Y, U, cm, _ = exports(key)
    alone = cm.run(Y, U, sampled=est.model.sampled)
    split = cm.run(Y, U, sampled=est.model.sampled, prepare=True)
    for part in ("x", "P", "status"):
        np.testing.assert_array_equal(split[part], alone[part])
    x, P, status = _python(est, Y, U, prepare=True)
    assert np.abs(split["x"] - x).max() <= TOL and np.abs(split["P"] - P).max() <= TOL
    assert split["status"].tolist() == [_code(s) for s in status]


@pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")
@pytest.mark.parametrize("key", ["oscillator_foh", "attitude"])
def test_the_example_program_runs_a_csv_record(exports, key, tmp_path):
    """``make example``: the MHE's program prepares before every measurement and steps,
    from a CSV record (outputs, then the input: here sampled, hold="foh"; on the attitude
    model the standard deviations are of the tangent directions), as Python does."""
    est, Y, U, cm, directory = exports(key)
    m = est.model
    run = subprocess.run(["make", f"CC={compiler()[0]}", "example"], cwd=directory,
                         capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    rows = [",".join(m.output_names + m.input_names)]
    rows += [",".join(f"{v:.17g}" for v in [*y, *_input(U, k, m.nu, m.sampled)])
             for k, y in enumerate(Y)]
    (tmp_path / "record.csv").write_text("\n".join(rows) + "\n")
    subprocess.run([str(directory / f"{key}_example"), "record.csv", "estimates.csv"],
                   cwd=tmp_path, check=True)
    tangent = m.state_names if m.manifold.euclidean_states else m.manifold.tangent_names
    header = (tmp_path / "estimates.csv").read_text().splitlines()[0]
    assert header == ",".join(["status", *m.state_names, *(f"sd_{n}" for n in tangent)])
    out = np.loadtxt(tmp_path / "estimates.csv", delimiter=",", skiprows=1, ndmin=2)
    x, P, status = _python(est, Y, U, prepare=True)
    assert out[:, 0].astype(int).tolist() == [_code(s) for s in status]
    assert np.abs(out[:, 1:1 + m.nx] - x).max() <= TOL
    sd = np.sqrt(np.diagonal(P, axis1=1, axis2=2))
    assert np.abs(out[:, 1 + m.nx:] - sd).max() <= TOL


def test_the_reactor_start_up_holds_and_halves(exports, monkeypatch):
    """The reactor's start-up (which the C code reproduces) holds variables at the bound
    x >= 0 and halves steps: more line-search trials than one per iteration."""
    est, Y, _, _, _ = exports("reactor")
    calls = {"trials": 0, "held": 0}
    cost, linearise = est._rti_cost.evaluate, est._linearise

    def counted_cost():
        calls["trials"] += 1
        return cost()

    def counted_linearise(u, free=None):
        calls["held"] += free is not None
        return linearise(u, free)

    monkeypatch.setattr(est._rti_cost, "evaluate", counted_cost)
    monkeypatch.setattr(est, "_linearise", counted_linearise)
    est.reset()
    iterations = 0
    for y in Y[:est.horizon]:
        est.step(y)
        iterations += est.info.iterations
    assert calls["held"] > 0
    assert calls["trials"] - iterations > iterations  # besides the cost before each step


def test_invalid_calls(exports):
    key = "oscillator"
    est, Y, U, cm, _ = exports(key)
    cm.init()
    for k in range(est.horizon + 2):
        cm.step(Y[k], _input(U, k, 1, False))
    before = cm.memory.copy()
    assert cm.step(np.array([np.inf]), U[0])[0] == -1
    assert cm.step(Y[0], np.array([np.nan]))[0] == -1
    assert cm.prepare(np.array([np.nan])) == -1
    np.testing.assert_array_equal(cm.memory, before)
    assert cm.prepare(U[5]) == 0
    prepared = cm.memory.copy()
    assert cm.prepare(U[5]) == 0  # again: nothing more happens
    assert cm.prepare(U[5] + 1.0) == -3  # another input: refused
    np.testing.assert_array_equal(cm.memory, prepared)
    assert cm.step(Y[5], U[5] + 1.0)[0] == -3  # not the prepared input
    np.testing.assert_array_equal(cm.memory, prepared)
    assert cm.step(Y[5], U[5])[0] == 0
    # a step that is not finite: -2 until reset
    assert cm.step(np.array([1e308]), U[6])[0] == -2
    assert cm.step(Y[7], U[7])[0] == -2
    assert getattr(cm.lib, f"{key}_reset")(cm.e) == 0
    assert cm.step(Y[0], np.zeros(1))[0] == 0


def test_what_export_refuses(tmp_path):
    sc = estim.scenarios.van_der_pol(n_steps=10)
    with pytest.raises(ValueError, match="rti"):
        codegen.export(estim.MHE(sc.model, **sc.tuning, horizon=5), tmp_path)
    with pytest.raises(ValueError, match="horizon"):
        codegen.export(estim.MHE(sc.model, **sc.tuning, horizon=1, rti=True), tmp_path)
    with pytest.raises(TypeError, match="estimator"):
        codegen.export(estim.FullInformation(sc.model, **sc.tuning), tmp_path)
    paths = codegen.export(estim.MHE(sc.model, **sc.tuning, horizon=5, rti=True),
                           tmp_path / "out")
    assert paths["h"].name == "mhe_van_der_pol.h" and paths["readme"].exists()


@pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")
def test_timing_in_c(exports, tmp_path):
    """The preparation and the feedback once the window is full, timed in C: best and
    median over the record's samples of many passes."""
    key = "vdp"
    est, Y, _, _, directory = exports(key)
    subprocess.run(["make", f"CC={compiler()[0]}", f"lib{key}.a"], cwd=directory,
                   check=True, capture_output=True)
    rows = ",\n".join("{" + ", ".join(repr(float(v)) for v in y) + "}" for y in Y)
    N, T, passes = est.horizon, len(Y), 200
    (tmp_path / "timing.c").write_text(f"""
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "{key}.h"
static const double Y[{T}][{est.model.ny}] = {{{rows}}};
static double prep[{passes * (T - N)}], feed[{passes * (T - N)}];
static double ns(struct timespec a, struct timespec b) {{
    return (b.tv_sec - a.tv_sec) * 1e9 + (b.tv_nsec - a.tv_nsec);
}}
static int order(const void *a, const void *b) {{
    double x = *(const double *) a, y = *(const double *) b;
    return (x > y) - (x < y);
}}
int main(void) {{
    static {key}_t e;
    double x[{est.model.nx}], P[{est.model.nx ** 2}];
    struct timespec t0, t1, t2;
    int r, k, m = 0;
    for (r = 0; r < {passes}; ++r) {{
        {key}_init(&e);
        for (k = 0; k < {T}; ++k) {{
            if (k < {N}) {{ {key}_step(&e, Y[k], NULL, x, P); continue; }}
            clock_gettime(CLOCK_MONOTONIC, &t0);
            {key}_prepare(&e, NULL);
            clock_gettime(CLOCK_MONOTONIC, &t1);
            {key}_step(&e, Y[k], NULL, x, P);
            clock_gettime(CLOCK_MONOTONIC, &t2);
            prep[m] = ns(t0, t1);
            feed[m++] = ns(t1, t2);
        }}
    }}
    qsort(prep, m, sizeof(double), order);
    qsort(feed, m, sizeof(double), order);
    printf("%.17g %g %g %g %g\\n", x[0], prep[0], prep[m / 2], feed[0], feed[m / 2]);
    return 0;
}}
""")
    cc = compiler()[0]
    subprocess.run([cc, "-O2", "-I", directory, "timing.c", f"{directory}/lib{key}.a",
                    "-lm", "-o", "timing"], cwd=tmp_path, check=True, capture_output=True)
    run = subprocess.run([str(tmp_path / "timing")], check=True, capture_output=True,
                         text=True)
    x_last, prep_best, prep_median, feed_best, feed_median = map(float, run.stdout.split())
    print(f"van der Pol, N = {N}: prepare {prep_best:.0f} ns best, {prep_median:.0f} ns "
          f"median; feedback {feed_best:.0f} ns best, {feed_median:.0f} ns median")
    log = estim.replay(est, Y, warn=False)
    assert x_last == log.x_hat[-1, 0]
    assert 0 < feed_best <= feed_median < 1e6 and 0 < prep_best <= prep_median < 1e6


def _forced_van_der_pol_stamps(n: int = 60, seed: int = 4):
    """A forced van der Pol oscillator with ``variable_dt=True`` and a sampled input
    (``hold="foh"``), intervals log-uniform in [0.02, 0.3] s: ``(model, t, Y, U)``
    (``U[k]`` the input at sample ``k``)."""
    model = estim.Model(
        states=["x1", "x2"], outputs=["x1"], inputs=["u"],
        ode=lambda x, u, p: ca.vertcat(x[1], (1 - x[0] ** 2) * x[1] - x[0] + u[0]),
        output=lambda x, u, p: x[0], dt=0.1, variable_dt=True, hold="foh",
        name="forced_vdp")
    rng = np.random.default_rng(seed)
    dts = np.exp(rng.uniform(np.log(0.02), np.log(0.3), n - 1))
    t = np.concatenate([[0.0], np.cumsum(dts)])
    U = np.sin(0.7 * t)[:, None]
    x, X = np.array([1.0, 0.0]), []
    for k in range(n):
        if k:
            w = model.transition(U[k - 1], U[k], dts[k - 1])
            x = np.asarray(model.F(x, w, model.p)).ravel() + rng.normal(0.0, 0.02, 2)
        X.append(x)
    Y = np.array(X)[:, :1] + rng.normal(0.0, 0.05, (n, 1))
    return model, t, Y, U


@pytest.mark.parametrize("noise", ["Q", "Qc"])
def test_a_variable_dt_mhe_is_exported_with_the_interval(tmp_path, noise):
    """``variable_dt`` in the MHE's C export: ``prepare(e, u, dt)`` and ``step(e, y, u,
    dt, x_hat, P)`` on a forced van der Pol with sampled inputs and intervals from 20 ms to
    0.3 s are Python's ``MHE(rti=True)`` with ``prepare(u, dt=)`` and ``step(y, u, dt=)``
    to 1e-12 (with and without prepare), with a per-transition ``Q`` and with a
    continuous noise (``Qc=``: each transition's weight from the density inside the
    generated preparation); a dt not positive and finite is refused (-1, nothing
    changed), a dt other than the prepared one too (-3); the example program reads the
    stamps from the record's first column."""
    model, t, Y, U = _forced_van_der_pol_stamps()
    dts = np.diff(t)
    tuning = {"Q": np.diag([4e-4, 4e-4])} if noise == "Q" else {"Qc": np.diag([4e-3, 4e-3])}
    est = estim.MHE(model, horizon=6, **tuning, R=0.0025, x0=[0.8, 0.1], P0=0.1, rti=True)
    codegen.export(est, tmp_path, name="vdt")
    lib = ctypes.CDLL(str(build(tmp_path, "vdt")))
    d = ctypes.POINTER(ctypes.c_double)
    lib.vdt_step.argtypes = [ctypes.c_void_p, d, d, ctypes.c_double, d, d]
    lib.vdt_prepare.argtypes = [ctypes.c_void_p, d, ctypes.c_double]
    lib.vdt_size.restype = ctypes.c_size_t
    memory = np.zeros(int(lib.vdt_size()) // 8 + 1)
    e = ctypes.c_void_p(memory.ctypes.data)

    def ptr(a):
        return np.ascontiguousarray(a, dtype=float).ctypes.data_as(d)

    for prepare in (False, True):
        est.reset()
        assert lib.vdt_init(e) == 0
        xs, Ps, codes, want_x, want_P, want = [], [], [], [], [], []
        for k, y in enumerate(Y):
            u, dt = U[k], float(dts[k - 1]) if k else 0.0
            if k == 20:  # refused intervals and a mismatch: nothing changes
                before = memory.copy()
                x, P = np.empty(2), np.empty(4)
                for bad in (0.0, -dt, np.nan, np.inf):
                    assert lib.vdt_step(e, ptr(y), ptr(u), bad, ptr(x), ptr(P)) == -1
                    assert lib.vdt_prepare(e, ptr(u), bad) == -1
                assert lib.vdt_prepare(e, ptr(u), dt) == 0
                assert lib.vdt_step(e, ptr(y), ptr(u), 2 * dt, ptr(x), ptr(P)) == -3
                if not prepare:
                    memory[:] = before
            if prepare and k:
                assert lib.vdt_prepare(e, ptr(u), dt) == 0
                est.prepare(u, dt=dt)
            x, P = np.empty(2), np.empty(4)
            xa, Pa = np.ascontiguousarray(x), np.ascontiguousarray(P)
            codes.append(lib.vdt_step(e, ptr(y), ptr(u), dt, xa.ctypes.data_as(d),
                                      Pa.ctypes.data_as(d)))
            xs.append(xa.copy())
            Ps.append(Pa.reshape(2, 2, order="F").copy())
            want_x.append(est.step(y, u, dt=dt if k else None))
            want_P.append(est.info.P)
            want.append(_code(est.info.status))
        assert codes == want
        print(f"prepare={prepare}: statuses {sorted(set(codes))}, largest difference "
              f"{np.abs(np.array(xs) - np.array(want_x)).max():.3g}, "
              f"{np.abs(np.array(Ps) - np.array(want_P)).max():.3g}")
        assert np.abs(np.array(xs) - np.array(want_x)).max() <= TOL
        assert np.abs(np.array(Ps) - np.array(want_P)).max() <= TOL
    # the stamps matter: the same record read as uniform is another estimate
    assert np.abs(np.array(want_x) - estim.replay(est, Y, U, warn=False).x_hat).max() > 1e-3
    if shutil.which("make") is None:
        return
    run = subprocess.run(["make", f"CC={compiler()[0]}", "example"], cwd=tmp_path,
                         capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stdout + run.stderr
    rows = ["t,x1,u"] + [f"{a!r},{b!r},{c!r}" for a, b, c in zip(
        t.tolist(), Y[:, 0].tolist(), U[:, 0].tolist(), strict=True)]
    (tmp_path / "record.csv").write_text("\n".join(rows) + "\n")
    subprocess.run([str(tmp_path / "vdt_example"), "record.csv", "estimates.csv"],
                   cwd=tmp_path, check=True)
    out = np.loadtxt(tmp_path / "estimates.csv", delimiter=",", skiprows=1, ndmin=2)
    assert out[:, 0].astype(int).tolist() == want
    assert np.abs(out[:, 1:3] - np.array(want_x)).max() <= TOL
