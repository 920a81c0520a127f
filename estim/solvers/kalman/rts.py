r"""The Rauch-Tung-Striebel backward recursion, and a model's transitions over a record.

From the filtered means :math:`\hat x_k` and covariances :math:`P_k`, and for each
transition :math:`k \to k+1` the predicted mean :math:`\bar x_{k+1}`, covariance
:math:`\bar P_{k+1}` and cross-covariance :math:`D_{k+1}` between :math:`x_k` and
:math:`x_{k+1}`:

.. math::
    G_k = D_{k+1} \bar P_{k+1}^{-1}, \qquad
    x^s_k = \hat x_k + G_k (x^s_{k+1} - \bar x_{k+1}), \qquad
    P^s_k = P_k + G_k (P^s_{k+1} - \bar P_{k+1}) G_k^\top,

from :math:`x^s_{T-1} = \hat x_{T-1}`, :math:`P^s_{T-1} = P_{T-1}`
(:mod:`estim.estimators.kalman.smoothing` says how the EKF and the UKF predict).

References
----------
H. E. Rauch, F. Tung, C. T. Striebel, "Maximum likelihood estimates of linear
dynamic systems", AIAA J. 3(8), 1965;
S. Särkkä, *Bayesian Filtering and Smoothing*, Cambridge University Press, 2013, ch. 8-9.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from estim._manifold import NP

__all__ = ["backward", "transitions"]


def backward(Xf: np.ndarray, Pf: np.ndarray, xb: np.ndarray, Pb: np.ndarray, D: np.ndarray,
             clip: Callable[[np.ndarray], np.ndarray] | None = None, manifold=None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""The smoothed means ``(T, nx)``, covariances ``(T, nd, nd)`` and gains
    ``(T-1, nd, nd)`` from the filtered ``Xf (T, nx)``, ``Pf (T, nd, nd)`` and the
    predictions ``xb (T-1, nx)``, ``Pb (T-1, nd, nd)``, ``D (T-1, nd, nd)``; ``clip``
    projects each smoothed mean (the filter's clipping). On a ``manifold`` (covariances
    in its tangent space, ``nd = ndx``) the correction is a tangent step:
    :math:`x^s_k = \hat x_k \oplus G_k (x^s_{k+1} \ominus \bar x_{k+1})`."""
    T, nd = len(Xf), Pf.shape[-1]
    Xs, Ps = Xf.copy(), Pf.copy()
    # G = D Pb^{-1} by a solve (Pb and so Pb^{-T} symmetric), all transitions at once
    G = np.linalg.solve(Pb, D.transpose(0, 2, 1)).transpose(0, 2, 1) if T > 1 else \
        np.empty((0, nd, nd))
    for k in range(T - 2, -1, -1):
        if manifold is None:
            Xs[k] = Xf[k] + G[k] @ (Xs[k + 1] - xb[k])
        else:
            step = G[k] @ manifold.local(xb[k], Xs[k + 1], NP)
            Xs[k] = manifold.retract(Xf[k], step, NP)
        if clip is not None:
            Xs[k] = clip(Xs[k])
        Pk = Pf[k] + G[k] @ (Ps[k + 1] - Pb[k]) @ G[k].T
        Ps[k] = 0.5 * (Pk + Pk.T)
    return Xs, Ps, G


def transitions(model, X: np.ndarray, W: np.ndarray, jacobian: bool = False) -> np.ndarray:
    """The model's ``F(x, w)`` at every row of ``X (n, nx)`` and ``W (n, nw)`` in one
    call, ``(n, nx)``; with ``jacobian``, ``dF/dx`` there, ``(n, nx, nx)``."""
    n, nx = X.shape
    fun = model.F_x if jacobian else model.F
    out = np.asarray(fun.map(n)(X.T, W.T, ca.DM(model.p)))
    return out.reshape(nx, n, nx).transpose(1, 0, 2) if jacobian else out.T
