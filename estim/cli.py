"""Command line: ``estim list``, ``estim run``, ``estim tune`` and ``estim observe``.

``estim run`` with no arguments is the main job: the batch reactor of the
KU Leuven course with EKF, clipped EKF, UKF and MHE (N = 25, zero prior,
within the model's bounds x >= 0) over 5 seeds, a table on standard output
and PNGs of the first seed.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import sys
from collections.abc import Sequence
from pathlib import Path

from estim import scenarios
from estim._validate import did_you_mean, unknown_keywords_message
from estim.compare import compare

DEFAULT_ESTIMATORS = ("ekf", "ekf:clip=true", "ukf", "mhe-25=mhe:horizon=25,arrival_cost=none")


_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")


def _option_kinds(cls, key: str) -> set[str]:
    """The type names in the annotation of ``cls``'s constructor parameter ``key``
    (``"dict | None"`` gives ``{"dict", "None"}``; unannotated gives an empty set)."""
    annotation = inspect.signature(cls).parameters[key].annotation
    if annotation is inspect.Parameter.empty:
        return set()
    if not isinstance(annotation, str):
        annotation = getattr(annotation, "__name__", str(annotation))
    return {part.strip() for part in annotation.split("|")}


def _option_value(cls, name: str, key: str, text: str):
    """The command-line text of option ``key`` converted by its annotated type."""
    import ast

    kinds = _option_kinds(cls, key)
    low = text.lower()
    if "None" in kinds and low == "none":
        return None
    if "bool" in kinds:
        if low in _TRUE or low in _FALSE:
            return low in _TRUE
        raise ValueError(f"{name} option {key} must be a boolean (true/false, yes/no, on/off, "
                         f"1/0), got {text!r}")
    for kind, convert, what in (("int", int, "an integer"), ("float", float, "a number")):
        if kind in kinds:
            try:
                return convert(text)
            except ValueError:
                raise ValueError(f"{name} option {key} must be {what}, got {text!r}") from None
    try:
        value = ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text
    if "str" in kinds and not isinstance(value, str):
        return text
    return value


def _options(text: str, spec: str) -> list[str]:
    """``key=value`` items of a spec's options, split at the commas outside brackets and
    quotes (``Q=[1e-6, 0.01],horizon=20`` is two items)."""
    items, depth, quote, start = [], 0, "", 0
    for i, c in enumerate(text):
        if quote:
            quote = "" if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c in "([{":
            depth += 1
        elif c in ")]}":
            depth -= 1
        elif c == "," and depth == 0:
            items.append(text[start:i])
            start = i + 1
        if depth < 0:
            raise ValueError(f"estimator spec {spec!r}: a {c!r} closes no bracket")
    if depth or quote:
        raise ValueError(f"estimator spec {spec!r}: an unclosed "
                         f"{'quote' if quote else 'bracket'}")
    return [*items, text[start:]]


def parse_estimator(spec: str):
    """``"[label=]name:key=value,key=value"`` to ``(label, class, kwargs)``.

    Each value is converted by the type of the estimator's parameter: booleans
    from ``true/false``, ``yes/no``, ``on/off`` or ``1/0`` (any case), integers,
    numbers and strings as such, ``none`` for an optional parameter, anything
    else (covariances, bounds) as a Python literal where possible: lists, tuples and
    dicts, nested, with commas inside their brackets (``mhe:Q=[1e-6, 0.01],horizon=20``;
    quote the whole spec in the shell). An unknown
    option name or a value of the wrong type is a ``ValueError`` or
    ``TypeError`` naming the option. The label (default: the whole spec) names
    the row of the table.
    """
    from estim.estimators import ESTIMATORS

    if not isinstance(spec, str):
        raise TypeError(f"spec must be a string, got {type(spec).__name__}")
    head, _, rest = spec.partition(":")
    label = spec
    if "=" in head:
        label, head = (p.strip() for p in head.split("=", 1))
        if not label:
            raise ValueError(f"estimator spec {spec!r} has an empty label")
    name = head.strip().lower()
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; known: {sorted(ESTIMATORS)}")
    cls = ESTIMATORS[name]
    known = [k for k, p in inspect.signature(cls).parameters.items()
             if k != "model" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    kwargs = {}
    for item in filter(None, (p.strip() for p in _options(rest, spec))):
        key, eq, val = item.partition("=")
        key = key.strip()
        if not eq:
            raise ValueError(f"estimator option {item!r} must be key=value")
        if key not in known:
            raise TypeError(unknown_keywords_message(cls.__name__, [key], known))
        if key in kwargs:
            raise ValueError(f"{name} option {key} is given twice in {spec!r}")
        kwargs[key] = _option_value(cls, name, key, val.strip())
    return label, cls, kwargs


def _factory(cls, kwargs):
    def make(model, tuning):
        return cls(model, **{**tuning, **kwargs})

    return make


def _cmd_list(args) -> int:
    from estim.estimators import ESTIMATORS

    print("scenarios:")
    for name, fn in scenarios.SCENARIOS.items():
        sc = fn()
        print(f"  {name:<16}{sc.description}")
    print("estimators:")
    for name, cls in ESTIMATORS.items():
        doc = (cls.__doc__ or "").strip().splitlines()[0]
        print(f"  {name:<16}{doc}")
    print("models for `estim observe`: " + ", ".join(OBSERVE_MODELS))
    return 0


def load_scenario(target: str) -> scenarios.Scenario:
    """A scenario by name (:mod:`estim.scenarios`), or from a user's file:
    ``path/to/file.py:name`` (``name`` default ``scenario``), a :class:`~estim.Scenario`
    or a function of no arguments returning one."""
    if ".py" not in target:
        return scenarios.get(target)
    # the file is what ends in ".py" (a folder may have ".py" in its name): the last
    # ".py" followed by ":name" or the end
    stem, _, rest = target.rpartition(".py")
    if rest and not rest.startswith(":"):
        raise ValueError(f"scenario target {target!r}: write path/to/file.py or "
                         f"path/to/file.py:name")
    path, name = Path(stem + ".py"), rest.lstrip(":") or "scenario"
    if not path.is_file():
        raise ValueError(f"scenario file {str(path)!r} does not exist")
    spec = importlib.util.spec_from_file_location(f"estim_user_{path.stem}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(path.parent.resolve()))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.pop(0)
    if not hasattr(module, name):
        found = [k for k, v in vars(module).items()
                 if isinstance(v, scenarios.Scenario) or (callable(v) and not k.startswith("_")
                                                          and not isinstance(v, type))]
        raise ValueError(f"{path} has no {name!r}; give file.py:name, one of {found}")
    value = getattr(module, name)
    if callable(value) and not isinstance(value, scenarios.Scenario):
        value = value()
    if not isinstance(value, scenarios.Scenario):
        raise TypeError(f"{path}:{name} must be an estim.Scenario or a function returning "
                        f"one, got {type(value).__name__}")
    return value


def _scenario_arg(value: str) -> str:
    """A scenario name or ``file.py[:name]``, checked when the command line is read."""
    if ".py" in value or value in scenarios.SCENARIOS:
        return value
    known = sorted(scenarios.SCENARIOS)
    raise argparse.ArgumentTypeError(f"unknown scenario {value!r}; known: {', '.join(known)}"
                                     f", or file.py:name{did_you_mean(value, known)}")


def _cmd_run(args) -> int:
    sc = load_scenario(args.scenario)
    if args.steps is not None:
        sc = sc.replace(n_steps=args.steps)
    if args.plot:
        if importlib.util.find_spec("matplotlib") is None:
            raise ImportError('--plot needs matplotlib: pip install "estim[plot]" '
                              "(or --plot '' for no plots)")
        folder = Path(args.plot).parent
        if not folder.is_dir():
            raise ValueError(f"--plot: the folder {str(folder)!r} does not exist")
    specs = args.estimator or list(DEFAULT_ESTIMATORS)
    factories = {}
    for spec in specs:
        label, cls, kwargs = parse_estimator(spec)
        if label in factories:
            raise ValueError(f"estimator label {label!r} is given twice; labels must be "
                             f"unique (-e label=name:...)")
        factories[label] = _factory(cls, kwargs)
    # an estimator that cannot be built is a row with its reason and the others run; when
    # none can be built the command line itself is wrong: its first error, exit status 2
    refused = []
    for make in factories.values():
        try:
            make(sc.model, sc.tuning)
        except (TypeError, ValueError) as exc:
            refused.append(exc)
    if len(refused) == len(factories):
        raise refused[0]
    result = compare(sc, factories, seeds=range(args.seeds), keep_logs=bool(args.plot),
                     n_jobs=args.jobs, progress=False if args.quiet else None)
    print(result.table())
    broken = [r.name for r in result.rows if r.errors and not r.runs]
    if broken:
        print(f"estim run: {', '.join(broken)} raised on every seed (see the notes)",
              file=sys.stderr)
    if args.plot:
        from estim.plotting import plot_comparison, plot_errors, plot_solve_times

        plot_comparison(result, args.plot)
        stem = args.plot[:-4] if args.plot.endswith(".png") else args.plot
        first = {name: logs[0] for name, logs in result.logs.items() if logs[0] is not None}
        plot_errors(first, f"{stem}_errors.png")
        plot_solve_times(first, f"{stem}_times.png")
        print(f"plots written to {args.plot}, {stem}_errors.png and {stem}_times.png")
    return 1 if broken else 0


def _cmd_tune(args) -> int:
    import numpy as np

    from estim.estimators.kalman.ekf import EKF
    from estim.metrics import rmse
    from estim.simulate import replay, simulate

    sc = load_scenario(args.scenario)
    if args.steps is not None:
        sc = sc.replace(n_steps=args.steps)
    model, guess = sc.model, {k: sc.tuning[k] for k in ("x0", "P0")}
    log = simulate(sc, EKF(model, **sc.tuning), seed=args.seed, warn=False)
    if args.method == "als":
        from estim.tuning import als

        # a second pass from the filter of the first estimate: ALS's variance grows with
        # the distance of the filter it starts from to the optimal one
        res = als(model, log.y, log.u, structure=args.structure, iterations=2, **guess)
    else:
        from estim.tuning import maximum_likelihood

        res = maximum_likelihood(model, log.y, log.u, structure=args.structure, **guess)
    print(f"{sc.name}: {sc.n_steps} samples (seed {args.seed}) with the plant's noise "
          f"Q = diag({', '.join(f'{v:.4g}' for v in np.diag(sc.Q))}), "
          f"R = diag({', '.join(f'{v:.4g}' for v in np.diag(sc.R))})")
    print(res.summary())
    tunings = {"scenario tuning": sc.tuning,
               "estimated": {**sc.tuning, "Q": res.Q, "R": _definite(res.R)}}
    seeds = [args.seed + 1 + i for i in range(args.check_seeds)]
    print(f"{'EKF RMSE':<18}{'scenario tuning':>16}{'estimated':>11}")
    on_record = [float(rmse(replay(EKF(model, **t), log.y, log.u, x=log.x, warn=False)))
                 for t in tunings.values()]
    print(f"{'  this record':<18}{on_record[0]:16.4g}{on_record[1]:11.4g}")
    if seeds:
        fresh = [np.mean([float(rmse(simulate(sc, EKF(model, **t), seed=s, warn=False)))
                          for s in seeds]) for t in tunings.values()]
        label = f"  {len(seeds)} new record" + ("s" if len(seeds) > 1 else "")
        print(f"{label:<18}{fresh[0]:16.4g}{fresh[1]:11.4g}")
    return 0


def _definite(R):
    """``R`` made positive definite for a filter (an estimate may sit on the boundary)."""
    import numpy as np

    lam = float(np.linalg.eigvalsh(R).min())
    floor = 1e-9 * max(float(np.trace(R)) / len(R), 1e-300)
    return R + (floor - lam) * np.eye(len(R)) if lam < floor else R


OBSERVE_MODELS = {
    "martinelli_simple": "estim.models.martinelli_simple()",
    "odometry_noncircular": "estim.models.odometry_noncircular()",
    "odometry_circular": "estim.models.odometry_circular()",
    "quadrotor": "estim.models.quadrotor_ko2019()",
}


def _cmd_observe(args) -> int:
    from estim import models, observability

    if args.target in scenarios.SCENARIOS:
        model = scenarios.get(args.target).model
    elif args.target in OBSERVE_MODELS:
        model = {"martinelli_simple": models.martinelli_simple,
                 "odometry_noncircular": models.odometry_noncircular,
                 "odometry_circular": models.odometry_circular,
                 "quadrotor": models.quadrotor_ko2019}[args.target]()
    else:
        raise ValueError(f"unknown scenario or model {args.target!r}; known: "
                         f"{sorted(scenarios.SCENARIOS) + sorted(OBSERVE_MODELS)}")
    print(observability.analyze(model, order=args.order, inputs=args.inputs,
                                method=args.method))
    return 0


def _int_arg(minimum: int | None, nonzero: bool = False):
    """An argparse ``type``: an integer, at least ``minimum``, non-zero if asked."""
    def integer(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
        if minimum is not None and value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, got {value}")
        if nonzero and value == 0:
            raise argparse.ArgumentTypeError("must be a non-zero integer (-1: all cores), "
                                             "got 0")
        return value

    return integer


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="estim", description="Command line: estim list, estim run, estim tune and estim "
                                  "observe (estim COMMAND --help for each).")
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("list", help="list scenarios and estimators")
    run = sub.add_parser("run", help="compare estimators on a scenario (Monte Carlo)")
    where = (f"one of {', '.join(sorted(scenarios.SCENARIOS))}, or file.py:name for a "
             f"Scenario (or a function returning one) in your own file")
    run.add_argument("scenario", nargs="?", default="batch_reactor", type=_scenario_arg,
                     help=f"the experiment (default batch_reactor): {where}")
    run.add_argument("--estimator", "-e", action="append",
                     help="[label=]name[:key=value,...], repeatable; a value is a word "
                          "(true/false, a number, a string, none) or a Python literal: "
                          "lists, tuples, dicts, nested, e.g. \"mhe:horizon=20,Q=[1e-6, "
                          "0.01]\" (quote it in the shell); an estimator that cannot be "
                          "built is a row with its reason and exit status 1 (none built: "
                          "an error) (default: "
                          + " ".join(f"-e {e}" for e in DEFAULT_ESTIMATORS) + ")")
    run.add_argument("--seeds", type=_int_arg(1), default=5, help="number of seeds (default 5)")
    run.add_argument("--steps", type=_int_arg(1), default=None,
                     help="override the scenario length")
    run.add_argument("--plot", default="estim_run.png",
                     help="PNG for truth vs estimates of seed 0 ('' for none)")
    run.add_argument("--jobs", type=_int_arg(None, nonzero=True), default=1,
                     help="parallel jobs (joblib; -1: all cores)")
    run.add_argument("--quiet", "-q", action="store_true",
                     help="no progress bar (shown on a terminal once the runs take 2 s; "
                          "ESTIM_PROGRESS=0 silences every bar)")
    tune = sub.add_parser("tune", help="estimate Q and R from a simulated record and compare "
                                       "the EKF tuned with them")
    tune.add_argument("scenario", type=_scenario_arg, help=f"the experiment: {where}")
    tune.add_argument("--method", default="als", choices=["als", "ml"],
                      help="autocovariance least squares (default; two passes, the second "
                           "from the filter of the first estimate) or maximum likelihood")
    tune.add_argument("--structure", default="diagonal", choices=["diagonal", "full", "scalar"],
                      help="free entries of Q and R (default diagonal)")
    tune.add_argument("--seed", type=_int_arg(0), default=0, help="seed of the record")
    tune.add_argument("--steps", type=_int_arg(1), default=None,
                      help="override the scenario length")
    tune.add_argument("--check-seeds", type=_int_arg(0), default=5,
                      help="new records the two tunings are compared on (default 5)")
    obs = sub.add_parser("observe", help="observability analysis of a scenario's model")
    obs.add_argument("target", help="a scenario name or one of " + ", ".join(OBSERVE_MODELS))
    obs.add_argument("--order", type=_int_arg(0), default=None)
    obs.add_argument("--inputs", default="varying", choices=["varying", "constant"])
    obs.add_argument("--method", default="numeric", choices=["numeric", "symbolic"])
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args(["run", *(argv or [])])
    try:
        return {"list": _cmd_list, "run": _cmd_run, "observe": _cmd_observe,
                "tune": _cmd_tune}[args.command](args)
    except (ValueError, TypeError, ImportError) as exc:
        print(f"estim: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
