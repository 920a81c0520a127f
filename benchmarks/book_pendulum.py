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
filter and RTS smoother. Run from the repository root::

    python benchmarks/book_pendulum.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import estim

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
    dt = 0.1
    A = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    Q = np.array([[dt**3 / 3, 0, dt**2 / 2, 0], [0, dt**3 / 3, 0, dt**2 / 2],
                  [dt**2 / 2, 0, dt, 0], [0, dt**2 / 2, 0, dt]])
    H = np.eye(2, 4)
    m = estim.Model(states=["x", "y", "vx", "vy"], outputs=["px", "py"],
                    dynamics=lambda x, u, p: A @ x, output=lambda x, u, p: H @ x, name="car")
    ekf = estim.EKF(m, Q=Q, R=0.25 * np.eye(2), x0=[0.0, 0.0, 1.0, -1.0], P0=np.eye(4))
    Y = np.vstack([[np.nan, np.nan], car["Y"]])

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((x[1:, :2] - car["X"][:, :2]) ** 2, axis=1))))

    for name, book, value in (("car KF", 0.4253824660526518, rmse(ekf.filter(Y).x)),
                              ("car RTS", 0.26497104638205465, rmse(ekf.smooth(Y).x))):
        print(f"| {name} | {book:.6f} | {value:.6f} | {abs(value - book):.1e} |")


if __name__ == "__main__":
    main()
