"""Monte Carlo coverage of the parameters' Laplace confidence intervals.

For each case, every seed simulates the model with the true parameters, adds
measurement noise of the covariance ``R`` the estimator is given, fits the augmented
model with ``FullInformation.fit`` from a wrong guess (parameters 30 % off, states
from zero), and checks whether each parameter's 95 % interval
(``res.parameters().interval(0.95)``) holds the truth. A correct interval covers it
in 95 % of the seeds, within the binomial standard error
:math:`\\sqrt{0.95 \\cdot 0.05 / n}`. Also printed: the mean standard error against
the empirical standard deviation of the estimates over the seeds (equal when the
Laplace covariance is right), the joint coverage of the 95 % ellipsoid
:math:`(\\hat\\theta - \\theta)^\\top \\Sigma_\\theta^{-1} (\\hat\\theta - \\theta) \\le
\\chi^2_{n,0.95}` (which checks the correlations too), and the time per fit.

Cases:

* ``first order``: :math:`\\dot x = (K u - x)/\\tau`, :math:`y = x`, ``tau = 1``,
  ``K = 2``, a square wave input of period 5 s, 100 samples of 0.1 s, noise std 0.05;
  no process noise in the plant, the estimator's ``Q`` at :math:`10^{-12}` of each
  state's squared scale (an output-error fit).
* ``van der pol``: ``mu = 1`` of :func:`estim.models.van_der_pol`, both states
  measured (std 0.1), 100 samples from ``(2, 0)``, no process noise, ``Q`` as above.
* ``first order, process noise``: the first case with process noise of std 0.02 on
  the state in the plant and the same ``Q`` in the estimator (a smoothing problem:
  the parameters' covariance is that of the joint maximum a posteriori trajectory).

Run: ``python benchmarks/coverage.py [--seeds 1000]``. No assertions.
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np
from scipy import stats

import estim

#: The parameters' process noise, relative to their squared magnitude: over 100
#: samples the random walk moves them by sqrt(100 * 1e-12) = 1e-5 of their value,
#: a thousandth of their standard errors here: a constant parameter.
Q_PARAMETER = 1e-12


def first_order() -> estim.Model:
    """dx/dt = (K u - x) / tau, y = x."""
    return estim.Model(states=["x"], outputs=["y"], inputs=["u"],
                       ode=lambda x, u, p: (p["K"] * u[0] - x[0]) / p["tau"],
                       output=lambda x, u, p: x[0], params={"tau": 1.0, "K": 2.0},
                       dt=0.1, name="first_order")


def cases() -> list[dict]:
    T = 100
    square = np.where((np.arange(T - 1) // 25) % 2 == 0, 1.0, -1.0)[:, None]
    fo = first_order().augment("tau", "K")
    vdp = estim.models.van_der_pol().augment("mu")
    return [
        {"name": "first order", "model": fo, "x0": [0.0, 1.0, 2.0], "U": square,
         "R": 0.05**2, "Q": Q_PARAMETER * np.array([1.0, 1.0, 4.0]), "Q_plant": 0.0},
        {"name": "van der pol", "model": vdp, "x0": [2.0, 0.0, 1.0], "U": None,
         "R": 0.1**2, "Q": Q_PARAMETER * np.array([4.0, 4.0, 1.0]), "Q_plant": 0.0},
        {"name": "first order, process noise", "model": fo, "x0": [0.0, 1.0, 2.0],
         "U": square, "R": 0.05**2, "Q": np.array([0.02**2, Q_PARAMETER, 4 * Q_PARAMETER]),
         "Q_plant": 0.02**2},
    ]


def simulate(model, x0, U, T, R, Q_plant, rng):
    """Outputs of the plant: process noise on the physical states only."""
    n_theta = len(model.augmented)
    nxp = model.nx - n_theta
    x, X = np.asarray(x0, float), []
    for k in range(T):
        X.append(x)
        if k < T - 1:
            x = model.f(x, None if U is None else U[k])
            if Q_plant:
                x = x + np.concatenate([np.sqrt(Q_plant) * rng.standard_normal(nxp),
                                        np.zeros(n_theta)])
    Y = np.array([model.h(x) for x in X])
    return Y + np.sqrt(R) * rng.standard_normal(Y.shape)


def study(case: dict, seeds: int, T: int = 100, level: float = 0.95) -> dict:
    """Coverage of one case over ``seeds`` seeds."""
    m = case["model"]
    truth = np.asarray(case["x0"], float)
    n_theta = len(m.augmented)
    theta = truth[-n_theta:]
    guess = np.concatenate([np.zeros(m.nx - n_theta), 0.7 * theta])
    fie = estim.FullInformation(m, Q=case["Q"], R=case["R"], x0=guess)
    q = stats.norm.ppf(0.5 + level / 2)
    chi2 = stats.chi2.ppf(level, n_theta)
    est, se, hit, joint, failed, times = [], [], [], [], 0, []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        Y = simulate(m, truth, case["U"], T, case["R"], case["Q_plant"], rng)
        t0 = time.perf_counter()
        res = fie.fit(Y, case["U"])
        if not res.success:
            failed += 1
            hit.append(np.zeros(n_theta, bool))
            joint.append(False)
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", estim.EstimationWarning)
            pe = res.parameters()
        times.append(time.perf_counter() - t0)
        err = pe.value - theta
        est.append(pe.value)
        se.append(pe.stderr)
        hit.append(np.abs(err) <= q * pe.stderr)
        joint.append(float(err @ np.linalg.solve(pe.covariance, err)) <= chi2)
    est, se, hit = np.array(est), np.array(se), np.array(hit)
    return {"names": list(m.augmented), "coverage": hit.mean(axis=0),
            "joint": float(np.mean(joint)), "mean_stderr": se.mean(axis=0),
            "spread": est.std(axis=0, ddof=1), "bias": est.mean(axis=0) - theta,
            "failed": failed, "time": float(np.median(times)), "seeds": seeds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=1000)
    args = parser.parse_args()
    n = args.seeds
    se_binomial = np.sqrt(0.95 * 0.05 / n)
    print(f"95 % intervals over {n} seeds; binomial standard error of a coverage "
          f"{100 * se_binomial:.2f} % (95 ± 3 % is ± {3 / (100 * se_binomial):.1f} "
          f"standard errors)")
    t_start = time.perf_counter()
    for case in cases():
        r = study(case, n)
        print(f"\n{case['name']} ({r['failed']} failed fits, median fit + covariance "
              f"{1e3 * r['time']:.2f} ms); joint {len(r['names'])}-parameter ellipsoid "
              f"covers {100 * r['joint']:.1f} %")
        print(f"  {'':6} {'coverage %':>11} {'mean stderr':>12} {'empirical sd':>13} "
              f"{'ratio':>6} {'bias':>10}")
        for i, name in enumerate(r["names"]):
            print(f"  {name:6} {100 * r['coverage'][i]:11.1f} {r['mean_stderr'][i]:12.4g} "
                  f"{r['spread'][i]:13.4g} {r['mean_stderr'][i] / r['spread'][i]:6.3f} "
                  f"{r['bias'][i]:10.2g}")
    print(f"\n{time.perf_counter() - t_start:.1f} s in all "
          f"(the ratio's own sampling error: {100 / np.sqrt(2 * (n - 1)):.1f} %)")


if __name__ == "__main__":
    main()
