"""SMC²'s log-evidence against the exact one on the linear Gaussian model of the
``particles`` book (chapter 16): the book's data (``particles_reference/lingauss_data.txt``,
T = 100), priors :math:`\\rho \\sim U(-1, 1)`, :math:`\\sigma_X^2, \\sigma_Y^2 \\sim
\\mathrm{InvGamma}(2, 2)`, :math:`X_0 \\sim N(0, \\sigma_X^2)`.

The exact :math:`\\log p(y)` integrates the Kalman filter's likelihood times the prior by
the midpoint rule over :math:`\\rho` and the logarithms of the variances (the grid refined
until the value moves by less than 1e-4). :func:`estim.inference.smc2` with
:math:`N_x` = 100 particles per parameter particle and :math:`N_\\theta` = 1000, 2000, 4000
parameter particles, ``--seeds`` seeds each: the mean, standard deviation and RMSE of
the estimates about the exact value, the share within 0.1, seconds per run (median
[range]), and the posterior means against the exact chain's.

Writes ``results/smc2_evidence.json``. Run from the repository root::

    python benchmarks/smc2_evidence.py [--seeds 10]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import estim
from estim.inference import smc2

HERE = Path(__file__).parent
sys.path.insert(0, str(HERE))
from lingauss import PRIORS, data, evidence, model, tuning  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--thetas", type=int, nargs="*", default=[1000, 2000, 4000])
    ap.add_argument("--out", default=str(HERE / "results" / "smc2_evidence.json"))
    args = ap.parse_args()
    Y = data()
    coarse, _ = evidence(Y, (100, 90, 90))
    exact, means = evidence(Y, (200, 180, 180))
    print(f"exact log-evidence {exact:.5f} (coarser grid: {coarse:.5f}); posterior means "
          + ", ".join(f"{k} {v:.4f}" for k, v in means.items()))
    pf = estim.ParticleFilter(model(), Q=1.0, R=0.04, x0=[0.0], P0=[[1.0]], n_particles=100,
                              jit=True)

    out = {"exact": exact, "exact_coarse": coarse, "exact_means": means, "runs": {}}
    print(f"{'N_theta':>8} {'mean - exact':>12} {'sd':>6} {'RMSE':>6} {'within 0.1':>10} "
          f"{'s/run':>16}  posterior means (rho, varX, varY) - exact")
    for n_theta in args.thetas:
        z, secs, pm = [], [], []
        for s in range(args.seeds):
            t0 = time.perf_counter()
            r = smc2(pf, Y, priors=PRIORS, tuning=tuning, n_theta=n_theta, seed=s)
            secs.append(time.perf_counter() - t0)
            z.append(r.log_evidence)
            pm.append([r.mean()[k] for k in means])
        z, pm = np.array(z), np.array(pm)
        d = z - exact
        row = {"log_evidence": z.tolist(), "seconds": secs, "mean_error": float(d.mean()),
               "sd": float(d.std(ddof=1)), "rmse": float(np.sqrt((d ** 2).mean())),
               "within_0.1": float((np.abs(d) <= 0.1).mean()),
               "posterior_means": pm.tolist()}
        out["runs"][n_theta] = row
        print(f"{n_theta:>8} {d.mean():>+12.4f} {d.std(ddof=1):>6.3f} {row['rmse']:>6.3f} "
              f"{row['within_0.1']:>10.2f} {np.median(secs):>6.1f} "
              f"[{min(secs):.1f}-{max(secs):.1f}]  "
              + ", ".join(f"{v:+.4f}" for v in pm.mean(axis=0) - np.array(list(
                  means.values()))))
        Path(args.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
