r"""Monte Carlo runs of an open-loop scenario over many seeds in compiled calls.

:func:`~estim.compare` runs every seed of a scenario through :func:`~estim.simulate`,
a Python loop of one plant step and one estimator step per sample. When the plant's
inputs are known in advance (no controller), the plant does not depend on the
estimator, and both halves can be batched (:func:`run_batches`, seed by seed the same
numbers as :func:`simulate_plant` and one filter call over all seeds):

1. :func:`simulate_plant`: the noise of every seed is drawn exactly as
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

:func:`run_batches` runs the three as a pipeline over chunks of seeds: workers, one
per core, draw the noise of a chunk, simulate its plant and filter it, while the
calling thread scores the chunks done (numpy's generators and CasADi release the GIL;
the NEES solves do not).

A seed whose plant leaves the finite numbers, or whose filter meets a failed update
(whose recovery depends on the filter's history), is run by the per-seed path
instead, so the numbers are those of :func:`~estim.simulate` in every case.

The one-seed Functions run over the seeds through :func:`estim.solvers.seeds.seed_map`:
mapped over chunks of seeds (in the pipeline: by the serial maps of its workers,
:mod:`estim.solvers.seed_threads`), reading and writing the seeds' rows in place.
Batches of at least
:data:`~estim.solvers.seeds.COMPILE_MIN_SAMPLES` samples are compiled to C once per machine
(:mod:`estim._compile`) with flags that keep the interpreter's arithmetic, so compiled
and interpreted batches give the same numbers.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim._scan import blocked_scan
from estim._validate import as_covariance, as_vector
from estim.experiment import silent_outputs
from estim.metrics import nees_values
from estim.scenarios import Scenario
from estim.solvers.seed_threads import evaluate
from estim.solvers.seeds import CHUNK, seed_map, threads
from estim.verdicts import seed_scores

if TYPE_CHECKING:
    from estim.estimators.kalman.fused import FusedKalman


def unsupported(scenario: Scenario) -> str:
    """Why the scenario's plant cannot be simulated for a batch of seeds ("" when it can)."""
    if scenario.controller is not None:
        return ("its input comes from a controller, a feedback law evaluated sample by "
                "sample")
    if not scenario.model.manifold.euclidean_states:
        return "its states include quaternions or angles (process noise on the manifold)"
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


class _Plant:
    """The plant of a scenario set up for a batch of seeds (as :func:`simulate_plant`
    describes it): its inputs and noise factors, then (:meth:`build`) its one-seed scan,
    run chunk by chunk."""

    def __init__(self, scenario: Scenario):
        from estim.simulate import _input_table, _sqrt_psd

        why = unsupported(scenario)
        if why:
            raise ValueError(f"the plant of {scenario.name} cannot be batched: {why}")
        m = scenario.model
        nx, ny, nu, T = m.nx, m.ny, m.nu, int(scenario.n_steps)
        self.T, self.nx, self.ny = T, nx, ny
        self.x0 = as_vector(scenario.x0, nx, "x0")
        self.Lq = _sqrt_psd(as_covariance(scenario.Q, nx, "Q", definite=False))
        self.Lr = _sqrt_psd(as_covariance(scenario.R, ny, "R", definite=False))
        U = _input_table(scenario.inputs, T, m)
        # the inputs of simulate's loop: h sees u_step[k] at sample k; the transition from
        # k to k+1 takes w[k]; the log's u[k] is the input applied after sample k
        if U is None:
            self.U_log = np.zeros((T, nu))
            self.u_step = np.zeros((T, nu))
        else:
            self.U_log = U.copy()
            self.u_step = U.copy() if m.sampled else np.vstack([U[:1], U[:-1]])
        # into the next sample: the input applied after k (and, sampled, the next one's)
        U_log = self.U_log
        self.W = m.transitions(U_log, np.vstack([U_log[1:], U_log[-1:]]) if m.sampled
                               else U_log).ravel()
        self.t = np.arange(T) * m.dt
        changes = sorted(scenario.plant_changes or [], key=lambda c: c[0])
        P = np.empty((T, m.p.size))
        p, nxt = m.p, 0
        for k in range(T):
            while nxt < len(changes) and self.t[k] >= changes[nxt][0] - 1e-12:
                p = m.with_params(**changes[nxt][1]).p
                nxt += 1
            P[k] = p
        self.P = P.ravel()
        self.scenario = scenario
        # the outputs a sensor does not report at a sample (Scenario.sampling): NaN
        self.silent = silent_outputs(scenario.sampling, m, T)

    def build(self, S: int, maps: bool = True) -> None:
        """The one-seed scan for ``S`` seeds (see :func:`~estim.solvers.seeds.seed_map`:
        compiled for a large batch), with the maps of a call over all of them if
        ``maps`` (a pipeline's workers use serial maps of their own)."""
        m, T, scenario = self.scenario.model, self.T, self.scenario
        key = ("plant", m.F.serialize(), m.H.serialize(), bool(scenario.clip),
               m.lower.tolist(), m.upper.tolist(), T)
        self.fun = seed_map(key, lambda expand: _plant_scan(scenario, T, expand), S * T)
        if maps:
            self.fun.build(S)

    def noise(self, seeds: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """``(W, V)`` of the seeds, ``(n, T, nx)`` and ``(n, T, ny)``, as
        :func:`~estim.simulate` draws them (:func:`estim.simulate.draw_noise`)."""
        from estim.simulate import draw_noise

        V, Wn = draw_noise(seeds, self.T, self.Lr, self.Lq)
        return Wn, V

    def run(self, Wn: np.ndarray, V: np.ndarray, out: tuple, slot: int | None = None
            ) -> None:
        """The seeds' plant under the noise ``Wn``, ``V`` (see :meth:`noise`), into the
        rows ``out = (x_T, X, Y)``: ``(n, nx)``, ``(n, T, nx)`` and ``(n, T, ny)`` (C
        contiguous); with the serial map of ``slot`` when given (for a pipeline's
        threads, :func:`estim.solvers.seed_threads.evaluate`)."""
        n = len(Wn)
        inputs = [self.x0, self.W, self.P, self.u_step.ravel(), Wn.reshape(n, -1),
                  V.reshape(n, -1)]
        if slot is not None:
            evaluate(self.fun, slot, inputs, [o.reshape(n, -1) for o in out])
        else:
            x_end, X, Y = self.fun(inputs, n)
            out[0][:], out[1][:], out[2][:] = x_end, X.reshape(n, self.T, -1), \
                Y.reshape(n, self.T, -1)
        if self.silent is not None:
            out[2][:, self.silent] = np.nan


def _finite(x_end: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """The seeds whose plant stayed finite (state and outputs)."""
    return np.isfinite(X).all(axis=(1, 2)) & ~np.isinf(Y).any(axis=(1, 2)) \
        & np.isfinite(x_end).all(axis=1)


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
    t0 = time.perf_counter()
    S = len(seeds)
    plant = _Plant(scenario)
    plant.build(S)
    out = (np.empty((S, plant.nx)), np.empty((S, plant.T, plant.nx)),
           np.empty((S, plant.T, plant.ny)))
    plant.run(*plant.noise(list(seeds)), out)
    return PlantBatch(seeds=list(seeds), t=plant.t, x=out[1], y=out[2], u=plant.U_log,
                      u_step=plant.u_step, finite=_finite(*out),
                      seconds=time.perf_counter() - t0, how=plant.fun.how)


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


def run_batches(scenario: Scenario, filters: dict[str, FusedKalman], seeds: list[int],
                burn_in: int, keep_logs: bool
                ) -> tuple[PlantBatch, dict[str, tuple[list[dict | None], float, str]]]:
    """What :func:`~estim.compare` records of every seed's run of each filter (see
    :func:`estim._runs.run_seed`), from batched calls over the seeds' records.

    The seeds go in chunks of :data:`~estim.solvers.seeds.CHUNK` through a pipeline:
    workers, one per core, take the chunks in turn, each drawing the noise of a chunk,
    simulating its plant and filtering it (numpy's generators and CasADi's serial maps,
    which release the GIL), while this thread scores the chunks as they come (the NEES
    solves, the errors). Every seed's numbers are those of one call over all seeds (each
    is computed from its own rows alone).

    Returns the plant (``seconds``: the noise and the plant's calls, summed over the
    workers) and, per filter, the summaries in seed order (None for a seed that the
    per-seed path must run: a plant that left the finite numbers, a failed update), the
    seconds of its filter calls (summed over the workers) and whether they were
    compiled (see :func:`~estim.solvers.seeds.seed_map`).
    """
    from estim.estimators.kalman.fused_calls import SeedFilter
    from estim.solvers.kalman.kalman import NFLAGS

    S = len(seeds)
    plant = _Plant(scenario)
    T, nx, ny = plant.T, plant.nx, plant.ny
    with ThreadPoolExecutor(1) as pool:  # the plant's Function built (compiled) meanwhile
        building = pool.submit(plant.build, S, False)
        runs = {name: SeedFilter(est, plant.u_step, S) for name, est in filters.items()}
        building.result()
    x_end, X, Y = np.empty((S, nx)), np.empty((S, T, nx)), np.empty((S, T, ny))
    states = {name: np.empty((S, T, est._s.size)) for name, est in filters.items()}
    flags = {name: np.empty((S, T, NFLAGS)) for name in filters}
    scores = {name: _Scores(S, nx) for name in filters}
    outs: dict[str, list[dict]] = {name: [] for name in filters}
    finite = np.empty(S, dtype=bool)
    chunks = [(lo, min(lo + CHUNK, S)) for lo in range(0, S, CHUNK)]
    nw = min(threads(S), len(chunks))  # the pipeline's workers
    seconds = np.zeros((nw, 1 + len(filters)))  # each worker's: the plant's, each filter's
    ready = [threading.Event() for _ in chunks]
    failed: list[BaseException] = []

    def work(w: int) -> None:  # chunks w, w + nw, ...: noise, plant, filters
        try:
            for c in range(w, len(chunks), nw):
                lo, hi = chunks[c]
                t0 = time.perf_counter()
                plant.run(*plant.noise(seeds[lo:hi]), (x_end[lo:hi], X[lo:hi], Y[lo:hi]),
                          slot=w)
                seconds[w, 0] += time.perf_counter() - t0
                for j, (name, run) in enumerate(runs.items()):
                    seconds[w, 1 + j] += run.run_into(Y[lo:hi], states[name][lo:hi],
                                                      flags[name][lo:hi], w)
                ready[c].set()
        except BaseException as exc:  # noqa: BLE001 - raised again by this thread
            failed.append(exc)
            for event in ready:
                event.set()

    def score(lo: int, hi: int) -> None:
        finite[lo:hi] = _finite(x_end[lo:hi], X[lo:hi], Y[lo:hi])
        for name, run in runs.items():
            out = run.results(states[name][lo:hi], flags[name][lo:hi])
            outs[name].append(out)
            scores[name].add(lo, out, X[lo:hi], finite[lo:hi], burn_in)

    with ThreadPoolExecutor(nw) as pool:  # the chunks in turn, while this thread scores
        for w in range(nw):
            pool.submit(work, w)
        for c, (lo, hi) in enumerate(chunks):
            ready[c].wait()
            if failed:
                raise failed[0]
            score(lo, hi)
    for est in filters.values():
        est.reset()
    took = seconds.sum(axis=0)
    batch = PlantBatch(seeds=list(seeds), t=plant.t, x=X, y=Y, u=plant.U_log,
                       u_step=plant.u_step, finite=finite, seconds=float(took[0]),
                       how=plant.fun.how)
    results = {name: (scores[name].runs(scenario, est, batch, outs[name], float(took[1 + j]),
                                        keep_logs), float(took[1 + j]), runs[name].how)
               for j, (name, est) in enumerate(filters.items())}
    return batch, results


class _Scores:
    """What :func:`run_batches` scores of every seed, chunk by chunk: the time-averaged
    NEES, the RMSE over the run and per state, the largest error after the start-up."""

    def __init__(self, S: int, nx: int):
        self.nees, self.has_p = np.full(S, np.nan), np.zeros(S, dtype=bool)
        self.level, self.diverged = np.full(S, np.nan), np.zeros(S, dtype=bool)
        self.batches: list[list[float]] = [[] for _ in range(S)]
        self.rmse, self.per_state = np.full(S, np.nan), np.full((S, nx), np.nan)
        self.peak, self.where = np.full(S, np.nan), np.zeros(S, dtype=int)

    def add(self, lo: int, out: dict, X: np.ndarray, finite: np.ndarray,
            burn_in: int) -> None:
        """Score the seeds ``lo, lo + 1, ...`` of a chunk whose plant stayed finite, from
        the filter's ``out`` (see :meth:`SeedFilter.results
        <estim.estimators.kalman.fused_calls.SeedFilter.results>`) and the true states ``X``."""
        from estim.metrics import startup_samples

        keep = np.flatnonzero(finite)
        every = len(keep) == len(finite)  # no copies of the records
        n, (T, nx) = len(keep), X.shape[1:]
        err = out["x"] - X if every else out["x"][keep] - X[keep]
        P = out["P"] if every else out["P"][keep]
        rows = lo + keep
        finite_P = np.isfinite(P)
        self.has_p[rows] = finite_P.any(axis=(1, 2, 3))
        ne = nees_values(err[:, burn_in:], P[:, burn_in:])
        for i, row in enumerate(rows):  # the consistency scores, as run_seed's
            scores = seed_scores(ne[i], nx)
            self.nees[row], self.level[row] = scores["ratio"], scores["level"]
            self.batches[row], self.diverged[row] = scores["batches"], scores["diverged"]
        # each seed's squared errors state by state, contiguous, as rmse() sums its copy
        # of them (err[:, states], column-major): over the whole run and per state
        squared = np.ascontiguousarray((err[:, burn_in:] ** 2).transpose(0, 2, 1))
        self.rmse[rows] = np.sqrt(np.mean(squared.reshape(n, -1), axis=1))
        self.per_state[rows] = np.sqrt(np.mean(squared, axis=2))
        # the largest error after the start-up, as compare finds it
        size = np.abs(err).reshape(n, T * nx)
        size[:, :startup_samples(T) * nx] = -np.inf
        size[np.isnan(size)] = -np.inf
        where = np.argmax(size, axis=1)
        self.where[rows] = where
        self.peak[rows] = size[np.arange(n), where]

    def runs(self, scenario: Scenario, estimator: FusedKalman, plant: PlantBatch,
             outs: list[dict], seconds: float, keep_logs: bool) -> list[dict | None]:
        """Every seed's summary (see :func:`estim._runs.run_seed`; None for a seed the
        per-seed path must run), with the filter's ``outs``, chunk by chunk."""
        from estim.metrics import peak_location
        from estim.simulate import _Recorder

        m = scenario.model
        nx = m.nx
        S, T = plant.x.shape[:2]
        per_step = seconds / max(int(plant.finite.sum()) * T, 1)
        kind, caveat = type(estimator).__name__, estimator.caveat
        results: list[dict | None] = [None] * S
        for i in np.flatnonzero(plant.finite):
            out, j = outs[i // CHUNK], i % CHUNK
            status = out["status"][j]
            if status is None:
                continue
            seed = plant.seeds[i]
            k, n = divmod(int(self.where[i]), nx)
            peak = self.peak[i]
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
                "seed": seed, "rmse": float(self.rmse[i]),
                "per_state": self.per_state[i].tolist(),
                "nees": float(self.nees[i]) if self.has_p[i] else np.nan,
                "level": float(self.level[i]) if self.has_p[i] else np.nan,
                "batches": self.batches[i], "diverged": bool(self.diverged[i]),
                "step": per_step, "failures": 0,
                "flagged": len(status), "steps": T, "log": log,
                "peak": (float(peak), peak_location(m.state_names[n], plant.t[k], seed))
                if np.isfinite(peak) else (float("nan"), ""),
                "kind": kind, "caveat": caveat,
            }
        return results
