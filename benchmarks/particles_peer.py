"""The ``particles`` side of ``benchmarks/particle_filters.py`` (N. Chopin's library, which needs
numpy < 2: run it with its own interpreter, e.g. ``venv-particles/bin/python``).

Reads the records that ``benchmarks/particle_filters.py`` simulated (an ``.npz``), runs
``particles``' bootstrap filter (``particles.SMC`` with ``ssm.Bootstrap``,
systematic resampling when the ESS falls below N/2, as estim's default) and prints
one JSON object: the filtered means and log-likelihoods per seed, and wall times.
It imports nothing from estim.

Usage: ``python particles_peer.py DATA.npz``
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import particles
from particles import distributions as dists
from particles import state_space_models as ssm
from particles.collectors import Moments


class LinearGauss2(ssm.StateSpaceModel):
    """The 2-state linear Gaussian model of the speed table (matrices in the data)."""

    default_params = {"A": None, "C": None, "Q": None, "R": None, "P0": None}

    def PX0(self):
        return dists.MvNormal(loc=np.zeros(2), cov=self.P0)

    def PX(self, t, xp):
        return dists.MvNormal(loc=xp @ self.A.T, cov=self.Q)

    def PY(self, t, xp, x):
        return dists.Normal(loc=x @ self.C[0], scale=np.sqrt(self.R[0, 0]))


def run(model, y, N, seed, moments=True):
    np.random.seed(seed)  # noqa: NPY002 - particles draws from numpy's global state
    fk = ssm.Bootstrap(ssm=model, data=list(y))
    pf = particles.SMC(fk=fk, N=N, resampling="systematic", ESSrmin=0.5,
                       collect=[Moments()] if moments else None)
    t0 = time.perf_counter()
    pf.run()
    wall = time.perf_counter() - t0
    means = [float(np.squeeze(m["mean"])) for m in pf.summaries.moments] if moments else []
    return means, float(pf.logLt), wall


def main(path):
    d = np.load(path)
    out = {"particles_version": getattr(particles, "__version__", "?"),
           "numpy": np.__version__}
    # speed on the linear Gaussian model
    lg = LinearGauss2(A=d["A"], C=d["C"], Q=d["Q"], R=d["R"], P0=d["P0"])
    speed = {}
    for N in [int(n) for n in d["speed_N"]]:
        walls = [run(lg, d["lg_y"][:, 0], N, s, moments=False)[2] for s in range(5)]
        speed[N] = float(np.median(walls))
    out["lg_seconds"] = speed
    # the growth model and stochastic volatility, one record per seed
    for name, make in (("ngm", lambda: ssm.Gordon_etal()),
                       ("sv", lambda: ssm.StochVol(mu=float(d["sv_mu"]), rho=float(d["sv_phi"]),
                                                   sigma=float(d["sv_sigma"])))):
        Y = d[f"{name}_y"]
        means, lls, walls = [], [], []
        for s in range(Y.shape[0]):
            m, ll, w = run(make(), Y[s], int(d[f"{name}_N"]), 1000 + s)
            means.append(m)
            lls.append(ll)
            walls.append(w)
        out[name] = {"means": means, "loglik": lls, "seconds": walls}
    print(json.dumps(out))


if __name__ == "__main__":
    main(sys.argv[1])
