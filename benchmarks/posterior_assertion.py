"""The error rates of ``estim.testing.assert_posterior_close``, measured.

The posterior of :math:`\\rho` on the ``particles`` book's linear model (its data, T = 100,
:math:`\\sigma_X^2 = 1`, :math:`\\sigma_Y^2 = 0.04` known, :math:`\\rho \\sim U(-1, 1)`),
its mean by quadrature of the Kalman likelihood (4001 points):

* **false failures**: ``--reps`` independent exact-likelihood Metropolis-Hastings runs (4
  chains of 2000 iterations, Haario adaptation) judged against the exact mean at
  confidence 0.99: the share that fails, to be at most about 1 %;
* **hostile chains**: ``--reps`` PMMH runs with 3 particles (the log-likelihood estimate's
  spread far above 3, the chains stick) of the same length: the share that *passes*
  (it should be small: a stuck chain must not be judged close on its tiny spread), and how
  they fail (not judgeable, or judged different);
* **a shifted posterior**: exact chains on the data with 0.3 added to every sample, judged
  against the unshifted mean (the power: the share that fails).

Run from the repository root::

    python benchmarks/posterior_assertion.py [--reps 200]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import estim
from estim.inference import Uniform, pmmh
from estim.inference.posterior import agreement

sys.path.insert(0, str(Path(__file__).parent))
from lingauss import data, kalman_loglik, model  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=200)
    args = ap.parse_args()
    Y = data()
    ll = kalman_loglik(Y, varX=1.0, varY=0.04)
    grid = np.linspace(-0.9995, 0.9995, 4001)
    lp = np.array([ll({"rho": r}) for r in grid])
    w = np.exp(lp - lp.max())
    exact = {"rho": float((grid * w).sum() / w.sum())}
    priors = {"rho": Uniform(-1, 1)}
    kw = dict(priors=priors, start={"rho": 0.5}, n_iter=2000, n_chains=4)
    t0 = time.perf_counter()
    fails = sum(not agreement(pmmh(ll, seed=s, **kw), exact)[0] for s in range(args.reps))
    print(f"exact chains judged against the exact mean {exact['rho']:.5f}: {fails} of "
          f"{args.reps} fail ({fails / args.reps:.3f}; at most 0.01 expected) "
          f"[{time.perf_counter() - t0:.0f} s]")
    shifted = kalman_loglik(Y + 0.3, varX=1.0, varY=0.04)
    fails = sum(not agreement(pmmh(shifted, seed=s, **kw), exact)[0]
                for s in range(args.reps // 4))
    print(f"a shifted record's chains: {fails} of {args.reps // 4} fail (the power)")
    pf = estim.ParticleFilter(model(), Q=1.0, R=0.04, x0=[0.0], P0=[[1.0]], n_particles=3,
                              jit=True)
    passed, unjudged = 0, 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", estim.EstimationWarning)
        for s in range(args.reps // 4):
            ok, text = agreement(pmmh(pf, Y, seed=s, **kw), exact)
            passed += ok
            unjudged += "cannot be judged" in text
    print(f"3-particle PMMH chains: {passed} of {args.reps // 4} pass, {unjudged} refused as "
          f"not judgeable")


if __name__ == "__main__":
    main()
