"""Outliers: robust MHE costs and the EKF/UKF NIS gate on van der Pol.

The van der Pol scenario of MPCTools (``estim.scenarios.van_der_pol()``: RK4 at
0.1 s, both states measured with unit noise, process noise std 0.1), 200 steps
per seed. In the contaminated records 5 % of the measured values (each value
independently) are replaced by the true output plus or minus 100 standard
deviations. Every estimator is run on the clean and on the contaminated record
of each seed; the RMSE of the state (both components, steps 20-199) is averaged
over the seeds, and the column "ratio" is the contaminated RMSE over the
outlier-free RMSE of the same estimator's least-squares form (the plain EKF for
the filters, the least-squares MHE for the MHEs). "ms/step" is the median over
the seeds of the median step time (``info.solve_time``: the whole step, without
building the estimator); "flagged" the share of the contaminated records' steps
whose status is not "ok".

    python benchmarks/robust.py [--seeds 20] [--solver gauss-newton]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np

import estim

TUNING = dict(Q=0.01, R=1.0, x0=[0.0, 0.0], P0=1.0)


def records(seed: int, T: int = 200, rate: float = 0.05):
    m = estim.models.van_der_pol()
    log = estim.simulate(m, estim.EKF(m, **TUNING), x0=[1.5, 1.5], n_steps=T, Q=0.01,
                         R=1.0, seed=seed)
    X, Y = log.x, log.y
    rng = np.random.default_rng(1000 + seed)
    mask = rng.random(Y.shape) < rate
    Yo = Y.copy()
    Yo[mask] = X[mask] + 100.0 * rng.choice([-1.0, 1.0], size=mask.sum())
    return m, X, Y, Yo


def estimators(m, solver: str):
    yield "EKF", "EKF", lambda: estim.EKF(m, **TUNING)
    yield "EKF, gate 1e-6", "EKF", lambda: estim.EKF(m, gate=1e-6, **TUNING)
    yield "UKF, gate 1e-6", "EKF", lambda: estim.UKF(m, gate=1e-6, **TUNING)
    for loss in ("squared", "huber", "soft_l1", "cauchy"):
        yield (f"MHE-15 {loss}", "MHE-15 squared",
               lambda loss=loss: estim.MHE(m, horizon=15, solver=solver, loss=loss, **TUNING))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--solver", default="gauss-newton")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", estim.EstimationWarning)
    rows: dict[str, dict] = {}
    for seed in range(args.seeds):
        m, X, Y, Yo = records(seed)
        for name, ref, make in estimators(m, args.solver):
            row = rows.setdefault(name, {"ref": ref, "clean": [], "outliers": [],
                                         "ms clean": [], "ms outliers": [], "flagged": []})
            est = make()  # replay resets it: one estimator serves both records
            for data, YY in (("clean", Y), ("outliers", Yo)):
                log = estim.replay(est, YY, None, X)
                e = log.x_hat[20:] - X[20:]
                row[data].append(np.sqrt(np.mean(np.sum(e ** 2, axis=1))))
                row[f"ms {data}"].append(1e3 * np.median(log.solve_time))
                if data == "outliers":
                    row["flagged"].append(np.mean(log.status != "ok"))
    print(f"van der Pol, {args.seeds} seeds x 200 steps, 5 % of the values 100 sigma off "
          f"(MHE solver: {args.solver})\n")
    print("| estimator | RMSE clean | RMSE outliers (mean / median) | ratio | "
          "ms/step clean / outliers | flagged |")
    print("|---|---|---|---|---|---|")
    for name, row in rows.items():
        base = np.mean(rows[row["ref"]]["clean"])
        mean, med = np.mean(row["outliers"]), np.median(row["outliers"])
        print(f"| {name} | {np.mean(row['clean']):.4f} | {mean:.4g} / {med:.4g} | "
              f"{mean / base:.3g} | {np.median(row['ms clean']):.3f} / "
              f"{np.median(row['ms outliers']):.3f} | "
              f"{100 * np.mean(row['flagged']):.1f} % |")


if __name__ == "__main__":
    main()
