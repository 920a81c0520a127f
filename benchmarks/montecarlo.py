"""End-to-end time of a Monte Carlo study (simulate, filter and score every seed) by
``estim.compare``'s batched path, its per-run path, and dynamax's jitted, vmapped
``extended_kalman_filter``.

The problem is van der Pol (``estim.scenarios.van_der_pol(n_steps=STEPS)``: RK4 at
0.1 s, mu = 1, both states measured, plant noise Q = 0.01 I, R = I, true x0 = (1.5, 1.5);
the EKF's tuning ``sc.tuning``: Q = 0.01 I, R = I, x0 = (0, 0), P0 = I) over SEEDS
seeds. Each row is timed end to end: the noise of every seed, the plant, the filter
and the RMSE of every seed against the true states:

* ``estim.compare(sc, {"EKF": estim.EKF}, range(SEEDS))``, the batched path (the
  seeds in chunks of 32: the plant of a chunk in one CasADi call, then the EKF of the
  chunk in one call, mapped over the seeds on the machine's cores, while the noise of
  the next chunk is drawn and the last one is scored; from 20000 samples (seeds x
  samples) on, both are compiled to C and kept in a library cache), steady
  state (after a first call in this process) and its first call in a fresh Python
  process (after ``import estim``), once with an empty library cache
  (``ESTIM_CACHE_DIR`` a new directory: it builds every CasADi Function and compiles
  them) and once with the libraries of an earlier process in the cache;
* the same with ``{"EKF": lambda m, tun: estim.EKF(m, jit=True, **tun)}``: the steps
  and the scans of the EKF compiled to C at any batch size (here the batch is compiled
  either way; ``jit=True`` also compiles the step functions), steady state and first
  calls with an empty and with a warm library cache;
* ``compare(..., batch=False)``, the per-run path (a Python loop of ``estim.simulate``,
  one plant step and one ``EKF.step`` per sample), timed on fewer seeds (``--loop-seeds``,
  default 16) and scaled to SEEDS;
* the filter alone: ``EKF._filter_seeds`` on the measurements of an
  ``estim.batch.simulate_plant`` batch;
* dynamax: ``jax.jit(jax.vmap(one_seed))``, where ``one_seed`` simulates the same plant
  in a ``jax.lax.scan`` (``x[k+1] = rk4(x[k]) + w[k]``, ``y[k] = x[k] + v[k]``), runs
  ``dynamax.nonlinear_gaussian_ssm.extended_kalman_filter`` (float64, the same tuning,
  Jacobians by ``jax.jacfwd``) and returns the RMSE of the filtered means. It is given
  the noise estim draws (``numpy.random.default_rng(seed)``: first V (T, ny), then
  W (T, nx), through the square roots of R and Q), drawn in the timed region as estim
  draws it in its own. Steady state waits for the result (``block_until_ready``); the
  first call runs in a fresh process (after ``import jax, dynamax``, so it includes
  tracing and XLA compilation). The filter alone is ``jax.vmap`` of the filter on the
  measurements of the same batch;
* dynamax as a JAX user writes it: the noise drawn by ``jax.random.normal`` inside the
  same ``jax.jit(jax.vmap(...))`` (one key per seed, from ``jax.random.split``), steady
  state. Its noise streams differ from numpy's, so only the statistics compare: the
  script prints its mean RMSE next to estim's and their difference in standard errors
  of the two Monte Carlo means.

Both filters start with an update of ``x0, P0`` by ``y[0]`` (dynamax takes
``initial_mean`` as the prior of the first emission, estim's EKF updates before it
predicts), then predict and update at every later sample; the script checks that the
first filtered means agree. estim updates ``P`` in Joseph form where dynamax uses
``P - K S K^T``, so the estimates agree to rounding, not bit for bit: the script prints
the largest difference of the per-seed RMSEs, of the true states and of the estimates
(no assertions).

Times are medians over ``--repeats`` calls with the garbage collector off (first calls:
one fresh process per repeat), with the range; the ratios are to dynamax's steady
state with numpy's noise, to its steady state with ``jax.random`` noise inside (the
goal's anchor) and, for first calls, to dynamax's first call. estim's maps run on
``os.cpu_count()`` threads; XLA runs the vmapped scan as it chooses (on CPU usually one
thread per computation).

Run from the repository root::

    python benchmarks/montecarlo.py [--repeats 5] [--seeds 256] [--steps 1000]

dynamax rows are skipped when it is not installed (``pip install -e ".[bench]"``).
There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import casadi
import numpy as np

import estim
import estim.batch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from whole_record import timings as timed  # noqa: E402 - the timing loop of whole_record.py

HERE = Path(__file__).resolve().parent
MU, DT = 1.0, 0.1


def full(v, n: int) -> np.ndarray:
    """A covariance given as a scalar, a diagonal or a matrix, as an (n, n) array."""
    v = np.asarray(v, float)
    return v if v.ndim == 2 else np.diag(np.broadcast_to(v, (n,))).astype(float)


def noise(sc: estim.Scenario, seeds) -> tuple[np.ndarray, np.ndarray]:
    """``(W, V)``, ``(S, T, nx)`` and ``(S, T, ny)``: the noise ``estim.simulate`` draws
    for every seed (first V, then W, through the square roots of the diagonal R, Q)."""
    m, T = sc.model, int(sc.n_steps)
    Lq = np.diag(np.sqrt(np.diag(full(sc.Q, m.nx))))
    Lr = np.diag(np.sqrt(np.diag(full(sc.R, m.ny))))
    W, V = [], []
    for s in seeds:
        rng = np.random.default_rng(s)
        V.append(rng.standard_normal((T, m.ny)) @ Lr.T)
        W.append(rng.standard_normal((T, m.nx)) @ Lq.T)
    return np.array(W), np.array(V)


# ------------------------------------------------------------------------------ dynamax
def dynamax_runs(sc: estim.Scenario):
    """``(monte_carlo, filter_only, monte_carlo_keys)`` by dynamax under
    ``jax.jit(jax.vmap(...))``, or None without dynamax. ``monte_carlo(W, V) -> (rmse, X,
    X_hat)`` per seed; ``filter_only(Y) -> X_hat``; ``monte_carlo_keys(keys) -> rmse``
    per seed, with the noise drawn by ``jax.random`` inside the compiled function (its
    streams differ from numpy's: only the RMSE statistics compare); all return jax arrays
    (not waited for)."""
    try:
        import jax
        jax.config.update("jax_enable_x64", True)
        import jax.numpy as jnp
        from dynamax.nonlinear_gaussian_ssm import ParamsNLGSSM, extended_kalman_filter
    except ImportError:
        return None

    def f(x):
        return jnp.array([x[1], MU * (1 - x[0] ** 2) * x[1] - x[0]])

    def rk4(x):
        k1 = f(x)
        k2 = f(x + DT / 2 * k1)
        k3 = f(x + DT / 2 * k2)
        k4 = f(x + DT * k3)
        return x + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)

    def emission(x):
        return x

    m, tun = sc.model, sc.tuning
    params = ParamsNLGSSM(
        initial_mean=jnp.asarray(np.asarray(tun["x0"], float)),
        initial_covariance=jnp.asarray(full(tun["P0"], m.nx)),
        dynamics_function=rk4, dynamics_covariance=jnp.asarray(full(tun["Q"], m.nx)),
        emission_function=emission, emission_covariance=jnp.asarray(full(tun["R"], m.ny)))
    x0 = jnp.asarray(np.asarray(sc.x0, float))

    def filtered(Y):
        return extended_kalman_filter(params, Y, output_fields=["filtered_means"]).filtered_means

    def one_seed(W, V):
        def plant(x, wv):
            w, v = wv
            return rk4(x) + w, (x, x + v)

        _, (X, Y) = jax.lax.scan(plant, x0, (W, V))
        X_hat = filtered(Y)
        return jnp.sqrt(jnp.mean((X_hat - X) ** 2)), X, X_hat

    Lq = jnp.asarray(np.sqrt(np.diag(full(sc.Q, m.nx))))
    Lr = jnp.asarray(np.sqrt(np.diag(full(sc.R, m.ny))))
    T = int(sc.n_steps)

    def one_key(key):
        # the noise drawn inside the compiled function, as a JAX user writes it
        kw, kv = jax.random.split(key)
        W = jax.random.normal(kw, (T, m.nx)) * Lq
        V = jax.random.normal(kv, (T, m.ny)) * Lr
        return one_seed(W, V)[0]

    return (jax.jit(jax.vmap(one_seed)), jax.jit(jax.vmap(filtered)),
            jax.jit(jax.vmap(one_key)))


def unboosted_filter(sc: estim.Scenario, Y: np.ndarray) -> np.ndarray | None:
    """dynamax's filtered means of ``Y`` (S, T, ny) with the ``diagonal_boost`` of its
    ``psd_solve`` (1e-9, added to ``S`` before the Cholesky solve) set to 0, for the
    agreement check only; None when dynamax's internals are not as expected."""
    import functools

    import jax
    try:
        from dynamax.nonlinear_gaussian_ssm import inference_ekf
    except ImportError:
        return None
    solve = getattr(inference_ekf, "psd_solve", None)
    if solve is None:
        return None
    _, run_filter, _ = dynamax_runs(sc)
    inference_ekf.psd_solve = functools.partial(solve, diagonal_boost=0.0)
    try:  # traced (for this shape of Y) with the patch in place
        return np.asarray(jax.block_until_ready(run_filter(jax.numpy.asarray(Y))))
    finally:
        inference_ekf.psd_solve = solve


# --------------------------------------------------------------- first calls (children)
def jit_ekf(model: estim.Model, tuning: dict) -> estim.EKF:
    """The EKF with ``jit=True``: its steps and scans compiled to C."""
    return estim.EKF(model, jit=True, **tuning)


def first_call(kind: str, seeds: int, steps: int) -> None:
    """Print the seconds of the first Monte Carlo call in this (fresh) process."""
    if kind in ("estim", "estim-jit"):
        t0 = time.perf_counter()
        sc = estim.scenarios.van_der_pol(n_steps=steps)
        estim.compare(sc, {"EKF": jit_ekf if kind == "estim-jit" else estim.EKF},
                      range(seeds))
    else:
        import dynamax  # noqa: F401 - imported before the clock starts, as estim is
        import jax
        t0 = time.perf_counter()
        sc = estim.scenarios.van_der_pol(n_steps=steps)
        run, _, _ = dynamax_runs(sc)
        W, V = noise(sc, range(seeds))
        jax.block_until_ready(run(W, V)[0])
    print(time.perf_counter() - t0)


def first_calls(kind: str, seeds: int, steps: int, repeats: int,
                cache: str | None = None) -> list[float]:
    """Seconds of the first call, one fresh process per repeat; ``cache``: the
    ``ESTIM_CACHE_DIR`` of the children (estim's compiled libraries), ``"empty"`` for a
    new empty directory each repeat."""
    code = (f"import sys; sys.path.insert(0, {str(HERE)!r}); import montecarlo; "
            f"montecarlo.first_call({kind!r}, {seeds}, {steps})")
    out = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory(prefix="estim-bench-") as empty:
            env = dict(os.environ)
            if cache is not None:
                env["ESTIM_CACHE_DIR"] = empty if cache == "empty" else cache
            done = subprocess.run([sys.executable, "-c", code], capture_output=True,
                                  text=True, check=True, env=env)
        out.append(float(done.stdout.split()[-1]))
    return out


# --------------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=256)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--loop-seeds", type=int, default=16,
                        help="seeds of the per-run path (its time is scaled to --seeds)")
    args = parser.parse_args()
    repeats, S, T = max(3, args.repeats), args.seeds, args.steps
    n_loop = max(1, min(args.loop_seeds, S))
    try:
        import jax
        jax_version = jax.__version__
    except ImportError:
        jax_version = "not installed"
    print(f"Python {platform.python_version()}, CasADi {casadi.__version__}, "
          f"numpy {np.__version__}, jax {jax_version}, {platform.machine()}, "
          f"{os.cpu_count()} cores; median of {repeats} runs")
    print(f"van der Pol, {S} seeds x {T} samples; load average "
          + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + " (1, 5, 15 min) at start")

    sc = estim.scenarios.van_der_pol(n_steps=T)
    seeds = list(range(S))
    rows: dict[str, list[float]] = {}
    agree: dict[str, str] = {}

    # estim, batched
    ref = estim.compare(sc, {"EKF": estim.EKF}, seeds)
    rmse = ref.rmse["EKF"]
    rows["estim compare, batched"] = timed(
        lambda: estim.compare(sc, {"EKF": estim.EKF}, seeds), repeats)
    agree["estim compare, batched"] = "reference"
    first = "estim compare, batched, first call"
    rows[first] = first_calls("estim", S, T, repeats, cache="empty")
    agree[first] = "fresh process, empty library cache"
    with tempfile.TemporaryDirectory(prefix="estim-bench-") as cache:
        first_calls("estim", S, T, 1, cache=cache)  # fills it
        rows[first + ", cache warm"] = first_calls("estim", S, T, repeats, cache=cache)
    agree[first + ", cache warm"] = "fresh process, libraries cached"

    # estim, batched, EKF(jit=True)
    fast = estim.compare(sc, {"EKF": jit_ekf}, seeds)
    label = "estim compare, batched, EKF(jit=True)"
    rows[label] = timed(lambda: estim.compare(sc, {"EKF": jit_ekf}, seeds), repeats)
    agree[label] = f"dRMSE {float(np.max(np.abs(fast.rmse['EKF'] - rmse))):.1e}"
    rows[label + ", first call"] = first_calls("estim-jit", S, T, repeats, cache="empty")
    agree[label + ", first call"] = "fresh process, empty library cache"
    with tempfile.TemporaryDirectory(prefix="estim-bench-") as cache:
        first_calls("estim-jit", S, T, 1, cache=cache)  # fills it
        rows[label + ", first call, cache warm"] = first_calls("estim-jit", S, T, repeats,
                                                               cache=cache)
    agree[label + ", first call, cache warm"] = "fresh process, libraries cached"

    # estim, per run
    loop_seeds = seeds[:n_loop]
    loop = estim.compare(sc, {"EKF": estim.EKF}, loop_seeds, batch=False)
    d = float(np.max(np.abs(loop.rmse["EKF"] - rmse[:n_loop])))
    scale = S / n_loop
    rows[f"estim compare, per run ({n_loop} seeds x {scale:g})"] = [
        t * scale for t in timed(lambda: estim.compare(sc, {"EKF": estim.EKF}, loop_seeds,
                                                       batch=False), repeats)]
    agree[f"estim compare, per run ({n_loop} seeds x {scale:g})"] = f"dRMSE {d:.1e}"

    # estim, filter only
    plant = estim.batch.simulate_plant(sc, seeds)
    est = estim.EKF(sc.model, **sc.tuning)
    out = est._filter_seeds(plant.y, plant.u_step)
    d = float(np.max(np.abs(np.sqrt(np.mean((out["x"] - plant.x) ** 2, axis=(1, 2))) - rmse)))
    inner = []

    def filter_only():
        inner.append(est._filter_seeds(plant.y, plant.u_step)["seconds"])

    rows["estim filter only (_filter_seeds)"] = timed(filter_only, repeats)
    rows["  its compiled call (seconds)"] = inner
    agree["estim filter only (_filter_seeds)"] = f"dRMSE {d:.1e}"
    plant_times = [estim.batch.simulate_plant(sc, seeds).seconds for _ in range(repeats)]
    rows["estim plant only (simulate_plant)"] = plant_times

    # dynamax
    runs = dynamax_runs(sc)
    dyn_steady = dyn_first = dyn_keys = None
    if runs is None:
        print("dynamax is not installed: its rows are skipped")
    else:
        run, run_filter, run_keys = runs

        def monte_carlo():
            W, V = noise(sc, seeds)
            return np.asarray(jax.block_until_ready(run(W, V)[0]))

        W, V = noise(sc, seeds)
        r_dyn, X_dyn, Xh_dyn = (np.asarray(a) for a in run(W, V))
        dx = float(np.max(np.abs(X_dyn - plant.x)))
        dxh = float(np.max(np.abs(Xh_dyn - out["x"])))
        d0 = float(np.max(np.abs(Xh_dyn[:, 0] - out["x"][:, 0])))
        dr = float(np.max(np.abs(r_dyn - rmse)))
        Yj = jax.numpy.asarray(plant.y)
        jax.block_until_ready(run_filter(Yj))
        monte_carlo()  # warm-up
        rows["dynamax jit(vmap), end to end"] = timed(monte_carlo, repeats)
        dyn_steady = statistics.median(rows["dynamax jit(vmap), end to end"])
        agree["dynamax jit(vmap), end to end"] = f"dRMSE {dr:.1e}"
        rows["dynamax first call"] = first_calls("dynamax", S, T, repeats)
        dyn_first = statistics.median(rows["dynamax first call"])
        agree["dynamax first call"] = "fresh process, incl. jit"
        rows["dynamax filter only (vmap)"] = timed(
            lambda: jax.block_until_ready(run_filter(Yj)), repeats)
        agree["dynamax filter only (vmap)"] = f"max|dx_hat| {dxh:.1e}"
        rows["dynamax noise drawing (numpy)"] = timed(lambda: noise(sc, seeds), repeats)
        keys = jax.random.split(jax.random.PRNGKey(0), S)
        r_keys = np.asarray(jax.block_until_ready(run_keys(keys)))  # compiles
        label = "dynamax jit(vmap), jax.random noise inside"
        rows[label] = timed(lambda: jax.block_until_ready(run_keys(keys)), repeats)
        dyn_keys = statistics.median(rows[label])
        # other noise streams: the mean RMSE agrees within Monte Carlo error
        se = float(np.hypot(np.std(r_keys), np.std(rmse)) / np.sqrt(S))
        agree[label] = (f"mean RMSE {np.mean(r_keys):.4f} vs {np.mean(rmse):.4f} "
                        f"({abs(np.mean(r_keys) - np.mean(rmse)) / se:.1f} s.e.)")
        print(f"estim against dynamax over {S} seeds: largest |RMSE difference| {dr:.2e}, "
              f"true states {dx:.2e}, filtered means {dxh:.2e}, "
              f"first filtered means (update of x0 by y[0]) {d0:.2e}")
        # every run: estim's compare, then dynamax with jax.random noise, one after the
        # other (the same load on the machine), and their ratio
        for name, spec in (("estim compare", estim.EKF), ("estim compare jit", jit_ekf)):
            pairs = [(timed(lambda spec=spec: estim.compare(sc, {"EKF": spec}, seeds), 1)[0],
                      timed(lambda: jax.block_until_ready(run_keys(keys)), 1)[0])
                     for _ in range(repeats)]
            ratios = [a / b for a, b in pairs]
            print(f"{name} / dynamax with jax.random noise, each of {repeats} runs (timed in "
                  "turn): " + " ".join(f"{r:.2f}" for r in ratios)
                  + f" (median {statistics.median(ratios):.2f}, at most 1.0 in "
                  f"{sum(r <= 1.0 for r in ratios)} of {repeats})")
        Xh0 = unboosted_filter(sc, plant.y)
        if Xh0 is not None:
            r0 = np.sqrt(np.mean((Xh0 - plant.x) ** 2, axis=(1, 2)))
            print("  dynamax's psd_solve adds 1e-9 I to S before solving; with that boost "
                  f"set to 0 (checked here only, not timed): RMSE "
                  f"{float(np.max(np.abs(r0 - rmse))):.2e}, filtered means "
                  f"{float(np.max(np.abs(Xh0 - out['x']))):.2e}, first filtered means "
                  f"{float(np.max(np.abs(Xh0[:, 0] - out['x'][:, 0]))):.2e}")

    print(f"\n{'row':<56} {'median s':>9} {'min-max s':>17} {'/dyn steady':>12} "
          f"{'/dyn jax.random':>16} {'/dyn first':>11}  agreement")
    for label, times in rows.items():
        med = statistics.median(times)
        r1 = f"{med / dyn_steady:.2f}x" if dyn_steady else "-"
        r3 = f"{med / dyn_keys:.2f}x" if dyn_keys else "-"
        r2 = f"{med / dyn_first:.2f}x" if dyn_first and "first" in label else ""
        span = f"{min(times):.3f}-{max(times):.3f}"
        print(f"{label:<56} {med:>9.3f} {span:>17} {r1:>12} {r3:>16} {r2:>11}  "
              f"{agree.get(label, '')}")
    print(f"\nestim's per-run row: {n_loop} seeds timed, multiplied by {scale:g}. "
          f"RMSE over the seeds: mean {np.mean(rmse):.4f}. estim's batched call: "
          f"{ref.batched}")
    print("load average " + ", ".join(f"{v:.2f}" for v in os.getloadavg())
          + " (1, 5, 15 min) at the end")


if __name__ == "__main__":
    main()
