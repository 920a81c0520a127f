"""Time of the generated C step of an EKF and a UKF, of the real-time iteration of the
MHE, and of the converged Gauss-Newton MHE compiled through the per-machine cache.

Three measurements, each in this process unless said:

1. **Generated C step** (``estim.codegen.export``) of the EKF and the UKF (merwe
   points) on the batch reactor (``estim.scenarios.batch_reactor()``, the 400 samples
   of its seed-0 record). The export goes into a temporary directory with a small C
   timing program that reads the record from a binary file, runs the 400 steps
   ``--c-reps`` times (each timed with ``clock_gettime(CLOCK_MONOTONIC)``, the filter
   reset in between, outside the timing) and prints the nanoseconds per step of the
   best and of the median run; it is compiled with ``cc -O2 -fno-fast-math
   -ffp-contract=off`` and run once per repeat. It also writes the estimates of its
   last run, compared with the Python ``step`` loop's (max ``|x_C - x_Python|``). The
   Python rows: the ``step`` loop of the same filter and ``est.filter(Y)`` (timed
   after a first call that builds it), per sample.
2. **Real-time iteration** (``MHE(rti=True)``) on van der Pol with ``N = 15`` (120
   samples) and on the batch reactor with ``N = 25``: per sample once the window is
   full, the wall time of ``mhe.prepare(None)`` and of ``mhe.step(y)`` (and the
   estimator's own ``info.extra["preparation_time"]`` and ``info.solve_time``), and
   their sum; interpreted and with ``solver_options={"jit": True}``. Against the
   converged MHE (``rti=False``, Gauss-Newton) step after the window is full. RMSE
   of each against the true states.
3. **The converged Gauss-Newton MHE with jit, from the compile cache and before it**
   (van der Pol, ``N = 15``), each in a fresh process (``sys.executable -c``):
   (a) a cold cache (an empty ``ESTIM_CACHE_DIR``: compiles), (b) a second process on
   that cache (loads), (c) the code of commit 7d66269 (a git worktree, by default
   ``/tmp/work/old``, on ``PYTHONPATH``), which compiled with CasADi's own jit into a
   temporary directory in every process, and (d) the current code without jit. Each
   reports the time to construct the MHE plus its first step, the median step time
   over ``--replays`` replays of the 120-sample record, and (current code) the time
   spent in ``estim._compile.compiled`` (wrapped with a timer: generating the code,
   hashing it, and loading or compiling the library). The load of a warm process is
   that time; the difference of (b) and (d)'s construction plus first step is printed
   too.

All times are medians over ``--repeats`` repeats (the garbage collector off while
timing), with the range (min-max) over the repeats. The jit compilations of this
process go to a temporary cache directory (``ESTIM_CACHE_DIR``), removed at the end.

Run from the repository root::

    python benchmarks/codegen.py [--repeats 5] [--old /tmp/work/old]

(create the worktree with ``git worktree add /tmp/work/old 7d66269``; without it part
3(c) is skipped). There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi
import numpy as np

import estim
from estim import _compile, codegen

FLAGS = ["-O2", "-fno-fast-math", "-ffp-contract=off"]

TIMER_C = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "@name@.h"

static int compare(const void *a, const void *b) {
    double x = *(const double *) a, y = *(const double *) b;
    return (x > y) - (x < y);
}

/* timer Y.bin n reps X.bin: prints the ns per step of the best and the median run
 * and the number of invalid steps; writes the estimates of the last run. */
int main(int argc, char **argv) {
    static @name@_t f;
    int n, reps, r, k, invalid = 0;
    double *Y, *X, *t;
    FILE *io;
    if (argc != 5) return 2;
    n = atoi(argv[2]);
    reps = atoi(argv[3]);
    Y = malloc(sizeof(double) * n * @NAME@_NY);
    X = malloc(sizeof(double) * n * @NAME@_NX);
    t = malloc(sizeof(double) * reps);
    io = fopen(argv[1], "rb");
    if (!io || fread(Y, sizeof(double), (size_t) n * @NAME@_NY, io)
            != (size_t) n * @NAME@_NY) return 3;
    fclose(io);
    if (@name@_init(&f) != 0) return 4;
    for (r = 0; r < reps; ++r) {
        struct timespec a, b;
        @name@_reset(&f);
        clock_gettime(CLOCK_MONOTONIC, &a);
        for (k = 0; k < n; ++k)
            invalid += @name@_step(&f, Y + k * @NAME@_NY, NULL, X + k * @NAME@_NX, NULL) < 0;
        clock_gettime(CLOCK_MONOTONIC, &b);
        t[r] = ((double) (b.tv_sec - a.tv_sec) * 1e9 + (double) (b.tv_nsec - a.tv_nsec)) / n;
    }
    io = fopen(argv[4], "wb");
    if (!io) return 5;
    fwrite(X, sizeof(double), (size_t) n * @NAME@_NX, io);
    fclose(io);
    qsort(t, (size_t) reps, sizeof(double), compare);
    printf("%.3f %.3f %d\n", t[0], t[reps / 2], invalid);
    return 0;
}
"""

#: Run in a fresh process: argv = [jit (0/1), replays]; prints one JSON line.
SNIPPET = r"""
import gc, json, statistics, sys, time
import numpy as np
import estim
jit, replays = sys.argv[1] == "1", int(sys.argv[2])
spent = [0.0, 0]
try:
    from estim import _compile
    inner = _compile.compiled
    def timed_compiled(fun):
        t0 = time.perf_counter()
        try:
            return inner(fun)
        finally:
            spent[0] += time.perf_counter() - t0
            spent[1] += 1
    _compile.compiled = timed_compiled
except ImportError:
    pass
sc = estim.scenarios.van_der_pol()
Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0).y
opts = {"solver_options": {"jit": True}} if jit else {}
gc.disable()
t0 = time.perf_counter()
mhe = estim.MHE(sc.model, horizon=15, **opts, **sc.tuning)
t1 = time.perf_counter()
mhe.step(Y[0])
t2 = time.perf_counter()
first = list(spent)
steps = []
for _ in range(replays):
    mhe.reset()
    X = []
    for y in Y:
        a = time.perf_counter()
        X.append(mhe.step(y))
        steps.append(time.perf_counter() - a)
print(json.dumps({"construct": t1 - t0, "first_step": t2 - t1, "setup": t2 - t0,
                  "compiled_time": first[0], "compiled_calls": first[1],
                  "compiled_time_all": spent[0], "step_median": statistics.median(steps),
                  "x": np.asarray(X).tolist()}))
"""


def span(values, scale: float = 1.0, digits: int = 2) -> str:
    """``median [min-max]`` of ``values`` times ``scale``."""
    v = [x * scale for x in values]
    return (f"{statistics.median(v):.{digits}f} [{min(v):.{digits}f}-"
            f"{max(v):.{digits}f}]")


def median(values) -> float:
    return statistics.median(values)


class NoGC:
    def __enter__(self):
        self.enabled = gc.isenabled()
        gc.disable()

    def __exit__(self, *exc):
        if self.enabled:
            gc.enable()


def record(sc: estim.Scenario):
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    return np.asarray(log.y, dtype=float), np.asarray(log.x, dtype=float)


# 1. generated C -------------------------------------------------------------------------

def python_step_loop(est, Y: np.ndarray) -> tuple[float, np.ndarray]:
    est.reset()
    step = est.step
    with NoGC():
        t0 = time.perf_counter()
        X = [step(y) for y in Y]
        elapsed = time.perf_counter() - t0
    return elapsed / len(Y), np.asarray(X)


def filter_time(est, Y: np.ndarray) -> float:
    with NoGC():
        t0 = time.perf_counter()
        est.filter(Y)
        return (time.perf_counter() - t0) / len(Y)


def generated_c(repeats: int, c_reps: int, tmp: Path) -> list[dict]:
    sc = estim.scenarios.batch_reactor()
    Y, _ = record(sc)
    T = len(Y)
    (tmp / "Y.bin").write_bytes(np.ascontiguousarray(Y).tobytes())
    rows = []
    for label, est in [("EKF", estim.EKF(sc.model, **sc.tuning)),
                       ("UKF (merwe)", estim.UKF(sc.model, points="merwe", **sc.tuning))]:
        name = f"{est.name}_timed"
        out = tmp / name
        codegen.export(est, out, name=name)
        (out / "timer.c").write_text(TIMER_C.replace("@name@", name)
                                     .replace("@NAME@", name.upper()))
        exe = out / "timer"
        subprocess.run(["cc", *FLAGS, "timer.c", f"{name}.c", f"{name}_functions.c",
                        "-o", exe.name, "-lm"], cwd=out, check=True)
        est.filter(Y)  # builds the whole-record Function
        _, ref = python_step_loop(est, Y)
        c_best, c_med, py_step, py_filter, diffs = [], [], [], [], []
        for _ in range(repeats):
            run = subprocess.run([str(exe), str(tmp / "Y.bin"), str(T), str(c_reps),
                                  str(out / "X.bin")], capture_output=True, text=True,
                                 check=True)
            best, med, invalid = run.stdout.split()
            if int(invalid):
                raise RuntimeError(f"{label}: {invalid} invalid C steps")
            c_best.append(float(best) * 1e-9)
            c_med.append(float(med) * 1e-9)
            Xc = np.frombuffer((out / "X.bin").read_bytes()).reshape(T, -1)
            diffs.append(float(np.max(np.abs(Xc - ref))))
            py_step.append(python_step_loop(est, Y)[0])
            py_filter.append(filter_time(est, Y))
        rows.append({"label": label, "c_best": c_best, "c_med": c_med,
                     "py_step": py_step, "py_filter": py_filter, "diff": max(diffs),
                     "bytes": codegen.memory(est)})
    return rows


def print_generated(rows: list[dict]) -> None:
    print("\n## 1. Generated C step, batch reactor (400 samples)\n")
    print("| filter | C best run ns/step | C median run ns/step | Python step µs | "
          "filter(Y) µs/sample | step / C | filter / C | max \\|x_C - x_step\\| |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        c = median(r["c_med"])
        print(f"| {r['label']} | {span(r['c_best'], 1e9, 1)} | {span(r['c_med'], 1e9, 1)} "
              f"| {span(r['py_step'], 1e6)} | {span(r['py_filter'], 1e6)} "
              f"| {median(r['py_step']) / c:.0f}× | {median(r['py_filter']) / c:.1f}× "
              f"| {r['diff']:.1e} |")
    ekf = rows[0]
    print(f"\nGoal: generated EKF step <= 1 µs: median run {median(ekf['c_med']) * 1e9:.0f} ns"
          f" -> {'met' if median(ekf['c_med']) <= 1e-6 else 'missed'}. Struct size: "
          + ", ".join(f"{r['label']} {r['bytes']} bytes" for r in rows))


# 2. real-time iteration ----------------------------------------------------------------

def rti_run(mhe, Y: np.ndarray, N: int) -> dict:
    """One pass over the record: per-sample times once the window is full."""
    mhe.reset()
    prep, prep_own, feed, feed_own, X = [], [], [], [], []
    with NoGC():
        for k, y in enumerate(Y):
            if k < N:
                X.append(mhe.step(y))
                continue
            t0 = time.perf_counter()
            mhe.prepare(None)
            t1 = time.perf_counter()
            x = mhe.step(y)
            t2 = time.perf_counter()
            X.append(x)
            prep.append(t1 - t0)
            feed.append(t2 - t1)
            prep_own.append(mhe.info.extra["preparation_time"])
            feed_own.append(mhe.info.solve_time)
    return {"prep": median(prep), "prep_own": median(prep_own), "feed": median(feed),
            "feed_own": median(feed_own),
            "total": median(np.add(prep, feed)), "X": np.asarray(X)}


def converged_run(mhe, Y: np.ndarray, N: int) -> dict:
    mhe.reset()
    steps, X = [], []
    with NoGC():
        for k, y in enumerate(Y):
            t0 = time.perf_counter()
            X.append(mhe.step(y))
            if k >= N:
                steps.append(time.perf_counter() - t0)
    return {"total": median(steps), "X": np.asarray(X)}


def rti(repeats: int) -> list[dict]:
    problems = [("van der Pol", estim.scenarios.van_der_pol(), 15),
                ("batch reactor", estim.scenarios.batch_reactor(), 25)]
    out = []
    for title, sc, N in problems:
        Y, Xtrue = record(sc)
        variants = []
        for label, kw, run in [
                ("RTI", {"rti": True}, rti_run),
                ("RTI, jit", {"rti": True, "solver_options": {"jit": True}}, rti_run),
                ("converged GN", {}, converged_run),
                ("converged GN, jit", {"solver_options": {"jit": True}}, converged_run)]:
            t0 = time.perf_counter()
            mhe = estim.MHE(sc.model, horizon=N, **kw, **sc.tuning)
            first = run(mhe, Y, N)  # warm-up (and any lazy build)
            build = time.perf_counter() - t0
            runs = [run(mhe, Y, N) for _ in range(repeats)]
            X = first["X"]
            rmse = float(np.sqrt(np.mean((X[N:] - Xtrue[N:]) ** 2)))
            variants.append({"label": label, "build": build, "runs": runs, "X": X,
                             "rmse": rmse})
        ref = variants[2]["X"]
        for v in variants:
            v["diff"] = float(np.max(np.abs(v["X"][N:] - ref[N:])))
        out.append({"title": title, "N": N, "T": len(Y), "variants": variants})
    return out


def print_rti(results: list[dict]) -> None:
    print("\n## 2. Real-time iteration MHE, per sample once the window is full (µs)\n")
    print("| problem | MHE | prepare (wall) | preparation_time | step (wall) | solve_time "
          "| total (wall) | converged / total | RMSE | max \\|x - converged\\| "
          "| built+1st pass s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for p in results:
        conv = median([r["total"] for r in p["variants"][2]["runs"]])
        for v in p["variants"]:
            runs = v["runs"]

            def col(key, runs=runs):
                return span([r[key] for r in runs], 1e6, 1) if key in runs[0] else "-"
            total = median([r["total"] for r in runs])
            print(f"| {p['title']} N={p['N']} ({p['T']} samples) | {v['label']} "
                  f"| {col('prep')} | {col('prep_own')} | {col('feed')} | {col('feed_own')} "
                  f"| {col('total')} | {conv / total:.1f}× | {v['rmse']:.4f} "
                  f"| {v['diff']:.1e} | {v['build']:.2f} |")
    vdp = {v["label"]: v for v in results[0]["variants"]}
    for label in ("RTI", "RTI, jit"):
        runs = vdp[label]["runs"]
        feed, total = median([r["feed"] for r in runs]), median([r["total"] for r in runs])
        print(f"\nGoals on van der Pol N=15 ({label}): feedback <= 10 µs: "
              f"{feed * 1e6:.1f} µs -> {'met' if feed <= 10e-6 else 'missed'}; total <= 30 µs: "
              f"{total * 1e6:.1f} µs -> {'met' if total <= 30e-6 else 'missed'}")


# 3. the compile cache ------------------------------------------------------------------

def fresh(jit: bool, replays: int, cache: Path, pythonpath: str) -> dict:
    env = dict(os.environ, ESTIM_CACHE_DIR=str(cache), PYTHONPATH=pythonpath)
    run = subprocess.run([sys.executable, "-c", SNIPPET, "1" if jit else "0", str(replays)],
                         env=env, capture_output=True, text=True, check=False,
                         cwd=tempfile.gettempdir())
    if run.returncode != 0:
        raise RuntimeError(f"subprocess failed:\n{run.stderr[-2000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def cache(repeats: int, replays: int, old: Path | None, tmp: Path) -> dict:
    here = str(Path(__file__).resolve().parent.parent)
    kinds = {"cold cache (compiles)": [], "warm cache (loads)": [],
             "no jit": []}
    if old is not None:
        kinds["7d66269, CasADi jit"] = []
    for r in range(repeats):
        cache_dir = tmp / f"cache-{r}"
        kinds["cold cache (compiles)"].append(fresh(True, replays, cache_dir, here))
        kinds["warm cache (loads)"].append(fresh(True, replays, cache_dir, here))
        kinds["no jit"].append(fresh(False, replays, cache_dir, here))
        if old is not None:
            kinds["7d66269, CasADi jit"].append(fresh(True, replays, tmp / "unused", str(old)))
    return kinds


def print_cache(kinds: dict) -> None:
    print("\n## 3. Converged Gauss-Newton MHE, van der Pol N=15, fresh processes\n")
    ref = np.asarray(kinds["no jit"][0]["x"])
    print("| process | construct + 1st step s | of which in compiled() s | median step µs "
          "| step / old jit | max \\|x - no jit\\| |")
    print("|---|---|---|---|---|---|")
    old = kinds.get("7d66269, CasADi jit")
    old_step = median([k["step_median"] for k in old]) if old else None
    for label, runs in kinds.items():
        step = median([k["step_median"] for k in runs])
        diff = max(float(np.max(np.abs(np.asarray(k["x"]) - ref))) for k in runs)
        inside = (span([k["compiled_time"] for k in runs], 1, 4)
                  if runs[0]["compiled_calls"] else "-")
        ratio = f"{step / old_step:.2f}×" if old_step else "-"
        print(f"| {label} | {span([k['setup'] for k in runs], 1, 3)} | {inside} "
              f"| {span([k['step_median'] for k in runs], 1e6, 1)} | {ratio} | {diff:.1e} |")
    warm = kinds["warm cache (loads)"]
    load = median([k["compiled_time"] for k in warm])
    diff = median([k["setup"] for k in warm]) - median([k["setup"] for k in kinds["no jit"]])
    calls = warm[0]["compiled_calls"]
    print(f"\nWarm process: {calls} compiled() calls, {load * 1e3:.1f} ms in them "
          f"(construct + 1st step with jit minus without: {diff * 1e3:.1f} ms); goal "
          f"load <= 0.1 s -> {'met' if load <= 0.1 else 'missed'}")
    if old_step:
        step = median([k["step_median"] for k in warm])
        print(f"Goal step from the cache within 1.2x of the old jit step: {step * 1e6:.1f} "
              f"vs {old_step * 1e6:.1f} µs = {step / old_step:.2f}x -> "
              f"{'met' if step <= 1.2 * old_step else 'missed'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--c-reps", type=int, default=1000,
                        help="runs of the record inside one C timing process")
    parser.add_argument("--replays", type=int, default=3,
                        help="replays of the record in each fresh process of part 3")
    parser.add_argument("--old", default="/tmp/work/old",
                        help="worktree of commit 7d66269 (part 3c; skipped if missing)")
    args = parser.parse_args()
    repeats = max(3, args.repeats)
    old = Path(args.old)
    old = old if (old / "estim" / "__init__.py").exists() else None
    cc = _compile.compiler()
    print(f"Python {platform.python_version()}, CasADi {casadi.__version__}, "
          f"numpy {np.__version__}, estim {estim.__version__}, {platform.machine()}, "
          f"{os.cpu_count()} cores; {cc[1] if cc else 'no C compiler'}")
    print(f"load average {os.getloadavg()}; median [min-max] of {repeats} repeats")
    tmp = Path(tempfile.mkdtemp(prefix="estim-codegen-bench-"))
    os.environ["ESTIM_CACHE_DIR"] = str(tmp / "cache")
    try:
        print_generated(generated_c(repeats, args.c_reps, tmp))
        print_rti(rti(repeats))
        if old is None:
            print(f"\n{args.old} does not hold estim: part 3(c) skipped (git worktree add "
                  f"{args.old} 7d66269)")
        print_cache(cache(repeats, args.replays, old, tmp))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"\nload average at the end {os.getloadavg()}")


if __name__ == "__main__":
    main()
