r"""Unscented Kalman filter on filterpy's ``UnscentedKalmanFilter``."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_bool, as_float
from estim.estimators.base import Estimator, StepInfo, chi2_limit
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
