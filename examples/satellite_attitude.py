"""The satellite's attitude and inertia: the quaternion as four ordinary states, or as a
unit quaternion with a 3-dof error.

The satellite of Oliva & Carnevale (sec. 2.1-2.4; ``estim.scenarios.satellite``: a gyro,
PD control on the true attitude towards a persistently exciting target) with its inertia
identified: the model is augmented with ``I1, I2, I3`` (bounded to [0.01, 10]) and the
filters start 20-25 % off (0.40, 0.50, 0.20 against 0.50, 0.40, 0.26; the inertia is
constant here, ``fault=False``). Two forms of the same EKF and UKF:

* additive: the quaternion as four ordinary states, with the 1e-10 process noise on it
  that keeps its 4 x 4 covariance from collapsing in the direction of the norm;
* multiplicative: ``models.satellite(quaternion=True)``, the error
  ``q = q_hat (x) exp(dtheta / 2)``, a 3 x 3 attitude covariance, no process noise on the
  attitude.

Printed, per form and filter, over ``--seeds`` seeds (medians): the attitude error at the
end (degrees; unobservable from the gyro, so it stays near the prior's), the error of the
inertia ratios I1/I3 and I2/I3 at the end, NEES per dimension after 100 s (``nx = 11``
for the additive form, ``ndx = 10`` for the multiplicative), the largest deviation of
the estimated quaternion's norm from 1, and the median step time. Run::

    python examples/satellite_attitude.py [--seeds 5] [--out satellite_attitude.png]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

import estim

INERTIA = np.array([0.50, 0.40, 0.26])
GUESS = np.array([0.40, 0.50, 0.20])


def scenario(quaternion: bool) -> estim.Scenario:
    """The satellite scenario, its model augmented with the inertia."""
    sc = estim.scenarios.satellite(fault=False, quaternion=quaternion)
    m = sc.model.augment("I1", "I2", "I3", lower=0.01, upper=10.0)
    t = sc.tuning
    return estim.Scenario(
        "satellite_inertia", m, x0=np.r_[sc.x0, INERTIA], n_steps=sc.n_steps, Q=0.0, R=sc.R,
        controller=sc.controller, feedback="truth",
        tuning={"Q": np.r_[t["Q"], [1e-8] * 3], "R": t["R"], "x0": np.r_[t["x0"], GUESS],
                "P0": np.r_[t["P0"], [0.01] * 3]})


def attitude_error(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """The angle (rad) between the true and the estimated attitude, ``(T,)``."""
    q, qh = x[:, :4], x_hat[:, :4] / np.linalg.norm(x_hat[:, :4], axis=1, keepdims=True)
    return 2 * np.arccos(np.clip(np.abs(np.sum(q * qh, axis=1)), 0.0, 1.0))


def ratio_error(x: np.ndarray, x_hat: np.ndarray) -> np.ndarray:
    """The largest error of the ratios I1/I3, I2/I3, ``(T,)``."""
    true, est = x[:, -3:], x_hat[:, -3:]
    return np.abs(est[:, :2] / est[:, 2:] - true[:, :2] / true[:, 2:]).max(axis=1)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--out", default="satellite_attitude.png", help="'' for no plot")
    args = parser.parse_args(argv)
    results, logs = {}, {}
    for form, quaternion in (("additive", False), ("multiplicative", True)):
        sc = scenario(quaternion)
        for cls in (estim.EKF, estim.UKF):
            rows = []
            est = cls(sc.model, **sc.tuning)
            for seed in range(args.seeds):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", estim.EstimationWarning)
                    log = estim.simulate(sc, est, seed=seed)
                late = log.t >= 100.0
                nees = estim.nees(log)[late]
                rows.append([np.degrees(attitude_error(log.x, log.x_hat)[-1]),
                             ratio_error(log.x, log.x_hat)[-1],
                             float(np.mean(nees)) / sc.model.ndx,
                             np.abs(np.linalg.norm(log.x_hat[:, :4], axis=1) - 1).max(),
                             float(np.median(log.solve_time)) * 1e6, log.failures])
                if seed == 0:
                    logs[(form, cls.name)] = log
            r = np.array(rows)
            results[(form, cls.name)] = {
                "attitude_deg": float(np.median(r[:, 0])), "ratio": float(np.median(r[:, 1])),
                "nees": float(np.median(r[:, 2])), "norm": float(r[:, 3].max()),
                "step_us": float(np.median(r[:, 4])), "failures": int(r[:, 5].sum())}
    print(f"satellite with inertia identification, {args.seeds} seeds (medians)")
    print(f"{'form':<16}{'filter':<6}{'attitude (deg)':>15}{'I ratios':>10}{'NEES/n':>8}"
          f"{'max ||q|-1|':>13}{'step (µs)':>11}{'failed':>8}")
    for (form, name), r in results.items():
        print(f"{form:<16}{name:<6}{r['attitude_deg']:>15.3f}{r['ratio']:>10.4f}"
              f"{r['nees']:>8.3f}{r['norm']:>13.1e}{r['step_us']:>11.1f}{r['failures']:>8}")
    if args.out:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
        for (form, name), log in logs.items():
            style = "-" if form == "multiplicative" else "--"
            label = f"{name} {form}"
            ax[0].plot(log.t, np.degrees(attitude_error(log.x, log.x_hat)), style, label=label)
            ax[1].plot(log.t, ratio_error(log.x, log.x_hat), style, label=label)
        ax[0].set_ylabel("attitude error (deg)")
        ax[1].set_ylabel("inertia ratio error")
        ax[1].set_yscale("log")
        ax[1].set_xlabel("time (s)")
        ax[0].legend(loc="upper right", fontsize=8)
        fig.tight_layout()
        fig.savefig(args.out, dpi=110)
        plt.close(fig)
    return results


if __name__ == "__main__":
    main()
