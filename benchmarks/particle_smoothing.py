"""The particle smoother's backward simulation: rejection sampling against the direct draw
and against a plain numpy loop over the paths.

The record: the univariate growth model of Kitagawa (1996) and Gordon, Salmond & Smith
(1993), :math:`x_{k+1} = x_k/2 + 25 x_k/(1 + x_k^2) + 8\\cos(1.2 k) + w_k`,
:math:`y_k = x_k^2/20 + v_k`, :math:`w \\sim N(0, 10)`, :math:`v \\sim N(0, 1)` (the
time index :math:`k` the model's input), ``--samples`` samples (default 500),
``ParticleFilter(n_particles=--particles)`` (default 10 000, compiled). Timed,
interleaved ``--repeats`` times after a first call:

* ``estim``: ``pf.smooth(Y, n_paths=100)`` less ``pf.filter(Y)`` (the backward pass);
* ``direct``: the same with every path drawn directly (``REJECTION_ROUNDS = 0``);
* ``numpy loop``: a plain per-path loop over the same forward trace, each path's backward
  weights over all particles (the textbook algorithm, numpy-vectorised over particles).

Printed: seconds (median [range]) and the ratios against the numpy loop, and the smoothed
means' difference between the three (Monte Carlo error only).

Run from the repository root::

    python benchmarks/particle_smoothing.py [--samples 500] [--particles 10000]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

import estim
import estim.estimators.sampling.particle_smoothing as smoothing


def growth(dt: float = 1.0) -> estim.Model:
    return estim.Model(
        states=["x"], outputs=["y"], inputs=["k"],
        dynamics=lambda x, u, p: 0.5 * x + 25 * x / (1 + x ** 2) + 8 * ca.cos(1.2 * u[0]),
        output=lambda x, u, p: x ** 2 / 20, dt=dt, name="growth")


def record(T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    x, X, Y = 0.1, [], []
    for k in range(T):
        if k:
            x = 0.5 * x + 25 * x / (1 + x * x) + 8 * np.cos(1.2 * (k - 1)) + \
                rng.normal(0, np.sqrt(10.0))
        X.append(x)
        Y.append(x * x / 20 + rng.normal())
    U = np.arange(T - 1, dtype=float)[:, None]
    return np.array(X), np.array(Y)[:, None], U


def numpy_loop(trace, Q, n_paths, rng, transit):
    """The textbook backward simulation, path by path."""
    T = len(trace)
    X, W, _ = trace[-1]
    N = W.size
    paths = np.empty((n_paths, T))
    paths[:, -1] = X[0, rng.choice(N, n_paths, p=W)]
    for t in range(T - 2, -1, -1):
        X, W, _ = trace[t]
        FX = transit(X, trace[t + 1][2], n=N)[0][0]
        with np.errstate(divide="ignore"):
            logW = np.log(W)
        for j in range(n_paths):
            logw = logW - 0.5 * (paths[j, t + 1] - FX) ** 2 / Q
            w = np.exp(logw - logw.max())
            paths[j, t] = X[0, rng.choice(N, p=w / w.sum())]
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=500)
    parser.add_argument("--particles", type=int, default=10_000)
    parser.add_argument("--paths", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    m = growth()
    X, Y, U = record(args.samples)
    pf = estim.ParticleFilter(m, Q=10.0, R=1.0, x0=[0.0], P0=5.0,
                              n_particles=args.particles, jit=True)
    pf.smooth(Y, U, n_paths=args.paths)  # built
    times = {"estim": [], "direct": [], "numpy loop": []}
    means = {}
    rounds = smoothing.REJECTION_ROUNDS
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        pf.filter(Y, U)
        forward = time.perf_counter() - t0
        for name in ("estim", "direct"):
            smoothing.REJECTION_ROUNDS = rounds if name == "estim" else 0
            t0 = time.perf_counter()
            res = pf.smooth(Y, U, n_paths=args.paths)
            times[name].append(time.perf_counter() - t0 - forward)
            means[name] = res.x[:, 0]
        smoothing.REJECTION_ROUNDS = rounds
        pf._trace = []
        pf.filter(Y, U)
        trace, pf._trace = pf._trace, None
        t0 = time.perf_counter()
        paths = numpy_loop(trace, 10.0, args.paths, np.random.default_rng(1), pf._transit)
        times["numpy loop"].append(time.perf_counter() - t0)
        means["numpy loop"] = paths.mean(axis=0)
    base = np.median(times["numpy loop"])
    print(f"# Backward simulation of the growth model: {args.samples} samples, "
          f"{args.particles} particles, {args.paths} paths\n")
    print("| backward pass | seconds (median [range]) | speed-up over the numpy loop |")
    print("|---|---|---|")
    for name, ts in times.items():
        ts = np.array(ts)
        print(f"| {name} | {np.median(ts):.3f} [{ts.min():.3f}-{ts.max():.3f}] | "
              f"{base / np.median(ts):.1f} |")
    rms = {k: float(np.sqrt(np.mean((v - X) ** 2))) for k, v in means.items()}
    print("\nRMSE of the smoothed means against the truth: " +
          ", ".join(f"{k} {v:.3f}" for k, v in rms.items()))


if __name__ == "__main__":
    main()
