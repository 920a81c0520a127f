r"""Monte Carlo runs of an open-loop scenario over many seeds in compiled calls.

:func:`~estim.compare` runs every seed of a scenario through :func:`~estim.simulate`,
a Python loop of one plant step and one estimator step per sample. When the plant's
inputs are known in advance (no controller), the plant does not depend on the
estimator, and both halves can be batched:

1. :func:`simulate_plant`: the noise of every seed is drawn up front exactly as
   :func:`~estim.simulate` draws it (``numpy.random.default_rng(seed)``: first
   :math:`V` (T, ny), then :math:`W` (T, nx), through the same square roots of
   :math:`R` and :math:`Q`), and the plant

   .. math::
       y_k = h(x_k, u^{h}_k) + v_k, \qquad
       x_{k+1} = \operatorname{clip}\big(F(x_k, w_k) + w^{\text{noise}}_k\big)

   is scanned over the record for all seeds in one CasADi call (the model's own
   ``F`` and ``h``, a ``mapaccum`` over the samples mapped over the seeds on the
   machine's cores), which gives the same floating-point operations as the loop;
2. a filter that supports it (:class:`~estim.EKF`, :class:`~estim.UKF`) filters all
   seeds in one call of its whole-record scan (:meth:`EKF.filter <estim.EKF.filter>`)
   mapped over the seeds;
3. the metrics of :func:`~estim.compare` (RMSE, NEES, the largest error) are
   computed over the batch with numpy.

A seed whose plant leaves the finite numbers, or whose filter meets a failed update
(whose recovery depends on the filter's history), is run by the per-seed path
instead, so the numbers are those of :func:`~estim.simulate` in every case.

The one-seed Functions run over the seeds through :func:`estim.solvers.seeds.seed_map`:
mapped over chunks of seeds, evaluated in threads on the machine's cores, reading and
writing the seeds' rows in place. Batches of at least
:data:`~estim.solvers.seeds.COMPILE_MIN_SAMPLES` samples are compiled to C once per machine
(:mod:`estim._compile`) with flags that keep the interpreter's arithmetic, so compiled
and interpreted batches give the same numbers.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np

from estim._scan import blocked_scan
from estim._validate import as_covariance, as_vector
from estim.scenarios import Scenario
from estim.solvers.seeds import seed_map


def unsupported(scenario: Scenario) -> str:
    """Why the scenario's plant cannot be simulated for a batch of seeds ("" when it can)."""
    if scenario.controller is not None:
        return ("its input comes from a controller, a feedback law evaluated sample by "
                "sample")
    return ""


@dataclass(frozen=True)
class PlantBatch:
    """The plant of a scenario simulated for several seeds (see :func:`simulate_plant`).

    Attributes
    ----------
    seeds : list of int
    t : (T,) array
        Sample times.
    x : (S, T, nx) array
        True states, seed by seed.
    y : (S, T, ny) array
        Measurements.
    u : (T, nu) array
        The input applied after each sample (what :func:`~estim.simulate` logs).
    u_step : (T, nu) array
        The input :func:`~estim.simulate` passes to ``estimator.step`` with ``y[k]``.
    finite : (S,) bool array
        The seed's plant stayed finite (state and outputs); the others must be run by
        :func:`~estim.simulate`, which raises where the plant left the finite numbers.
    seconds : float
        Wall time of the simulation.
    how : str
        ``"compiled"`` or ``"interpreted"`` (see :func:`~estim.solvers.seeds.seed_map`).
    """

    seeds: list[int]
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    u_step: np.ndarray
    finite: np.ndarray
    seconds: float
    how: str = "interpreted"


def simulate_plant(scenario: Scenario, seeds: list[int]) -> PlantBatch:
    """The scenario's plant over ``seeds``, as :func:`~estim.simulate` runs it.

    Parameters
    ----------
    scenario : Scenario
        A scenario without a controller (see :func:`unsupported`).
    seeds : list of int
        Noise seeds.

    Returns
    -------
    PlantBatch
        States ``(S, T, nx)``, measurements ``(S, T, ny)`` and the inputs; seeds whose
        plant did not stay finite are marked in ``finite``.
    """
    from estim.simulate import _input_table, _sqrt_psd, draw_noise

    why = unsupported(scenario)
    if why:
        raise ValueError(f"the plant of {scenario.name} cannot be batched: {why}")
    t0 = time.perf_counter()
    m = scenario.model
    nx, ny, nu, T, S = m.nx, m.ny, m.nu, int(scenario.n_steps), len(seeds)
    x0 = as_vector(scenario.x0, nx, "x0")
    Lq = _sqrt_psd(as_covariance(scenario.Q, nx, "Q", definite=False))
    Lr = _sqrt_psd(as_covariance(scenario.R, ny, "R", definite=False))
    U = _input_table(scenario.inputs, T, m)
    # the inputs of simulate's loop: h sees u_step[k] at sample k; the transition from k
    # to k+1 takes w[k]; the log's u[k] is the input applied after sample k
    if U is None:
        U_log = np.zeros((T, nu))
        u_step = np.zeros((T, nu))
    else:
        U_log = U.copy()
        u_step = U.copy() if m.sampled else np.vstack([U[:1], U[:-1]])
    # into the next sample: the input applied after k (and, sampled, the next one's)
    W = m.transitions(U_log, np.vstack([U_log[1:], U_log[-1:]]) if m.sampled else U_log)
    ts = np.arange(T) * m.dt
    changes = sorted(scenario.plant_changes or [], key=lambda c: c[0])
    P = np.empty((T, m.p.size))
    p, nxt = m.p, 0
    for k in range(T):
        while nxt < len(changes) and ts[k] >= changes[nxt][0] - 1e-12:
            p = m.with_params(**changes[nxt][1]).p
            nxt += 1
        P[k] = p
    V, Wn = draw_noise(seeds, T, Lr, Lq)  # as simulate draws it
    key = ("plant", m.F.serialize(), m.H.serialize(), bool(scenario.clip),
           m.lower.tolist(), m.upper.tolist(), T)
    fun = seed_map(key, lambda expand: _plant_scan(scenario, T, expand), S * T)
    x_end, X, Y = fun([x0, W.ravel(), P.ravel(), u_step.ravel(), Wn.reshape(S, -1),
                       V.reshape(S, -1)], S)
    X, Y = X.reshape(S, T, nx), Y.reshape(S, T, ny)
    finite = np.isfinite(X).all(axis=(1, 2)) & ~np.isinf(Y).any(axis=(1, 2)) \
        & np.isfinite(x_end).all(axis=1)
    return PlantBatch(seeds=list(seeds), t=ts, x=X, y=Y, u=U_log, u_step=u_step,
                      finite=finite, seconds=time.perf_counter() - t0, how=fun.how)


def _plant_scan(scenario: Scenario, T: int, expand: bool) -> ca.Function:
    """``(x0, W, P, U_h, noise_w, noise_v) -> (x_T, X, Y)``: the plant over one seed's
    record (``W``, ``P``, ``U_h`` and the noise one column per sample)."""
    m = scenario.model
    nx, ny = m.nx, m.ny
    x, w = ca.SX.sym("x", nx), ca.SX.sym("w", m.nw)
    p, u = ca.SX.sym("p", m.p.size), ca.SX.sym("u", m.nu)
    wn, v = ca.SX.sym("noise_w", nx), ca.SX.sym("noise_v", ny)
    y = m.H(x, u, p) + v
    x_next = m.F(x, w, p) + wn
    if scenario.clip:
        x_next = ca.fmin(ca.fmax(x_next, ca.DM(m.lower)), ca.DM(m.upper))
    step = ca.Function("plant", [x, w, p, u, wn, v], [x_next, x, y],
                       ["x", "w", "p", "u", "noise_w", "noise_v"], ["x_next", "x_k", "y"])
    return blocked_scan(step, T, (1, 2, 3, 4, 5), expand=expand)


def run_seeds(scenario: Scenario, estimator, plant: PlantBatch, burn_in: int,
              keep_logs: bool) -> tuple[list[dict | None], float, str]:
    """What :func:`~estim.compare` records of every seed's run (see
    :func:`estim._runs.run_seed`), from one batched filter call over the seeds' records.

    Returns the summaries in seed order, None for a seed that the per-seed path must
    run (a plant that left the finite numbers, a failed update), the seconds of the
    filter call and whether it was compiled (see :func:`~estim.solvers.seeds.seed_map`).
    """
    from estim.metrics import nees_values, peak_location, startup_samples
    from estim.simulate import _Recorder

    m = scenario.model
    nx = m.nx
    S, T = plant.x.shape[:2]
    keep = np.flatnonzero(plant.finite)
    out = estimator._filter_seeds(plant.y[keep], plant.u_step)
    per_step = out["seconds"] / max(len(keep) * T, 1)
    err = out["x"] - plant.x[keep]
    ne = nees_values(err[:, burn_in:], out["P"][:, burn_in:])  # one batched solve
    has_p = np.isfinite(out["P"]).any(axis=(1, 2, 3))
    with warnings.catch_warnings():  # seeds without any covariance: NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        nees = np.nanmean(ne, axis=1) / nx
    # per state: each seed's squared errors of a state contiguous, as rmse() sums them
    per_state = np.sqrt(np.mean(np.ascontiguousarray(
        (err[:, burn_in:] ** 2).transpose(0, 2, 1)), axis=2))
    # the largest error after the start-up, as compare finds it
    size = np.abs(err).reshape(len(keep), T * nx)
    size[:, :startup_samples(T) * nx] = -np.inf
    size[np.isnan(size)] = -np.inf
    where = np.argmax(size, axis=1)
    results: list[dict | None] = [None] * S
    states = list(range(nx))
    for j, i in enumerate(keep):
        status = out["status"][j]
        if status is None:
            continue
        seed = plant.seeds[i]
        e = err[j, burn_in:][:, states]  # the copy rmse() reduces: the same sums
        k, n = divmod(int(where[j]), nx)
        peak = size[j, where[j]]
        log = None
        if keep_logs:
            rec = _Recorder(T, nx)
            rec.x_hat, rec.P, rec.nis = out["x"][j], out["P"][j], out["nis"][j]
            rec.solve_time[:] = per_step
            rec.status[:] = "ok"
            for sample, text in status.items():
                rec.status[sample] = text
            rec.extra[:] = [{} for _ in range(T)]
            rec.done = T
            log = rec.log(m, estimator, plant.t, plant.x[i], plant.y[i], plant.u)
        results[i] = {
            "seed": seed, "rmse": float(np.sqrt(np.mean(e ** 2))),
            "per_state": per_state[j].tolist(),
            "nees": float(nees[j]) if has_p[j] else np.nan,
            "step": per_step, "failures": 0,
            "flagged": len(status), "steps": T, "log": log,
            "peak": (float(peak), peak_location(m.state_names[n], plant.t[k], seed))
            if np.isfinite(peak) else (float("nan"), ""),
            "kind": type(estimator).__name__, "caveat": estimator.caveat,
        }
    return results, out["seconds"], out["how"]
