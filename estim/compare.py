r"""Seeded Monte Carlo comparison of several estimators on one scenario.

Every estimator sees the same noise for a given seed, so differences in the
table are the estimators', not the draws'. An estimator that draws random numbers
(a particle filter, an EnKF) draws its own stream on every seed, from its ``seed`` and
the run's (``estim._runs.run_stream``): the runs are independent in their Monte
Carlo error too, as the verdicts over seeds assume, and the same at every call.

Runs go through joblib: with ``n_jobs=1`` they run in this process; with ``n_jobs>1``
in worker processes (``backend="loky"``), and any joblib backend works, e.g. a dask
cluster::

    from dask.distributed import Client
    client = Client("tcp://scheduler:8786")       # or Client() for a local cluster
    estim.compare(sc, estimators, seeds=range(200), n_jobs=16, backend="dask")

The numbers do not depend on how the runs were distributed.

With ``n_jobs != 1`` the first runs of every estimator are done in this
process and timed; the rest go to the workers only when that pays for
starting them (see :func:`compare`), in chunks of similar cost, and each worker
builds an estimator once per call (:mod:`estim._parallel`). The filters that can run
every seed in one compiled call do so (:mod:`estim.batch`).

The runs themselves are in :mod:`estim._runs`; the table's text, HTML and notes are
written by :mod:`estim._report`.
"""

from __future__ import annotations

import importlib.util
import inspect
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

import numpy as np

from estim import _report
from estim._parallel import dispatch
from estim._parallel import makespan as _makespan  # compare's names for the scheduling
from estim._parallel import plan as _plan
from estim._parallel import startup as _startup
from estim._progress import bar as progress_bar
from estim._runs import Factory, Run, Spec, build, run_batch, run_seed, summary
from estim._validate import as_bool, as_float, as_int, check_keywords, did_you_mean
from estim.estimators.base import Estimator
from estim.log import Log
from estim.model import Model
from estim.scenarios import Scenario
from estim.simulate import dimensions_message
from estim.solvers.seeds import CHUNK
from estim.solvers.seeds import threads as seed_threads
from estim.verdicts import Consistency

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure

    from estim.batch import PlantBatch

__all__ = ["Comparison", "ComparisonRow", "Factory", "compare"]


@dataclass
class ComparisonRow:
    """Summary of one estimator over all seeds.

    ``rmse_mean``/``rmse_std``: RMSE over all states, mean and standard
    deviation over seeds; ``rmse_per_state``: mean per state. ``nees_mean``:
    time-averaged NEES divided by the state dimension (1 for a consistent filter), mean
    over seeds; ``consistent``: the verdict of :func:`estim.verdicts.consistency` at level
    0.99 (no diverged seeds beyond chance, and the typical step's NEES calibrated; None
    without covariance), which ``consistency`` holds in full (the diverged seeds, the
    statistics) and :func:`estim.testing.assert_consistent` repeats.
    ``step_median``/``step_p90``: seconds per step.
    ``failures``: steps that failed (``success`` False: the estimator re-anchored);
    ``flagged``: successful steps whose status was not ``"ok"`` (``"inexact"``,
    ``"suspect"``); ``steps``: steps of the completed runs. ``runs``: runs that
    completed; ``errors``: ``{seed: "ExceptionType: message"}`` of the runs that
    raised (the statistics are over the completed runs). ``nees_se``: standard
    error of ``nees_mean`` over seeds; ``largest_error``: the largest absolute
    error of any state, where and when; ``kind``: the estimator's class name;
    ``caveat``: a known limitation of its configuration
    (:attr:`Estimator.caveat`).
    """

    name: str
    rmse_mean: float
    rmse_std: float
    rmse_per_state: dict[str, float]
    nees_mean: float
    consistent: bool | None
    step_median: float
    step_p90: float
    failures: int
    runs: int
    flagged: int = 0
    steps: int = 0
    errors: dict[int, str] = field(default_factory=dict)
    nees_se: float = float("nan")
    largest_error: str = ""
    kind: str = ""
    caveat: str = ""
    consistency: Consistency | None = None

    def notes(self) -> list[str]:
        """What went wrong in these runs, a line each (empty when nothing did)."""
        return _report.row_notes(self)


@dataclass
class Comparison:
    """Result of :func:`compare`: one row per estimator, per-seed RMSEs, logs if kept.

    Attributes
    ----------
    scenario : str
        Scenario name.
    seeds : list of int
    rows : list of ComparisonRow
    rmse : dict of str -> (n_seeds,) array
        RMSE of every run, per estimator, in seed order (NaN for a run that raised).
    logs : dict of str -> list of Log
        Every run's log (with ``keep_logs=True``); a run that raised has the log of
        the steps it completed, or None.
    remarks : dict of str -> str
        The scenario's :attr:`~estim.Scenario.remarks` (what is known about an
        estimator class on it), used by :meth:`notes`.
    parallel : str
        With ``n_jobs != 1``, how the runs were distributed and why ("serial: ..."
        or "parallel (...): ..."), printed under the table; empty with ``n_jobs=1``.
    batched : str
        Which estimators ran all seeds in one batched call (``compare(batch=)``) and
        how long that took, printed under the table; empty when none did.
    nees : dict of str -> (n_seeds,) array
        The time-averaged NEES per state dimension of every run (after the burn-in), per
        estimator, in seed order (NaN without a covariance or for a run that raised).
    burn_in : int
        The samples left out of RMSE and NEES at the start of every run (the table says
        so).
    augmented : list of str
        The model's parameters estimated as states (``Model.augment``): a filter that
        gives them process noise the plant's constant parameters do not have is
        pessimistic by design, which the notes say.
    nees_level : dict of str -> (n_seeds,) array
        Every run's average chi-square probability level of its NEES (1/2 for a
        consistent estimator; :func:`estim.verdicts.seed_scores`), NaN as ``nees``.
    diverged : dict of str -> (n_seeds,) bool array
        Whether each run diverged (its NEES beyond the 1e-8 tail of chi-square on at least
        a tenth of its steps).
    nees_batches : dict of str -> list of lists
        Every run's levels in 10 batches of its steps (the verdict of a single seed).
    """

    scenario: str
    seeds: list[int]
    rows: list[ComparisonRow]
    rmse: dict[str, np.ndarray]
    logs: dict[str, list[Log | None]] = field(default_factory=dict)
    remarks: dict[str, str] = field(default_factory=dict)
    parallel: str = ""
    batched: str = ""
    nees: dict[str, np.ndarray] = field(default_factory=dict)
    burn_in: int = 0
    augmented: list[str] = field(default_factory=list)
    nees_level: dict[str, np.ndarray] = field(default_factory=dict)
    diverged: dict[str, np.ndarray] = field(default_factory=dict)
    nees_batches: dict[str, list[list[float]]] = field(default_factory=dict)

    #: What the columns mean, printed under the table.
    LEGEND = ("RMSE: root mean square error over states, samples and seeds. NEES/n: "
              "normalised estimation error squared per state, averaged over time and seeds; "
              "1 when the reported covariance matches the errors, above 1 overconfident, "
              "below 1 pessimistic. cons.: the consistency verdict at level 0.99 "
              "(estim.testing.assert_consistent): 'yes' when no more seeds diverged than "
              "chance allows and the NEES of the typical step follows its chi-square "
              "law ('k/S div.': k of S seeds diverged, too few to reject); 'diverged k/S' "
              "when too many seeds diverged (errors beyond about 6 σ on a tenth of "
              "their steps); else 'overconfident' or 'pessimistic', 'slightly' when the "
              "median seed's errors are within 10 % of the σ reported; '-' without a "
              "covariance. step: wall time per step. failed: steps "
              "that failed and were re-anchored; flagged: inexact or suspect steps.")

    def notes(self) -> list[str]:
        r"""Why a row looks the way it does, a line per estimator that needs one.

        A row gets a note when a run raised, steps failed or were flagged
        (:meth:`ComparisonRow.notes`), when it is inconsistent (how far its
        errors are from the :math:`\sigma` it reports: :math:`\sqrt{NEES/n}`
        times), or when its RMSE is more than three times the best row's (with
        its largest error). The estimator's :attr:`~estim.Estimator.caveat` and
        the scenario's remark about its class follow, when there are such.
        """
        return _report.notes(self)

    def table(self) -> str:
        """Plain-text table."""
        return _report.table(self)

    def plot(self, path: str | os.PathLike[str] | None = None, *, kind: str = "overview",
             seed_index: int = 0) -> Figure:
        r"""Figures of the kept logs (needs ``compare(..., keep_logs=True)`` and matplotlib).

        Parameters
        ----------
        path : str or Path, optional
            Write the figure there (PNG by extension).
        kind : {"overview", "errors", "times"}
            ``"overview"``: truth and every estimator's estimate per state for
            one seed, and the RMSE of every seed as box plots
            (:func:`estim.plotting.plot_comparison`); ``"errors"``: the
            estimation error per state with the :math:`\pm 2\sigma` bands
            of the estimators that report a covariance
            (:func:`estim.plotting.plot_errors`); ``"times"``: the wall time of
            every step (:func:`estim.plotting.plot_solve_times`).
        seed_index : int
            Which seed to draw, as an index into :attr:`seeds`.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from estim import plotting

        kinds = ("overview", "errors", "times")
        if kind not in kinds:
            raise ValueError(f"kind must be one of {kinds}, got {kind!r}")
        seed_index = as_int(seed_index, "seed_index")
        if not self.logs:
            raise ValueError("Comparison.plot needs the logs: run compare(..., keep_logs=True)")
        if not -len(self.seeds) <= seed_index < len(self.seeds):
            raise ValueError(f"seed_index {seed_index} is out of range for "
                             f"{len(self.seeds)} seed(s)")
        if kind == "overview":
            return plotting.plot_comparison(self, path, seed_index=seed_index)
        logs = {name: logs[seed_index] for name, logs in self.logs.items()
                if logs[seed_index] is not None}
        if kind == "errors":
            return plotting.plot_errors(logs, path)
        return plotting.plot_solve_times(logs, path)

    def to_pandas(self) -> pd.DataFrame:
        """The rows as a DataFrame indexed by estimator (needs pandas)."""
        import pandas as pd

        return pd.DataFrame([r.__dict__ for r in self.rows]).set_index("name")

    def __str__(self) -> str:
        return self.table()

    def __repr__(self) -> str:
        return self.table()

    def _repr_html_(self) -> str:
        return _report.html_table(self)


def _fmt_s(seconds: float) -> str:
    return f"{seconds:.2g} s" if seconds < 10 else f"{seconds:.0f} s"


@check_keywords
def compare(scenario: Scenario, estimators: Mapping[str, Spec],
            seeds: Iterable[int] = range(5), *, n_jobs: int = 1, backend: str = "loky",
            keep_logs: bool = False, burn_in: int = 0, progress: bool | None = None,
            min_parallel_seconds: float | None = None, batch: bool | None = None,
            **experiment: Any) -> Comparison:
    """Run every estimator on the scenario for every seed (same noise per seed).

    Parameters
    ----------
    scenario : Scenario or Model
        The experiment; a bare :class:`~estim.Model` with the experiment's fields as
        keywords (below), as :func:`~estim.simulate` takes them.
    **experiment
        Fields of :class:`~estim.Scenario`: with a model, ``x0``, ``n_steps``, ``Q``,
        ``R`` and ``tuning`` (the estimators' ``{Q, R, x0, P0}``) are required, and
        ``inputs``, ``controller``, ``feedback``, ``clip``, ``plant_changes``,
        ``sampling``, ``name`` may be given; with a scenario, any of them replaces the
        scenario's (e.g. ``n_steps=50``).
    estimators : dict
        Name to an estimator class, a factory ``(model, tuning) -> estimator``,
        or a ready instance (copied for every worker).
    seeds : iterable of int
        Noise seeds; seed ``s`` gives the same noise to every estimator.
    n_jobs : int
        Parallel jobs through joblib (``-1``: all cores). 1 runs in this process.
    backend : str
        ``"loky"`` (processes, default), ``"threading"`` or any other joblib
        backend (``"ray"`` after ``ray.util.joblib.register_ray()``);
        ``"dask"`` submits the runs to the active ``dask.distributed`` client
        (create one first: ``Client()`` for a local cluster or
        ``Client("tcp://scheduler:8786")``).
    keep_logs : bool
        Keep every :class:`~estim.Log` in ``result.logs``.
    burn_in : int
        Samples skipped by RMSE and NEES.
    progress : bool, optional
        Show a tqdm progress bar (its notebook front end in Jupyter). Default: on a
        terminal or in Jupyter, once the runs have taken 2 s, whatever their number;
        never when stderr is redirected; ``ESTIM_PROGRESS=0`` in the environment
        silences every bar of estim (see :mod:`estim._progress`).
    min_parallel_seconds : float, optional
        With ``n_jobs != 1``: the first two runs of every estimator are done in
        this process and timed, giving each estimator's cost (build and first
        run's extra, then seconds per run). By default the other runs go to the
        workers only when the estimated parallel time (the workers' start-up,
        measured on the last cold start in this process, about 2 s before any,
        or about 0.1 s when they are still up from a call with the same backend
        and ``n_jobs``, plus the busiest worker's share) is at most 80 % of the
        estimated serial time; otherwise they run here. A number: in parallel
        when the estimated serial time of the other runs is at least that many
        seconds (``0``: always). :attr:`Comparison.parallel` says what was done
        and why. The numbers are the same either way.
    batch : bool, optional
        Run the filters that support it (:class:`~estim.EKF`, :class:`~estim.UKF`)
        over all seeds at once (see :mod:`estim.batch`): the seeds in chunks, the
        plant and each such filter over a chunk's whole records in one compiled call,
        the chunks on the machine's cores while they are scored. The numbers are
        those of the per-run path (a seed whose filter meets a failed update is run
        per run); their ``step`` time is those calls' time per sample. By default (None)
        whenever the scenario's inputs are known in advance (no controller);
        ``False``: never; ``True``: a ValueError if the scenario cannot be batched.
        :attr:`Comparison.batched` says what was batched.

    Returns
    -------
    Comparison
    """
    scenario = _experiment(scenario, experiment)
    seed_list, n_jobs, burn_in, keep_logs, progress = _check_compare(
        scenario, estimators, seeds, n_jobs, backend, keep_logs, burn_in, progress)
    if min_parallel_seconds is not None:
        min_parallel_seconds = as_float(min_parallel_seconds, "min_parallel_seconds",
                                        minimum=0.0)
    batch = as_bool(batch, "batch", allow_none=True)
    if batch is not False:
        from estim import batch as batching  # numpy/CasADi batches, loaded when used
        from estim.estimators.kalman.fused import FusedKalman  # the filters that batch

        why = batching.unsupported(scenario)
        if why and batch:
            raise ValueError(f"batch=True: the runs of {scenario.name} cannot be batched: "
                             f"{why}")
        batch = not why
    workers = (os.cpu_count() or 1) if n_jobs < 0 else int(n_jobs)
    total = len(estimators) * len(seed_list)
    # a bar on a terminal or in Jupyter once the runs take a while (progress=True: at once)
    bar = progress_bar(total, f"compare on {scenario.name}", "run", show=progress,
                       delay=0.0 if progress else None)
    per_name: dict[str, list[Run]] = {name: [] for name in estimators}
    # this process: every run with n_jobs=1; else the first two runs of every estimator,
    # timed (build + first run, then a run), to decide whether workers pay
    built: dict[str, Estimator | str] = {}
    costs: dict[str, tuple[float, float, int]] = {}
    pilot = seed_list if n_jobs == 1 else seed_list[:2]
    plant: PlantBatch | None = None
    batched: list[str] = []
    building: dict[str, float] = {}
    for name, spec in estimators.items():
        t0 = time.perf_counter()
        built[name] = build(spec, scenario)
        building[name] = time.perf_counter() - t0
    filters = {name: est for name, est in built.items()
               if batch and isinstance(est, FusedKalman) and est._batchable()}
    if filters:  # the plant and these filters over all seeds at once
        plant, batch_runs = run_batch(scenario, filters, seed_list, burn_in, keep_logs)
        for name, (summaries, seconds, how) in batch_runs.items():
            per_name[name] = summaries
            batched.append(f"{name} ({_fmt_s(seconds)}, {how})")
            costs[name] = (0.0, 0.0, 0)
            bar.update(len(seed_list))
    for name, est in built.items():
        if name in filters:
            continue
        times = []
        for s in pilot:
            t1 = time.perf_counter()
            per_name[name].append(run_seed(scenario, est, s, burn_in, keep_logs))
            times.append(time.perf_counter() - t1)
            bar.update(1)
        setup = building[name] + (times[0] - times[-1] if len(times) > 1 else 0.0)
        costs[name] = (max(setup, 0.0), times[-1], len(seed_list) - len(pilot))
    rest = seed_list[len(pilot):] if any(n for _, _, n in costs.values()) else []
    note = ""
    if rest:
        serial_s = sum(per * n for _, per, n in costs.values())
        tasks = _plan(costs, workers)
        startup, warm = _startup(backend, workers)
        par_s = startup + _makespan(tasks, costs, workers)
        estimate = (f"{len(rest) * len(estimators)} runs estimated at {_fmt_s(serial_s)} "
                    f"in this process, {_fmt_s(par_s)} on {workers} workers (starting "
                    f"{'warm' if warm else 'cold'} workers: about {_fmt_s(startup)})")
        if min_parallel_seconds is None:
            go = par_s <= 0.8 * serial_s
        else:
            go = serial_s >= min_parallel_seconds
        if not go:
            note = f"serial: {estimate}"
            for name in estimators:
                if not costs[name][2]:
                    continue
                for s in rest:
                    per_name[name].append(run_seed(scenario, built[name], s, burn_in,
                                                   keep_logs))
                    bar.update(1)
    bar.close()
    if rest and go:
        del built, est  # the workers build their own
        results, wall, started = dispatch(scenario, estimators, rest, tasks, burn_in,
                                          keep_logs, n_jobs=n_jobs, backend=backend,
                                          workers=workers, warm=warm)
        for (name, _, _), res in zip(tasks, results, strict=True):
            per_name[name].extend(res)
        how = "forced, " if min_parallel_seconds is not None else ""
        note = (f"parallel ({how}{len(tasks)} chunks): {estimate}; took {_fmt_s(wall)}, "
                f"the workers started in {_fmt_s(started)}")
    elif n_jobs != 1 and not rest and len(batched) < len(estimators):
        note = "serial: every run was one of the first runs, timed in this process"
    batch_note = ""
    if batched and plant is not None:
        S = len(seed_list)
        threads = min(seed_threads(S), -(-S // CHUNK))
        batch_note = (f"{', '.join(batched)}: the {S} runs of each filtered in chunks of "
                      f"{CHUNK} seeds (whole records in one call per chunk, on {threads} "
                      f"thread(s)), with the plant of every seed ({_fmt_s(plant.seconds)}, "
                      f"{plant.how}); times summed over the threads; their step time is the "
                      f"filter's time per sample")
    rows: list[ComparisonRow] = []
    all_rmse: dict[str, np.ndarray] = {}
    all_nees: dict[str, np.ndarray] = {}
    levels: dict[str, np.ndarray] = {}
    diverged: dict[str, np.ndarray] = {}
    batches: dict[str, list[list[float]]] = {}
    logs: dict[str, list[Log | None]] = {}
    m = scenario.model  # errors of quaternions and angles: in the tangent space
    names = m.state_names if m.manifold.euclidean_states else m.manifold.tangent_names
    order = {s: i for i, s in enumerate(seed_list)}
    for name, runs in per_name.items():
        runs.sort(key=lambda r: order[r["seed"]])
        rows.append(ComparisonRow(name, **summary(runs, names)))
        all_rmse[name] = np.array([r.get("rmse", np.nan) for r in runs])
        all_nees[name] = np.array([r.get("nees", np.nan) for r in runs])
        levels[name] = np.array([r.get("level", np.nan) for r in runs])
        diverged[name] = np.array([bool(r.get("diverged", False)) for r in runs])
        batches[name] = [list(r.get("batches", [])) for r in runs]
        if keep_logs:
            logs[name] = [r["log"] for r in runs]
    return Comparison(scenario.name, seed_list, rows, all_rmse, logs, remarks=scenario.remarks,
                      parallel=note, batched=batch_note, nees=all_nees, burn_in=burn_in,
                      augmented=list(scenario.model.augmented), nees_level=levels,
                      diverged=diverged, nees_batches=batches)


#: What compare takes of a Scenario as keywords: its fields but the model.
_FIELDS = tuple(f.name for f in fields(Scenario) if f.name != "model")


def _experiment(scenario: object, given: dict[str, Any]) -> Scenario:
    """The scenario of :func:`compare`: a Scenario (with the ``given`` fields replaced) or one
    built from a model and them."""
    unknown = sorted(set(given) - set(_FIELDS))
    if unknown:
        options = [n for n in inspect.signature(compare).parameters if n != "experiment"]
        raise TypeError(f"unknown option {unknown[0]!r} of compare"
                        f"{did_you_mean(unknown[0], options + list(_FIELDS))} (its options: "
                        f"{options}; the experiment's fields: {list(_FIELDS)})")
    if isinstance(scenario, Scenario):
        return scenario.replace(**given) if given else scenario
    if isinstance(scenario, Model):
        missing = [k for k in ("x0", "n_steps", "Q", "R", "tuning") if k not in given]
        if missing:
            raise TypeError(f"scenario: compare on a bare Model needs {missing} as keywords "
                            f"(the truth's x0, the length, the plant's Q and R, and the "
                            f"estimators' tuning {{Q, R, x0, P0}}), or an estim.Scenario")
        return Scenario(given.pop("name", scenario.name), scenario, **given)
    raise TypeError(f"scenario must be an estim.Scenario or an estim.Model, got "
                    f"{type(scenario).__name__}")


def _check_compare(scenario: Scenario, estimators: object, seeds: object, n_jobs: object,
                   backend: object, keep_logs: object, burn_in: object, progress: object
                   ) -> tuple[list[int], int, int, bool, bool | None]:
    """Check the arguments of :func:`compare` before any run."""
    if not isinstance(estimators, Mapping):
        raise TypeError(f"estimators must be a dict {{label: class, factory or estimator}}, "
                        f"got {type(estimators).__name__}")
    if not estimators:
        raise ValueError("estimators must name at least one estimator")
    for name, spec in estimators.items():
        if not isinstance(name, str):
            raise TypeError(f"estimators labels must be strings, got {name!r}")
        if not (callable(spec) or isinstance(spec, Estimator)):
            raise TypeError(f"estimators[{name!r}] must be a class, a factory or an estimator")
        if isinstance(spec, type) and not issubclass(spec, Estimator):
            raise TypeError(f"estimators[{name!r}] must be an estimator class, a factory or "
                            f"an estimator, got the class {spec.__name__}")
        if isinstance(spec, Estimator) and (spec.model.nx, spec.model.ny, spec.model.nu) != (
                scenario.model.nx, scenario.model.ny, scenario.model.nu):
            raise ValueError(dimensions_message(f"estimators[{name!r}]", spec.model,
                                                 scenario.model))
    if isinstance(seeds, str | bytes) or not hasattr(seeds, "__iter__"):
        raise TypeError(f"seeds must be an iterable of seeds (e.g. range(5)), "
                        f"got {type(seeds).__name__}")
    seed_list = [as_int(s, f"seeds[{i}]", minimum=0) for i, s in enumerate(seeds)]
    if not seed_list:
        raise ValueError("seeds must contain at least one seed")
    if len(set(seed_list)) != len(seed_list):
        raise ValueError(f"seeds must not repeat a seed, got {seed_list}")
    jobs = as_int(n_jobs, "n_jobs", expected="a non-zero integer (-1: all cores)")
    if jobs == 0:
        raise ValueError("n_jobs must be a non-zero integer (-1: all cores), got 0")
    if not isinstance(backend, str):
        raise TypeError(f"backend must be a string (a joblib backend or 'dask'), "
                        f"got {type(backend).__name__}")
    try:
        from joblib.parallel import BACKENDS  # joblib's own and any registered (ray, ...)
    except ImportError:  # no joblib: n_jobs != 1 is refused below, with the fix
        BACKENDS = {"loky", "multiprocessing", "threading"}
    known = sorted({*BACKENDS, "dask"})
    if backend not in known:
        raise ValueError(f"backend must be one of {known} (joblib's registered backends "
                         f"and 'dask'), got {backend!r}{did_you_mean(backend, known)}")
    keep = as_bool(keep_logs, "keep_logs")
    show = as_bool(progress, "progress", allow_none=True)
    burn = as_int(burn_in, "burn_in", minimum=0)
    if burn >= scenario.n_steps:
        raise ValueError(f"burn_in ({burn}) must be shorter than the scenario "
                         f"({scenario.n_steps} steps)")
    if jobs != 1:
        if backend == "dask":
            if importlib.util.find_spec("dask") is None or \
                    importlib.util.find_spec("dask.distributed") is None:
                raise ImportError('backend="dask" needs dask.distributed: '
                                  'pip install "estim[dask]"')
            from dask.distributed import default_client

            try:
                default_client()
            except ValueError:
                raise ValueError('backend="dask" submits the runs to the active '
                                 'dask.distributed client, and there is none: create one '
                                 'first (from dask.distributed import Client; client = '
                                 'Client() for a local cluster, or Client("tcp://...")'
                                 ')') from None
        elif importlib.util.find_spec("joblib") is None:
            raise ImportError(f"n_jobs={jobs} runs in parallel through joblib: "
                              "pip install joblib (a dependency of estim)")
    return seed_list, jobs, burn, keep, show
