r"""Prior distributions of the parameters a Bayesian fit infers: a few named families, and
any log-density with its support.

Each prior is a proper density on an interval :math:`[\text{low}, \text{high}]` (its
support) with its log-density :meth:`Prior.logpdf` (normalised: the named families agree
with ``scipy.stats``), so that Metropolis-Hastings ratios and the model evidence of
:mod:`estim.inference` are those of the stated model. A sampler refuses a parameter whose
start lies outside its prior's support (:func:`check_start`), and an improper prior is
refused when it is made (a uniform without finite bounds; a log-density is taken as given:
its integral is the caller's to keep finite).

========================== ========================================= ==================
prior                      density                                   support
========================== ========================================= ==================
``Normal(mean, sd)``       :math:`N(\mu, \sigma^2)`                  the real line
``LogNormal(mu, sigma)``   :math:`\log\theta \sim N(\mu, \sigma^2)`  :math:`(0, \infty)`
``Uniform(low, high)``     constant                                  :math:`[a, b]`
``Gamma(shape, scale)``    :math:`\theta^{k-1} e^{-\theta/s}`        :math:`(0, \infty)`
``InverseGamma(shape,      :math:`\theta^{-k-1} e^{-s/\theta}`       :math:`(0, \infty)`
scale)``
``HalfNormal(sd)``         :math:`2 N(0, \sigma^2)` on the positives :math:`[0, \infty)`
``Beta(a, b)``             :math:`\theta^{a-1}(1-\theta)^{b-1}`      :math:`[0, 1]`
``LogDensity(f, low,       ``f(theta)``, as given                    :math:`[a, b]`
high)``
========================== ========================================= ==================
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np

from estim._validate import as_float

__all__ = ["Beta", "Gamma", "HalfNormal", "InverseGamma", "LogDensity", "LogNormal", "Normal",
           "Prior", "Uniform", "as_priors", "check_start"]

_LOG_2PI = math.log(2 * math.pi)


class Prior:
    """A proper prior density on ``[low, high]``: :meth:`logpdf` (``-inf`` outside the
    support) and :meth:`sample`."""

    low, high = -math.inf, math.inf
    #: the support excludes ``low`` (the densities of the positives)
    open_low = False

    def logpdf(self, theta: float) -> float:
        """The log-density at ``theta`` (``-inf`` outside the support)."""
        theta = float(theta)
        if not self.low <= theta <= self.high or not math.isfinite(theta) \
                or (self.open_low and theta == self.low):
            return -math.inf
        return self._log(theta)

    def _log(self, theta: float) -> float:
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` draws (the named families; a :class:`LogDensity` cannot)."""
        raise TypeError(f"{type(self).__name__} cannot be sampled directly")

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in vars(self).items()
                           if not k.startswith("_"))
        return f"{type(self).__name__}({fields})"


def _positive(value: object, name: str) -> float:
    v = as_float(value, name)
    if not v > 0:
        raise ValueError(f"{name} must be positive, got {value!r}")
    return v


class Normal(Prior):
    """:math:`N(\\mu, \\sigma^2)` on the real line."""

    def __init__(self, mean: float, sd: float):
        self.mean, self.sd = as_float(mean, "mean"), _positive(sd, "sd")

    def _log(self, theta: float) -> float:
        z = (theta - self.mean) / self.sd
        return -0.5 * (z * z + _LOG_2PI) - math.log(self.sd)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.normal(self.mean, self.sd, n)


class LogNormal(Prior):
    """:math:`\\log\\theta \\sim N(\\mu, \\sigma^2)`, on the positives."""

    low, open_low = 0.0, True

    def __init__(self, mu: float, sigma: float):
        self.mu, self.sigma = as_float(mu, "mu"), _positive(sigma, "sigma")

    def _log(self, theta: float) -> float:
        z = (math.log(theta) - self.mu) / self.sigma
        return -0.5 * (z * z + _LOG_2PI) - math.log(self.sigma * theta)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.lognormal(self.mu, self.sigma, n)


class Uniform(Prior):
    """Uniform on ``[low, high]`` (finite: an unbounded uniform is improper)."""

    def __init__(self, low: float, high: float):
        self.low, self.high = as_float(low, "low"), as_float(high, "high")
        if not self.low < self.high:
            raise ValueError(f"Uniform needs low < high, got [{low!r}, {high!r}]")

    def _log(self, theta: float) -> float:
        return -math.log(self.high - self.low)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.uniform(self.low, self.high, n)


class _ShapeScale(Prior):
    """A density on the positives with a ``shape`` and a ``scale``."""

    low, open_low = 0.0, True

    def __init__(self, shape: float, scale: float):
        self.shape, self.scale = _positive(shape, "shape"), _positive(scale, "scale")


class Gamma(_ShapeScale):
    """The gamma density of ``shape`` :math:`k` and ``scale`` :math:`s`, on the
    positives."""

    def _log(self, theta: float) -> float:
        k, s = self.shape, self.scale
        return (k - 1) * math.log(theta) - theta / s - math.lgamma(k) - k * math.log(s)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.gamma(self.shape, self.scale, n)


class InverseGamma(_ShapeScale):
    """The inverse gamma density of ``shape`` :math:`k` and ``scale`` :math:`s` (the
    conjugate prior of a variance), on the positives."""

    def _log(self, theta: float) -> float:
        k, s = self.shape, self.scale
        return k * math.log(s) - math.lgamma(k) - (k + 1) * math.log(theta) - s / theta

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return self.scale / rng.gamma(self.shape, 1.0, n)


class HalfNormal(Prior):
    """:math:`|N(0, \\sigma^2)|`, on the non-negatives (a scale's weakly informative
    prior)."""

    low = 0.0

    def __init__(self, sd: float):
        self.sd = _positive(sd, "sd")

    def _log(self, theta: float) -> float:
        z = theta / self.sd
        return math.log(2.0) - 0.5 * (z * z + _LOG_2PI) - math.log(self.sd)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return np.abs(rng.normal(0.0, self.sd, n))


class Beta(Prior):
    """The beta density on ``[0, 1]`` (a probability, a correlation mapped to it)."""

    low, high = 0.0, 1.0

    def __init__(self, a: float, b: float):
        self.a, self.b = _positive(a, "a"), _positive(b, "b")

    def _log(self, theta: float) -> float:
        if theta in (0.0, 1.0):
            edge = self.a if theta == 0.0 else self.b
            return math.inf if edge < 1 else (-math.inf if edge > 1 else -self._lbeta())
        return ((self.a - 1) * math.log(theta) + (self.b - 1) * math.log1p(-theta)
                - self._lbeta())

    def _lbeta(self) -> float:
        return math.lgamma(self.a) + math.lgamma(self.b) - math.lgamma(self.a + self.b)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.beta(self.a, self.b, n)


class LogDensity(Prior):
    """Any log-density ``f(theta)`` on ``[low, high]``, as given (its normalising constant
    only shifts the evidence; its integral must be finite)."""

    def __init__(self, f: Callable[[float], float], low: float = -math.inf,
                 high: float = math.inf):
        if not callable(f):
            raise TypeError(f"LogDensity needs a callable f(theta), got {type(f).__name__}")
        self.f = f
        self.low = as_float(low, "low", finite=False)
        self.high = as_float(high, "high", finite=False)
        if not self.low < self.high or math.isnan(self.low) or math.isnan(self.high):
            raise ValueError(f"LogDensity needs low < high, got [{low!r}, {high!r}]")

    def _log(self, theta: float) -> float:
        value = float(self.f(theta))
        return value if not math.isnan(value) else -math.inf


def as_priors(priors: object) -> dict[str, Prior]:
    """``{name: Prior}`` checked: a mapping of parameter names to priors (a callable is
    taken as a :class:`LogDensity` on the real line)."""
    if not isinstance(priors, Mapping) or not priors:
        raise TypeError(f"priors must be a non-empty dict of parameter names to priors "
                        f"(estim.inference.priors), got {type(priors).__name__}")
    out: dict[str, Prior] = {}
    for name, prior in priors.items():
        if not isinstance(name, str):
            raise TypeError(f"priors: the keys are parameter names, got {name!r}")
        if isinstance(prior, Prior):
            out[name] = prior
        elif callable(prior):
            out[name] = LogDensity(prior)
        else:
            raise TypeError(f"priors[{name!r}] must be a prior (Normal, Uniform, ...) or a "
                            f"log-density function, got {type(prior).__name__}")
    return out


def check_start(priors: Mapping[str, Prior], start: Mapping[str, float]) -> None:
    """A ``ValueError`` naming each parameter whose start has no prior density (outside
    its prior's support, or a density of zero there)."""
    missing = [k for k in priors if k not in start]
    if missing:
        raise ValueError(f"start: no value for {missing} (every parameter with a prior "
                         f"needs one)")
    bad = [f"{k} = {start[k]!r} ({priors[k]!r})" for k in priors
           if not math.isfinite(priors[k].logpdf(start[k]))]
    if bad:
        raise ValueError(f"start: outside the support of the prior: {', '.join(bad)}; "
                         f"a chain cannot leave a point of zero posterior density")
