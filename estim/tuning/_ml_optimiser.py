r"""The optimiser of maximum likelihood: multi-start quasi-Newton, then a Newton polish.

:math:`\ell(\theta) = -\log L(\theta)` and its exact gradient come from the compiled
graph (:mod:`~estim.tuning._ml_graph`); its Hessian from central differences of that
gradient or from algorithmic differentiation. Each start runs a scipy method on
:math:`\ell` per measured output (values and steps of order one whatever the record's
length) into the basin of Newton's method; the best optimum is then polished by Newton
steps :math:`d = -\nabla^2\ell^{-1}\nabla\ell` with a backtracking (Armijo) line search
until the gain a Newton step still predicts,

.. math::
    \tfrac12 \nabla\ell^\top (\nabla^2\ell)^{-1} \nabla\ell,

is below the tolerance (or the rounding level of :math:`\ell`); where the Hessian is
not positive definite on the way a trust region finishes (Nocedal & Wright 2006,
ch. 3-4).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import casadi as ca
import numpy as np

from estim._validate import as_choice
from estim.model import Model
from estim.tuning._ml_graph import _CORES, _core
from estim.tuning._ml_parametrisation import _Parametrisation

#: The scipy methods that use the Hessian at every iteration (no Newton polish after).
_HESSIAN_METHODS = ("trust-exact", "trust-krylov", "trust-ncg", "trust-constr", "Newton-CG",
                    "dogleg")
#: The scipy methods that use the gradient only (then the Newton polish).
_GRADIENT_METHODS = ("L-BFGS-B", "BFGS", "CG", "TNC", "SLSQP")


class _Objective:
    """``-log L(theta)`` with its exact gradient and its Hessian for one record."""

    def __init__(self, model: Model, kind: str, T: int, ukf: tuple,
                 par: _Parametrisation, data: list[np.ndarray], hessian: str):
        key = ("objective", kind, T, ukf if kind.startswith("ukf") else None, par.key)
        cache = _CORES.setdefault(model, {})
        if key not in cache:
            core = _core(model, kind, T, ukf)
            theta = ca.MX.sym("theta", par.theta0.size)
            fixed = ca.MX.sym("fixed", par.fixed.size)
            args = [ca.MX.sym(n, core.size_in(i)) for i, n in enumerate(core.name_in())][3:]
            nll, eps = core(*par.unpack(theta, fixed), *args)
            inputs = [theta, fixed, *args]
            cache[key] = {
                "fg": ca.Function("nll_grad", inputs, [nll, ca.gradient(nll, theta)]),
                "whitened": ca.Function("whitened", inputs, [eps]),
                "hessian": lambda: ca.Function("nll_hess", inputs,  # built when first used
                                               [ca.hessian(nll, theta)[0]])}
        self._funs = cache[key]
        self._fg, self._eps = self._funs["fg"], self._funs["whitened"]
        self._data = [par.fixed, *data]
        # 1 / the number of measured outputs in the likelihood
        self.scale = 1.0 / max(1.0, float(np.sum(data[3] * data[5])))
        self.exact = hessian == "exact"
        self.evaluations = 0

    def __call__(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        self.evaluations += 1
        f, g = self._fg(theta, *self._data)
        f, g = float(f), np.asarray(g, dtype=float).ravel()
        if not (np.isfinite(f) and np.isfinite(g).all()):
            return np.inf, np.zeros_like(g)
        return f, g

    def hessian(self, theta: np.ndarray) -> np.ndarray:
        r"""The exact Hessian (AD, forward over reverse), or central differences of the
        exact gradient, :math:`(\nabla\ell(\theta + h e_i) - \nabla\ell(\theta - h e_i))
        / 2h` with :math:`h = 10^{-4}\max(1, |\theta_i|)`."""
        theta = np.asarray(theta, dtype=float)
        if self.exact:
            if callable(self._funs["hessian"]) and not isinstance(self._funs["hessian"],
                                                                  ca.Function):
                self._funs["hessian"] = self._funs["hessian"]()
            H = np.asarray(self._funs["hessian"](theta, *self._data), dtype=float)
        else:
            n = theta.size
            H = np.empty((n, n))
            for i in range(n):
                h = 1e-4 * max(1.0, abs(theta[i]))
                step = np.zeros(n)
                step[i] = h
                gp = np.asarray(self._fg(theta + step, *self._data)[1], dtype=float).ravel()
                gm = np.asarray(self._fg(theta - step, *self._data)[1], dtype=float).ravel()
                H[:, i] = (gp - gm) / (2 * h)
        return 0.5 * (H + H.T) if np.isfinite(H).all() else np.full_like(H, np.nan)

    def whitened(self, theta: np.ndarray) -> np.ndarray:
        """The whitened innovations ``(T, ny)`` of the filter at ``theta``."""
        return np.asarray(self._eps(theta, *self._data), dtype=float).T


def _limit(tol: float, f: float) -> float:
    """The Newton gain below which an optimum is converged: ``tol``, or the rounding
    level of the objective's value when that is larger."""
    return max(tol, 1e3 * np.finfo(float).eps * abs(f))


def _newton(obj: _Objective, theta: np.ndarray, tol: float, max_iter: int
            ) -> tuple[np.ndarray, np.ndarray | None, int]:
    r"""Newton steps :math:`d = -H^{-1} g` with a backtracking (Armijo) line search until
    the predicted gain :math:`\frac12 g^\top H^{-1} g` is below the limit of
    :func:`_limit`. Returns the point, its Hessian (None if it is not positive
    definite, NaN if it is not finite) and the number of steps."""
    f, g = obj(theta)
    for it in range(max_iter):
        H = obj.hessian(theta)
        if not np.isfinite(H).all():  # the filter breaks down next to theta: stop here
            return theta, H, it
        try:
            L = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            return theta, None, it
        d = -np.linalg.solve(L.T, np.linalg.solve(L, g))
        gain = -0.5 * float(g @ d)
        if gain <= _limit(tol, f):  # converged: the last full step costs one evaluation
            fn, _ = obj(theta + d)
            return (theta + d if fn <= f + _limit(tol, f) else theta), H, it
        t = 1.0
        while t > 1e-10:
            fn, gn = obj(theta + t * d)
            if fn <= f - 1e-4 * t * 2 * gain:
                break
            t *= 0.5
        else:
            return theta, H, it
        theta, f, g = theta + t * d, fn, gn
    return theta, obj.hessian(theta), max_iter


def _minimize(obj: _Objective, theta: np.ndarray, method: str, tol: float, max_iter: int
              ) -> Any:
    """One local minimisation with scipy, the exact gradient (and Hessian where used);
    returns scipy's ``OptimizeResult`` with ``fun`` the value of ``obj``."""
    from scipy.optimize import minimize

    options: dict = {"maxiter": max_iter, "gtol": tol}
    if method == "L-BFGS-B":  # no stop on a small relative decrease: flat likelihoods
        options["ftol"] = 1e-15
    elif method == "TNC":
        options = {"maxfun": 20 * max_iter, "gtol": tol, "ftol": 0.0}
    elif method == "Newton-CG":
        options = {"maxiter": max_iter, "xtol": tol}
    elif method == "SLSQP":
        options = {"maxiter": max_iter, "ftol": tol}
    c = obj.scale  # -log L per measured output: O(1) values and steps for any record

    def fun(th: np.ndarray) -> tuple[float, np.ndarray]:
        f, g = obj(th)
        return f * c, g * c

    hess = (lambda th: obj.hessian(th) * c) if method in _HESSIAN_METHODS else None
    res = minimize(fun, theta, jac=True, hess=hess, method=method, options=options)
    res.fun = res.fun / c
    return res


def _check_method(method: object) -> str:
    return as_choice(method, _HESSIAN_METHODS + _GRADIENT_METHODS, "method")


@dataclass
class _Optimum:
    r"""The best of the starts, polished: ``theta`` with ``nll`` :math:`=\ell(\theta)`,
    its gradient and Hessian ``H``; every start's scipy result (``runs``, None where
    the filter broke down), the ``best`` one's index and message, and the number of
    ``polish`` iterations."""

    theta: np.ndarray
    nll: float
    grad: np.ndarray
    H: np.ndarray
    runs: list[Any | None]
    best: int
    message: str
    polish: int


def _optimise(obj: _Objective, par: _Parametrisation, f0: float, starts: int,
              seed: int | None, spread: float, method: str, tol: float, max_iter: int,
              param_spread: float = 0.0) -> _Optimum:
    r"""Minimise ``obj`` from ``par.theta0`` (whose value is ``f0``) and ``starts - 1``
    starts whose noise parameters are perturbed by :math:`\mathcal N(0,
    \text{spread}^2)` and model parameters by the factor :math:`e^{\mathcal N(0,
    \text{param\_spread}^2)}` (seeded), then polish the best with Newton steps (for the
    gradient methods)."""
    rng = np.random.default_rng(seed)
    thetas = [par.theta0]
    n_par = par.theta0.size - par.n_noise
    varied = (par.n_noise and spread > 0) or (n_par and param_spread > 0)
    for _ in range(starts - 1 if varied else 0):  # else all the same
        th = par.theta0.copy()
        th[:par.n_noise] += spread * rng.standard_normal(par.n_noise)
        if n_par and param_spread > 0:  # (no draw otherwise: the same starts as before)
            th[par.n_noise:] *= np.exp(param_spread * rng.standard_normal(n_par))
        thetas.append(th)
    runs: list[Any | None] = []
    for th in thetas:
        if th is par.theta0 and not np.isfinite(f0):
            runs.append(None)
            continue
        # quasi-Newton to the basin of Newton's method, which the polish then finishes
        res = _minimize(obj, th, method, tol if method in _HESSIAN_METHODS else
                        max(tol, 1e-5), max_iter)
        runs.append(res if np.isfinite(res.fun) else None)
    found = {i: r for i, r in enumerate(runs) if r is not None}
    if not found:
        raise ValueError("the filter breaks down (a non-finite likelihood) at every start: "
                         "check Q0, R0, x0, P0 and the model")
    best = min(found, key=lambda i: found[i].fun)
    res = found[best]
    polish, H = 0, None
    theta = np.asarray(res.x, dtype=float)
    if method not in _HESSIAN_METHODS:  # Newton steps with the Hessian from the best
        theta, H, polish = _newton(obj, theta, tol, max_iter)
        if H is None:  # not positive definite on the way: a trust region copes
            fine = _minimize(obj, theta, "trust-exact", tol, max_iter)
            polish += int(fine.nit)
            if np.isfinite(fine.fun) and fine.fun <= obj(theta)[0]:
                theta = np.asarray(fine.x, dtype=float)
    nll, grad = obj(theta)
    H = obj.hessian(theta) if H is None else H
    return _Optimum(theta, nll, grad, H, runs, best, str(res.message), polish)
