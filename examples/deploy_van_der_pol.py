"""Validate estimators in Python, ship the same computation as C.

Two van der Pol estimators (both states measured, RK4 at 0.1 s) are exported with
``estim.codegen.export``: the moving horizon estimator's real-time iteration
(``MHE(horizon=15, rti=True)``) and an EKF with a gate. For each, a small C program
(``main.c``, written here next to the export) reads a recorded file of measurements, one
sample per line, runs the exported estimator (for the MHE: ``prepare`` before each
measurement, then the step) and writes its estimates. The script builds them with the
system C compiler, runs them on a record simulated here (a few measurements removed, one
outlier), and compares the programs' estimates with the Python estimators' ``step`` loops:
they are the same numbers.

Run from the repository root::

    python examples/deploy_van_der_pol.py [--out build/vdp]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

import estim
from estim import codegen

MAIN = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "@name@.h"

/* Reads "y1,y2" per line ("nan" for a missing output), writes "x1,x2,status". */
int main(int argc, char **argv) {
    if (argc != 3) { fprintf(stderr, "usage: %s record.csv estimates.csv\n", argv[0]); return 2; }
    FILE *in = fopen(argv[1], "r"), *out = fopen(argv[2], "w");
    if (!in || !out) { perror("open"); return 2; }
    static @name@_t e;                /* the whole estimator: no allocation */
    @name@_init(&e);
    double y[2], x[2], P[4];
    char a[64], b[64];
    while (fscanf(in, " %63[^,],%63s", a, b) == 2) {
        @prepare@
        y[0] = strtod(a, NULL);       /* strtod reads "nan" */
        y[1] = strtod(b, NULL);
        int status = @name@_step(&e, y, NULL, x, P);
        fprintf(out, "%.17g,%.17g,%d\n", x[0], x[1], status);
    }
    fclose(in);
    fclose(out);
    return 0;
}
"""


def run_in_c(estimator, name: str, record: np.ndarray, directory: Path, cc: str
             ) -> np.ndarray:
    """Export ``estimator``, build the program for it and run it on ``record``: the
    estimates and status codes it writes, (T, 3)."""
    codegen.export(estimator, directory, name=name)
    prepare = f"{name}_prepare(&e, NULL);  /* before y arrives */" \
        if isinstance(estimator, estim.MHE) else ""
    (directory / "main.c").write_text(MAIN.replace("@name@", name)
                                      .replace("@prepare@", prepare))
    np.savetxt(directory / "record.csv", record, delimiter=",", fmt="%.17g")
    sources = ["main.c", f"{name}.c", f"{name}_functions.c"]
    subprocess.run([cc, "-O2", "-fno-fast-math", "-ffp-contract=off", *sources,
                    "-o", f"{name}_run", "-lm"], cwd=directory, check=True)
    subprocess.run([str(directory / f"{name}_run"), "record.csv", "estimates.csv"],
                   cwd=directory, check=True)
    return np.loadtxt(directory / "estimates.csv", delimiter=",", ndmin=2)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="directory of the export and program "
                        "(default: a temporary one)")
    args = parser.parse_args(argv)
    cc = next(filter(None, map(shutil.which, ("cc", "gcc", "clang"))), None)
    if cc is None:
        raise SystemExit("this example needs a C compiler (cc, gcc or clang)")
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp()) / "vdp"

    sc = estim.scenarios.van_der_pol(n_steps=300)
    ekf = estim.EKF(sc.model, **sc.tuning, gate=1e-6)
    record = estim.simulate(sc, ekf, seed=3).y
    record[[40, 41], 0] = np.nan  # a sensor missing twice
    record[120] += 25.0           # an outlier the gate rejects

    if out.exists():
        shutil.rmtree(out)
    mhe = estim.MHE(sc.model, horizon=15, rti=True, **sc.tuning)
    results = {}
    for name, est in (("vdp_mhe", mhe), ("vdp_ekf", ekf)):
        c_out = run_in_c(est, name, record, out / name, cc)
        log = estim.replay(est, record, warn=False)  # Python, step by step
        if isinstance(est, estim.MHE):  # with prepare before each measurement
            est.reset()
            x_py = []
            for y in record:
                est.prepare()
                x_py.append(est.step(y))
            assert np.array_equal(np.array(x_py), log.x_hat)
        diff = float(np.max(np.abs(c_out[:, :2] - log.x_hat)))
        codes = {"ok": 0, "inexact": 1, "suspect": 2, "failed": 3} \
            if isinstance(est, estim.MHE) else {"ok": 0, "suspect": 1, "rejected": 2}
        results[name] = {"difference": diff, "memory": codegen.memory(est),
                         "statuses": c_out[:, 2].astype(int), "directory": out / name,
                         "python_statuses": [codes[s.split(":")[0]] for s in log.status]}
        print(f"{name}: exported to {out / name}; the C program filtered {len(record)} "
              f"samples; largest |x_C - x_Python| = {diff:.3g}; {codegen.memory(est)} bytes")
    rejected = int(np.sum(results["vdp_ekf"]["statuses"] == 2))
    print(f"samples the EKF's gate rejected: C {rejected}, Python "
          f"{sum(s.startswith('rejected') for s in estim.replay(ekf, record).status)}")
    return {**results, "samples": len(record), "rejected": rejected}


if __name__ == "__main__":
    main()
