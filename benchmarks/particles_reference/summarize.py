#!/usr/bin/env python
"""Summarise benchmarks/results/particles_pmmh_lingauss.json (written by
pmmh_lingauss_particles.py) as a Markdown table.

Plain Python 3 (no particles needed).  Besides the raw pooled acceptance rate
(particles' ``acc_rate`` = nacc/(niter-1), pooled over chains), it flags chains
that had not reached the posterior bulk: a chain is flagged "stuck" if, after
the 10% burn-in, the posterior mean of some parameter is more than 5 posterior
SDs away from the median (over chains) of the exact-likelihood ('mh') chains.  Such
chains typically start from a prior draw far in the InvGamma tail (e.g.
varY ~ 40) where the likelihood is flat, and then accept almost everything.

Usage:  python3 summarize.py [in.json] [out.md]
"""
import json
import os
import statistics as st
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
inp = sys.argv[1] if len(sys.argv) > 1 else os.path.join(
    REPO, "benchmarks", "results", "particles_pmmh_lingauss.json")
out = sys.argv[2] if len(sys.argv) > 2 else os.path.join(
    REPO, "benchmarks", "results", "particles_pmmh_lingauss_table.md")

R = json.load(open(inp))
per = R["per_nx"]
params = ["rho", "varX", "varY"]

ref = None
if per.get("mh"):
    mh = per["mh"]
    ref = {p: (st.median(c["post_mean"][p] for c in mh),
               st.median(c["post_sd"][p] for c in mh)) for p in params}


def stuck(c):
    if ref is None:
        return False
    return any(abs(c["post_mean"][p] - ref[p][0]) > 5 * ref[p][1] for p in params)


lines = []
s = R["settings"]
lines.append("# particles %s PMMH lingauss reference (book/pmcmc/pmmh_lingauss.py)\n"
             % R["particles_version"])
lines.append("niter=%d per chain, chains=%d, burn-in=%d, numpy %s, complete=%s\n"
             % (s["niter"], s["chains"], s["burnin"], R["numpy_version"],
                R["complete"]))
if ref:
    lines.append("Exact-likelihood RWHM posterior (median over chains of post-burn-in "
                 "means; median SD): " + ", ".join(
                     "%s=%.4f (sd %.4f)" % (p, ref[p][0], ref[p][1]) for p in params)
                 + "\n")
lines.append("| alg | Nx | pooled acc | min | max | median | iters/chain | chains "
             "| s/iter | stuck chains | pooled acc excl. stuck | pooled acc after "
             "burn-in excl. stuck |")
lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
for k, chains in per.items():
    if not chains:
        continue
    rates = [c["acc_rate"] for c in chains]
    nacc = sum(c["nacc"] for c in chains)
    nst = sum(c["niter"] - 1 for c in chains)
    good = [c for c in chains if not stuck(c)]
    nacc_g = sum(c["nacc"] for c in good)
    nst_g = sum(c["niter"] - 1 for c in good)
    nacc_gb = sum(round(c["acc_rate_after_burnin"] * (c["niter"] - 1 - c["burnin"]))
                  for c in good)
    nst_gb = sum(c["niter"] - 1 - c["burnin"] for c in good)
    secs = sum(c["wall_seconds"] for c in chains) / sum(c["niter"] for c in chains)
    iters = sorted(set(c["niter"] for c in chains))
    nx = chains[0]["Nx"] or "exact (Kalman)"
    lines.append("| %s | %s | %.4f | %.4f | %.4f | %.4f | %s | %d | %.4f | %s | %s | %s |" % (
        k, nx, nacc / nst, min(rates), max(rates), st.median(rates),
        ",".join(map(str, iters)), len(chains), secs,
        ", ".join("c%d(acc %.2f, varY %.2f, varX %.2f)" % (
            c["chain"], c["acc_rate"], c["post_mean"]["varY"], c["post_mean"]["varX"])
            for c in chains if stuck(c)) or "-",
        "%.4f" % (nacc_g / nst_g) if nst_g else "-",
        "%.4f" % (nacc_gb / nst_gb) if nst_gb else "-"))
txt = "\n".join(lines) + "\n"
print(txt)
with open(out, "w") as f:
    f.write(txt)
