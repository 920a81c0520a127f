r"""Unscented Kalman filter on filterpy's ``UnscentedKalmanFilter``."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from estim._validate import check_options
from estim.estimators.base import Estimator, StepInfo
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

    References
    ----------
    R. van der Merwe, *Sigma-Point Kalman Filters for Probabilistic Inference
    in Dynamic State-Space Models*, PhD thesis, OGI 2004;
    E. A. Wan, R. van der Merwe, "The unscented Kalman filter for nonlinear
    estimation", IEEE AS-SPCC 2000.
    """

    name = "ukf"

    def __init__(self, model: Model, *, Q, R, x0, P0, alpha: float = 0.1, beta: float = 2.0,
                 kappa: float = 0.0, clip: bool = False, **options):
        check_options(options, (), "UKF")
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        if not alpha > 0:
            raise ValueError(f"alpha must be positive, got {alpha!r}")
        self.alpha, self.beta, self.kappa, self.clip = float(alpha), float(beta), float(kappa), clip
        self._reset()

    def _fx(self, x, dt, u):
        return self.model._fast_F(x, u, self.model.p)[0].copy()

    def _hx(self, x, u, rows=None):
        y = self.model._fast_H(x, u, self.model.p)[0]
        return y.copy() if rows is None else y[rows].copy()

    def _reset(self) -> None:
        m = self.model
        points = MerweScaledSigmaPoints(m.nx, alpha=self.alpha, beta=self.beta, kappa=self.kappa)
        ukf = UnscentedKalmanFilter(dim_x=m.nx, dim_z=m.ny, dt=m.dt, hx=self._hx, fx=self._fx,
                                    points=points)
        ukf.x = self.x0.copy()
        ukf.P = self.P0.copy()
        ukf.Q = self.Q.copy()
        ukf.R = self.R.copy()
        self._ukf = ukf

    @property
    def x(self) -> np.ndarray:
        return self._ukf.x.copy()

    @property
    def P(self) -> np.ndarray:
        return self._ukf.P.copy()

    def _step(self, y, u, first):
        ukf = self._ukf
        saved = (ukf.x.copy(), ukf.P.copy())
        try:
            if first:  # no prediction: the sigma points of the prior x0, P0
                ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
            else:
                ukf.predict(u=u)
            rows = np.isfinite(y)
            if rows.all():
                ukf.update(y, u=u)
            elif rows.any():
                idx = np.flatnonzero(rows)
                ukf.update(y[idx], R=self.R[np.ix_(idx, idx)],
                           hx=lambda x, u: self._hx(x, u, idx), u=u)
            # with nothing measured the prediction is the estimate
            if self.clip:
                ukf.x = self.model.clip(ukf.x)
            ok = np.isfinite(ukf.x).all() and np.isfinite(ukf.P).all()
            status = "ok" if ok else "failed: non-finite update"
        except np.linalg.LinAlgError as exc:  # sigma points need a Cholesky factor of P
            ok, status = False, f"failed: {exc}"
        if not ok:
            ukf.x, ukf.P = saved
            return ukf.x.copy(), StepInfo(status=status, success=False, P=ukf.P.copy())
        ukf.P = 0.5 * (ukf.P + ukf.P.T)
        e = np.zeros(self.model.ny)
        nis = float("nan")
        if rows.any():
            e[rows] = np.ravel(ukf.y)
            nis = float(np.ravel(ukf.y) @ np.linalg.solve(ukf.S, np.ravel(ukf.y)))
        return ukf.x.copy(), StepInfo(P=ukf.P.copy(), innovation=e, nis=nis)
