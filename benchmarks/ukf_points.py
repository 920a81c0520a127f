"""Which sigma-point set should ``estim.UKF`` use by default? The candidates on the
textbook's pendulum record and on every scenario of ``estim.scenarios`` a UKF runs.

Candidates (``n`` the state's dimension, ``model.ndx``):

* ``merwe(0.1,2,0)``: van der Merwe's scaled points, ``alpha = 0.1``, ``beta = 2``,
  ``kappa = 0`` (the default before this study; the default is now ``merwe(1,2,0)``;
  every candidate passes its parameters explicitly);
* ``merwe(1e-3,2,0)``: Wan and van der Merwe's recommended ``alpha = 1e-3``;
* ``merwe(1,0,3-n)``: the textbook's (Särkkä & Svensson), the same rule as Julier's
  with ``kappa = 3 - n``;
* ``merwe(1,2,0)``: unit spread, ``beta = 2`` (a zero-weight centre for the mean);
* ``cubature``: the ``2n`` equally weighted points of the cubature Kalman filter;
* ``julier(3-n)``: Julier's points with ``kappa = 3 - n`` (a check: the same numbers
  as ``merwe(1,0,3-n)``);
* ``GH3``: Gauss-Hermite of order 3 (``3^n`` points), only where ``n <= 4``.

Cases:

1. ``book record``: the book's pendulum record (``examples/data/book_pendulum.npz``)
   with the book's prior one step before the first measurement; RMSE of the angle,
   NEES of the full state against the record's truth;
2. every scenario of ``estim.scenarios`` (with its own tuning, guess and noise), over
   ``--seeds`` seeds through ``estim.compare`` (seed ``s`` gives every candidate the
   same noise); RMSE over all states and samples (no burn-in), NEES/n averaged over
   time. The satellite also without its inertia fault and with its quaternion declared
   (a 3-dof attitude error, ``ndx = 7``).

Per case and candidate: the median RMSE over seeds and its range, the ratio of that
median to the best candidate's, the seeds on which it is better / worse than merwe(0.1,2,0)
by more than 0.5 % (same noise), for the pendulums the median RMSE of the angle
alone, the NEES/n (mean over seeds, the median seed in brackets), compare's consistency
verdict at level 0.99, the seeds that diverged (NEES beyond the 1e-8 chi-square tail on a
tenth of the steps), the seeds with a failed step (re-anchored) and with a flagged one
(``"suspect"``: NIS beyond the 1e-9 tail), runs that raised, and the time of ``filter``
over the seed-0 record relative to merwe(0.1,2,0)'s (interpreted, ``jit=False``;
calls repeated for 0.1 s, the candidates in turn, best of five rounds).

The summary ranks the candidates over the cases: the geometric mean over cases of the
ratio of its median RMSE to the best candidate's (over all cases, and over the cases
where the candidates differ by more than 1 %), the cases where it is within 5 % of the
best, its worst ratio, the median seed's NEES/n (median over cases), the cases with a
consistent verdict, the diverged seeds beyond the fewest of any candidate, and the
failed seeds and runs that raised or gave NaN. Run from the repository root::

    python benchmarks/ukf_points.py [--seeds 50] [--quick]

``--quick``: 5 seeds and no timing.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import casadi
import numpy as np

import estim
from estim.estimators.kalman.ukf import sigma_rule

ROOT = Path(__file__).resolve().parent.parent
CURRENT = "merwe(0.1,2,0)"


def _kwargs(label: str, n: int) -> dict | None:
    """The UKF keywords of a candidate for ``n`` states (None: not run at that size)."""
    table = {
        "merwe(0.1,2,0)": {"points": "merwe", "alpha": 0.1, "beta": 2.0, "kappa": 0.0},
        "merwe(1e-3,2,0)": {"points": "merwe", "alpha": 1e-3, "beta": 2.0, "kappa": 0.0},
        "merwe(1,0,3-n)": {"points": "merwe", "alpha": 1.0, "beta": 0.0, "kappa": 3.0 - n},
        "merwe(1,2,0)": {"points": "merwe", "alpha": 1.0, "beta": 2.0, "kappa": 0.0},
        "cubature": {"points": "cubature"},
        "julier(3-n)": {"points": "julier", "kappa": 3.0 - n},
        "GH3": {"points": "gauss-hermite", "order": 3} if n <= 4 else None,
    }
    return table[label]


CANDIDATES = ("merwe(0.1,2,0)", "merwe(1e-3,2,0)", "merwe(1,0,3-n)", "merwe(1,2,0)",
              "cubature", "julier(3-n)", "GH3")

#: The scenario cases: label and scenario.
CASES: dict[str, Callable[[], estim.Scenario]] = {
    "book_pendulum": estim.scenarios.book_pendulum,
    "van_der_pol": estim.scenarios.van_der_pol,
    "lorenz": estim.scenarios.lorenz,
    "batch_reactor": estim.scenarios.batch_reactor,
    "reactor_feed": estim.scenarios.reactor_feed,
    "pendulum (DAE)": estim.scenarios.pendulum,
    "sine_pendulum": estim.scenarios.sine_pendulum,
    "sensor_fusion": estim.scenarios.sensor_fusion,
    "runaway": estim.scenarios.runaway,
    "satellite": estim.scenarios.satellite,
    "satellite, no fault": lambda: estim.scenarios.satellite(fault=False),
    "satellite, quaternion": lambda: estim.scenarios.satellite(quaternion=True),
}


#: Seeds whose RMSEs differ by less than this fraction are ties.
TIE = 0.005

#: The cases whose first state is an angle: its RMSE alone is shown too.
ANGLE_CASES = ("book_pendulum", "sine_pendulum")


def factory(kw: dict) -> Callable:
    def make(m, t):
        return estim.UKF(m, **t, **kw)
    return make


def span(values: np.ndarray) -> str:
    v = values[np.isfinite(values)]
    if not v.size:
        return "NaN"
    return f"{np.median(v):.4g} [{v.min():.3g}-{v.max():.3g}]"


def seconds_per_call(calls: dict[str, Callable[[], object]], rounds: int = 5,
                     least: float = 0.1) -> dict[str, float]:
    """Seconds per call of every function: in each of ``rounds`` rounds, taken in turn,
    each is called repeatedly for at least ``least`` seconds; the best round (after a
    first call that builds)."""
    counts = {}
    for label, fn in calls.items():
        t0 = time.perf_counter()
        fn()
        counts[label] = max(1, int(least / max(time.perf_counter() - t0, 1e-6)))
    best = dict.fromkeys(calls, math.inf)
    for _ in range(rounds):
        for label, fn in calls.items():
            t0 = time.perf_counter()
            for _ in range(counts[label]):
                fn()
            best[label] = min(best[label], (time.perf_counter() - t0) / counts[label])
    return best


def rules() -> None:
    """The candidates' rules for n = 2, 4, 8: the points' distance from the mean along a
    principal axis (in its standard deviations), their number, the centre's weights and
    the sum of the covariance weights' magnitudes (how much a step's weighted sums can
    magnify rounding)."""
    print("\n## The rules\n")
    print("distance: of the points from the mean, in standard deviations along a principal "
          "axis (Gauss-Hermite: the outer points). sum |Wc|: the magnitudes of the "
          "covariance weights summed, the factor by which a step's weighted sums can "
          "magnify rounding.\n")
    print("| candidate | n | points | distance | W0 mean | W0 covariance | sum abs(Wc) |")
    print("|---" * 7 + "|")
    for label in CANDIDATES:
        for n in (2, 4, 8):
            kw = _kwargs(label, n)
            if kw is None:
                continue
            c, Wm, Wc, unit = sigma_rule(n=n, **kw)
            dist = math.sqrt(c) if unit is None else float(np.abs(unit).max())
            centre = kw["points"] not in ("cubature", "gauss-hermite")
            w0 = (f"{Wm[0]:.4g} | {Wc[0]:.4g}" if centre else "- | -")
            print(f"| {label} | {n} | {Wm.size} | {dist:.3g} | {w0} | "
                  f"{np.abs(Wc).sum():.4g} |")


def record_case(timing: bool) -> dict[str, dict]:
    """The book's pendulum record: one run per candidate."""
    data = np.load(ROOT / "examples" / "data" / "book_pendulum.npz")
    sc = estim.scenarios.book_pendulum()
    Y = np.vstack([[np.nan], data["Y"][:, None]])  # the prior one step before y_0
    X = data["X"]
    out, calls = {}, {}
    for label in CANDIDATES:
        kw = _kwargs(label, sc.model.ndx)
        est = estim.UKF(sc.model, **sc.tuning, **kw)
        res = est.filter(Y)
        x, P = res.x[1:], res.P[1:]
        e = x - X
        nees = np.einsum("ti,tij,tj->t", e, np.linalg.inv(P), e) / 2
        status = np.array([str(s) for s in res.status])
        out[label] = {
            "rmse": np.array([math.sqrt(float(np.mean(e[:, 0] ** 2)))]),
            "nees": np.array([float(np.mean(nees))]),
            "grade": "-", "diverged": 0, "runs": 1,
            "failed": int(any(s.startswith("failed") for s in status)),
            "flagged": int(any(s != "ok" and not s.startswith("failed") for s in status)),
            "errors": 0, "time": float("nan")}
        calls[label] = lambda est=est: est.filter(Y)
    if timing:
        for label, t in seconds_per_call(calls).items():
            out[label]["time"] = t
    return out


def scenario_case(sc: estim.Scenario, seeds: list[int], timing: bool,
                  angle: bool = False) -> dict[str, dict]:
    """One scenario over the seeds, one ``estim.compare`` call per candidate (with
    ``angle``, the RMSE of the first state too)."""
    out, calls = {}, {}
    plant = estim.simulate(sc, None, seed=seeds[0])
    for label in CANDIDATES:
        kw = _kwargs(label, sc.model.ndx)
        if kw is None:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", estim.EstimationWarning)
            res = estim.compare(sc, {label: factory(kw)}, seeds=seeds, keep_logs=True,
                                progress=False)
        row = res.rows[0]
        logs = [lg for lg in res.logs[label] if lg is not None]
        est = estim.UKF(sc.model, **sc.tuning, **kw)
        calls[label] = lambda est=est: est.filter(plant.y, plant.u)
        out[label] = {
            "rmse": res.rmse[label], "nees": res.nees[label],
            "angle": np.array([estim.rmse(lg).per_state[lg.state_names[0]]
                               if lg is not None and angle else np.nan
                               for lg in res.logs[label]]),
            "grade": row.consistency.grade() if row.consistency is not None else "-",
            "diverged": int(np.sum(res.diverged[label])), "runs": len(seeds),
            "failed": sum(lg.failures > 0 for lg in logs),
            "flagged": sum(lg.flagged > 0 for lg in logs),
            "errors": len(row.errors), "time": float("nan")}
        del res, logs
    if timing:
        for label, t in seconds_per_call(calls).items():
            out[label]["time"] = t
    return out


def median(values: np.ndarray) -> float:
    """The median of the finite values (NaN when there are none)."""
    v = values[np.isfinite(values)]
    return float(np.median(v)) if v.size else float("nan")


def print_case(name: str, results: dict[str, dict], n: int, seeds: int,
               angle: bool = False) -> None:
    medians = {k: median(r["rmse"]) for k, r in results.items()}
    best = min(v for v in medians.values() if np.isfinite(v))
    cur = results[CURRENT]
    base = cur["time"]
    extra = " angle RMSE median (ratio) |" if angle else ""
    best_angle = min(median(r["angle"]) for r in results.values()) if angle else 1.0
    print(f"\n### {name} (n = {n}, {seeds} seed{'s' if seeds > 1 else ''})\n")
    print(f"| candidate | RMSE median [range] | ratio to best | better / worse than merwe(0.1,2,0) "
          f"|{extra} NEES/n mean (median) | consistent | diverged | seeds failed / flagged "
          "| raised | time ratio |")
    print("|---" * (10 + angle) + "|")
    for label, r in results.items():
        nees = r["nees"][np.isfinite(r["nees"])]
        ne = f"{np.mean(nees):.3g} ({np.median(nees):.3g})" if nees.size else "NaN"
        tr = f"{r['time'] / base:.2f}" if np.isfinite(r["time"]) else "-"
        better = int(np.sum(r["rmse"] < cur["rmse"] * (1 - TIE)))
        worse = int(np.sum(r["rmse"] > cur["rmse"] * (1 + TIE)))
        ang = (f" {median(r['angle']):.4g} ({median(r['angle']) / best_angle:.3f}) |"
               if angle else "")
        print(f"| {label} | {span(r['rmse'])} | {medians[label] / best:.3f} | "
              f"{better} / {worse} |{ang} {ne} | {r['grade']} | {r['diverged']} | "
              f"{r['failed']} / {r['flagged']} | {r['errors']} | {tr} |", flush=True)


def summary(all_results: dict[str, dict[str, dict]]) -> None:
    bests, fewest, sensitive = {}, {}, set()
    for case, results in all_results.items():
        meds = [median(r["rmse"]) for r in results.values()]
        bests[case] = min(m for m in meds if np.isfinite(m))
        fewest[case] = min(r["diverged"] for r in results.values())
        if max(meds) > 1.01 * bests[case] or not np.isfinite(meds).all():
            sensitive.add(case)
    print("\n## Summary over the cases\n")
    print("ratio: the candidate's median RMSE over the best candidate's median, per case; "
          "geometric mean over all the cases the candidate ran, and over the cases where "
          f"the candidates' medians differ by more than 1 % ({', '.join(sorted(sensitive))}"
          "). NEES/n: the median over the cases of the median seed's NEES/n. consistent: "
          "cases with compare's verdict 'yes' (the record has no verdict). extra diverged: "
          "diverged seeds beyond the fewest of any candidate in that case, summed over the "
          "cases. failed: seeds with a failed (re-anchored) step; raised or NaN: runs that "
          "raised or gave a non-finite RMSE.\n")
    print("| candidate | cases | geo. mean ratio | geo. mean ratio, sensitive cases | "
          "within 5 % of best | worst ratio (case) | NEES/n median over cases | "
          "consistent | extra diverged seeds | seeds failed | raised or NaN |")
    print("|---" * 11 + "|")
    for label in CANDIDATES:
        ratios, sens, nees, cases = [], [], [], []
        cons = extra = fail = bad = 0
        for case, results in all_results.items():
            if label not in results:
                continue
            r = results[label]
            cases.append(case)
            med = median(r["rmse"])
            ratio = med / bests[case] if np.isfinite(med) else np.inf
            ratios.append(ratio)
            if case in sensitive:
                sens.append(ratio)
            nees.append(median(r["nees"]))
            cons += r["grade"].startswith("yes")
            extra += r["diverged"] - fewest[case]
            fail += r["failed"]
            bad += r["errors"] + int(np.sum(~np.isfinite(r["rmse"])))
        ratios_a = np.array(ratios)
        worst = int(np.argmax(ratios_a))
        scen = sum(c != "book record" for c in cases)
        print(f"| {label} | {len(cases)} | {np.exp(np.mean(np.log(ratios_a))):.3f} | "
              f"{np.exp(np.mean(np.log(sens))):.3f} ({len(sens)}) | "
              f"{int(np.sum(ratios_a <= 1.05))}/{len(cases)} | "
              f"{ratios_a[worst]:.3f} ({cases[worst]}) | {statistics.median(nees):.3g} | "
              f"{cons}/{scen} | {extra} | {fail} | {bad} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--quick", action="store_true", help="5 seeds, no timing")
    args = parser.parse_args()
    n_seeds = 5 if args.quick else args.seeds
    timing = not args.quick
    seeds = list(range(n_seeds))
    start = time.perf_counter()
    cmd = " ".join(["python", "benchmarks/ukf_points.py", *sys.argv[1:]])
    print("# UKF sigma-point sets: which default\n")
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.machine()}, "
          f"{os.cpu_count()} cores, "
          f"Python {platform.python_version()}, numpy {np.__version__}, CasADi "
          f"{casadi.__version__}, estim {estim.__version__}; `{cmd}`\n")
    print("The cases, candidates and columns are described in `benchmarks/ukf_points.py`. "
          "RMSE over all states and samples (the record: the angle); NEES/n of the full "
          "state, 1 for a consistent filter. The time ratio is `filter` on one record "
          "against merwe(0.1,2,0)'s; between rules with the same number of points "
          "(2n + 1, cubature 2n) it shows the timing's noise.")
    rules()
    all_results: dict[str, dict[str, dict]] = {}
    all_results["book record"] = record_case(timing)
    print_case("book record", all_results["book record"], 2, 1)
    for name, make in CASES.items():
        sc = make()
        all_results[name] = scenario_case(sc, seeds, timing, angle=name in ANGLE_CASES)
        print_case(f"{name}: {sc.n_steps} steps", all_results[name], sc.model.ndx, n_seeds,
                   angle=name in ANGLE_CASES)
    summary(all_results)
    print(f"\n{time.perf_counter() - start:.0f} s in all.")


if __name__ == "__main__":
    main()
