"""The ``particles`` book experiment ``book/pmcmc/pmmh_lingauss.py`` (Chopin &
Papaspiliopoulos 2020, ch. 16) with :func:`estim.inference.pmmh` on the compiled particle
filter.

The model (``ReparamLinGauss``): :math:`X_0 \\sim N(0, \\sigma_X^2)`,
:math:`X_t = \\rho X_{t-1} + U_t`, :math:`U_t \\sim N(0, \\sigma_X^2)`,
:math:`Y_t = X_t + V_t`, :math:`V_t \\sim N(0, \\sigma_Y^2)`, T = 100; the book's data
(``particles_reference/lingauss_data.txt``, simulated with :math:`\\rho = 0.9`,
:math:`\\sigma_X^2 = 1`, :math:`\\sigma_Y^2 = 0.04`); priors
:math:`\\rho \\sim U(-1, 1)`, :math:`\\sigma_X^2, \\sigma_Y^2 \\sim \\mathrm{InvGamma}(2, 2)`;
the book's sampler: a random walk of covariance :math:`0.15^2 I` on the raw parameters,
not adapted, the start drawn from the prior, the bootstrap filter with systematic
resampling below half the particles' effective size; one chain of ``--niter``
iterations (the book: :math:`10^5`) for each :math:`N_x = 100, 200, \\dots, 1500`
(15 chains), dealt longest first to ``--jobs`` worker processes.

Compared:

* the acceptance rate at each :math:`N_x` with ``particles``' own run of the same
  experiment (``results/particles_pmmh_lingauss.json``, made by
  ``particles_reference/pmmh_lingauss_particles.py`` in its own numpy < 2 environment):
  inside the 95 % binomial (Wilson) band of its pooled rate after the burn-in (10 %, as
  here)? Its chains are 1200 iterations each (15 per N_x), started from the prior as
  here; the few still stuck in a prior tail after their burn-in (posterior mean more
  than 5 posterior standard deviations from the exact chains', counted in ``stuck``)
  are left out, so that both rates are the stationary chain's. The band treats the
  acceptances as independent; those of a chain are not, so the rates' real spread is
  wider: also printed, two standard errors of the pooled rate from the spread of
  ``particles``' own chains.
* the posterior means of each chain with an exact-likelihood (Kalman) Metropolis-Hastings
  run of 4 chains with the same proposal: within 2 combined Monte Carlo standard errors?

Writes ``results/pmmh_lingauss.json`` and prints the tables. Run from the repository root::

    python benchmarks/pmmh_lingauss.py [--niter 100000] [--jobs 2]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import estim
from estim.inference import pmmh

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from lingauss import PRIORS, data, kalman_loglik, model, tuning  # noqa: E402

PROPOSAL = 0.15 ** 2 * np.eye(3)
GRID = list(range(100, 1600, 100))


def chain(nx: int, niter: int, seed: int) -> dict:
    """One PMMH chain at ``nx`` particles (a worker's task)."""
    Y = data()
    pf = estim.ParticleFilter(model(), Q=1.0, R=0.04, x0=[0.0], P0=[[1.0]], n_particles=nx,
                              jit=True)
    t0 = time.perf_counter()
    post = pmmh(pf, Y, priors=PRIORS, tuning=tuning, n_iter=niter, n_chains=1,
                proposal=PROPOSAL, adapt=None, warmup=niter // 10, seed=seed)
    return {"nx": nx, "seconds": time.perf_counter() - t0,
            "acceptance": float(post.acceptance[0]),
            "mean": post.mean(), "mcse": post.mcse(), "ess": post.ess(),
            "loglik_sd_start": post.details["loglik_sd_start"],
            "loglik_sd": post.details.get("loglik_sd")}


def wilson(p: float, n: int, z: float = 1.96) -> tuple[float, float]:
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--niter", type=int, default=100_000)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=2020)
    ap.add_argument("--grid", type=int, nargs="*", default=GRID)
    ap.add_argument("--out", default=str(HERE / "results" / "pmmh_lingauss.json"))
    args = ap.parse_args()
    from joblib import Parallel, delayed

    Y = data()
    t0 = time.perf_counter()
    exact = pmmh(kalman_loglik(Y), priors=PRIORS, n_iter=args.niter, n_chains=4,
                 proposal=PROPOSAL, adapt=None, warmup=args.niter // 10, seed=args.seed)
    t_exact = time.perf_counter() - t0
    ex_mean, ex_se, ex_sd = exact.mean(), exact.mcse(), exact.sd()
    ex_acc = float(exact.acceptance.mean())
    t0 = time.perf_counter()
    order = sorted(args.grid, reverse=True)  # longest first
    runs = Parallel(n_jobs=args.jobs, batch_size=1)(
        delayed(chain)(nx, args.niter, args.seed + nx) for nx in order)
    wall = time.perf_counter() - t0
    runs = sorted(runs, key=lambda r: r["nx"])
    ref_path = HERE / "results" / "particles_pmmh_lingauss.json"
    ref = json.loads(ref_path.read_text()) if ref_path.exists() else None
    rows = []
    print(f"PMMH, the particles book experiment: {len(runs)} chains x {args.niter} "
          f"iterations, wall {wall:.0f} s on {args.jobs} workers (the book: more than 10 h)")
    print(f"exact (Kalman) MH, 4 chains: acceptance {ex_acc:.4f}; means "
          + ", ".join(f"{k} {v:.4f} +- {ex_se[k]:.4f}" for k, v in ex_mean.items())
          + f" ({t_exact:.0f} s)")
    head = (f"{'Nx':>5} {'estim acc':>9} {'particles acc':>13} {'95% band':>17} {'in':>3} "
            f"{'2se':>6} {'stuck':>5} "
            f"{'sd(ll)':>6} {'s':>6}  z of the means vs Kalman (rho, varX, varY)")
    print(head)
    for r in runs:
        row = dict(r)
        z = {k: (r["mean"][k] - ex_mean[k]) / math.hypot(r["mcse"][k], ex_se[k])
             for k in ex_mean}
        row["z"] = z
        row["within_2_mcse"] = all(abs(v) <= 2 for v in z.values())
        band, pacc, inside, spread, stuck = None, None, None, None, 0
        if ref is not None and f"pmmh-{r['nx']}" in ref.get("per_nx", {}):
            # particles' chains of 1200 iterations after their burn-in, without those
            # still stuck in a prior tail they started in (posterior mean more than 5
            # posterior sd from the exact chains'): the stationary acceptance, as here
            chains = [c for c in ref["per_nx"][f"pmmh-{r['nx']}"]
                      if all(abs(c["post_mean"][k] - ex_mean[k]) <= 5 * ex_sd[k]
                             for k in ex_mean)]
            stuck = len(ref["per_nx"][f"pmmh-{r['nx']}"]) - len(chains)
            n = sum(c["niter"] - 1 - c["burnin"] for c in chains)
            pacc = sum(c["acc_rate_after_burnin"] * (c["niter"] - 1 - c["burnin"])
                       for c in chains) / n
            band = wilson(pacc, n)
            inside = band[0] <= r["acceptance"] <= band[1]
            rates = np.array([c["acc_rate_after_burnin"] for c in chains])
            spread = 2 * rates.std(ddof=1) / math.sqrt(len(rates))
        row["particles_chain_spread_2se"] = spread
        row["particles_stuck_chains"] = stuck
        row.update(particles_acceptance=pacc, band=band, inside=inside)
        rows.append(row)
        b = f"[{band[0]:.4f}, {band[1]:.4f}]" if band else "-"
        print(f"{r['nx']:>5} {r['acceptance']:>9.4f} "
              f"{(f'{pacc:.4f}' if pacc is not None else '-'):>13} {b:>17} "
              f"{('yes' if inside else 'no' if inside is not None else '-'):>3} "
              f"{(f'{spread:.4f}' if spread is not None else '-'):>6} {stuck:>5} "
              f"{r['loglik_sd_start']:>6.2f} {r['seconds']:>6.0f}  "
              + ", ".join(f"{v:+.2f}" for v in z.values()))
    if ref is not None:  # particles' own seconds per iteration, for the same experiment
        per = [ref["summary"][f"pmmh-{r['nx']}"]["seconds_per_iteration"] for r in runs
               if f"pmmh-{r['nx']}" in ref.get("summary", {})]
        if len(per) == len(runs):
            projected = sum(per) * args.niter
            print(f"particles at its measured seconds per iteration: {projected / 3600:.1f} h "
                  f"on one core for the same chains ({projected / wall:.0f} x this run's "
                  f"wall time on {args.jobs} workers, "
                  f"{projected / sum(r['seconds'] for r in runs):.0f} x per core)")
    out = {"niter": args.niter, "jobs": args.jobs, "wall_seconds": wall,
           "exact": {"acceptance": ex_acc, "mean": ex_mean, "mcse": ex_se,
                     "seconds": t_exact},
           "runs": rows, "estim": estim.__version__}
    Path(args.out).write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
