r"""The least squares of ALS: :math:`\hat\theta` with ``Q`` and ``R`` positive semidefinite.

The stacked autocovariance equations :math:`\mathcal A \theta \approx \hat b` are solved as

.. math::
    \hat\theta = \operatorname{arg\,min}_\theta\, (\mathcal A\theta - \hat b)^\top W
    (\mathcal A\theta - \hat b) \quad \text{s.t.} \quad Q(\theta) \succeq 0,\;
    R(\theta) \succeq 0,

by plain least squares when its solution is already positive semidefinite, bounded
least squares when every free entry is a variance, and otherwise a log-determinant
barrier (Rajamani & Rawlings 2009 solve the same problem as a semidefinite program).
With :math:`W = I` or the optimal :math:`W = \hat S^{-1}`, the inverse of the
covariance of :math:`\hat b` by Bartlett's formula, the estimate's covariance is the
sandwich

.. math::
    \operatorname{cov}\hat\theta \approx (\mathcal A^\top W \mathcal A)^{-1}
    \mathcal A^\top W S W \mathcal A (\mathcal A^\top W \mathcal A)^{-1} / n.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estim.tuning._als_equations import _bartlett
from estim.tuning._als_structure import _Block


def _psd(blocks: list[_Block], splits: list[slice], theta: np.ndarray) -> bool:
    """Whether every block's matrix at ``theta`` is positive semidefinite."""
    for blk, sl in zip(blocks, splits, strict=True):
        if np.linalg.eigvalsh(blk.matrix(theta[sl])).min() < 0:
            return False
    return True


def _barrier(Aw, bw, blocks, splits, theta0) -> np.ndarray:
    r"""``min ||Aw θ - bw||²`` subject to each block's matrix being positive semidefinite:
    Newton's method on :math:`\tfrac12\lVert A_w\theta - b_w\rVert^2 - \mu\sum \log\det
    M_b(\theta)` for decreasing :math:`\mu` (the log-determinant barrier; Boyd &
    Vandenberghe 2004, ch. 11)."""
    H0 = Aw.T @ Aw
    g0 = Aw.T @ bw
    m = sum(blk.basis[0].shape[0] for blk in blocks)
    scale = 0.5 * float(bw @ bw) + 1e-300

    def chol_inv(theta):
        out = []
        for blk, sl in zip(blocks, splits, strict=True):
            Mb = blk.matrix(theta[sl])
            try:
                Lc = np.linalg.cholesky(Mb)
            except np.linalg.LinAlgError:
                return None, None
            out.append((np.linalg.inv(Mb), 2 * np.log(np.diag(Lc)).sum()))
        return out, sum(ld for _, ld in out)

    def f(theta, mu):
        inv, logdet = chol_inv(theta)
        if inv is None:
            return np.inf
        r = Aw @ theta - bw
        return 0.5 * float(r @ r) - mu * logdet

    theta = theta0.copy()
    r0 = Aw @ theta - bw
    mu = max(0.5 * float(r0 @ r0), scale * 1e-6) / m
    for _ in range(40):
        for _ in range(60):
            inv, _ld = chol_inv(theta)
            grad = H0 @ theta - g0
            hess = H0.copy()
            for (Mi, _), blk, sl in zip(inv, blocks, splits, strict=True):
                MB = [Mi @ B for B in blk.basis]
                idx = np.arange(len(theta))[sl]
                grad[idx] -= mu * np.array([np.trace(X) for X in MB])
                hess[np.ix_(idx, idx)] += mu * np.array([[np.sum(X * Y.T) for Y in MB]
                                                          for X in MB])
            d = np.sqrt(np.maximum(np.diag(hess), 1e-300))
            step = -np.linalg.solve(hess / np.outer(d, d), grad / d) / d
            dec = -float(grad @ step)
            if dec < 1e-12 * scale:
                break
            t, f0 = 1.0, f(theta, mu)
            while t > 1e-12 and f(theta + t * step, mu) > f0 - 0.25 * t * dec:
                t *= 0.5
            theta = theta + t * step
        if mu * m < 1e-10 * scale:
            break
        mu *= 0.1
    return theta


def _solve(Aw: np.ndarray, bw: np.ndarray, blocks: list[_Block], splits: list[slice]
           ) -> tuple[np.ndarray, np.ndarray, bool]:
    """The unconstrained and the positive-semidefinite least-squares solutions, and
    whether the constraint is active."""
    theta_u = np.linalg.lstsq(Aw, bw, rcond=None)[0]
    if _psd(blocks, splits, theta_u):
        return theta_u, theta_u, False
    if all(blk.diagonal for blk in blocks):  # PSD is non-negativity of every parameter
        from scipy.optimize import lsq_linear

        d = np.linalg.norm(Aw, axis=0)
        res = lsq_linear(Aw / d, bw, bounds=(0.0, np.inf), method="bvls")
        return theta_u, res.x / d, True
    # a strictly feasible start: the diagonal parameters positive, the rest zero
    theta0 = np.zeros_like(theta_u)
    for blk, sl in zip(blocks, splits, strict=True):
        idx = np.arange(len(theta_u))[sl]
        diag = [i for i, B in zip(idx, blk.basis, strict=True)
                if np.count_nonzero(B - np.diag(np.diag(B))) == 0]
        size = max(np.max(np.abs(theta_u[diag])), 1e-300)
        theta0[diag] = np.maximum(np.abs(theta_u[diag]), 1e-3 * size)
    return theta_u, _barrier(Aw, bw, blocks, splits, theta0), True


@dataclass
class _Fit:
    r"""The ALS estimate: the unconstrained ``theta_u`` and constrained ``theta``,
    whether the constraint is ``active``, the covariance ``cov`` of the estimate and the
    weighted ``objective`` :math:`r^\top W r`."""

    theta_u: np.ndarray
    theta: np.ndarray
    active: bool
    cov: np.ndarray
    objective: float


def _fit(A_als: np.ndarray, b: np.ndarray, coef_all: np.ndarray,
         rows: list[tuple[int, int, int]], M: int, blocks: list[_Block],
         splits: list[slice], optimal: bool, n: int) -> _Fit:
    """Solve the stacked equations ``A_als θ ≈ b`` (``rows`` of them, from ``n``
    samples) with the identity or, when ``optimal``, the inverse Bartlett covariance at
    the identity-weighted estimate, and the sandwich covariance of the estimate
    (``coef_all`` and ``M`` as :func:`~estim.tuning._als_equations._design` gives)."""

    def S_at(theta: np.ndarray) -> np.ndarray:
        gamma = np.tensordot(theta, coef_all, axes=([0], [1]))  # (lags, ny, ny)
        return _bartlett(gamma, rows, M)

    Wh = np.eye(len(rows))
    theta_u, theta, active = _solve(A_als, b, blocks, splits)
    if optimal:
        Lw = np.linalg.cholesky(S_at(theta))
        Wh = np.linalg.inv(Lw)
        theta_u, theta, active = _solve(Wh @ A_als, Wh @ b, blocks, splits)
    S = S_at(theta)
    Aw, r = Wh @ A_als, Wh @ (A_als @ theta - b)
    Binv = np.linalg.inv(Aw.T @ Aw)
    cov = Binv @ Aw.T @ (Wh @ S @ Wh.T) @ Aw @ Binv / n
    return _Fit(theta_u, theta, active, cov, float(r @ r))
