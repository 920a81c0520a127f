#!/usr/bin/env python
r"""Reference run of the ``particles`` book experiment ``book/pmcmc/pmmh_lingauss.py``.

This script re-runs the PMMH part of the experiment of Chopin & Papaspiliopoulos,
"An Introduction to Sequential Monte Carlo" (Springer 2020), end of Chapter 16
(Figures 16.4-16.6), with the *unmodified* ``particles`` library (Nicolas Chopin,
https://github.com/nchopin/particles), so that acceptance rates can be compared
with ``estim``'s own PMMH implementation.  It does NOT import ``estim``.

Set-up (identical to the book script, particles commit 8f2c4bf / PyPI particles 0.4):

* model (``ReparamLinGauss``, subclass of ``particles.kalman.LinearGauss``)::

      X_0 ~ N(0, varX)
      X_t = rho X_{t-1} + U_t,   U_t ~ N(0, varX)
      Y_t = X_t + V_t,           V_t ~ N(0, varY),      t = 0, ..., T-1,  T = 100

* data: the book's file ``book/pmcmc/simulated_linGauss_T100_varX1_varY.04_rho.9.txt``
  (simulated by the author with varX=1, varY=0.2**2, rho=0.9, T=100; no seed given),
  copied verbatim into ``lingauss_data.txt`` next to this script;
* prior: rho ~ U([-1, 1]); varX, varY ~ InvGamma(a=2, b=2) (independent);
* PMMH: ``particles.mcmc.PMMH(ssm_cls=ReparamLinGauss, prior=prior, data=data,
  Nx=Nx, niter=niter, adaptive=False, rw_cov=0.15**2 * I_3)`` -- i.e. a
  NON-adaptive Gaussian random walk on the raw (rho, varX, varY), bootstrap
  filter with systematic resampling when ESS < N/2, theta0 drawn from the prior;
* Nx grid: 100, 200, ..., 1500.
* Also (as in the book, option ``--no-mh`` disables it): the "ideal" random-walk
  Metropolis ``mcmc.BasicRWHM`` with the same proposal but the exact (Kalman)
  likelihood, whose acceptance rate is the book's horizontal reference line.

Differences from the book script (deliberate):
* the book runs ONE chain of niter = 10**5 per Nx (and warns it takes > 10 h);
  here ``niter`` is a command-line argument and ``--chains`` independent chains
  (default 15) are run per Nx, each with its own seed (np.random.seed(seed)
  immediately before ``alg.run()``; particles draws everything, including
  theta0 from the prior, from numpy's global RNG);
* chains are run in the order "chain 0 for every Nx, chain 1 for every Nx, ..."
  and the JSON is re-written after every chain, so a partial run still covers
  the whole Nx grid;
* the plotting / log-likelihood-variance parts of the book script are omitted.

Venv and run (one core)::

    python3 -m venv /work/scratch/particles_ref/venv
    /work/scratch/particles_ref/venv/bin/pip install "numpy<2" "scipy<1.14" particles
    export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1
    /work/scratch/particles_ref/venv/bin/python \
        benchmarks/particles_reference/pmmh_lingauss_particles.py --niter 1200

    # quick timing probe: 1 chain per Nx, 200 iterations, separate output file
    ... pmmh_lingauss_particles.py --niter 200 --chains 1 --out /tmp/probe.json

Output: JSON (default ``benchmarks/results/particles_pmmh_lingauss.json``).
"""

import argparse
import json
import os
import platform
import sys
import time
from collections import OrderedDict

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
           "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import particles  # noqa: E402
import scipy  # noqa: E402
from particles import distributions as dists  # noqa: E402
from particles import kalman, mcmc, smc_samplers  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
DATA_FILE = os.path.join(HERE, "lingauss_data.txt")
DEFAULT_OUT = os.path.join(REPO, "benchmarks", "results",
                           "particles_pmmh_lingauss.json")

# --------------------------------------------------------------------------
# Exactly as in book/pmcmc/pmmh_lingauss.py
# --------------------------------------------------------------------------
dict_prior = {'varX': dists.InvGamma(a=2., b=2.),
              'varY': dists.InvGamma(a=2., b=2.),
              'rho': dists.Uniform(a=-1., b=1.)
              }
prior = dists.StructDist(dict_prior)   # field order: sorted -> rho, varX, varY


class ReparamLinGauss(kalman.LinearGauss):
    def __init__(self, varX=1., varY=1., rho=0.):
        sigmaX = np.sqrt(varX) if varX > 0 else 0.
        sigmaY = np.sqrt(varY) if varY > 0 else 0.
        sigma0 = sigmaX
        # Note: We take X_0 ~ N(0, sigmaX^2) so that Gibbs step is tractable
        kalman.LinearGauss.__init__(self, sigmaX=sigmaX, sigmaY=sigmaY, rho=rho,
                                    sigma0=sigma0)


rw_cov = (0.15) ** 2 * np.eye(3)


def make_static_model(data):
    class StaticLGModel(smc_samplers.StaticModel):
        def loglik(self, theta, t=None):
            ll = np.zeros(theta.shape[0])
            for n, th in enumerate(theta):
                mod = ReparamLinGauss(**smc_samplers.rec_to_dict(th))
                kf = kalman.Kalman(ssm=mod, data=data)
                kf.filter()
                ll[n] = np.sum(kf.logpyt)
            return ll
    return StaticLGModel(data=data, prior=prior)


# --------------------------------------------------------------------------
def chain_summary(alg, burnin):
    theta = alg.chain.theta
    arr = smc_samplers.view_2d_array(theta)
    niter = theta.shape[0]
    moved = np.any(arr[1:] != arr[:-1], axis=1)      # moved[n-1]: step n accepted
    nacc_post = int(np.sum(moved[burnin:]))          # steps burnin+1 .. niter-1
    nsteps_post = niter - 1 - burnin
    return OrderedDict(
        niter=int(niter),
        nacc=int(alg.nacc),
        acc_rate=float(alg.acc_rate),                # particles: nacc / (niter-1)
        nacc_check=int(np.sum(moved)),
        acc_rate_after_burnin=(nacc_post / nsteps_post) if nsteps_post > 0 else None,
        burnin=int(burnin),
        theta0={p: float(theta[p][0]) for p in theta.dtype.names},
        post_mean={p: float(np.mean(theta[p][burnin:])) for p in theta.dtype.names},
        post_sd={p: float(np.std(theta[p][burnin:])) for p in theta.dtype.names},
        msjd_after_burnin=float(mcmc.msjd(theta[burnin:])),
        final_theta={p: float(theta[p][-1]) for p in theta.dtype.names},
    )


def pooled(chains):
    nacc = sum(c["nacc"] for c in chains)
    nsteps = sum(c["niter"] - 1 for c in chains)
    rates = [c["acc_rate"] for c in chains]
    post = [c["acc_rate_after_burnin"] for c in chains
            if c["acc_rate_after_burnin"] is not None]
    nacc_b = sum(round(c["acc_rate_after_burnin"] * (c["niter"] - 1 - c["burnin"]))
                 for c in chains if c["acc_rate_after_burnin"] is not None)
    nsteps_b = sum(c["niter"] - 1 - c["burnin"] for c in chains
                   if c["acc_rate_after_burnin"] is not None)
    secs = [c["wall_seconds"] for c in chains]
    return OrderedDict(
        n_chains=len(chains),
        pooled_acc_rate=nacc / nsteps if nsteps else None,
        min_acc_rate=min(rates), max_acc_rate=max(rates),
        mean_acc_rate=float(np.mean(rates)),
        pooled_acc_rate_after_burnin=nacc_b / nsteps_b if nsteps_b else None,
        min_acc_rate_after_burnin=min(post) if post else None,
        max_acc_rate_after_burnin=max(post) if post else None,
        total_wall_seconds=float(sum(secs)),
        seconds_per_iteration=float(sum(secs) / sum(c["niter"] for c in chains)),
        post_mean_over_chains={p: float(np.mean([c["post_mean"][p] for c in chains]))
                               for p in chains[0]["post_mean"]},
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--niter", type=int, default=1200,
                    help="MCMC iterations per chain (book: 10**5)")
    ap.add_argument("--chains", type=int, default=15)
    ap.add_argument("--nx", type=int, nargs="*", default=list(range(100, 1600, 100)))
    ap.add_argument("--seed", type=int, default=20240,
                    help="base seed; chain c at Nx uses seed + 10000*c + Nx "
                         "(Nx=0 for the exact-likelihood 'mh' sampler)")
    ap.add_argument("--no-mh", action="store_true",
                    help="skip the exact-likelihood (Kalman) RWHM baseline")
    ap.add_argument("--burnin-frac", type=float, default=0.1)
    ap.add_argument("--out", default=DEFAULT_OUT)
    args = ap.parse_args()

    data = np.loadtxt(DATA_FILE)   # comment lines ('#') skipped
    assert data.shape == (100,), data.shape
    burnin = int(args.niter * args.burnin_frac)

    try:
        from importlib.metadata import version
        particles_version = version("particles")
    except Exception:  # pragma: no cover
        particles_version = None

    settings = OrderedDict(
        source="particles book/pmcmc/pmmh_lingauss.py (github nchopin/particles "
               "commit 8f2c4bfa85cc7a287c0fd36b13710bfe4bd41856)",
        model=OrderedDict(
            cls="ReparamLinGauss(kalman.LinearGauss): sigmaX=sqrt(varX), "
                "sigmaY=sqrt(varY), sigma0=sigmaX",
            equations="X_0~N(0,varX); X_t=rho*X_{t-1}+N(0,varX); "
                      "Y_t=X_t+N(0,varY), t=0..T-1",
            T=int(data.shape[0]),
            data_file=os.path.relpath(DATA_FILE, REPO),
            data_generated_with=dict(varX=1.0, varY=0.04, rho=0.9),
        ),
        prior=OrderedDict(
            rho="Uniform(a=-1, b=1)",
            varX="InvGamma(a=2, b=2)  [scipy invgamma(a, scale=b)]",
            varY="InvGamma(a=2, b=2)  [scipy invgamma(a, scale=b)]",
        ),
        parameter_order=list(prior.dtype.names if hasattr(prior.dtype, "names")
                             else [d[0] for d in prior.dtype]),
        proposal=OrderedDict(
            algorithm="particles.mcmc.PMMH (GenericRWHM)",
            adaptive=False,
            rw_cov="0.15**2 * eye(3) on raw (rho, varX, varY)",
            rw_sd=0.15,
            theta0="drawn from prior (theta0=None)",
            inner_filter="ssms.Bootstrap + particles.SMC defaults: "
                         "resampling='systematic', ESSrmin=0.5, qmc=False",
            acc_rate_definition="nacc / (niter - 1)  (all iterations, no burn-in)",
        ),
        nx_grid=args.nx,
        niter=args.niter,
        chains=args.chains,
        burnin=burnin,
        base_seed=args.seed,
        seed_rule="np.random.seed(base_seed + 10000*chain + Nx) before alg.run(); "
                  "Nx=0 for the exact-likelihood 'mh' sampler",
        exact_mh_baseline=not args.no_mh,
    )

    results = OrderedDict(
        particles_version=particles_version,
        particles_module_version_attr=getattr(particles, "__version__", None),
        numpy_version=np.__version__,
        scipy_version=scipy.__version__,
        python_version=sys.version.split()[0],
        platform=platform.platform(),
        threads=dict((k, os.environ.get(k)) for k in (
            "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
            "NUMBA_NUM_THREADS")),
        settings=settings,
        complete=False,
        started=time.strftime("%Y-%m-%d %H:%M:%S"),
        per_nx=OrderedDict(),
        summary=OrderedDict(),
    )
    keys = (["mh"] if not args.no_mh else []) + ["pmmh-%d" % nx for nx in args.nx]
    for k in keys:
        results["per_nx"][k] = []

    def dump():
        for k in keys:
            if results["per_nx"][k]:
                results["summary"][k] = pooled(results["per_nx"][k])
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        tmp = args.out + ".tmp"
        with open(tmp, "w") as f:
            json.dump(results, f, indent=1)
        os.replace(tmp, args.out)

    sm = make_static_model(data) if not args.no_mh else None
    t_start = time.perf_counter()
    for c in range(args.chains):
        for k in keys:
            nx = 0 if k == "mh" else int(k.split("-")[1])
            seed = args.seed + 10000 * c + nx
            if k == "mh":
                alg = mcmc.BasicRWHM(model=sm, niter=args.niter, adaptive=False,
                                     rw_cov=rw_cov)
            else:
                alg = mcmc.PMMH(ssm_cls=ReparamLinGauss, prior=prior, data=data,
                                Nx=nx, niter=args.niter, adaptive=False,
                                rw_cov=rw_cov)
            np.random.seed(seed)
            t0 = time.perf_counter()
            alg.run()
            wall = time.perf_counter() - t0
            s = chain_summary(alg, burnin)
            s["chain"] = c
            s["Nx"] = nx if nx else None
            s["seed"] = seed
            s["wall_seconds"] = wall
            s["seconds_per_iteration"] = wall / args.niter
            results["per_nx"][k].append(s)
            print("chain %2d %-9s seed %6d acc %.3f (post-burnin %.3f) "
                  "%.1fs (%.2f ms/it) mean rho=%.3f varX=%.3f varY=%.4f  [%.0fs]"
                  % (c, k, seed, s["acc_rate"], s["acc_rate_after_burnin"] or -1,
                     wall, 1e3 * wall / args.niter, s["post_mean"]["rho"],
                     s["post_mean"]["varX"], s["post_mean"]["varY"],
                     time.perf_counter() - t_start), flush=True)
            dump()
    results["complete"] = True
    results["finished"] = time.strftime("%Y-%m-%d %H:%M:%S")
    results["total_wall_seconds"] = time.perf_counter() - t_start
    dump()

    print("\n%-9s %8s %8s %8s %8s %10s" % ("alg", "pooled", "min", "max",
                                         "postBI", "s/iter"))
    for k in keys:
        sm_ = results["summary"][k]
        print("%-9s %8.4f %8.4f %8.4f %8.4f %10.5f" % (
            k, sm_["pooled_acc_rate"], sm_["min_acc_rate"], sm_["max_acc_rate"],
            sm_["pooled_acc_rate_after_burnin"], sm_["seconds_per_iteration"]))


if __name__ == "__main__":
    main()
