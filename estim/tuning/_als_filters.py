r"""The innovations autocovariance least squares works from: the filter runs.

ALS needs, at every sample :math:`k`, the innovation :math:`e_k = y_k - h(\bar x_k)`
of a filter with a stable gain :math:`K_k` and the Jacobians
:math:`A_k = \partial F/\partial x` (at :math:`\hat x_k`) and
:math:`C_k = \partial h/\partial x` (at :math:`\bar x_k`) along its estimates, for
the error recursion

.. math::
    \varepsilon_{k+1} = A_k (I - K_k C_k) \varepsilon_k + w_k - A_k K_k v_k, \qquad
    e_k = C_k \varepsilon_k + v_k.

Three filters give them: a constant gain on a linear model (plain numpy, the
time-invariant ALS of Odelson, Rajamani & Rawlings 2006), a constant gain on a
nonlinear model, and an :class:`~estim.EKF` replayed over the record (the
time-varying ALS of Lima & Rawlings 2011). The filter of the estimated ``Q, R``
then whitens the innovations for the result's check.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim.model import Model

if TYPE_CHECKING:
    from estim.estimators.kalman.ekf import EKF


@dataclass
class _Run:
    """A filter's run over a record of ``T`` samples: innovations ``e (T, ny)``, gains
    ``K (T, nx, ny)``, Jacobians ``A (T-1, nx, nx)`` and ``C (T, ny, nx)``, the
    estimates ``xh (T, nx)``, and the innovation covariances ``S (T, ny, ny)`` of an
    EKF (None for a constant gain)."""

    e: np.ndarray
    K: np.ndarray
    A: np.ndarray
    C: np.ndarray
    xh: np.ndarray
    S: np.ndarray | None = None


@dataclass
class _Invariant:
    """A linear model with a constant gain: ``A (nx, nx)``, ``C (ny, nx)``, the gain
    ``L (nx, ny)`` and ``Abar = A (I - L C)``."""

    A: np.ndarray
    C: np.ndarray
    L: np.ndarray
    Abar: np.ndarray


@dataclass
class _Filter:
    r"""The filter ALS uses: its ``run``, a description (``what``), the spectral radius
    ``rho`` of :math:`\bar A` (median over samples when it varies), its prior
    covariance ``P0``, and ``invariant`` for a linear model with a constant gain."""

    run: _Run
    what: str
    rho: float
    P0: np.ndarray
    invariant: _Invariant | None


def _inputs(model: Model, U: np.ndarray, dts: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """``W[k]``: the input of the transition into sample ``k`` (row 0 unused; with
    ``variable_dt`` the interval ``dts[k-1]`` last, default the model's ``dt``), and
    ``Uh[k]``: the input ``h`` sees at sample ``k``, with :func:`estim.replay`'s
    conventions."""
    T, nu = U.shape
    prev = np.vstack([np.zeros((1, nu)), U[:-1]])
    Uh = U.copy() if model.sampled else prev
    steps = np.full(T, model.dt) if dts is None else np.concatenate([[model.dt], dts])
    return model.transitions(prev, U if model.sampled else prev, steps), Uh


def _mapped(fun: ca.Function, n: int, *args: np.ndarray) -> np.ndarray:
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


def _ekf_run(model: Model, Y: np.ndarray, U: np.ndarray, W: np.ndarray, Uh: np.ndarray,
             ekf: EKF, t: np.ndarray | None = None) -> _Run:
    """Replay an :class:`~estim.EKF` (at the times ``t`` of a ``variable_dt`` model) and
    rebuild, per sample, its prediction, innovation, innovation covariance, gain and
    Jacobians (the EKF's own equations; with ``Qc=`` its moment equations, and ``A`` the
    Jacobian of the mean's flow over each interval)."""
    from estim.simulate import replay

    log = replay(ekf, Y, U, t=t, warn=False)
    T, nx = log.x_hat.shape
    xh, P = log.x_hat, log.P
    p = np.tile(model.p, (T, 1))
    xb = np.empty_like(xh)
    xb[0] = ekf.x0
    Pb = np.empty_like(P)
    Pb[0] = ekf.P0
    if ekf.Qc is not None and T > 1:  # the continuous-discrete prediction
        from estim.estimators.kalman.continuous import ekf_moments

        xb[1:], Pb[1:], A = ekf_moments(ekf)(xh[:-1], P[:-1], W[1:])
        C = _mapped(model.H_x, T, xb, Uh, p)
    else:
        if T > 1:
            xb[1:] = _mapped(model.F, T - 1, xh[:-1], W[1:], p[:-1])[:, :, 0]
        A, C = _jacobians(model, xh, xb, W, Uh)
        Pb[1:] = A @ P[:-1] @ A.transpose(0, 2, 1) + ekf.Q
    e = Y - _mapped(model.H, T, xb, Uh, p)[:, :, 0]
    S = C @ Pb @ C.transpose(0, 2, 1) + ekf.R
    S = 0.5 * (S + S.transpose(0, 2, 1))
    K = np.linalg.solve(S, C @ Pb).transpose(0, 2, 1)
    return _Run(e=e, K=K, A=A, C=C, xh=xh, S=S)


def _fixed_run(model: Model, Y: np.ndarray, W: np.ndarray, Uh: np.ndarray, L: np.ndarray,
               x0: np.ndarray) -> _Run:
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
    return _Run(e=e, K=K, A=A, C=C, xh=xh)


def _affine_run(model: Model, Y: np.ndarray, W: np.ndarray, Uh: np.ndarray, L: np.ndarray,
                x0: np.ndarray, A0: np.ndarray, C0: np.ndarray) -> _Run:
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
    return _Run(e=e, K=K, A=np.broadcast_to(A0, (max(T - 1, 0), nx, nx)),
                C=np.broadcast_to(C0, (T,) + C0.shape), xh=xb + e @ L.T)


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


def _run_filter(model: Model, Y: np.ndarray, U: np.ndarray, W: np.ndarray, Uh: np.ndarray,
                ekf: EKF | None, L: np.ndarray | None, x0: np.ndarray, P0: np.ndarray,
                Q0: np.ndarray, R0: np.ndarray, linear: bool, Qc0: np.ndarray | None = None,
                t: np.ndarray | None = None) -> _Filter:
    """The filter of :func:`~estim.tuning.als` run over the record.

    A linear model without an EKF: the constant gain ``L`` or, when None, the
    steady-state Kalman gain of ``(Q0, R0)`` (it must stabilise the filter). Otherwise
    the constant gain ``L`` on the nonlinear model, or ``ekf``, or an EKF with
    ``Q0, R0, x0, P0`` (with a continuous noise ``Qc0``: ``EKF(Qc=Qc0)`` at the times
    ``t``).
    """
    from estim.estimators.kalman.ekf import EKF

    nx = model.nx
    T = Y.shape[0]
    if linear and ekf is None:
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
        return _Filter(run, what, rho, P0, _Invariant(A0, C0, L, Abar0))
    if L is not None:
        run = _fixed_run(model, Y, W, Uh, L, x0)
        what = "fixed gain"
    else:
        what = "EKF (its own tuning)" if ekf is not None else "EKF of (Q0, R0)"
        if ekf is None:
            ekf = EKF(model, Q=Q0, R=R0, x0=x0, P0=P0) if Qc0 is None else \
                EKF(model, Qc=Qc0, R=R0, x0=x0, P0=P0)
        assert ekf.P0 is not None  # an EKF always has its prior covariance
        P0 = ekf.P0
        run = _ekf_run(model, Y, U, W, Uh, ekf, t)
    I_ = np.eye(nx)
    Abar_t = run.A @ (I_ - run.K[:-1] @ run.C[:-1])
    rho = float(np.median(np.max(np.abs(np.linalg.eigvals(Abar_t)), axis=1))) \
        if T > 1 else 0.0
    return _Filter(run, what, rho, P0, None)


def _whitened(model: Model, Y: np.ndarray, U: np.ndarray, W: np.ndarray, Uh: np.ndarray,
              filt: _Filter, Q: np.ndarray, R: np.ndarray, x0: np.ndarray,
              Qc: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    r"""The whitened innovations :math:`L_k^{-1} e_k` (:math:`L_k L_k^\top = S_k`)
    ``(T, ny)`` of a filter with the estimates ``Q, R``: the steady-state Kalman filter
    of a linear model (when it exists and is stable), else an EKF from ``x0`` and the
    filter's ``P0`` (``EKF(Qc=Qc)`` at the times ``t`` with a continuous noise). ``R`` is
    raised to a positive definite matrix first."""
    from estim.estimators.kalman.ekf import EKF

    nx, ny = model.nx, model.ny
    Rf = R.copy()
    lam = np.linalg.eigvalsh(Rf).min()
    floor = 1e-9 * max(np.trace(Rf) / ny, 1e-300)
    if lam < floor:
        Rf += (floor - lam) * np.eye(ny)
    lti = filt.invariant
    if lti is not None:
        from scipy.linalg import solve_discrete_are

        A0, C0 = lti.A, lti.C
        try:
            Pp = solve_discrete_are(A0.T, C0.T, Q, Rf)
            Sk = C0 @ Pp @ C0.T + Rf
            Lk = np.linalg.solve(Sk, C0 @ Pp).T
            if np.all(np.isfinite(Lk)) and np.max(np.abs(np.linalg.eigvals(
                    A0 @ (np.eye(nx) - Lk @ C0)))) < 1:
                chk = _affine_run(model, Y, W, Uh, Lk, x0, A0, C0)
                return np.linalg.solve(np.linalg.cholesky(Sk), chk.e.T).T
        except (np.linalg.LinAlgError, ValueError):
            pass
    ekf = EKF(model, Q=Q, R=Rf, x0=x0, P0=filt.P0) if Qc is None else \
        EKF(model, Qc=Qc, R=Rf, x0=x0, P0=filt.P0)
    chk = _ekf_run(model, Y, U, W, Uh, ekf, t)
    assert chk.S is not None  # an EKF's run has its innovation covariances
    Ls = np.linalg.cholesky(chk.S)
    return np.linalg.solve(Ls, chk.e[..., None])[..., 0]
