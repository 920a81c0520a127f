r"""Maximum-likelihood noise covariances: the prediction-error likelihood of the EKF or UKF.

A Kalman filter run with covariances :math:`Q, R` (and model parameters :math:`p`) turns
a record :math:`y_0, \dots, y_{T-1}` into innovations :math:`e_k = y_k - \hat y_{k|k-1}`
with covariances :math:`S_k`. For a linear-Gaussian model they are independent Gaussians,
and the likelihood of the record factorises into theirs (Schweppe 1965):

.. math::
    -\log L(\theta) = \tfrac12 \sum_{k \ge b} \left( \log\det S_k + e_k^\top S_k^{-1} e_k
    + m_k \log 2\pi \right)

(:math:`m_k` outputs measured at sample :math:`k`, the first :math:`b` samples left out
by ``burn``). For a nonlinear model the EKF (UKF) gives the same expression with its
approximate innovations: the prediction-error likelihood (Ljung 1999, ch. 7). The whole
recursion is one CasADi graph (the filter step scanned over the record), so the gradient
of :math:`-\log L` with respect to :math:`\theta` is exact, by algorithmic
differentiation through every step of the filter (and so is the Hessian on request).

The pieces: the filter step and the whole-record graph (:mod:`~estim.tuning._ml_graph`),
the parametrisation of ``Q``, ``R`` and the model parameters
(:mod:`~estim.tuning._ml_parametrisation`), the multi-start optimiser with its Newton
polish (:mod:`~estim.tuning._ml_optimiser`), and the standard errors and the verdict
(:mod:`~estim.tuning._ml_uncertainty`).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_bool, as_choice, as_covariance, as_float, as_int, as_seed
from estim.estimators.kalman.ukf import POINTS
from estim.model import Model
from estim.tuning._ml_graph import DIFFUSE_VARIANCE, _core, _Record, noise_dim
from estim.tuning._ml_optimiser import _check_method, _Objective, _optimise
from estim.tuning._ml_parametrisation import (
    STRUCTURES,
    _Parametrisation,
    _params_spec,
    _structures,
)
from estim.tuning._ml_uncertainty import _estimates
from estim.tuning._result import TuningResult, innovation_check

__all__ = ["DIFFUSE_VARIANCE", "ESTIMATORS", "STRUCTURES", "log_likelihood",
           "maximum_likelihood"]

ESTIMATORS = ("ekf", "ukf")


def log_likelihood(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
                   Q: ArrayLike | None = None, R: ArrayLike, x0: ArrayLike | None = None,
                   P0: ArrayLike | None = None, params: Mapping[str, float] | None = None,
                   estimator: str = "ekf", burn: int | None = None, alpha: float = 1.0,
                   beta: float = 2.0, kappa: float = 0.0, points: str = "merwe",
                   order: int = 3, Qc: ArrayLike | None = None, t: ArrayLike | None = None,
                   substeps: int = 4) -> float:
    r"""The prediction-error log-likelihood of a record under the EKF or UKF.

    .. math::
        \log L = -\tfrac12 \sum_{k=b}^{T-1} \left( \log\det S_k
        + e_k^\top S_k^{-1} e_k + m_k \log 2\pi \right),

    with the innovations :math:`e_k = y_k - \hat y_{k|k-1}` and their covariances
    :math:`S_k` of the filter (``estim.EKF`` or ``estim.UKF`` with the same ``Q, R, x0,
    P0``; the first sample is an update of the prior ``x0, P0``), over the :math:`m_k`
    outputs measured at sample :math:`k` (NaN in ``Y``: missing).

    Parameters
    ----------
    model : Model
    Y : (T, ny) array
        Measurements, NaN where missing (``T >= 2``).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as :func:`~estim.replay` takes them (``U[k]`` acts after sample ``k``).
    Q, R : float, vector of variances or matrix
        Process- and measurement-noise covariances.
    x0, P0 : optional
        Prior of the first state; default the approximate diffuse prior
        :math:`x_0 = 0`, :math:`P_0 = 10^6 I`.
    params : dict, optional
        Model parameter values to use instead of the model's.
    estimator : {"ekf", "ukf"}
    burn : int, optional
        Number :math:`b` of first samples whose terms are left out (the filter still
        uses them). Default 0, or ``nx`` with the diffuse prior (statsmodels'
        ``loglikelihood_burn``).
    alpha, beta, kappa, points, order :
        The UKF's sigma points (as :class:`~estim.UKF`: ``points`` one of ``"merwe"``,
        ``"julier"``, ``"cubature"``, ``"gauss-hermite"`` of ``order``).
    Qc, substeps :
        Instead of ``Q``, on a continuous model: the spectral density of a
        continuous-time noise (as the filters' ``Qc=``, ``(nq, nq)`` for the ``nq``
        columns of the model's ``noise_input``), the moment equations integrated by
        ``substeps`` Runge-Kutta steps per interval (docs/continuous_noise.md).
    t : (T,) array, optional
        Sample times, for a model built with ``variable_dt=True``.

    Returns
    -------
    float
        :math:`\log L` (``-inf`` where the filter breaks down).

    References
    ----------
    F. C. Schweppe, "Evaluation of likelihood functions for Gaussian signals", IEEE
    Trans. Inf. Theory 11(1), 1965; J. Durbin, S. J. Koopman, *Time Series Analysis by
    State Space Methods*, 2nd ed., Oxford 2012, sec. 7.2.
    """
    model, kind, ukf = _check_common(model, estimator, alpha, beta, kappa, points, order)
    if (Q is None) == (Qc is None):
        raise ValueError("give Q= (a covariance per transition) or Qc= (a spectral density "
                         "per unit time, on a continuous model), one of them")
    if Qc is not None:
        kind = _continuous_kind(model, kind, substeps)
    rec = _Record(model, Y, U, x0, P0, burn, t)
    Qm = as_covariance(Q if Qc is None else Qc, noise_dim(model, kind),
                       "Q" if Qc is None else "Qc", definite=False)
    Rm = as_covariance(R, model.ny, "R", definite=True)
    p = model.p.copy()
    for k, v in _params_spec(model, params or {}).items():
        p[model.param_names.index(k)] = v
    core = _core(model, kind, rec.T, ukf)
    nll = float(core(Qm.ravel(order="F"), Rm.ravel(order="F"), p, *rec.data())[0])
    return -nll if np.isfinite(nll) else -np.inf


def _continuous_kind(model: Model, kind: str, substeps: object) -> str:
    """The likelihood graph's kind with a continuous noise (``"ekf@4"``: the filter, the
    Runge-Kutta sub-steps of its moments), checked."""
    substeps = as_int(substeps, "substeps", minimum=1)
    if not model.continuous or model.nz or not model.manifold.trivial:
        raise ValueError("a continuous noise (Qc) needs a continuous model (ode=) on vector "
                         "states without algebraic equations")
    return f"{kind}@{substeps}"


def _check_common(model: object, estimator: str, alpha: float, beta: float, kappa: float,
                  points: str = "merwe", order: int = 3) -> tuple[Model, str, tuple]:
    """The model, the filter's kind and the UKF's ``(points, order, alpha, beta, kappa)``,
    checked."""
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    kind = as_choice(estimator, ESTIMATORS, "estimator")
    ukf = (as_choice(points, POINTS, "points"), as_int(order, "order", minimum=1),
           as_float(alpha, "alpha", positive=True), as_float(beta, "beta"),
           as_float(kappa, "kappa"))
    if kind == "ukf" and ukf[0] in ("merwe", "julier") and model.nx + ukf[4] <= 0:
        raise ValueError(f"kappa must make nx + kappa positive for the UKF's sigma points "
                         f"(nx = {model.nx}), got {kappa!r}")
    return model, kind, ukf


def maximum_likelihood(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
                       estimator: str = "ekf", Q0: ArrayLike | None = None,
                       R0: ArrayLike | None = None, x0: ArrayLike | None = None,
                       P0: ArrayLike | None = None,
                       params: Sequence[str] | Mapping[str, float] | None = None,
                       structure: str | Mapping[str, str] = "diagonal", starts: int = 5,
                       seed: int | None = 0, spread: float = 1.0, burn: int | None = None,
                       method: str = "BFGS", hessian: str = "differences", tol: float = 1e-8,
                       max_iter: int = 200,
                       alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0,
                       points: str = "merwe", order: int = 3, continuous: bool = False,
                       t: ArrayLike | None = None, substeps: int = 4,
                       param_spread: float = 0.0) -> TuningResult:
    r"""Noise covariances (and model parameters) that maximise the likelihood of a record.

    Minimises the prediction-error negative log-likelihood of the EKF (or UKF)

    .. math::
        \ell(\theta) = -\log L(\theta) = \tfrac12 \sum_{k=b}^{T-1} \left( \log\det S_k(\theta)
        + e_k(\theta)^\top S_k(\theta)^{-1} e_k(\theta) + m_k \log 2\pi \right)

    (see :func:`log_likelihood`) over :math:`\theta`: the noise covariances, kept
    positive definite by their parametrisation, and optionally model parameters.

    * ``structure="diagonal"``: :math:`\theta` holds the log-variances,
      :math:`Q = \operatorname{diag}(e^{\theta_1}, \dots)`; ``"full"``: the
      log-Cholesky factor, :math:`Q = LL^\top` with :math:`L_{ii} = e^{\theta_{ii}}`
      and :math:`L_{ij} = \theta_{ij}` below the diagonal (Pinheiro & Bates 1996);
      ``"scalar"``: :math:`Q = e^{\theta} I`; ``"fixed"``: held at ``Q0``. A dict
      ``{"Q": ..., "R": ...}`` sets each matrix's structure.
    * The filter recursion over the whole record is one compiled CasADi graph (the
      filter step scanned with ``mapaccum``, built once per model, filter and record
      length), so :math:`\nabla\ell` is exact (algorithmic differentiation through
      every step); :math:`\nabla^2\ell` is its central differences, or exact by AD
      (``hessian``). Each start runs scipy's BFGS with the exact
      gradient (on :math:`\ell` per measured output, whose steps are of order one
      whatever the record's length) into the basin of Newton's method; the best optimum
      is then polished by Newton steps with the Hessian and a backtracking line search,
      and declared converged when the Hessian is positive definite and the gain a Newton
      step still predicts, :math:`\frac12 \nabla\ell^\top (\nabla^2\ell)^{-1}
      \nabla\ell`, is below ``tol`` (or the rounding level of :math:`\ell`).
    * Multi-start: the first start is ``Q0, R0`` (and the parameters' starts), the
      others perturb the noise parameters by :math:`\mathcal N(0, \text{spread}^2)` on
      the log scale and, with ``param_spread``, each model parameter by the factor
      :math:`e^{\mathcal N(0, \text{param\_spread}^2)}` (seeded); the best optimum is
      returned. A local optimum has a positive definite Hessian and small standard errors
      like the global one: where the likelihood is rugged (a chaotic model seen sparsely)
      only several starts over the parameters can tell them apart.
    * Standard errors: the inverse observed information
      :math:`\operatorname{cov}\hat\theta \approx \nabla^2\ell(\hat\theta)^{-1}`, taken to
      the entries of ``Q``, ``R`` by the delta method,
      :math:`\operatorname{cov} g(\hat\theta) \approx J \nabla^2\ell^{-1} J^\top`,
      :math:`J = \partial g / \partial\theta`.

    Parameters
    ----------
    model : Model
    Y : (T, ny) array
        Measurements, NaN where missing (``T >= 2``).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as :func:`~estim.replay` takes them.
    estimator : {"ekf", "ukf"}
        The filter whose likelihood is maximised.
    Q0, R0 : float, vector of variances or matrix, optional
        Starting covariances (and the values held by ``"fixed"``). Default: ``R0`` half
        the sample variance of each output, ``Q0`` :math:`10^{-2}` times the diagonal of
        ``P0``.
    x0, P0 : optional
        Prior of the first state, as for the filters; default the approximate diffuse
        prior :math:`x_0 = 0`, :math:`P_0 = 10^6 I`.
    params : list of str or dict, optional
        Model parameters estimated along, by name (starting at the model's values), or
        ``{name: start}``.
    structure : {"diagonal", "full", "scalar", "fixed"} or dict
        Parametrisation of ``Q`` and ``R``.
    starts : int
        Number of starts (>= 1); one when nothing is perturbed (every covariance
        ``"fixed"``, or ``spread=0``).
    seed : int, optional
        Seed of the perturbed starts.
    spread : float
        Standard deviation of the perturbations of the log-variances (natural log).
    param_spread : float
        Standard deviation of the perturbations of the model parameters' logs (relative
        changes; default 0: the parameters start where given at every start).
    burn : int, optional
        Number of first samples whose terms are left out of the likelihood. Default 0,
        or ``nx`` with the diffuse prior (statsmodels' ``loglikelihood_burn``).
    method : str
        The scipy.optimize.minimize method of each start: ``"BFGS"`` (default),
        ``"L-BFGS-B"``, ``"CG"``, ``"TNC"``, ``"SLSQP"`` (exact gradient, then the Newton
        polish), or ``"trust-exact"``, ``"trust-krylov"``, ``"trust-ncg"``,
        ``"trust-constr"``, ``"Newton-CG"``, ``"dogleg"`` (the Hessian at every
        iteration, no polish).
    hessian : {"differences", "exact"}
        The Hessian of the polish and of the standard errors: central differences of the
        exact gradient (:math:`2 n_\theta` gradients; they agree with the exact Hessian to
        about :math:`10^{-9}`), or ``"exact"``, by algorithmic differentiation (forward
        over reverse through the scan), whose graph takes longer to build than a fit of a
        short record lasts (0.14 s at 100 samples, 0.8 s at 1000, 1.3 s at 2000; once per
        model and record length).
    tol : float
        The largest gain of :math:`\log L` a Newton step may still predict at a
        converged optimum (and the gradient tolerance ``gtol`` of the Hessian methods,
        on :math:`\ell` per measured output).
    max_iter : int
        Iterations per start.
    alpha, beta, kappa : float
        The UKF's sigma-point parameters.
    continuous, substeps :
        Estimate the spectral density :math:`Q_c` of a continuous-time noise instead of a
        per-transition ``Q`` (``Q0`` then starts it, and the result's ``Q`` is
        :math:`Q_c`, ``(nq, nq)`` for the ``nq`` columns of the model's ``noise_input``: a
        density per noise channel), the filter's moment equations
        integrated by ``substeps`` Runge-Kutta steps per interval (docs/continuous_noise.md).
    t : (T,) array, optional
        Sample times, for a model built with ``variable_dt=True`` (irregular stamps).

    Returns
    -------
    TuningResult
        ``method="maximum likelihood"``, ``Q``, ``R``, ``params``, ``stderr`` (NaN for
        entries the structure holds fixed), ``check`` (the innovations of the filter with
        the estimates), ``objective`` :math:`\ell(\hat\theta)`, and ``details`` with
        ``"starts"`` (each start's objective), ``"optima"`` (the different values of
        :math:`\ell` the starts ended at, more than one unit apart: several is a
        multimodal likelihood, said in ``status``), ``"iterations"`` (per start),
        ``"polish_iterations"``, ``"evaluations"`` (of :math:`\ell` and its gradient),
        ``"theta"``, ``"covariance"`` (of :math:`\hat\theta`), ``"log_likelihood"``,
        ``"compile_time"`` and ``"fit_time"`` (seconds).

    Notes
    -----
    The likelihood assumes Gaussian noises, independent in time, and (for a nonlinear
    model) that the filter's innovations are close to Gaussian with covariance
    :math:`S_k`; the standard errors are asymptotic (large :math:`T`, an interior
    optimum). A variance whose estimate runs to zero (the likelihood largest without that
    noise) has a log going to :math:`-\infty`: the status then starts with
    ``"boundary: "``, names the entry, and its standard errors are NaN.

    References
    ----------
    F. C. Schweppe, "Evaluation of likelihood functions for Gaussian signals", IEEE
    Trans. Inf. Theory 11(1), 1965; R. K. Mehra, "On the identification of variances
    and adaptive Kalman filtering", IEEE Trans. Autom. Control 15(2), 1970;
    J. Durbin, S. J. Koopman, *Time Series Analysis by State Space Methods*, 2nd ed.,
    Oxford 2012, ch. 7; J. C. Pinheiro, D. M. Bates, "Unconstrained parametrizations for
    variance-covariance matrices", Statistics and Computing 6, 1996.
    """
    t_start = time.perf_counter()
    model, kind, ukf = _check_common(model, estimator, alpha, beta, kappa, points, order)
    if as_bool(continuous, "continuous"):
        kind = _continuous_kind(model, kind, substeps)
    rec = _Record(model, Y, U, x0, P0, burn, t)
    structures = _structures(structure)
    starts = as_int(starts, "starts", minimum=1)
    seed = as_seed(seed)
    spread = as_float(spread, "spread", minimum=0.0)
    param_spread = as_float(param_spread, "param_spread", minimum=0.0)
    tol = as_float(tol, "tol", positive=True)
    max_iter = as_int(max_iter, "max_iter", minimum=1)
    method = _check_method(method)
    hessian = as_choice(hessian, ("differences", "exact"), "hessian")
    spec = _params_spec(model, params)
    for k, v in spec.items():
        if not np.isfinite(v):
            raise ValueError(f"params[{k!r}] needs a finite start")
    if R0 is None:
        var = np.array([np.nanvar(rec.Y[i][rec.measured[:, i]]) for i in range(model.ny)])
        R0 = np.maximum(0.5 * var, 1e-12)
    nq = noise_dim(model, kind)
    if Q0 is None:  # a hundredth of the prior's variance, seen through the noise input
        L = model.noise_input if "@" in kind else None
        G = np.eye(nq) if L is None else np.linalg.pinv(L)
        Q0 = 1e-2 * np.diag(np.diag(G @ rec.P0 @ G.T))
    Q0m = as_covariance(Q0, nq, "Q0", definite=False)
    R0m = as_covariance(R0, model.ny, "R0", definite=True)
    if structures["Q"] == "fixed" and structures["R"] == "fixed" and not spec:
        raise ValueError("nothing to estimate: structure holds Q and R fixed and params is "
                         "empty")
    par = _Parametrisation(model, structures, Q0m, R0m, spec)
    measured = int(rec.measured[rec.burn:].sum())
    if measured <= len(par.theta0):
        raise ValueError(f"Y has {measured} measured values after the burn-in for "
                         f"{len(par.theta0)} free parameters: a maximum-likelihood fit needs "
                         f"more data than parameters (a longer record, or a structure with "
                         f"fewer free entries)")

    t0 = time.perf_counter()
    obj = _Objective(model, kind, rec.T, ukf, par, rec.data(), hessian)
    f0, _ = obj(par.theta0)  # the first evaluation builds the derivative graphs
    compile_time = time.perf_counter() - t0

    opt = _optimise(obj, par, f0, starts, seed, spread, method, tol, max_iter, param_spread)
    est = _estimates(par, opt, tol, nq, model.ny)
    optima = _distinct_optima([r.fun for r in opt.runs if r is not None], opt.nll)
    status = est.status if len(optima) < 2 else est.status + (
        f"; the starts ended at {len(optima)} different optima (-log L "
        f"{', '.join(f'{v:.6g}' for v in optima)}): the likelihood is multimodal here, the "
        f"best is returned and the standard errors are those of its own basin")
    eps = obj.whitened(opt.theta)
    eps[~rec.measured] = np.nan
    eps[:rec.burn] = np.nan
    details = {
        "starts": [float(r.fun) if r is not None else float("inf") for r in opt.runs],
        "best_start": opt.best,
        "iterations": [int(getattr(r, "nit", 0)) if r is not None else 0 for r in opt.runs],
        "evaluations": obj.evaluations,
        "theta": opt.theta,
        "covariance": est.cov_theta,
        "gradient": opt.grad,
        "log_likelihood": -float(opt.nll),
        "optimizer": method,
        "hessian": "exact" if obj.exact else "differences",
        "polish_iterations": opt.polish,
        "newton_decrement": est.decrement,
        "message": opt.message,
        "compile_time": compile_time,
        "fit_time": time.perf_counter() - t_start,
        "structure": structures,
        "burn": rec.burn,
        "estimator": kind.partition("@")[0],
        "noise": "continuous (Q is the spectral density Qc)" if "@" in kind else
        "per transition",
    }
    return TuningResult(method="maximum likelihood", Q=est.Q, R=est.R, params=est.params,
                        stderr=est.stderr, check=innovation_check(eps),
                        objective=float(opt.nll), success=est.success, status=status,
                        details={**details, "optima": optima})


#: Starts whose negative log-likelihoods differ by more than this ended at different
#: optima (a likelihood ratio of e: twice it is the chi-square(1) quantile 0.84).
DISTINCT_OPTIMA = 1.0


def _distinct_optima(values: Sequence[float], best: float) -> list[float]:
    """The different optima among the starts' final ``-log L`` ``values`` (the polished
    ``best`` for the lowest): sorted, those within :data:`DISTINCT_OPTIMA` of the one
    below merged."""
    out = [float(best)]
    for v in sorted(float(x) for x in values if np.isfinite(x)):
        if v > out[-1] + DISTINCT_OPTIMA:
            out.append(v)
    return out
