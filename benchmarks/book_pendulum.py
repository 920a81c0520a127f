"""The Gaussian filters and smoothers of Särkkä & Svensson, *Bayesian Filtering and
Smoothing* (2nd ed., 2023) on the book's pendulum record (``examples/data/book_pendulum.npz``,
from the book's companion repository) with the book's settings, beside the RMSEs the
companion notebooks print.

The settings (``python/example_notebooks/pendulum_*.ipynb``): Euler steps of 0.01 s,
``R = 0.1``, ``Q = 0.01 [[dt^3/3, dt^2/2], [dt^2/2, dt]]``, the prior ``(0, 0)``,
``P0 = I`` one step before the first measurement (a NaN row prepended), the unscented
filter's ``alpha = 1``, ``beta = 0``, ``kappa = 3 - n``, Gauss-Hermite of order 5, 10
iterations of the iterated filter and smoother; the posterior-linearisation filter and
smoother (IPLF, IPLS: rows IPLKF and IPLRTS) with Gauss-Hermite of order 3 and 10
iterations. The RMSE of the angle.

Then the book's car-tracking record (``examples/data/book_car_track.npz``): its Kalman
filter and RTS smoother. Then the particle filter and smoother on the record of the
book's particle-filter notebook, over ``--pf-seeds`` seeds (default 100). Run from the
repository root::

    python benchmarks/book_pendulum.py [--pf-seeds 100]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import estim
from estim.solvers.kalman.continuous import van_loan

ROOT = Path(__file__).resolve().parent.parent
BOOK = {"EKF": 0.16830859061153763, "ERTS": 0.057446202494837,
        "IEKF": 0.16547516472119136, "IERTS": 0.03463604419042699,
        "UKF": 0.09524392125923083, "URTS": 0.036617555415464256,
        "CKF": 0.1141966031380275, "CRTS": 0.04064624229594188,
        "GHKF": 0.0998062421916222, "GHRTS": 0.03710181978632009,
        "IPLKF": 0.14055766458714145, "IPLRTS": 0.034733224044175594}


def main() -> None:
    data = np.load(ROOT / "examples" / "data" / "book_pendulum.npz")
    sc = estim.scenarios.book_pendulum()
    m, tuning = sc.model, sc.tuning
    Y = np.vstack([[np.nan], data["Y"][:, None]])  # the prior one step before y_0

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x[1:, 0] - data["X"][:, 0]) ** 2)))

    filters = {"E": estim.EKF(m, **tuning), "IE": estim.EKF(m, **tuning, iterations=10),
               "U": estim.UKF(m, **tuning, alpha=1.0, beta=0.0, kappa=1.0),
               "C": estim.UKF(m, **tuning, points="cubature"),
               "GH": estim.UKF(m, **tuning, points="gauss-hermite", order=5),
               "IPL": estim.UKF(m, **tuning, points="gauss-hermite", order=3,
                                iterations=10)}
    print("| method | book | estim | difference |")
    print("|---|---|---|---|")
    for kind, est in filters.items():
        for name, value in ((f"{kind}KF", rmse(est.filter(Y).x)),
                            (f"{kind}RTS", rmse(est.smooth(Y).x))):
            print(f"| {name} | {BOOK[name]:.6f} | {value:.6f} | "
                  f"{abs(value - BOOK[name]):.1e} |")
    car_track()


def car_track() -> None:
    """The book's car-tracking record (``car_track`` notebook): the Kalman filter and RTS
    smoother, the RMSE of the positions as the book computes it."""
    car = np.load(ROOT / "examples" / "data" / "book_car_track.npz")
    m = estim.models.constant_velocity(dt=0.1)  # the white acceleration's Q, q = 1:
    Q = van_loan(np.eye(4, k=2), np.diag([0.0, 0.0, 1.0, 1.0]), 0.1)[1]
    ekf = estim.EKF(m, Q=Q, R=0.25 * np.eye(2), x0=[0.0, 0.0, 1.0, -1.0], P0=np.eye(4))
    Y = np.vstack([[np.nan, np.nan], car["Y"]])

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((x[1:, :2] - car["X"][:, :2]) ** 2, axis=1))))

    for name, book, value in (("car KF", 0.4253824660526518, rmse(ekf.filter(Y).x)),
                              ("car RTS", 0.26497104638205465, rmse(ekf.smooth(Y).x))):
        print(f"| {name} | {book:.6f} | {value:.6f} | {abs(value - book):.1e} |")


def particle_filters(seeds: int) -> None:
    """The book's ``pendulum_pf`` notebook: its own record (``book_pendulum_pf.npz``, the
    notebook's ``generate_pendulum`` with ``RandomState(1)``), the prior ``(1.6, 0)``,
    ``P0 = 0.1 I`` one step before the first measurement, the bootstrap filter with 1000
    particles and stratified resampling at every step, backward simulation of 100
    trajectories. The book prints one run; here the RMSE over ``seeds`` seeds (compiled
    filter): its mean, standard deviation and 2.5-97.5 % range, and where the book's run
    falls (in standard deviations from the mean)."""
    data = np.load(ROOT / "examples" / "data" / "book_pendulum_pf.npz")
    sc = estim.scenarios.book_pendulum()
    tuning = {**sc.tuning, "x0": [1.6, 0.0], "P0": 0.1 * np.eye(2)}
    Y = np.vstack([[np.nan], data["Y"][:, None]])

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x[1:, 0] - data["X"][:, 0]) ** 2)))

    runs: dict[str, list[float]] = {"PF": [], "PF-BS": []}
    for seed in range(seeds):
        pf = estim.ParticleFilter(sc.model, **tuning, n_particles=1000,
                                  resampling="stratified", ess_threshold=1.0, seed=seed,
                                  jit=True)
        res = pf.smooth(Y, n_paths=100)
        runs["PF"].append(rmse(res.x_filtered))
        runs["PF-BS"].append(rmse(res.x))
    print(f"\n| method | book (one run) | estim, {seeds} seeds: mean ± sd | 2.5-97.5 % | "
          f"book's run |")
    print("|---|---|---|---|---|")
    for name, book in (("PF", 0.07992204807089615), ("PF-BS", 0.0305902657204688)):
        v = np.array(runs[name])
        mean, sd = float(v.mean()), float(v.std(ddof=1))
        lo, hi = np.quantile(v, [0.025, 0.975])
        print(f"| {name} | {book:.4f} | {mean:.4f} ± {sd:.4f} | {lo:.4f}-{hi:.4f} | "
              f"{(book - mean) / sd:+.2f} sd |")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pf-seeds", type=int, default=100)
    args = parser.parse_args()
    main()
    if args.pf_seeds:
        particle_filters(args.pf_seeds)
