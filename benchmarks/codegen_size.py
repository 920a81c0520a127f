"""Size, build time and step time of the C that ``estim.codegen.export`` writes, for the
exportable estimators of the examples, optimised for speed (``-O2``) and for size
(``-Os``).

For each estimator and each ``optimize``: the generated source (every ``.c`` and ``.h``
of the export, bytes), the time of ``make`` (the static and the shared library, one job:
wall time), the shared library's size (bytes) and the C step's time (a timing program
linked with the static library runs the scenario's record ``--reps`` times, the
estimator reset in between; the median run's nanoseconds per step; for the MHE each
sample is ``prepare`` then ``step``). Build and step times are the median over
``--repeats`` builds (the range in brackets); every build starts from a clean directory.

The estimators: the batch reactor's EKF, UKF (merwe points) and square-root EKF, van der
Pol's EKF and real-time MHE (``N = 15``, as ``examples/deploy_van_der_pol.py``), the
textbook pendulum's real-time MHE (``N = 20``) and the satellite's unit-quaternion
real-time MHE (``N = 10``, ``models.satellite(quaternion=True)`` with its inputs; the
scenario's zero process noise on the attitude made 1e-10: the real-time iteration needs
a definite ``Q``).

Run from the repository root::

    python benchmarks/codegen_size.py [--repeats 3] [--reps 200] [--only pendulum]

There are no assertions; the numbers depend on the machine and its compiler.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

import estim
from estim import codegen
from estim._compile import compiler

TIMER_C = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "@name@.h"

static int compare(const void *a, const void *b) {
    double x = *(const double *) a, y = *(const double *) b;
    return (x > y) - (x < y);
}

/* timer Y.bin U.bin n reps: the median run's ns per step */
int main(int argc, char **argv) {
    static @name@_t e;
    int n, reps, r, k;
    double *Y, *U, *t, x[@NAME@_NX];
    FILE *io;
    if (argc != 5) return 2;
    n = atoi(argv[3]);
    reps = atoi(argv[4]);
    Y = malloc(sizeof(double) * n * @NAME@_NY);
    U = malloc(sizeof(double) * n * (@NAME@_NU + 1));
    t = malloc(sizeof(double) * reps);
    io = fopen(argv[1], "rb");
    if (!io || fread(Y, sizeof(double), (size_t) n * @NAME@_NY, io)
            != (size_t) n * @NAME@_NY) return 3;
    fclose(io);
    io = fopen(argv[2], "rb");
    if (!io || fread(U, sizeof(double), (size_t) n * @NAME@_NU, io)
            != (size_t) n * @NAME@_NU) return 3;
    fclose(io);
    if (@name@_init(&e) != 0) return 4;
    for (r = 0; r < reps; ++r) {
        struct timespec a, b;
        @name@_reset(&e);
        clock_gettime(CLOCK_MONOTONIC, &a);
        for (k = 0; k < n; ++k) {
            const double *u = @NAME@_NU ? U + k * @NAME@_NU : NULL;
            @prepare@
            @name@_step(&e, Y + k * @NAME@_NY, u, x, NULL);
        }
        clock_gettime(CLOCK_MONOTONIC, &b);
        t[r] = ((double) (b.tv_sec - a.tv_sec) * 1e9 + (double) (b.tv_nsec - a.tv_nsec)) / n;
    }
    qsort(t, (size_t) reps, sizeof(double), compare);
    printf("%.3f\n", t[reps / 2]);
    return 0;
}
"""


def estimators() -> dict:
    """``label -> (estimator, Y (T, ny), U given to each step (T, nu))``."""
    out = {}
    reactor = estim.scenarios.batch_reactor()
    vdp = estim.scenarios.van_der_pol(n_steps=300)
    pend = estim.models.sine_pendulum()
    Q = np.diag([1e-4, 0.06])  # (the real-time iteration needs a definite Q)
    pend_tuning = {"Q": Q, "R": 0.01, "x0": [1.2, 0.0], "P0": 0.09}
    sat = estim.scenarios.satellite(fault=False, quaternion=True, n_steps=300)
    Qs = np.array(sat.tuning["Q"], float)
    Qs = np.diag(np.where(np.diag(Qs) > 0, np.diag(Qs), 1e-10)) if Qs.ndim == 2 else \
        np.where(Qs > 0, Qs, 1e-10)  # the attitude's zero noise made tiny (rti: definite Q)
    sat = sat.replace(tuning={**sat.tuning, "Q": Qs})
    for label, sc, make in [
            ("reactor EKF", reactor, lambda s: estim.EKF(s.model, **s.tuning)),
            ("reactor UKF (merwe)", reactor, lambda s: estim.UKF(s.model, **s.tuning)),
            ("reactor EKF, form='sqrt'", reactor,
             lambda s: estim.EKF(s.model, **s.tuning, form="sqrt")),
            ("van der Pol EKF", vdp, lambda s: estim.EKF(s.model, **s.tuning)),
            ("van der Pol MHE, N = 15, rti", vdp,
             lambda s: estim.MHE(s.model, horizon=15, rti=True, **s.tuning)),
            ("satellite MHE (unit quaternion), N = 10, rti", sat,
             lambda s: estim.MHE(s.model, horizon=10, rti=True, **s.tuning))]:
        log = estim.simulate(sc, None, seed=0, warn=False)
        out[label] = (make(sc), np.asarray(log.y, float), given_inputs(sc.model, log))
    log = estim.simulate(pend, None, x0=[1.5, 0.0], n_steps=300, Q=Q, R=0.01, seed=0)
    out["pendulum MHE, N = 20, rti"] = (
        estim.MHE(pend, horizon=20, rti=True, **pend_tuning), np.asarray(log.y, float),
        np.zeros((len(log.y), 0)))
    return out


def given_inputs(model, log) -> np.ndarray:
    """The input each step is given: the one that acted since the previous sample (the
    input at the sample for a sampled model)."""
    if not model.nu:
        return np.zeros((len(log), 0))
    u = np.asarray(log.u, float)
    if model.sampled:
        return u
    return np.vstack([np.zeros((1, model.nu)), u[:-1]])


def measure(est, Y, U, optimize: str, tmp: Path, repeats: int, reps: int) -> dict:
    name = "est"
    sizes, builds, libs, steps = [], [], [], []
    cc = compiler()[0]
    for r in range(repeats):
        directory = tmp / f"{optimize}_{r}"
        paths = codegen.export(est, directory, name=name, optimize=optimize)
        sizes.append(sum(p.stat().st_size for p in directory.iterdir()
                         if p.suffix in (".c", ".h") and p.name != f"{name}_example.c"))
        t0 = time.perf_counter()
        subprocess.run(["make", f"CC={cc}", "-j1"], cwd=directory, check=True,
                       capture_output=True)
        builds.append(time.perf_counter() - t0)
        libs.append((directory / f"lib{name}.so").stat().st_size)
        prepare = f"{name}_prepare(&e, u);" if isinstance(est, estim.MHE) else ""
        (directory / "timer.c").write_text(TIMER_C.replace("@name@", name)
                                           .replace("@NAME@", name.upper())
                                           .replace("@prepare@", prepare))
        flags = codegen.files.cflags(optimize).split()
        subprocess.run([cc, *flags, "timer.c", f"lib{name}.a", "-o", "timer", "-lm"],
                       cwd=directory, check=True, capture_output=True)
        (directory / "Y.bin").write_bytes(np.ascontiguousarray(Y).tobytes())
        (directory / "U.bin").write_bytes(np.ascontiguousarray(U).tobytes())
        run = subprocess.run(["./timer", "Y.bin", "U.bin", str(len(Y)), str(reps)],
                             cwd=directory, check=True, capture_output=True, text=True)
        steps.append(float(run.stdout))
        assert paths["example"].exists()
    return {"source": sizes[0], "build": builds, "library": libs[0], "step": steps}


def span(values, digits: int = 3) -> str:
    med = statistics.median(values)
    if len(values) == 1:
        return f"{med:.{digits}g}"
    return f"{med:.{digits}g} [{min(values):.{digits}g}-{max(values):.{digits}g}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reps", type=int, default=200, help="runs of the record per timing")
    parser.add_argument("--only", default="", help="estimators whose label contains this")
    args = parser.parse_args()
    cc = compiler()
    if cc is None:
        raise SystemExit("no C compiler")
    print(f"# C export: size, build time and step time ({platform.machine()}, "
          f"{cc[1].splitlines()[0] if cc[1] else cc[0]}, CasADi {estim.__version__ and ''}"
          f"{__import__('casadi').__version__})\n")
    print("| estimator | optimize | generated C | make | lib .so | C step (prepare + step) |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="estim-codegen-size-") as tmp:
        for label, (est, Y, U) in estimators().items():
            if args.only and args.only not in label:
                continue
            for optimize in ("speed", "size"):
                res = measure(est, Y, U, optimize, Path(tmp) / label.replace(" ", "_")
                              .replace("/", "").replace(",", "").replace("=", "")
                              .replace("'", "").replace("(", "").replace(")", ""),
                              args.repeats, args.reps)
                print(f"| {label} | {optimize} | {res['source'] / 1e3:.0f} kB | "
                      f"{span(res['build'])} s | {res['library'] / 1e3:.0f} kB | "
                      f"{span([t / 1e3 for t in res['step']])} µs |", flush=True)


if __name__ == "__main__":
    main()
