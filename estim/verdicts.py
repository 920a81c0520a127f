r"""The statistical verdicts of comparisons over seeds: consistency and paired tests.

One rule each, used wherever estim states a verdict (the comparison table's consistency
column and its notes, :mod:`estim.testing`, the pytest plugin's summary, report and
baselines), so that no two of them can disagree.

**Consistency** (:func:`consistency`). For a consistent estimator the NEES
:math:`\epsilon_k = e_k^\top P_k^{-1} e_k` of every step follows :math:`\chi^2(n)`
(Bar-Shalom, Li, Kirubarajan 2001, sec. 5.4). Divergence makes the per-seed averages of
:math:`\epsilon_k` heavy-tailed: one lost seed moves their mean by hundreds and widens
its interval with it, so a mean-based test is blind exactly when it matters. The verdict
rests on two statistics that no single seed can dominate:

1. *Diverged seeds.* A seed **diverged** when its NEES lies beyond the
   :data:`DIVERGED_TAIL` point of :math:`\chi^2(n)` (errors of about 6 σ and more) on at
   least a :data:`DIVERGED_SHARE` of its steps. For a consistent estimator the expected
   share of such steps is :data:`DIVERGED_TAIL`, so by Markov's inequality a seed is
   called diverged with probability at most :data:`P_DIVERGED` = tail / share, whatever
   the correlation of the steps over time. The count :math:`k` of diverged seeds among
   :math:`S` is tested against Binomial(:math:`S`, :data:`P_DIVERGED`): at
   :data:`P_DIVERGED` = 1e-7, a single diverged seed makes an estimator inconsistent
   unless it ran more than 50 000 seeds.
2. *Calibration of the typical step.* The probability level
   :math:`u_k = F_{\chi^2(n)}(\epsilon_k)` of every step is uniform on (0, 1) for a
   consistent estimator, so each seed's average level :math:`\bar u_s` has expectation
   1/2 exactly (whatever the correlation over time), and it is bounded: a seed moves
   the mean over seeds by at most :math:`1 / (2S)`. The mean of :math:`\bar u_s` over the
   independent seeds must lie in its t-interval about 1/2 (above: overconfident; below:
   pessimistic). One seed: the levels of :data:`BATCHES` batches of its steps.

Each test is made at :math:`\alpha / 2` (:math:`\alpha` = 1 - ``level``): the verdict's
false-alarm rate is at most :math:`\alpha` (Bonferroni).

**Paired tests** (:func:`paired`). Seed :math:`s` gives both estimators the same noise,
so the differences :math:`d_s = m_b(s) - m_a(s)` are independent over seeds. The default
test is Wilcoxon's signed-rank test (exact up to 50 seeds without ties): its
false-alarm rate is the nominal one whenever the differences are symmetric about zero,
in particular for interchangeable estimators, however heavy their tails; the sign test
and Student's t-test on the mean are there to compare with. The location reported with
the rank test is the Hodges-Lehmann estimate (the median of the pairwise averages
:math:`(d_i + d_j)/2`).

References
----------
Y. Bar-Shalom, X. R. Li, T. Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, Wiley 2001, sec. 5.4; F. Wilcoxon, "Individual comparisons by ranking
methods", Biometrics Bulletin 1(6), 1945; J. L. Hodges, E. L. Lehmann, "Estimates of
location based on rank tests", Ann. Math. Stat. 34(2), 1963; C. J. Clopper, E. S.
Pearson, "The use of confidence or fiducial limits illustrated in the case of the
binomial", Biometrika 26(4), 1934.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["BATCHES", "DIVERGED_SHARE", "DIVERGED_TAIL", "P_DIVERGED", "TESTS",
           "Consistency", "PairedTest", "SeedScores", "consistency", "paired", "seed_scores",
           "seed_list_text", "seed_range_text"]

#: A step whose NEES lies beyond this tail of chi2(n) counts towards divergence.
DIVERGED_TAIL = 1e-8
#: The share of a seed's steps beyond :data:`DIVERGED_TAIL` that makes the seed diverged.
DIVERGED_SHARE = 0.1
#: The bound (Markov) on the probability that a consistent estimator's seed is called
#: diverged: :data:`DIVERGED_TAIL` / :data:`DIVERGED_SHARE`.
P_DIVERGED = DIVERGED_TAIL / DIVERGED_SHARE
#: Batches of one seed's steps, for a verdict on a single seed (batch means).
BATCHES = 10
#: How far from 1 the ratio of the errors to the reported sigma, sqrt(NEES/n) of the
#: median seed, may be for an inconsistent estimator to be graded "slightly" off.
SLIGHT = 0.1
#: The paired tests by name.
TESTS = ("wilcoxon", "sign", "t")


class SeedScores(TypedDict):
    """One seed's consistency scores (:func:`seed_scores`)."""

    ratio: float
    level: float
    batches: list[float]
    diverged: bool


def seed_scores(values: ArrayLike, dof: ArrayLike) -> SeedScores:
    r"""One seed's consistency scores from its per-step statistic (NEES or NIS).

    Parameters
    ----------
    values : (T,) array
        The statistic of every step (NaN where there is none: skipped).
    dof : int or (T,) array
        Its chi-square degrees of freedom (the state dimension for the NEES, the outputs
        measured at each step for the NIS).

    Returns
    -------
    dict
        ``ratio``: the average of ``values / dof`` (the NEES/n of the table);
        ``level``: the average probability level :math:`F_{\chi^2}(\epsilon_k)`;
        ``batches``: the average level of each of :data:`BATCHES` batches of the steps
        (fewer with fewer steps); ``diverged``: whether the seed diverged; all NaN
        (``diverged`` False) without a finite value.
    """
    from scipy import stats

    v = np.asarray(values, dtype=float)
    n = np.broadcast_to(np.asarray(dof, dtype=float), v.shape)
    ok = np.isfinite(v) & (n > 0)
    if not ok.any():
        return {"ratio": float("nan"), "level": float("nan"), "batches": [],
                "diverged": False}
    v, n = v[ok], n[ok]
    level = stats.chi2.cdf(v, n)
    beyond = v > stats.chi2.isf(DIVERGED_TAIL, n)
    return {"ratio": float(np.mean(v / n)), "level": float(level.mean()),
            "batches": [float(c.mean()) for c in np.array_split(level, min(BATCHES, v.size))],
            "diverged": bool(beyond.mean() >= DIVERGED_SHARE)}


def seed_range_text(seeds: Sequence[int]) -> str:
    """``"0..19 (20)"`` for consecutive seeds, else ``"[3, 17, 40, ...]"``."""
    seeds = [int(s) for s in seeds]
    if seeds and seeds == list(range(seeds[0], seeds[0] + len(seeds))):
        return f"{seeds[0]}..{seeds[-1]} ({len(seeds)})"
    return "[" + seed_list_text(seeds, 6) + "]"


def seed_list_text(seeds: Sequence[int], most: int = 8) -> str:
    """``"3, 17, 40"`` (``", ..."`` after ``most`` of them)."""
    seeds = [int(s) for s in seeds]
    return ", ".join(map(str, seeds[:most])) + (", ..." if len(seeds) > most else "")


@dataclass(frozen=True)
class Consistency:
    r"""The consistency verdict of one estimator's runs (:func:`consistency`).

    Attributes
    ----------
    consistent : bool
        Neither test rejects at ``level``.
    level : float
        The verdict's confidence; its false-alarm rate is at most ``1 - level``.
    units : str
        ``"seeds"``, or ``"batches of steps"`` for a single seed.
    n : int
        The seeds (or batches) tested.
    seeds : list of int
        The seeds tested.
    diverged : list of int
        The seeds that diverged (see the module).
    p_diverged : float
        The probability that a consistent estimator has at least as many diverged seeds
        (a bound: :data:`P_DIVERGED` per seed).
    mean_level : float
        The mean over seeds of the seeds' average probability level (1/2 when
        consistent); ``interval`` its t-interval at :math:`1 - \alpha/2`.
    nees_median, nees_mean : float
        The median and the mean over seeds of the time-averaged NEES/n.
    direction : str
        ``"consistent"``, ``"overconfident"`` or ``"pessimistic"``.
    what : str
        The statistic tested, ``"NEES"`` or ``"NIS"``.
    """

    consistent: bool
    level: float
    units: str
    n: int
    seeds: list[int]
    diverged: list[int]
    p_diverged: float
    mean_level: float
    interval: tuple[float, float]
    nees_median: float
    nees_mean: float
    direction: str
    what: str = "NEES"
    reasons: list[str] = field(default_factory=list)

    def grade(self) -> str:
        """The table's column: ``"yes"`` (with ``", k/S div."`` when some seeds diverged
        but too few to reject), ``"diverged k/S"``, ``"overconfident"``,
        ``"pessimistic"``, or ``"slightly over."``/``"slightly pess."`` when the median
        seed's errors are within :data:`SLIGHT` of the reported sigma."""
        k, S = len(self.diverged), len(self.seeds)
        if self.consistent:
            return f"yes, {k}/{S} div." if k else "yes"
        if self.p_diverged <= (1 - self.level) / 2:
            return f"diverged {k}/{S}"
        over = self.direction == "overconfident"
        if np.isfinite(self.nees_median) and \
                abs(np.sqrt(max(self.nees_median, 0.0)) - 1) <= SLIGHT:
            return "slightly over." if over else "slightly pess."
        return self.direction

    def divergence_text(self) -> str:
        """``"diverged on 24 of 200 seeds: 3, 17, ..."`` (empty when none did)."""
        if not self.diverged:
            return ""
        return (f"diverged on {len(self.diverged)} of {len(self.seeds)} seed"
                f"{'s' if len(self.seeds) > 1 else ''}: {seed_list_text(self.diverged)}")

    def summary(self) -> str:
        """One sentence: the verdict, the divergence, the level test, the NEES/n."""
        head = "consistent" if self.consistent else f"not consistent ({self.direction})"
        parts = [f"{self.what} {head} at level {self.level:g}"]
        if self.diverged:
            parts.append(f"{self.divergence_text()} (a consistent estimator has so many "
                         f"with probability <= {self.p_diverged:.2g})")
        lo, hi = self.interval
        parts.append(f"mean chi-square level {self.mean_level:.3f} over {self.n} "
                     f"{self.units}, its {1 - (1 - self.level) / 2:.1%} interval "
                     f"[{lo:.3f}, {hi:.3f}] {'contains' if lo <= 0.5 <= hi else 'excludes'}"
                     f" 0.5")
        parts.append(f"{self.what}/n median {self.nees_median:.3g}, mean {self.nees_mean:.3g}"
                     f" over the seeds" if len(self.seeds) > 1 else
                     f"{self.what}/n {self.nees_mean:.3g} over the log")
        return "; ".join(parts)


def consistency(ratio: ArrayLike, level_by_seed: ArrayLike, diverged: ArrayLike,
                seeds: Sequence[int], *, level: float = 0.99,
                batches: Sequence[float] | None = None, what: str = "NEES"
                ) -> Consistency | None:
    r"""The consistency verdict of one estimator over seeds (see the module).

    Parameters
    ----------
    ratio, level_by_seed, diverged : (S,) arrays
        Each seed's :func:`seed_scores` (``ratio``, ``level``, ``diverged``); seeds whose
        level is NaN (no covariance, or a run that raised) are left out.
    seeds : (S,) sequence of int
        The seeds' names, for the message.
    level : float
        One minus the false-alarm rate, in (0, 1).
    batches : sequence of float, optional
        The batch levels of the one seed, used when a single seed is left.

    Returns
    -------
    Consistency or None
        None when no seed has a covariance, or one seed too few steps to batch.
    """
    from scipy import stats

    r_all, lv = np.asarray(ratio, float), np.asarray(level_by_seed, float)
    div = np.asarray(diverged, bool)
    ok = np.isfinite(lv)
    kept = [int(s) for s, k in zip(seeds, ok, strict=True) if k]
    S = len(kept)
    if S == 0:
        return None
    alpha = 1.0 - level
    down = [s for s, d in zip(kept, div[ok], strict=True) if d]
    p_div = float(stats.binom.sf(len(down) - 1, S, P_DIVERGED)) if down else 1.0
    if S >= 2:
        units, sample = "seeds", lv[ok]
    else:
        units = "batches of steps"
        sample = np.asarray(batches if batches is not None else [], float)
        if sample.size < 2 and not down:
            return None
    if sample.size >= 2:
        mean = float(sample.mean())
        se = float(sample.std(ddof=1) / np.sqrt(sample.size))
        q = float(stats.t.ppf(1 - alpha / 4, sample.size - 1))
        lo, hi = mean - q * se, mean + q * se
    else:
        mean, lo, hi = float(sample.mean()) if sample.size else float("nan"), \
            float("nan"), float("nan")
    level_ok = not (sample.size >= 2 and not lo <= 0.5 <= hi)
    div_ok = p_div > alpha / 2
    finite = r_all[ok][np.isfinite(r_all[ok])]
    direction = "consistent"
    if not div_ok or (not level_ok and mean > 0.5):
        direction = "overconfident"
    elif not level_ok:
        direction = "pessimistic"
    return Consistency(
        consistent=level_ok and div_ok, level=level, units=units,
        n=int(sample.size) if S == 1 else S, seeds=kept, diverged=down, p_diverged=p_div,
        mean_level=mean, interval=(lo, hi),
        nees_median=float(np.median(finite)) if finite.size else float("nan"),
        nees_mean=float(np.mean(finite)) if finite.size else float("nan"),
        direction=direction, what=what)


@dataclass(frozen=True)
class PairedTest:
    r"""The result of a paired test over seeds (:func:`paired`).

    Attributes
    ----------
    test : str
        ``"wilcoxon"``, ``"sign"`` or ``"t"``.
    alternative : str
        ``"greater"`` (the differences above zero), ``"less"`` or ``"two-sided"``.
    n : int
        The paired seeds.
    p_value : float
        The test's p-value (1.0 when every difference is zero).
    location : float
        The test's estimate of the differences' location: Hodges-Lehmann (Wilcoxon),
        the median (sign test) or the mean (t-test).
    mean, median : float
        Of the differences.
    above, below : int
        Seeds whose difference is above, below zero.
    """

    test: str
    alternative: str
    n: int
    p_value: float
    location: float
    mean: float
    median: float
    above: int
    below: int

    def text(self, counts: bool = True) -> str:
        """``"Wilcoxon signed-rank p = 0.003, 41 of 50 seeds above 0 and 9 below,
        Hodges-Lehmann 0.052"`` (without the seeds' counts: ``counts=False``)."""
        name = {"wilcoxon": "Wilcoxon signed-rank", "sign": "sign test",
                "t": "paired t-test"}[self.test]
        where = {"wilcoxon": "Hodges-Lehmann", "sign": "median", "t": "mean"}[self.test]
        seeds = f"{self.above} of {self.n} seeds above 0 and {self.below} below, " \
            if counts else ""
        return f"{name} p = {self.p_value:.3g}, {seeds}{where} {self.location:.4g}"


def hodges_lehmann(d: np.ndarray) -> float:
    """The median of the pairwise averages ``(d_i + d_j) / 2``, ``i <= j`` (of a random
    subset of 2000 differences beyond that many)."""
    if d.size > 2000:
        d = np.random.default_rng(0).choice(d, 2000, replace=False)
    i, j = np.triu_indices(d.size)
    return float(np.median((d[i] + d[j]) / 2))


def paired(d: np.ndarray, alternative: str = "greater", test: str = "wilcoxon") -> PairedTest:
    """A paired test of the differences ``d`` (one per seed) against zero.

    Parameters
    ----------
    d : (S,) array
        The differences, finite.
    alternative : {"greater", "less", "two-sided"}
        What the test looks for.
    test : {"wilcoxon", "sign", "t"}
        Wilcoxon's signed-rank test (zeros dropped; exact up to 50 differences without
        ties, else the normal approximation with the tie correction), the exact sign
        test, or Student's one-sample t-test.
    """
    from scipy import stats

    d = np.asarray(d, dtype=float)
    above, below = int((d > 0).sum()), int((d < 0).sum())
    mean, median = float(d.mean()), float(np.median(d))
    location = {"wilcoxon": hodges_lehmann(d), "sign": median, "t": mean}[test]
    if above + below == 0:
        p = 1.0
    elif test == "wilcoxon":
        p = float(stats.wilcoxon(d, alternative=alternative, zero_method="wilcox").pvalue)
    elif test == "sign":
        p = float(stats.binomtest(above, above + below, 0.5, alternative=alternative).pvalue)
    else:
        p = float(stats.ttest_1samp(d, 0.0, alternative=alternative).pvalue) \
            if np.ptp(d) > 0 else (0.0 if (alternative == "greater") == (mean > 0) or
                                   alternative == "two-sided" else 1.0)
    return PairedTest(test, alternative, int(d.size), p, location, mean, median, above,
                      below)


def smallest_p(n: int, test: str, alternative: str = "greater") -> float:
    """The smallest p-value a rank or sign test can give with ``n`` differences
    (``2^-n`` one-sided): below ``1 - confidence`` it can never pass."""
    if test == "t":
        return 0.0
    return 0.5 ** n * (2 if alternative == "two-sided" else 1)
