r"""Autocovariance least squares: ``Q`` and ``R`` from the innovations of any stable filter.

A filter run with a gain that is not optimal leaves innovations that are correlated in
time, and their autocovariances are linear in the noise covariances (Mehra 1970;
Odelson, Rajamani & Rawlings 2006). With the state error
:math:`\varepsilon_k = x_k - \bar x_k` of the prediction and the filter gain
:math:`K_k` (:math:`\hat x_k = \bar x_k + K_k e_k`),

.. math::
    \varepsilon_{k+1} = \bar A_k \varepsilon_k + w_k - A_k K_k v_k, \qquad
    e_k = C_k \varepsilon_k + v_k, \qquad \bar A_k = A_k (I - K_k C_k),

so :math:`\mathbb E[e_{k+j} e_k^\top]` is linear in ``(Q, R)``. Stacking the lags
``0..N-1`` of the sample autocovariances gives the least-squares problem
:math:`\min_\theta \lVert \mathcal A \theta - \hat b \rVert_W^2` over the free entries
:math:`\theta` of ``Q`` and ``R``, with :math:`Q, R \succeq 0`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_choice, as_covariance, as_inputs, as_int, as_record, as_vector
from estim.model import Model
from estim.tuning._result import TuningResult, innovation_check

STRUCTURES = ("diagonal", "full", "scalar")
WEIGHTINGS = ("identity", "optimal")

#: Default number of lags of the stacked autocovariances.
DEFAULT_ALS_LAGS = 15


@dataclass
class _Block:
    """The free entries of one covariance (``Q``, or ``Q_w`` with a shaping matrix, or
    ``R``): ``basis[i]`` is the symmetric matrix multiplying parameter ``i``."""

    name: str
    basis: list
    diagonal: bool  # every basis matrix is diagonal (PSD is then non-negativity)

    def matrix(self, theta: np.ndarray) -> np.ndarray:
        return np.tensordot(theta, np.asarray(self.basis), axes=1)


def _block(spec, n: int, name: str) -> _Block:
    """The basis of a covariance of size ``n`` with structure ``spec``."""
    eye = np.eye(n)
    if isinstance(spec, str):
        spec = as_choice(spec, STRUCTURES, f"structure[{name!r}]")
        if spec == "scalar":
            return _Block(name, [eye], True)
        if spec == "diagonal":
            return _Block(name, [np.outer(eye[i], eye[i]) for i in range(n)], True)
        mask = np.ones((n, n), dtype=bool)
    else:
        mask = np.asarray(spec)
        if mask.dtype != bool:
            raise TypeError(f"structure[{name!r}] must be 'diagonal', 'full', 'scalar' or a "
                            f"boolean mask of the free entries, got an array of {mask.dtype}")
        if mask.shape != (n, n):
            raise ValueError(f"structure[{name!r}] as a mask must have shape ({n}, {n}), "
                             f"got {mask.shape}")
        if not np.array_equal(mask, mask.T):
            raise ValueError(f"structure[{name!r}] must be a symmetric mask")
        if not mask.diagonal().all():
            raise ValueError(f"structure[{name!r}] must leave the whole diagonal free (a "
                             f"covariance with a zero variance has no correlations)")
    basis = []
    for i in range(n):
        for j in range(i, n):
            if mask[i, j]:
                E = np.zeros((n, n))
                E[i, j] = E[j, i] = 1.0
                basis.append(E)
    return _Block(name, basis, all(np.count_nonzero(B - np.diag(np.diag(B))) == 0
                                   for B in basis))


def _structures(structure, ng: int, ny: int) -> tuple[_Block, _Block]:
    if isinstance(structure, Mapping):
        unknown = sorted(set(structure) - {"Q", "R"})
        if unknown:
            raise ValueError(f"structure names unknown covariances {unknown}; it maps 'Q' "
                             f"and/or 'R' to a structure")
        q, r = structure.get("Q", "diagonal"), structure.get("R", "diagonal")
    else:
        q = r = structure
    if not isinstance(q, str | np.ndarray | list) or not isinstance(r, str | np.ndarray | list):
        raise TypeError(f"structure must be 'diagonal', 'full', 'scalar', a boolean mask or "
                        f"a dict of them for 'Q' and 'R', got {structure!r}")
    return _block(q, ng, "Q"), _block(r, ny, "R")


# ---------------------------------------------------------------- the filter's data
def _inputs(model: Model, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``W[k]``: the input of the transition into sample ``k`` (row 0 unused), and
    ``Uh[k]``: the input ``h`` sees at sample ``k``, with :func:`estim.replay`'s
    conventions."""
    T, nu = U.shape
    prev = np.vstack([np.zeros((1, nu)), U[:-1]])
    if model.sampled:
        return np.hstack([prev, U]), U.copy()
    return prev, prev


def _mapped(fun, n: int, *args) -> np.ndarray:
    """``fun`` evaluated on the columns of ``args`` (each ``(n, m)`` row-major), as
    ``(n, rows, cols)``."""
    out = fun.map(n)(*[a.T for a in args])
    out = np.asarray(out.full() if hasattr(out, "full") else out)
    rows = out.shape[0]
    return out.reshape(rows, n, -1).transpose(1, 0, 2)


def _jacobians(model: Model, xh: np.ndarray, xb: np.ndarray, W: np.ndarray,
               Uh: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``A[k] = dF/dx`` at ``(x̂_k, W[k+1])`` for ``k < T-1`` and ``C[k] = dh/dx`` at
    ``(x̄_k, Uh[k])``."""
    T = xh.shape[0]
    p = np.tile(model.p, (T, 1))
    A = _mapped(model.F_x, T - 1, xh[:-1], W[1:], p[:-1]) if T > 1 else np.zeros((0,) * 3)
    C = _mapped(model.H_x, T, xb, Uh, p)
    return A, C


def _ekf_run(model: Model, Y, U, W, Uh, ekf) -> dict:
    """Replay an :class:`~estim.EKF` and rebuild, per sample, its prediction, innovation,
    innovation covariance, gain and Jacobians (the EKF's own equations)."""
    from estim.simulate import replay

    log = replay(ekf, Y, U, warn=False)
    T, nx = log.x_hat.shape
    xh, P = log.x_hat, log.P
    p = np.tile(model.p, (T, 1))
    xb = np.empty_like(xh)
    xb[0] = ekf.x0
    if T > 1:
        xb[1:] = _mapped(model.F, T - 1, xh[:-1], W[1:], p[:-1])[:, :, 0]
    A, C = _jacobians(model, xh, xb, W, Uh)
    Pb = np.empty_like(P)
    Pb[0] = ekf.P0
    Pb[1:] = A @ P[:-1] @ A.transpose(0, 2, 1) + ekf.Q
    e = Y - _mapped(model.H, T, xb, Uh, p)[:, :, 0]
    S = C @ Pb @ C.transpose(0, 2, 1) + ekf.R
    S = 0.5 * (S + S.transpose(0, 2, 1))
    K = np.linalg.solve(S, C @ Pb).transpose(0, 2, 1)
    return {"e": e, "S": S, "K": K, "A": A, "C": C, "x_hat": xh}


def _fixed_run(model: Model, Y, W, Uh, L: np.ndarray, x0: np.ndarray) -> dict:
    """The filter with the constant gain ``L``: ``x̂_k = x̄_k + L e_k``,
    ``x̄_{k+1} = F(x̂_k)``."""
    from estim._fast import FastFunction

    T = Y.shape[0]
    F, H = FastFunction(model.F), FastFunction(model.H)
    p = model.p
    xb = np.empty((T, model.nx))
    xh = np.empty_like(xb)
    e = np.empty_like(Y)
    x = np.array(x0, dtype=float)
    for k in range(T):
        xb[k] = x
        e[k] = Y[k] - H(x, Uh[k], p)[0]
        xh[k] = x + L @ e[k]
        if k + 1 < T:
            x = F(xh[k], W[k + 1], p)[0].copy()
        if not np.isfinite(x).all():
            raise ValueError(f"gain: the filter with this fixed gain diverged at sample {k} "
                             f"(non-finite prediction); give a stabilising gain")
    A, C = _jacobians(model, xh, xb, W, Uh)
    K = np.broadcast_to(L, (T,) + L.shape)
    return {"e": e, "K": K, "A": A, "C": C, "x_hat": xh}


def _affine_run(model: Model, Y, W, Uh, L, x0, A0, C0) -> dict:
    """:func:`_fixed_run` for a linear model, ``F(x, w) = A0 x + F(0, w)`` and
    ``h(x, u) = C0 x + h(0, u)``, in plain numpy."""
    T, nx = Y.shape[0], model.nx
    p = np.tile(model.p, (T, 1))
    zero = np.zeros((T, nx))
    c = _mapped(model.H, T, zero, Uh, p)[:, :, 0]
    b = _mapped(model.F, T - 1, zero[1:], W[1:], p[1:])[:, :, 0] if T > 1 else zero
    # x̄_{k+1} = A0 (I - L C0) x̄_k + A0 L (y_k - c_k) + b_k
    Abar = A0 @ (np.eye(nx) - L @ C0)
    z = (Y - c) @ (A0 @ L).T
    z[:T - 1] += b[:T - 1]
    xb = np.empty((T, nx))
    x = np.array(x0, dtype=float)
    for k in range(T):
        xb[k] = x
        x = Abar @ x + z[k]
    e = Y - xb @ C0.T - c
    K = np.broadcast_to(L, (T,) + L.shape)
    return {"e": e, "K": K, "A": np.broadcast_to(A0, (max(T - 1, 0), nx, nx)),
            "C": np.broadcast_to(C0, (T,) + C0.shape), "x_hat": None}


def _is_linear(model: Model, W: np.ndarray, Uh: np.ndarray, x0: np.ndarray) -> bool:
    """Whether ``dF/dx`` and ``dh/dx`` are the same at a few random states and inputs
    (a linear model's Jacobians are constant)."""
    rng = np.random.default_rng(0)
    picks = rng.integers(0, W.shape[0], size=3)
    ref = None
    for i, k in enumerate(picks):
        x = x0 + (1.0 + np.abs(x0)) * rng.standard_normal(model.nx) * (i > 0)
        with np.errstate(all="ignore"):
            J = np.concatenate([np.ravel(model.F_x(x, W[max(k, 1)], model.p).full()),
                                np.ravel(model.H_x(x, Uh[k], model.p).full())])
        if not np.isfinite(J).all():
            return False
        if ref is None:
            ref = J
        elif np.max(np.abs(J - ref)) > 1e-9 * (1.0 + np.max(np.abs(ref))):
            return False
    return True


# ------------------------------------------------------- the autocovariance equations
def _qbasis(block: _Block, G: np.ndarray) -> list:
    return [G @ B @ G.T for B in block.basis]


def _lti_coef(Abar, D, C, QB, RB, lags: int) -> np.ndarray:
    """``coef[j, i]``: the lag-``j`` autocovariance of the innovations per unit of
    parameter ``i`` (stationary, time-invariant)."""
    from scipy.linalg import solve_discrete_lyapunov

    ny = C.shape[0]
    n = len(QB) + len(RB)
    coef = np.zeros((lags, n, ny, ny))
    sources = list(QB) + [D @ B @ D.T for B in RB]
    Ps = [solve_discrete_lyapunov(Abar, E) for E in sources]
    G = C.copy()  # C Abar^j
    G_prev = None  # C Abar^(j-1)
    for j in range(lags):
        for i, P in enumerate(Ps):
            coef[j, i] = G @ P @ C.T
        for r, B in enumerate(RB):
            coef[j, len(QB) + r] += B if j == 0 else -(G_prev @ D) @ B
        G_prev, G = G, G @ Abar
    return coef


def _ltv_states(Abar, D, QB, RB, k_hi: int) -> np.ndarray:
    """``P[k, i]``: the prediction-error covariance at sample ``k`` per unit of parameter
    ``i``, from zero at sample 0 (``k <= k_hi``)."""
    nx = Abar.shape[1]
    n = len(QB) + len(RB)
    P = np.zeros((k_hi + 1, n, nx, nx))
    Qs = np.asarray(QB).reshape(len(QB), nx, nx)
    Rb = np.asarray(RB)
    for k in range(k_hi):
        Ak = Abar[k]
        nxt = Ak @ P[k] @ Ak.T
        nxt[:len(QB)] += Qs
        if len(RB):
            nxt[len(QB):] += D[k] @ Rb @ D[k].T
        P[k + 1] = nxt
    return P


def _ltv_coef(Abar, D, C, P, RB, lags: int, k_lo: int, k_hi: int) -> np.ndarray:
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
    Psi = None
    Rb = np.asarray(RB)
    for j in range(lags):
        if j:
            Phi = Abar[ks + j - 1] @ Phi
            Psi = D[ks] if j == 1 else Abar[ks + j - 1] @ Psi
        Gj = C[ks + j] @ Phi  # (m, ny, nx)
        coef[j] = np.einsum("kax,kixb->iab", Gj, PC) / m
        if len(RB):
            if j == 0:
                coef[0, nq:] += Rb
            else:
                CPsi = (C[ks + j] @ Psi).mean(axis=0)  # (ny, ny)
                coef[j, nq:] -= CPsi @ Rb
    return coef


def _rows(lags: int, ny: int) -> list:
    """The entries ``(j, a, b)`` of the stacked autocovariances (lag 0: ``a >= b``, the
    rest of a symmetric matrix being the same numbers)."""
    return [(j, a, b) for j in range(lags) for a in range(ny) for b in range(ny)
            if j or a >= b]


def _stack(M: np.ndarray, rows: list) -> np.ndarray:
    """``M[j, ..., a, b]`` at the rows as the first axis."""
    return np.stack([M[j, ..., a, b] for j, a, b in rows])


def _bartlett(gamma: np.ndarray, rows: list, M: int) -> np.ndarray:
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


# -------------------------------------------------------------------- the solvers
def _psd(blocks, splits, theta) -> bool:
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


def _solve(Aw, bw, blocks, splits) -> tuple[np.ndarray, np.ndarray, bool]:
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


def _floored(M: np.ndarray) -> np.ndarray:
    """``M`` with its eigenvalues raised to a millionth of its mean variance (positive
    definite, for the filter of the next ALS pass)."""
    floor = 1e-6 * max(float(np.trace(M)) / len(M), 1e-300)
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    return (V * np.maximum(lam, floor)) @ V.T


# ---------------------------------------------------------------------- the API
def als(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
        gain: ArrayLike | object | None = None, Q0: ArrayLike | None = None,
        R0: ArrayLike | None = None, x0: ArrayLike | None = None,
        P0: ArrayLike | None = None, lags: int = DEFAULT_ALS_LAGS,
        structure: str | Mapping | ArrayLike = "diagonal", G: ArrayLike | None = None,
        weighting: str = "identity", burn_in: int | None = None,
        iterations: int = 1) -> TuningResult:
    r"""Autocovariance least squares: estimate ``Q`` and ``R`` from a record.

    A filter with a stable gain runs over the record; the sample autocovariances of its
    innovations :math:`e_k` at lags :math:`0..N-1`,
    :math:`\hat C_j = \frac1n \sum_k e_{k+j} e_k^\top`, are matched to their values
    predicted from the model, which are linear in the free entries :math:`\theta` of
    ``Q`` and ``R``. With the filter's prediction error
    :math:`\varepsilon_{k+1} = \bar A_k \varepsilon_k + w_k - A_k K_k v_k`,
    :math:`e_k = C_k \varepsilon_k + v_k`, :math:`\bar A_k = A_k (I - K_k C_k)` and
    its covariance :math:`P_{k+1} = \bar A_k P_k \bar A_k^\top + Q
    + A_k K_k R K_k^\top A_k^\top`,

    .. math::
        \mathbb E[e_k e_k^\top] = C_k P_k C_k^\top + R, \qquad
        \mathbb E[e_{k+j} e_k^\top] = C_{k+j} \Phi_{k+j,k} P_k C_k^\top
        - C_{k+j} \Phi_{k+j,k+1} A_k K_k R \quad (j \ge 1),

    :math:`\Phi_{k+j,k} = \bar A_{k+j-1} \cdots \bar A_k`. Averaged over the samples and
    stacked (lag 0 by its lower triangle) these give
    :math:`\mathcal A \theta \approx \hat b`, solved as

    .. math::
        \hat\theta = \operatorname{arg\,min}_\theta\, (\mathcal A\theta - \hat b)^\top W
        (\mathcal A\theta - \hat b) \quad \text{s.t.} \quad Q(\theta) \succeq 0,\;
        R(\theta) \succeq 0.

    A linear model with a constant gain is the classic time-invariant ALS (Odelson,
    Rajamani & Rawlings 2006): :math:`P` is the stationary solution of the Lyapunov
    equation. Otherwise (a nonlinear model, or an EKF's time-varying gain) the
    Jacobians are taken along the filter's estimates (the time-varying ALS of Lima &
    Rawlings 2011), an approximation for a nonlinear model that is good while the
    estimation errors are small compared with the model's curvature.

    Parameters
    ----------
    model : Model
        The model of the record (uniform samples; ``variable_dt`` is refused).
    Y : (T, ny) array
        Measurements; every output at every sample (no NaN).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as for :func:`estim.replay` (zero if omitted).
    gain : None, (nx, ny) array or EKF, optional
        The filter whose innovations are used. None (default): for a linear model the
        steady-state Kalman gain of ``(Q0, R0)``, for a nonlinear one an
        :class:`~estim.EKF` with ``Q0, R0, x0, P0``. An array: the constant filter gain
        :math:`L` of :math:`\hat x_k = \bar x_k + L e_k` (it must stabilise the
        filter). An ``EKF`` (without ``clip`` and ``gate``): replayed over the record
        with its own tuning.
    Q0, R0 : float, (n,) or (n, n), optional
        The rough covariances of the default filter. Default: ``R0`` the variances of
        the first differences of ``Y`` halved (an upper bound of the noise when the
        outputs change slowly) and ``Q0 = 0.1 C⁺ R0 C⁺ᵀ`` (its diagonal, floored),
        ``C = ∂h/∂x`` at ``x0``.
    x0, P0 : optional
        Initial guess of the filter and its covariance (default zeros and the
        identity).
    lags : int
        Number :math:`N` of lags ``0..N-1`` stacked (default 15). More lags than the
        filter's error takes to decay (:math:`\rho(\bar A)^N \ll 1`) add little.
    structure : "diagonal", "full", "scalar", bool mask or dict
        Free entries of ``Q`` (of ``Q_w`` with ``G``) and ``R``: the diagonal
        (default), all entries, a multiple of the identity, a symmetric ``(n, n)``
        boolean mask of the free entries (the diagonal free), or a dict
        ``{"Q": ..., "R": ...}`` of these (a missing key is "diagonal").
    G : (nx, ng) array, optional
        Noise-shaping matrix: ``Q = G Q_w Gᵀ`` with ``Q_w`` ``(ng, ng)`` of the given
        structure (``Q_w`` is in ``details["Q_w"]``). Identifiability of ``Q`` needs
        few enough free entries: with ``ny < nx`` a full ``Q`` is not identifiable.
    weighting : "identity" or "optimal"
        :math:`W = I`, or the inverse of the estimated covariance of :math:`\hat b`
        (evaluated at the identity-weighted estimate; Rajamani & Rawlings 2009), the
        minimum-variance weight.
    burn_in : int, optional
        Samples left out at the start, where the filter forgets its initial guess.
        Default: the samples the error dynamics take to decay to 1e-3
        (:math:`\rho(\bar A)^{k} \le 10^{-3}`, from ``lags`` to ``T/4``).
    iterations : int
        With ``gain=None``: run ALS this many times, each with the filter of the
        previous estimates (``Q0, R0`` for the first). ALS is consistent for any stable
        gain, but its variance grows with the gain's distance from the optimal one: a
        second pass from a badly tuned filter often shrinks the standard errors several
        times (``details["Q0"]``, ``details["R0"]`` are the last filter's).

    Returns
    -------
    TuningResult
        ``method="als"``; ``Q (nx, nx)``, ``R (ny, ny)``; ``status`` "ok", or
        "poorly determined: ..." naming the variances whose standard error exceeds ten
        times the largest variance of their matrix (the record hardly tells them apart);
        ``stderr["Q"]``, ``stderr["R"]`` (NaN for entries held at zero by the
        structure); ``check`` the :func:`innovation_check` of a filter run with the
        estimates (after the burn-in; the steady-state Kalman filter for a linear model,
        else an EKF);
        ``objective`` :math:`(\mathcal A\hat\theta - \hat b)^\top W (\mathcal A
        \hat\theta - \hat b)`; ``details``: ``lags``, ``weighting``, ``burn_in``,
        ``samples`` (:math:`n`), ``linearization`` ("time-invariant" or
        "time-varying"), ``gain`` (what filter), ``spectral_radius`` of
        :math:`\bar A` (median over samples), ``constraint_active``, ``unconstrained``
        (``{"Q", "R"}`` of the unconstrained least squares), ``theta`` and
        ``theta_cov``, ``autocovariance`` :math:`\hat C_j` ``(N, ny, ny)``,
        ``equations`` the unweighted :math:`(\mathcal A, \hat b)`, ``Q0`` and
        ``R0`` of the default filter, ``iterations``, ``Q_w`` with ``G``, and with the
        optimal weight ``overidentification``: ``(statistic, dof, p_value)`` of
        :math:`n\,r^\top \hat S^{-1} r \sim \chi^2` (a small p-value says the model does
        not explain the autocovariances).

    Notes
    -----
    Standard errors are asymptotic: :math:`\hat b` is a mean over :math:`n` samples,
    its covariance :math:`S/n` is given by Bartlett's formula for a stationary Gaussian
    sequence evaluated with the innovation autocovariances of the fitted model (up to
    the lag where they vanish), and the estimate's covariance is the sandwich
    :math:`(\mathcal A^\top W \mathcal A)^{-1} \mathcal A^\top W S W \mathcal A
    (\mathcal A^\top W \mathcal A)^{-1}/n` (:math:`(\mathcal A^\top S^{-1}
    \mathcal A)^{-1}/n` with the optimal weight; Rajamani & Rawlings 2009). They are
    those of the unconstrained estimate: where the PSD constraint is active they
    overstate the uncertainty of the constrained one. For a nonlinear model the
    sequence is treated as stationary with the time-averaged autocovariances.

    ``Q`` and ``R`` are identifiable when :math:`\mathcal A` has full column rank
    (Odelson et al. 2006, Rajamani & Rawlings 2009); otherwise a ``ValueError`` says
    so (use a diagonal or scalar structure, ``G``, or more lags).

    References
    ----------
    B. J. Odelson, M. R. Rajamani, J. B. Rawlings, "A new autocovariance least-squares
    method for estimating noise covariances", *Automatica* 42(2), 303-308, 2006.
    M. R. Rajamani, J. B. Rawlings, "Estimation of the disturbance structure from data
    using semidefinite programming and optimal weighting", *Automatica* 45(1),
    142-148, 2009.
    F. V. Lima, J. B. Rawlings, "Nonlinear stochastic modeling to improve state
    estimation in process monitoring and control", *AIChE J.* 57(4), 996-1007, 2011.
    R. K. Mehra, "On the identification of variances and adaptive Kalman filtering",
    *IEEE Trans. Automatic Control* 15(2), 175-184, 1970.
    """
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    iterations = as_int(iterations, "iterations", minimum=1)
    if iterations > 1:
        if gain is not None:
            raise ValueError("iterations > 1 re-tunes the default filter with each estimate: "
                             "give gain=None")
        same = {"x0": x0, "P0": P0, "lags": lags, "structure": structure, "G": G,
                "weighting": weighting, "burn_in": burn_in}
        res = als(model, Y, U, Q0=Q0, R0=R0, **same)
        for _ in range(iterations - 1):
            res = als(model, Y, U, Q0=_floored(res.Q), R0=_floored(res.R), **same)
        res.details["iterations"] = iterations
        return res
    if model.variable_dt:
        raise ValueError("model: als needs uniform samples; this model was built with "
                         "variable_dt=True")
    nx, ny = model.nx, model.ny
    Y = as_record(Y, ny, "Y", missing=False, names=model.output_names, what="outputs")
    T = Y.shape[0]
    U = as_inputs(U, T, model, "U")
    lags = as_int(lags, "lags", minimum=1)
    weighting = as_choice(weighting, WEIGHTINGS, "weighting")
    burn_in = as_int(burn_in, "burn_in", minimum=0, allow_none=True)
    if G is None:
        Gm = np.eye(nx)
    else:
        Gm = np.asarray(G, dtype=float)
        if Gm.ndim == 1:
            Gm = Gm[:, None]
        if Gm.ndim != 2 or Gm.shape[0] != nx or not np.isfinite(Gm).all():
            raise ValueError(f"G must be a finite ({nx}, ng) array, got shape {Gm.shape}")
    qblock, rblock = _structures(structure, Gm.shape[1], ny)
    W, Uh = _inputs(model, U)

    # ---- the filter
    from estim.estimators.ekf import EKF

    if gain is not None and not isinstance(gain, EKF):
        if hasattr(gain, "step"):
            raise TypeError(f"gain must be None, an (nx, ny) gain array or an estim.EKF, "
                            f"got {type(gain).__name__}")
        L = np.asarray(gain, dtype=float)
        if L.shape != (nx, ny) or not np.isfinite(L).all():
            raise ValueError(f"gain must be a finite ({nx}, {ny}) array, got shape {L.shape}")
    else:
        L = None
    if isinstance(gain, EKF):
        if gain.model is not model:
            raise ValueError("gain: the EKF must be built on the same model")
        if gain.clip or gain.gate is not None:
            raise ValueError("gain: the EKF must run without clip and gate (its innovations "
                             "must follow the linearised filter)")
        x0 = gain.x0
    x0 = np.zeros(nx) if x0 is None else as_vector(x0, nx, "x0")
    P0 = np.eye(nx) if P0 is None else as_covariance(P0, nx, "P0")
    linear = _is_linear(model, W, Uh, x0)
    if R0 is None:
        R0 = np.diag(np.maximum(np.var(np.diff(Y, axis=0), axis=0) / 2 if T > 2 else
                                np.ones(ny), 1e-12))
    R0 = as_covariance(R0, ny, "R0")
    if Q0 is None:
        C0 = np.asarray(model.H_x(x0, Uh[0], model.p).full())
        Cp = np.linalg.pinv(C0)
        q = 0.1 * np.diag(Cp @ R0 @ Cp.T)
        Q0 = np.diag(np.maximum(q, 1e-3 * max(q.max(), 1e-12)))
    Q0 = as_covariance(Q0, nx, "Q0", definite=False)

    A0 = C0 = None
    if linear and not isinstance(gain, EKF):
        A0 = np.asarray(model.F_x(x0, W[min(1, T - 1)], model.p).full())
        C0 = np.asarray(model.H_x(x0, Uh[0], model.p).full())
        if L is None:
            from scipy.linalg import solve_discrete_are

            try:
                Pp = solve_discrete_are(A0.T, C0.T, Q0, R0)
            except (np.linalg.LinAlgError, ValueError) as exc:
                raise ValueError(f"Q0, R0: no steady-state Kalman gain ({exc}); give other "
                                 f"Q0, R0 or a gain") from None
            L = np.linalg.solve(C0 @ Pp @ C0.T + R0, C0 @ Pp).T
            what = "steady-state Kalman gain of (Q0, R0)"
        else:
            what = "fixed gain"
        Abar0 = A0 @ (np.eye(nx) - L @ C0)
        rho = float(np.max(np.abs(np.linalg.eigvals(Abar0))))
        if rho >= 1:
            raise ValueError(f"gain: the filter is unstable (spectral radius of "
                             f"A (I - L C) is {rho:.4g} >= 1); ALS needs a stable gain")
        run = _affine_run(model, Y, W, Uh, L, x0, A0, C0)
        invariant = True
    else:
        if L is not None:
            run = _fixed_run(model, Y, W, Uh, L, x0)
            what = "fixed gain"
        else:
            ekf = gain if isinstance(gain, EKF) else EKF(model, Q=Q0, R=R0, x0=x0, P0=P0)
            what = "EKF (its own tuning)" if isinstance(gain, EKF) else "EKF of (Q0, R0)"
            P0 = ekf.P0
            run = _ekf_run(model, Y, U, W, Uh, ekf)
        invariant = False
        I_ = np.eye(nx)
        Abar_t = run["A"] @ (I_ - run["K"][:-1] @ run["C"][:-1])
        rho = float(np.median(np.max(np.abs(np.linalg.eigvals(Abar_t)), axis=1))) \
            if T > 1 else 0.0

    # ---- burn-in and samples
    decay = int(np.ceil(np.log(1e-3) / np.log(rho))) if 0 < rho < 1 else 1
    if burn_in is None:
        burn_in = int(min(max(decay, lags), T // 4))
    k_lo, k_hi = burn_in, T - lags  # the products e_{k+j} e_k^T, j < lags
    n = k_hi - k_lo + 1
    if n < max(20, 2 * lags):
        raise ValueError(f"Y has too few samples ({T}) for lags={lags} and burn_in={burn_in}: "
                         f"{n} products per lag; give a longer record or fewer lags")
    e = run["e"]
    rows = _rows(lags, ny)
    Chat = np.stack([e[k_lo + j:k_hi + j + 1].T @ e[k_lo:k_hi + 1] / n for j in range(lags)])
    b = _stack(Chat, rows)

    # ---- the design
    QB = _qbasis(qblock, Gm)
    RB = list(rblock.basis)
    nq = len(QB)
    M = int(np.clip(np.ceil(np.log(1e-6) / np.log(rho)) if 0 < rho < 1 else 1,
                    2 * lags, 400))
    if invariant:
        D0 = A0 @ L
        coef_all = _lti_coef(Abar0, D0, C0, QB, RB, M + lags + 1)
        coef = coef_all[:lags]
    else:
        Ak, Kk, Ck = run["A"], run["K"], run["C"]
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
    A_als = _stack(coef, rows)  # (rows, params)
    blocks = [qblock, rblock]
    splits = [slice(0, nq), slice(nq, nq + len(RB))]

    d = np.linalg.norm(A_als, axis=0)
    if np.any(d == 0):
        raise ValueError("structure: some free entries do not affect the innovations: "
                         "Q and R are not identifiable with this structure")
    sv = np.linalg.svd(A_als / d, compute_uv=False)
    if sv[-1] < 1e-9 * sv[0]:
        raise ValueError(f"structure: Q and R are not identifiable from these outputs with "
                         f"this structure and lags={lags} (the stacked autocovariance "
                         f"equations have rank {int(np.sum(sv > 1e-9 * sv[0]))} < "
                         f"{A_als.shape[1]} free entries); use a diagonal or scalar "
                         f"structure, a noise-shaping matrix G, or more lags")

    def S_at(theta):
        gamma = np.tensordot(theta, coef_all, axes=([0], [1]))  # (lags, ny, ny)
        return _bartlett(gamma, rows, M)

    Wh = np.eye(len(rows))
    theta_u, theta, active = _solve(A_als, b, blocks, splits)
    if weighting == "optimal":
        Lw = np.linalg.cholesky(S_at(theta))
        Wh = np.linalg.inv(Lw)
        theta_u, theta, active = _solve(Wh @ A_als, Wh @ b, blocks, splits)
    S = S_at(theta)
    Aw, r = Wh @ A_als, Wh @ (A_als @ theta - b)
    Binv = np.linalg.inv(Aw.T @ Aw)
    cov = Binv @ Aw.T @ (Wh @ S @ Wh.T) @ Aw @ Binv / n
    objective = float(r @ r)

    # ---- the estimates and their standard errors
    def mats(th):
        Qw = qblock.matrix(th[:nq])
        return Gm @ Qw @ Gm.T, rblock.matrix(th[nq:]), Qw

    Qh, Rh, Qw = mats(theta)
    Qh, Rh = 0.5 * (Qh + Qh.T), 0.5 * (Rh + Rh.T)
    JQ = np.stack([mats(np.eye(len(theta))[i])[0] for i in range(len(theta))], axis=-1)
    JR = np.stack([mats(np.eye(len(theta))[i])[1] for i in range(len(theta))], axis=-1)

    def se(J):
        v = np.sqrt(np.maximum(np.einsum("abi,ij,abj->ab", J, cov, J), 0.0))
        return np.where(np.any(J != 0, axis=-1), v, np.nan)

    stderr = {"Q": se(JQ), "R": se(JR), "params": {}}
    Qu, Ru, _ = mats(theta_u)

    # ---- the check: a filter with the estimates (the steady-state Kalman filter of a
    # linear model, else the EKF), after the burn-in
    Rf = Rh.copy()
    lam = np.linalg.eigvalsh(Rf).min()
    floor = 1e-9 * max(np.trace(Rf) / ny, 1e-300)
    if lam < floor:
        Rf += (floor - lam) * np.eye(ny)
    white = None
    if invariant:
        from scipy.linalg import solve_discrete_are

        try:
            Pp = solve_discrete_are(A0.T, C0.T, Qh, Rf)
            Sk = C0 @ Pp @ C0.T + Rf
            Lk = np.linalg.solve(Sk, C0 @ Pp).T
            if np.all(np.isfinite(Lk)) and np.max(np.abs(np.linalg.eigvals(
                    A0 @ (np.eye(nx) - Lk @ C0)))) < 1:
                chk = _affine_run(model, Y, W, Uh, Lk, x0, A0, C0)
                white = np.linalg.solve(np.linalg.cholesky(Sk), chk["e"].T).T
        except (np.linalg.LinAlgError, ValueError):
            white = None
    if white is None:
        chk = _ekf_run(model, Y, U, W, Uh, EKF(model, Q=Qh, R=Rf, x0=x0, P0=P0))
        Ls = np.linalg.cholesky(chk["S"])
        white = np.linalg.solve(Ls, chk["e"][..., None])[..., 0]
    check = innovation_check(white[burn_in:])

    details = {"lags": lags, "weighting": weighting, "burn_in": burn_in, "samples": n,
               "linearization": "time-invariant" if invariant else "time-varying",
               "gain": what, "spectral_radius": rho, "constraint_active": active,
               "unconstrained": {"Q": Qu, "R": Ru}, "theta": theta, "theta_cov": cov,
               "autocovariance": Chat, "equations": (A_als, b), "Q0": Q0, "R0": R0,
               "iterations": 1}
    if G is not None:
        details["Q_w"] = Qw
    if weighting == "optimal":
        from scipy import stats

        dof = len(rows) - len(theta)
        stat = n * objective
        details["overidentification"] = (stat, dof, float(stats.chi2.sf(stat, dof)))
    # variances the record hardly determines: a standard error beyond ten times the
    # largest variance of their matrix
    vague = [f"{name}[{i},{i}]" for name, M in (("Q", Qh), ("R", Rh))
             for i in range(len(M))
             if stderr[name][i, i] > 10 * max(float(np.max(np.diag(M))), 1e-300)]
    status = "ok" if not vague else (f"poorly determined: {', '.join(vague)} (standard error "
                                     f"above ten times the largest variance of its matrix)")
    return TuningResult(method="als", Q=Qh, R=Rh, stderr=stderr, check=check,
                        objective=objective, status=status, details=details)
