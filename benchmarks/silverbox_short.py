r"""Silverbox, short and zero-order-hold records: estim's fit against least_squares in wall time.

The two cases where fixed costs and iterations weigh most: the Duffing grey-box of
``examples/silverbox_model.py`` fitted on the first 2000 training samples with the
first-order hold (native ``hold="foh"``), and on 10 000 samples with the zero-order
hold. Both fits are those of ``benchmarks/silverbox.py`` (whose docstring describes
them): ``scipy.optimize.least_squares`` (``method="trf"``) on the simulation error
with CasADi Jacobians, its wall time including building the CasADi Functions, and
``estim.FullInformation`` (structured Gauss-Newton, ``q = 1e-8``, ``q_θ = 1e-14``)
on the model augmented with its five parameters, from the same start (the
"measured" trajectory and the ARX parameters).

Each run is a fresh process (``--run``): the imports first (``from estim import
FullInformation`` included), then least_squares (build and solve), then estim's
first fit (model, estimator, graphs built, solve: what a first call costs) and a
second fit of the same estimator. Each timed section starts after ``gc.collect()``
(untimed), so that a full collection of the objects the imports left (about 10^5, 40-50
ms here) does not land in whichever section happens to cross Python's threshold
(``--no-collect`` times without; the script counts the full collections that start
inside each section either way). Printed per case: the median and range over the
runs of each wall time, of the ratios estim / least_squares measured within each
process, and the agreement of the optima, :math:`\max_i |\theta_i^{estim} /
\theta_i^{lsq} - 1|` (the five parameters; it should stay below 1e-4).

estim runs at least_squares' own relative-reduction tolerance, ``ftol = 1e-8``
(``--ftol``). Measured (2-CPU x86_64 shared with other work, casadi 3.8.2, scipy
1.17; three processes each, the machine's load moving every wall time by up to 2x,
the ratios less): at 2000 samples (FOH) estim's first fit takes 0.91x least_squares'
wall time [0.82-0.99] (0.137 s against 0.148 s; 4 iterations), its second fit 0.41x;
at 10 000 samples (ZOH) 0.64x [0.63-0.69] (8 iterations), the second fit 0.51x.
Without the collections 0.86x [0.79-0.92] and 0.77x [0.73-0.89] (a full collection
started inside estim's fits at 10 000 samples in each process); at ``ftol = 1e-10``
1.00x [0.95-1.00] and 0.80x [0.75-0.87]. The parameters agree with least_squares' to
1.6e-5 and 6.4e-6 (3.1e-6 at 1e-10).

Run from the repository root::

    python benchmarks/silverbox_short.py [--runs 3] [--cases 2000:foh 10000:zoh]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np
import scipy

import estim
from estim import FullInformation  # noqa: F401 - imported before timing, as a user does

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "examples"))
from silverbox_identification import load  # noqa: E402 - the shipped data
from silverbox_model import fit_estim, fit_least_squares  # noqa: E402 - the two fits

#: the estim fit's process noise, relative (q for the states, q_θ for the parameters)
Q, Q_PARAM = 1e-8, 1e-14
DEFAULT_CASES = ["2000:foh", "10000:zoh"]
#: estim's relative-decrease tolerance (``solver_options={"ftol": ...}``): least_squares'
#: own ``ftol = 1e-8`` (it stops once the last step reduced the cost by less than that
#: fraction, estim once the next Gauss-Newton step promises less, and takes it);
#: ``--ftol default`` runs estim's own default, 1e-13
FTOL = 1e-8


class FullCollections:
    """Counts Python's full (generation-2) garbage collections that the interpreter
    starts on its own (:meth:`collect` runs one that is not counted)."""

    def __init__(self) -> None:
        self.count, self._explicit = 0, False
        gc.callbacks.append(self._seen)

    def _seen(self, phase: str, info: dict) -> None:
        if phase == "start" and info["generation"] == 2 and not self._explicit:
            self.count += 1

    def collect(self) -> None:
        """``gc.collect()``, not counted."""
        self._explicit = True
        try:
            gc.collect()
        finally:
            self._explicit = False


def run(samples: int, hold: str, ftol: float | None = FTOL, collect: bool = True) -> dict:
    """One run in this process: least_squares, then estim's first and second fits, each
    timed from a collected heap (``collect``: ``gc.collect()`` before it, untimed)."""
    data = load()
    u, y = data.u_train[:samples], data.y_train[:samples]
    full = FullCollections()
    if collect:
        full.collect()
    t0 = time.perf_counter()
    ls = fit_least_squares(u, y, hold, method="trf")
    ls_s = time.perf_counter() - t0
    ls_full = full.count
    options = None if ftol is None else {"ftol": ftol}
    if collect:
        full.collect()
    fit = fit_estim(u, y, hold, "gauss-newton", Q, Q_PARAM, options, "measured", foh="native",
                    collect=full.collect if collect else None)
    return {"samples": samples, "hold": hold, "ls_s": ls_s, "ls_build_s": ls.build_seconds,
            "ls_nfev": ls.nfev, "first_s": fit.first_seconds, "build_s": fit.build_seconds,
            "second_s": fit.second_seconds, "solve_s": fit.solve_seconds,
            "iterations": fit.iterations, "success": fit.success,
            "agreement": float(np.max(np.abs(fit.theta / ls.theta - 1))),
            "full_collections": [ls_full, full.count - ls_full],
            "theta": fit.theta.tolist(), "theta_ls": ls.theta.tolist()}


def run_isolated(samples: int, hold: str, ftol: float | None, collect: bool) -> dict:
    """:func:`run` in a fresh process."""
    proc = subprocess.run([sys.executable, __file__, "--run", f"{samples}:{hold}", "--ftol",
                           "default" if ftol is None else repr(ftol)]
                          + ([] if collect else ["--no-collect"]), cwd=ROOT,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-1])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def stat(values: list[float], fmt: str) -> str:
    """``median [min-max]``."""
    v = np.asarray(values)
    return f"{np.median(v):{fmt}} [{v.min():{fmt}}-{v.max():{fmt}}]"


def case(text: str) -> tuple[int, str]:
    """``"samples:hold"``."""
    n, _, hold = text.partition(":")
    if hold not in ("foh", "zoh"):
        raise argparse.ArgumentTypeError(f"expected samples:foh or samples:zoh, got {text!r}")
    return int(n), hold


def main(argv: list[str] | None = None) -> dict:
    """Run every case ``--runs`` times, each in a fresh process; print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--cases", type=case, nargs="+", default=[case(c) for c in DEFAULT_CASES])
    parser.add_argument("--ftol", type=lambda v: None if v == "default" else float(v),
                        default=FTOL, help="estim's ftol, or 'default' (default 1e-8)")
    parser.add_argument("--no-collect", dest="collect", action="store_false",
                        help="time without gc.collect() before each timed section")
    parser.add_argument("--run", type=case, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.run:
        print(json.dumps(run(*args.run, ftol=args.ftol, collect=args.collect)))
        return {}
    print(f"estim {estim.__version__}, casadi {ca.__version__}, scipy {scipy.__version__}, "
          f"numpy {np.__version__}, Python {platform.python_version()}, "
          f"{platform.machine()}, {os.cpu_count()} CPUs; estim from {Path(estim.__file__).parent}")
    rows = {}
    for n, hold in args.cases:
        rows[n, hold] = [run_isolated(n, hold, args.ftol, args.collect)
                         for _ in range(args.runs)]
    ftol = "default (1e-13)" if args.ftol is None else f"{args.ftol:g}"
    print(f"\nSilverbox, q = {Q:g}, q_θ = {Q_PARAM:g}, 'measured' start, estim's ftol "
          f"{ftol} (least_squares' 1e-8); median [range] of {args.runs} processes, seconds\n")
    head = (f"{'case':<10} {'estim 1st fit':>20} {'estim 2nd fit':>20} {'least_squares':>20} "
            f"{'1st / lsq':>17} {'2nd / lsq':>17} {'agreement':>9}  iterations")
    print(head)
    print("-" * len(head))
    for (n, hold), rs in rows.items():
        first, second, ls = ([r[k] for r in rs] for k in ("first_s", "second_s", "ls_s"))
        print(f"{n:>5} {hold.upper():<4} {stat(first, '.3f'):>20} {stat(second, '.3f'):>20} "
              f"{stat(ls, '.3f'):>20} "
              f"{stat([a / b for a, b in zip(first, ls, strict=True)], '.2f'):>17} "
              f"{stat([a / b for a, b in zip(second, ls, strict=True)], '.2f'):>17} "
              f"{max(r['agreement'] for r in rs):>9.1e}  "
              f"{rs[0]['iterations']} (lsq nfev {rs[0]['ls_nfev']})")
    print("\nestim 1st fit: model, estimator, graphs built and solve in a fresh process; of "
          "which building:")
    for (n, hold), rs in rows.items():
        print(f"  {n} {hold.upper()}: build {stat([r['build_s'] for r in rs], '.3f')}, "
              f"solve {stat([r['solve_s'] for r in rs], '.3f')} (2nd fit); least_squares "
              f"build {stat([r['ls_build_s'] for r in rs], '.3f')}")
    print("agreement: max over the runs of max_i |θ_i(estim) / θ_i(least_squares) - 1|.")
    print("full garbage collections inside the timed sections (least_squares, estim's two "
          "fits), over the runs, " + ("each section timed after gc.collect()" if args.collect
                                      else "without gc.collect()") + ": " + ", ".join(
        f"{n} {hold.upper()} {sum(r['full_collections'][0] for r in rs)} / "
        f"{sum(r['full_collections'][1] for r in rs)}" for (n, hold), rs in rows.items()))
    return rows


if __name__ == "__main__":
    main()
