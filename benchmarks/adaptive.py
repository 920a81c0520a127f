"""Measurement noise that switches and drifts: the variational Bayes adaptive filter
against an oracle Kalman filter that knows the noise at every sample, and against a filter
tuned once.

The set-up follows Särkkä & Nummenmaa (2009): a stochastic resonator
:math:`\\ddot p = -\\omega^2 p + w` (:math:`\\omega = 0.5` rad/s, sampled exactly at 0.1 s,
acceleration noise density 0.1) whose position is measured with a noise variance that
switches and drifts: 1 for the first 300 samples, 4 until 600, 1 until 900, then
:math:`1.5 + \\sin(2\\pi (k - 900)/400)` to 1500. On ``--seeds`` records:

* ``oracle``: filterpy's ``KalmanFilter`` with the true :math:`R_k` at every sample;
* ``VB-EKF``: ``estim.EKF(..., adapt="R", forgetting=rho)`` from R = 1 (``--forgetting``,
  default 0.95);
* ``VB-UKF``: the same with the UKF;
* ``Sage-Husa EKF``: ``adapt="sage-husa"`` with the same forgetting, the classical
  fading-memory estimate;
* ``VB-QR EKF``: ``adapt="QR"``, the process noise learnt too (Huang et al. 2018);
* ``fixed R``: ``estim.EKF`` with R = 1.5, the record's mean noise variance.

Printed: RMSE against the oracle's (median and range over seeds), the learnt R at 100
samples after each switch against the truth (median relative error, the share of seeds
within 20 %), and the step cost against the plain EKF's (``filter`` per sample, median and
range of interleaved repeats). ``--q-factor f``: every filter's Q is f times the true one
(the oracle's stays right). ``--stationary`` instead: the noise constant at 1, the
adaptive filters against an EKF tuned by maximum likelihood on the record (do no harm),
with the NEES.

Run from the repository root::

    python benchmarks/adaptive.py [--seeds 50] [--forgetting 0.98] [--stationary]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

import estim

OMEGA, DT, Q_DENSITY, T = 0.5, 0.1, 0.1, 1500
SWITCHES = (300, 600, 900)


def variance(k: np.ndarray, stationary: bool) -> np.ndarray:
    if stationary:
        return np.ones_like(k, dtype=float)
    return np.select([k < 300, k < 600, k < 900],
                     [1.0, 4.0, 1.0], 1.5 + np.sin(2 * np.pi * (k - 900) / 400))


def discretised() -> tuple[np.ndarray, np.ndarray]:
    """The resonator's exact transition and Q over DT (Van Loan, numbers)."""
    A = np.array([[0.0, 1.0], [-OMEGA ** 2, 0.0]])
    W = np.diag([0.0, Q_DENSITY])
    M = expm(np.block([[-A, W], [np.zeros((2, 2)), A.T]]) * DT)
    F = M[2:, 2:].T
    Qd = F @ M[:2, 2:]
    return F, 0.5 * (Qd + Qd.T)


def model(F: np.ndarray) -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"], dynamics=lambda x, u, p: ca.DM(F) @ x,
                       output=lambda x, u, p: x[0], dt=DT, name="resonator")


def record(seed: int, F: np.ndarray, Qd: np.ndarray, stationary: bool):
    rng = np.random.default_rng(seed)
    x, X, Y = np.array([1.0, 0.0]), [], []
    Rk = variance(np.arange(T), stationary)
    for k in range(T):
        if k:
            x = F @ x + rng.multivariate_normal(np.zeros(2), Qd)
        X.append(x)
        Y.append([x[0] + rng.normal(0.0, np.sqrt(Rk[k]))])
    return np.array(X), np.array(Y), Rk


def oracle(F, Qd, Y, Rk):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x, kf.P, kf.F, kf.Q, kf.H = np.zeros(2), np.eye(2), F, Qd, np.array([[1.0, 0.0]])
    xs = []
    for k, y in enumerate(Y):
        if k:
            kf.predict()
        kf.R = np.array([[Rk[k]]])
        kf.update(y)
        xs.append(kf.x.copy())
    return np.array(xs)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--forgetting", type=float, default=0.95)
    parser.add_argument("--repeats", type=int, default=21)
    parser.add_argument("--stationary", action="store_true")
    parser.add_argument("--q-factor", type=float, default=1.0)
    args = parser.parse_args()
    F, Qd = discretised()
    m = model(F)
    tun = {"Q": args.q_factor * Qd, "x0": [0.0, 0.0], "P0": np.eye(2)}
    filters = {"VB-EKF": estim.EKF(m, **tun, R=1.0, adapt="R", forgetting=args.forgetting),
               "VB-UKF": estim.UKF(m, **tun, R=1.0, adapt="R", forgetting=args.forgetting),
               "Sage-Husa EKF": estim.EKF(m, **tun, R=1.0, adapt="sage-husa",
                                          forgetting=args.forgetting),
               "VB-QR EKF": estim.EKF(m, **tun, R=1.0, adapt="QR", forgetting=args.forgetting),
               "fixed R": estim.EKF(m, **tun, R=1.5 if not args.stationary else 1.0)}
    rmse = {k: [] for k in ["oracle", *filters, "ML-tuned EKF"]}
    nees = {k: [] for k in filters}
    learnt = {k: [] for k in ("VB-EKF", "VB-UKF", "Sage-Husa EKF", "VB-QR EKF")}
    for seed in range(args.seeds):
        X, Y, Rk = record(seed, F, Qd, args.stationary)
        rmse["oracle"].append(np.sqrt(np.mean((oracle(F, Qd, Y, Rk) - X) ** 2)))
        for name, f in filters.items():
            res = f.filter(Y)
            err = res.x - X
            rmse[name].append(np.sqrt(np.mean(err ** 2)))
            nees[name].append(np.mean(np.einsum("ka,kab,kb->k", err, np.linalg.inv(res.P),
                                                err)) / 2)
            if name in learnt:
                learnt[name].append([res.R[s + 99, 0, 0] / Rk[s + 99] - 1 for s in SWITCHES]
                                    + [np.median(np.abs(res.R[1000:, 0, 0] / Rk[1000:] - 1))])
        if args.stationary:
            ml = estim.tuning.maximum_likelihood(m, Y, x0=[0.0, 0.0], P0=np.eye(2),
                                                 Q0=Qd, structure={"Q": "fixed"}, starts=1)
            res = estim.EKF(m, **tun, R=ml.R).filter(Y)  # (Q as the other filters')
            rmse["ML-tuned EKF"].append(np.sqrt(np.mean((res.x - X) ** 2)))
    _, Y, _ = record(0, F, Qd, args.stationary)
    plain = estim.EKF(m, **tun, R=1.0)
    times = {k: [] for k in filters}
    for f in (plain, *filters.values()):  # built before the timing
        f.filter(Y)
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        plain.filter(Y)
        base = time.perf_counter() - t0
        for name, f in filters.items():
            t0 = time.perf_counter()
            f.filter(Y)
            times[name].append((time.perf_counter() - t0) / base)
    ref = np.array(rmse["ML-tuned EKF" if args.stationary else "oracle"])
    what = "constant noise (1)" if args.stationary else "switching and drifting noise"
    print(f"# The resonator with {what}: {args.seeds} seeds x {T} samples, "
          f"forgetting {args.forgetting:g}, the filters' Q {args.q_factor:g} times the "
          f"true one\n")
    print(f"| filter | RMSE (median) | RMSE / {'ML-tuned EKF' if args.stationary else 'oracle'}"
          " (median [range]) | NEES/n (median) | step cost / EKF (median [range]) |")
    print("|---|---|---|---|---|")
    for name, r in rmse.items():
        r = np.array(r)
        if not r.size:
            continue
        ratio = r / ref
        cost = np.array(times[name]) if name in times else None
        cost_text = "-" if cost is None else \
            f"{np.median(cost):.2f} [{cost.min():.2f}-{cost.max():.2f}]"
        nees_text = f"{np.median(nees[name]):.3f}" if name in nees else "-"
        print(f"| {name} | {np.median(r):.4f} | {np.median(ratio):.4f} [{ratio.min():.3f}-"
              f"{ratio.max():.3f}] | {nees_text} | {cost_text} |")
    if not args.stationary:
        print("\n| filter | learnt R against the truth | median relative error [5-95 % of "
              "the seeds] | seeds within 20 % |")
        print("|---|---|---|---|")
        for name, rel in learnt.items():
            rel = np.array(rel)
            for j, s in enumerate(SWITCHES):
                lo, hi = np.percentile(rel[:, j], [5, 95])
                print(f"| {name} | 100 samples after the switch at {s} (R "
                      f"{variance(np.array([s - 1]), False)[0]:g} -> "
                      f"{variance(np.array([s]), False)[0]:g}) | {np.median(rel[:, j]):+.3f} "
                      f"[{lo:+.2f}, {hi:+.2f}] | {np.mean(np.abs(rel[:, j]) < 0.2):.0%} |")
            print(f"| {name} | through the drift (samples 1000-1500): each seed's median "
                  f"absolute relative error | {np.median(rel[:, -1]):.3f} | "
                  f"{np.mean(rel[:, -1] < 0.2):.0%} |")


if __name__ == "__main__":
    main()
