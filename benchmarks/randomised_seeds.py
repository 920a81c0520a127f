"""False alarms of a paired verdict between two identical particle filters, with each
seed's run on its own stream (what ``compare`` does) and with every run restarting the
filter's one stream (what it did before).

Two particle filters that differ only in their seed are equally good: ``assert_better``
at confidence 0.95 should call one better than the other in at most 5 % of comparisons.
Each comparison here runs both filters on 20 seeds of a short pendulum record; the
trials use different filter seeds. With one stream per filter, every seed's run of a
filter draws the same numbers, so its Monte Carlo error is shared by all the seeds and
the paired differences have a common part the test takes for a real difference.

    python benchmarks/randomised_seeds.py [--trials 200] [--seeds 20]

Writes results/randomised_seeds.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import estim
from estim.adapters import from_function

RESULTS = Path(__file__).parent / "results"


def _one_stream(pf: estim.ParticleFilter, model: estim.Model):
    """The filter as compare ran it before: a wrapper that restarts its stream at every
    reset (not marked randomised, so compare does not reseed it)."""
    return from_function(lambda y, u: pf.step(y, u), model, name="pf", reset=pf.reset)


def rates(trials: int, n_seeds: int) -> dict:
    sc = estim.scenarios.get("book_pendulum").replace(n_steps=100)
    m, tuning = sc.model, {**sc.tuning, "x0": [1.5, 0.0], "P0": 0.1 * np.eye(2)}
    out = {}
    for mode in ("own stream per seed", "one stream for all seeds"):
        alarms, t0 = 0, time.perf_counter()
        for k in range(trials):
            a = estim.ParticleFilter(m, **tuning, n_particles=100, seed=2 * k, jit=True)
            b = estim.ParticleFilter(m, **tuning, n_particles=100, seed=2 * k + 1, jit=True)
            if mode != "own stream per seed":
                a, b = _one_stream(a, m), _one_stream(b, m)
            res = estim.compare(sc, {"a": a, "b": b}, seeds=range(1000 * k, 1000 * k + n_seeds),
                                progress=False)
            for x, y in (("a", "b"), ("b", "a")):
                try:
                    estim.testing.assert_better(res, x, y, confidence=0.95)
                    alarms += 1
                except AssertionError:
                    pass
        n = 2 * trials
        out[mode] = {"alarms": alarms, "tests": n, "rate": alarms / n,
                     "seconds": time.perf_counter() - t0}
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args(argv)
    res = rates(args.trials, args.seeds)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "randomised_seeds.json").write_text(json.dumps(
        {"trials": args.trials, "seeds": args.seeds, "confidence": 0.95, **res}, indent=1))
    for mode, r in res.items():
        print(f"{mode:26s} false alarms {r['alarms']:4d} of {r['tests']} "
              f"({r['rate']:.1%}; at most 5 % expected) in {r['seconds']:.0f} s")


if __name__ == "__main__":
    main()
