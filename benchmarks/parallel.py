"""Wall time of ``estim.compare`` serial against ``n_jobs=2``, first and warm calls.

Two workloads on the van der Pol scenario (``estim.scenarios.van_der_pol()``,
120 steps):

* big: ``estim.MHE`` (Gauss-Newton) at horizons 10, 15, 20, 25 and 30 over
  ``--seeds`` seeds (default 85: 425 runs, about 15-20 s serially);
* tiny: ``estim.EKF`` over 4 seeds (a few tens of milliseconds serially).

Every measurement runs in a fresh Python process, which times two calls of
``estim.compare`` with the same arguments: the first call (nothing started
yet: with ``n_jobs=2`` the workers start and import estim) and a warm second
call (loky's workers are still up). Serial is ``n_jobs=1``; "forced" is
``n_jobs=2, min_parallel_seconds=0``, the workers used whatever the workload.
The ratio is serial time over ``n_jobs=2`` time (above 1: parallel is
faster), from the medians over ``--repeats`` processes. Every run checks that
the per-seed RMSEs equal the serial ones bit for bit.

Run from the repository root::

    python benchmarks/parallel.py [--seeds 85] [--repeats 3] [--tiny-repeats 5]

There are no timing assertions; the numbers depend on the machine and on what
else runs on it (a core held by another process halves the parallel gain).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time

import numpy as np

HORIZONS = (10, 15, 20, 25, 30)


def _workload(kind: str, seeds: int):
    import estim

    sc = estim.scenarios.van_der_pol()
    if kind == "tiny":
        return sc, {"ekf": estim.EKF}, range(4)
    est = {f"mhe-{n}": (lambda m, t, n=n: estim.MHE(m, horizon=n, solver="gauss-newton", **t))
           for n in HORIZONS}
    return sc, est, range(seeds)


def child(kind: str, mode: str, seeds: int) -> None:
    """Two timed calls in this (fresh) process; JSON on stdout."""
    import estim

    sc, est, seed_range = _workload(kind, seeds)
    kw = {} if mode == "serial" else {"n_jobs": 2}
    if mode == "forced":
        kw["min_parallel_seconds"] = 0
    out = {"times": [], "notes": []}
    for _ in range(2):
        t0 = time.perf_counter()
        res = estim.compare(sc, est, seeds=seed_range, **kw)
        out["times"].append(time.perf_counter() - t0)
        out["notes"].append(res.parallel)
    out["rmse"] = {k: v.tolist() for k, v in res.rmse.items()}
    print(json.dumps(out))


def measure(kind: str, mode: str, seeds: int, repeats: int) -> dict:
    runs = []
    for _ in range(repeats):
        proc = subprocess.run([sys.executable, __file__, "--child", kind, mode,
                               "--seeds", str(seeds)], capture_output=True, text=True,
                              check=True)
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    times = np.array([r["times"] for r in runs])  # (repeats, 2): first, warm
    return {"first": float(np.median(times[:, 0])), "warm": float(np.median(times[:, 1])),
            "all": times.tolist(), "notes": runs[-1]["notes"], "rmse": [r["rmse"] for r in runs]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=85)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--tiny-repeats", type=int, default=5)
    ap.add_argument("--child", nargs=2, metavar=("KIND", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(*args.child, args.seeds)
        return
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}; load average {os.getloadavg()[0]:.2f} at start")
    for kind, repeats, modes in (("big", args.repeats, ("serial", "parallel")),
                                 ("tiny", args.tiny_repeats, ("serial", "parallel", "forced"))):
        res = {m: measure(kind, m, args.seeds, repeats) for m in modes}
        ref = res["serial"]["rmse"][0]
        same = all(r == ref for m in modes for r in res[m]["rmse"])
        runs = sum(len(v) for v in ref.values())
        print(f"\n{kind}: {runs} runs, median of {repeats} processes; results identical to "
              f"serial bit for bit: {same}")
        print(f"  {'':<22}{'first call':>12}{'warm call':>12}{'ratio first':>13}"
              f"{'ratio warm':>12}")
        s = res["serial"]
        for m in modes:
            r = res[m]
            label = {"serial": "serial", "parallel": "n_jobs=2",
                     "forced": "n_jobs=2, forced"}[m]
            print(f"  {label:<22}{r['first']:>11.3f}s{r['warm']:>11.3f}s"
                  f"{s['first'] / r['first']:>12.2f}×{s['warm'] / r['warm']:>11.2f}×")
        for m in modes[1:]:
            print(f"  {m} (first / warm): {res[m]['notes'][0]}\n    / {res[m]['notes'][1]}")
            print(f"  {m} all times: {[[round(t, 3) for t in ts] for ts in res[m]['all']]}")
        print(f"  serial all times: {[[round(t, 3) for t in ts] for ts in s['all']]}")
    print(f"\nload average {os.getloadavg()[0]:.2f} at the end")


if __name__ == "__main__":
    main()
