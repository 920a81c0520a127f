"""Autocovariance least squares: recovery against the record length, calibration of the
standard errors, and the EKF it tunes on van der Pol.

* Linear, three states and two outputs (``x+ = A x + w``, ``y = C x + v``, the first and
  third state measured), ``Q = diag(0.5, 0.2, 0.1)``, ``R = [[1, 0.3], [0.3, 0.5]]``:
  the estimates (diagonal Q, full R) with their standard errors from the first
  T = 1000, 4000, 16000 samples of one record (seed 1), identity and optimal weight.
* The same at T = 4000 over ``--seeds`` records: the spread of the estimates against
  the mean of the reported standard errors.
* van der Pol (``estim.scenarios.van_der_pol``, Q = 0.1^2 I, R = I), records of 10000
  samples (seeds 0-3): the estimates, and the RMSE of an EKF tuned with them against
  one with the true covariances on seeds 100-105 (1000 samples each); the time of a fit.

Run: ``python benchmarks/als.py [--seeds 30]``. No assertions.
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

import estim
from estim.tuning import als

A = np.array([[0.9, 0.2, 0.0], [0.0, 0.7, 0.1], [0.1, 0.0, 0.8]])
C = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
Q = np.diag([0.5, 0.2, 0.1])
R = np.array([[1.0, 0.3], [0.3, 0.5]])
NAMES = ["Q11", "Q22", "Q33", "R11", "R12", "R22"]
TRUTH = np.r_[np.diag(Q), R[0, 0], R[0, 1], R[1, 1]]
STRUCTURE = {"Q": "diagonal", "R": "full"}


def model() -> estim.Model:
    return estim.Model(states=["x1", "x2", "x3"], outputs=["y1", "y2"],
                       dynamics=lambda x, u, p: ca.mtimes(ca.DM(A), x),
                       output=lambda x, u, p: ca.mtimes(ca.DM(C), x), dt=1.0)


def record(T: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    W = rng.standard_normal((T, 3)) @ np.sqrt(Q)
    V = rng.standard_normal((T, 2)) @ np.linalg.cholesky(R).T
    x, Y = np.zeros(3), np.empty((T, 2))
    for k in range(T):
        Y[k] = C @ x + V[k]
        x = A @ x + W[k]
    return Y


def entries(res) -> tuple[np.ndarray, np.ndarray]:
    def pick(M):
        return np.r_[np.diag(M["Q"]), M["R"][0, 0], M["R"][0, 1], M["R"][1, 1]]
    return pick({"Q": res.Q, "R": res.R}), pick(res.stderr)


def recovery() -> None:
    m = model()
    Y = record(16000, seed=1)
    print("linear, 3 states, 2 outputs: estimate ± standard error (seed 1)")
    print(f"{'T':>6} {'weight':>9} " + " ".join(f"{n:>16}" for n in NAMES))
    print(f"{'':>6} {'truth':>9} " + " ".join(f"{v:>16.3g}" for v in TRUTH))
    for T in (1000, 4000, 16000):
        for weighting in ("identity", "optimal"):
            est, se = entries(als(m, Y[:T], structure=STRUCTURE, weighting=weighting))
            print(f"{T:>6} {weighting:>9} " + " ".join(f"{f'{e:.3f} ± {s:.3f}':>16}"
                                                      for e, s in zip(est, se, strict=True)))


def calibration(seeds: int) -> None:
    m = model()
    for weighting in ("identity", "optimal"):
        est, se = zip(*(entries(als(m, record(4000, 1000 + s), structure=STRUCTURE,
                                    weighting=weighting)) for s in range(seeds)),
                      strict=True)
        est, se = np.array(est), np.array(se)
        print(f"\nT = 4000, {seeds} records, {weighting} weight")
        print(f"{'':>24}" + " ".join(f"{n:>8}" for n in NAMES))
        for label, row in (("mean of the estimates", est.mean(0)),
                           ("spread (std)", est.std(0, ddof=1)),
                           ("mean standard error", se.mean(0))):
            print(f"{label:>24}" + " ".join(f"{v:>8.3g}" for v in row))


def van_der_pol() -> None:
    sc = estim.scenarios.van_der_pol(n_steps=10000)
    test = estim.scenarios.van_der_pol(n_steps=1000)

    def rmse(tuning):
        return np.mean([float(estim.rmse(estim.simulate(test, estim.EKF(test.model, **tuning),
                                                        seed=s))) for s in range(100, 106)])

    true = rmse(sc.tuning)
    print(f"\nvan der Pol, 10000 samples; EKF RMSE on seeds 100-105 with the true "
          f"covariances: {true:.4f}")
    print(f"{'seed':>4} {'diag Q ± se':>34} {'diag R ± se':>30} {'RMSE':>7} {'ratio':>6} "
          f"{'time s':>7}")
    for seed in range(4):
        log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed)
        t0 = time.perf_counter()
        res = als(sc.model, log.y, x0=sc.tuning["x0"], P0=sc.tuning["P0"])
        elapsed = time.perf_counter() - t0
        r = rmse({**sc.tuning, "Q": res.Q, "R": res.R})

        def fmt(M, S):
            return ", ".join(f"{M[i, i]:.4f} ± {S[i, i]:.4f}" for i in range(len(M)))
        print(f"{seed:>4} {fmt(res.Q, res.stderr['Q']):>34} {fmt(res.R, res.stderr['R']):>30} "
              f"{r:>7.4f} {r / true:>6.3f} {elapsed:>7.2f}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=30, help="records of the calibration")
    args = parser.parse_args(argv)
    recovery()
    calibration(args.seeds)
    van_der_pol()


if __name__ == "__main__":
    main()
