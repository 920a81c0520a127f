"""``estim.ParticleFilter`` against the particle filters users have: speed in particle-steps
per second, and accuracy on the standard test problems.

* **Speed**, the 2-state linear Gaussian model ``x' = A x + v``, ``y = x_1 + w``
  (``A = [[1, 0.1], [0, 1]]``, ``Q = diag(1e-3, 1e-2)``, ``R = 0.1``), a record of
  ``T = 100`` samples: ``ParticleFilter.filter`` at ``N = 10^2 .. 10^6``, interpreted
  and compiled (``jit=True``) (particle-steps per second, median of 5 runs, and the
  peak memory of one run by ``tracemalloc``),
  against, at every ``N`` up to 10^5, a bootstrap filter written in numpy around
  filterpy's ``systematic_resample`` (what a filterpy user writes), and ``particles``
  (Chopin's library: ``SMC`` with ``ssm.Bootstrap``, systematic resampling at ESS < N/2).
  The peak memory is that of building the compiled filter and running it once.
  LowLevelParticleFilters.jl's published figure (8.4 million particle-steps in 1.14 s,
  about 7.4 M/s, one Julia thread) is quoted for scale, not measured here.
* **Error against the exact filter**: the RMS difference of the filtered means from filterpy's
  Kalman filter over 10 seeds at ``N = 10^2 .. 10^5``, and its log-log slope (the Monte Carlo
  rate is -1/2).
* **Nonstationary growth model** (Gordon, Salmond, Smith 1993, as ``particles``'
  ``Gordon_etal``: ``x_0 ~ N(0, 4)``, ``x_t = x/2 + 25 x/(1+x^2) + 8 cos(1.2 (t-1)) + v``,
  ``v ~ N(0, 10)``, ``y = x^2/20 + w``, ``w ~ N(0, 1)``), ``T = 100``, ``N = 1000``, 100
  records (one per seed): the RMSE of the filtered mean against the true state, and the
  wall time of one run.
* **Stochastic volatility** (``x_t = mu + phi (x_{t-1} - mu) + sigma v``,
  ``y_t ~ N(0, exp(x_t))``, ``(mu, phi, sigma) = (-0.10, 0.97, 0.15)``, ``x_0`` from the
  stationary law), ``T = 500``, ``N = 1000``, one record filtered with 100 seeds: the
  variance over seeds of the log-likelihood estimate (both filters are bootstrap
  filters with the same resampling: the variances should agree within sampling
  error; an F-interval is printed).

``particles`` needs numpy < 2: it runs in its own interpreter (``--peer-python``, default
``../venv-particles/bin/python`` beside the repository, skipped when absent) through
``benchmarks/particles_peer.py`` on the records simulated here, first and to completion,
so that neither runs while the other is timed. Install it with ``python -m venv venv-particles &&
venv-particles/bin/pip install "numpy<2" particles``.

Run from the repository root::

    python benchmarks/particle_filters.py [--quick] [--peer-python PATH]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import casadi as ca
import numpy as np
from filterpy.kalman import KalmanFilter
from filterpy.monte_carlo import systematic_resample
from scipy import stats

import estim
from estim.solvers.sampling.particle_kernel import AHEAD_MIN as AHEAD

A = np.array([[1.0, 0.1], [0.0, 1.0]])
C = np.array([[1.0, 0.0]])
Q = np.diag([1e-3, 1e-2])
R = np.array([[0.1]])
P0 = np.eye(2)
SV = (-0.10, 0.97, 0.15)
LLPF_MPS = 8.4e6 / 1.14 / 1e6  # LowLevelParticleFilters.jl's published figure, M/s


# ---------------------------------------------------------------------------- models
def _lg_dynamics(x, u, p):
    return A @ x


def _lg_output(x, u, p):
    return C @ x


def linear_gaussian() -> estim.Model:
    return estim.Model(states=["p", "v"], outputs=["y"], dynamics=_lg_dynamics,
                       output=_lg_output)


def growth() -> estim.Model:
    """The growth model; the input is the time ``t - 1`` of the transition into ``t``."""
    return estim.Model(
        states=["x"], inputs=["t"], outputs=["y"],
        dynamics=lambda x, u, p: x / 2 + 25 * x / (1 + x ** 2) + 8 * ca.cos(1.2 * u[0]),
        output=lambda x, u, p: x ** 2 / 20)


def volatility() -> estim.Model:
    mu, phi, _ = SV
    return estim.Model(states=["x"], outputs=["x_out"],
                       dynamics=lambda x, u, p: mu + phi * (x - mu), output=lambda x, u, p: x)


def sv_loglik(y, yhat, p):
    """``y ~ N(0, exp(x))`` with ``yhat = x``."""
    return -0.5 * (np.log(2 * np.pi) + yhat[0] + y[0] ** 2 * ca.exp(-yhat[0]))


# ---------------------------------------------------------------------------- records
def lg_record(T: int, rng) -> np.ndarray:
    x, Y = rng.multivariate_normal(np.zeros(2), P0), []
    for k in range(T):
        if k:
            x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
        Y.append(C @ x + rng.normal(0.0, np.sqrt(R[0, 0]), 1))
    return np.array(Y)


def ngm_record(T: int, rng) -> tuple[np.ndarray, np.ndarray]:
    x, X, Y = rng.normal(0.0, 2.0), [], []
    for t in range(T):
        if t:
            x = x / 2 + 25 * x / (1 + x ** 2) + 8 * np.cos(1.2 * (t - 1)) + \
                rng.normal(0.0, np.sqrt(10.0))
        X.append(x)
        Y.append(x ** 2 / 20 + rng.normal())
    return np.array(X), np.array(Y)


def sv_record(T: int, rng) -> np.ndarray:
    mu, phi, sigma = SV
    x, Y = rng.normal(mu, sigma / np.sqrt(1 - phi ** 2)), []
    for t in range(T):
        if t:
            x = mu + phi * (x - mu) + sigma * rng.normal()
        Y.append(np.exp(0.5 * x) * rng.normal())
    return np.array(Y)


# ---------------------------------------------------------------------------- baselines
def numpy_bootstrap(Y: np.ndarray, N: int, rng) -> np.ndarray:
    """A bootstrap filter in numpy with filterpy's systematic resampling (ESS < N/2)."""
    LQ = np.linalg.cholesky(Q)
    X = rng.multivariate_normal(np.zeros(2), P0, size=N)  # (N, 2)
    w = np.full(N, 1.0 / N)
    means = np.empty((len(Y), 2))
    for k, y in enumerate(Y):
        if k:
            X = X @ A.T + rng.standard_normal((N, 2)) @ LQ.T
        w = w * np.exp(-0.5 * (y[0] - X[:, 0]) ** 2 / R[0, 0])
        w /= w.sum()
        means[k] = w @ X
        if 1.0 / np.sum(w ** 2) < N / 2:
            X = X[systematic_resample(w)]
            w = np.full(N, 1.0 / N)
    return means


def kalman_means(Y: np.ndarray) -> np.ndarray:
    """filterpy's Kalman filter on the linear Gaussian model, started with an update."""
    kf = KalmanFilter(2, 1)
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = A, C, Q, R, np.zeros(2), P0.copy()
    means = []
    for k, y in enumerate(Y):
        if k:
            kf.predict()
        kf.update(y)
        means.append(kf.x.copy())
    return np.array(means)


def timed(fn, repeats: int = 5) -> float:
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        walls.append(time.perf_counter() - t0)
    return statistics.median(walls)


def peak_mb(fn) -> float:
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2 ** 20


# ---------------------------------------------------------------------------- main
def main(argv=None) -> None:
    here = Path(__file__).resolve().parent
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer seeds and sizes")
    parser.add_argument("--peer-python", default=str(here.parent.parent / "venv-particles" /
                                                     "bin" / "python"))
    args = parser.parse_args(argv)
    seeds = 20 if args.quick else 100
    sizes = [100, 1000, 10_000, 100_000] + ([] if args.quick else [1_000_000])
    T = 100
    rng = np.random.default_rng(0)
    lg_y = lg_record(T, rng)
    ngm = [ngm_record(T, np.random.default_rng(100 + s)) for s in range(seeds)]
    sv_T = 500
    sv = [sv_record(sv_T, np.random.default_rng(200))] * seeds  # one record, many filter seeds

    # the peer first, to completion: nothing else runs while either is timed
    out = None
    if os.path.exists(args.peer_python):
        data = tempfile.NamedTemporaryFile(suffix=".npz", delete=False)
        np.savez(data, A=A, C=C, Q=Q, R=R, P0=P0, lg_y=lg_y,
                 speed_N=np.array([n for n in sizes if n <= 100_000]),
                 ngm_y=np.array([y for _, y in ngm]), ngm_N=1000,
                 sv_y=np.array(sv), sv_N=1000, sv_mu=SV[0], sv_phi=SV[1], sv_sigma=SV[2])
        data.close()
        peer = subprocess.run([args.peer_python, str(here / "particles_peer.py"), data.name],
                              capture_output=True, text=True, check=False)
        out = json.loads(peer.stdout) if peer.returncode == 0 else None
        if out is None:
            print(f"particles failed: {peer.stderr.strip().splitlines()[-1:]}")

    print(f"estim {estim.__version__}, numpy {np.__version__}, casadi {ca.__version__}, "
          f"Python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs")
    lg = linear_gaussian()
    rows = []
    for N in sizes:
        Tn = T if N < 1_000_000 else 20
        walls = {}
        for jit, one_core in ((False, True), (True, True), (True, False)):
            pf = estim.ParticleFilter(lg, Q=Q, R=R, x0=np.zeros(2), P0=P0, n_particles=N,
                                      jit=jit)
            if one_core and pf._kernel is not None:  # no thread drawing the normals ahead
                pf._kernel.ahead = False
            pf.filter(lg_y[:Tn])
            walls[jit, one_core] = timed(lambda pf=pf, Tn=Tn: pf.filter(lg_y[:Tn]))
        mem = peak_mb(lambda N=N, Tn=Tn: estim.ParticleFilter(
            lg, Q=Q, R=R, x0=np.zeros(2), P0=P0, n_particles=N, jit=True).filter(lg_y[:Tn]))
        base = timed(lambda N=N: numpy_bootstrap(lg_y, N, np.random.default_rng(1))) \
            if N <= 100_000 else float("nan")
        rows.append((N, Tn, walls[False, True], walls[True, True], walls[True, False], mem, base))
    print(f"\nSpeed: linear Gaussian model, 2 states, T = {T}; million particle-steps per second"
          f" (median of 5): interpreted, compiled on one core, compiled (from {AHEAD} normal"
          f" numbers per step a second thread draws the next step's); the ratios are the"
          f" compiled filter's speed-up\n")
    print(f"{'N':>9} {'estim':>8} {'jit 1':>8} {'jit':>8} {'MB peak':>8} {'numpy+filterpy':>15} "
          f"{'particles':>10} {'/numpy':>7} {'/particles':>10}")
    for N, Tn, wall, wall_1, wall_jit, mem, base in rows:
        peer_s = out["lg_seconds"].get(str(N)) if out else None
        peer_mps = N * T / peer_s / 1e6 if peer_s else float("nan")
        per_T = wall_jit * T / Tn  # the compiled filter's time for T samples
        print(f"{N:9d} {N * Tn / wall / 1e6:8.2f} {N * Tn / wall_1 / 1e6:8.2f} "
              f"{N * Tn / wall_jit / 1e6:8.2f} {mem:8.1f} "
              f"{N * T / base / 1e6:15.2f} {peer_mps:10.2f} {base / per_T:7.1f} "
              f"{peer_s / per_T if peer_s else np.nan:10.1f}")
    print(f"LowLevelParticleFilters.jl (published, not measured here): {LLPF_MPS:.1f} M/s")

    # error against the exact filter as N grows (Monte Carlo rate 1/sqrt(N))
    x_kf = kalman_means(lg_y)
    Ns = [100, 1000, 10_000] + ([] if args.quick else [100_000])
    errs = []
    for N in Ns:
        d = [estim.ParticleFilter(lg, Q=Q, R=R, x0=np.zeros(2), P0=P0, n_particles=N,
                                  seed=s).filter(lg_y).x - x_kf for s in range(10)]
        errs.append(float(np.sqrt(np.mean(np.square(d)))))
    slope = np.polyfit(np.log(Ns), np.log(errs), 1)[0]
    print(f"\nError of the filtered means against the Kalman filter (RMS over 10 seeds, T = {T}):")
    print("  " + ", ".join(f"N = {N}: {e:.2e}" for N, e in zip(Ns, errs, strict=True)) +
          f"; log-log slope {slope:.2f} (1/sqrt(N): -0.5)")

    # the growth model
    g = growth()
    rmse: dict[bool, list] = {False: [], True: []}
    walls_g: dict[bool, list] = {False: [], True: []}
    for jit in (False, True):
        estim.ParticleFilter(g, Q=10.0, R=1.0, x0=[0.0], P0=4.0, n_particles=1000,
                             jit=jit)  # (built once: later filters load it)
        for s, (X, Y) in enumerate(ngm):
            pf = estim.ParticleFilter(g, Q=10.0, R=1.0, x0=[0.0], P0=4.0, n_particles=1000,
                                      seed=s, jit=jit)
            t0 = time.perf_counter()
            res = pf.filter(Y[:, None], np.arange(T, dtype=float)[:, None])
            walls_g[jit].append(time.perf_counter() - t0)
            rmse[jit].append(np.sqrt(np.mean((res.x[:, 0] - X) ** 2)))
    print(f"\nGrowth model, N = 1000, T = {T}, {seeds} records:")
    for jit, name in ((False, "estim    "), (True, "estim jit")):
        print(f"  {name} RMSE {np.mean(rmse[jit]):.3f}  (median run "
              f"{1e3 * np.median(walls_g[jit]):.1f} ms, range "
              f"{1e3 * min(walls_g[jit]):.1f}-{1e3 * max(walls_g[jit]):.1f})")
    if out:
        prmse = [np.sqrt(np.mean((np.asarray(m) - X) ** 2))
                 for m, (X, _) in zip(out["ngm"]["means"], ngm, strict=True)]
        print(f"  particles RMSE {np.mean(prmse):.3f}  (median run "
              f"{1e3 * np.median(out['ngm']['seconds']):.1f} ms)")
        for jit, name in ((False, "estim"), (True, "estim jit")):
            diff = np.asarray(rmse[jit]) - np.asarray(prmse)
            print(f"  {name} - particles: {np.mean(diff):+.3f} ± "
                  f"{diff.std(ddof=1) / np.sqrt(seeds):.3f} (paired, same records), "
                  f"{100 * np.mean(diff) / np.mean(prmse):+.1f} %")

    # stochastic volatility
    v = volatility()
    mu, phi, sigma = SV
    lls: dict[bool, list] = {False: [], True: []}
    walls_v: dict[bool, list] = {False: [], True: []}
    for jit in (False, True):
        for s, Y in enumerate(sv):
            pf = estim.ParticleFilter(v, Q=sigma ** 2, R=1.0, x0=[mu],
                                      P0=sigma ** 2 / (1 - phi ** 2), n_particles=1000,
                                      loglik=sv_loglik, seed=s, jit=jit)
            t0 = time.perf_counter()
            lls[jit].append(pf.filter(Y[:, None]).log_likelihood)
            walls_v[jit].append(time.perf_counter() - t0)
    print(f"\nStochastic volatility, N = 1000, T = {sv_T}, one record, {seeds} seeds:")
    for jit, name in ((False, "estim    "), (True, "estim jit")):
        print(f"  {name} var(log L) {np.var(lls[jit], ddof=1):.4f}  (median run "
              f"{1e3 * np.median(walls_v[jit]):.1f} ms)")
    if out:
        pll = np.asarray(out["sv"]["loglik"])
        print(f"  particles var(log L) {np.var(pll, ddof=1):.4f}  (median run "
              f"{1e3 * np.median(out['sv']['seconds']):.1f} ms)")
        for jit, name in ((False, "estim"), (True, "estim jit")):
            ratio = np.var(lls[jit], ddof=1) / np.var(pll, ddof=1)
            lo, hi = (ratio / stats.f.ppf(q, seeds - 1, seeds - 1) for q in (0.975, 0.025))
            print(f"  {name}/particles {ratio:.2f}, 95 % interval [{lo:.2f}, {hi:.2f}]; "
                  f"mean log L difference {np.mean(np.asarray(lls[jit]) - pll):+.3f}")
    if out is None:
        print("\n(particles not run: no interpreter at --peer-python)")


if __name__ == "__main__":
    sys.exit(main())
