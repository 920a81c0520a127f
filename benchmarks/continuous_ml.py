"""Maximum likelihood of a continuous-time model on irregular stamps: Lorenz-63's
(sigma, rho, beta) from one record of 2000 samples, with the continuous-discrete EKF's
likelihood (``estim.tuning.maximum_likelihood(..., continuous=True, t=...)``).

The record: Lorenz-63 (sigma = 10, rho = 28, beta = 8/3) with a unit diffusion on each
state, every state measured with unit variance, at stamps whose intervals are log-uniform
in [shortest, longest] (default [0.001, 0.1]; ``benchmarks/continuous_noise.py``'s
generator, seed 0). The noise
densities are held at the truth (``Qc = I``, ``R = I``: ``structure="fixed"``); the three
parameters start 20 % off. Printed: each estimate, its standard error (the inverse observed
information), its distance from the truth in standard errors, and the fit's time.

Run from the repository root::

    python benchmarks/continuous_ml.py [--samples 2000] [--shortest 0.001] [--longest 0.1]

With intervals up to 0.5 s (``--shortest 0.01 --longest 0.5``) the filter is not consistent
(``benchmarks/continuous_noise.py``) and the likelihood of the chaotic flow over the long
intervals is rugged: from the same start the fit ends in a local optimum (its negative
log-likelihood 100 887 against 11 729 at the truth) with standard errors far too small, and
its status cannot tell (``benchmarks/results/continuous_ml.md``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from continuous_noise import BETA, RHO, SIGMA, lorenz, record

import estim


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=2000)
    parser.add_argument("--shortest", type=float, default=0.001)
    parser.add_argument("--longest", type=float, default=0.1)
    parser.add_argument("--substeps", type=int, default=50)
    parser.add_argument("--estimator", default="ekf")
    args = parser.parse_args()
    t, X, Y = record(0, args.samples, args.shortest, args.longest)
    m = lorenz(args.substeps)
    truth = {"sigma": SIGMA, "rho": RHO, "beta": BETA}
    t0 = time.perf_counter()
    res = estim.tuning.maximum_likelihood(
        m, Y, t=t, continuous=True, substeps=args.substeps, estimator=args.estimator,
        Q0=np.eye(3), R0=np.eye(3), x0=X[0], P0=np.eye(3),
        structure={"Q": "fixed", "R": "fixed"},
        params={k: 1.2 * v for k, v in truth.items()}, starts=1)
    seconds = time.perf_counter() - t0
    print(f"# Lorenz-63 (sigma, rho, beta) by maximum likelihood: {args.samples} samples, "
          f"intervals log-uniform in [{args.shortest:g}, {args.longest:g}], the CD-"
          f"{args.estimator.upper()} with {args.substeps} sub-steps\n")
    print(f"status: {res.status}; {seconds:.1f} s (building the graphs "
          f"{res.details['compile_time']:.1f} s)\n")
    print("| parameter | truth | estimate | standard error | (estimate - truth) / se |")
    print("|---|---|---|---|---|")
    for k, v in truth.items():
        est, se = res.params[k], res.stderr["params"][k]
        print(f"| {k} | {v:.4g} | {est:.4f} | {se:.4f} | {(est - v) / se:+.2f} |")


if __name__ == "__main__":
    main()
