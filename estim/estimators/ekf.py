r"""Extended Kalman filter with AD Jacobians, fused into one compiled call per step."""

from __future__ import annotations

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim._validate import check_options
from estim.estimators.base import Estimator, StepInfo
from estim.model import Model


class EKF(Estimator):
    r"""Extended Kalman filter (discrete time, additive noise).

    Prediction from the previous estimate with the input :math:`u_{k-1}`,

    .. math::
        \bar x_k = F(\hat x_{k-1}, u_{k-1}), \qquad
        \bar P_k = A P_{k-1} A^\top + Q, \quad A = \partial F / \partial x,

    then the measurement update, with :math:`C = \partial h/\partial x` at
    :math:`\bar x_k`,

    .. math::
        e = y_k - h(\bar x_k), \quad S = C \bar P_k C^\top + R, \quad
        K = \bar P_k C^\top S^{-1}, \\
        \hat x_k = \bar x_k + K e, \qquad
        P_k = (I - KC) \bar P_k (I - KC)^\top + K R K^\top

    (Joseph form, kept symmetric). :math:`K` comes from a linear solve,
    never an explicit inverse. On the first step there is no prediction:
    ``x0, P0`` are the prior of :math:`x_0`. Missing outputs (NaN in ``y``)
    drop their rows of :math:`C`, :math:`e` and :math:`R` exactly.

    The prediction, Jacobians, update and optional clipping are one CasADi
    Function evaluated on preallocated buffers, so a step costs a few
    microseconds of Python.

    Parameters
    ----------
    model : Model
    Q, R, x0, P0 :
        Process and measurement covariances, initial guess and its
        covariance (see :class:`~estim.estimators.base.Estimator`).
    clip : bool
        Project each estimate onto ``[lower, upper]`` after the update (the
        covariance is left as it is), as in the KU Leuven course, exercise 4.
    lower, upper : optional
        Bounds for clipping (default: the model's).

    Attributes
    ----------
    x : (nx,) array
        Current estimate :math:`\hat x_{k|k}`.
    P : (nx, nx) array
        Its covariance.

    References
    ----------
    D. Simon, *Optimal State Estimation*, Wiley 2006, ch. 13;
    R. S. Bucy, P. D. Joseph, *Filtering for Stochastic Processes*, 1968.
    """

    name = "ekf"

    def __init__(self, model: Model, *, Q, R, x0, P0, clip: bool = False, lower=None,
                 upper=None, **options):
        check_options(options, (), "EKF")
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.clip = bool(clip)
        self.lower = model.lower if lower is None else np.broadcast_to(
            np.asarray(lower, float), (model.nx,)).copy()
        self.upper = model.upper if upper is None else np.broadcast_to(
            np.asarray(upper, float), (model.nx,)).copy()
        self._update = FastFunction(self._build(predict=False))
        self._predict_update = FastFunction(self._build(predict=True))
        self._reset()

    def _build(self, predict: bool) -> ca.Function:
        m = self.model
        nx, nu, ny = m.nx, m.nu, m.ny
        x = ca.SX.sym("x", nx)
        P = ca.SX.sym("P", nx, nx)
        u = ca.SX.sym("u", nu)
        y = ca.SX.sym("y", ny)
        mask = ca.SX.sym("mask", ny)
        p = ca.DM(m.p)
        if predict:
            xb = m.F(x, u, p)
            A = m.F_x(x, u, p)
            Pb = A @ P @ A.T + ca.DM(self.Q)
        else:
            xb, Pb = x, P
        D = ca.diag(mask)
        C = D @ m.H_x(xb, u, p)
        e = mask * (y - m.H(xb, u, p))
        R = ca.DM(self.R)
        Rm = D @ R @ D + ca.diag(1 - mask)
        S = C @ Pb @ C.T + Rm
        S = 0.5 * (S + S.T)
        K = ca.solve(S, C @ Pb).T
        xh = xb + K @ e
        if self.clip:
            xh = ca.fmin(ca.fmax(xh, ca.DM(self.lower)), ca.DM(self.upper))
        IKC = ca.DM.eye(nx) - K @ C
        Ph = IKC @ Pb @ IKC.T + K @ Rm @ K.T
        Ph = 0.5 * (Ph + Ph.T)
        nis = ca.dot(e, ca.solve(S, e))
        name = "ekf_predict_update" if predict else "ekf_update"
        return ca.Function(name, [x, P, u, y, mask], [xh, Ph, xb, Pb, e, nis],
                           ["x", "P", "u", "y", "mask"], ["x_hat", "P_hat", "x_prior", "P_prior",
                                                          "innovation", "nis"])

    def _reset(self) -> None:
        self.x = self.x0.copy()
        self.P = self.P0.copy()

    def _step(self, y, u, first):
        mask = np.isfinite(y)
        y0 = np.where(mask, y, 0.0)
        fun = self._update if first else self._predict_update
        xh, Ph, xb, Pb, e, nis = fun(self.x, self.P, u, y0, mask.astype(float))
        nx = self.model.nx
        if np.isfinite(xh).all() and np.isfinite(Ph).all():
            self.x = xh.copy()
            self.P = Ph.reshape(nx, nx, order="F").copy()
            return self.x.copy(), StepInfo(P=self.P, innovation=e.copy(), nis=float(nis[0]))
        # The update produced NaN/inf: keep the prediction where it is usable.
        if np.isfinite(xb).all() and np.isfinite(Pb).all():
            self.x = xb.copy()
            self.P = Pb.reshape(nx, nx, order="F").copy()
            status = "failed: non-finite update, kept the prediction"
        else:
            status = "failed: non-finite prediction, kept the previous estimate"
        return self.x.copy(), StepInfo(status=status, success=False, P=self.P)
