r"""The estimates of maximum likelihood, their standard errors and the convergence verdict.

At the optimum :math:`\hat\theta` of :math:`\ell = -\log L`, the inverse observed
information gives the asymptotic covariance, and the delta method takes it to the
entries :math:`g(\theta) = (\operatorname{vec} Q, \operatorname{vec} R, p)`:

.. math::
    \operatorname{cov}\hat\theta \approx \nabla^2\ell(\hat\theta)^{-1}, \qquad
    \operatorname{cov} g(\hat\theta) \approx J \nabla^2\ell^{-1} J^\top, \quad
    J = \partial g / \partial\theta.

The optimum is converged when the Hessian is positive definite and the gain a Newton
step still predicts, :math:`\frac12 \nabla\ell^\top (\nabla^2\ell)^{-1} \nabla\ell`, is
below the tolerance. A variance whose log runs far below the others of its matrix, or
that the likelihood hardly bounds, is on the boundary (the likelihood largest without
that noise): its standard errors are not given (Durbin & Koopman 2012, ch. 7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estim.tuning._ml_optimiser import _limit, _Optimum
from estim.tuning._ml_parametrisation import _Parametrisation


@dataclass
class _Estimates:
    r"""``Q (nx, nx)`` (``Qc (nq, nq)`` with a continuous noise), ``R (ny, ny)`` and
    the estimated ``params`` with their ``stderr`` (as :class:`~estim.tuning.TuningResult`
    holds them), the covariance ``cov_theta`` of :math:`\hat\theta` (NaN when the
    Hessian is not positive definite), the Newton ``decrement``, ``success`` and the ``status``."""

    Q: np.ndarray
    R: np.ndarray
    params: dict[str, float]
    stderr: dict
    cov_theta: np.ndarray
    decrement: float
    success: bool
    status: str


def _estimates(par: _Parametrisation, opt: _Optimum, tol: float, nx: int, ny: int
               ) -> _Estimates:
    """The estimates at the optimum ``opt`` of the parametrisation ``par`` and their
    uncertainty; ``tol`` as for the Newton polish."""
    theta, H, grad, nll = opt.theta, opt.H, opt.grad, opt.nll
    values, J = par.entries(theta)
    cov_theta = np.full_like(H, np.nan)
    decrement = np.inf  # the gain of log L a Newton step predicts
    definite = bool(np.isfinite(H).all() and np.linalg.eigvalsh(H)[0] > 0)
    if definite:
        cov_theta = np.linalg.inv(H)
        decrement = 0.5 * float(grad @ cov_theta @ grad)
    success = definite and decrement <= _limit(tol, nll)
    if success:
        status = "ok"
    elif not definite:
        status = ("not converged: the Hessian of -log L is not positive definite at the "
                  "optimum (a variance on its boundary, or parameters the record does not "
                  "identify): no standard errors")
    else:
        status = (f"not converged: a Newton step would still gain {decrement:.3g} in log L "
                  f"({opt.message})")
    cov_entries = J @ cov_theta @ J.T
    se = np.sqrt(np.abs(np.diag(cov_entries)))
    free = np.abs(J).sum(axis=1) > 0
    se = np.where(free, se, np.nan)
    # variances run to zero: a log far below the others of its matrix, or one the
    # likelihood hardly bounds (standard error of the log above 3, a factor 20)
    boundary = []
    for idx, name, i, power in par.logs:
        top = max(pw * theta[j] for j, other, _, pw in par.logs if other == name)
        loose = np.isfinite(cov_theta[idx, idx]) and np.sqrt(cov_theta[idx, idx]) > 3
        if power * theta[idx] < top - np.log(1e8) or loose:
            n = nx if name == "Q" else ny
            rows = range(n) if i is None else [i]
            offset = 0 if name == "Q" else nx * nx
            for row in rows:
                for col in range(n):
                    se[offset + row + n * col] = se[offset + col + n * row] = np.nan
            boundary.append(f"{name}[{i},{i}]" if i is not None else name)
    if boundary and status == "ok":
        status = (f"boundary: {', '.join(boundary)} "
                  f"{'runs' if len(boundary) == 1 else 'run'} to zero (the likelihood is "
                  f"largest without that noise); no standard error")
    q, r, _ = par.matrices(theta)
    Qh, Rh = q.reshape(nx, nx, order="F"), r.reshape(ny, ny, order="F")
    Qh, Rh = 0.5 * (Qh + Qh.T), 0.5 * (Rh + Rh.T)
    stderr = {"Q": se[:nx * nx].reshape(nx, nx, order="F"),
              "R": se[nx * nx:nx * nx + ny * ny].reshape(ny, ny, order="F"),
              "params": {k: float(s) for k, s in zip(par.names, se[nx * nx + ny * ny:],
                                                     strict=True)}}
    est_params = {k: float(v) for k, v in zip(par.names, values[nx * nx + ny * ny:].ravel(),
                                              strict=True)}
    return _Estimates(Qh, Rh, est_params, stderr, cov_theta, decrement, success, status)
