"""Cost of the iterated EKF's step against the EKF's, and of the iterated extended
smoother against full information, in the same process.

The textbook pendulum (``estim.models.sine_pendulum``, 300 samples, ``Q = diag(1e-4,
0.06)``, R = 0.01):

1. the median time of ``step`` over the record (``estim.replay``) and the time per sample
   of ``filter`` (the compiled scan: the step's arithmetic without Python's overhead) for
   ``EKF`` and ``EKF(iterations=K)``, K = 2, 3, 5, plain and damped, interpreted and with
   ``jit=True``: the ratio to the EKF's (the bound: at most K + 1; the iterated update
   adds one linearisation for its convergence test);
2. ``EKF(...).smooth(Y, iterations=100)`` (converged) against
   ``FullInformation(solver="gauss-newton")`` on the same record and the same prior,
   from the extended smoother's trajectory: time and the largest difference.

Medians over ``--repeats`` repeats, the range in brackets. Run from the repository root::

    python benchmarks/iterated.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import estim
from estim._compile import compiler


def span(values, digits=3) -> str:
    return (f"{statistics.median(values):.{digits}g} "
            f"[{min(values):.{digits}g}-{max(values):.{digits}g}]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    m = estim.models.sine_pendulum()
    Q = np.diag([1e-4, 0.06])
    tuning = {"Q": Q, "R": 0.01, "x0": [1.2, 0.0], "P0": 0.09}
    log = estim.simulate(m, None, x0=[1.5, 0.0], n_steps=300, Q=Q, R=0.01, seed=1)
    print("## 1. step time, ratio to the EKF's step\n")
    print("step: the median of `step` over the record (`estim.replay`, Python's overhead "
          "included); per sample: `filter` over the record (the compiled scan) divided by "
          "its length, the arithmetic of the step.\n")
    print("| filter | jit | step | ratio | per sample in `filter` | ratio |")
    print("|---|---|---|---|---|---|")
    variants = {"EKF": {}, **{f"EKF(iterations={K})": {"iterations": K} for K in (2, 3, 5)},
                "EKF(iterations=5, damping='line-search')": {"iterations": 5,
                                                             "damping": "line-search"},
                "EKF(iterations=5, damping='levenberg-marquardt')": {
                    "iterations": 5, "damping": "levenberg-marquardt"}}
    for jit in ([False, True] if compiler() else [False]):
        times: dict[str, list[float]] = {}
        scans: dict[str, list[float]] = {}
        for label, kw in variants.items():
            est = estim.EKF(m, **tuning, **kw, jit=jit)
            estim.replay(est, log.y)  # builds, loads
            est.filter(log.y)
            times[label] = [float(np.median(estim.replay(est, log.y).solve_time))
                            for _ in range(args.repeats)]
            scans[label] = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                for _ in range(5):
                    est.filter(log.y)
                scans[label].append((time.perf_counter() - t0) / 5 / len(log.y))
        base, base_scan = statistics.median(times["EKF"]), statistics.median(scans["EKF"])
        for label in variants:
            runs, scan = times[label], scans[label]
            print(f"| {label} | {jit} | {span([t * 1e6 for t in runs])} µs | "
                  f"{span([t / base for t in runs])} | {span([t * 1e6 for t in scan])} µs | "
                  f"{span([t / base_scan for t in scan])} |", flush=True)
    print("\n## 2. the iterated smoother against full information\n")
    ekf = estim.EKF(m, **tuning)
    first = ekf.smooth(log.y)
    ieks, fie = [], []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = ekf.smooth(log.y, iterations=100)
        ieks.append(time.perf_counter() - t0)
        solver = estim.FullInformation(m, **tuning, solver="gauss-newton",
                                       solver_options={"xtol": 1e-15, "ftol": 1e-25,
                                                       "max_iter": 500})
        solver.fit(log.y, guess=first.x)  # builds
        t0 = time.perf_counter()
        fit = solver.fit(log.y, guess=first.x)
        fie.append(time.perf_counter() - t0)
    print(f"iterated smoother: {res.iterations} passes, converged {res.converged}, "
          f"{span([t * 1e3 for t in ieks])} ms; full information (Gauss-Newton, "
          f"{fit.iterations} iterations): {span([t * 1e3 for t in fie])} ms; largest "
          f"difference of the means {np.abs(res.x - fit.x).max():.2g}, of the covariances "
          f"{np.abs(res.P - fit.P).max():.2g}")


if __name__ == "__main__":
    main()
