"""Maximum-likelihood noise covariances: agreement with and time against statsmodels.

* Nile (the local level model of Durbin & Koopman, 100 annual flows): the maximum of
  statsmodels' ``UnobservedComponents(y, "llevel")`` likelihood (approximate diffuse
  prior, first term left out), found by Nelder-Mead on statsmodels' own ``loglike``
  tightly converged, against ``estim.tuning.maximum_likelihood`` on the same likelihood
  and against statsmodels' default ``fit()``; the time of a full fit of each, median of
  several runs in this process, and their ratio.
* van der Pol (``estim.scenarios.van_der_pol``, true Q = 0.1^2 I, R = I, 1000 samples):
  the fit's time and iterations, and the RMSE of an EKF tuned with the estimates against
  one with the true covariances on ten other seeds; ``mu`` estimated along from 0.5.

Run: ``python benchmarks/tuning.py [--runs 7]``. No assertions.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

import estim
from estim.tuning import maximum_likelihood


def median_time(fun, runs: int) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fun()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def nile(runs: int) -> None:
    import statsmodels.api as sm
    from scipy.optimize import minimize
    from statsmodels.datasets import nile as data

    y = data.load_pandas().data["volume"].to_numpy(dtype=float)
    ref = sm.tsa.UnobservedComponents(y, "llevel")
    default = ref.fit(disp=False)
    tight = minimize(lambda v: -ref.loglike(v), default.params, method="Nelder-Mead",
                     options={"xatol": 1e-10, "fatol": 1e-13, "maxiter": 20000})
    model = estim.Model(states=["level"], outputs=["volume"], dynamics=lambda x, u, p: x,
                        output=lambda x, u, p: x, name="local_level")
    res = maximum_likelihood(model, y, x0=0.0, P0=1e6, burn=1)
    print("Nile, local level model (T = 100): sigma2_eps, sigma2_eta, log L")
    rows = [("true maximum (Nelder-Mead on statsmodels' loglike)", *tight.x, -tight.fun),
            ("estim.tuning.maximum_likelihood", res.R[0, 0], res.Q[0, 0],
             -res.objective),
            ("statsmodels UnobservedComponents.fit() default", *default.params, default.llf)]
    for name, e, h, ll in rows:
        print(f"  {name:52s} {e:10.2f} {h:9.2f} {ll:.8f}")
    rel = np.abs(np.array([res.R[0, 0], res.Q[0, 0]]) / tight.x - 1)
    print(f"  estim vs true maximum: relative differences {rel[0]:.1e}, {rel[1]:.1e}; "
          f"standard errors {res.stderr['R'][0, 0]:.0f}, {res.stderr['Q'][0, 0]:.0f}")
    print(f"  estim: iterations per start {res.details['iterations']}, "
          f"polish {res.details['polish_iterations']}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_sm = median_time(lambda: ref.fit(disp=False), runs)
        t_es = median_time(lambda: maximum_likelihood(model, y, x0=0.0, P0=1e6, burn=1), runs)
        t_es1 = median_time(lambda: maximum_likelihood(model, y, x0=0.0, P0=1e6, burn=1,
                                                       starts=1), runs)
    print(f"  fit time (median of {runs}): statsmodels {t_sm * 1e3:.1f} ms, estim "
          f"{t_es * 1e3:.1f} ms with 5 starts (ratio {t_es / t_sm:.2f}), "
          f"{t_es1 * 1e3:.1f} ms with 1 start (ratio {t_es1 / t_sm:.2f})")


def van_der_pol() -> None:
    sc = estim.scenarios.van_der_pol(n_steps=1000)
    log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)
    kw = {"x0": sc.tuning["x0"], "P0": sc.tuning["P0"], "Q0": [0.05, 0.05], "R0": [0.5, 0.5]}
    print("van der Pol (T = 1000, true Q = 0.01 I, R = I)")
    for kind in ("ekf", "ukf"):
        res = maximum_likelihood(sc.model, log.y, estimator=kind, **kw)
        d = res.details
        print(f"  {kind}: Q = {np.diag(res.Q).round(4)}, R = {np.diag(res.R).round(3)}; "
              f"{d['fit_time']:.2f} s (graph {d['compile_time']:.2f} s), iterations per "
              f"start {d['iterations']}, polish {d['polish_iterations']}, "
              f"{d['evaluations']} evaluations")
        if kind == "ekf":
            fitted = res

    def rmse(Q, R):
        out = []
        for seed in range(1, 11):
            run = estim.simulate(sc, estim.EKF(sc.model, Q=Q, R=R, x0=sc.tuning["x0"],
                                               P0=sc.tuning["P0"]), seed=seed)
            out.append(np.sqrt(np.mean((run.x_hat - run.x) ** 2)))
        return float(np.mean(out))

    a, b = rmse(sc.Q, sc.R), rmse(fitted.Q, fitted.R)
    print(f"  EKF RMSE on seeds 1-10: true covariances {a:.4f}, ML estimates {b:.4f} "
          f"(ratio {b / a:.4f})")
    for kind in ("ekf", "ukf"):
        res = maximum_likelihood(sc.model.with_params(mu=0.5), log.y, estimator=kind,
                                 params=["mu"], starts=1, **kw)
        print(f"  {kind}, mu from 0.5: {res.params['mu']:.3f} ± "
              f"{res.stderr['params']['mu']:.3f} ({res.details['fit_time']:.2f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    nile(args.runs)
    van_der_pol()


if __name__ == "__main__":
    main()
