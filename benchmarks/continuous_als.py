"""Autocovariance least squares of a spectral density on irregular stamps: how often the
estimate lies within 2 and 3 of its standard errors, against maximum likelihood.

The records: the Wiener velocity (position measured with variance R = 0.05, a white
acceleration of density q = 0.7 entering through ``noise_input = [0, 1]^T``), ``samples``
samples at stamps whose intervals are log-uniform in [shortest, longest] (default
[0.01, 0.5] s), the exact transition of each interval; one record per seed. On each:
``estim.tuning.als(..., continuous=True, t=t, iterations=2)`` (the time-varying
autocovariance equations along the continuous-discrete EKF, two passes from the default
start) and ``estim.tuning.maximum_likelihood(..., continuous=True, t=t)``. Printed: the
standardised errors' mean and standard deviation (0 and 1 for honest standard errors), the
share within 2 and 3 standard errors with its binomial 95 % interval, the estimates' root
mean square error, and the time per record (median and range).

Run from the repository root::

    python benchmarks/continuous_als.py [--seeds 100] [--samples 2000]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np
from scipy import stats

import estim

Q_DENSITY, R_VAR = 0.7, 0.05


def wiener_velocity() -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"],
                       ode=lambda x, u, p: ca.vertcat(x[1], 0), output=lambda x, u, p: x[0],
                       variable_dt=True, dt=0.1, noise_input=[[0.0], [1.0]])


def record(seed: int, samples: int, shortest: float, longest: float
           ) -> tuple[np.ndarray, np.ndarray]:
    """``(t, Y)``: the stamps and the measured positions."""
    rng = np.random.default_rng(seed)
    dts = np.exp(rng.uniform(np.log(shortest), np.log(longest), samples - 1))
    x, Y = np.array([0.0, 1.0]), []
    for k in range(samples):
        if k:
            dt = dts[k - 1]
            Qd = Q_DENSITY * np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
            x = np.array([[1.0, dt], [0.0, 1.0]]) @ x + rng.multivariate_normal(np.zeros(2),
                                                                                  Qd)
        Y.append([x[0] + rng.normal(0.0, np.sqrt(R_VAR))])
    return np.concatenate([[0.0], np.cumsum(dts)]), np.array(Y)


def share(inside: np.ndarray) -> str:
    """The share of True with its Clopper-Pearson 95 % interval."""
    n, k = len(inside), int(inside.sum())
    lo = stats.beta.ppf(0.025, k, n - k + 1) if k else 0.0
    hi = stats.beta.ppf(0.975, k + 1, n - k) if k < n else 1.0
    return f"{k / n:.0%} [{lo:.0%}, {hi:.0%}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--shortest", type=float, default=0.01)
    parser.add_argument("--longest", type=float, default=0.5)
    args = parser.parse_args()
    m = wiener_velocity()
    prior = {"x0": [0.0, 1.0], "P0": np.diag([1.0, 2.0])}
    rows: dict[str, dict[str, list[float]]] = {k: {"q": [], "R": [], "zq": [], "zR": [],
                                                   "time": []} for k in ("als", "ml")}
    for seed in range(args.seeds):
        t, Y = record(1000 + seed, args.samples, args.shortest, args.longest)
        for name in ("als", "ml"):
            t0 = time.perf_counter()
            if name == "als":
                res = estim.tuning.als(m, Y, t=t, continuous=True, iterations=2, **prior)
            else:
                res = estim.tuning.maximum_likelihood(m, Y, t=t, continuous=True, starts=1,
                                                      **prior)
            r = rows[name]
            r["time"].append(time.perf_counter() - t0)
            r["q"].append(res.Q[0, 0])
            r["R"].append(res.R[0, 0])
            r["zq"].append((res.Q[0, 0] - Q_DENSITY) / res.stderr["Q"][0, 0])
            r["zR"].append((res.R[0, 0] - R_VAR) / res.stderr["R"][0, 0])
    print(f"# The Wiener velocity's density (q = {Q_DENSITY}) and R ({R_VAR}) from "
          f"{args.seeds} records of {args.samples} samples, intervals log-uniform in "
          f"[{args.shortest:g}, {args.longest:g}] s\n")
    print("| method | entry | RMSE | z mean | z sd | within 2 se | within 3 se | "
          "time per record (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, label in (("als", "ALS, 2 passes"), ("ml", "maximum likelihood")):
        r = rows[name]
        times = np.array(r["time"])
        for entry, truth in (("q", Q_DENSITY), ("R", R_VAR)):
            z = np.array(r["z" + entry])
            rmse = float(np.sqrt(np.mean((np.array(r[entry]) - truth) ** 2)))
            print(f"| {label} | {entry} | {rmse:.4g} | {z.mean():+.2f} | {z.std():.2f} | "
                  f"{share(np.abs(z) < 2)} | {share(np.abs(z) < 3)} | "
                  f"{np.median(times):.2f} ({times.min():.2f}-{times.max():.2f}) |")


if __name__ == "__main__":
    main()
