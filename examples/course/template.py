"""KU Leuven MPC course (H0E76A), session 5 -- state estimation, exercise template on estim.

The batch reactor is written once, in ``estim.models.batch_reactor()``: its CasADi
functions ``F, H`` and Jacobians ``F_x, H_x`` serve the simulation, your EKF and the MHE.
Fill in the ``TODO (exercise N)`` gaps in order and run ``python template.py``: it stops
with ``NotImplementedError: exercise N ...`` at the next gap. ``solution.py`` is the key.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import estim  # noqa: E402

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
    # TODO (exercise 1): one matplotlib axis per state (MODEL.state_names): the truth
    #  log.x[:, i] of the first log against log.t, every log's estimate log.x_hat[:, i]
    #  labelled with its name; a legend; ax.set_yscale("symlog", linthresh=symlog) when
    #  symlog is given; save to path if given; return the figure. Compare with fig. 1.
    raise NotImplementedError("exercise 1: plot the truth and the estimates in plot()")


class EKF:
    """Exercises 2-4: the extended Kalman filter on the model's CasADi functions.

    TODO (exercise 2): write down the measurement update and the time update here.
    """

    def __init__(self, model: estim.Model, x0, P0, Q, R, clipping: bool = False):
        self.model, self.clipping = model, clipping
        self.x, self.P = np.array(x0, float), np.array(P0, float)  # the prior x̄_0, P̄_0
        self.Q, self.R = np.array(Q, float), np.array(R, float)

    def clip(self, x: np.ndarray) -> np.ndarray:
        """Exercise 4: project the estimate onto the constraint x >= 0."""
        # TODO (exercise 4)
        raise NotImplementedError("exercise 4: clip the estimate to x >= 0 in EKF.clip()")

    def __call__(self, y: np.ndarray, log) -> None:
        # TODO (exercise 3): the measurement update at the prior (self.x, self.P) with
        #  C = self.model.H_x(x, u, p).full() (u = np.zeros(self.model.nu), p = self.model.p),
        #  a Kalman gain and the output self.model.H(x, u, p); if self.clipping:
        #  x = self.clip(x) (exercise 4); then the time update with F and F_x, stored in
        #  self.x, self.P for the next call. Log the measurement and your estimate:
        #  log("y", y), log("x_hat", x).
        raise NotImplementedError("exercise 3: write the EKF updates in EKF.__call__()")


def mhe(horizon: int, solver: str = "fatrop") -> estim.MHE:
    r"""Exercises 5-6: the course's MHE, without prior (Γ = 0), as an ``estim.MHE``.

    TODO (exercise 5): write down the problem solved at time T. Which parameters does it
    need? How many measurements are kept, and what happens before there are that many?
    """
    # TODO (exercise 6): return estim.MHE(MODEL, horizon=horizon, Q=..., R=..., x0=GUESS,
    #  arrival_cost="none", lower=..., upper=10.0, solver=solver), where Q and R are the
    #  covariances whose inverses weigh w and v in your cost of exercise 5.
    raise NotImplementedError("exercise 6: build the MHE in mhe() with estim.MHE(...)")


def compare(logs: dict[str, estim.Log], path) -> dict:
    """Final: the RMSE table and one figure with all four estimates; returns the numbers."""
    # TODO (final): print estim.rmse(log) (also with burn_in=BURN_IN) and log.x_hat.min()
    #  per estimator, draw them all with plot(logs, path, symlog=0.1) and return the
    #  numbers as {"rmse": {name: ...}, "rmse_after_burn_in": {...}, "min_estimate": {...}}.
    #  Does the MHE beat the EKF? Does N = 25 beat N = 10? Does clipping help?
    raise NotImplementedError("final exercise: compare the four estimators in compare()")


def main(argv: list[str] | None = None) -> dict:
    """Run the session; every figure goes to ``--out`` (the last one is the comparison)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="course_template.png", help="PNG to write")
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
