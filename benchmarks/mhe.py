"""Per-step time of ``estim.MHE`` against moving horizon estimation written "the obvious way".

Two problems (models.md sec. 2 and 3):

* (a) van der Pol (``estim.scenarios.van_der_pol()``, RK4 at 0.1 s, both
  states measured), horizon ``N = 15``, no bounds, arrival cost
  ``"filtering"`` (estim's default) and ``"none"`` (the MPCTools source);
* (b) the batch reactor (``estim.scenarios.batch_reactor()``, RK4 at 0.25 s,
  one output), ``N = 25``, arrival cost ``"none"``, ``0 <= x <= 10``.

For each seed the measurement record is generated once with
``estim.simulate(scenario, estim.EKF(...), seed=s)`` and replayed through
``estim.MHE(model, horizon=N, arrival_cost=..., solver=S)`` for ``S`` in
``"ipopt"``, ``"gauss-newton"``, ``"sqp"`` and ``"fatrop"``, one ``mhe.step(y_k, u_{k-1})`` per
sample. The time of a step is ``mhe.info.solve_time`` (wall time of the whole
step: data shift, arrival-cost update, parameter vector and solve).

The baseline is the windowed problem written the way a CasADi user would
write it: at time ``T`` the decision variables are ``x_{T-N+1}, ..., x_T``
(SX), the cost

.. math::
    \\sum_{k=T-N+1}^{T-1} \\|x_{k+1} - F(x_k, u_k)\\|^2_{Q^{-1}}
    + \\sum_{k=T-N+1}^{T} \\|y_k - h(x_k, u_{k-1})\\|^2_{R^{-1}}

built from the model's ``F(x, u, p)`` and ``H(x, u, p)`` with
``p = model.p``, zero arrival cost, the bounds as simple bounds, and Ipopt
(exact Hessian, cold start from zeros, ``tol = 1e-10`` as estim's Ipopt
path uses, so both stop at the same accuracy). Two variants:

* "build+solve": one ``casadi.nlpsol`` per step with the window's data as
  constants, built and solved once (the build is timed with the solve);
* "parametric": the ``nlpsol`` is built once with the window's measurements
  and inputs as parameters, then cold-started at every step.

This is exactly estim's ``arrival_cost="none"`` problem, so the script first
checks that the baseline's estimates agree with every estim solver on it
(``max |Δx̂|`` column). With ``"filtering"`` estim solves a different problem
(it has a prior); that row compares timings only.

Only samples ``k >= N`` count (the window is full and has moved at least
once); before that the baselines do not run. Times are pooled over seeds,
with the garbage collector off as ``timeit`` does; with ``--repeats > 1``
each step's time is the median over the replays.

Run from the repository root::

    python benchmarks/mhe.py [--seeds 3] [--repeats 1]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import textwrap
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

import estim

SOLVERS = ("ipopt", "gauss-newton", "sqp", "fatrop")
#: per-solver options (``--jit`` compiles the Gauss-Newton iterations to machine code)
SOLVER_OPTIONS: dict[str, dict] = {}
# the only non-default options: no printing, and the tolerance of estim's Ipopt path
BASELINE_OPTIONS = {"ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
                    "ipopt.tol": 1e-10}
AGREE_TOL = 1e-6  # max |Δx̂| expected between two solvers of the same problem

# goals of the issue, in ms per step
GOAL_IPOPT_VDP = 2.0
GOAL_FAST_VDP = 0.4
GOAL_FAST_REACTOR = 0.5
DOMPC_VDP_MS = 6.1  # do-mpc 5.1.2 MHE, vdP N = 15, median per step (models.md sec. 2)


# ------------------------------------------------------------------------------ problems
@dataclass
class Problem:
    """A scenario with the MHE set-up benchmarked on it."""

    name: str
    scenario: estim.Scenario
    horizon: int
    arrival_costs: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    mhe_options: dict = field(default_factory=dict)


@dataclass
class Record:
    """One seed's simulated run: true states, measurements, inputs (time-major)."""

    x: np.ndarray
    y: np.ndarray
    u: np.ndarray


def record(sc: estim.Scenario, seed: int) -> Record:
    """The measurement record of ``sc`` for ``seed`` (an EKF runs in the loop)."""
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=seed)
    return Record(np.asarray(log.x, float), np.ascontiguousarray(log.y, dtype=float),
                  np.ascontiguousarray(log.u, dtype=float))


@dataclass
class Replay:
    """Estimates of every sample, and per-step data for the samples ``k >= N``."""

    x_hat: np.ndarray         # (T, nx), NaN where the method did not run
    times: np.ndarray         # (T - N,) seconds
    iterations: np.ndarray    # (T - N,)
    statuses: Counter


def _gc_off(fn: Callable[[], Replay]) -> Replay:
    enabled = gc.isenabled()
    gc.disable()
    try:
        return fn()
    finally:
        if enabled:
            gc.enable()


# --------------------------------------------------------------------------------- estim
def replay_estim(mhe: estim.MHE, rec: Record, N: int) -> Replay:
    """``mhe.step(y_k, u_{k-1})`` over the record; time from ``mhe.info.solve_time``."""
    T, nx, nu = len(rec.y), mhe.model.nx, mhe.model.nu
    mhe.reset()
    x_hat = np.empty((T, nx))
    times, iters = np.empty(T), np.empty(T)
    statuses: Counter = Counter()
    u_prev = np.zeros(nu)
    for k in range(T):
        x_hat[k] = mhe.step(rec.y[k], u_prev)
        info = mhe.info
        times[k], iters[k] = info.solve_time, info.iterations
        statuses[info.status] += 1
        u_prev = rec.u[k]
    return Replay(x_hat, times[N:], iters[N:], statuses)


# ------------------------------------------------------------------------------ baseline
def window_nlp(model: estim.Model, X, Y, U, Uprev, Qinv: np.ndarray, Rinv: np.ndarray):
    """Cost of the window written directly with ``model.F`` and ``model.H``.

    ``X (nx, N)`` are the decision variables; ``Y (ny, N)``, ``U (nu, N)``
    (input from slot ``j`` to ``j + 1``) and ``Uprev (nu, N)`` (input held when
    ``y_j`` was taken) are numbers or CasADi symbols.
    """
    p = model.p
    N = X.shape[1]
    J = 0
    for j in range(N - 1):
        w = X[:, j + 1] - model.F(X[:, j], U[:, j], p)
        J += ca.bilin(Qinv, w, w)
    for j in range(N):
        v = Y[:, j] - model.H(X[:, j], Uprev[:, j], p)
        J += ca.bilin(Rinv, v, v)
    return J


def _window_data(rec: Record, k: int, N: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Y (ny, N)``, ``U (nu, N)``, ``Uprev (nu, N)`` of the window ending at sample ``k >= N``."""
    s = k - N + 1
    Y = rec.y[s:k + 1].T
    U = rec.u[s:k + 1].T      # the last column is not used (no slot after the newest)
    Uprev = rec.u[s - 1:k].T  # rec.u[j] is the input applied after sample j
    return Y, U, Uprev


def _stats(solver) -> tuple[int, str]:
    st = solver.stats()
    status = "ok" if st.get("success", False) else str(st.get("return_status", "unknown"))
    return int(st.get("iter_count", 0)), status


def _replay(p: Problem, rec: Record, solve_window) -> Replay:
    """Estimates and per-step times over the steps ``k >= N``, from zeros (no warm
    start). ``solve_window(Y, U, Uprev, lbx, ubx) -> (solution, nlpsol)`` is what is
    timed."""
    m, N = p.scenario.model, p.horizon
    T, nx = len(rec.y), m.nx
    lbx, ubx = np.tile(p.lower, N), np.tile(p.upper, N)
    x_hat = np.full((T, nx), np.nan)
    times, iters = np.empty(T - N), np.empty(T - N)
    statuses: Counter = Counter()
    for i, k in enumerate(range(N, T)):
        Y, U, Uprev = _window_data(rec, k, N)
        t0 = time.perf_counter()
        sol, solver = solve_window(Y, U, Uprev, lbx, ubx)
        times[i] = time.perf_counter() - t0
        iters[i], status = _stats(solver)
        statuses[status] += 1
        x_hat[k] = np.asarray(sol["x"]).reshape(N, nx)[-1]
    return Replay(x_hat, times, iters, statuses)


def replay_build_solve(p: Problem, rec: Record, Qinv, Rinv) -> Replay:
    """One ``nlpsol`` per step: build the window NLP with the data as constants, solve cold."""
    m, N = p.scenario.model, p.horizon
    x0 = np.zeros(m.nx * N)

    def solve_window(Y, U, Uprev, lbx, ubx):
        X = ca.SX.sym("X", m.nx, N)
        J = window_nlp(m, X, ca.DM(Y), ca.DM(U), ca.DM(Uprev), Qinv, Rinv)
        solver = ca.nlpsol("mhe_window", "ipopt", {"x": ca.vec(X), "f": J}, BASELINE_OPTIONS)
        return solver(x0=x0, lbx=lbx, ubx=ubx), solver

    return _replay(p, rec, solve_window)


def build_parametric(p: Problem, Qinv, Rinv):
    """The window NLP built once, with ``(Y, U, Uprev)`` as parameters."""
    m, N = p.scenario.model, p.horizon
    X = ca.SX.sym("X", m.nx, N)
    Y, U, Uprev = ca.SX.sym("Y", m.ny, N), ca.SX.sym("U", m.nu, N), ca.SX.sym("Up", m.nu, N)
    J = window_nlp(m, X, Y, U, Uprev, Qinv, Rinv)
    nlp = {"x": ca.vec(X), "f": J, "p": ca.vertcat(ca.vec(Y), ca.vec(U), ca.vec(Uprev))}
    return ca.nlpsol("mhe_parametric", "ipopt", nlp, BASELINE_OPTIONS)


def replay_parametric(p: Problem, rec: Record, solver) -> Replay:
    """The prebuilt NLP solved at every step from zeros (no warm start)."""
    x0 = np.zeros(p.scenario.model.nx * p.horizon)

    def solve_window(Y, U, Uprev, lbx, ubx):
        par = np.concatenate([Y.ravel(order="F"), U.ravel(order="F"), Uprev.ravel(order="F")])
        return solver(x0=x0, p=par, lbx=lbx, ubx=ubx), solver

    return _replay(p, rec, solve_window)


# -------------------------------------------------------------------------------- timing
@dataclass
class Row:
    problem: str
    method: str
    times: list = field(default_factory=list)       # per seed, (T - N,) seconds
    iterations: list = field(default_factory=list)  # per seed
    errors: list = field(default_factory=list)      # per seed, (T, nx) x̂ - x
    x_hat: list = field(default_factory=list)       # per seed, (T, nx)
    statuses: Counter = field(default_factory=Counter)
    build_s: float = float("nan")
    max_dx: float = float("nan")                    # vs the build+solve baseline
    same_problem: bool = True                       # solves the baseline's problem

    @property
    def median_ms(self) -> float:
        return 1e3 * float(np.median(np.concatenate(self.times)))

    @property
    def p90_ms(self) -> float:
        return 1e3 * float(np.percentile(np.concatenate(self.times), 90))

    @property
    def median_iterations(self) -> float:
        return float(np.median(np.concatenate(self.iterations)))

    def rmse(self, start: int = 0) -> float:
        err = np.concatenate([e[start:] for e in self.errors])
        return float(np.sqrt(np.mean(err**2))) if np.isfinite(err).all() else float("nan")


def run(make: Callable[[], Replay], repeats: int) -> Replay:
    """Replay ``repeats`` times; each step's time is the median over the replays."""
    reps = [_gc_off(make) for _ in range(repeats)]
    out = reps[-1]
    if repeats > 1:
        out.times = np.median(np.stack([r.times for r in reps]), axis=0)
    return out


def add(row: Row, rep: Replay, rec: Record) -> None:
    row.times.append(rep.times)
    row.iterations.append(rep.iterations)
    row.x_hat.append(rep.x_hat)
    row.errors.append(rep.x_hat - rec.x)
    row.statuses.update(rep.statuses)


def benchmark(p: Problem, records: list[Record], repeats: int) -> list[Row]:
    """All rows of one problem: every arrival cost × solver, then the two baselines."""
    m, N = p.scenario.model, p.horizon
    rows = []
    for arrival in p.arrival_costs:
        for solver in SOLVERS:
            t0 = time.perf_counter()
            mhe = estim.MHE(m, horizon=N, arrival_cost=arrival, solver=solver,
                            solver_options=SOLVER_OPTIONS.get(solver, {}),
                            **p.mhe_options, **p.scenario.tuning)
            row = Row(p.name, f"estim {solver} ({arrival})", build_s=time.perf_counter() - t0,
                      same_problem=arrival == "none")
            replay_estim(mhe, records[0], N)  # warm-up (first calls load plugins)
            for rec in records:
                add(row, run(lambda rec=rec, mhe=mhe: replay_estim(mhe, rec, N), repeats), rec)
            rows.append(row)
    Qinv = np.linalg.inv(mhe.Q)  # the same covariance matrices estim uses
    Rinv = np.linalg.inv(mhe.R)
    base = Row(p.name, "nlpsol build+solve/step")
    for rec in records:
        add(base, run(lambda rec=rec: replay_build_solve(p, rec, Qinv, Rinv), repeats), rec)
    t0 = time.perf_counter()
    solver = build_parametric(p, Qinv, Rinv)
    par = Row(p.name, "nlpsol parametric, cold", build_s=time.perf_counter() - t0)
    for rec in records:
        add(par, run(lambda rec=rec: replay_parametric(p, rec, solver), repeats), rec)
    rows += [base, par]
    for row in rows:
        if row.same_problem:
            row.max_dx = max(float(np.max(np.abs(a[N:] - b[N:])))
                             for a, b in zip(row.x_hat, base.x_hat, strict=True))
    return rows


# --------------------------------------------------------------------------------- report
def _max_dx_between(a: Row, b: Row, N: int) -> float:
    return max(float(np.max(np.abs(x[N:] - y[N:]))) for x, y in zip(a.x_hat, b.x_hat, strict=True))


def print_table(rows: list[Row], horizons: dict[str, int]) -> None:
    head = (f"{'problem':<18} {'method':<26} {'med ms':>8} {'p90 ms':>8} {'med it':>6} "
            f"{'RMSE':>7} {'RMSE≥N':>7} {'×build':>7} {'×param':>7} {'max|Δx̂|':>9}")
    print(head)
    print("-" * len(head))
    last = None
    for r in rows:
        if last is not None and r.problem != last:
            print()
        last = r.problem
        ref = {q.method: q for q in rows if q.problem == r.problem}
        base = ref["nlpsol build+solve/step"]
        par = ref["nlpsol parametric, cold"]
        N = horizons[r.problem]
        full = r.rmse() if r.method.startswith("estim") else float("nan")
        rmse_full = f"{full:>7.4f}" if np.isfinite(full) else f"{'—':>7}"
        dx = f"{r.max_dx:>9.1e}" if r.same_problem and r is not base else f"{'—':>9}"
        print(f"{r.problem:<18} {r.method:<26} {r.median_ms:>8.3f} {r.p90_ms:>8.3f} "
              f"{r.median_iterations:>6.0f} {rmse_full} {r.rmse(N):>7.4f} "
              f"{base.median_ms / r.median_ms:>6.1f}× {par.median_ms / r.median_ms:>6.1f}× {dx}")


def _verdict(value: float, goal: float) -> str:
    return "met" if value <= goal else "not met"


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3,
                        help="number of measurement records (seeds 0, 1, ...)")
    parser.add_argument("--repeats", type=int, default=1, help="timed replays per record")
    parser.add_argument("--jit", action="store_true",
                        help="compile the gauss-newton iterations (needs a C compiler)")
    args = parser.parse_args(argv)
    if args.jit:
        SOLVER_OPTIONS["gauss-newton"] = {"jit": True}
    if args.seeds < 1:
        parser.error("--seeds must be at least 1")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")

    vdp_sc = estim.scenarios.van_der_pol()
    reactor_sc = estim.scenarios.batch_reactor()
    problems = [
        Problem("van der Pol N=15", vdp_sc, 15, ("filtering", "none"),
                vdp_sc.model.lower, vdp_sc.model.upper),
        Problem("batch reactor N=25", reactor_sc, 25, ("none",),
                reactor_sc.model.lower, np.full(reactor_sc.model.nx, 10.0),
                {"upper": 10.0}),
    ]
    rows: list[Row] = []
    t_start = time.perf_counter()
    for p in problems:
        records = [record(p.scenario, s) for s in range(args.seeds)]
        rows += benchmark(p, records, args.repeats)
    wall = time.perf_counter() - t_start
    horizons = {p.name: p.horizon for p in problems}

    print(f"estim {estim.__version__}, casadi {ca.__version__}, numpy {np.__version__}, "
          f"Python {platform.python_version()}, {platform.machine()}, "
          f"{os.cpu_count()} CPUs")
    steps = ", ".join(f"{p.name}: {p.scenario.n_steps - p.horizon} of {p.scenario.n_steps}"
                      for p in problems)
    print(f"{args.seeds} seeds × {args.repeats} replay(s); timed steps per seed (k >= N): "
          f"{steps}; time.perf_counter, gc off\n")
    print_table(rows, horizons)
    print()
    print("med/p90 ms: median / 90th percentile of the per-step wall time over steps k >= N and "
          "seeds (estim:\nmhe.info.solve_time, the whole step; baselines: build+solve, or "
          "parameter vector+solve). med it:\nmedian solver iterations. RMSE: all samples, "
          "pooled over seeds and states; RMSE≥N: samples k >= N only\n(the baselines run only "
          "there). ×build, ×param: time of the build+solve / parametric baseline divided by\n"
          "the row's time (speed-up). max|Δx̂|: largest difference of x̂_k (k >= N) from the "
          "build+solve baseline,\nfor the rows that solve its problem (arrival cost none). "
          "With arrival cost none and no prior the first\nwindows of the reactor (fewer "
          "measurements than states) have no unique optimum, so RMSE may differ\nbetween "
          "solvers through samples k < N; RMSE≥N compares like with like.")

    # ------------------------------------------------------------------- checks and notes
    print()
    same = [r for r in rows if r.same_problem and not r.method.startswith("nlpsol build")]
    bad = [r for r in same if not r.max_dx <= AGREE_TOL]
    if bad:
        print("Agreement: NOT within 1e-6 of the baseline: "
              + ", ".join(f"{r.problem} {r.method} ({r.max_dx:.1e})" for r in bad) + ".")
    else:
        print(f"Agreement: every solver of the arrival-cost-none problem is within "
              f"{max(r.max_dx for r in same):.1e} of the baseline (k >= N).")
    for p in problems:
        for arrival in p.arrival_costs:
            ref = next(r for r in rows if r.method == f"estim ipopt ({arrival})"
                       and r.problem == p.name)
            diffs = [f"{s} {_max_dx_between(r, ref, p.horizon):.1e}" for r in rows
                     for s in SOLVERS[1:]
                     if r.problem == p.name and r.method == f"estim {s} ({arrival})"]
            print(f"  {p.name}, {arrival}: max |Δx̂| vs estim ipopt (k >= N): "
                  + ", ".join(diffs))
    not_ok = [(r, n - r.statuses.get("ok", 0)) for r in rows
              for n in [sum(r.statuses.values())]]
    not_ok = [(r, n) for r, n in not_ok if n]
    if not_ok:
        print("Steps whose status is not 'ok': " + "; ".join(
            f"{r.problem} {r.method}: {n} ({dict(r.statuses)})" for r, n in not_ok) + ".")
    else:
        print("Every step of every method reported status 'ok'.")
    print("Construction time, not in the per-step times (ms):")
    for p in problems:
        print(textwrap.fill(f"{p.name}: " + "; ".join(
            f"{r.method.removeprefix('estim ')} {1e3 * r.build_s:.0f}"
            for r in rows if r.problem == p.name and np.isfinite(r.build_s)),
            width=100, initial_indent="  ", subsequent_indent="    "))

    # ------------------------------------------------------------------------------ goals
    def med(problem: str, method: str) -> float:
        return next(r.median_ms for r in rows if r.problem == problem and r.method == method)

    vdp, reactor = problems[0].name, problems[1].name
    ipopt_vdp = med(vdp, "estim ipopt (filtering)")
    fast_vdp = min((med(vdp, f"estim {s} (filtering)"), s) for s in SOLVERS[1:])
    fast_reactor = min((med(reactor, f"estim {s} (none)"), s) for s in SOLVERS[1:])
    print()
    print("Goals of the issue (measured medians, arrival cost filtering on van der Pol):")
    print(f"  Ipopt path <= {GOAL_IPOPT_VDP:g} ms/step on van der Pol N=15 (do-mpc needs about "
          f"{DOMPC_VDP_MS:g} ms, models.md): {ipopt_vdp:.3f} ms "
          f"(none: {med(vdp, 'estim ipopt (none)'):.3f} ms) -> "
          f"{_verdict(ipopt_vdp, GOAL_IPOPT_VDP)}")
    print(f"  fast path <= {GOAL_FAST_VDP:g} ms/step on van der Pol N=15: {fast_vdp[0]:.3f} ms "
          f"({fast_vdp[1]}) -> {_verdict(fast_vdp[0], GOAL_FAST_VDP)}")
    print(f"  fast path <= {GOAL_FAST_REACTOR:g} ms/step on the batch reactor N=25: "
          f"{fast_reactor[0]:.3f} ms ({fast_reactor[1]}) -> "
          f"{_verdict(fast_reactor[0], GOAL_FAST_REACTOR)}")
    print(f"\nTotal run time {wall:.0f} s.")
    return rows


if __name__ == "__main__":
    main()
