"""Wall time of ``estim.FullInformation.fit`` on the Lorenz record against Ipopt written plainly.

Problem (models.md sec. 1, OpEn's "Nonlinear State Estimation", seed 000):
the Lorenz system, Euler map at ``ts = 0.02`` (``estim.models.lorenz()``),
output ``y = (2 x1, x2 + x3, x3^2/10 - x1)``, ``x0 = (-10, -12, 27)``, process
noise ``0.02 N(0, I)``, measurement noise ``0.1 N(0, I)``. Records of
``T`` samples come from ``estim.simulate(model, EKF, x0=..., n_steps=T,
Q=0.02**2, R=0.1**2, seed=0)`` (the EKF only rides along). Full-information
estimation with the seed's weights and no prior,

.. math::
    \\min_{x_0..x_{T-1}} \\sum_{t=0}^{T-2} 20\\,\\|x_{t+1} - f(x_t)\\|^2
    + \\sum_{t=0}^{T-1} \\|y_t - h(x_t)\\|^2,

is ``estim.FullInformation(model, Q=np.eye(3) / 20, R=np.eye(3))``; every
method starts from the zero trajectory. (The seed's own code also drops the
``y_{T-1}`` term; that changes only the last few states and none of the
timings.)

* (a) ``T = 100``: the median wall time of ``fie.fit(Y)`` with
  ``solver="gauss-newton"`` (``mode="auto"``, the default: one expanded SX
  graph up to about 4200 samples; the row "mapped" forces the graph of 64-sample
  chunks that long records use) and ``solver="ipopt"``, against the
  baseline a CasADi user would write: one ``casadi.nlpsol("ipopt")`` over the
  stacked states with the measurements as parameters and the Lorenz map and
  output typed in as SX expressions (as in the seed), Ipopt's default options
  except silence (``ipopt.print_level 0``, ``ipopt.sb yes``, ``print_time
  False``), built once; only the solver call is timed. The script checks that
  all methods reach the same optimum (``max |Δx̂|``, ``Δcost`` against
  gauss-newton).
* (b) ``T = 1000`` and ``T = 10000`` (the same recipe, a longer simulation:
  the Lorenz attractor stays bounded): gauss-newton only, plus the Ipopt
  baseline at ``T = 1000`` (skipped if one solve takes over 10 s), to show
  how the time grows with ``T``. ``T = 10000`` runs on the mapped graph
  (``mode="auto"`` beyond about 4200 samples of this model).
* (a') the same problem by a plain Gauss-Newton with a generic sparse solve:
  the residual vector and the sparse normal equations :math:`J^\top J`,
  :math:`J^\top r` from CasADi (SX, built once), solved each iteration by
  ``scipy.sparse.linalg.spsolve`` (SuperLU); full steps from zeros, stopped
  when the step is below ``1e-8 (1 + max|X|)``. This is what the structured
  solver replaces (the issue quotes 3.2 ms for it).
* (c) ``--jit``: gauss-newton with ``solver_options={"jit": True}`` at every
  ``T`` (the mapped graph of 16-sample chunks compiled to C by the system
  compiler, 2-4 s to build).

Each timed call runs with the garbage collector off (as ``timeit`` does),
after one untimed call that builds the solver. OpEn's figure for the seed's
problem, 2.73 ms in 65 iterations (generated Rust, PANOC, the seed's machine
and noise draw), is quoted for scale, not measured here.

Run from the repository root::

    python benchmarks/fie.py [--repeats 50] [--jit] [--profile]

``--jit`` builds the compiled rows in a fresh compile cache (``ESTIM_CACHE_DIR`` set
to a temporary directory for the run), so their build time is a cold compilation;
a later process loads the libraries from the user's cache in milliseconds.
``--profile`` splits one interpreted fit at ``T = 100`` into its compiled evaluations
(calls, instructions, time per call, nanoseconds per instruction) and the Python
around them.

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy.sparse.linalg import spsolve

import estim

X0 = (-10.0, -12.0, 27.0)
SIGMA_W, SIGMA_V = 0.02, 0.1
W_PROCESS, W_MEASURE = 20.0, 1.0           # the seed's weights
Q_FIE, R_FIE = np.eye(3) / W_PROCESS, np.eye(3) / W_MEASURE
SIGMA, RHO, BETA, TS = 10.0, 28.0, 8.0 / 3.0, 0.02
BASELINE_OPTIONS = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False}
BASELINE_LIMIT_S = 10.0   # skip further baseline solves at T = 1000 beyond this
AGREE_TOL = 1e-6          # max |Δx̂| expected between two solvers of the same problem
OPEN_MS, OPEN_ITERATIONS = 2.73, 65

# goals of the issue
GOAL_MS_T100 = 0.5
GOAL_SPEEDUP = 25.0
GOAL_GROWTH = 15.0


# ---------------------------------------------------------------------------------- data
def record(T: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """True states and measurements ``(T, 3)`` of the seed's recipe."""
    model = estim.models.lorenz()
    ekf = estim.EKF(model, Q=SIGMA_W**2, R=SIGMA_V**2, x0=X0, P0=1.0)
    log = estim.simulate(model, ekf, x0=X0, n_steps=T, Q=SIGMA_W**2, R=SIGMA_V**2, seed=seed)
    return np.asarray(log.x, float), np.ascontiguousarray(log.y, dtype=float)


# ------------------------------------------------------------------------------ baseline
def lorenz_map(x):
    """Euler map of the Lorenz system, as the seed writes it."""
    dx = ca.vertcat(SIGMA * (x[1] - x[0]), x[0] * (RHO - x[2]) - x[1], x[0] * x[1] - BETA * x[2])
    return x + TS * dx


def lorenz_output(x):
    return ca.vertcat(2.0 * x[0], x[1] + x[2], x[2] ** 2 / 10.0 - x[0])


def build_baseline(T: int):
    """One Ipopt NLP over the stacked states, measurements as parameters."""
    X = ca.SX.sym("X", 3 * T)
    Y = ca.SX.sym("Y", 3 * T)
    J = 0
    for t in range(T - 1):
        w = X[3 * (t + 1):3 * (t + 2)] - lorenz_map(X[3 * t:3 * (t + 1)])
        J += W_PROCESS * ca.dot(w, w)
    for t in range(T):
        v = Y[3 * t:3 * (t + 1)] - lorenz_output(X[3 * t:3 * (t + 1)])
        J += W_MEASURE * ca.dot(v, v)
    return ca.nlpsol("fie_baseline", "ipopt", {"x": X, "p": Y, "f": J}, BASELINE_OPTIONS)


def build_sparse_gauss_newton(T: int):
    """Plain Gauss-Newton: sparse normal equations from CasADi, solved by SuperLU."""
    X = ca.SX.sym("X", 3 * T)
    Y = ca.SX.sym("Y", 3 * T)
    res = [np.sqrt(W_PROCESS) * (X[3 * (t + 1):3 * (t + 2)] - lorenz_map(X[3 * t:3 * (t + 1)]))
           for t in range(T - 1)]
    res += [np.sqrt(W_MEASURE) * (Y[3 * t:3 * (t + 1)] - lorenz_output(X[3 * t:3 * (t + 1)]))
            for t in range(T)]
    r = ca.vertcat(*res)
    J = ca.jacobian(r, X)
    normal = ca.Function("normal", [X, Y], [ca.sumsqr(r), J.T @ r, J.T @ J])

    def solve(x0: np.ndarray, y: np.ndarray, max_iter: int = 50):
        x = x0.copy()
        for it in range(1, max_iter + 1):
            _, g, H = normal(x, y)
            d = spsolve(H.sparse(), -np.asarray(g).ravel())
            x += d
            if np.abs(d).max() <= 1e-8 * (1.0 + np.abs(x).max()):
                return x, it, float(normal(x, y)[0]), "ok"
        return x, max_iter, float(normal(x, y)[0]), "max_iter"

    return solve


# -------------------------------------------------------------------------------- timing
@dataclass
class Row:
    T: int
    method: str
    seconds: float            # median wall time of one solve
    iterations: int
    cost: float
    x: np.ndarray             # (T, 3)
    status: str
    solver_seconds: float = float("nan")   # FitResult.solve_time (estim rows)
    build_seconds: float = float("nan")    # construction + first, untimed call
    repeats: int = 0

    @property
    def ms(self) -> float:
        return 1e3 * self.seconds

    @property
    def us_per_sample(self) -> float:
        return 1e6 * self.seconds / self.T


def _timed(fn: Callable[[], object], repeats: int, limit: float = np.inf):
    """Median wall time of ``repeats`` calls (gc off) and the last result.

    Stops early once one call takes longer than ``limit`` seconds.
    """
    times, out = [], None
    enabled = gc.isenabled()
    gc.disable()
    try:
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = fn()
            times.append(time.perf_counter() - t0)
            if times[-1] > limit:
                break
    finally:
        if enabled:
            gc.enable()
    return statistics.median(times), out, len(times)


def run_estim(Y: np.ndarray, method: str, solver: str, options: dict | None,
              repeats: int) -> Row:
    t0 = time.perf_counter()
    fie = estim.FullInformation(estim.models.lorenz(), Q=Q_FIE, R=R_FIE, solver=solver,
                                solver_options=options)
    guess = np.zeros((len(Y), 3))
    fie.fit(Y, guess=guess)
    build = time.perf_counter() - t0
    solver_times = []

    def call():
        res = fie.fit(Y, guess=guess)
        solver_times.append(res.solve_time)
        return res

    sec, res, n = _timed(call, repeats)
    return Row(len(Y), method, sec, res.iterations, res.cost, res.x, res.status,
               solver_seconds=statistics.median(solver_times), build_seconds=build, repeats=n)


def profile_fit(Y: np.ndarray, repeats: int) -> None:
    """Where one interpreted fit's time goes: each compiled function's calls per fit,
    instructions and median time per call, and the Python around them."""
    from estim._fast import FastFunction

    fie = estim.FullInformation(estim.models.lorenz(), Q=Q_FIE, R=R_FIE)
    fie.fit(Y)
    wall, _, n = _timed(lambda: fie.fit(Y), repeats)  # without the counting below
    calls: dict[str, list[float]] = {}
    instructions: dict[str, int] = {}
    plain = FastFunction.evaluate

    def counted(self):
        t0 = time.perf_counter()
        out = plain(self)
        calls.setdefault(self.fun.name(), []).append(time.perf_counter() - t0)
        instructions[self.fun.name()] = self.fun.n_instructions()
        return out

    FastFunction.evaluate = counted  # type: ignore[method-assign]
    try:
        _timed(lambda: fie.fit(Y), repeats)
    finally:
        FastFunction.evaluate = plain  # type: ignore[method-assign]
    print(f"\nProfile of one fit (T = {len(Y)}, interpreted, median of {n} fits: "
          f"{1e3 * wall:.3f} ms; each function's median call, the rest Python):")
    print(f"  {'function':24s} {'calls/fit':>9s} {'instructions':>12s} {'us/call':>8s} "
          f"{'ns/instr':>8s} {'us/fit':>8s}")
    inside = 0.0
    for name, ts in sorted(calls.items(), key=lambda kv: -sum(kv[1])):
        per_fit, med = len(ts) / n, statistics.median(ts)
        inside += per_fit * med
        print(f"  {name:24s} {per_fit:9.1f} {instructions[name]:12d} {1e6 * med:8.1f} "
              f"{1e9 * med / instructions[name]:8.2f} {1e6 * per_fit * med:8.1f}")
    print(f"  {'Python around them':24s} {'':9s} {'':12s} {'':8s} {'':8s} "
          f"{1e6 * (wall - inside):8.1f}")


def run_baseline(Y: np.ndarray, repeats: int, limit: float = np.inf) -> Row:
    T = len(Y)
    t0 = time.perf_counter()
    solver = build_baseline(T)
    build = time.perf_counter() - t0
    x0, p = np.zeros(3 * T), Y.ravel()

    sec, sol, n = _timed(lambda: solver(x0=x0, p=p), repeats, limit)
    st = solver.stats()
    status = "ok" if st.get("success", False) else str(st.get("return_status"))
    return Row(T, "nlpsol ipopt (plain)", sec, int(st["iter_count"]), float(sol["f"]),
               np.asarray(sol["x"]).reshape(T, 3), status, build_seconds=build, repeats=n)


def run_sparse_gauss_newton(Y: np.ndarray, repeats: int) -> Row:
    T = len(Y)
    t0 = time.perf_counter()
    solve = build_sparse_gauss_newton(T)
    x0, y = np.zeros(3 * T), Y.ravel()
    solve(x0, y)
    build = time.perf_counter() - t0
    sec, (x, it, cost, status), n = _timed(lambda: solve(x0, y), repeats)
    return Row(T, "gauss-newton, sparse LU (plain)", sec, it, cost, x.reshape(T, 3), status,
               build_seconds=build, repeats=n)


# -------------------------------------------------------------------------------- report
def _fmt(value: float, spec: str, width: int) -> str:
    return f"{value:>{width}{spec}}" if np.isfinite(value) else f"{'—':>{width}}"


def print_table(rows: list[Row], ref: dict[int, Row]) -> None:
    head = (f"{'T':>6} {'method':<34} {'med ms':>9} {'solver ms':>9} {'µs/sample':>9} "
            f"{'iter':>5} {'cost':>14} {'max|Δx̂|':>9} {'Δcost':>9} {'reps':>4} {'status':>6}")
    print(head)
    print("-" * len(head))
    last = None
    for r in rows:
        if last is not None and r.T != last:
            print()
        last = r.T
        g = ref[r.T]
        same = r is g
        dx = np.nan if same else float(np.max(np.abs(r.x - g.x)))
        dc = np.nan if same else r.cost - g.cost
        print(f"{r.T:>6} {r.method:<34} {r.ms:>9.3f} {_fmt(1e3 * r.solver_seconds, '.3f', 9)} "
              f"{r.us_per_sample:>9.2f} {r.iterations:>5d} {r.cost:>14.8f} "
              f"{_fmt(dx, '.1e', 9)} {_fmt(dc, '.1e', 9)} {r.repeats:>4d} {r.status:>6}")


def _verdict(ok: bool) -> str:
    return "met" if ok else "NOT met"


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50,
                        help="timed calls of gauss-newton at T = 100 (fewer for the slower rows)")
    parser.add_argument("--jit", action="store_true",
                        help="add gauss-newton with jit=True at every T "
                             "(needs a C compiler; 2-4 s to compile, in a fresh cache)")
    parser.add_argument("--profile", action="store_true",
                        help="split an interpreted fit at T = 100 into its evaluations")
    args = parser.parse_args(argv)
    if args.jit:  # a cold compile cache for this run (see the module docstring)
        os.environ["ESTIM_CACHE_DIR"] = tempfile.mkdtemp(prefix="estim-fie-bench-")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    R = args.repeats
    t_start = time.perf_counter()

    # the plain SX model is the estim model
    m = estim.models.lorenz()
    x_test = np.array([1.3, -2.1, 20.5])
    assert np.allclose(np.asarray(ca.evalf(lorenz_map(ca.DM(x_test)))).ravel(),
                       np.asarray(m.F(x_test, np.zeros(0), m.p)).ravel(), rtol=1e-14)
    assert np.allclose(np.asarray(ca.evalf(lorenz_output(ca.DM(x_test)))).ravel(),
                       np.asarray(m.H(x_test, np.zeros(0), m.p)).ravel(), rtol=1e-14)

    rows: list[Row] = []
    ref: dict[int, Row] = {}
    truth: dict[int, np.ndarray] = {}

    # (a) T = 100
    x100, y100 = record(100)
    truth[100] = x100
    gn100 = run_estim(y100, "estim gauss-newton (auto)", "gauss-newton", None, R)
    ref[100] = gn100
    rows.append(gn100)
    mapped = run_estim(y100, "estim gauss-newton (mapped)", "gauss-newton",
                       {"mode": "mapped"}, R)
    rows.append(mapped)
    jit_row = None
    if args.jit:
        jit_row = run_estim(y100, "estim gauss-newton (jit)", "gauss-newton", {"jit": True}, R)
        rows.append(jit_row)
    ipopt100 = run_estim(y100, "estim ipopt", "ipopt", None, max(3, R // 4))
    rows.append(ipopt100)
    base100 = run_baseline(y100, max(3, R // 2))
    rows.append(base100)
    sparse100 = run_sparse_gauss_newton(y100, max(3, R // 2))
    rows.append(sparse100)

    # (b) T = 1000 and 10000
    growth: dict[int, Row] = {100: gn100}
    jit_growth: dict[int, Row] = {100: jit_row} if jit_row is not None else {}
    base1000 = None
    for T, reps in ((1000, max(3, R // 2)), (10000, max(3, R // 5))):
        xT, yT = record(T)
        truth[T] = xT
        row = run_estim(yT, "estim gauss-newton (auto)", "gauss-newton", None, reps)
        ref[T] = growth[T] = row
        rows.append(row)
        if args.jit:
            jit_growth[T] = run_estim(yT, "estim gauss-newton (jit)", "gauss-newton",
                                      {"jit": True}, reps)
            rows.append(jit_growth[T])
        if T == 1000:
            base1000 = run_baseline(yT, max(3, R // 4), limit=BASELINE_LIMIT_S)
            rows.append(base1000)
    wall = time.perf_counter() - t_start

    # ------------------------------------------------------------------------------ report
    print(f"estim {estim.__version__}, casadi {ca.__version__}, numpy {np.__version__}, "
          f"Python {platform.python_version()}, {platform.machine()}, {os.cpu_count()} CPUs")
    print("Lorenz FIE (seed 000 recipe, seed 0): cost sum 20 ||x_t+1 - f(x_t)||^2 + "
          "||y_t - h(x_t)||^2, no prior,\nzero initial trajectory; time.perf_counter, gc off, "
          "median over 'reps' calls after an untimed first call\n")
    print_table(rows, ref)
    print()
    print("med ms: median wall time of fie.fit(Y) (estim rows) or of the nlpsol call (baseline). "
          "solver ms: median\nFitResult.solve_time (the solver alone, without fit's set-up and "
          "result). µs/sample: med ms / T.\nmax|Δx̂|, Δcost: against estim gauss-newton (auto) "
          "at the same T (all rows solve the same problem).")
    print(f"OpEn, the seed's figure (generated Rust, PANOC, its own machine and noise draw, not "
          f"measured here):\n  T = 100: {OPEN_MS} ms, {OPEN_ITERATIONS} iterations.")

    print("\nRMSE of x̂ against the true states: " + ", ".join(
        f"T = {T}: {np.sqrt(np.mean((ref[T].x - truth[T]) ** 2)):.4f}" for T in ref))
    print("Build time (construction + first call, s): " + "; ".join(
        f"T={r.T} {r.method.removeprefix('estim ')} {r.build_seconds:.2f}" for r in rows))

    # agreement
    print()
    bad = [r for r in rows if r is not ref[r.T]
           and not np.max(np.abs(r.x - ref[r.T].x)) <= AGREE_TOL]
    agree = max(float(np.max(np.abs(r.x - ref[r.T].x))) for r in rows if r is not ref[r.T])
    if bad:
        print("Agreement: NOT within 1e-6 of gauss-newton: " + ", ".join(
            f"T={r.T} {r.method}" for r in bad))
    else:
        print(f"Agreement: every method is within {agree:.1e} of gauss-newton (max |Δx̂|), "
              f"|Δcost| <= {max(abs(r.cost - ref[r.T].cost) for r in rows):.1e}.")
    not_ok = [r for r in rows if r.status != "ok"]
    print("Status: " + ("every solve reported 'ok'." if not not_ok else
                        "not ok: " + ", ".join(f"T={r.T} {r.method}: {r.status}" for r in not_ok)))

    # ratios
    print("\nSpeed-ups at T = 100 (time / gauss-newton auto time):")
    print(f"  plain nlpsol Ipopt / gauss-newton: {base100.seconds / gn100.seconds:.1f}×  "
          f"(iterations {base100.iterations} vs {gn100.iterations})")
    print(f"  estim ipopt / gauss-newton:        {ipopt100.seconds / gn100.seconds:.1f}×  "
          f"(iterations {ipopt100.iterations} vs {gn100.iterations})")
    print(f"  estim ipopt / plain nlpsol Ipopt:  {ipopt100.seconds / base100.seconds:.1f}×")
    print(f"  plain sparse Gauss-Newton / gauss-newton: {sparse100.seconds / gn100.seconds:.1f}×  "
          f"(iterations {sparse100.iterations} vs {gn100.iterations})")
    if jit_row is not None:
        print(f"  plain nlpsol Ipopt / gauss-newton jit: "
              f"{base100.seconds / jit_row.seconds:.1f}×")
    if base1000 is not None:
        print(f"  at T = 1000: plain nlpsol Ipopt / gauss-newton: "
              f"{base1000.seconds / growth[1000].seconds:.1f}×")
    for label, series in (("gauss-newton auto", growth), ("gauss-newton jit", jit_growth)):
        if not series:
            continue
        print(f"Growth with T ({label}):")
        for a, b in ((100, 1000), (1000, 10000)):
            ra, rb = series[a], series[b]
            print(f"  T = {b} / T = {a}: {rb.seconds / ra.seconds:.1f}× the time for {b // a}× "
                  f"the samples ({ra.us_per_sample:.1f} -> {rb.us_per_sample:.1f} µs/sample, "
                  f"iterations {ra.iterations} -> {rb.iterations})")

    # goals
    best = min([gn100, mapped] + ([jit_row] if jit_row is not None else []),
               key=lambda r: r.seconds)
    speedup = base100.seconds / gn100.seconds
    grow = growth[1000].seconds / gn100.seconds
    print("\nGoals:")
    print(f"  T = 100 in <= {GOAL_MS_T100:g} ms (fie.fit wall time, gauss-newton auto): "
          f"{gn100.ms:.3f} ms -> {_verdict(gn100.ms <= GOAL_MS_T100)}"
          f"  [fastest gauss-newton variant: {best.method.removeprefix('estim ')} "
          f"{best.ms:.3f} ms -> {_verdict(best.ms <= GOAL_MS_T100)}]")
    print(f"  >= {GOAL_SPEEDUP:g}× faster than Ipopt (the plain nlpsol baseline) at T = 100: "
          f"{speedup:.1f}× -> {_verdict(speedup >= GOAL_SPEEDUP)}"
          f"  [{best.method.removeprefix('estim ')}: {base100.seconds / best.seconds:.1f}× -> "
          f"{_verdict(base100.seconds / best.seconds >= GOAL_SPEEDUP)}]")
    print(f"  T = 1000 within {GOAL_GROWTH:g}× of T = 100: {grow:.1f}× -> "
          f"{_verdict(grow <= GOAL_GROWTH)}")
    if args.profile:
        profile_fit(y100, R)
    print(f"\nTotal run time {wall:.0f} s.")
    return rows


if __name__ == "__main__":
    main()
