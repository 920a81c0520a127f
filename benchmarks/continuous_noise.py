"""Continuous-time process noise on irregular stamps: the continuous-discrete EKF and UKF
(``Qc=``) against today's per-transition ``Q``, on Lorenz-63 with a diffusion.

The system: Lorenz-63 (sigma = 10, rho = 28, beta = 8/3) driven by a Brownian motion of unit
intensity on each state (``Qc = I``, ``noise_input`` the identity), every state measured
with unit variance (``R = I``), at stamps whose intervals are log-uniform in [0.01, 0.5].
The truth is integrated by Euler-Maruyama with steps of at most 1e-3 between the stamps
(each seed its own stamps and noise).

Filters, all with the model's Runge-Kutta (``--substeps`` per interval, 50 by default: an
interval of 0.5 needs them for stability), from the prior N(x_0 + 1, I):

* ``CD-EKF``: ``EKF(Qc=I, substeps=n)``, the moment equations per interval;
* ``CD-UKF``: ``UKF(Qc=I, substeps=n)``, the sigma-point moment equations;
* ``EKF, Q per transition``: ``EKF(Q=mean interval * I)``, the per-transition covariance
  of the mean interval (what a user without ``Qc`` would choose);
* ``CD-MHE``: ``MHE(Qc=I, horizon=10)`` (filtering arrival cost), each defect weighed by
  the inverse of its own interval's Q_d, linearised at the estimate;
* ``MHE, Q per transition``: ``MHE(Q=mean interval * I, horizon=10)``.

The MHE rows are run step by step (``estim.replay``; ``--no-windows`` leaves them out).

Reported per filter over the seeds: the RMSE, the average NEES/n (all steps and seeds)
and the fraction of the time steps whose NEES averaged over the seeds lies in its 95 %
chi-square band ([chi2_0.025(3 S) / S, chi2_0.975(3 S) / S] for S seeds: 95 % for a
consistent filter); NEES/n by the interval's length (short, middle, long thirds) shows
where the per-transition Q is wrong. The step cost: ``filter`` per sample against the
EKF's with the same model and a per-transition Q (median and range of three runs).

Run from the repository root::

    python benchmarks/continuous_noise.py [--seeds 100] [--samples 200] [--substeps 50]
"""

from __future__ import annotations

import argparse
import statistics
import time

import casadi as ca
import numpy as np
from scipy import stats

import estim

SIGMA, RHO, BETA = 10.0, 28.0, 8.0 / 3.0


def lorenz(substeps: int) -> estim.Model:
    return estim.Model(
        states=["x", "y", "z"], outputs=["x_m", "y_m", "z_m"],
        ode=lambda x, u, p: ca.vertcat(p["sigma"] * (x[1] - x[0]),
                                       x[0] * (p["rho"] - x[2]) - x[1],
                                       x[0] * x[1] - p["beta"] * x[2]),
        output=lambda x, u, p: x, params={"sigma": SIGMA, "rho": RHO, "beta": BETA},
        dt=0.1, variable_dt=True, substeps=substeps, name="Lorenz-63 with diffusion")


def drift(X: np.ndarray) -> np.ndarray:
    x, y, z = X
    return np.array([SIGMA * (y - x), x * (RHO - z) - y, x * y - BETA * z])


def record(seed: int, T: int, shortest: float = 0.01, longest: float = 0.5
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps ``t (T,)``, truth ``X (T, 3)`` and measurements ``Y (T, 3)`` of one seed."""
    rng = np.random.default_rng(seed)
    dts = np.exp(rng.uniform(np.log(shortest), np.log(longest), T - 1))
    x = np.array([1.0, 1.0, 25.0]) + rng.normal(size=3)
    X = [x]
    for dt in dts:
        n = int(np.ceil(dt / 1e-3))
        h = dt / n
        for _ in range(n):
            x = x + h * drift(x) + np.sqrt(h) * rng.normal(size=3)
        X.append(x)
    X = np.array(X)
    return np.concatenate([[0.0], np.cumsum(dts)]), X, X + rng.normal(size=X.shape)


def run(est, Y: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """Estimates, covariances and statuses over a record: ``filter`` where the estimator
    has it, else step by step."""
    if hasattr(est, "filter"):
        res = est.filter(Y, t=t)
        return res.x, res.P, list(res.status)
    log = estim.replay(est, Y, t=t)
    return log.x_hat, log.P, list(log.status)


def span(values, digits=3) -> str:
    return (f"{statistics.median(values):.{digits}g} "
            f"[{min(values):.{digits}g}-{max(values):.{digits}g}]")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--samples", type=int, default=200)
    parser.add_argument("--substeps", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--shortest", type=float, default=0.01,
                        help="the shortest interval (default 0.01)")
    parser.add_argument("--longest", type=float, default=0.5,
                        help="the longest interval (default 0.5)")
    parser.add_argument("--no-windows", action="store_true",
                        help="leave out the moving-horizon estimators")
    args = parser.parse_args()
    S, T, n = args.seeds, args.samples, args.substeps
    m = lorenz(n)
    records = [record(s, T, args.shortest, args.longest) for s in range(S)]
    mean_dt = float(np.mean([np.diff(t).mean() for t, _, _ in records]))
    tuning = {"R": np.eye(3), "P0": np.eye(3)}
    filters = {
        "CD-EKF": lambda x0: estim.EKF(m, Qc=np.eye(3), substeps=n, x0=x0, **tuning),
        "CD-UKF": lambda x0: estim.UKF(m, Qc=np.eye(3), substeps=n, x0=x0, **tuning),
        "EKF, Q per transition": lambda x0: estim.EKF(m, Q=mean_dt * np.eye(3), x0=x0,
                                                      **tuning)}
    if not args.no_windows:
        filters["CD-MHE"] = lambda x0: estim.MHE(m, horizon=10, Qc=np.eye(3), x0=x0,
                                                 **tuning)
        filters["MHE, Q per transition"] = lambda x0: estim.MHE(
            m, horizon=10, Q=mean_dt * np.eye(3), x0=x0, **tuning)
    lo, hi = stats.chi2.ppf([0.025, 0.975], 3 * S) / S
    print(f"# Lorenz-63 with diffusion on irregular stamps: {S} seeds x {T} samples, "
          f"intervals log-uniform in [{args.shortest:g}, {args.longest:g}] (mean {mean_dt:.3f}), "
          f"{n} "
          f"Runge-Kutta sub-steps per interval\n")
    print(f"95 % band of the NEES averaged over {S} seeds at one step: "
          f"[{lo / 3:.3f}, {hi / 3:.3f}] (as NEES/n)\n")
    print("| filter | RMSE | NEES/n | steps in the 95 % band | NEES/n, short / middle / "
          "long intervals | failed steps |")
    print("|---|---|---|---|---|---|")
    results = {}
    for name, make in filters.items():
        est = make(np.array([1.0, 1.0, 25.0]))
        nees, err2, dt_of, failed = np.empty((S, T)), [], [], 0
        for s, (t, X, Y) in enumerate(records):
            est.reset(x0=X[0] + 1.0)
            x, P, status = run(est, Y, t)
            e = x - X
            nees[s] = np.einsum("ka,kab,kb->k", e, np.linalg.inv(P), e)
            err2.append((e ** 2).mean())
            dt_of.append(np.concatenate([[np.nan], np.diff(t)]))
            failed += sum(st.startswith("failed") for st in status)
        dts = np.concatenate(dt_of)
        flat = nees.ravel()
        thirds = np.nanquantile(dts, [1 / 3, 2 / 3])
        parts = [np.nanmean(flat[(dts > a) & (dts <= b)]) / 3
                 for a, b in ((0, thirds[0]), (thirds[0], thirds[1]), (thirds[1], np.inf))]
        inside = np.mean((nees.mean(axis=0) >= lo) & (nees.mean(axis=0) <= hi))
        results[name] = nees
        print(f"| {name} | {np.sqrt(np.mean(err2)):.4g} | {flat.mean() / 3:.3f} | "
              f"{100 * inside:.0f} % | {parts[0]:.2f} / {parts[1]:.2f} / {parts[2]:.2f} | "
              f"{failed} |", flush=True)
    print("\n## Step cost: per sample (`filter`, or `replay` for the MHE), against the EKF "
          "with a per-transition Q\n")
    t, X, Y = records[0]
    cost = {}
    for name, make in filters.items():
        est = make(X[0] + 1.0)
        run(est, Y, t)  # builds
        cost[name] = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            for _ in range(3):
                est.reset(x0=X[0] + 1.0)
                run(est, Y, t)
            cost[name].append((time.perf_counter() - t0) / 3 / T)
    base = cost["EKF, Q per transition"]
    print("| filter | per sample | ratio |")
    print("|---|---|---|")
    for name, runs in cost.items():
        print(f"| {name} | {span([c * 1e6 for c in runs])} µs | "
              f"{span([c / statistics.median(base) for c in runs])} |")


if __name__ == "__main__":
    main()
