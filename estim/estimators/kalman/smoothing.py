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
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_inputs, as_intervals, as_record
from estim.estimators.base import Estimator
from estim.estimators.filtering import Estimates, stamped
from estim.solvers.kalman.rts import backward

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
