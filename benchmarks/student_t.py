"""Measurement outliers: the variational Student-t EKF and UKF against the EKF, the gated
EKF and a bootstrap particle filter that knows the true noise.

The scenario: ``estim.scenarios.van_der_pol()`` (both states measured, R = I), each
output value replaced, with probability ``share`` (default 0.1), by one with noise of
standard deviation ``scale`` (default 10) instead of 1: the measurement noise is the
mixture :math:`0.9\\,N(0, I) + 0.1\\,N(0, 10^2 I)` of whole samples. On the same seeds:

* ``EKF``: the plain filter (R = I);
* ``EKF, gate``: the NIS gate (``gate=1e-3``: a measurement beyond the 0.999 quantile of
  its chi-square dropped);
* ``EKF(noise="student-t", dof=nu)`` and ``UKF(...)`` for nu = 3 to 20;
* ``EKF(noise="student-t-roth", dof=5)``: Roth et al.'s closed-form Student's t filter;
* ``PF, true likelihood``: ``ParticleFilter`` with 1000 particles and the mixture's
  log-density (``loglik=``), the reference with the right noise model;

and the same without outliers (``share=0``), where the Student-t filters should cost
nothing. Printed: RMSE over the seeds (median, and the mean with its range), NEES/n, and
the time per sample of ``filter`` against the EKF's in the same process (median and range
of ``--repeats`` timings, interleaved).

Run from the repository root::

    python benchmarks/student_t.py [--seeds 50] [--share 0.1] [--scale 10]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

import estim

DOFS = (3, 4, 5, 8, 10, 20)


def record(sc: estim.Scenario, seed: int, share: float, scale: float):
    """``(x, y)``: the truth and its measurements with the outliers."""
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed, warn=False)
    rng = np.random.default_rng(10_000 + seed)
    y = log.y.copy()
    hit = np.repeat(rng.random((len(y), 1)) < share, y.shape[1], axis=1)  # whole samples
    y[hit] = log.x[hit] + scale * rng.standard_normal(int(hit.sum()))
    return log.x, y


def mixture(share: float, scale: float):
    """The measurement log-density of the mixture of whole samples (``loglik=``, R = I)."""
    def loglik(y, yhat, p):
        r2, m = ca.sumsqr(y - yhat), y.numel()
        return ca.log((1 - share) * ca.exp(-0.5 * r2)
                      + share / scale ** m * ca.exp(-0.5 * r2 / scale ** 2))
    return loglik


def estimators(sc: estim.Scenario, share: float, scale: float) -> dict:
    m, tun = sc.model, sc.tuning
    out = {"EKF": estim.EKF(m, **tun), "EKF, gate 1e-3": estim.EKF(m, **tun, gate=1e-3)}
    for nu in DOFS:
        out[f"EKF, Student-t {nu}"] = estim.EKF(m, **tun, noise="student-t", dof=nu)
    out["EKF, Roth's t filter 5"] = estim.EKF(m, **tun, noise="student-t-roth", dof=5)
    out["UKF"] = estim.UKF(m, **tun)
    for nu in (4,):
        out[f"UKF, Student-t {nu}"] = estim.UKF(m, **tun, noise="student-t", dof=nu)
    if share > 0:
        out["PF 1000, true likelihood"] = estim.ParticleFilter(
            m, **tun, n_particles=1000, loglik=mixture(share, scale), seed=0, jit=True)
    return out


def run(seeds: int, share: float, scale: float, repeats: int) -> None:
    sc = estim.scenarios.van_der_pol()
    ests = estimators(sc, share, scale)
    rmse = {k: [] for k in ests}
    nees = {k: [] for k in ests}
    data = [record(sc, s, share, scale) for s in range(seeds)]
    for name, est in ests.items():
        for s, (x, y) in enumerate(data):
            if hasattr(est, "seed"):
                est.seed = s
            res = est.filter(y)
            err = res.x - x
            rmse[name].append(float(np.sqrt(np.mean(err ** 2))))
            nees[name].append(float(np.mean(np.einsum("ka,kab,kb->k", err,
                                                      np.linalg.inv(res.P), err)) / 2))
    times = {k: [] for k in ests}
    y = data[0][1]
    for _ in range(repeats):  # interleaved
        for name, est in ests.items():
            t0 = time.perf_counter()
            est.filter(y)
            times[name].append((time.perf_counter() - t0) / len(y))
    base = np.array(times["EKF"])
    print(f"# Van der Pol, {seeds} seeds x {sc.n_steps} steps, outliers: {share:.0%} of the "
          f"samples with noise std {scale:g} (instead of 1)\n")
    print("| filter | RMSE median | RMSE mean [range] | NEES/n median | step cost / EKF "
          "(median [range]) |")
    print("|---|---|---|---|---|")
    for name in ests:
        r = np.array(rmse[name])
        ratio = np.array(times[name]) / base
        print(f"| {name} | {np.median(r):.4f} | {r.mean():.4f} [{r.min():.3f}-{r.max():.3f}] "
              f"| {np.median(nees[name]):.3f} | {np.median(ratio):.2f} "
              f"[{ratio.min():.2f}-{ratio.max():.2f}] |")
    print()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--share", type=float, default=0.1)
    parser.add_argument("--scale", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    run(args.seeds, args.share, args.scale, args.repeats)
    run(args.seeds, 0.0, args.scale, args.repeats)


if __name__ == "__main__":
    main()
