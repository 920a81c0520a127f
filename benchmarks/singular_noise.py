"""Cost of a singular process noise in the windowed estimators, against the same problem
with a tiny definite noise instead, in the same process.

The textbook pendulum (``estim.models.sine_pendulum``, ``y = sin(theta) + v``, R = 0.01)
with noise on the angular rate only, ``Q = diag(0, 0.06)``, 300 samples (seed 0), the
prior ``x0 = (1.2, 0)``, ``P0 = 0.09 I``:

* MHE, ``N = 20``, filtering arrival cost: the singular ``Q`` (the constrained window,
  Ipopt, the default) against ``Q = diag(1e-6, 0.06)`` with the structured Gauss-Newton
  solver (the default) and with Ipopt (the plain NLP formulation, the baseline): the
  median time per step after the window is full, and the RMSE;
* full information over the record, from the smoother's trajectory: the same three.

Times are medians over ``--repeats`` runs (the range in brackets). Run from the
repository root::

    python benchmarks/singular_noise.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import estim


def span(values, scale=1.0, digits=3) -> str:
    v = [x * scale for x in values]
    return f"{statistics.median(v):.{digits}g} [{min(v):.{digits}g}-{max(v):.{digits}g}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    m = estim.models.sine_pendulum()
    Q = np.diag([0.0, 0.06])
    prior = {"R": 0.01, "x0": [1.2, 0.0], "P0": 0.09}
    log = estim.simulate(m, None, x0=[1.5, 0.0], n_steps=300, Q=Q, R=0.01, seed=0)
    guess = estim.EKF(m, Q=Q, **prior).smooth(log.y).x
    cases = {"singular Q, Ipopt (constrained window)": (Q, "auto"),
             "Q = diag(1e-6, 0.06), Gauss-Newton": (np.diag([1e-6, 0.06]), "auto"),
             "Q = diag(1e-6, 0.06), Ipopt (baseline)": (np.diag([1e-6, 0.06]), "ipopt")}
    print("| estimator | case | time | ratio to the baseline | RMSE |")
    print("|---|---|---|---|---|")
    for what in ("MHE, N = 20: per step", "full information, 300 samples: per fit"):
        times, rmse = {}, {}
        for label, (Qc, solver) in cases.items():
            runs = []
            for _ in range(args.repeats):
                if what.startswith("MHE"):
                    mhe = estim.MHE(m, horizon=20, Q=Qc, solver=solver, **prior)
                    run = estim.replay(mhe, log.y)
                    runs.append(float(np.median(run.solve_time[20:])))
                    rmse[label] = float(estim.rmse(run, truth=log))
                else:
                    fie = estim.FullInformation(m, Q=Qc, solver=solver, **prior)
                    fie.fit(log.y, guess=guess)  # builds
                    t0 = time.perf_counter()
                    fit = fie.fit(log.y, guess=guess)
                    runs.append(time.perf_counter() - t0)
                    rmse[label] = float(estim.rmse(fit, truth=log))
            times[label] = runs
        base = statistics.median(times["Q = diag(1e-6, 0.06), Ipopt (baseline)"])
        for label, runs in times.items():
            ratio = [t / base for t in runs]
            unit, scale = ("ms", 1e3)
            print(f"| {what} | {label} | {span(runs, scale)} {unit} | {span(ratio)} | "
                  f"{rmse[label]:.4f} |", flush=True)


if __name__ == "__main__":
    main()
