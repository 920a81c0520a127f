"""KU Leuven MPC course (H0E76A), session 5 -- state estimation, solved on estim.

The batch reactor is written once, in ``estim.models.batch_reactor()``: its CasADi
functions ``F, H`` and Jacobians ``F_x, H_x`` serve the simulation, your EKF and the MHE.
Run ``python solution.py [--out course_solution.png] [--seed 0] [--solver fatrop]``.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import estim  # noqa: E402
from estim.plotting import plot_estimates  # noqa: E402

SC = estim.scenarios.batch_reactor()  # truth x0 = (0.5, 0.05, 0), 400 steps of 0.25 s, x >= 0
MODEL = SC.model                      # F(x, u, p), H(x, u, p), F_x, H_x (CasADi), nu = 0
SIG_W, SIG_V, SIG_P = 0.002, 0.25, 0.5  # model noise, measurement noise, confidence in the guess
GUESS = np.array([1.0, 0.0, 4.0])       # the bad initial guess of the estimators
BURN_IN = 200                           # samples skipped by the second RMSE column (50 s)


def run(observer, seed: int = 0) -> estim.Log:
    """The course's ``simulate``: the seeded run of the reactor, seen by ``observer(y, log)``.

    An estim estimator (``estim.MHE``) runs in ``estim.simulate`` directly. The truth and
    the measurements do not depend on the estimator (the noise is drawn from the seed up
    front), so a course-style observer gets the measurements of that same run, one by one.
    """
    if isinstance(observer, estim.Estimator):
        return estim.simulate(SC, observer, seed=seed)
    record = estim.simulate(SC, estim.EKF(MODEL, **SC.tuning), seed=seed)
    log = estim.Log(MODEL.state_names, dt=MODEL.dt, estimator=type(observer).__name__)
    log.set("t", record.t)
    log.set("x", record.x)  # the truth; the observer logs "y" and its estimate "x_hat"
    for y in record.y:
        observer(y, log)
    return log


def placeholder(y, log):
    """The course's placeholder observer: it only logs the measurement and the guess."""
    log("y", y)
    log("x_hat", GUESS)


def plot(logs: dict[str, estim.Log], path=None, title: str = "", symlog: float | None = None):
    """Exercise 1: truth and estimates, one axis per concentration, with labels and a legend."""
    fig = plot_estimates(logs, title=title, symlog=symlog)
    fig.axes[-1].set_xlabel("time [s]")
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


class EKF:
    """Exercises 2-4: the extended Kalman filter on the model's CasADi functions.

    Measurement update at the prior (x̄, P̄): C = ∂h/∂x(x̄), L = P̄ Cᵀ (C P̄ Cᵀ + R)⁻¹,
    x̂ = x̄ + L (y - h(x̄)), P = P̄ - L C P̄, then x̂ clipped to x >= 0 (exercise 4).
    Time update: A = ∂f/∂x(x̂), x̄ = f(x̂), P̄ = A P Aᵀ + Q (G = I).
    """

    def __init__(self, model: estim.Model, x0, P0, Q, R, clipping: bool = False):
        self.model, self.clipping = model, clipping
        self.x, self.P = np.array(x0, float), np.array(P0, float)  # the prior x̄_0, P̄_0
        self.Q, self.R = np.array(Q, float), np.array(R, float)

    def clip(self, x: np.ndarray) -> np.ndarray:
        """Exercise 4: project the estimate onto the constraint x >= 0."""
        return np.maximum(x, 0.0)

    def __call__(self, y: np.ndarray, log) -> None:
        m, u = self.model, np.zeros(self.model.nu)
        C = m.H_x(self.x, u, m.p).full()
        L = self.P @ C.T @ np.linalg.inv(C @ self.P @ C.T + self.R)
        x = self.x + L @ (y - m.H(self.x, u, m.p).full().ravel())
        P = self.P - L @ C @ self.P
        if self.clipping:
            x = self.clip(x)
        A = m.F_x(x, u, m.p).full()
        self.x, self.P = m.F(x, u, m.p).full().ravel(), A @ P @ A.T + self.Q
        log("y", y)
        log("x_hat", x)


def mhe(horizon: int, solver: str = "fatrop") -> estim.MHE:
    r"""Exercises 5-6: the course's MHE, without prior (Γ = 0), as an ``estim.MHE``.

    At time T, with s = T - N + 1 (fewer samples while the window fills):
    min over x_s..x_T of Σ_{k=s}^{T-1} |x_{k+1} - f(x_k)|²/σ_w² + Σ_{k=s}^{T} |y_k - h(x_k)|²/σ_v²
    subject to 0 <= x_k <= 10; the estimate is x_T. ``Q, R`` are the covariances whose
    inverses weigh w and v; estim.MHE keeps the last N measurements.
    """
    return estim.MHE(MODEL, horizon=horizon, Q=SIG_W**2, R=SIG_V**2, x0=GUESS,
                     arrival_cost="none", lower=0.0, upper=10.0, solver=solver)


def compare(logs: dict[str, estim.Log], path) -> dict:
    """Final: the RMSE table and one figure with all four estimates; returns the numbers."""
    res = {"rmse": {}, "rmse_after_burn_in": {}, "min_estimate": {}}
    print(f"{'estimator':<12} {'RMSE':>8} {f'after {BURN_IN}':>10} {'min x̂':>8}")
    for name, log in logs.items():
        row = estim.rmse(log), estim.rmse(log, burn_in=BURN_IN), log.x_hat.min()
        for key, value in zip(res, row, strict=True):
            res[key][name] = float(value)
        print(f"{name:<12} {row[0]:8.4f} {row[1]:10.4f} {row[2]:8.4f}")
    plt.close(plot(logs, path, symlog=0.1,
                   title="Batch reactor from the guess (1, 0, 4) (symlog y, linear within ±0.1)"))
    return res


def main(argv: list[str] | None = None) -> dict:
    """Run the session; every figure goes to ``--out`` (the last one is the comparison)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="course_solution.png", help="PNG to write")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    parser.add_argument("--solver", default="fatrop", help="MHE solver: fatrop, ipopt, ...")
    args = parser.parse_args(argv)
    # exercise 1: plot a run of the placeholder observer
    plt.close(plot({"placeholder": run(placeholder, args.seed)}, args.out, title="exercise 1"))
    # exercises 3-4: the EKF from the bad guess, without and with clipping
    tuning = {"x0": GUESS, "P0": SIG_P**2 * np.eye(3), "Q": SIG_W**2 * np.eye(3),
              "R": SIG_V**2 * np.eye(1)}
    logs = {"EKF": run(EKF(MODEL, **tuning), args.seed),
            "clipped EKF": run(EKF(MODEL, **tuning, clipping=True), args.seed)}
    # exercises 5-6: MHE with N = 10 and N = 25
    for n in (10, 25):
        logs[f"MHE N={n}"] = run(mhe(n, args.solver), args.seed)
    # final: compare them
    res = compare(logs, args.out)
    print(f"wrote {args.out}")
    return res


if __name__ == "__main__":
    main()
