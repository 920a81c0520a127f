r"""Standard errors, correlations and confidence intervals of identified parameters.

A parameter identified as a state (``model.augment("k")``) has, at the optimum of a
full-information fit, the Laplace approximation of its posterior: the fit minimises
the sum of whitened squares :math:`V(z) = \lVert r(z) \rVert^2` over the trajectory
:math:`z = (x_0, \dots, x_{T-1})`, and near the optimum :math:`\hat z`

.. math::
    z \sim \mathcal N\big(\hat z,\; (J^\top J)^{-1}\big), \qquad
    J = \partial r / \partial z \,\big|_{\hat z},

the Gauss-Newton form of the inverse Hessian of :math:`V/2` (exact on a
linear-Gaussian model, where it is the Rauch-Tung-Striebel smoother's covariance).
The parameters are the last :math:`n_\theta` components :math:`\theta` of the state;
their covariance is the :math:`\theta` block of the last state's covariance
(``FitResult.P_last``, ``info.P`` of MHE),

.. math::
    \Sigma_\theta = \big[(J^\top J)^{-1}\big]_{\theta_{T-1}\theta_{T-1}}, \qquad
    \sigma_i = \sqrt{(\Sigma_\theta)_{ii}}, \qquad
    \rho_{ij} = \frac{(\Sigma_\theta)_{ij}}{\sigma_i \sigma_j}, \qquad
    \hat\theta_i \pm z_{(1+\ell)/2}\, \sigma_i ,

with :math:`z_q` the standard normal quantile (1.96 at :math:`\ell = 0.95`). With
known :math:`R` (the weights are :math:`R^{-1}`) nothing is rescaled: the residuals
are already in units of their standard deviation (``absolute_sigma=True`` in
scipy's ``curve_fit``). When :math:`R` is only known up to a factor,
``scale="residual"`` multiplies :math:`\Sigma_\theta` by the residual variance
:math:`s^2 = V(\hat z)/\nu`, :math:`\nu = m - n_x` (:math:`m` measured values, plus
:math:`n_x` with a prior on :math:`x_0`), and takes the intervals from Student's
:math:`t_\nu`.

With a parameter's process noise :math:`q_\theta` tiny the parameter is a
constant, :math:`\theta_{T-1} = \theta_0`, and :math:`\Sigma_\theta` is the
inverse of the Fisher information of :math:`(x_0, \theta)` reduced to
:math:`\theta` plus the random walk :math:`(T-1)\, q_\theta`:
:math:`\Sigma_\theta = [F^{-1}]_{\theta\theta} + (T-1) q_\theta` with
:math:`F = \sum_k S_k^\top R^{-1} S_k`, :math:`S_k = \partial h(x_k)/\partial x_0`
(add :math:`P_0^{-1}` to :math:`F` with a prior), the ``fisher`` of
:func:`estim.observability.window` from the fitted :math:`\hat x_0`.

References
----------
L. Tierney, J. B. Kadane (1986), "Accurate approximations for posterior moments and
marginal densities", JASA 81(394); G. A. F. Seber, C. J. Wild (1989), *Nonlinear
Regression*, Wiley, ch. 5; B. M. Bell (1994), "The iterated Kalman smoother as a
Gauss-Newton method", SIAM J. Optim. 4(3).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from statistics import NormalDist
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_choice, as_float, as_vector, check_keywords
from estim.exceptions import EstimationWarning
from estim.model import Model

if TYPE_CHECKING:  # annotations only: an estimator is told by what it reports
    from estim.estimators.base import Estimator


class Fit(Protocol):
    """What this module reads of a fit (:class:`estim.FitResult`): the estimated
    trajectory ``x (T, nx)``, the covariance of its last state, the success, status and
    cost of the solve, the residuals ``v`` and ``_context``, ``(model, arrival term used,
    lower, upper)`` or None. Defined here, below the estimators, so that the fit's
    :meth:`~estim.FitResult.parameters` can call this module and not the reverse."""

    @property
    def x(self) -> np.ndarray: ...

    @property
    def success(self) -> bool: ...

    @property
    def status(self) -> str: ...

    @property
    def cost(self) -> float: ...

    @property
    def _context(self) -> Any: ...

    @property
    def P_last(self) -> np.ndarray | None: ...

    @property
    def v(self) -> np.ndarray: ...


#: A parameter whose standard error exceeds this fraction of its magnitude is reported
#: as poorly determined.
RELATIVE_STDERR_LIMIT = 0.5
#: Two parameters whose correlation exceeds this in magnitude are reported as hardly
#: separable by the data.
CORRELATION_LIMIT = 0.99
#: A smallest eigenvalue of the correlation matrix below this (its condition number
#: above about its inverse) reports confounded parameters: the data determine one
#: combination of them far better than each alone.
EIGENVALUE_LIMIT = 1e-3

_SCALES = ("none", "residual")


@dataclass(frozen=True)
class ParameterEstimates:
    r"""Identified parameters with their Laplace covariance.

    Returned by :func:`estim.parameter_uncertainty` and
    :meth:`estim.FitResult.parameters`; arrays follow the order of ``names``
    (the order of ``model.augment``).

    Attributes
    ----------
    names : tuple of str
        The augmented parameters :math:`\theta`.
    value : (n,) array
        Their estimates :math:`\hat\theta` (the last sample's, a constant parameter's
        value over the record).
    covariance : (n, n) array
        :math:`\Sigma_\theta`, the parameters' block of the last state's covariance
        (times :math:`s^2` with ``scale="residual"``).
    scale : {"none", "residual"}
        Whether the covariance was rescaled by the residual variance.
    residual_variance : float
        :math:`s^2 = V(\hat z)/\nu` of the fit (NaN where unknown); the factor applied
        with ``scale="residual"``, about 1 when ``R`` is right.
    dof : int or None
        :math:`\nu`, the degrees of freedom of Student's :math:`t` intervals
        (``scale="residual"``); None for normal intervals.
    model : str
        Name of the model.
    issues : tuple of str
        Why some parameters are poorly determined (empty when none is): a relative
        standard error above :data:`RELATIVE_STDERR_LIMIT`, a correlation beyond
        :data:`CORRELATION_LIMIT`, a near-singular block, a parameter at a bound.
    """

    names: tuple[str, ...]
    value: np.ndarray
    covariance: np.ndarray
    scale: str = "none"
    residual_variance: float = float("nan")
    dof: int | None = None
    model: str = ""
    issues: tuple[str, ...] = ()

    @property
    def stderr(self) -> np.ndarray:
        r"""Standard errors :math:`\sigma_i = \sqrt{(\Sigma_\theta)_{ii}}`, ``(n,)``."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def relative_stderr(self) -> np.ndarray:
        r""":math:`\sigma_i / |\hat\theta_i|`, ``(n,)`` (inf for a zero estimate)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.value != 0, self.stderr / np.abs(self.value), np.inf)

    @property
    def correlation(self) -> np.ndarray:
        r"""Correlation matrix :math:`\rho_{ij} = \Sigma_{ij}/(\sigma_i\sigma_j)`, ``(n, n)``."""
        s = self.stderr
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = self.covariance / np.outer(s, s)
        np.fill_diagonal(rho, 1.0)
        return rho

    @property
    def params(self) -> dict[str, float]:
        """The estimates by name."""
        return dict(zip(self.names, self.value.tolist(), strict=True))

    def quantile(self, level: float = 0.95) -> float:
        r"""The two-sided quantile :math:`z_{(1+\ell)/2}` (or :math:`t_{\nu,(1+\ell)/2}`).

        Parameters
        ----------
        level : float
            Confidence level in (0, 1).
        """
        level = _level(level)
        if self.dof is None:
            return NormalDist().inv_cdf(0.5 + level / 2)
        from scipy import stats

        return float(stats.t.ppf(0.5 + level / 2, self.dof))

    def interval(self, level: float = 0.95) -> np.ndarray:
        r"""Confidence intervals :math:`\hat\theta_i \pm z_{(1+\ell)/2}\,\sigma_i`.

        Parameters
        ----------
        level : float
            Confidence level in (0, 1).

        Returns
        -------
        (n, 2) array
            Lower and upper bounds, one row per parameter.
        """
        half = self.quantile(level) * self.stderr
        return np.column_stack([self.value - half, self.value + half])

    def summary(self, level: float = 0.95) -> str:
        """A plain-text table: estimates, standard errors, intervals, correlations, issues.

        Parameters
        ----------
        level : float
            Confidence level of the intervals.
        """
        ci = self.interval(level)
        how = ("known R" if self.scale == "none"
               else f"scaled by the residual variance {self.residual_variance:.3g}, "
                    f"t with {self.dof} dof")
        width = max(5, *(len(n) for n in self.names))
        lines = [f"parameters of {self.model or 'the model'} (Laplace approximation, {how}; "
                 f"{100 * level:g} % intervals)",
                 f"  {'':{width}} {'value':>12} {'stderr':>10} {'rel. %':>7} "
                 f"{'lower':>12} {'upper':>12}"]
        for name, v, s, r, (lo, hi) in zip(self.names, self.value, self.stderr,
                                           self.relative_stderr, ci, strict=True):
            lines.append(f"  {name:{width}} {v:12.6g} {s:10.3g} {100 * r:7.3g} "
                         f"{lo:12.6g} {hi:12.6g}")
        if len(self.names) > 1:
            lines.append("  correlation:")
            rho = self.correlation
            lines.append(f"  {'':{width}} " + " ".join(f"{n[:7]:>7}" for n in self.names))
            for name, row in zip(self.names, rho, strict=True):
                lines.append(f"  {name:{width}} " + " ".join(f"{c:7.3f}" for c in row))
        lines.extend("  poorly determined: " + issue for issue in self.issues)
        return "\n".join(lines)

    def __repr__(self) -> str:
        return self.summary()

    def to_pandas(self, level: float = 0.95) -> Any:
        """The table as a pandas DataFrame indexed by name (columns ``value``,
        ``stderr``, ``relative_stderr``, ``lower``, ``upper``).

        Parameters
        ----------
        level : float
            Confidence level of ``lower`` and ``upper``.
        """
        import pandas as pd

        ci = self.interval(level)
        return pd.DataFrame({"value": self.value, "stderr": self.stderr,
                             "relative_stderr": self.relative_stderr,
                             "lower": ci[:, 0], "upper": ci[:, 1]},
                            index=pd.Index(self.names, name="parameter"))


def _level(level) -> float:
    level = as_float(level, "level", expected="a number in (0, 1)")
    if not 0 < level < 1:
        raise ValueError(f"level must be a number in (0, 1), got {level!r}")
    return level


def _issues(names, value, cov, lower, upper) -> list[str]:
    """Why the parameters are poorly determined (empty when they are not)."""
    out = []
    if not np.isfinite(cov).all():
        return ["the covariance is not finite (the data do not determine the parameters)"]
    s = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if (s <= 0).any():
        return ["the covariance is singular: "
                + ", ".join(n for n, si in zip(names, s, strict=True) if si <= 0)]
    rel = [f"{n} ({si / abs(v):.2g})" if v else f"{n} (estimate 0, stderr {si:.3g})"
           for n, v, si in zip(names, value, s, strict=True)
           if si > RELATIVE_STDERR_LIMIT * abs(v)]
    if rel:
        out.append(f"relative standard error above {RELATIVE_STDERR_LIMIT:g}: "
                   + ", ".join(rel))
    rho = cov / np.outer(s, s)
    pairs = [f"{names[i]} and {names[j]} ({rho[i, j]:+.4f})"
             for i in range(len(names)) for j in range(i + 1, len(names))
             if abs(rho[i, j]) > CORRELATION_LIMIT]
    if pairs:
        out.append(f"correlation beyond ±{CORRELATION_LIMIT:g}: " + ", ".join(pairs))
    if len(names) > 1:
        lam, vec = np.linalg.eigh((rho + rho.T) / 2)
        if lam[0] < EIGENVALUE_LIMIT:
            v = vec[:, 0] / np.abs(vec[:, 0]).max()
            combo = " ".join(f"{c:+.2f}·{n}" for c, n in zip(v, names, strict=True)
                             if abs(c) > 0.05)
            out.append(f"near-singular block (smallest eigenvalue of the correlation "
                       f"{lam[0]:.2g}): the parameters are confounded, the data determine "
                       f"mainly the combination {combo} (in standard errors), "
                       f"{1 / np.sqrt(max(lam[0], 1e-300)):.3g} times better than each "
                       "alone")
    at = [n for n, v, lo, hi in zip(names, value, lower, upper, strict=True)
          if np.isclose(v, lo, rtol=1e-9, atol=0) or np.isclose(v, hi, rtol=1e-9, atol=0)]
    if at:
        out.append("at a bound, where the Laplace approximation does not hold: "
                   + ", ".join(at))
    return out


def _fit_model(fit: Fit) -> Model:
    """The model a fit was made with."""
    context = getattr(fit, "_context", None)
    if context is None:
        raise ValueError("this FitResult does not know its model: pass the model as "
                         "source with x and P, e.g. parameter_uncertainty(model, "
                         "res.x[-1], res.P_last)")
    return context[0]


def _is_estimator(source: object) -> bool:
    """Whether ``source`` is an estimator (:class:`~estim.Estimator`): it has a model, a
    ``step`` and reports ``info``. Told by what it has, so that this module sits below
    the estimators (full-information estimation's fits call it)."""
    return all(hasattr(source, name) for name in ("model", "step", "reset", "info"))


def _is_fit(source: object) -> bool:
    """Whether ``source`` is a fit (:class:`Fit`), told without evaluating its lazy
    covariance or residuals."""
    return (not isinstance(source, Model) and not _is_estimator(source)
            and hasattr(source, "_context")
            and all(hasattr(type(source), name) for name in ("P_last", "v")))


def _source(source, x, P) -> tuple[Model, np.ndarray | None, np.ndarray | None, Any]:
    """``(model, x, P, fit or None)`` of a fit, an estimator or a model; ``x`` and ``P``
    override the source's."""
    if _is_fit(source):
        return (_fit_model(source), source.x[-1] if x is None else x,
                source.P_last if P is None else P, source)
    if _is_estimator(source):
        if x is None:
            extra = source.info.extra
            traj = extra.get("window", extra.get("trajectory"))
            if traj is None:
                raise ValueError(f"{type(source).__name__} does not report its last "
                                 "estimate: pass x (the estimate step returned)")
            x = traj[-1]
        return source.model, x, source.info.P if P is None else P, None
    if isinstance(source, Model):
        if x is None or P is None:
            raise ValueError("with a model as source, x (nx,) and P (nx, nx) are required")
        return source, x, P, None
    raise TypeError("source must be a FitResult, an estimator or a Model, got "
                    f"{type(source).__name__}")


def _values(fit: Fit) -> dict[str, float]:
    """The augmented parameters' last values of a fit, by name."""
    model, x = _fit_model(fit), fit.x[-1]
    if not model.augmented:
        raise ValueError(f"model {model.name!r} has no augmented parameters: identify "
                         "parameters as states with model.augment('name', ...)")
    return {n: float(x[model.state_names.index(n)]) for n in model.augmented}


def _estimates(source, x=None, P=None, scale: str = "none", warn: bool = True,
               stacklevel: int = 2) -> ParameterEstimates:
    """:func:`parameter_uncertainty` (``stacklevel``: of the warning)."""
    scale = as_choice(scale, _SCALES, "scale")
    model, x, P, fit = _source(source, x, P)
    if not model.augmented:
        raise ValueError(f"model {model.name!r} has no augmented parameters: identify "
                         "parameters as states with model.augment('name', ...)")
    if fit is not None and not fit.success:
        raise ValueError(f"the fit did not succeed (status {fit.status!r}): no covariance "
                         "to report")
    if P is None:
        raise ValueError("no covariance: the estimator reports none (info.P is None: no step "
                         "yet, or a failed one) or the fit's covariance is not finite (a state "
                         "the data do not determine; see estim.observability.window)")
    x = as_vector(x, model.nx, "x")
    P = np.asarray(P, dtype=float)
    if P.shape != (model.nx, model.nx):
        raise ValueError(f"P must have shape ({model.nx}, {model.nx}), got {P.shape}")
    names = tuple(model.augmented)
    idx = [model.state_names.index(n) for n in names]
    value, cov = x[idx].copy(), P[np.ix_(idx, idx)].copy()
    cov = (cov + cov.T) / 2
    s2, dof = float("nan"), None
    if fit is not None:
        measured = int(np.isfinite(fit.v).sum())
        nu = measured - model.nx + (model.nx if fit._context[1] else 0)
        if nu > 0:
            s2 = float(fit.cost) / nu
        if scale == "residual":
            if nu <= 0:
                raise ValueError(f"scale='residual' needs more measured values ({measured}) "
                                 f"than unknown initial states ({model.nx})")
            cov, dof = cov * s2, nu
    elif scale == "residual":
        raise ValueError("scale='residual' needs a FitResult (its cost and degrees of "
                         "freedom); an estimator's covariance is reported as it is")
    if fit is not None:
        lower, upper = fit._context[2], fit._context[3]
    else:
        lower = getattr(source, "lower", model.lower)
        upper = getattr(source, "upper", model.upper)
    issues = _issues(names, value, cov, np.asarray(lower)[idx], np.asarray(upper)[idx])
    if issues and warn:
        warnings.warn(
            f"poorly determined parameters of {model.name}: " + "; ".join(issues)
            + ". Their intervals are unreliable: the data hardly inform them. See the "
            "Fisher information of the record, estim.observability.window(model, x0, "
            "n_steps, inputs, R).fisher (its inverse is this covariance for constant "
            "parameters), and add excitation, a prior, or fix them.",
            EstimationWarning, stacklevel=stacklevel + 1)
    return ParameterEstimates(names=names, value=value, covariance=cov, scale=scale,
                              residual_variance=s2, dof=dof, model=model.name,
                              issues=tuple(issues))


@check_keywords
def parameter_uncertainty(source: Fit | Estimator | Model, x: ArrayLike | None = None,
                          P: ArrayLike | None = None, *, scale: str = "none",
                          warn: bool = True) -> ParameterEstimates:
    r"""Standard errors, correlations and confidence intervals of augmented parameters.

    The parameters :math:`\theta` of ``model.augment(...)`` are the last states; their
    covariance is the :math:`\theta` block of the estimate's covariance, for a fit the
    Laplace approximation :math:`[(J^\top J)^{-1}]_{\theta\theta}` at the optimum
    (``FitResult.P_last``; see :mod:`estim.uncertainty`):

    .. math::
        \sigma_i = \sqrt{(\Sigma_\theta)_{ii}}, \qquad
        \rho_{ij} = \frac{(\Sigma_\theta)_{ij}}{\sigma_i\sigma_j}, \qquad
        \hat\theta_i \pm 1.96\, \sigma_i \;(95\,\%).

    Warns (:class:`~estim.EstimationWarning`) when some parameters are poorly
    determined: a standard error above half the estimate, a correlation beyond
    ±0.99, a near-singular block, a parameter at a bound.

    Parameters
    ----------
    source : FitResult, Estimator or Model
        A :meth:`~estim.FullInformation.fit` of an augmented model (its last state and
        ``P_last``); an estimator after a step (``info.P``; the last estimate of
        :class:`~estim.MHE` and of :class:`~estim.FullInformation`, others need ``x``),
        e.g. MHE's window covariance, which includes the arrival cost; or the augmented
        model itself with ``x`` and ``P`` (e.g. ``log.x_hat[-1]``, ``log.P[-1]`` of an
        EKF run).
    x : (nx,) array, optional
        The estimate (default: the source's last).
    P : (nx, nx) array, optional
        Its covariance (default: the source's).
    scale : {"none", "residual"}
        ``"none"``: ``R`` is the known noise covariance, nothing is rescaled.
        ``"residual"`` (fits only): ``R`` is known up to a factor; the covariance is
        multiplied by :math:`s^2 = V/\nu` (cost over :math:`\nu` = measured values
        minus :math:`n_x`, plus :math:`n_x` with a prior) and the intervals use
        Student's :math:`t_\nu` (scipy's ``curve_fit`` with ``absolute_sigma=False``).
    warn : bool
        Warn about poorly determined parameters (they are listed in ``issues``
        either way).

    Returns
    -------
    ParameterEstimates

    Raises
    ------
    ValueError
        The model has no augmented parameters, the fit failed, or there is no
        covariance.

    References
    ----------
    L. Tierney, J. B. Kadane (1986), JASA 81(394); G. A. F. Seber, C. J. Wild (1989),
    *Nonlinear Regression*, ch. 5.
    """
    return _estimates(source, x, P, scale=scale, warn=warn, stacklevel=3)
