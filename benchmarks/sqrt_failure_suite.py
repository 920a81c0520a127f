r"""The failure suite of the square-root filters: ``estim.EKF`` and ``estim.UKF`` in the
covariance and the square-root form (``form="sqrt"``) on linear-Gaussian cases where
the covariance form is known to break, over many seeds.

The cases (``suite_cases`` in ``tests/sqrt_cases.py``, which the tests import too):

* ``R = 1e-12 I``: a constant-velocity target, its position measured almost exactly
  (``Q = 0``, ``P0 = 1e6 I``), 100 samples;
* rank-deficient ``Q``: a random walk and two constants, ``Q = diag(1, 0, 0)``,
  ``y = [x1 + x2, x2 + x3]``, ``R = 1e-12 I``, 100 samples;
* five parameters: a damped cart driven by five known inputs through five unknown
  constant gains, estimated jointly with position and velocity as augmented states
  whose random-walk variances are ``1e-14 .. 1e-12``, ``R = 1e-12 I``, 100 samples.
  The plant's gains walk with the same tiny variances: with a gain that does not move
  at all the filters would not be exact and the NEES criterion would not apply;
* long run: a target whose velocity reverts to 0 (``v+ = 0.99 v``) under white-noise
  acceleration (``Q`` of rank one, variance 1e-6), its position measured with
  ``R = 1e-12``, ``P0 = 1e6 I``. Not a constant-velocity target: its free velocity
  (about 1e3 from the prior) carries the position to about 1e9 in 10^6 steps, 1e15
  times its standard deviation, beyond what double precision can resolve (measured:
  the UKF's sigma points lose every digit of their spread, and the square-root UKF's
  NEES drifts down to 1.2 while the EKF's stays at 2); with the reverting velocity the
  position stays within about 1e5. Run twice: 1000
  samples for every seed (``--seeds`` x 1000 = 10^6 steps per filter and form at the
  default 1000 seeds), and ``--long-steps`` (10^6) samples in one record for
  ``--long-seeds`` seeds (default 4: 4 x 10^6 steps per filter and form; 1000 records
  of 10^6 samples would be 10^9 steps per filter and form, hours on this machine).
  The one long record goes through ``step`` at every sample ("long run, by step"):
  building ``filter``'s whole-record Function for 10^6 samples takes about 50 s and
  5 GB here (its blocks of sqrt(T) steps are expanded), each filter and form anew;
* badly scaled state: components of about 1e6 and 1e-6 measured through their sum
  (``C = [1, 1e12]``), 100 samples.

Every filter is exact on its case (the plant draws its initial state from the prior,
the noises from ``Q`` and ``R``), so the normalised estimation error squared (NEES)
``e_k' P_k^-1 e_k`` of every sample is chi-square with ``nx`` degrees of freedom. Per
case, filter and form the records of all seeds are filtered one ``filter(Y, U)`` call
per record (one compiled scan; from a failed step on, ``filter`` goes on step by step;
the long record by ``step``), and the table gives:

* the seeds with a failed step and the failed steps (a status ``"failed: ..."``: a kept
  prediction or a re-anchoring on the last trusted estimate);
* the samples whose covariance is not positive definite (no Cholesky factor of ``P``
  in the covariance form; the square-root form's NEES uses the filter's own factor,
  read from the compiled scan, since forming ``S S^T`` squares the condition number);
* the NEES averaged over the samples of each run and then over the seeds, against the
  two-sided 95 % band of ``chi2(seeds * nx) / seeds`` (the band of one sample's
  average over the seeds: a time average has the same mean and at most the variance
  of one sample, so the band is conservative), "no" where a sample has no NEES;
  and whether the NEES summed over the seeds stays inside its 95 % band at every
  sample (Bonferroni over the samples, ``nees_band``), the test's criterion;
* the time of a step, with the ratio sqrt / covariance: "filter us/step", the
  ``filter`` call's seconds over its samples (``step``'s for the long record), the
  median over the seeds (where the covariance form fails a step, ``filter`` goes on
  with the step loop, so this includes its recoveries); and "scan us/step", the
  seconds over its samples of the compiled scan alone (the Function ``filter`` calls,
  whatever the step's outcome) on one record of the case of ``--timing-steps``
  (10^4) samples or the case's length where longer (not for the record run by
  ``step``), the median over ``--repeats`` (15) with both forms taking turns: the
  cost of the step itself.

Failures of the covariance form are the point of the suite. On a failed step the
covariance form's estimate is kept or re-anchored, so its NEES over a run is not that
of the Kalman filter (values far above the band come from re-anchored runs).

Run from the repository root::

    python benchmarks/sqrt_failure_suite.py [--seeds 1000] [--long-seeds 4]
        [--long-steps 1000000] [--quick] [--output PATH]

``--quick`` runs 50 seeds, a long record of 2 x 10^5 samples and times the scan on
2000 samples, and writes no file unless ``--output`` is given (about 30 s); the full
run writes the table as markdown to ``benchmarks/results/sqrt_failure_suite.md``
(the machine and versions in its header) and takes about five minutes on two cores.
There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import casadi
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent / "tests"))

from ekf import without_gc  # noqa: E402  (benchmarks/ekf.py's timing helper)
from sqrt_cases import (  # noqa: E402  (tests/sqrt_cases.py)
    Case,
    filter_runs,
    mean_nees_band,
    nees_band,
    scan_function,
    step_runs,
    suite_cases,
)

import estim  # noqa: E402

FILTERS = {"EKF": estim.EKF, "UKF": estim.UKF}
FORMS = ("covariance", "sqrt")
COLUMNS = ("case", "filter", "form", "seeds", "steps/seed", "seeds failed", "failed steps",
           "not definite", "mean NEES [95 % band]", "in band", "every sample",
           "filter us/step", "ratio", "scan us/step", "ratio")


def scan_seconds(case: Case, ests: list[estim.Estimator], T: int, seed: int, repeats: int
                 ) -> list[float]:
    """Per filter of ``ests`` (the forms of one filter on the case), the median over
    ``repeats`` of the compiled scan's seconds per sample on one record of ``T``
    samples of the case (its inputs repeated where longer), the filters taking turns
    in each repeat."""
    if T != case.T:
        U = None if case.U is None else np.resize(case.U, (T - 1, case.U.shape[1]))
        case = dataclasses.replace(case, T=T, U=U)
    Y = case.records(1, seed)[1][0]
    calls = [scan_function(est, Y, case.U) for est in ests]
    for fun, args in calls:
        fun(*args)  # builds it
    times: list[list[float]] = [[] for _ in calls]
    for _ in range(repeats):
        for (fun, args), t in zip(calls, times, strict=True):
            t0 = time.perf_counter()
            fun(*args)
            t.append(time.perf_counter() - t0)
    return [statistics.median(t) / T for t in times]


def rows_of(case: Case, n: int, seed: int, repeats: int, timing_T: int,
            stepwise: bool = False) -> list[dict]:
    """The table's rows of one case: every filter and form on the same ``n`` records
    (by ``filter``, or with ``stepwise`` by ``step``), the scan timed on a record of
    ``max(T, timing_T)`` samples (``timing_T`` where ``stepwise``)."""
    X, Y = case.records(n, seed)
    nx = len(case.A)
    lo, hi = mean_nees_band(n, nx)
    lo_k, hi_k = nees_band(n, nx, case.T)
    rows = []
    for kind, cls in FILTERS.items():
        ests = []
        for form in FORMS:
            r = (step_runs if stepwise else filter_runs)(case, cls, form, n, records=(X, Y))
            nees = r["nees"]
            undefined = int(np.isnan(nees).sum())
            mean = float(np.mean(np.nanmean(nees, axis=1)))
            total = nees.sum(axis=0)
            rows.append({
                "case": case.name, "filter": kind, "form": form, "seeds": n,
                "steps": case.T, "seeds failed": int((r["failed"] > 0).sum()),
                "failed": int(r["failed"].sum()), "undefined": undefined,
                "mean": mean, "band": (lo, hi),
                "in band": not undefined and lo <= mean <= hi,
                "every": bool(np.all((total >= lo_k) & (total <= hi_k))),
                "filter s": float(np.median(r["seconds"])) / case.T,
            })
            ests.append(r["estimator"])
            del r, nees
        cov, sqrt = rows[-2:]
        cov["scan s"], sqrt["scan s"] = without_gc(lambda ests=ests: scan_seconds(
            case, ests, timing_T if stepwise else max(case.T, timing_T), seed + 1, repeats))
        sqrt["filter ratio"] = sqrt["filter s"] / cov["filter s"]
        sqrt["scan ratio"] = sqrt["scan s"] / cov["scan s"]
    return rows


def cells(row: dict) -> list[str]:
    """The table's cells of a row."""
    lo, hi = row["band"]
    mean = row["mean"]
    shown = f"{mean:.3f}" if abs(mean) < 1e4 else f"{mean:.2g}"

    def ratio(key: str) -> str:
        return f"{row[key]:.2f}" if key in row else ""

    return [row["case"], row["filter"], row["form"], str(row["seeds"]), str(row["steps"]),
            str(row["seeds failed"]), str(row["failed"]), str(row["undefined"]),
            f"{shown} [{lo:.3f}, {hi:.3f}]", "yes" if row["in band"] else "no",
            "yes" if row["every"] else "no", f"{row['filter s'] * 1e6:.2f}",
            ratio("filter ratio"), f"{row['scan s'] * 1e6:.2f}", ratio("scan ratio")]


def header() -> str:
    """The machine and the versions."""
    return (f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
            f"{platform.machine()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, numpy {np.__version__}, CasADi "
            f"{casadi.__version__}, estim {estim.__version__}")


def markdown(rows: list[dict], head: str, seconds: float, args: argparse.Namespace) -> str:
    lines = ["# Square-root filters: the failure suite", "",
             f"{head}; `python benchmarks/sqrt_failure_suite.py --seeds {args.seeds} "
             f"--long-seeds {args.long_seeds} --long-steps {args.long_steps}`, "
             f"{seconds:.0f} s.", "",
             "The cases, the columns and the NEES band are described in "
             "`benchmarks/sqrt_failure_suite.py`. Failed steps and samples without a "
             "positive definite covariance of the covariance form are what the suite "
             "shows (its mean NEES is over the samples that have one). \"filter "
             "us/step\" is the `filter` call's time over its samples (`step`'s for the "
             "long record run by step), which for a covariance form that fails includes "
             "its step-by-step recoveries; \"scan us/step\" is the compiled step alone, "
             f"on {args.timing_steps} samples.", "",
             "| " + " | ".join(COLUMNS) + " |",
             "|" + "|".join("---" if i < 3 else "---:" for i in range(len(COLUMNS))) + "|"]
    lines += ["| " + " | ".join(cells(r)) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=1000)
    parser.add_argument("--long-seeds", type=int, default=4)
    parser.add_argument("--long-steps", type=int, default=10 ** 6)
    parser.add_argument("--repeats", type=int, default=15,
                        help="repeats of the scan timing")
    parser.add_argument("--timing-steps", type=int, default=10 ** 4,
                        help="the samples of the record the scan is timed on")
    parser.add_argument("--seed", type=int, default=0, help="the records' random seed")
    parser.add_argument("--quick", action="store_true",
                        help="50 seeds, a long run of 2 x 10^5 samples, no file written")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args()
    if args.quick:
        args.seeds, args.long_seeds, args.long_steps = 50, 2, 2 * 10 ** 5
        args.timing_steps = 2000
    output = args.output or (None if args.quick else HERE / "results" / "sqrt_failure_suite.md")
    head = header()
    print(head, "\n")
    print(" | ".join(COLUMNS))
    t0 = time.perf_counter()
    rows = []
    for case in suite_cases():
        runs = [(case, args.seeds, False)]
        if case.name == "long run":
            runs.append((dataclasses.replace(case, T=args.long_steps, name="long run, by step"),
                         args.long_seeds, True))
        for c, n, stepwise in runs:
            for row in rows_of(c, n, args.seed, args.repeats, args.timing_steps, stepwise):
                rows.append(row)
                print(" | ".join(cells(row)), flush=True)
    seconds = time.perf_counter() - t0
    print(f"\n{seconds:.0f} s")
    if output is not None:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(markdown(rows, head, seconds, args))
        print(f"written to {output}")


if __name__ == "__main__":
    main()
