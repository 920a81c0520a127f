r"""What a sampler of :mod:`estim.inference` returns: the chains of the parameters and what
users do with them.

:class:`Posterior` holds every chain's draws (warm-up included, :attr:`Posterior.warmup`
marks where it ends), their log-likelihoods and log-priors, the accepted moves, and
answers with the draws after the warm-up: :meth:`~Posterior.mean`, :meth:`~Posterior.sd`,
the Monte Carlo standard error of the mean :math:`\mathrm{sd}/\sqrt{S_\text{eff}}`
(:meth:`~Posterior.mcse`), :func:`~estim.inference.rhat` and
:func:`~estim.inference.ess` per parameter, the acceptance rates, a table
(:meth:`~Posterior.summary`), ``arviz.InferenceData`` (:meth:`~Posterior.to_arviz`), and,
when the chains ran on a particle filter, the states' posterior
(:meth:`~Posterior.states`: smoothed paths at posterior draws) and forecasts
(:meth:`~Posterior.forecast`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_int
from estim.inference.chains import ess, rhat

__all__ = ["Forecast", "Posterior", "StatePosterior", "agreement"]


@dataclass(frozen=True)
class StatePosterior:
    """The states' posterior :math:`p(x_{0:T-1} \\mid y)`: smoothed ``paths (n, T, nx)``,
    one set per posterior draw of the parameters (``draws (n, d)``), their mean ``x``
    and pointwise 2.5 % and 97.5 % quantiles ``lower``, ``upper`` ``(T, nx)``."""

    paths: np.ndarray
    draws: np.ndarray
    x: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    state_names: list[str]


@dataclass(frozen=True)
class Forecast:
    """Draws of the next ``h`` states ``x (n, h, nx)`` and outputs ``y (n, h, ny)`` after
    the record (the parameters' uncertainty, the filter's at the last sample and the
    noises included; ``draws (n, d)``: the parameters of each), their means and
    pointwise 2.5 % and 97.5 % quantiles of ``y``."""

    x: np.ndarray
    y: np.ndarray
    draws: np.ndarray
    y_mean: np.ndarray
    y_lower: np.ndarray
    y_upper: np.ndarray
    output_names: list[str]


@dataclass(frozen=True, repr=False)
class Posterior:
    """Chains of parameter draws (see the module).

    Attributes
    ----------
    names : list of str
        The parameters.
    draws : (chains, iterations, d) array
        Every state of every chain, warm-up included.
    log_likelihood, log_prior : (chains, iterations) arrays
        At each state (the particle filter's estimate kept with its point, for PMMH).
    accepted : (chains, iterations) bool array
        Whether the move to each state was accepted (the first state: True).
    warmup : int
        Iterations of each chain before the draws that count.
    method : str
        How the chains were drawn.
    seconds : float
        Wall time.
    details : dict
        The sampler's settings and diagnostics (the likelihood estimate's spread, the
        final proposal covariance, the points without likelihood).
    """

    names: list[str]
    draws: np.ndarray
    log_likelihood: np.ndarray
    log_prior: np.ndarray
    accepted: np.ndarray
    warmup: int
    method: str
    seconds: float
    details: dict = field(default_factory=dict)
    likelihood: Any = None

    # ------------------------------------------------------------ draws
    def samples(self, name: str | None = None) -> np.ndarray:
        """The draws after the warm-up: ``(chains, n)`` of one parameter, or
        ``(chains, n, d)``."""
        kept = self.draws[:, self.warmup:]
        if name is None:
            return kept
        return kept[:, :, self._index(name)]

    def _index(self, name: str) -> int:
        if name not in self.names:
            raise ValueError(f"unknown parameter {name!r}; the chains hold {self.names}")
        return self.names.index(name)

    def _each(self, fn) -> dict[str, float]:
        return {n: float(fn(self.samples(n))) for n in self.names}

    def mean(self) -> dict[str, float]:
        """Posterior means."""
        return self._each(np.mean)

    def sd(self) -> dict[str, float]:
        """Posterior standard deviations."""
        return self._each(lambda s: np.std(s, ddof=1))

    def quantile(self, q: float) -> dict[str, float]:
        """The posterior ``q``-quantiles."""
        return self._each(lambda s: np.quantile(s, q))

    def rhat(self) -> dict[str, float]:
        """The rank-normalised split :math:`\\hat R` of each parameter (1.01 the usual
        limit)."""
        return self._each(rhat)

    def ess(self) -> dict[str, float]:
        """The bulk effective sample size of each parameter."""
        return self._each(ess)

    def mcse(self) -> dict[str, float]:
        """The Monte Carlo standard error of each posterior mean,
        :math:`\\mathrm{sd} / \\sqrt{S_\\text{eff}}`."""
        sd, n = self.sd(), self.ess()
        return {k: sd[k] / np.sqrt(n[k]) for k in self.names}

    @property
    def acceptance(self) -> np.ndarray:
        """Each chain's acceptance rate after the warm-up ``(chains,)``."""
        return self.accepted[:, max(self.warmup, 1):].mean(axis=1)

    def summary(self) -> str:
        """A table: mean, sd, MCSE, 2.5 % and 97.5 % quantiles, R-hat and ESS of each
        parameter, and the acceptance rates."""
        mean, sd, se, lo, hi, rh, ne = (self.mean(), self.sd(), self.mcse(),
                                        self.quantile(0.025), self.quantile(0.975),
                                        self.rhat(), self.ess())
        width = max(9, *(len(n) for n in self.names))
        head = (f"{'parameter':<{width}} {'mean':>10} {'sd':>9} {'mcse':>9} {'2.5%':>10} "
                f"{'97.5%':>10} {'R-hat':>6} {'ESS':>7}")
        rows = [f"{n:<{width}} {mean[n]:>10.4g} {sd[n]:>9.3g} {se[n]:>9.2g} "
                f"{lo[n]:>10.4g} {hi[n]:>10.4g} {rh[n]:>6.3f} {ne[n]:>7.0f}"
                for n in self.names]
        acc = self.acceptance
        C, S = self.draws.shape[:2]
        foot = (f"{self.method}: {C} chains x {S} iterations ({self.warmup} warm-up), "
                f"acceptance {acc.mean():.3f} [{acc.min():.3f}-{acc.max():.3f}], "
                f"{self.seconds:.1f} s")
        return "\n".join([head, *rows, foot])

    def __repr__(self) -> str:
        return f"Posterior(\n{self.summary()}\n)"

    def to_arviz(self) -> Any:
        """The chains as ``arviz.InferenceData`` (posterior after the warm-up, the warm-up
        in ``warmup_posterior``; ``lp``, the log-likelihood ``loglik`` and ``accepted`` in
        ``sample_stats``);
        needs arviz."""
        try:
            import arviz as az
        except ImportError as exc:
            raise ImportError("Posterior.to_arviz needs arviz: pip install arviz") from exc
        w = self.warmup
        post = {n: self.draws[:, w:, i] for i, n in enumerate(self.names)}
        warm = {n: self.draws[:, :w, i] for i, n in enumerate(self.names)}
        stats = {"lp": (self.log_likelihood + self.log_prior)[:, w:],
                 "loglik": self.log_likelihood[:, w:],
                 "accepted": self.accepted[:, w:]}
        return az.from_dict(posterior=post, sample_stats=stats,
                            warmup_posterior=warm if w else None,
                            save_warmup=bool(w))

    # ------------------------------------------------------ states, forecasts
    def _thinned(self, n_draws: int, rng: np.random.Generator) -> np.ndarray:
        kept = self.samples().reshape(-1, len(self.names))
        n_draws = as_int(n_draws, "n_draws", minimum=1)
        return kept[rng.choice(len(kept), size=min(n_draws, len(kept)), replace=False)]

    def _engine(self):
        if self.likelihood is None or not hasattr(self.likelihood, "pf"):
            raise ValueError("the states' posterior and forecasts need chains run on a "
                             "particle filter (pmmh(pf, Y, ...)); these chains had an "
                             "exact likelihood function")
        return self.likelihood

    def states(self, n_draws: int = 100, n_paths: int = 1, seed: int = 0) -> StatePosterior:
        """The states' posterior: at ``n_draws`` posterior draws of the parameters,
        ``n_paths`` paths each drawn from the particle filter's smoother (forward
        filtering, backward simulation), pooled."""
        L = self._engine()
        rng = np.random.default_rng(seed)
        draws = self._thinned(n_draws, rng)
        paths, used = [], []
        for i, theta in enumerate(draws):
            if not L.apply(theta):
                continue
            used.append(i)
            res = L.pf.smooth(L.Y, L.U, n_paths=n_paths, t=L.t,
                              seed=int(rng.integers(2 ** 62)))
            paths.append(res.paths)
        L.restore()
        P = np.concatenate(paths)
        lo, hi = np.quantile(P, [0.025, 0.975], axis=0)
        return StatePosterior(P, draws[used], P.mean(axis=0), lo, hi, list(L.pf.model.state_names))

    def forecast(self, h: int, U: ArrayLike | None = None, n_draws: int = 200,
                 seed: int = 0) -> Forecast:
        """Draws of the ``h`` samples after the record: at each of ``n_draws`` posterior
        draws of the parameters, the filter's particles at the last sample moved on by
        the model with its process noise, and measured with its measurement noise
        (``U (h, nu)``: the inputs from the last sample on; default zero)."""
        L = self._engine()
        pf = L.pf
        m = pf.model
        h = as_int(h, "h", minimum=1)
        rng = np.random.default_rng(seed)
        draws = self._thinned(n_draws, rng)
        U = np.zeros((h, m.nu)) if U is None else np.asarray(U, float).reshape(h, m.nu)
        xs, ys, used = [], [], []
        for i, theta in enumerate(draws):
            if not L.apply(theta):
                continue
            used.append(i)
            pf.filter(L.Y, L.U, t=L.t, seed=int(rng.integers(2 ** 62)))
            X, W = pf.particles
            x = X[rng.choice(len(W), p=W)]
            path_x, path_y = [], []
            LQ, LR = _factor(pf.Q), _factor(pf.R)
            u_prev = U[0]
            for k in range(h):
                w = pf._stage_input(U[k] if m.sampled else u_prev)
                x = np.asarray(pf._transit(x[:, None], w, n=1)[0])[:, 0] + \
                    LQ @ rng.standard_normal(m.ndx)
                u_prev = U[k]
                ymean = np.asarray(m._fast("H")(x, U[k], pf._p)[0]).ravel()
                path_x.append(x)
                path_y.append(ymean + LR @ rng.standard_normal(m.ny))
            xs.append(path_x)
            ys.append(path_y)
        L.restore()
        Xf, Yf = np.array(xs), np.array(ys)
        lo, hi = np.quantile(Yf, [0.025, 0.975], axis=0)
        return Forecast(Xf, Yf, draws[used], Yf.mean(axis=0), lo, hi, list(m.output_names))


def _factor(C: np.ndarray) -> np.ndarray:
    """A factor :math:`L L^\\top = C` of a covariance that may be singular."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


#: a chain whose R-hat exceeds this, or whose effective sample size is below
#: :data:`FEWEST_EFFECTIVE`, cannot be judged by its Monte Carlo standard error
RHAT_LIMIT = 1.05
FEWEST_EFFECTIVE = 100


def agreement(post: Posterior, reference: Posterior | dict[str, float],
              confidence: float = 0.99) -> tuple[bool, str]:
    r"""Whether ``post``'s posterior means agree with ``reference`` (another
    :class:`Posterior`, or exact values): for each parameter
    :math:`z = (\bar\theta - \bar\theta_\text{ref}) / \sqrt{\mathrm{MCSE}^2 +
    \mathrm{MCSE}_\text{ref}^2}` within :math:`\pm z^*`, :math:`z^*` the two-sided normal
    quantile at ``confidence`` over the :math:`d` parameters (Bonferroni: the chance of
    failing chains that do sample the same posterior is at most ``1 - confidence``, when
    their MCSEs are right). Chains with :math:`\hat R` above :data:`RHAT_LIMIT` or fewer
    than :data:`FEWEST_EFFECTIVE` effective draws fail: their MCSE is not to be
    trusted, and a stuck chain's tiny spread would otherwise pass. Returns the verdict
    and its text."""
    from scipy import stats

    names = post.names
    if isinstance(reference, Posterior):
        ref_mean, ref_se = reference.mean(), reference.mcse()
        chains = [("chains", post), ("reference", reference)]
    else:
        missing = [n for n in names if n not in reference]
        if missing:
            raise ValueError(f"reference: no value for {missing}")
        ref_mean, ref_se = {n: float(reference[n]) for n in names}, dict.fromkeys(names, 0.0)
        chains = [("chains", post)]
    for label, p in chains:
        rh, ne = p.rhat(), p.ess()
        bad = [f"{n}: R-hat {rh[n]:.3f}, ESS {ne[n]:.0f}" for n in p.names
               if rh[n] > RHAT_LIMIT or ne[n] < FEWEST_EFFECTIVE]
        if bad:
            return False, (f"the {label} cannot be judged (R-hat above {RHAT_LIMIT} or "
                           f"fewer than {FEWEST_EFFECTIVE} effective draws): "
                           f"{'; '.join(bad)}; run longer chains (or more particles if "
                           f"the acceptance is low: {p.acceptance.mean():.3f})")
    zstar = float(stats.norm.ppf(1 - (1 - confidence) / (2 * len(names))))
    mean, se = post.mean(), post.mcse()
    parts, passed = [], True
    for n in names:
        s = math.hypot(se[n], ref_se[n])
        z = (mean[n] - ref_mean[n]) / s if s > 0 else math.inf
        passed &= abs(z) <= zstar
        parts.append(f"{n}: {mean[n]:.4g} vs {ref_mean[n]:.4g} (z = {z:+.2f}, MCSE "
                     f"{s:.2g})")
    verdict = "agree" if passed else "differ"
    return passed, (f"posterior means {verdict} at confidence {confidence} (|z| <= "
                    f"{zstar:.2f} for each of {len(names)}): {'; '.join(parts)}")
