"""One submission per exercise that is wrong on purpose, and the feedback it gets.

Each mistake is a change to the solution's code (``old`` replaced by ``new`` in the
submitted notebook), made the way a student would make it. ``python mistakes.py``
builds every exercise, grades its mistaken submission and prints the points per part and
the messages; ``tests/test_course_series.py`` (``-m slow``) checks that each message
names what ``expect`` says.

    python mistakes.py [NAME ...] [--out dist]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import course


@dataclass(frozen=True)
class Mistake:
    """A change to exercise ``name``'s solution code, what it is, and the words the
    feedback must contain."""
    name: str
    what: str
    old: str
    new: str
    expect: tuple[str, ...]


MISTAKES = [
    Mistake("01_kalman_filter", "the prediction forgets Q",
            "P_pred = A @ P @ A.T + Q", "P_pred = A @ P @ A.T",
            ("the covariance P differs first at sample 1", "A P Aᵀ + Q", "overconfident")),
    Mistake("02_ekf_pendulum", "the innovation linearised: y - H m instead of y - h(m)",
            "m_new = m + K @ (y - h(m))", "m_new = m + K @ (y - H @ m)",
            ("the updated mean differs first", "eq. (6): m + K (y - h(m))",
             "the estimate x̂ differs first at sample 2", "the covariance P is still right")),
    Mistake("03_ukf_sigma_points", "the covariance weight of the centre point without "
            "1 - alpha² + beta",
            "Wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)", "Wc[0] = lam / (n + lam)",
            ("the vector of covariance weights W(c) (n = 2, alpha = 0.5, beta = 2.0",
             "(1 - alpha² + beta)")),
    Mistake("04_rts_smoother", "the covariance recursion with G where it needs Gᵀ",
            "P_s = P + G @ (P_s_next - P_pred) @ G.T", "P_s = P + G @ (P_s_next - P_pred) @ G",
            ("the smoothed covariance P_s differs first at sample 0",
             "P + G (P_s_next - P̄) Gᵀ", "pessimistic")),
    Mistake("05_bootstrap_pf", "the log-likelihood without its ½",
            "logw = -0.5 * (y - np.sin(X[:, 0])) ** 2 / R",
            "logw = -(y - np.sin(X[:, 0])) ** 2 / R",
            ("the vector of weights differs first at particle 0", "-(y - sin θ)² / (2R)",
             "not shown equivalent")),
    Mistake("06_mhe_least_squares", "the arrival mean one sample off: the previous "
            "window's first state instead of its second",
            "self.xbar = self.Xw[1].copy()", "self.xbar = self.Xw[0].copy()",
            ("differs first at sample 20", "eq. (6)")),
    Mistake("07_observability_lie", "every Lie derivative taken of h, not of the previous "
            "one",
            "lies.append(lie_derivative(lies[-1], f, x))",
            "lies.append(lie_derivative(h, f, x))",
            ("L_f^2 h of the sine_pendulum model differs first", "applied k times (eq. 2)")),
    Mistake("08_noise_tuning", "the likelihood without log det S",
            "value = 0.5 * float(np.sum(np.linalg.slogdet(S)[1] + nis(E, S) + "
            "2 * np.log(2 * np.pi)))",
            "value = 0.5 * float(np.sum(nis(E, S) + 2 * np.log(2 * np.pi)))",
            ("Look at eq. (8)", "log det S")),
    Mistake("09_batch_reactor", "the MHE weighted by standard deviations, not variances",
            "return estim.MHE(MODEL, horizon=horizon, Q=SIG_W**2, R=SIG_V**2, x0=GUESS,",
            "return estim.MHE(MODEL, horizon=horizon, Q=SIG_W, R=SIG_V, x0=GUESS,",
            ("your MHE: the covariance P differs first at sample 1", "eq. (6)")),
    Mistake("10_information_filter", "the prediction forgets Q",
            "A @ P @ A.T + Q)", "A @ P @ A.T)",
            ("the covariance P differs first at sample 1", "(A Y⁻¹ Aᵀ + Q)⁻¹")),
]


def submission(mistake: Mistake, dist: Path, folder: Path) -> Path:
    """The solution notebook of ``dist`` with ``mistake`` made, written to ``folder``."""
    import nbformat

    nb = nbformat.read(dist / "autograder" / f"{mistake.name}.ipynb", as_version=4)
    hits = [c for c in nb.cells if c.cell_type == "code" and mistake.old in c.source]
    if len(hits) != 1:
        raise ValueError(f"{mistake.name}: the code {mistake.old!r} is in {len(hits)} "
                         f"cells of the solution, expected 1")
    hits[0].source = hits[0].source.replace(mistake.old, mistake.new)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{mistake.name}.ipynb"
    nbformat.write(nb, path)
    return path


def grade_mistake(mistake: Mistake, out: Path) -> dict[str, course.Part]:
    """Build ``mistake``'s exercise in ``out`` and grade the mistaken submission."""
    dist = course.build(mistake.name, out)
    return course.grade(dist, submission(mistake, dist, out / "mistakes"))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*")
    parser.add_argument("--out", default="dist")
    args = parser.parse_args(argv)
    for m in MISTAKES:
        if args.names and m.name not in args.names:
            continue
        parts = grade_mistake(m, Path(args.out))
        print(f"{m.name}, {m.what}: {course._report(parts)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
