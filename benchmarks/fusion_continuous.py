"""The vertical-channel sensor fusion (``examples/sensor_fusion.py``) with a continuous-time
noise: ``EKF(Qc=...)`` against a per-transition ``Q``, RMSE and NEES side by side.

The truth: height, climb rate and acceleration whose rate of change (the jerk) is white
noise of density ``q = 0.5`` (m²/s⁵), each interval between stamps discretised exactly
(``van_loan``); the streams of the example (IMU 100 Hz, GNSS 1 Hz, barometer 20 Hz 3 ms
after the IMU) merged on one time line, whose intervals are 3 ms and 7 ms. Filters:

* ``EKF(Qc=q)``: the density through the noise input ``[0, 0, 1]``, the moment
  equations per interval (4 sub-steps: exact for these polynomial moments);
* ``EKF(Q=Q_d(10 ms))``: the exact covariance of the IMU's interval, per transition (what
  the example chooses "for the typical interval");
* ``EKF(Q=Q_d(mean interval))``.

Over ``--seeds`` records of ``--seconds`` each: RMSE of height and climb rate after the
first half-second, NEES/n (mean over samples and seeds) and the fraction of the stamps
whose NEES averaged over the seeds lies in its 95 % chi-square band. Run::

    python benchmarks/fusion_continuous.py [--seeds 50] [--seconds 20]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import stats

import estim
from estim.records import merge
from estim.solvers.kalman.continuous import van_loan

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import sensor_fusion  # noqa: E402  (the example's sensors and record)

SENSORS = sensor_fusion.SENSORS

A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
L = np.array([[0.0], [0.0], [1.0]])
DENSITY = 0.5


def jerk(x: np.ndarray, dt: float, rng: np.random.Generator) -> np.ndarray:
    """The truth over an interval: the exact transition of a white jerk of density
    ``DENSITY`` (Van Loan)."""
    Phi, Qd = van_loan(A, DENSITY * L @ L.T, dt)
    return Phi @ x + rng.multivariate_normal(np.zeros(3), Qd)


def record(seconds: float, seed: int):
    return sensor_fusion.record(seconds, seed, transition=jerk)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    m = estim.models.vertical_channel(variable_dt=True)
    mc = estim.Model(states=m.state_names, outputs=m.output_names, ode=m._ode,
                     output=m._output, dt=m.dt, variable_dt=True, noise_input=L,
                     name="vertical channel, jerk noise")
    variances = {s: sd ** 2 for s, (_, _, _, sd) in SENSORS.items()}
    prior = {"x0": [100.0, 0.0, 0.0], "P0": np.diag([25.0, 1.0, 0.1])}
    records = [record(args.seconds, s) for s in range(args.seeds)]
    rec0 = merge(records[0][0], outputs=m.output_names)
    mean_dt = float(np.diff(rec0.t).mean())
    filters = {
        "EKF(Qc=q), moments per interval": lambda R: estim.EKF(mc, Qc=DENSITY, R=R, **prior),
        "EKF(Q=Q_d(10 ms)), per transition": lambda R: estim.EKF(
            m, Q=van_loan(A, DENSITY * L @ L.T, 0.01)[1], R=R, **prior),
        f"EKF(Q=Q_d({1e3 * mean_dt:.1f} ms, the mean interval))": lambda R: estim.EKF(
            m, Q=van_loan(A, DENSITY * L @ L.T, mean_dt)[1], R=R, **prior)}
    S = args.seeds
    lo, hi = stats.chi2.ppf([0.025, 0.975], 3 * S) / S
    print(f"# Vertical channel with a continuous jerk noise (q = {DENSITY}): {S} seeds x "
          f"{args.seconds:g} s, IMU 100 Hz, GNSS 1 Hz, barometer 20 Hz (intervals 3 and 7 ms, "
          f"mean {1e3 * mean_dt:.2f} ms)\n")
    print(f"95 % band of the NEES averaged over {S} seeds at one stamp: [{lo / 3:.3f}, "
          f"{hi / 3:.3f}] (as NEES/n)\n")
    print("| filter | RMSE h (m) | RMSE v (m/s) | NEES/n | stamps in the band | NEES/n after "
          "3 ms / after 7 ms |")
    print("|---|---|---|---|---|---|")
    for name, make in filters.items():
        nees, eh, ev, short = [], [], [], None
        for streams, truth in records:
            rec = merge(streams, outputs=m.output_names)
            res = make(rec.R(variances)).filter(rec.Y, t=rec.t)
            X = np.array([truth[float(tk)] for tk in rec.t])
            e = res.x - X
            half = rec.t >= 0.5
            eh.append(np.mean(e[half, 0] ** 2))
            ev.append(np.mean(e[half, 1] ** 2))
            nees.append(np.einsum("ka,kab,kb->k", e, np.linalg.inv(res.P), e))
            short = np.concatenate([[False], np.diff(rec.t) < 0.005])
        N = np.array(nees)
        inside = np.mean((N.mean(axis=0) >= lo) & (N.mean(axis=0) <= hi))
        print(f"| {name} | {np.sqrt(np.mean(eh)):.3f} | {np.sqrt(np.mean(ev)):.4f} | "
              f"{N.mean() / 3:.3f} | {100 * inside:.0f} % | {N[:, short].mean() / 3:.3f} / "
              f"{N[:, ~short][:, 1:].mean() / 3:.3f} |", flush=True)


if __name__ == "__main__":
    main()
