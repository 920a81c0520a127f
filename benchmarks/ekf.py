"""Per-step time of ``estim.EKF`` against filterpy's ``ExtendedKalmanFilter``.

Both filters run in the same process on the same measurement record:

* (a) the batch reactor of the KU Leuven course (``estim.scenarios.batch_reactor()``,
  RK4 at ``Ts = 0.25``, models.md sec. 3) and
* (b) the Lorenz system of OpEn's example (``estim.scenarios.lorenz()``,
  Euler map at ``ts = 0.02``, models.md sec. 1),

plus an extra row: ``estim.UKF`` (one compiled CasADi call per step) against
filterpy's ``UnscentedKalmanFilter`` on the batch reactor (``benchmarks/filters.py``
compares the UKF with the EKF too). (A
filterpy UKF updates with the sigma points of its last ``predict``, zeros
before the first one; for the update-first start the baseline draws them from
``x0, P0``, as ``estim.UKF`` does.)

The filterpy baseline is written the way a filterpy user would write it: the
model in plain numpy, the Jacobian of the RK4 map by hand (chain rule through
the four stages, analytic), the prediction by overriding
``ExtendedKalmanFilter.predict_x`` (the documented way to use a nonlinear
transition; it also sets ``F`` to the Jacobian at the old state before
``predict`` propagates ``P``), and ``update(z, HJacobian, Hx)``.

The measurement record is generated once with
``estim.simulate(scenario, estim.EKF(...), seed=0)``; it is then replayed
through each filter. Both start with an update from ``x0, P0`` alone, then
predict with ``Q`` and update at every later sample. The script first checks
that the numpy models equal the CasADi ones and that both filters give the
same estimates (the maths is the same; estim uses a linear solve where
filterpy inverts ``S``), then times only the filter steps with
``time.perf_counter`` over the whole record, with the garbage collector off
as ``timeit`` does, and reports the median over the repeats.

Run from the repository root::

    python benchmarks/ekf.py [--repeats 20] [--steps N]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi
import filterpy
import numpy as np
from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

import estim

# ---------------------------------------------------------------- batch reactor (numpy)
K1, KM1, K2, KM2, GAIN, TS = 0.5, 0.05, 0.2, 0.01, 32.84, 0.25


def reactor_f(x: np.ndarray) -> np.ndarray:
    """Continuous right-hand side of A <-> B + C, 2B <-> C."""
    r1 = K1 * x[0] - KM1 * x[1] * x[2]
    r2 = K2 * x[1] ** 2 - KM2 * x[2]
    return np.array([-r1, r1 - 2 * r2, r1 + r2])


def reactor_f_x(x: np.ndarray) -> np.ndarray:
    """Jacobian of :func:`reactor_f`."""
    dr1 = np.array([K1, -KM1 * x[2], -KM1 * x[1]])
    dr2 = np.array([0.0, 2 * K2 * x[1], -KM2])
    return np.array([-dr1, dr1 - 2 * dr2, dr1 + dr2])


def rk4(f: Callable, x: np.ndarray, h: float) -> np.ndarray:
    """One classic RK4 step of size ``h``."""
    k1 = f(x)
    k2 = f(x + h / 2 * k1)
    k3 = f(x + h / 2 * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def rk4_with_jacobian(f: Callable, f_x: Callable, x: np.ndarray,
                      h: float) -> tuple[np.ndarray, np.ndarray]:
    """One RK4 step and its Jacobian, by the chain rule through the four stages.

    With :math:`D_i = \\partial k_i / \\partial x`: :math:`D_1 = f_x(x)`,
    :math:`D_2 = f_x(x_2)(I + \\tfrac h2 D_1)`, :math:`D_3 = f_x(x_3)(I + \\tfrac h2 D_2)`,
    :math:`D_4 = f_x(x_4)(I + h D_3)` and
    :math:`A = I + \\tfrac h6 (D_1 + 2D_2 + 2D_3 + D_4)`.
    """
    eye = np.eye(len(x))
    k1 = f(x)
    d1 = f_x(x)
    x2 = x + h / 2 * k1
    k2 = f(x2)
    d2 = f_x(x2) @ (eye + h / 2 * d1)
    x3 = x + h / 2 * k2
    k3 = f(x3)
    d3 = f_x(x3) @ (eye + h / 2 * d2)
    x4 = x + h * k3
    k4 = f(x4)
    d4 = f_x(x4) @ (eye + h * d3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4), eye + h / 6 * (d1 + 2 * d2 + 2 * d3 + d4)


def reactor_step(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return rk4_with_jacobian(reactor_f, reactor_f_x, x, TS)


def reactor_fx(x: np.ndarray, dt: float) -> np.ndarray:
    """Transition in filterpy's UKF signature ``fx(x, dt)``."""
    return rk4(reactor_f, x, dt)


def reactor_h(x: np.ndarray) -> np.ndarray:
    return np.array([GAIN * (x[0] + x[1] + x[2])])


REACTOR_C = np.full((1, 3), GAIN)


def reactor_h_x(x: np.ndarray) -> np.ndarray:
    return REACTOR_C


# ------------------------------------------------------------------------ Lorenz (numpy)
SIGMA, RHO, BETA, TS_LORENZ = 10.0, 28.0, 8.0 / 3.0, 0.02


def lorenz_step(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Euler map ``x + ts f(x)`` and its Jacobian ``I + ts f_x(x)``."""
    x1, x2, x3 = x
    h = TS_LORENZ
    x_next = x + h * np.array([SIGMA * (x2 - x1), x1 * (RHO - x3) - x2, x1 * x2 - BETA * x3])
    A = np.array([[1 - h * SIGMA, h * SIGMA, 0.0],
                  [h * (RHO - x3), 1 - h, -h * x1],
                  [h * x2, h * x1, 1 - h * BETA]])
    return x_next, A


def lorenz_h(x: np.ndarray) -> np.ndarray:
    return np.array([2 * x[0], x[1] + x[2], x[2] ** 2 / 10 - x[0]])


def lorenz_h_x(x: np.ndarray) -> np.ndarray:
    return np.array([[2.0, 0.0, 0.0], [0.0, 1.0, 1.0], [-1.0, 0.0, x[2] / 5]])


# ------------------------------------------------------------------------------ problems
@dataclass
class Problem:
    """A scenario with its hand-written numpy model for filterpy."""

    name: str
    scenario: estim.Scenario
    step: Callable  # x -> (F(x), dF/dx)
    h: Callable
    h_x: Callable


def check_model(p: Problem, n_points: int = 20) -> float:
    """Largest difference between the numpy model and estim's CasADi model."""
    m = p.scenario.model
    rng = np.random.default_rng(1)
    worst = 0.0
    for _ in range(n_points):
        x = p.scenario.x0 + rng.standard_normal(m.nx)
        x_next, A = p.step(x)
        A_ref, C_ref = m.jacobians(x)
        for a, b in ((x_next, m.f(x)), (A, A_ref), (p.h(x), m.h(x)), (p.h_x(x), C_ref)):
            worst = max(worst, float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))))
    return worst


# ------------------------------------------------------------------------------- filters
class NonlinearEKF(ExtendedKalmanFilter):
    """filterpy's EKF with a nonlinear transition (override ``predict_x``, as its docs say).

    ``transition(x)`` returns ``(F(x), dF/dx(x))``; ``predict()`` then
    propagates ``P`` with that Jacobian and ``Q``.
    """

    def __init__(self, dim_x: int, dim_z: int, transition: Callable):
        super().__init__(dim_x, dim_z)
        self.transition = transition

    def predict_x(self, u=0):
        self.x, self.F = self.transition(self.x)


def make_filterpy_ekf(p: Problem) -> NonlinearEKF:
    m, tun = p.scenario.model, tuning(p.scenario)
    kf = NonlinearEKF(m.nx, m.ny, p.step)
    kf.x, kf.P, kf.Q, kf.R = tun["x0"].copy(), tun["P0"].copy(), tun["Q"], tun["R"]
    return kf


def replay_filterpy_ekf(kf: NonlinearEKF, p: Problem, Y: np.ndarray, out: np.ndarray) -> float:
    h, h_x = p.h, p.h_x
    t0 = time.perf_counter()
    kf.update(Y[0], h_x, h)
    out[0] = kf.x
    for k in range(1, len(Y)):
        kf.predict()
        kf.update(Y[k], h_x, h)
        out[k] = kf.x
    return time.perf_counter() - t0


def make_filterpy_ukf(p: Problem) -> UnscentedKalmanFilter:
    m, tun = p.scenario.model, tuning(p.scenario)
    # the same sigma points as estim.UKF's defaults
    points = MerweScaledSigmaPoints(m.nx, alpha=0.1, beta=2.0, kappa=0.0)
    kf = UnscentedKalmanFilter(dim_x=m.nx, dim_z=m.ny, dt=m.dt, hx=reactor_h, fx=reactor_fx,
                               points=points)
    kf.x, kf.P, kf.Q, kf.R = tun["x0"].copy(), tun["P0"].copy(), tun["Q"], tun["R"]
    return kf


def replay_filterpy_ukf(kf: UnscentedKalmanFilter, p: Problem, Y: np.ndarray,
                        out: np.ndarray) -> float:
    t0 = time.perf_counter()
    # filterpy's update uses the sigma points left by the last predict (zeros
    # before the first one): draw them from the prior x0, P0 for the first update
    kf.sigmas_f = kf.points_fn.sigma_points(kf.x, kf.P)
    kf.update(Y[0])
    out[0] = kf.x
    for k in range(1, len(Y)):
        kf.predict()
        kf.update(Y[k])
        out[k] = kf.x
    return time.perf_counter() - t0


def replay_estim(est: estim.Estimator, p: Problem, Y: np.ndarray, out: np.ndarray) -> float:
    step = est.step
    t0 = time.perf_counter()
    for k in range(len(Y)):
        out[k] = step(Y[k])
    return time.perf_counter() - t0


def tuning(sc: estim.Scenario) -> dict[str, np.ndarray]:
    """The scenario's estimator tuning as full arrays (what filterpy wants)."""
    m = sc.model
    t = sc.tuning

    def cov(v, n):
        v = np.asarray(v, float)
        return v if v.ndim == 2 else np.diag(np.broadcast_to(v, (n,))).astype(float)

    return {"Q": cov(t["Q"], m.nx), "R": cov(t["R"], m.ny),
            "x0": np.asarray(t["x0"], float).copy(), "P0": cov(t["P0"], m.nx)}


# -------------------------------------------------------------------------------- timing
def without_gc(run: Callable):
    """``run()`` with the garbage collector off (as it was afterwards); its result."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        return run()
    finally:
        if enabled:
            gc.enable()


def measure(make: Callable, replay: Callable, p: Problem, Y: np.ndarray,
            repeats: int) -> tuple[float, np.ndarray, object]:
    """Median seconds per step over ``repeats`` replays (construction not timed).

    Returns the median, the estimates of the last replay and the last filter.
    """
    out = np.empty((len(Y), p.scenario.model.nx))
    times = []
    kf = None
    for _ in range(repeats):
        kf = make()
        times.append(without_gc(lambda kf=kf: replay(kf, p, Y, out)) / len(Y))
    return statistics.median(times), out, kf


@dataclass
class Row:
    problem: str
    estim_us: float
    filterpy_us: float
    max_dx: float
    rel_dx: float
    max_dP: float


def compare(label: str, p: Problem, Y: np.ndarray, repeats: int, make_est: Callable,
            make_fp: Callable, replay_fp: Callable, tol: float | None) -> Row:
    """Check both filters agree on ``Y`` (one untimed run each, also a warm-up), then time."""
    est = make_est()

    def make_estim():
        est.reset()
        return est

    _, x_est, _ = measure(make_estim, replay_estim, p, Y, 1)
    P_est = est.P.copy()
    _, x_fp, kf = measure(make_fp, replay_fp, p, Y, 1)
    dx = float(np.max(np.abs(x_est - x_fp)))
    scale = max(1.0, float(np.max(np.abs(x_est))))
    dP = float(np.max(np.abs(P_est - kf.P)))
    if tol is not None:
        assert np.isfinite(dx) and dx / scale < tol, (
            f"{label}: estim and filterpy disagree, max |dx| = {dx:.3g} (state scale {scale:.3g})")
    t_est, _, _ = measure(make_estim, replay_estim, p, Y, repeats)
    t_fp, _, _ = measure(make_fp, replay_fp, p, Y, repeats)
    return Row(label, 1e6 * t_est, 1e6 * t_fp, dx, dx / scale, dP)


def record(sc: estim.Scenario) -> np.ndarray:
    """The measurement record of ``sc`` with seed 0 (an EKF runs in the loop)."""
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    return np.ascontiguousarray(log.y, dtype=float)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20, help="timed replays per filter")
    parser.add_argument("--steps", type=int, default=None,
                        help="samples per record (default: each scenario's own, 400 and 100)")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    if args.steps is not None and args.steps < 2:
        parser.error("--steps must be at least 2")
    kw = {} if args.steps is None else {"n_steps": args.steps}

    reactor = Problem("batch reactor", estim.scenarios.batch_reactor(**kw), reactor_step,
                      reactor_h, reactor_h_x)
    lorenz = Problem("Lorenz", estim.scenarios.lorenz(**kw), lorenz_step, lorenz_h, lorenz_h_x)
    for p in (reactor, lorenz):
        err = check_model(p)
        assert err < 1e-12, f"{p.name}: numpy model differs from estim's by {err:.3g}"

    records = {p.name: record(p.scenario) for p in (reactor, lorenz)}
    rows = []
    for p in (reactor, lorenz):
        sc, Y = p.scenario, records[p.name]
        rows.append(compare(f"{p.name} EKF ({len(Y)} steps)", p, Y, args.repeats,
                            lambda sc=sc: estim.EKF(sc.model, **sc.tuning),
                            lambda p=p: make_filterpy_ekf(p), replay_filterpy_ekf, tol=1e-6))
    sc, Y = reactor.scenario, records[reactor.name]
    rows.append(compare(f"batch reactor UKF ({len(Y)} steps)", reactor, Y, args.repeats,
                        lambda: estim.UKF(sc.model, **sc.tuning),
                        lambda: make_filterpy_ukf(reactor), replay_filterpy_ukf, tol=1e-6))

    print(f"estim {estim.__version__}, filterpy {filterpy.__version__}, numpy {np.__version__}, "
          f"casadi {casadi.__version__}, Python {platform.python_version()}")
    print(f"median of {args.repeats} replays of the seed-0 record, time.perf_counter, gc off\n")
    head = (f"{'problem':<30} {'estim µs/step':>14} {'filterpy µs/step':>17} {'speed-up':>9} "
            f"{'max |Δx|':>10}")
    print(head)
    print("-" * len(head))
    for r in rows:
        print(f"{r.problem:<30} {r.estim_us:>14.1f} {r.filterpy_us:>17.1f} "
              f"{r.filterpy_us / r.estim_us:>8.2f}× {r.max_dx:>10.2e}")
    print()
    ekf_rows = rows[:2]
    print("Goal for the EKF: estim at least 5× faster than filterpy; measured "
          + ", ".join(f"{r.filterpy_us / r.estim_us:.2f}×" for r in ekf_rows)
          + (" (met)." if all(r.filterpy_us >= 5 * r.estim_us for r in ekf_rows)
             else " (not met)."))
    print("speed-up = filterpy / estim. max |Δx| is over all samples and states; relative to "
          "the largest |x̂|:", ", ".join(f"{r.rel_dx:.1e}" for r in rows) + ".")
    print("Final covariance, max |ΔP|:", ", ".join(f"{r.max_dP:.1e}" for r in rows)
          + " (both EKFs use the Joseph form; estim solves with S, filterpy inverts it).")
    print("estim.UKF and filterpy's UnscentedKalmanFilter use the same sigma points (Van der "
          "Merwe's, alpha 0.1);\nbenchmarks/filters.py compares the UKF with the EKF.")
    return rows


if __name__ == "__main__":
    main()
