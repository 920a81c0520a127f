"""Speed of the iterated posterior linearisation smoother (IPLS; García-Fernández,
Svensson & Särkkä 2017) against the same algorithm written in plain numpy, in the same
process.

The book's pendulum (Särkkä & Svensson, *Bayesian Filtering and Smoothing*, 2nd ed.,
2023; ``examples/data/book_pendulum.npz``, 500 samples, ``estim.scenarios.book_pendulum``:
Euler steps of 0.01 s, ``R = 0.1``, the prior ``(0, 0)``, ``P0 = I`` one step before the
first measurement). ``UKF(points="gauss-hermite", order=3, iterations=10).smooth(Y)``:
the iterated posterior linearisation filter (IPLF: the Gauss-Hermite update, then 9
re-linearisations of ``h`` by statistical linear regression about the latest posterior),
then up to 10 smoother passes, each the statistical linear regression of ``f`` and ``h``
on the sigma points of the current smoothed posteriors and the Kalman filter and RTS
smoother of the affine model (stopping when no mean moves by more than 1e-12 relative).

The numpy version is the book's way: loops over the samples, numpy over the 9 sigma
points of one sample, ``f`` and ``h`` as numpy functions. First the check (the largest
differences from estim, the RMSEs of the angle against the book's IPLKF 0.140558 and
IPLRTS 0.034733), then the times: the forward filter (``UKF.filter``), the smoother's
passes alone (from the filter's estimates) and the whole ``smooth``, estim interpreted
and with ``jit=True`` (when a C compiler is found), the ratio numpy / estim; then the
largest items of a profile of estim's ``smooth``. Medians over ``--repeats`` repeats
(interleaved), the range in brackets. Run from the repository root::

    python benchmarks/ipls_speed.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import cProfile
import datetime
import os
import platform
import pstats
import statistics
import time
from itertools import product
from pathlib import Path

import casadi
import numpy as np
from numpy.polynomial.hermite_e import hermegauss

import estim
from estim._compile import compiler
from estim.estimators.kalman.smoothing import posterior_linearised

ROOT = Path(__file__).resolve().parent.parent
DT, G = 0.01, 9.81
BOOK = {"IPLKF": 0.14055766458714145, "IPLRTS": 0.034733224044175594}
ITERATIONS = 10


def span(values, digits=3) -> str:
    return (f"{statistics.median(values):.{digits}g} "
            f"[{min(values):.{digits}g}-{max(values):.{digits}g}]")


# --- the numpy version ---------------------------------------------------------------

def f(X: np.ndarray) -> np.ndarray:
    """The Euler step of the pendulum at the points ``X (2, N)`` (columns)."""
    return np.vstack([X[0] + DT * X[1], X[1] - G * np.sin(X[0]) * DT])


def h(X: np.ndarray) -> np.ndarray:
    """The measurement ``sin(angle)`` at the points ``X (2, N)``: ``(1, N)``."""
    return np.sin(X[:1])


def gauss_hermite(n: int, order: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit points ``(n, order^n)`` and weights of the Gauss-Hermite rule."""
    nodes, w = hermegauss(order)
    w = w / w.sum()
    unit = np.array(list(product(nodes, repeat=n))).T
    return unit, np.prod(np.array(list(product(w, repeat=n))), axis=1)


def moments(fun, m, P, unit, W):
    """The mean of ``fun(x)``, ``x ~ N(m, P)``, its cross-covariance with ``x`` and its
    covariance, by the sigma points ``m + L xi``, ``L L^T = P``."""
    X = m[:, None] + np.linalg.cholesky(P) @ unit
    Z = fun(X)
    z = Z @ W
    dZ = Z - z[:, None]
    return z, ((X - m[:, None]) * W) @ dZ.T, (dZ * W) @ dZ.T


def slr(fun, m, P, unit, W):
    """The statistical linear regression ``fun(x) ~ A x + b + N(0, Omega)`` about
    ``N(m, P)``."""
    z, Psi, Phi = moments(fun, m, P, unit, W)
    A = np.linalg.solve(P, Psi).T
    return A, z - A @ m, Phi - A @ P @ A.T


def iplf(Y, x0, P0, Q, R, iterations, unit, W):
    """The iterated posterior linearisation filter: the filtered means ``(T, n)`` and
    covariances; the prior ``(x0, P0)`` on the first sample, NaN: no measurement."""
    T, n = len(Y), len(x0)
    Xf, Pf = np.empty((T, n)), np.empty((T, n, n))
    m, P = x0, P0
    for k in range(T):
        if k:  # the Gauss-Hermite prediction
            m, _, P = moments(f, m, P, unit, W)
            P = P + Q
        if np.isfinite(Y[k]).all():
            mp, Pp = m, P
            for _ in range(iterations):  # the first: the Gauss-Hermite update
                H, b, Om = slr(h, m, P, unit, W)
                S = H @ Pp @ H.T + Om + R
                K = np.linalg.solve(S, H @ Pp).T
                m = mp + K @ (Y[k] - H @ mp - b)
                P = Pp - K @ S @ K.T
                P = 0.5 * (P + P.T)
        Xf[k], Pf[k] = m, P
    return Xf, Pf


def ipls(Y, x0, P0, Q, R, Xs, Ps, passes, unit, W, tol=1e-12):
    """Up to ``passes`` passes of the iterated posterior linearisation smoother from the
    posteriors ``(Xs, Ps)``: the smoothed means, covariances and the passes done."""
    T, n = Xs.shape
    A, a, Lam = np.empty((T - 1, n, n)), np.empty((T - 1, n)), np.empty((T - 1, n, n))
    H, b, Om = np.empty((T, 1, n)), np.empty((T, 1)), np.empty((T, 1, 1))
    Xf, Pf = np.empty((T, n)), np.empty((T, n, n))
    mp, Pp, D = np.empty((T - 1, n)), np.empty((T - 1, n, n)), np.empty((T - 1, n, n))
    done = 0
    for _ in range(passes):
        for k in range(T):  # the regressions about the current posteriors
            H[k], b[k], Om[k] = slr(h, Xs[k], Ps[k], unit, W)
            if k < T - 1:
                A[k], a[k], Lam[k] = slr(f, Xs[k], Ps[k], unit, W)
        m, P = x0, P0
        for k in range(T):  # the Kalman filter of the affine model
            if k:
                m = A[k - 1] @ m + a[k - 1]
                D[k - 1] = P @ A[k - 1].T
                P = A[k - 1] @ D[k - 1] + Lam[k - 1] + Q
                mp[k - 1], Pp[k - 1] = m, 0.5 * (P + P.T)
            if np.isfinite(Y[k]).all():
                S = H[k] @ P @ H[k].T + Om[k] + R
                K = np.linalg.solve(S, H[k] @ P).T
                m = m + K @ (Y[k] - H[k] @ m - b[k])
                P = P - K @ S @ K.T
            Xf[k], Pf[k] = m, 0.5 * (P + P.T)
        new, Ps = Xf.copy(), Pf.copy()
        for k in range(T - 2, -1, -1):  # the RTS smoother
            Gk = np.linalg.solve(Pp[k], D[k].T).T
            new[k] = Xf[k] + Gk @ (new[k + 1] - mp[k])
            Pk = Pf[k] + Gk @ (Ps[k + 1] - Pp[k]) @ Gk.T
            Ps[k] = 0.5 * (Pk + Pk.T)
        done += 1
        moved = np.abs(new - Xs).max()
        Xs = new
        if moved <= tol * max(1.0, np.abs(Xs).max()):
            break
    return Xs, Ps, done


# --- the benchmark ---------------------------------------------------------------------

def header(args: argparse.Namespace) -> str:
    cc = compiler()
    return (f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, "
            f"{platform.machine()}, {os.cpu_count()} cores, Python "
            f"{platform.python_version()}, numpy {np.__version__}, CasADi "
            f"{casadi.__version__}, estim {estim.__version__}, "
            f"{cc[1].splitlines()[0] if cc else 'no C compiler'}; "
            f"`python benchmarks/ipls_speed.py --repeats {args.repeats}`")


def timed(fun) -> float:
    t0 = time.perf_counter()
    fun()
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    data = np.load(ROOT / "examples" / "data" / "book_pendulum.npz")
    sc = estim.scenarios.book_pendulum()
    m, tuning = sc.model, sc.tuning
    assert m.dt == DT and m.p[0] == G and m.p[1] == 1.0
    Y = np.vstack([[np.nan], data["Y"][:, None]])  # the prior one step before y_0
    x0, P0 = np.asarray(tuning["x0"], float), np.asarray(tuning["P0"], float)
    Q, R = np.asarray(tuning["Q"], float), np.atleast_2d(tuning["R"])
    unit, W = gauss_hermite(2, 3)

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x[1:, 0] - data["X"][:, 0]) ** 2)))

    def by_numpy():
        Xf, Pf = iplf(Y, x0, P0, Q, R, ITERATIONS, unit, W)
        return Xf, Pf, *ipls(Y, x0, P0, Q, R, Xf, Pf, ITERATIONS, unit, W)

    print("# The iterated posterior linearisation smoother: estim against plain numpy\n")
    print(header(args) + "\n")
    ests = {False: None, True: None}
    first_call = {}
    for jit in ([False, True] if compiler() else [False]):
        build = timed(lambda jit=jit: ests.__setitem__(
            jit, estim.UKF(m, **tuning, points="gauss-hermite", order=3,
                           iterations=ITERATIONS, jit=jit)))
        first_call[jit] = (build, timed(lambda jit=jit: ests[jit].smooth(Y)))
    ukf = ests[False]
    res = ukf.smooth(Y)
    Xf, Pf, Xs, Ps, done = by_numpy()
    print("## 1. the check\n")
    print("| | estim | numpy | largest difference of the means | of the covariances |")
    print("|---|---|---|---|---|")
    print(f"| IPLF (RMSE; book {BOOK['IPLKF']:.6f}) | {rmse(res.x_filtered):.6f} | "
          f"{rmse(Xf):.6f} | {np.abs(res.x_filtered - Xf).max():.1e} | "
          f"{np.abs(res.P_filtered - Pf).max():.1e} |")
    print(f"| IPLS (RMSE; book {BOOK['IPLRTS']:.6f}) | {rmse(res.x):.6f} | {rmse(Xs):.6f} | "
          f"{np.abs(res.x - Xs).max():.1e} | {np.abs(res.P - Ps).max():.1e} |")
    print(f"\nsmoother passes: estim {res.iterations} (converged {res.converged}), "
          f"numpy {done}")
    if ests[True] is not None:
        rj = ests[True].smooth(Y)
        print(f"jit=True against interpreted: largest difference of the smoothed means "
              f"{np.abs(rj.x - res.x).max():.1e}")

    stages = {"IPLF forward filter": {}, "IPLS passes (from the filter's estimates)": {},
              "whole smoother": {}}
    for _ in range(args.repeats):
        for jit, est in ests.items():
            if est is None:
                continue
            first = est.smooth(Y, iterations=1)
            for stage, fun in zip(stages, (
                    lambda est=est: est.filter(Y),
                    lambda est=est, first=first: posterior_linearised(
                        est, first, Y, None, None, ITERATIONS),
                    lambda est=est: est.smooth(Y)), strict=True):
                stages[stage].setdefault(jit, []).append(timed(fun))
        Xf, Pf = iplf(Y, x0, P0, Q, R, ITERATIONS, unit, W)
        for stage, fun in zip(stages, (
                lambda: iplf(Y, x0, P0, Q, R, ITERATIONS, unit, W),
                lambda Xf=Xf, Pf=Pf: ipls(Y, x0, P0, Q, R, Xf, Pf, ITERATIONS, unit, W),
                by_numpy), strict=True):
            stages[stage].setdefault("numpy", []).append(timed(fun))

    jits = [jit for jit in (False, True) if ests[jit] is not None]
    print("\n## 2. times (ms) and the ratio numpy / estim\n")
    for jit in jits:
        build, call = first_call[jit]
        print(f"- jit={jit}: building the UKF {build * 1e3:.0f} ms"
              f"{' (compiling, or loading the per-machine cache)' if jit else ''}, its "
              f"first `smooth` {call * 1e3:.0f} ms")
    cols = [f"estim, jit={jit}" for jit in jits]
    print("\n| stage | " + " | ".join(cols) + " | numpy | "
          + " | ".join(f"numpy / estim, jit={jit}" for jit in jits) + " |")
    print("|---" * (2 + 2 * len(jits)) + "|")
    for stage, runs in stages.items():
        ms = [span([t * 1e3 for t in runs[jit]]) for jit in jits]
        ratios = [span([a / b for a, b in zip(runs["numpy"], runs[jit], strict=True)])
                  for jit in jits]
        print(f"| {stage} | " + " | ".join(ms) + f" | {span([t * 1e3 for t in runs['numpy']])}"
              f" | " + " | ".join(ratios) + " |")

    print("\n## 3. where estim's `smooth` spends its time (cProfile, interpreted, 3 calls)\n")
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(3):
        ukf.smooth(Y)
    prof.disable()
    stats = pstats.Stats(prof)
    total = stats.total_tt
    items = stats.stats.items()
    print(f"{total / 3 * 1e3:.0f} ms a call under the profiler. estim's functions, by time "
          f"with their callees:\n")
    table([item for item in items if f"{os.sep}estim{os.sep}" in item[0][0]], 3, total, 9)
    print("\nEverything, by own time:\n")
    table(items, 2, total, 10)


def table(items, key: int, total: float, rows: int) -> None:
    """The ``rows`` largest profile entries by ``key`` (2: own time, 3: with callees),
    per ``smooth`` of the 3 profiled."""
    print("| function | calls per smooth | own time | share | with callees |")
    print("|---|---|---|---|---|")
    for (path, line, name), (_, calls, tottime, cumtime, _) in sorted(
            items, key=lambda item: -item[1][key])[:rows]:
        where = f"{Path(path).name}:{line}({name})" if line else name
        print(f"| `{where}` | {calls // 3} | {tottime / 3 * 1e3:.1f} ms | "
              f"{tottime / total:.0%} | {cumtime / 3 * 1e3:.1f} ms |")


if __name__ == "__main__":
    main()
