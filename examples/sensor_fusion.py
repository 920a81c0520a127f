"""Sensor fusion of asynchronous streams: an IMU at 100 Hz, GNSS at 1 Hz, a barometer at 20 Hz.

A vehicle's vertical channel, height ``h``, climb rate ``v`` and acceleration ``a`` (a
random walk: a manoeuvre is a change of acceleration), seen by three sensors with their
own clocks: the IMU measures ``a`` (σ = 0.05 m/s², every 10 ms), the GNSS receiver ``h``
(σ = 2 m, every second, on the IMU's stamps) and the barometer ``h`` (σ = 0.5 m, every
50 ms, 3 ms after the IMU's tick). ``estim.records.merge`` puts the streams on one time
line (NaN where a sensor was silent, the GNSS and IMU samples of one stamp in one row),
``rec.R`` expands the sensors' variances block-diagonally, and an EKF on a model with
``variable_dt=True`` integrates over each interval between stamps.

Printed: the RMSE of height and climb rate with the GNSS alone, GNSS and barometer, and
all three; the median time of a step of the compiled EKF (``jit=True``; interpreted with
``--no-jit`` or without a C compiler) at the IMU rate, and its time per sample when it
filters the whole record in one compiled call (``ekf.filter``). Run::

    python examples/sensor_fusion.py [--seconds 60] [--out sensor_fusion.png] [--no-jit]
"""

from __future__ import annotations

import argparse
import shutil
import time

import numpy as np
from scipy.linalg import expm

import estim
from estim.records import merge

A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
Q = np.diag([1e-6, 1e-4, 1e-2])  # per transition (about 10 ms)
SENSORS = {"imu": ("acc", 100.0, 0.0, 0.05), "gnss": ("h_gnss", 1.0, 0.0, 2.0),
           "baro": ("h_baro", 20.0, 0.003, 0.5)}  # output, rate (Hz), offset (s), σ
ROW = {"acc": 2, "h_gnss": 0, "h_baro": 0}  # the state each output reads


def vehicle() -> estim.Model:
    """The vertical channel with an interval of its own between stamps (RK4, exact for
    its nilpotent dynamics)."""
    return estim.models.vertical_channel(variable_dt=True)


def record(seconds: float, seed: int = 0, transition=None) -> tuple[dict, dict]:
    """The streams ``{sensor: (t, Y, output)}`` and the truth ``{t: x}`` at every stamp;
    ``transition(x, dt, rng)`` moves the truth over an interval (default: the exact
    dynamics and the per-transition noise ``Q``)."""
    rng = np.random.default_rng(seed)
    times = {s: np.arange(int(rate * seconds)) / rate + off
             for s, (_, rate, off, _) in SENSORS.items()}
    t_all = np.unique(np.concatenate(list(times.values())))
    if transition is None:
        def transition(x, dt, rng):
            return expm(A * dt) @ x + rng.multivariate_normal(np.zeros(3), Q)
    x, truth = np.array([100.0, 0.0, 0.0]), {}
    for k, tk in enumerate(t_all):
        if k:
            x = transition(x, tk - t_all[k - 1], rng)
        truth[float(tk)] = x.copy()
    streams = {}
    for s, (out, _, _, sd) in SENSORS.items():
        Y = np.array([truth[float(tk)][ROW[out]] for tk in times[s]])
        streams[s] = (times[s], Y + sd * rng.standard_normal(len(Y)), out)
    return streams, truth


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--out", default="sensor_fusion.png", help="'' for no plot")
    parser.add_argument("--no-jit", action="store_true", help="interpreted EKF")
    args = parser.parse_args(argv)
    jit = not args.no_jit and (shutil.which("cc") or shutil.which("gcc")) is not None
    streams, truth = record(args.seconds)
    m = vehicle()
    variances = {s: sd**2 for s, (_, _, _, sd) in SENSORS.items()}
    rec = merge(streams, outputs=m.output_names)
    R = rec.R(variances)
    results, logs = {}, {}
    for label, used in (("gnss", ["gnss"]), ("gnss+baro", ["gnss", "baro"]),
                        ("gnss+baro+imu", ["gnss", "baro", "imu"])):
        # the same time line for all (Q is the noise of one transition between stamps),
        # the sensors left out silent
        Y = rec.Y.copy()
        for s in SENSORS:
            if s not in used:
                Y[:, m.output_names.index(SENSORS[s][0])] = np.nan
        ekf = estim.EKF(m, Q=Q, R=R, x0=[100.0, 0.0, 0.0], P0=np.diag([25.0, 1.0, 0.1]),
                        jit=jit)
        log = estim.replay(ekf, Y, t=rec.t)
        X = np.array([truth[float(tk)] for tk in rec.t])
        err = np.asarray(log.x_hat) - X
        half = rec.t >= rec.t[-1] / 2  # after the start-up
        results[label] = {"rmse_h": float(np.sqrt(np.mean(err[half, 0] ** 2))),
                          "rmse_v": float(np.sqrt(np.mean(err[half, 1] ** 2))),
                          "samples": int(np.any([rec.reported[u] for u in used], axis=0).sum()),
                          "all_ok": bool(np.all(log.status == "ok"))}
        logs[label] = (rec, log, X)
    rec, log, X = logs["gnss+baro+imu"]
    step_us = float(np.median(np.asarray(log.solve_time))) * 1e6
    # the whole record in one compiled call (a scan of the same fused step): the same
    # estimates; its time per sample is the median over five calls
    ekf = estim.EKF(m, Q=Q, R=R, x0=[100.0, 0.0, 0.0], P0=np.diag([25.0, 1.0, 0.1]), jit=jit)
    ekf.filter(rec.Y, t=rec.t)  # builds (and compiles) the scan for this record length
    seconds = []
    for _ in range(5):
        t0 = time.perf_counter()
        whole = ekf.filter(rec.Y, t=rec.t)
        seconds.append(time.perf_counter() - t0)
    results["filter_equal"] = float(np.abs(whole.x - np.asarray(log.x_hat)).max())
    results["filter_us"] = float(np.median(seconds)) / len(rec.t) * 1e6
    results["step_us"], results["jit"] = step_us, jit
    print(f"Vertical channel, {args.seconds:g} s: IMU 100 Hz, GNSS 1 Hz, barometer 20 Hz "
          f"({len(rec.t)} stamps)")
    print(f"{'sensors':<16}{'RMSE h (m)':>12}{'RMSE v (m/s)':>14}{'samples':>9}")
    for label in ("gnss", "gnss+baro", "gnss+baro+imu"):
        r = results[label]
        print(f"{label:<16}{r['rmse_h']:>12.3f}{r['rmse_v']:>14.3f}{r['samples']:>9}")
    how = "compiled" if jit else "interpreted"
    print(f"EKF ({how}): {step_us:.2f} µs per step (median, ekf.step at every stamp); "
          f"{results['filter_us']:.2f} µs per sample over the whole record (ekf.filter, "
          f"equal to the steps to {results['filter_equal']:.0e})")
    if args.out:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
        for label, style in (("gnss", ":"), ("gnss+baro", "--"), ("gnss+baro+imu", "-")):
            r, lg, Xl = logs[label]
            ax[0].plot(r.t, np.asarray(lg.x_hat)[:, 0] - Xl[:, 0], style, label=label)
            ax[1].plot(r.t, np.asarray(lg.x_hat)[:, 1] - Xl[:, 1], style, label=label)
        ax[0].set_ylabel("height error (m)")
        ax[1].set_ylabel("climb-rate error (m/s)")
        ax[1].set_xlabel("time (s)")
        ax[0].legend(loc="upper right")
        fig.tight_layout()
        fig.savefig(args.out, dpi=110)
        plt.close(fig)
    return results


if __name__ == "__main__":
    main()
