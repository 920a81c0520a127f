"""Command line: ``estim list``, ``estim run`` and ``estim observe``.

``estim run`` with no arguments is the main job: the batch reactor of the
KU Leuven course with EKF, clipped EKF, UKF and MHE (N = 25, zero prior,
0 <= x <= 10) over 5 seeds, a table on standard output and PNGs of the
first seed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from estim import scenarios
from estim.compare import compare
from estim.estimators import ESTIMATORS

DEFAULT_ESTIMATORS = ("ekf", "ekf:clip=true", "ukf",
                      "mhe-25=mhe:horizon=25,arrival_cost=none,upper=10.0,solver=gauss-newton")


def parse_estimator(spec: str):
    """``"[label=]name:key=value,key=value"`` to ``(label, class, kwargs)``.

    Values are read as Python literals where possible (numbers, True/False,
    lists), else kept as strings; ``true``/``false`` are booleans. The label
    (default: the whole spec) names the row of the table.
    """
    import ast

    head, _, rest = spec.partition(":")
    label = spec
    if "=" in head:
        label, head = (p.strip() for p in head.split("=", 1))
    name = head.strip().lower()
    if name not in ESTIMATORS:
        raise ValueError(f"unknown estimator {name!r}; known: {sorted(ESTIMATORS)}")
    kwargs = {}
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"estimator option {item!r} must be key=value")
        low = val.strip().lower()
        if low in ("true", "false"):
            kwargs[key.strip()] = low == "true"
            continue
        try:
            kwargs[key.strip()] = ast.literal_eval(val.strip())
        except (ValueError, SyntaxError):
            kwargs[key.strip()] = val.strip()
    return label, ESTIMATORS[name], kwargs


def _factory(cls, kwargs):
    def make(model, tuning):
        return cls(model, **tuning, **kwargs)

    return make


def _cmd_list(args) -> int:
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


def _cmd_run(args) -> int:
    sc = scenarios.get(args.scenario)
    if args.steps:
        sc = sc.replace(n_steps=args.steps)
    specs = args.estimator or list(DEFAULT_ESTIMATORS)
    factories = {}
    for spec in specs:
        label, cls, kwargs = parse_estimator(spec)
        factories[label] = _factory(cls, kwargs)
    result = compare(sc, factories, seeds=range(args.seeds), keep_logs=bool(args.plot),
                     n_jobs=args.jobs)
    print(result.table())
    if args.plot:
        from estim.plotting import plot_comparison, plot_errors, plot_solve_times

        plot_comparison(result, args.plot)
        stem = args.plot[:-4] if args.plot.endswith(".png") else args.plot
        first = {name: logs[0] for name, logs in result.logs.items()}
        plot_errors(first, f"{stem}_errors.png")
        plot_solve_times(first, f"{stem}_times.png")
        print(f"plots written to {args.plot}, {stem}_errors.png and {stem}_times.png")
    return 0


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


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="estim", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("list", help="list scenarios and estimators")
    run = sub.add_parser("run", help="compare estimators on a scenario (Monte Carlo)")
    run.add_argument("scenario", nargs="?", default="batch_reactor",
                     choices=sorted(scenarios.SCENARIOS))
    run.add_argument("--estimator", "-e", action="append",
                     help="[label=]name[:key=value,...], repeatable (default: ekf, ekf:clip=true, "
                          "ukf, mhe-25)")
    run.add_argument("--seeds", type=int, default=5, help="number of seeds (default 5)")
    run.add_argument("--steps", type=int, default=None, help="override the scenario length")
    run.add_argument("--plot", default="estim_run.png",
                     help="PNG for truth vs estimates of seed 0 ('' for none)")
    run.add_argument("--jobs", type=int, default=1, help="parallel jobs (joblib; -1: all cores)")
    obs = sub.add_parser("observe", help="observability analysis of a scenario's model")
    obs.add_argument("target", help="a scenario name or one of " + ", ".join(OBSERVE_MODELS))
    obs.add_argument("--order", type=int, default=None)
    obs.add_argument("--inputs", default="varying", choices=["varying", "constant"])
    obs.add_argument("--method", default="numeric", choices=["numeric", "symbolic"])
    args = parser.parse_args(argv)
    if args.command is None:
        args = parser.parse_args(["run", *(argv or [])])
    try:
        return {"list": _cmd_list, "run": _cmd_run, "observe": _cmd_observe}[args.command](args)
    except (ValueError, TypeError) as exc:
        print(f"estim: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
