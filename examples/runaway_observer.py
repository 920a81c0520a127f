r"""Runaway electrons: the shooting observer identifies (gamma, gamma1), with and without dy/dt.

Oliva & Carnevale's report, sec. 2.5 (seed 004, ``models.md`` sec. 4). The
runaway-electron model, augmented with its parameters :math:`(\gamma,
\gamma_1)` as constant states, is measured through :math:`y = x_2` with noise
std 1e-4 at :math:`T_s = 5\cdot10^{-4}` s (``estim.scenarios.runaway``, 8000
steps = 4 s, seed 0). ``estim.ShootingObserver`` buffers ``w = 10`` samples
every ``N_Ts = 20`` steps (a window of 0.09 s) and, each time a new sample
enters the full buffer, fits the augmented state at the window's start by BFGS
(the report's ``fminunc``), with ``resolution=0.003``. It runs without the
measurement-derivative term (``derivative_weight=0.0``, report sec. 2.5.1) and
with it, balanced against the output term on the first window
(``derivative_weight=None``, sec. 2.5.2), from two starts: the report's guess
:math:`(-0.0001, 0.0006, 0.5004, 2.4886)` (eq. 2.13, about 1e-3 relative on
the parameters) and a harder one with the parameters 5 % off,
:math:`(\gamma, \gamma_1) = (0.525, 2.375)` (truth 0.5, 2.5).

What this run measured (seed 0; "settle": the last time either parameter's
relative error is >= 1 %, 0 if never; mean error :math:`\bar e` of
:math:`x - \hat x` over the 4 s; "rel. after 2 s": the mean of the two
parameters' relative errors over 2-4 s; ms: median wall time of an
optimisation step on one 2-CPU x86_64 machine):

=================  =======  ======================================  =========  ====  ======
start, dy/dt term  settle   mean error (x1, x2, gamma, gamma1)      rel. >2 s  ms    failed
=================  =======  ======================================  =========  ====  ======
report, none       0 s      (-5.1e-05, 3.6e-06, 1.0e-04, 1.3e-03)   7.4e-04    1.3   0
report, balanced   0 s      (-5.4e-05, 5.0e-06, 1.2e-04, 1.3e-03)   7.5e-04    1.3   0
5 %, none          0.30 s   (4.5e-04, -3.6e-05, -1.5e-03, 1.0e-02)  7.4e-04    1.3   0
5 %, balanced      0.30 s   (4.5e-04, -3.4e-05, -1.5e-03, 1.0e-02)  7.5e-04    1.3   0
report eq. 2.15    30 s *   (3.8e-04, -9.3e-06, 2.2e-04, 1.3e-03)   —          —     —
report eq. 2.20    2 s *    (7.6e-04, 2.2e-06, 3.4e-03, 2.0e-02)    —          —     —
=================  =======  ======================================  =========  ====  ======

\* the report's own runs (without / with the derivative term; the second from
its guess of eq. 2.18), its "time to estimate the parameters correctly"; the
sign convention of its :math:`\bar e` is not stated.

* From the report's guess both configurations stay within 1 % all along (the
  parameters start 0.08 % and 0.46 % off). From the 5 % guess both settle at
  the first burst (peak at 0.287 s): the optimisation at 0.30 s, whose window
  (0.21-0.30 s, shaded in panel (a)) holds the burst's rise and peak, puts both
  parameters within 1 % and they stay there. Over 2-4 s the relative error
  averages 7.4e-4 and never exceeds 0.4 %, whatever the start.
* The derivative term makes no measurable difference: the two
  configurations' parameter estimates differ by at most 0.05 % (relative)
  over the run, and settle at the same sample. So the report's "2 s with the
  derivative against 30 s without" is **not** reproduced: here one burst is
  enough without it. Two likely reasons (this script does not separate
  them): the BFGS is preconditioned with the Gauss-Newton Hessian of the
  window and only moves along the directions the window determines to
  ``resolution`` (so the burst window's information is used at once, and
  uninformative windows do not push the parameters around); and the
  balanced weight is tiny, :math:`W_2/W_1 \approx 7\cdot10^{-8}`, because the
  numerical derivative of a signal with noise 1e-4 at 5e-4 s is noisy (std
  about 0.22 for the 5-sample differentiator, against 1e-4 on y), so "equal
  magnitude" on the first window leaves the derivative residuals almost no
  weight in the Hessian.
* Our mean errors are of the report's order. That of gamma1 from the
  report's guess, 1.32e-3, is close to eq. 2.15's 1.31e-3, but this is a
  coincidence of the run length: most of ours (8.5e-4) is the guess's offset
  (0.46 %) held for the 0.3 s before the first burst, averaged over 4 s. The
  5 % start's larger means likewise come from its first 0.3 s.
* The window condition number (relative output sensitivity,
  ``info.extra["condition"]``; its square is the Fisher information's) is
  4e6 to 6e10 (median about 1e9) in the quiet windows before the first
  burst, where x2 decays from the initial 1e-3 to 1e-7, below the noise: the
  parameters are not identifiable there and the observer keeps the
  propagated estimate. Windows holding the first burst's onset are also
  badly conditioned (about 5e7), presumably because the onset time depends
  on the logarithm of the tiny x2 at the window's start. On the limit cycle
  that follows, x2 never falls below 3e-3 (30 times the noise) and every
  window is informative: 90 to 1e4, median 2.7e2, the worst (about 1e4)
  being the windows that end on a burst's rise, the best (about 90) those
  ending in the slow rise before a burst. The contrast between burst
  windows and quiet ones (``models.md``: identifiable only from windows that
  contain a burst) is thus a feature of the start-up, not of every interval
  between bursts.
* An optimisation step costs about 1.3 ms; no step failed. The script runs
  in about 5 s.
* Seeds 1 and 2 (``--seed``) give the same picture: settling at 0 s and
  0.30 s, mean relative error over 2-4 s 8.2e-4 to 8.4e-4, no failed step,
  :math:`W_2/W_1` 2e-7 to 3e-7.

The figure (``--out``, default ``runaway_observer.png``) shows (a) the
measured y and the buffered samples (every 20th) over the first second,
(b) x1 and x2 against the estimates from the 5 % start, (c) the parameter
estimates of all four runs against the truth, (d) the window condition
number over time (log scale). Run ``python examples/runaway_observer.py``;
``main()`` returns the numbers as a dict.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import estim  # noqa: E402

WINDOW, EVERY, RESOLUTION = 10, 20, 0.003
TOLERANCE = 0.01  # relative parameter error for "settled"
AFTER = 2.0  # s: mean relative parameter error from here on
CYCLE = 0.5  # s: on the limit cycle from here on (after the first burst)
#: The report's mean errors (eqs. 2.15 and 2.20; x1, x2, gamma, gamma1).
REPORT_MEAN_ERROR = {
    "none": np.array([3.7966e-04, -9.3456e-06, 2.2238e-04, 1.3079e-03]),
    "balanced": np.array([7.5779e-04, 2.2452e-06, 3.3596e-03, 1.9828e-02]),
}
#: derivative_weight of each configuration: 0 removes the term, None balances it.
DERIVATIVE = {"none": 0.0, "balanced": None}
LABELS = {"report": "report guess", "hard": "5 % guess"}
COLORS = {("report", "none"): "tab:blue", ("report", "balanced"): "tab:cyan",
          ("hard", "none"): "tab:red", ("hard", "balanced"): "tab:orange"}


def guesses(sc: estim.Scenario) -> dict[str, np.ndarray]:
    """The report's guess (eq. 2.13) and the same with (gamma, gamma1) 5 % off the truth."""
    report = np.asarray(sc.tuning["x0"], float)
    hard = report.copy()
    hard[2:] = sc.x0[2:] * np.array([1.05, 0.95])
    return {"report": report, "hard": hard}


def summary(log: estim.Log, history: list[dict]) -> dict:
    """Settling time, mean errors, timing, failures and condition numbers of one run."""
    rel = np.abs(log.x_hat[:, 2:] - log.x[:, 2:]) / np.abs(log.x[:, 2:])
    bad = np.flatnonzero((rel >= TOLERANCE).any(axis=1))
    k, cond, solve_time, success, w2 = (
        np.array([h[f] for h in history])
        for f in ("k", "condition", "solve_time", "success", "derivative_weight"))
    # the largest true x2 among each window's buffered samples (k - span, ..., k)
    span = (WINDOW - 1) * EVERY
    peak = np.array([log.x[j - span:j + 1:EVERY, 1].max() for j in k])
    quiet = peak < 1e-3  # only before the first burst: x2 decays from 1e-3 below the noise
    cycle = k * log.dt >= CYCLE
    after = log.t >= AFTER
    return {
        "settling_time": float(log.t[bad[-1]]) if len(bad) else 0.0,
        "mean_error": (log.x - log.x_hat).mean(axis=0),
        "max_rel_error": float(rel.max()),
        "mean_rel_error_after": float(rel[after].mean()) if after.any() else float("nan"),
        "max_rel_error_after": float(rel[after].max()) if after.any() else float("nan"),
        "ms_per_optimisation": float(np.median(solve_time) * 1e3),
        "failed_steps": int((~success.astype(bool)).sum()),
        "derivative_weight": float(w2[-1]),
        "k": k, "condition": cond,
        "condition_quiet": np.percentile(cond[quiet], [0, 50, 100]).tolist(),
        "condition_cycle": np.percentile(cond[cycle], [0, 50, 100]).tolist(),
    }


def plot(logs: dict, results: dict, out: str) -> None:
    """(a) windowed data, (b) x1, x2, (c) gamma, gamma1, (d) condition numbers."""
    ref = logs[("hard", "none")]
    t = ref.t
    fig, ax = plt.subplot_mosaic([["a", "a"], ["x1", "x2"], ["g", "g1"], ["d", "d"]],
                                 figsize=(10, 11), constrained_layout=True)
    # (a) the measurement and the samples the buffer holds
    first = t <= 1.0
    buffered = first & (np.arange(len(t)) % EVERY == 0)
    ax["a"].plot(t[first], ref.y[first, 0], color="0.6", lw=0.6, label="y (every sample)")
    ax["a"].plot(t[buffered], ref.y[buffered, 0], "o", ms=2.5, color="tab:blue",
                 label=f"buffered (every {EVERY}th)")
    k_settle = int(round(0.30 / ref.dt))
    ax["a"].axvspan(t[k_settle - (WINDOW - 1) * EVERY], t[k_settle], color="tab:green",
                    alpha=0.15, label=f"window of the optimisation at {t[k_settle]:.2f} s")
    ax["a"].set_ylabel("y = x2")
    ax["a"].set_title("(a) windowed data, first second", fontsize="medium", loc="left")
    ax["a"].legend(loc="upper right", fontsize="small")
    # (b) the states, truth against the 5 % start
    for i, key in ((0, "x1"), (1, "x2")):
        ax[key].plot(t, ref.x[:, i], color="black", lw=2, label="truth")
        for d in DERIVATIVE:
            ax[key].plot(t, logs[("hard", d)].x_hat[:, i], lw=1, ls="-" if d == "none" else "--",
                         color=COLORS[("hard", d)], label=f"5 % guess, dy/dt {d}")
        ax[key].set_ylabel(key)
        ax[key].set_title(f"(b) {key}", fontsize="medium", loc="left")
    ax["x1"].legend(loc="upper right", fontsize="small")
    # (c) the parameters
    for i, (key, name) in ((2, ("g", "gamma")), (3, ("g1", "gamma1"))):
        truth = ref.x[0, i]
        ax[key].axhline(truth, color="black", lw=2, label="truth")
        for (start, d), log in logs.items():
            ax[key].plot(t, log.x_hat[:, i], lw=1, ls="-" if d == "none" else "--",
                         color=COLORS[(start, d)], label=f"{LABELS[start]}, dy/dt {d}")
        ax[key].axhspan(truth * (1 - TOLERANCE), truth * (1 + TOLERANCE), color="0.85",
                        zorder=0, label="±1 %")
        ax[key].set_ylim(truth * 0.93, truth * 1.07)
        ax[key].set_ylabel(name)
        ax[key].set_title(f"(c) {name}", fontsize="medium", loc="left")
    ax["g"].legend(loc="upper right", fontsize="x-small")
    # (d) the window condition number
    for (start, d), r in results.items():
        if d == "none":
            ax["d"].semilogy(r["k"] * ref.dt, r["condition"], ".-", ms=2, lw=0.5,
                             color=COLORS[(start, d)], label=f"{LABELS[start]}, dy/dt {d}")
    ax["d"].set_ylabel("window condition")
    ax["d"].set_title("(d) condition number of the window's relative output sensitivity",
                      fontsize="medium", loc="left")
    ax["d"].legend(loc="upper right", fontsize="small")
    for key in ("x1", "x2", "g", "g1", "d"):
        ax[key].set_xlabel("time [s]")
        ax[key].grid(True, alpha=0.3)
    ax["a"].grid(True, alpha=0.3)
    fig.suptitle(f"Runaway electrons: shooting observer, w = {WINDOW}, N_Ts = {EVERY}, "
                 f"BFGS, resolution {RESOLUTION:g}")
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    """Run both configurations from both guesses, print the table, write the figure."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="runaway_observer.png", help="PNG to write")
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    parser.add_argument("--steps", type=int, default=8000,
                        help="samples of 5e-4 s (> 2 s = 4000 for the error after 2 s)")
    args = parser.parse_args(argv)
    if args.steps * 5e-4 <= 1.0:
        parser.error("--steps must cover more than 1 s (2000 steps)")

    sc = estim.scenarios.runaway(n_steps=args.steps)
    logs, results = {}, {}
    for start, x0 in guesses(sc).items():
        for d, weight in DERIVATIVE.items():
            obs = estim.ShootingObserver(sc.model, window=WINDOW, every=EVERY, R=sc.R, x0=x0,
                                    resolution=RESOLUTION, derivative_weight=weight)
            logs[(start, d)] = estim.simulate(sc, obs, seed=args.seed)
            results[(start, d)] = summary(logs[(start, d)], obs.history)

    print(f"runaway electrons, seed {args.seed}, {args.steps} steps of {sc.model.dt:g} s, "
          f"w = {WINDOW}, N_Ts = {EVERY}, BFGS, resolution {RESOLUTION:g}")
    head = (f"{'start':<13} {'dy/dt':<9} {'settle [s]':>10}  "
            f"{'mean error x - x̂ (x1, x2, gamma, gamma1)':<44} {'rel >2 s':>9} "
            f"{'ms/opt':>7} {'failed':>6} {'W2/W1':>8}")
    print(head)
    print("-" * len(head))
    for (start, d), r in results.items():
        err = ", ".join(f"{e:9.2e}" for e in r["mean_error"])
        print(f"{LABELS[start]:<13} {d:<9} {r['settling_time']:>10.4f}  ({err}) "
              f"{r['mean_rel_error_after']:>9.2e} {r['ms_per_optimisation']:>7.2f} "
              f"{r['failed_steps']:>6d} {r['derivative_weight']:>8.2g}")
    for d, eq in (("none", "2.15"), ("balanced", "2.20")):
        err = ", ".join(f"{e:9.2e}" for e in REPORT_MEAN_ERROR[d])
        print(f"{'report':<13} {d:<9} {'':>10}  ({err})  eq. {eq}")
    diff = max(float(np.max(np.abs(logs[(s, "none")].x_hat[:, 2:]
                                   - logs[(s, "balanced")].x_hat[:, 2:]) / sc.x0[2:]))
               for s in LABELS)
    print(f"settle: last time a parameter is >= {TOLERANCE:.0%} off (0: never); rel >2 s: "
          f"mean relative parameter error after {AFTER:g} s")
    print(f"largest relative difference of the parameter estimates with and without the "
          f"derivative term: {diff:.2e}")
    for (start, d), r in results.items():
        if d == "none":
            q, c = r["condition_quiet"], r["condition_cycle"]
            print(f"window condition ({LABELS[start]}): quiet windows before the first burst "
                  f"(x2 < 1e-3) {q[0]:.1e} to {q[2]:.1e} (median {q[1]:.1e}); on the limit "
                  f"cycle (t >= {CYCLE:g} s) {c[0]:.1e} to {c[2]:.1e} (median {c[1]:.1e})")
    plot(logs, results, args.out)
    print(f"wrote {args.out}")
    out = {"seed": args.seed, "n_steps": args.steps, "out": args.out,
           "max_relative_difference_derivative": diff,
           "report_mean_error": {d: e.tolist() for d, e in REPORT_MEAN_ERROR.items()}}
    for (start, d), r in results.items():
        out[f"{start}_{d}"] = {key: (val.tolist() if key == "mean_error" else val)
                               for key, val in r.items() if key not in ("k", "condition")}
    return out


if __name__ == "__main__":
    main()
