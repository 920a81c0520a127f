"""The square-root form of ``estim.EKF`` and ``estim.UKF`` (``form="sqrt"``) against the
covariance form: the time of a step, and the failures on hard linear-Gaussian cases.

Part 1, the step: both forms of each filter run in the same process on the same
measurement record of the van der Pol oscillator (2 states, both measured) and the
batch reactor (3 states, 1 output) of ``estim.scenarios``, every step timed with
``time.perf_counter`` over the whole record, the garbage collector off, the forms
taking turns in each repeat; the table gives the median seconds per step and the ratio
sqrt / covariance (the target is at most 1.3). The estimates of both forms are checked
to agree to 1e-10 first.

Part 2, the failures: the cases of ``tests/sqrt_cases.py`` (a constant-velocity target
measured almost exactly, a badly scaled state, a joint state/parameter estimate with
tiny parameter noise), each run step by step for many seeds with both forms of both
filters. The table gives per case and form the failed steps (``info.success`` false),
the steps whose covariance has no Cholesky factor (the filter's own factor in the
square-root form), whether the NEES summed over the seeds stays at every sample inside
the band that holds with 95 % probability over the whole run (chi-square with
``seeds * nx`` degrees of freedom, Bonferroni over the samples), and the median step
time.

Run from the repository root::

    python benchmarks/sqrt_filters.py [--repeats 20] [--seeds 50]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from ekf import without_gc  # noqa: E402  (benchmarks/ekf.py's timing helper)
from sqrt_cases import cases, nees_band, run  # noqa: E402  (tests/sqrt_cases.py)

import estim  # noqa: E402

FILTERS = {"EKF": estim.EKF, "UKF": estim.UKF}


def replay(est: estim.Estimator, Y: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Seconds per step over the record after a reset, the estimates and covariances."""
    est.reset()
    X, P = np.empty((len(Y), est.model.nx)), np.empty((len(Y), est.model.nx, est.model.nx))

    def go():
        t0 = time.perf_counter()
        for k, y in enumerate(Y):
            X[k] = est.step(y)
            P[k] = est.info.P
        return time.perf_counter() - t0

    return without_gc(go) / len(Y), X, P


def step_times(repeats: int) -> list[tuple[str, str, float, float, float]]:
    """``(scenario, filter, covariance s/step, sqrt s/step, ratio)`` rows."""
    rows = []
    for name in ("van_der_pol", "batch_reactor"):
        sc = estim.scenarios.get(name)
        for kind, cls in FILTERS.items():
            forms = {form: cls(sc.model, **sc.tuning, form=form)
                     for form in ("covariance", "sqrt")}
            Y = estim.simulate(sc, forms["covariance"], seed=0).y
            _, Xc, Pc = replay(forms["covariance"], Y)
            _, Xs, Ps = replay(forms["sqrt"], Y)
            assert np.abs(Xs - Xc).max() < 1e-10 and np.abs(Ps - Pc).max() < 1e-10
            times: dict[str, list[float]] = {"covariance": [], "sqrt": []}
            for _ in range(repeats):
                for form, est in forms.items():
                    times[form].append(replay(est, Y)[0])
            cov, sqrt = (statistics.median(times[f]) for f in ("covariance", "sqrt"))
            rows.append((name, kind, cov, sqrt, sqrt / cov))
    return rows


def failure_suite(n_seeds: int) -> list[tuple]:
    """``(case, filter, form, failed steps, indefinite steps, NEES in band, s/step)``."""
    rows = []
    for case in cases():
        lo, hi = nees_band(n_seeds, len(case.A), case.T)
        for kind, cls in FILTERS.items():
            for form in ("covariance", "sqrt"):
                runs = [run(case, cls, form, seed) for seed in range(n_seeds)]
                seconds = statistics.median(r["seconds"] for r in runs)
                nees = np.sum([r["nees"] for r in runs], axis=0)
                inside = bool(np.all((nees >= lo) & (nees <= hi)))
                rows.append((case.name, kind, form, sum(r["failed"] for r in runs),
                             sum(r["indefinite"] for r in runs), inside, seconds))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--seeds", type=int, default=50)
    args = parser.parse_args()
    print(f"estim {estim.__version__}, median of {args.repeats} repeats\n")
    print(f"{'scenario':15s} {'filter':6s} {'covariance':>12s} {'sqrt':>12s} {'ratio':>6s}")
    for name, kind, cov, sqrt, ratio in step_times(args.repeats):
        print(f"{name:15s} {kind:6s} {cov * 1e6:9.2f} us {sqrt * 1e6:9.2f} us {ratio:6.2f}")
    print(f"\nfailure suite, {args.seeds} seeds per case (steps summed over the seeds; "
          f"step: the median over the seeds of the mean time of a step)\n")
    print(f"{'case':24s} {'filter':6s} {'form':10s} {'failed':>7s} {'indefinite':>10s} "
          f"{'NEES in band':>12s} {'step':>9s}")
    for case, kind, form, failed, indefinite, inside, seconds in failure_suite(args.seeds):
        print(f"{case:24s} {kind:6s} {form:10s} {failed:7d} {indefinite:10d} "
              f"{'yes' if inside else 'no':>12s} {seconds * 1e6:6.1f} us")


if __name__ == "__main__":
    main()
