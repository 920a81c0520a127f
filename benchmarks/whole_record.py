"""Per-sample time of ``EKF.filter`` and ``UKF.filter`` (a whole record in one compiled
call) against their ``step`` loops, filterpy's ``ExtendedKalmanFilter`` loop and dynamax's
jitted ``extended_kalman_filter`` and ``unscented_kalman_filter`` (Merwe points with
estim's defaults: alpha 0.1, beta 2, kappa 0).

Two records, each replayed through every filter in the same process:

* the batch reactor of the KU Leuven course (``estim.scenarios.batch_reactor()``,
  400 samples, RK4 at 0.25 h) and
* van der Pol (``estim.scenarios.van_der_pol(n_steps=1000)``, RK4 at 0.1 s, both
  states measured).

Every filter starts with an update from ``x0, P0`` alone, then predicts with ``Q``
and updates at every later sample. The filterpy models are the hand-written numpy
ones of ``benchmarks/ekf.py`` (the RK4 Jacobian by the chain rule); dynamax gets the
same RK4 maps written in ``jax.numpy`` (its Jacobians by ``jax.jacfwd``), runs in
float64 and is timed after a first call that compiles it (``jax.jit``), waiting for
its result (``block_until_ready``). ``EKF.filter`` is timed after a first call that
builds its Function for that record length (the build time is printed too), and so is
``EKF(..., jit=True).filter``, whose steps and scan run compiled to C (through estim's
library cache: the first call of the first process compiles them, later ones load
them; the time of that first call is printed).

The script prints the largest difference of each filter's estimates from the step
loop's (``EKF.filter`` should equal it to rounding; filterpy and dynamax update
``P`` as ``P - K S K^T`` where estim uses the Joseph form), then the median
per-sample time over the repeats and the ratios, to the interpreted filter and to
dynamax; then, for the interpreted and the compiled filter, the ratio to dynamax in
each of the repeats (the two timed one after the other, each the median of three calls).
dynamax is skipped when it is not installed (``pip install dynamax``).

Run from the repository root::

    python benchmarks/whole_record.py [--repeats 7]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import casadi
import numpy as np

import estim

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ekf import (  # noqa: E402 - the numpy models of benchmarks/ekf.py
    GAIN,
    K1,
    K2,
    KM1,
    KM2,
    TS,
    Problem,
    make_filterpy_ekf,
    reactor_h,
    reactor_h_x,
    reactor_step,
    replay_filterpy_ekf,
    rk4_with_jacobian,
    tuning,
    without_gc,
)

MU, TS_VDP = 1.0, 0.1


def vdp_f(x: np.ndarray) -> np.ndarray:
    return np.array([x[1], MU * (1 - x[0] ** 2) * x[1] - x[0]])


def vdp_f_x(x: np.ndarray) -> np.ndarray:
    return np.array([[0.0, 1.0], [-2 * MU * x[0] * x[1] - 1, MU * (1 - x[0] ** 2)]])


def vdp_step(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return rk4_with_jacobian(vdp_f, vdp_f_x, x, TS_VDP)


def vdp_h(x: np.ndarray) -> np.ndarray:
    return x.copy()


def vdp_h_x(x: np.ndarray) -> np.ndarray:
    return np.eye(2)


def timings(run, repeats: int) -> list[float]:
    """Seconds of ``run()`` over ``repeats`` calls, the garbage collector off."""
    def once() -> float:
        t0 = time.perf_counter()
        run()
        return time.perf_counter() - t0

    return [without_gc(once) for _ in range(repeats)]


def timed(run, repeats: int) -> float:
    """Median seconds of ``run()`` over ``repeats`` calls, the garbage collector off."""
    return statistics.median(timings(run, repeats))


def step_loop(est: estim.EKF, Y: np.ndarray) -> np.ndarray:
    est.reset()
    step = est.step
    return np.array([step(y) for y in Y])


def filterpy_loop(p: Problem, Y: np.ndarray) -> np.ndarray:
    """filterpy's EKF over the record as benchmarks/ekf.py runs it: the estimates."""
    out = np.empty((len(Y), p.scenario.model.nx))
    replay_filterpy_ekf(make_filterpy_ekf(p), p, Y, out)
    return out


def dynamax_filter(name: str, sc: estim.Scenario, kind: str = "EKF"):
    """``Y -> estimates`` by dynamax's EKF (or UKF, with estim's default Merwe points
    alpha = 0.1, beta = 2, kappa = 0) under ``jax.jit``, or None without dynamax."""
    try:
        import jax
        jax.config.update("jax_enable_x64", True)
        import jax.numpy as jnp
        from dynamax.nonlinear_gaussian_ssm import (
            ParamsNLGSSM,
            UKFHyperParams,
            extended_kalman_filter,
            unscented_kalman_filter,
        )
    except ImportError:
        return None

    def rk4(f, x, h):
        k1 = f(x)
        k2 = f(x + h / 2 * k1)
        k3 = f(x + h / 2 * k2)
        k4 = f(x + h * k3)
        return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    if name == "batch_reactor":
        def f(x):
            r1 = K1 * x[0] - KM1 * x[1] * x[2]
            r2 = K2 * x[1] ** 2 - KM2 * x[2]
            return jnp.array([-r1, r1 - 2 * r2, r1 + r2])

        def dynamics(x):
            return rk4(f, x, TS)

        def emission(x):
            return jnp.array([GAIN * (x[0] + x[1] + x[2])])
    else:
        def f(x):
            return jnp.array([x[1], MU * (1 - x[0] ** 2) * x[1] - x[0]])

        def dynamics(x):
            return rk4(f, x, TS_VDP)

        def emission(x):
            return x

    tun = tuning(sc)
    params = ParamsNLGSSM(initial_mean=jnp.asarray(tun["x0"]),
                          initial_covariance=jnp.asarray(tun["P0"]),
                          dynamics_function=dynamics, dynamics_covariance=jnp.asarray(tun["Q"]),
                          emission_function=emission, emission_covariance=jnp.asarray(tun["R"]))
    if kind == "UKF":
        hyper = UKFHyperParams(alpha=0.1, beta=2, kappa=0)
        run = jax.jit(lambda Y: unscented_kalman_filter(params, Y, hyper).filtered_means)
    else:
        run = jax.jit(lambda Y: extended_kalman_filter(params, Y).filtered_means)
    return lambda Y: np.asarray(run(jnp.asarray(Y)).block_until_ready())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    repeats = max(3, args.repeats)
    print(f"Python {platform.python_version()}, CasADi {casadi.__version__}, "
          f"numpy {np.__version__}, {platform.machine()}, {os.cpu_count()} cores; median of "
          f"{repeats} runs; load average "
          + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + " (1, 5, 15 min) at start")
    problems = [("batch_reactor", estim.scenarios.batch_reactor(), reactor_step, reactor_h,
                 reactor_h_x),
                ("van_der_pol", estim.scenarios.van_der_pol(n_steps=1000), vdp_step, vdp_h,
                 vdp_h_x)]
    for problem in problems:
        benchmark(*problem, repeats)
    print("\nload average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())
          + " (1, 5, 15 min) at the end")


def benchmark(name, sc, step, h, h_x, repeats: int) -> None:
    """Check every filter against the step loop on one record (also a warm-up), then
    print the median per-sample times: the EKF's, then the UKF's; and each run's ratio of
    the filters (interpreted and compiled) to dynamax, timed in turn in every run."""
    Y = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0).y
    T = len(Y)
    for kind in ("EKF", "UKF"):
        est = getattr(estim, kind)(sc.model, **sc.tuning)
        t0 = time.perf_counter()
        est.filter(Y)  # builds the Function for this record length
        build = time.perf_counter() - t0
        t0 = time.perf_counter()
        fast = getattr(estim, kind)(sc.model, jit=True, **sc.tuning)
        fast.filter(Y)  # compiles (or loads from the cache) its steps and this record's scan
        jit_build = time.perf_counter() - t0
        print(f"\n{name}, {kind}: {T} samples; {kind}.filter's first call (build + run) "
              f"{build * 1e3:.1f} ms; with jit=True (construction + first call: compile or "
              f"load from the cache) {jit_build * 1e3:.1f} ms")
        ref = step_loop(est, Y)
        runs = {f"{kind}.filter": lambda est=est: est.filter(Y).x,
                f"{kind}.filter jit": lambda fast=fast: fast.filter(Y).x,
                "step loop": lambda est=est: step_loop(est, Y),
                "step loop jit": lambda fast=fast: step_loop(fast, Y)}
        if kind == "EKF":
            problem = Problem(name, sc, step, h, h_x)
            runs["filterpy EKF loop"] = lambda problem=problem: filterpy_loop(problem, Y)
        dyn = dynamax_filter(name, sc, kind)
        label = f"dynamax {kind} (jit)"
        if dyn is not None:
            t0 = time.perf_counter()
            dyn(Y)  # compiles
            print(f"  dynamax's jit compilation {time.perf_counter() - t0:.2f} s")
            runs[label] = lambda dyn=dyn: dyn(Y)
        print(f"  {'filter':<20} {'max |x - step loop|':>20} {'us/sample':>10} "
              f"{'/ ' + kind + '.filter':>13} {'/ dynamax':>10}")
        times, diffs = {}, {}
        for key, run in runs.items():
            diffs[key] = float(np.max(np.abs(run() - ref)))
            times[key] = timed(run, repeats) / T
        for key in runs:
            ratio = times[key] / times[f"{kind}.filter"]
            vs = f"{times[key] / times[label]:>9.2f}x" if dyn is not None else ""
            print(f"  {key:<20} {diffs[key]:>20.2e} {times[key] * 1e6:>10.2f} {ratio:>12.2f}x "
                  f"{vs}")
        if dyn is None:
            print("  dynamax is not installed: skipped")
            continue
        # every run: the filter, then dynamax (each the median of three calls), and their
        # ratio
        for key in (f"{kind}.filter", f"{kind}.filter jit"):
            pairs = [(timed(runs[key], 3), timed(runs[label], 3)) for _ in range(repeats)]
            ratios = [a / b for a, b in pairs]
            print(f"  {key} / dynamax, each of {repeats} runs: "
                  + " ".join(f"{r:.2f}" for r in ratios)
                  + f" (median {statistics.median(ratios):.2f}, at most 1.0 in "
                  f"{sum(r <= 1.0 for r in ratios)} of {repeats})")


if __name__ == "__main__":
    main()
