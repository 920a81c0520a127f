"""Per-step time of ``estim.UKF`` against ``estim.EKF`` and filterpy's ``UnscentedKalmanFilter``.

All three filters run in the same process on the same measurement record of

* (a) the batch reactor of the KU Leuven course (``estim.scenarios.batch_reactor()``,
  RK4 at ``Ts = 0.25``, 3 states, 1 output) and
* (b) the van der Pol oscillator of MPCTools (``estim.scenarios.van_der_pol()``,
  RK4 at ``dt = 0.1``, 2 states, both measured).

``estim.UKF`` does the sigma points, their propagation through ``F`` and ``h``, the
update and its checks in one compiled CasADi call per step; the filterpy baseline is
written the way a filterpy user would write it, the model in plain numpy, with the
same sigma points (Van der Merwe's, ``alpha = 0.1, beta = 2, kappa = 0``). Both
start with an update from ``x0, P0`` (filterpy's update uses the sigma points of its
last ``predict``: the baseline draws them from the prior for the first update).

The script first checks that the numpy models equal the CasADi ones and that the two
UKFs give the same estimates, then times only the filter steps with
``time.perf_counter`` over the whole record, with the garbage collector off, and
reports the median over the repeats (the three filters take turns in each repeat).

Run from the repository root::

    python benchmarks/filters.py [--repeats 20] [--steps N]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi
import filterpy
import numpy as np
from ekf import rk4, tuning, without_gc  # benchmarks/ekf.py's RK4, tuning and timing
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

import estim

K1, KM1, K2, KM2, GAIN = 0.5, 0.05, 0.2, 0.01, 32.84


def reactor_ode(x: np.ndarray) -> np.ndarray:
    r1 = K1 * x[0] - KM1 * x[1] * x[2]
    r2 = K2 * x[1] ** 2 - KM2 * x[2]
    return np.array([-r1, r1 - 2 * r2, r1 + r2])


def van_der_pol_ode(x: np.ndarray) -> np.ndarray:
    return np.array([x[1], (1 - x[0] ** 2) * x[1] - x[0]])


@dataclass
class Problem:
    """A scenario with its numpy model for filterpy."""

    name: str
    scenario: estim.Scenario
    fx: Callable  # filterpy's fx(x, dt)
    hx: Callable


PROBLEMS = {
    "batch reactor": (estim.scenarios.batch_reactor, lambda x, dt: rk4(reactor_ode, x, dt),
                      lambda x: np.array([GAIN * (x[0] + x[1] + x[2])])),
    "van der Pol": (estim.scenarios.van_der_pol, lambda x, dt: rk4(van_der_pol_ode, x, dt),
                    lambda x: x.copy()),
}


def check_model(p: Problem, n_points: int = 20) -> float:
    """Largest difference between the numpy model and estim's CasADi model."""
    m = p.scenario.model
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(n_points):
        x = np.asarray(p.scenario.x0, float) + rng.standard_normal(m.nx)
        for a, b in ((p.fx(x, m.dt), m.f(x)), (p.hx(x), m.h(x))):
            worst = max(worst, float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))))
    return worst


def make_filterpy_ukf(p: Problem) -> UnscentedKalmanFilter:
    m, tun = p.scenario.model, tuning(p.scenario)
    points = MerweScaledSigmaPoints(m.nx, alpha=0.1, beta=2.0, kappa=0.0)
    kf = UnscentedKalmanFilter(dim_x=m.nx, dim_z=m.ny, dt=m.dt, hx=p.hx, fx=p.fx,
                               points=points)
    kf.x, kf.P, kf.Q, kf.R = tun["x0"].copy(), tun["P0"].copy(), tun["Q"], tun["R"]
    return kf


def replay_filterpy(kf: UnscentedKalmanFilter, Y: np.ndarray, out: np.ndarray,
                    P_out: np.ndarray) -> float:
    t0 = time.perf_counter()
    kf.sigmas_f = kf.points_fn.sigma_points(kf.x, kf.P)  # the update-first start
    kf.update(Y[0])
    out[0] = kf.x
    for k in range(1, len(Y)):
        kf.predict()
        kf.update(Y[k])
        out[k] = kf.x
    elapsed = time.perf_counter() - t0
    P_out[:] = kf.P
    return elapsed


def replay_estim(est: estim.Estimator, Y: np.ndarray, out: np.ndarray,
                 P_out: np.ndarray) -> float:
    step = est.step
    t0 = time.perf_counter()
    for k in range(len(Y)):
        out[k] = step(Y[k])
    elapsed = time.perf_counter() - t0
    P_out[:] = est.info.P
    return elapsed


def measure(make: Callable, replay: Callable, Y: np.ndarray, nx: int
            ) -> tuple[float, np.ndarray, np.ndarray]:
    """Seconds per step of one replay (construction not timed), its estimates and its
    last covariance."""
    out, P = np.empty((len(Y), nx)), np.empty((nx, nx))
    kf = make()
    return without_gc(lambda: replay(kf, Y, out, P)) / len(Y), out, P


@dataclass
class Row:
    problem: str
    steps: int
    ekf_us: float
    ukf_us: float
    filterpy_us: float
    max_dx: float
    max_dP: float


def run(p: Problem, repeats: int) -> Row:
    sc = p.scenario
    m = sc.model
    log = estim.simulate(sc, estim.EKF(m, **sc.tuning), seed=0)
    Y = np.ascontiguousarray(log.y, dtype=float)
    ekf, ukf = estim.EKF(m, **sc.tuning), estim.UKF(m, **sc.tuning)

    def fresh(est):
        def make():
            est.reset()
            return est
        return make

    # untimed runs: agreement (and warm-up)
    _, x_ukf, P_ukf = measure(fresh(ukf), replay_estim, Y, m.nx)
    _, x_fp, P_fp = measure(lambda: make_filterpy_ukf(p), replay_filterpy, Y, m.nx)
    measure(fresh(ekf), replay_estim, Y, m.nx)
    dx = float(np.max(np.abs(x_ukf - x_fp)))
    dP = float(np.max(np.abs(P_ukf - P_fp)))
    assert dx < 1e-8, f"{p.name}: estim.UKF and filterpy's UKF differ by {dx:.3g}"
    # the three filters take turns, so that a change of the machine's load affects all
    times: dict[str, list[float]] = {"ekf": [], "ukf": [], "filterpy": []}
    for _ in range(repeats):
        times["ekf"].append(measure(fresh(ekf), replay_estim, Y, m.nx)[0])
        times["ukf"].append(measure(fresh(ukf), replay_estim, Y, m.nx)[0])
        times["filterpy"].append(measure(lambda: make_filterpy_ukf(p), replay_filterpy, Y,
                                         m.nx)[0])
    t_ekf, t_ukf, t_fp = (statistics.median(times[k]) for k in ("ekf", "ukf", "filterpy"))
    return Row(p.name, len(Y), 1e6 * t_ekf, 1e6 * t_ukf, 1e6 * t_fp, dx, dP)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed replays per filter")
    parser.add_argument("--steps", type=int, default=None,
                        help="samples per record (default: each scenario's own, 400 and 120)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if args.steps is not None and args.steps < 2:
        parser.error("--steps must be at least 2")
    kw = {} if args.steps is None else {"n_steps": args.steps}
    problems = [Problem(name, make(**kw), fx, hx) for name, (make, fx, hx) in PROBLEMS.items()]
    for p in problems:
        err = check_model(p)
        assert err < 1e-12, f"{p.name}: numpy model differs from estim's by {err:.3g}"
    rows = [run(p, args.repeats) for p in problems]

    print(f"estim {estim.__version__}, filterpy {filterpy.__version__}, numpy {np.__version__}, "
          f"casadi {casadi.__version__}, Python {platform.python_version()}")
    print(f"median of {args.repeats} replays of the seed-0 record, time.perf_counter, gc off\n")
    head = (f"{'problem':<26} {'EKF µs':>8} {'UKF µs':>8} {'filterpy UKF µs':>16} "
            f"{'UKF/EKF':>8} {'filterpy/UKF':>13} {'max |Δx|':>10} {'|ΔP| end':>10}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r.problem + f' ({r.steps} steps)':<26} {r.ekf_us:>8.1f} {r.ukf_us:>8.1f} "
              f"{r.filterpy_us:>16.1f} {r.ukf_us / r.ekf_us:>7.2f}× "
              f"{r.filterpy_us / r.ukf_us:>12.1f}× {r.max_dx:>10.1e} {r.max_dP:>10.1e}")
    print()
    ratios = [r.ukf_us / r.ekf_us for r in rows]
    print("Goal: a UKF step at most 2× an EKF step; measured "
          + ", ".join(f"{q:.2f}×" for q in ratios)
          + (" (met)." if all(q <= 2 for q in ratios) else " (not met)."))
    print("max |Δx|: estim.UKF against filterpy's UKF over all samples and states; |ΔP| end: "
          "the last covariance.")
    return rows


if __name__ == "__main__":
    main()
