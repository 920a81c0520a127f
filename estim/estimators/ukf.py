r"""Unscented Kalman filter on filterpy's ``UnscentedKalmanFilter``."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_bool, as_float
from estim.estimators.base import Estimator, StepInfo, chi2_limit
from estim.estimators.smoothing import SmoothResult, rts, transitions
from estim.model import Model


class UKF(Estimator):
    r"""Unscented Kalman filter with Van der Merwe's scaled sigma points.

    Same constructor, ``step`` and ``reset`` as :class:`~estim.EKF`; the
    prediction and update propagate :math:`2n_x + 1` sigma points through the
    model's :math:`F` and :math:`h` instead of linearising. filterpy's
    :class:`~filterpy.kalman.UnscentedKalmanFilter` does the arithmetic; the
    model functions are the compiled CasADi ones.

    Parameters
    ----------
    model : Model
    Q, R, x0, P0 :
        As for every estimator.
    alpha, beta, kappa : float
        Sigma-point spread (:math:`\alpha`), prior knowledge of the
        distribution (:math:`\beta = 2` for Gaussian) and secondary scaling.
    clip : bool
        Project the estimate onto the model bounds after each update.
    gate : float, optional
        Reject a measurement whose normalised innovation squared lies beyond this
        tail probability of its chi-square distribution, as :class:`~estim.EKF` does.

    References
    ----------
    R. van der Merwe, *Sigma-Point Kalman Filters for Probabilistic Inference
    in Dynamic State-Space Models*, PhD thesis, OGI 2004;
    E. A. Wan, R. van der Merwe, "The unscented Kalman filter for nonlinear
    estimation", IEEE AS-SPCC 2000.
    """

    name = "ukf"

    def __init__(self, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                 P0: ArrayLike, alpha: float = 0.1, beta: float = 2.0,
                 kappa: float = 0.0, clip: bool = False, gate: float | None = None):
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.gate = self._gate(gate)
        self.alpha = as_float(alpha, "alpha", positive=True)
        self.beta, self.kappa = as_float(beta, "beta"), as_float(kappa, "kappa")
        self.clip = as_bool(clip, "clip")
        self.lower, self.upper = model.lower, model.upper
        # buffered model evaluations of this filter's own (never shared between threads)
        self._F, self._H = FastFunction(model.F), FastFunction(model.H)
        self._reset()

    def _tuning_changed(self) -> None:
        self._ukf.Q, self._ukf.R = self.Q.copy(), self.R.copy()

    def _fx(self, x, dt, u):
        return self._F(x, u, self.model.p)[0].copy()

    def _hx(self, x, u, rows=None):
        y = self._H(x, u, self.model.p)[0]
        return y.copy() if rows is None else y[rows].copy()

    def _reset(self) -> None:
        # filterpy imports scipy.stats (~0.3 s): on the first filter, not with estim
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

        m = self.model
        points = MerweScaledSigmaPoints(m.nx, alpha=self.alpha, beta=self.beta, kappa=self.kappa)
        ukf = UnscentedKalmanFilter(dim_x=m.nx, dim_z=m.ny, dt=m.dt, hx=self._hx, fx=self._fx,
                                    points=points)
        ukf.x = self.x0.copy()
        ukf.P = self.P0.copy()
        ukf.Q = self.Q.copy()
        ukf.R = self.R.copy()
        self._ukf = ukf
        self._trusted = True  # the last step was "ok" (or none was taken)
        self._anchor_state = (self.x0.copy(), self.P0.copy())

    def smooth(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None) -> SmoothResult:
        r"""Unscented Rauch-Tung-Striebel smoother over a whole record (Särkkä 2008).

        The filter runs forward over the record with :meth:`step` (after a
        :meth:`reset`; inputs, missing outputs, gating and clipping as in
        :func:`~estim.replay`). Backwards from :math:`x^s_{T-1} = \hat x_{T-1}`,
        :math:`P^s_{T-1} = P_{T-1}`: the filter's sigma points
        :math:`\mathcal X^{(i)}` of :math:`(\hat x_k, P_k)` (weights
        :math:`W^m_i, W^c_i`) go through :math:`F` with the input :math:`u_k`,

        .. math::
            \bar x_{k+1} = \sum_i W^m_i F(\mathcal X^{(i)}), \quad
            \bar P_{k+1} = \sum_i W^c_i\, \delta F_i\, \delta F_i^\top + Q, \quad
            D_{k+1} = \sum_i W^c_i (\mathcal X^{(i)} - \hat x_k)\, \delta F_i^\top,

        with :math:`\delta F_i = F(\mathcal X^{(i)}) - \bar x_{k+1}`, and

        .. math::
            G_k = D_{k+1} \bar P_{k+1}^{-1}, \quad
            x^s_k = \hat x_k + G_k (x^s_{k+1} - \bar x_{k+1}), \quad
            P^s_k = P_k + G_k (P^s_{k+1} - \bar P_{k+1}) G_k^\top .

        This is filterpy's ``UnscentedKalmanFilter.rts_smoother`` with the
        inputs passed to :math:`F` (filterpy's calls ``fx(x, dt)`` without them)
        and a linear solve for :math:`G_k`. With ``clip``, each smoothed mean is
        projected on the model's bounds too.

        Parameters
        ----------
        Y : (T, ny) array
            Measurements, NaN where missing.
        U : (T-1, nu) or (T, nu) array, optional
            ``U[k]`` acts from sample k to k+1 (with ``hold="foh"``: ``(T, nu)``,
            the input at each sample), as in ``FullInformation.fit``. Zero if omitted.
        t : (T,) array, optional
            Sample times, for a model built with ``variable_dt=True``.

        Returns
        -------
        SmoothResult
            ``x (T, nx)``, ``P (T, nx, nx)``, the filtered ``x_filtered``,
            ``P_filtered``, the predictions, gains and statuses. The filter is
            left at the end of the record.

        References
        ----------
        S. Särkkä, "Unscented Rauch-Tung-Striebel smoother", IEEE TAC 53(3), 2008.
        """
        m, Q = self.model, self.Q

        def predict(X, P, W):
            pts = self._ukf.points_fn
            n, ns, nx = len(X), pts.num_sigmas(), m.nx
            sig = np.array([pts.sigma_points(X[k], P[k]) for k in range(n)])  # (n, ns, nx)
            Fs = transitions(m, sig.reshape(n * ns, nx), np.repeat(W, ns, axis=0)
                             ).reshape(n, ns, nx)
            xb = np.einsum("i,kij->kj", pts.Wm, Fs)
            dF, dX = Fs - xb[:, None, :], sig - X[:, None, :]
            Pb = np.einsum("i,kia,kib->kab", pts.Wc, dF, dF) + Q
            D = np.einsum("i,kia,kib->kab", pts.Wc, dX, dF)
            return xb, 0.5 * (Pb + Pb.transpose(0, 2, 1)), D

        return rts(self, Y, U, t, predict, self.model.clip if self.clip else None)

    @property
    def x(self) -> np.ndarray:
        return self._ukf.x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._ukf.P.copy()

    def _step(self, y, u, first):
        ukf = self._ukf
        if self._trusted:  # the anchor of a failed step: the last state reported "ok"
            self._anchor_state = (ukf.x.copy(), ukf.P.copy())
        if first:  # no prediction: the sigma points of the prior x0, P0
            ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
            error = None
        else:
            w = self._transition(u)
            error = self._guard(lambda: ukf.predict(u=w), "prediction F(x, u)")
        if error is None:
            prediction = (ukf.x.copy(), ukf.P.copy())
            update_error = self._update(y, u)
            if update_error is None:
                return self._accepted(y, prediction)
            if self._trusted:  # a usable prediction of a trusted estimate: keep it
                ukf.x, ukf.P = prediction
                self._trusted = False
                return ukf.x.copy(), StepInfo(
                    status=f"failed: {update_error}; kept the prediction", success=False,
                    P=ukf.P.copy())
            error = update_error
        # re-anchor on the last trusted estimate with P + P0 and update with this y
        ukf.x, ukf.P = self._anchor(*self._anchor_state)
        ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
        saved = (ukf.x.copy(), ukf.P.copy())
        again = self._update(y, u)
        if again is not None:
            ukf.x, ukf.P = saved
        self._trusted = False
        status = (f"failed: {error}; re-anchored on the last trusted estimate with P + P0"
                  + ("" if again is None else " (no update: non-finite)"))
        return ukf.x.copy(), StepInfo(status=status, success=False, P=ukf.P.copy())

    def _guard(self, action, what: str) -> str | None:
        """Run a filterpy step; None, or what went wrong (an exception or non-finite
        values; scipy's Cholesky raises ``ValueError`` on NaN, ``LinAlgError`` when
        the covariance is not positive definite)."""
        ukf = self._ukf
        try:
            action()
        except (np.linalg.LinAlgError, ValueError) as exc:
            return f"{what}: {exc}"
        if not (np.isfinite(ukf.x).all() and np.isfinite(ukf.P).all()):
            return f"non-finite {what}"
        try:  # the next sigma points need a Cholesky factor
            np.linalg.cholesky(0.5 * (ukf.P + ukf.P.T))
        except np.linalg.LinAlgError:
            return f"{what}: covariance not positive definite"
        return None

    def _update(self, y, u) -> str | None:
        """Measurement update with the measured rows of ``y`` (none: the prediction is
        the estimate); None or what went wrong."""
        ukf = self._ukf
        rows = np.isfinite(y)
        if rows.all():
            error = self._guard(lambda: ukf.update(y, u=u), "update")
        elif rows.any():
            idx = np.flatnonzero(rows)
            error = self._guard(lambda: ukf.update(
                y[idx], R=self.R[np.ix_(idx, idx)], hx=lambda x, u: self._hx(x, u, idx), u=u),
                "update")
        else:
            error = None
        if error is None and self.clip:
            ukf.x = self.model.clip(ukf.x)
        return error

    def _accepted(self, y, prediction):
        """Estimate and information of a successful update (the prediction with
        ``P + P0`` where the gate rejects the measurement)."""
        ukf = self._ukf
        ukf.P = 0.5 * (ukf.P + ukf.P.T)
        rows = np.isfinite(y)
        e = np.zeros(self.model.ny)
        nis, status = float("nan"), "ok"
        if rows.any():
            e[rows] = np.ravel(ukf.y)
            nis = float(np.ravel(ukf.y) @ np.linalg.solve(ukf.S, np.ravel(ukf.y)))
            dof = int(rows.sum())
            gated = self.gate is not None and nis > chi2_limit(dof, self.gate)
            if gated or nis > chi2_limit(dof):
                status = self._consistency(nis, dof, gated)
            if gated:
                ukf.x, ukf.P = prediction[0], prediction[1] + self.P0
        self._trusted = status == "ok"
        return ukf.x.copy(), StepInfo(status=status, P=ukf.P.copy(), innovation=e, nis=nis)
