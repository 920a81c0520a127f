"""Error rates of the Monte Carlo check of tests/test_book.py
(``test_the_books_particle_filter_and_smoother_within_monte_carlo_error``): a single run of
the book's particle filter and backward-simulation smoother is accepted when it lies
within 3 standard deviations of the mean of 10 seeds of estim's.

* false alarm: one of 100 correct runs (compiled, 1000 particles, stratified resampling
  at every step, 100 backward paths) taken as the "book's" run against 2000 random sets
  of 10 of the others;
* detection: 40 runs of a filter told ``R = 0.4`` (four times the truth) against sets of
  10 correct runs.

Run from the repository root (about two minutes)::

    python benchmarks/book_pf_check_rates.py
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import estim

DATA = np.load(Path(__file__).resolve().parent.parent / "examples" / "data" /
               "book_pendulum_pf.npz")


def main() -> None:
    sc = estim.scenarios.book_pendulum()
    tuning = {**sc.tuning, "x0": [1.6, 0.0], "P0": 0.1 * np.eye(2)}
    Y = np.vstack([[np.nan], DATA["Y"][:, None]])

    def rmse(x: np.ndarray) -> float:
        return float(np.sqrt(np.mean((x[1:, 0] - DATA["X"][:, 0]) ** 2)))

    def run(seed: int, **kw) -> tuple[float, float]:
        res = estim.ParticleFilter(sc.model, **{**tuning, **kw}, n_particles=1000,
                                   resampling="stratified", ess_threshold=1.0, seed=seed,
                                   jit=True).smooth(Y, n_paths=100)
        return rmse(res.x_filtered), rmse(res.x)

    good = np.array([run(s) for s in range(100)])
    bad = np.array([run(1000 + s, R=0.4) for s in range(40)])
    rng = np.random.default_rng(0)

    def flagged(book: float, pool: np.ndarray, col: int) -> float:
        fails = 0
        for _ in range(2000):
            v = pool[rng.choice(len(pool), 10, replace=False), col]
            fails += abs(book - v.mean()) >= 3 * v.std(ddof=1)
        return fails / 2000

    for col, name in ((0, "PF"), (1, "PF-BS")):
        null = np.mean([flagged(good[i, col], np.delete(good, i, 0), col)
                        for i in range(0, 100, 5)])
        detect = np.mean([flagged(b, good, col) for b in bad[:, col]])
        print(f"{name}: false alarm {null:.4f}; detection of R x 4 {detect:.3f}; RMSE "
              f"correct {good[:, col].mean():.4f} ± {good[:, col].std():.4f}, R x 4 "
              f"{bad[:, col].mean():.4f} ± {bad[:, col].std():.4f}")


if __name__ == "__main__":
    main()
