r"""Rauch-Tung-Striebel smoothing of a whole record by a Kalman-type filter.

:meth:`EKF.smooth <estim.EKF.smooth>` and :meth:`UKF.smooth <estim.UKF.smooth>`
run the filter forward over the record (its whole-record ``filter``, equal to its
``step`` at every sample: inputs, missing outputs, gating and clipping as in
:func:`~estim.replay`), then go back from the last sample. For each transition
:math:`k \to k+1` the prediction from the filtered estimate gives a mean
:math:`\bar x_{k+1}`, a covariance :math:`\bar P_{k+1}` and a cross-covariance
:math:`D_{k+1}` between
:math:`x_k` and :math:`x_{k+1}`; then

.. math::
    G_k = D_{k+1} \bar P_{k+1}^{-1}, \qquad
    x^s_k = \hat x_k + G_k (x^s_{k+1} - \bar x_{k+1}), \qquad
    P^s_k = P_k + G_k (P^s_{k+1} - \bar P_{k+1}) G_k^\top,

from :math:`x^s_{T-1} = \hat x_{T-1}`, :math:`P^s_{T-1} = P_{T-1}`. The extended
smoother linearises, :math:`\bar x_{k+1} = F(\hat x_k, u_k)`,
:math:`\bar P_{k+1} = A_k P_k A_k^\top + Q`, :math:`D_{k+1} = P_k A_k^\top` with
:math:`A_k = \partial F/\partial x` at :math:`\hat x_k`; the unscented one
propagates the sigma points :math:`\mathcal X^{(i)}` of :math:`(\hat x_k, P_k)`:
:math:`\bar x_{k+1} = \sum_i W^m_i F(\mathcal X^{(i)})`,
:math:`\bar P_{k+1} = \sum_i W^c_i (F(\mathcal X^{(i)}) - \bar x_{k+1})(\cdot)^\top + Q`,
:math:`D_{k+1} = \sum_i W^c_i (\mathcal X^{(i)} - \hat x_k)(F(\mathcal X^{(i)}) -
\bar x_{k+1})^\top`.

References
----------
H. E. Rauch, F. Tung, C. T. Striebel, "Maximum likelihood estimates of linear
dynamic systems", AIAA J. 3(8), 1965;
S. Särkkä, "Unscented Rauch-Tung-Striebel smoother", IEEE TAC 53(3), 2008;
S. Särkkä, *Bayesian Filtering and Smoothing*, Cambridge University Press, 2013, ch. 9.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_inputs, as_int, as_intervals, as_record
from estim.estimators.base import Estimator
from estim.estimators.filtering import Estimates, stamped
from estim.solvers.kalman.continuous import discretised_noises
from estim.solvers.kalman.rts import backward, transitions

#: A prediction of a whole record: from the filtered means ``(T-1, nx)``, covariances
#: ``(T-1, nx, nx)`` and transitions' inputs ``(T-1, nw)``, the predicted means and
#: covariances of the next samples and the cross-covariances ``D``.
Predictor = Callable[[np.ndarray, np.ndarray, np.ndarray],
                     tuple[np.ndarray, np.ndarray, np.ndarray]]


@dataclass(frozen=True, repr=False)
class SmoothResult(Estimates):
    """A record smoothed by :meth:`EKF.smooth <estim.EKF.smooth>` or
    :meth:`UKF.smooth <estim.UKF.smooth>`.

    Attributes
    ----------
    x : (T, nx) array
        Smoothed means :math:`x^s_k = E[x_k \\mid y_0, \\dots, y_{T-1}]`.
    P : (T, nx, nx) array
        Smoothed covariances :math:`P^s_k`.
    x_filtered : (T, nx) array
        The filter's estimates :math:`\\hat x_{k|k}` (what ``step`` returned).
    P_filtered : (T, nx, nx) array
        Their covariances.
    x_predicted : (T-1, nx) array
        Predictions :math:`\\bar x_{k+1}` from the filtered estimates, one per transition.
    P_predicted : (T-1, nx, nx) array
        Their covariances :math:`\\bar P_{k+1}`.
    gain : (T-1, nx, nx) array
        Smoother gains :math:`G_k`.
    status : tuple of str
        The filter's status of every sample (``"ok"``, ``"rejected: ..."``, ...).
    success : bool
        Every step of the filter succeeded.
    iterations : int
        Passes of the iterated smoother (1: the extended or unscented smoother).
    converged : bool
        The iterated smoother's last pass moved no mean (beyond rounding); True for one
        pass.
    t, state_names, manifold :
        Sample times, state names and the states' manifold (see
        :class:`~estim.estimators.filtering.Estimates`).
    """

    x: np.ndarray
    P: np.ndarray
    x_filtered: np.ndarray
    P_filtered: np.ndarray
    x_predicted: np.ndarray
    P_predicted: np.ndarray
    gain: np.ndarray
    status: tuple[str, ...]
    success: bool
    iterations: int = 1
    converged: bool = True


def record(model, Y: ArrayLike, U: ArrayLike | None, t: ArrayLike | None
           ) -> tuple[np.ndarray, list, np.ndarray]:
    """The measurements ``(T, ny)``, the ``step`` arguments ``(u, dt)`` of every sample and
    the transitions' inputs ``W (T-1, nw)`` of a record (as :func:`~estim.replay` and
    ``FullInformation.fit`` read it)."""
    Y = as_record(Y, model.ny, "Y", names=model.output_names, what="outputs")
    T = Y.shape[0]
    U = as_inputs(U, T, model)
    dts = as_intervals(t, T, model)
    steps = []
    for k in range(T):
        # the input since the previous sample (held), or at this one (sampled models)
        u = U[k] if model.sampled else U[k - 1] if k else np.zeros(model.nu)
        steps.append((u, None if dts is None or k == 0 else float(dts[k - 1])))
    return Y, steps, model.transitions(U[:-1], U[1:] if model.sampled else U[:-1], dts)


def rts(estimator: Estimator, Y: ArrayLike, U: ArrayLike | None, t: ArrayLike | None,
        predict: Predictor, clip: Callable[[np.ndarray], np.ndarray] | None = None
        ) -> SmoothResult:
    r"""Filter the record (with ``estimator.filter``, the whole record in one compiled
    call, where the estimator has it; else ``step`` at every sample after a reset),
    then the backward pass.

    Parameters
    ----------
    estimator : Estimator
        A filter whose ``info.P`` is the covariance of its estimate.
    Y, U, t :
        The record, as for :meth:`EKF.smooth <estim.EKF.smooth>`.
    predict : callable
        ``(X, P, W) -> (x_bar, P_bar, D)`` over all transitions at once, shapes
        ``(T-1, nx)``, ``(T-1, nx, nx)``, ``(T-1, nx, nx)``.
    clip : callable, optional
        Projection applied to each smoothed mean (the filter's clipping).
    """
    m = estimator.model
    Y, steps, W = record(m, Y, U, t)
    T, nx, nd = Y.shape[0], m.nx, m.ndx
    if hasattr(estimator, "filter"):  # the whole record in one compiled call
        res = estimator.filter(Y, U, t=t)
        Xf, Pf, status, success = res.x, res.P, list(res.status), res.success
    else:
        Xf, Pf = np.empty((T, nx)), np.empty((T, nd, nd))
        status, success = [], True
        estimator.reset()
        for k in range(T):
            u, dt = steps[k]
            Xf[k] = estimator.step(Y[k].copy(), u, dt=dt)
            info = estimator.info
            Pf[k] = np.nan if info.P is None else info.P
            status.append(info.status)
            success = success and info.success
    xb, Pb, D = predict(Xf[:-1], Pf[:-1], W) if T > 1 else \
        (np.empty((0, nx)), np.empty((0, nd, nd)), np.empty((0, nd, nd)))
    M = m.manifold
    Xs, Ps, G = backward(Xf, Pf, xb, Pb, D, clip, None if M.euclidean_states else M)
    return stamped(SmoothResult(x=Xs, P=Ps, x_filtered=Xf, P_filtered=Pf, x_predicted=xb,
                                P_predicted=Pb, gain=G, status=tuple(status),
                                success=success), m, t)


def smoothing_passes(estimator, iterations: int | None) -> int:
    """The passes of an iterated smoother: ``iterations`` (default the filter's), checked;
    more than one needs unconstrained passes over every measurement on vector states."""
    passes = estimator.iterations if iterations is None else \
        as_int(iterations, "iterations", minimum=1)
    if passes > 1 and (estimator.clip or estimator.gate is not None or estimator._sqrt
                       or not estimator.model.manifold.trivial):
        raise ValueError(f"iterations={passes}: the iterated smoother's passes are "
                         f"unconstrained, use every measurement and vector states: not "
                         f"with clip=True, a gate, the square-root form, quaternion or "
                         f"angle states")
    return passes


def iterated(estimator: Estimator, first: SmoothResult, Y: ArrayLike, U: ArrayLike | None,
             t: ArrayLike | None, iterations: int, tol: float = 1e-12) -> SmoothResult:
    r"""The iterated extended Rauch-Tung-Striebel smoother (Bell 1994): from the
    extended smoother's result ``first``, up to ``iterations - 1`` more passes, each the
    Kalman filter and RTS smoother of the model linearised about the previous smoothed
    trajectory :math:`\bar x_{0:T-1}`:

    .. math::
        x_{k+1} \approx F(\bar x_k) + A_k (x_k - \bar x_k), \qquad
        y_k \approx h(\bar x_k) + C_k (x_k - \bar x_k),

    with :math:`A_k = \partial F/\partial x`, :math:`C_k = \partial h/\partial x` at
    :math:`\bar x_k`, the prior :math:`(x_0, P_0)` on the first sample. Each pass is a
    Gauss-Newton step on the whole record's MAP problem, so the fixed point is
    :meth:`FullInformation.fit <estim.FullInformation.fit>`'s optimum (with the same
    prior), the covariances its Laplace covariances. With a continuous noise (``Qc=``)
    the noise of transition :math:`k` is :math:`Q_d(\Delta t_k)` of the drift linearised
    at :math:`\bar x_k` (:func:`~estim.solvers.kalman.continuous.discretised_noise`),
    the weights of ``FullInformation(Qc=...)``, whose optimum is then the fixed point.
    Stops early when no mean moved by more than ``tol`` relative to its size;
    ``iterations`` and ``converged`` say how it ended.

    References
    ----------
    B. M. Bell, "The iterated Kalman smoother as a Gauss-Newton method", SIAM J.
    Optim. 4(3), 1994; S. Särkkä, L. Svensson, *Bayesian Filtering and Smoothing*, 2nd
    ed., 2023, sec. 13.1.
    """
    m = estimator.model
    Y, steps, W = record(m, Y, U, t)
    T, nx = Y.shape[0], m.nx
    Uy = np.array([u for u, _ in steps]).reshape(T, m.nu)
    pm = ca.DM(m.p)
    out = (m.H.map(T), m.H_x.map(T))
    Qs = np.broadcast_to(estimator.Q, (max(T - 1, 0), nx, nx))
    Rs = np.broadcast_to(estimator.R, (T, m.ny, m.ny))
    continuous = getattr(estimator, "Qc", None) is not None

    def linearise(Xs, Ps):  # the Jacobians and the affine terms at the trajectory
        nonlocal Qs
        if continuous and T > 1:  # each interval's Q_d at the trajectory
            Qs = discretised_noises(m, estimator.Q, Xs[:-1], W)
        FX = transitions(m, Xs[:-1], W) if T > 1 else np.empty((0, nx))
        A = transitions(m, Xs[:-1], W, jacobian=True) if T > 1 else np.empty((0, nx, nx))
        HX = np.asarray(out[0](Xs.T, Uy.T, pm)).T
        C = np.asarray(out[1](Xs.T, Uy.T, pm)).reshape(m.ny, T, nx).transpose(1, 0, 2)
        return (A, FX - np.einsum("kab,kb->ka", A, Xs[:-1]), Qs,
                C, HX - np.einsum("kab,kb->ka", C, Xs), Rs)

    return _passes(estimator, first, Y, first.x, first.P, iterations - 1, tol, linearise,
                   start=1)


def posterior_linearised(estimator, first: SmoothResult, Y: ArrayLike, U: ArrayLike | None,
                         t: ArrayLike | None, iterations: int, tol: float = 1e-12,
                         moments: Predictor | None = None) -> SmoothResult:
    r"""The iterated posterior linearisation smoother (IPLS; García-Fernández, Svensson
    & Särkkä 2017) of a sigma-point filter: from the filter's estimates
    (``first.x_filtered``, ``first.P_filtered``), up to ``iterations`` passes, each the
    Kalman filter and RTS smoother of the model linearised by statistical linear
    regression on the sigma points of the current posteriors :math:`N(\bar x_k, \bar P_k)`:

    .. math::
        f(x_k) \approx A_k x_k + a_k + \lambda_k, \quad \lambda_k \sim N(0, \Lambda_k),
        \qquad h(x_k) \approx H_k x_k + b_k + \omega_k, \quad \omega_k \sim N(0, \Omega_k),

    with :math:`A_k = \Psi_k^\top \bar P_k^{-1}`, :math:`a_k = \bar f_k - A_k \bar x_k`,
    :math:`\Lambda_k = \Phi_k - A_k \bar P_k A_k^\top` from the sigma-point mean
    :math:`\bar f_k`, cross-covariance :math:`\Psi_k` and covariance :math:`\Phi_k` of
    :math:`f` (the same for :math:`h`), then the posteriors are the smoothed ones. Stops
    early when no mean moved by more than ``tol`` relative to its size.

    With a continuous noise (``Qc=``; ``moments`` the filter's sigma-point moment
    equations of every transition, ``(X, P, W) -> (mean, covariance, _)``) the transition
    over an interval is that of the
    stochastic differential equation: :math:`A_k` from the cross-covariance of the
    noise-free flow (the model's ``F``) at the sigma points, as the continuous-discrete
    unscented smoother takes it, and the mean and covariance of :math:`x_{k+1}` from the
    sigma-point moment equations started at :math:`N(\bar x_k, \bar P_k)`:
    :math:`a_k = \bar m_k - A_k \bar x_k`, :math:`Q_k + \Lambda_k = \bar P^{+}_k -
    A_k \bar P_k A_k^\top` (on a linear model :math:`A_k = e^{A\Delta t_k}` and this is
    the exact :math:`Q_d(\Delta t_k)`)."""
    m = estimator.model
    Y, steps, W = record(m, Y, U, t)
    T, nx, ny = Y.shape[0], m.nx, m.ny
    Uy = np.array([u for u, _ in steps]).reshape(T, m.nu)
    Wm, Wc = estimator._Wm, estimator._Wc
    ns = len(Wm)
    H_map, F_map = m.H.map(T * ns), m.F.map(max(T - 1, 1) * ns)
    Wr = np.repeat(W, ns, axis=0).T  # the transitions' inputs at each sigma point
    pm = ca.DM(m.p)

    def regression(sig, X, P, out):
        """``(A, a, Lambda)`` of the outputs ``out (n, ns, d)`` at the points ``sig``."""
        mean = np.einsum("j,kjd->kd", Wm, out)
        dO, dX = out - mean[:, None], sig - X[:, None]
        Phi = np.einsum("j,kja,kjb->kab", Wc, dO, dO)
        Psi = np.einsum("j,kja,kjb->kab", Wc, dX, dO)
        A = np.linalg.solve(P, Psi).transpose(0, 2, 1)
        return A, mean - np.einsum("kab,kb->ka", A, X), \
            Phi - A @ P @ A.transpose(0, 2, 1)

    def linearise(Xs, Ps):  # by regression on the posteriors' sigma points
        sig = estimator.sigma_points(Xs, Ps)  # (T, ns, nx)
        Z = np.asarray(H_map(sig.reshape(T * ns, nx).T, np.repeat(Uy, ns, axis=0).T,
                             pm)).T.reshape(T, ns, ny)
        H, b, Om = regression(sig, Xs, Ps, Z)
        A, a, Lam = np.empty((0, nx, nx)), np.empty((0, nx)), np.empty((0, nx, nx))
        if T > 1:
            Fs = np.asarray(F_map(sig[:-1].reshape((T - 1) * ns, nx).T, Wr, pm)).T.reshape(
                T - 1, ns, nx)
            A, a, Lam = regression(sig[:-1], Xs[:-1], Ps[:-1], Fs)
            if moments is not None:  # the SDE's moments over each interval
                mean, cov, _ = moments(Xs[:-1], Ps[:-1], W)
                a = mean - np.einsum("kab,kb->ka", A, Xs[:-1])
                Lam = cov - A @ Ps[:-1] @ A.transpose(0, 2, 1) - estimator.Q
        return A, a, Lam + estimator.Q, H, b, Om + estimator.R

    return _passes(estimator, first, Y, first.x_filtered, first.P_filtered, iterations, tol,
                   linearise)


def _passes(estimator, first: SmoothResult, Y: np.ndarray, Xs: np.ndarray, Ps: np.ndarray,
            passes: int, tol: float, linearise: Callable, start: int = 0) -> SmoothResult:
    r"""Up to ``passes`` passes from the posteriors ``(Xs, Ps)``: each the Kalman filter
    (from the estimator's prior, on the first sample) and RTS smoother of the affine model
    ``linearise(Xs, Ps)`` gives, :math:`x_{k+1} = A_k x_k + a_k + N(0, Q_k)`,
    :math:`y_k = H_k x_k + b_k + N(0, R_k)`, whose smoothed posteriors are the next
    pass's; ``first`` with the last, the passes done (``start`` counted before) and
    whether no mean moved beyond ``tol`` relative to its size."""
    T, nx = len(Xs), Xs.shape[1]
    mask = np.isfinite(Y)
    full, some = mask.all(axis=1).tolist(), mask.any(axis=1).tolist()
    eye = np.eye(nx)
    done, converged = start, passes == 0
    for _ in range(passes):
        A, a, Qk, H, b, Rk = linearise(Xs, Ps)
        Xf, Pf = np.empty((T, nx)), np.empty((T, nx, nx))
        xb, Pb, D = np.empty((T - 1, nx)), np.empty((T - 1, nx, nx)), np.empty((T - 1, nx, nx))
        x, P = np.asarray(estimator.x0, float), np.asarray(estimator.P0, float)
        AT = A.transpose(0, 2, 1)
        r = Y - b  # the measurements less the affine terms (NaN where missing)
        for k in range(T):
            if k:
                x = A[k - 1] @ Xf[k - 1] + a[k - 1]
                Dk = D[k - 1] = Pf[k - 1] @ AT[k - 1]
                P = A[k - 1] @ Dk + Qk[k - 1]
                xb[k - 1], Pb[k - 1] = x, 0.5 * (P + P.T)
            if some[k]:  # the update by the measured rows (Joseph form)
                if full[k]:
                    C, Rm, rk = H[k], Rk[k], r[k]
                else:
                    rows = mask[k]
                    C, Rm, rk = H[k][rows], Rk[k][np.ix_(rows, rows)], r[k, rows]
                CP = C @ P
                S = CP @ C.T + Rm
                K = np.linalg.solve(0.5 * (S + S.T), CP).T
                x = x + K @ (rk - C @ x)
                IKC = eye - K @ C
                P = IKC @ P @ IKC.T + K @ Rm @ K.T
            Xf[k], Pf[k] = x, 0.5 * (P + P.T)
        new, Ps, _ = backward(Xf, Pf, xb, Pb, D)
        done += 1
        moved = np.abs(new - Xs).max()
        Xs = new
        if not np.isfinite(Xs).all():
            break
        if moved <= tol * max(1.0, np.abs(Xs).max()):
            converged = True
            break
    return replace(first, x=Xs, P=Ps, iterations=done, converged=bool(converged))
