"""PyNOA's observability examples, analysed with the correct ranks (seed 003).

For each system the script prints the rank of the observability matrix, the
singular-value gap that decided it, the classification of the states and the
time, and draws the singular values (row-normalised, log scale) so the gap is
visible. Measured here (2 cores): Martinelli's simple localisation rank 2 of 3,
D observable, (phi_R, theta_R) jointly observable; odometry calibration,
non-circular trajectory rank 7 of 7; circular trajectory rank 4 of 5 with only
xi_q observable (PyNOA prints 5 because it substitutes floating-point numbers
before an exact-arithmetic rank); the 33-state quadrotor of Ko et al. (2019)
with IMU, GNSS and barometer rank 31 of 33, the two scale symmetries of its
parameters (PyNOA prints 33). Each small example takes 5-40 ms, the quadrotor
about 0.2-0.6 s.

Run ``python examples/observability_pynoa.py [--out observability.png]``.
"""

from __future__ import annotations

import argparse

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import estim  # noqa: E402
from estim.observability import analyze  # noqa: E402

SYSTEMS = {
    "simple localisation": (estim.models.martinelli_simple, {}),
    "odometry, non-circular": (estim.models.odometry_noncircular, {}),
    "odometry, circular": (estim.models.odometry_circular, {}),
    "quadrotor IMU+GNSS+baro": (estim.models.quadrotor_ko2019, {"order": 2}),
}


def main(argv: list[str] | None = None) -> dict:
    """Analyse every system, print the table, write the figure; return the ranks."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="observability.png", help="PNG to write")
    args = parser.parse_args(argv)
    reports = {name: analyze(factory(), **kw) for name, (factory, kw) in SYSTEMS.items()}
    print(f"{'system':<26}{'rank':>9}{'gap':>10}{'ms':>8}  classification")
    for name, rep in reports.items():
        joint = "; ".join("(" + ", ".join(g) + ")" for g in rep.jointly_observable)
        cls = (f"observable: {', '.join(rep.observable) or '-'}"
               + (f" | jointly: {joint}" if joint else "")
               + (f" | unobservable: {', '.join(rep.unobservable)}" if rep.unobservable else ""))
        if len(cls) > 90:
            cls = cls[:87] + "..."
        print(f"{name:<26}{rep.rank:>4} of {rep.n:<3}{rep.gap:>10.2g}{rep.seconds * 1e3:>8.1f}  "
              f"{cls}")
    fig, axes = plt.subplots(1, len(reports), figsize=(3.2 * len(reports), 3.4),
                             constrained_layout=True)
    for ax, (name, rep) in zip(axes, reports.items(), strict=True):
        s = np.maximum(rep.singular_values, 1e-18)
        colors = ["tab:blue" if i < rep.rank else "tab:red" for i in range(len(s))]
        ax.bar(np.arange(1, len(s) + 1), s, color=colors)
        ax.set_yscale("log")
        ax.set_ylim(1e-18, 10)
        ax.set_title(f"{name}\nrank {rep.rank} of {rep.n}", fontsize="small")
        ax.set_xlabel("singular value index")
    axes[0].set_ylabel("singular value (rows normalised)")
    fig.savefig(args.out, dpi=110)
    plt.close(fig)
    print(f"wrote {args.out}")
    return {name: rep.rank for name, rep in reports.items()}


if __name__ == "__main__":
    main()
