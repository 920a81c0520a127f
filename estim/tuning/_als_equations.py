r"""The autocovariance equations of ALS: the regressor :math:`\mathcal A` and the weight.

With the filter's prediction error
:math:`\varepsilon_{k+1} = \bar A_k \varepsilon_k + w_k - A_k K_k v_k`,
:math:`e_k = C_k \varepsilon_k + v_k`, :math:`\bar A_k = A_k (I - K_k C_k)`, and its
covariance :math:`P_{k+1} = \bar A_k P_k \bar A_k^\top + Q + A_k K_k R K_k^\top A_k^\top`,

.. math::
    \mathbb E[e_k e_k^\top] = C_k P_k C_k^\top + R, \qquad
    \mathbb E[e_{k+j} e_k^\top] = C_{k+j} \Phi_{k+j,k} P_k C_k^\top
    - C_{k+j} \Phi_{k+j,k+1} A_k K_k R \quad (j \ge 1),

:math:`\Phi_{k+j,k} = \bar A_{k+j-1} \cdots \bar A_k`: linear in the free entries
:math:`\theta` of ``Q`` and ``R``. A constant gain on a linear model makes :math:`P`
the stationary solution of a Lyapunov equation (Odelson, Rajamani & Rawlings 2006);
otherwise the autocovariances are averaged over the samples (Lima & Rawlings 2011).
The lags stacked (lag 0 by its lower triangle) are the columns of :math:`\mathcal A`
per parameter. The covariance of the sample autocovariances, for the optimal weight
and the standard errors, is Bartlett's formula (:func:`_bartlett`).
"""

from __future__ import annotations

import numpy as np

from estim.tuning._als_filters import _Filter


def _lti_coef(Abar: np.ndarray, D: np.ndarray, C: np.ndarray, QB: list[np.ndarray],
              RB: list[np.ndarray], lags: int) -> np.ndarray:
    """``coef[j, i]``: the lag-``j`` autocovariance of the innovations per unit of
    parameter ``i`` (stationary, time-invariant; ``D = A L``)."""
    from scipy.linalg import solve_discrete_lyapunov

    ny = C.shape[0]
    n = len(QB) + len(RB)
    coef = np.zeros((lags, n, ny, ny))
    sources = list(QB) + [D @ B @ D.T for B in RB]
    Ps = [solve_discrete_lyapunov(Abar, E) for E in sources]
    G = C.copy()  # C Abar^j
    G_prev = C  # C Abar^(j-1), first used at j = 1
    for j in range(lags):
        for i, P in enumerate(Ps):
            coef[j, i] = G @ P @ C.T
        for r, B in enumerate(RB):
            coef[j, len(QB) + r] += B if j == 0 else -(G_prev @ D) @ B
        G_prev, G = G, G @ Abar
    return coef


def _ltv_states(Abar: np.ndarray, D: np.ndarray, QB: list[np.ndarray] | np.ndarray,
                RB: list[np.ndarray], k_hi: int) -> np.ndarray:
    """``P[k, i]``: the prediction-error covariance at sample ``k`` per unit of parameter
    ``i``, from zero at sample 0 (``k <= k_hi``; ``D[k] = A_k K_k``). ``QB``: the
    process noise's basis, the same for every transition (a list of ``(nx, nx)``) or
    per transition (``(T-1, nq, nx, nx)``: a continuous noise over each interval)."""
    nx = Abar.shape[1]
    Qs = np.asarray(QB)
    per_step = Qs.ndim == 4
    nq = Qs.shape[1] if per_step else len(QB)
    n = nq + len(RB)
    P = np.zeros((k_hi + 1, n, nx, nx))
    if not per_step:
        Qs = Qs.reshape(nq, nx, nx)
    Rb = np.asarray(RB)
    for k in range(k_hi):
        Ak = Abar[k]
        nxt = Ak @ P[k] @ Ak.T
        nxt[:nq] += Qs[k] if per_step else Qs
        if len(RB):
            nxt[nq:] += D[k] @ Rb @ D[k].T
        P[k + 1] = nxt
    return P


def _ltv_coef(Abar: np.ndarray, D: np.ndarray, C: np.ndarray, P: np.ndarray,
              RB: list[np.ndarray], lags: int, k_lo: int, k_hi: int) -> np.ndarray:
    """``coef[j, i]``: the lag-``j`` autocovariance averaged over the samples
    ``k_lo..k_hi`` (which need ``k_hi + lags - 1 < T``) per unit of parameter ``i``."""
    ks = np.arange(k_lo, k_hi + 1)
    m = len(ks)
    nq = P.shape[1] - len(RB)
    ny, nx = C.shape[1:]
    coef = np.zeros((lags, P.shape[1], ny, ny))
    Pk = P[ks]
    Ck = C[ks]
    PC = Pk @ Ck[:, None].transpose(0, 1, 3, 2)  # (m, n, nx, ny)
    Phi = np.broadcast_to(np.eye(nx), (m, nx, nx))
    Psi = D[ks]  # Φ_{k+j,k+1} A_k K_k at j = 1
    Rb = np.asarray(RB)
    for j in range(lags):
        if j:
            Phi = Abar[ks + j - 1] @ Phi
            if j > 1:
                Psi = Abar[ks + j - 1] @ Psi
        Gj = C[ks + j] @ Phi  # (m, ny, nx)
        coef[j] = np.einsum("kax,kixb->iab", Gj, PC) / m
        if len(RB):
            if j == 0:
                coef[0, nq:] += Rb
            else:
                CPsi = (C[ks + j] @ Psi).mean(axis=0)  # (ny, ny)
                coef[j, nq:] -= CPsi @ Rb
    return coef


def _rows(lags: int, ny: int) -> list[tuple[int, int, int]]:
    """The entries ``(j, a, b)`` of the stacked autocovariances (lag 0: ``a >= b``, the
    rest of a symmetric matrix being the same numbers)."""
    return [(j, a, b) for j in range(lags) for a in range(ny) for b in range(ny)
            if j or a >= b]


def _stack(M: np.ndarray, rows: list[tuple[int, int, int]]) -> np.ndarray:
    """``M[j, ..., a, b]`` at the rows as the first axis."""
    return np.stack([M[j, ..., a, b] for j, a, b in rows])


def _design(filt: _Filter, QB: list[np.ndarray] | np.ndarray, RB: list[np.ndarray],
            lags: int, k_lo: int, k_hi: int, T: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The autocovariances per unit of each parameter: ``coef (lags, n, ny, ny)`` at the
    stacked lags, ``coef_all`` at lags ``0..M+lags`` for Bartlett's formula, and ``M``,
    the lags where the autocovariances have vanished (to :math:`10^{-6}`, from
    ``2 lags`` to 400, and within the record). ``QB`` per transition (an array
    ``(T-1, nq, nx, nx)``) takes the time-varying equations."""
    nx = filt.run.C.shape[-1]
    rho = filt.rho
    M = int(np.clip(np.ceil(np.log(1e-6) / np.log(rho)) if 0 < rho < 1 else 1,
                    2 * lags, 400))
    lti = filt.invariant
    if lti is not None:
        assert isinstance(QB, list)  # (a constant basis: uniform samples)
        D0 = lti.A @ lti.L
        coef_all = _lti_coef(lti.Abar, D0, lti.C, QB, RB, M + lags + 1)
        return coef_all[:lags], coef_all, M
    Ak, Kk, Ck = filt.run.A, filt.run.K, filt.run.C
    Abar_t = Ak @ (np.eye(nx) - Kk[:-1] @ Ck[:-1])
    D = Ak @ Kk[:-1]
    Pst = _ltv_states(Abar_t, D, QB, RB, k_hi)
    coef = _ltv_coef(Abar_t, D, Ck, Pst, RB, lags, k_lo, k_hi)
    M = int(min(M, max((T - 1 - k_lo) // 2 - lags, lags)))
    Mb = M + lags + 1
    k_hi_b = T - Mb
    coef_all = _ltv_coef(Abar_t, D, Ck, Pst, RB, Mb, k_lo, max(k_hi_b, k_lo)) \
        if k_hi_b > k_lo + 10 else np.concatenate([coef, np.zeros((Mb - lags,)
                                                                  + coef.shape[1:])])
    return coef, coef_all, M


def _bartlett(gamma: np.ndarray, rows: list[tuple[int, int, int]], M: int) -> np.ndarray:
    r"""``n`` times the covariance of the sample autocovariances at ``rows`` for a
    stationary Gaussian sequence with autocovariances ``gamma[h]`` (``h = 0..H``):

    .. math::
        n\,\mathrm{cov}(\hat c_{ab}(j), \hat c_{cd}(l)) \approx \sum_{|m| \le M}
        \Gamma_{ac}(m+j-l)\Gamma_{bd}(m) + \Gamma_{ad}(m+j)\Gamma_{bc}(m-l)

    (Bartlett 1946; Brockwell & Davis 1991, prop. 11.2.2), ``Γ(-h) = Γ(h)ᵀ``."""
    Hh = gamma.shape[0] - 1
    full = np.concatenate([gamma[:0:-1].transpose(0, 2, 1), gamma])  # h = -H..H
    ms = np.arange(-M, M + 1) + Hh
    lags = max(j for j, _, _ in rows) + 1
    blocks = {}
    for j in range(lags):
        for l_ in range(lags):
            blocks[j, l_] = (np.einsum("mac,mbd->abcd", full[ms + j - l_], full[ms])
                             + np.einsum("mad,mbc->abcd", full[ms + j], full[ms - l_]))
    S = np.empty((len(rows), len(rows)))
    for r, (j, a, b) in enumerate(rows):
        for s, (l_, c, d) in enumerate(rows):
            S[r, s] = blocks[j, l_][a, b, c, d]
    S = 0.5 * (S + S.T)
    return S + 1e-12 * np.trace(S) / len(S) * np.eye(len(S))
