"""``estim.MHE`` on a differential-algebraic model against do-mpc's MHE on the same DAE:
the same estimates, and the wall time per step.

The problem is the reactor with a fast equilibrium of ``docs/dae.md``: ``A <-> B`` at
equilibrium (``c_B = K c_A``, ``K = 2``), ``B -> C`` at rate ``0.3 c_B``, A fed by
``feed``; differential states the total ``n = c_A + c_B`` and ``c_C``, algebraic state
``c_A``, measured ``y = n - c_A + 2 c_C``::

    dn/dt = -0.3 (n - c_A) + feed,   dc_C/dt = 0.3 (n - c_A),   0 = (n - c_A) - K c_A.

A record of ``T = 100`` samples at ``dt = 0.1`` (``estim.simulate`` with ``Q = 1e-4 I``,
``R = 1e-2``, seed 0, feed ``0.1 (1 + sin(0.1 k))``) is replayed through

* estim: ``estim.MHE(model, horizon=N, Q, R, arrival_cost="none")`` with
  ``solver="gauss-newton"`` (and ``"ipopt"`` for reference), the model built with
  ``integrator="collocation", substeps=2`` (Radau IIA, degree 3, two finite elements per
  sample), one ``mhe.step(y_k, u_{k-1})`` per sample;
* do-mpc (``do_mpc.estimator.MHE``, Ipopt with do-mpc's defaults, printing off, or
  ``ipopt.tol`` from ``--dompc-tol``): the
  continuous model with ``_z`` ``c_A`` and ``set_alg``, ``n_horizon = N``,
  ``collocation_type="radau"``, ``collocation_deg=3``, ``collocation_ni=2``, the
  measurements taken from its own data (``meas_from_data=True``), the feed a model input
  pinned by an exact measurement (``set_meas(..., meas_noise=False)``), one
  ``mhe.make_step([y_k, u_{k-1}])`` per sample.

Both then solve the same discretised problem on a full window:

* The discretisations are identical: both are Radau IIA collocation of degree 3 with two
  finite elements per sample from the consistent ``c_A`` (do-mpc writes the collocation
  equations into its NLP as constraints; estim writes them into the transition's
  expression graph and, the model being linear, solves them there exactly: the MHE's
  graph has no inner solve; a nonlinear model's are solved by Newton's method inside the
  transition, see ``docs/dae.md``).
* do-mpc's window has one state more, ``x_0``, carrying the arrival cost and no
  measurement; with its arrival weight ``P_x = 0`` that state is free, and its process
  noise ``w_0`` is zero at the optimum, so the window is estim's zero-prior window
  (``arrival_cost="none"``) over the same ``N`` measurements.
* do-mpc adds the process noise to the right-hand side of the ODE (``dx/dt = f + w``,
  ``w`` held over the sample), estim to the sampled state
  (``x_{k+1} = F(x_k, u_k) + w_k``). The model is linear, so the collocation map is
  ``F(x, u) + G w`` exactly, with ``G`` the map's derivative in ``w`` (computed here from
  the collocation of ``f + w``); ``P_w = G^T Q^{-1} G`` in do-mpc is then estim's
  ``Q^{-1}`` weight on the same residual. ``P_v = R^{-1}``.
* The first ``N - 1`` samples differ by design: do-mpc fills its window with copies of the
  oldest measurement, estim solves the shorter window. The agreement is taken over the
  samples ``k >= N - 1`` (full windows); the start-up difference is printed too. At
  do-mpc's default Ipopt tolerance (1e-8) the estimates differ by about 1e-7; with
  ``--dompc-tol 1e-10`` by about 1e-9 (estim's two solvers agree to about 1e-11).

Per-step time is the wall time of ``step`` / ``make_step`` (Python overhead included)
over the samples ``k >= N``, with the garbage collector off; the median of each replay,
then the median and range over ``--repeats`` replays (estim and do-mpc alternate, in one
process). The build (``estim.MHE(...)``, do-mpc's ``setup()``) is timed separately.

do-mpc is a benchmark reference only (``pip install do-mpc``), not a dependency of estim.

Run from the repository root::

    python benchmarks/dae_dompc.py [--horizon 10] [--steps 100] [--repeats 3] [--dompc-tol T]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import platform
import statistics
import time
import warnings
from collections.abc import Callable

import casadi as ca
import numpy as np

import estim

K, KR, DT, SUBSTEPS = 2.0, 0.3, 0.1, 2
Q_VAR, R_VAR = 1e-4, 1e-2
X0 = np.array([1.0, 0.0])
AGREE_TOL = 1e-6  # max |Δx̂| expected between two solvers of the same problem


# ------------------------------------------------------------------------------ model
def reactor(noise_inputs: bool = False) -> estim.Model:
    """The fast-equilibrium reactor (collocation, 2 elements of degree 3 per sample); with
    ``noise_inputs`` two more inputs ``w`` are added to the right-hand side, as do-mpc
    adds its process noise."""
    def ode(x, z, u, p):
        rhs = ca.vertcat(-KR * (x[0] - z[0]) + u[0], KR * (x[0] - z[0]))
        return rhs + u[1:3] if noise_inputs else rhs

    return estim.Model(states=["n", "cC"], algebraic=["cA"],
                       inputs=["feed", "w_n", "w_cC"] if noise_inputs else ["feed"],
                       outputs=["y"], ode=ode,
                       alg=lambda x, z, u, p: (x[0] - z[0]) - K * z[0],
                       output=lambda x, z, u, p: x[0] - z[0] + 2 * x[1],
                       dt=DT, integrator="collocation", substeps=SUBSTEPS)


def noise_gain(model: estim.Model) -> np.ndarray:
    """``G = dF/dw`` of the collocation map of ``dx/dt = f + w`` (w held over a sample).
    The model is linear, so the differences with unit ``w`` are exact to rounding; the
    map at ``w = 0`` is checked against ``model``'s."""
    mw = reactor(noise_inputs=True)
    x, u = np.array([0.7, 0.2]), 0.05
    base = mw.f(x, [u, 0.0, 0.0])
    if np.abs(base - model.f(x, [u])).max() > 1e-12:
        raise RuntimeError("the noise-augmented model does not reduce to the model at w = 0")
    return np.column_stack([mw.f(x, [u, *e]) - base for e in np.eye(2)])


def make_record(model: estim.Model, T: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Measurements ``(T, 1)`` and inputs ``(T, 1)`` (``U[k]`` acts from sample k to k+1)."""
    U = 0.1 * (1 + np.sin(0.1 * np.arange(T)))[:, None]
    tuning = dict(Q=Q_VAR, R=R_VAR, x0=X0, P0=0.1)
    sc = estim.Scenario("equilibrium reactor", model, x0=X0, n_steps=T, Q=Q_VAR, R=R_VAR,
                        tuning=tuning, inputs=U)
    log = estim.simulate(sc, estim.EKF(model, **tuning), seed=seed)
    return np.ascontiguousarray(log.y, dtype=float), U


# ----------------------------------------------------------------------------- runners
def _timed_replay(step: Callable[[int], np.ndarray], T: int, nx: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Estimates ``(T, nx)`` and the wall time of every step, garbage collector off."""
    x_hat, times = np.empty((T, nx)), np.empty(T)
    enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(T):
            t0 = time.perf_counter()
            x_hat[k] = np.ravel(step(k))
            times[k] = time.perf_counter() - t0
    finally:
        if enabled:
            gc.enable()
    return x_hat, times


def run_estim(mhe: estim.MHE, Y: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``mhe.step(y_k, u_{k-1})`` over the record, from a reset."""
    mhe.reset()
    u_prev = np.vstack([np.zeros((1, U.shape[1])), U[:-1]])
    return _timed_replay(lambda k: mhe.step(Y[k], u_prev[k]), len(Y), mhe.model.nx)


def build_dompc(N: int, P_w: np.ndarray, tol: float | None = None):
    """do-mpc's MHE on the same DAE: collocation as estim's model, ``P_x = 0``,
    ``P_v = R^{-1}``, ``P_w`` as given; the feed pinned by an exact measurement; Ipopt's
    ``tol`` if given (else do-mpc's default)."""
    import do_mpc

    m = do_mpc.model.Model("continuous")
    n = m.set_variable("_x", "n")
    cC = m.set_variable("_x", "cC")
    cA = m.set_variable("_z", "cA")
    feed = m.set_variable("_u", "feed")
    m.set_rhs("n", -KR * (n - cA) + feed, process_noise=True)
    m.set_rhs("cC", KR * (n - cA), process_noise=True)
    m.set_alg("equilibrium", (n - cA) - K * cA)
    m.set_meas("y", n - cA + 2 * cC, meas_noise=True)
    m.set_meas("feed_meas", feed, meas_noise=False)
    m.setup()
    mhe = do_mpc.estimator.MHE(m)
    s = mhe.settings
    s.n_horizon, s.t_step, s.meas_from_data = N, DT, True
    s.state_discretization, s.collocation_type = "collocation", "radau"
    s.collocation_deg, s.collocation_ni = 3, SUBSTEPS
    s.supress_ipopt_output()
    if tol is not None:
        s.nlpsol_opts["ipopt.tol"] = tol
    mhe.set_default_objective(P_x=np.zeros((2, 2)), P_v=np.array([[1.0 / R_VAR]]), P_w=P_w)
    mhe.setup()
    mhe.x0 = X0
    mhe.z0 = np.array([X0[0] / (1 + K)])
    mhe.set_initial_guess()
    return mhe


def run_dompc(N: int, P_w: np.ndarray, Y: np.ndarray, U: np.ndarray, tol: float | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """A fresh do-mpc MHE over the record: estimates, step times, the algebraic state
    and the build time."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # casadi's notice on numpy calls inside do-mpc
        warnings.simplefilter("ignore", FutureWarning)
        mhe = build_dompc(N, P_w, tol)
    build = time.perf_counter() - t0
    u_prev = np.vstack([np.zeros((1, U.shape[1])), U[:-1]])
    meas = np.hstack([Y, u_prev])
    x_hat, times = _timed_replay(lambda k: mhe.make_step(meas[k]), len(Y), 2)
    z_hat = np.asarray(mhe.data["_z"], dtype=float)
    return x_hat, times, z_hat, build


# -------------------------------------------------------------------------------- main
def _ms(values: list[float]) -> str:
    return (f"{1e3 * statistics.median(values):8.2f} ms  "
            f"[{1e3 * min(values):.2f}, {1e3 * max(values):.2f}]")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--horizon", type=int, default=10, help="window length N")
    parser.add_argument("--steps", type=int, default=100, help="record length T")
    parser.add_argument("--repeats", type=int, default=3, help="replays of each method")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-ipopt", action="store_true",
                        help="skip estim's Ipopt path (reference row)")
    parser.add_argument("--dompc-tol", type=float, default=None,
                        help="Ipopt tol for do-mpc (default: do-mpc's, i.e. Ipopt's 1e-8)")
    args = parser.parse_args(argv)
    N, T = args.horizon, args.steps
    with warnings.catch_warnings():  # do-mpc warns about its optional features
        warnings.simplefilter("ignore")
        import do_mpc

    model = reactor()
    Y, U = make_record(model, T, args.seed)
    G = noise_gain(model)
    P_w = G.T @ np.linalg.inv(Q_VAR * np.eye(2)) @ G

    print(f"python {platform.python_version()}, estim {estim.__version__}, "
          f"do-mpc {do_mpc.__version__}, casadi {ca.__version__}, numpy {np.__version__}")
    print(f"fast-equilibrium reactor (2 states, 1 algebraic, 1 output), T = {T}, N = {N}, "
          f"Radau IIA degree 3 x {SUBSTEPS} elements per sample, zero arrival cost")
    print(f"do-mpc process-noise weight P_w = G^T Q^-1 G, G = {np.array2string(G, precision=6)}")

    solvers = ["gauss-newton"] + ([] if args.no_ipopt else ["ipopt"])
    builds: dict[str, list[float]] = {s: [] for s in [*solvers, "do-mpc"]}
    steps: dict[str, list[float]] = {s: [] for s in builds}
    mhes = {}
    for s in solvers:
        t0 = time.perf_counter()
        mhes[s] = estim.MHE(model, horizon=N, Q=Q_VAR, R=R_VAR, x0=X0, arrival_cost="none",
                            solver=s)
        builds[s].append(time.perf_counter() - t0)
    x_hat: dict[str, np.ndarray] = {}
    z_dompc = np.empty(0)
    for _ in range(args.repeats):
        for s in solvers:
            x_hat[s], times = run_estim(mhes[s], Y, U)
            steps[s].append(float(np.median(times[N:])))
        x_hat["do-mpc"], times, z_dompc, build = run_dompc(N, P_w, Y, U, args.dompc_tol)
        steps["do-mpc"].append(float(np.median(times[N:])))
        builds["do-mpc"].append(build)

    full, start = slice(N - 1, None), slice(0, N - 1)
    ref = x_hat["do-mpc"]
    print(f"\nagreement with do-mpc, max |x_hat - x_hat_do-mpc| (samples k >= {N - 1}, "
          f"full windows; start-up k < {N - 1} differs by design)")
    z_estim = np.array([model.z(x) for x in x_hat["gauss-newton"]])
    for s in solvers:
        d_full = np.abs(x_hat[s][full] - ref[full]).max()
        d_start = np.abs(x_hat[s][start] - ref[start]).max() if N > 1 else 0.0
        verdict = "ok" if d_full <= AGREE_TOL else f"DIFFERS (> {AGREE_TOL:g})"
        print(f"  estim {s:13s} {d_full:.1e}  {verdict}   (start-up: {d_start:.1e})")
    dz = np.abs(z_estim[full] - z_dompc[full]).max()
    print(f"  algebraic state c_A (gauss-newton): {dz:.1e}")
    if len(solvers) > 1:
        d_own = np.abs(x_hat["gauss-newton"][full] - x_hat["ipopt"][full]).max()
        print(f"  (estim gauss-newton against estim ipopt, full windows: {d_own:.1e})")

    print(f"\nwall time per step, samples k >= {N}: median of each replay, then median "
          f"[range] over {args.repeats} replays")
    for s in [*solvers, "do-mpc"]:
        label = "do-mpc (Ipopt)" if s == "do-mpc" else f"estim {s}"
        print(f"  {label:22s} {_ms(steps[s])}   build {_ms(builds[s])}")
    base = statistics.median(steps["do-mpc"])
    print("\nratio do-mpc / estim per step (> 1: estim faster)")
    for s in solvers:
        ratios = [b / a for a, b in zip(steps[s], steps["do-mpc"], strict=True)]
        print(f"  estim {s:13s} {base / statistics.median(steps[s]):6.2f}x   "
              f"[{min(ratios):.2f}, {max(ratios):.2f}] replay by replay")


if __name__ == "__main__":
    main()
