"""SMC²'s log-evidence against the exact one on the linear Gaussian model of the
``particles`` book (chapter 16): the book's data (``particles_reference/lingauss_data.txt``,
T = 100), priors :math:`\\rho \\sim U(-1, 1)`, :math:`\\sigma_X^2, \\sigma_Y^2 \\sim
\\mathrm{InvGamma}(2, 2)`, :math:`X_0 \\sim N(0, \\sigma_X^2)`.

The exact :math:`\\log p(y)` integrates the Kalman filter's likelihood times the prior by
the midpoint rule over :math:`\\rho` and the logarithms of the variances (the grid refined
until the value moves by less than 1e-4). :func:`estim.inference.smc2` with
:math:`N_x` = 100 particles per parameter particle and :math:`N_\\theta` = 500, 1000, 2000
parameter particles, ``--seeds`` seeds each: the mean, standard deviation and RMSE of
the estimates about the exact value, the share within 0.1, seconds per run (median
[range]), and the posterior means against the exact chain's.

Writes ``results/smc2_evidence.json``. Run from the repository root::

    python benchmarks/smc2_evidence.py [--seeds 20]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from scipy import stats

import estim
from estim.inference import InverseGamma, Uniform, smc2

HERE = Path(__file__).parent
PRIORS = {"rho": Uniform(-1, 1), "varX": InverseGamma(2, 2), "varY": InverseGamma(2, 2)}


def kalman(Y, rho, q, r):
    m, P, total = np.zeros_like(rho), np.array(q, float), np.zeros_like(rho)
    for k, yk in enumerate(Y[:, 0]):
        if k:
            m, P = rho * m, rho * rho * P + q
        S = P + r
        e = yk - m
        total = total - 0.5 * (np.log(2 * np.pi * S) + e * e / S)
        K = P / S
        m, P = m + K * e, (1 - K) * P
    return total


def evidence(Y, n) -> tuple[float, dict]:
    """log p(y) and the posterior means by the midpoint rule on an n-grid."""
    rho = np.linspace(-1, 1, n[0] + 1)[:-1] + 1 / n[0]
    lq, lr = np.linspace(-5, 4, n[1]), np.linspace(-7, 3, n[2])
    R, LQ, LR = np.meshgrid(rho, lq, lr, indexing="ij")
    q, r = np.exp(LQ), np.exp(LR)
    a = kalman(Y, R, q, r) + math.log(0.5) + stats.invgamma.logpdf(q, 2, scale=2) + \
        stats.invgamma.logpdf(r, 2, scale=2) + LQ + LR
    top = a.max()
    w = np.exp(a - top)
    vol = (2 / n[0]) * (lq[1] - lq[0]) * (lr[1] - lr[0])
    means = {"rho": float((w * R).sum() / w.sum()), "varX": float((w * q).sum() / w.sum()),
             "varY": float((w * r).sum() / w.sum())}
    return float(top + np.log(w.sum() * vol)), means


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--thetas", type=int, nargs="*", default=[500, 1000, 2000])
    ap.add_argument("--out", default=str(HERE / "results" / "smc2_evidence.json"))
    args = ap.parse_args()
    Y = np.loadtxt(HERE / "particles_reference" / "lingauss_data.txt")[:, None]
    coarse, _ = evidence(Y, (100, 90, 90))
    exact, means = evidence(Y, (200, 180, 180))
    print(f"exact log-evidence {exact:.5f} (coarser grid: {coarse:.5f}); posterior means "
          + ", ".join(f"{k} {v:.4f}" for k, v in means.items()))
    model = estim.Model(states=["x"], outputs=["y"], params={"rho": 0.9},
                        dynamics=lambda x, u, p: p["rho"] * x, output=lambda x, u, p: x)
    pf = estim.ParticleFilter(model, Q=1.0, R=0.04, x0=[0.0], P0=[[1.0]], n_particles=100,
                              jit=True)

    def tuning(th):
        return {"Q": [[th["varX"]]], "R": [[th["varY"]]], "P0": [[th["varX"]]]}

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
