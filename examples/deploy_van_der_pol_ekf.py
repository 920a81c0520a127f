"""Validate a filter in Python, ship the same computation as C.

The van der Pol EKF (both states measured, RK4 at 0.1 s) is exported with
``estim.codegen.export``; a small C program (``main.c``, written here next to the export)
reads a recorded file of measurements, one sample per line, runs the exported filter and
writes its estimates. The script builds it with the system C compiler, runs it on a
record simulated here (a few measurements removed, one outlier), and compares the
program's estimates with the Python filter's ``step`` loop: they are the same numbers.

Run from the repository root::

    python examples/deploy_van_der_pol_ekf.py [--out build/vdp_ekf]
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
#include "vdp_ekf.h"

/* Reads "y1,y2" per line ("nan" for a missing output), writes "x1,x2,status". */
int main(int argc, char **argv) {
    if (argc != 3) { fprintf(stderr, "usage: %s record.csv estimates.csv\n", argv[0]); return 2; }
    FILE *in = fopen(argv[1], "r"), *out = fopen(argv[2], "w");
    if (!in || !out) { perror("open"); return 2; }
    static vdp_ekf_t f;               /* the whole filter: no allocation */
    vdp_ekf_init(&f);
    double y[2], x[2], P[4];
    char a[64], b[64];
    while (fscanf(in, " %63[^,],%63s", a, b) == 2) {
        y[0] = strtod(a, NULL);       /* strtod reads "nan" */
        y[1] = strtod(b, NULL);
        int status = vdp_ekf_step(&f, y, NULL, x, P);
        fprintf(out, "%.17g,%.17g,%d\n", x[0], x[1], status);
    }
    fclose(in);
    fclose(out);
    return 0;
}
"""


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None, help="directory of the export and program "
                        "(default: a temporary one)")
    args = parser.parse_args(argv)
    cc = next(filter(None, map(shutil.which, ("cc", "gcc", "clang"))), None)
    if cc is None:
        raise SystemExit("this example needs a C compiler (cc, gcc or clang)")
    out = Path(args.out) if args.out else Path(tempfile.mkdtemp()) / "vdp_ekf"

    sc = estim.scenarios.van_der_pol(n_steps=300)
    ekf = estim.EKF(sc.model, **sc.tuning, gate=1e-6)
    record = estim.simulate(sc, ekf, seed=3).y
    record[[40, 41], 0] = np.nan  # a sensor missing twice
    record[120] += 25.0           # an outlier the gate rejects

    if out.exists():
        shutil.rmtree(out)
    codegen.export(ekf, out, name="vdp_ekf")
    (out / "main.c").write_text(MAIN)
    np.savetxt(out / "record.csv", record, delimiter=",", fmt="%.17g")
    sources = ["main.c", "vdp_ekf.c", "vdp_ekf_functions.c"]
    subprocess.run([cc, "-O2", "-fno-fast-math", "-ffp-contract=off", *sources,
                    "-o", "vdp_ekf_run", "-lm"], cwd=out, check=True)
    subprocess.run([str(out / "vdp_ekf_run"), "record.csv", "estimates.csv"], cwd=out,
                   check=True)
    c_out = np.loadtxt(out / "estimates.csv", delimiter=",", ndmin=2)

    log = estim.replay(ekf, record, warn=False)  # the Python filter, step by step
    diff = float(np.max(np.abs(c_out[:, :2] - log.x_hat)))
    rejected = int(np.sum(c_out[:, 2] == 2))
    print(f"exported to {out}; the C program filtered {len(record)} samples")
    print(f"largest |x_C - x_Python| = {diff:.3g}; samples rejected by the gate: C "
          f"{rejected}, Python {sum(s.startswith('rejected') for s in log.status)}")
    print(f"memory of the filter: {codegen.memory(ekf)} bytes")
    return {"difference": diff, "rejected": rejected, "samples": len(record),
            "directory": out}


if __name__ == "__main__":
    main()
