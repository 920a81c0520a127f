r"""Extended Kalman filter with AD Jacobians, fused into one compiled call per step."""

from __future__ import annotations

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_bool, as_choice, as_int
from estim.estimators.kalman.adaptive import (
    adapted,
    check_adapt,
    noise_update,
    predicted_statistics,
    sqrt_noise,
    start_statistics,
)
from estim.estimators.kalman.continuous import (
    DISCRETISATIONS,
    SUBSTEPS,
    continuous_noise,
    ekf_prediction,
    smoother_prediction,
)
from estim.estimators.kalman.fused import FusedKalman
from estim.estimators.kalman.heavy_tails import check_noise
from estim.estimators.kalman.iterated_updates import check_iterated, ekf_update
from estim.estimators.kalman.smoothing import SmoothResult, iterated, rts, smoothing_passes
from estim.estimators.kalman.square_root import check_form, covariances, ekf_step
from estim.estimators.manifold_steps import (
    check_manifold_options,
    mekf_step,
    tangent_transition_jacobian,
)
from estim.model import Model
from estim.solvers.kalman.kalman import ekf_checks
from estim.solvers.kalman.rts import transitions


class EKF(FusedKalman):
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
    Qc : (nq, nq) array, optional
        Instead of ``Q``, on a continuous model: the spectral density of a
        continuous-time process noise entering through the model's ``noise_input``
        :math:`L`. The prediction then integrates
        :math:`\dot m = f(m, u)`, :math:`\dot P = A P + P A^\top + L Q_c L^\top` over each
        interval by ``substeps`` Runge-Kutta steps (the continuous-discrete EKF;
        :mod:`estim.estimators.kalman.continuous`, docs/continuous_noise.md): the noise of
        a transition is that of its interval, with irregular stamps too; in the
        square-root form the factor's own moment equation.
    substeps : int
        Runge-Kutta steps per interval of the moment equations with ``Qc`` (default 4).
    discretisation : {"moments", "van-loan"}
        With ``Qc``: integrate the moment equations (default), or carry the covariance by
        the exact discretisation of the linearisation at the estimate,
        :math:`\bar P = \Phi P \Phi^\top + Q_d(\Delta t)` (Van Loan; exact on a linear
        model whatever ``substeps``), the mean by the model's ``F``.
    noise, dof :
        ``"gaussian"`` (default); ``"student-t"`` with ``dof`` (above 2; 5 to 10) and scale
        ``R``, the variational update that inflates a measurement's noise in the tails;
        ``"student-t-roth"``, Roth et al.'s closed-form t filter (covariance form; see
        :mod:`~estim.estimators.kalman.heavy_tails`). Vector states, ``iterations=1``.
    adapt, forgetting :
        ``adapt="R"``: learn a drifting measurement noise covariance online, the variational
        Bayes filter with the forgetting factor :math:`\rho \in (0, 1]` (about
        :math:`1/(1-\rho)` samples remembered; :mod:`~estim.estimators.kalman.adaptive`);
        the learnt ``R`` in ``info.extra["R"]`` and ``FilterResult.R``, starting at ``R``;
        ``"sage-husa"``: Sage and Husa's estimate, definiteness guarded; ``"QR"``: Q too.
    clip : bool
        Project each estimate onto ``[lower, upper]`` after the update (the
        covariance is left as it is), as in the KU Leuven course, exercise 4.
    lower, upper : optional
        Bounds for clipping (default: the model's).
    gate : float, optional
        Reject a measurement whose normalised innovation squared lies beyond this
        tail probability of its chi-square distribution (e.g. ``1e-9``): the
        prediction is kept, with ``P0`` added to its covariance so that a lasting
        disagreement (a diverged estimate rather than an outlier) opens the gate
        again, and the status says ``"rejected: ..."``. None (default): every
        measurement is used, as in the textbook filter.
    form : {"covariance", "sqrt"}
        ``"covariance"`` (default): the equations above. ``"sqrt"``: the square-root
        form, which carries the Cholesky factor :math:`S` of :math:`P = S S^\top`
        and forms every factor by orthogonal transformations (time update
        :math:`\bar S = \operatorname{tria}([A S, L_Q])`, measurement update by the
        array form of Morf and Kailath): the covariance stays symmetric and positive
        semi-definite where the covariance form loses definiteness (nearly exact
        measurements, badly scaled states). The same estimates to rounding otherwise
        (:mod:`estim.estimators.kalman.square_root`, docs/ekf.md).
    iterations : int
        Gauss-Newton iterations of the measurement update (default 1: the EKF above).
        With :math:`K > 1`, the iterated EKF (Bell & Cathey 1993): from
        :math:`x^{(0)} = \bar x_k`, with :math:`C_i = \partial h/\partial x` at
        :math:`x^{(i)}`, :math:`S_i = C_i \bar P_k C_i^\top + R`,
        :math:`K_i = \bar P_k C_i^\top S_i^{-1}`,

        .. math::
            x^{(i+1)} = \bar x_k + K_i \left(y_k - h(x^{(i)})
                        - C_i (\bar x_k - x^{(i)})\right),

        :math:`\hat x_k = x^{(K)}`, :math:`P_k` the Joseph form with the last
        :math:`K_i, C_i`; the innovation, NIS and gate are the prediction's
        (:math:`i = 0`). The iterations are unrolled in the one compiled step;
        ``info.iterations`` is :math:`K`, ``info.extra["converged"]`` whether the update
        converged (its next Gauss-Newton step below ``tol`` posterior standard
        deviations; ``FilterResult.converged`` over a record). :meth:`smooth` then
        iterates the smoother too. Covariance form, vector states.
    damping : {None, "line-search", "levenberg-marquardt"}
        Damp the iterations (with ``iterations`` > 1) so that each lowers the update's MAP
        cost :math:`V(x) = \|x - \bar x_k\|^2_{\bar P_k^{-1}} + \|y_k - h(x)\|^2_{R^{-1}}`:
        a backtracking line search on the Gauss-Newton step, or Levenberg-Marquardt steps
        (:mod:`estim.estimators.kalman.iterated_updates`), for outputs so nonlinear that the
        plain iteration overshoots or diverges. The covariance is then the Joseph form
        linearised at the final iterate. A damped update that has not converged after
        ``iterations`` makes the step ``"suspect: ..."`` (the estimate is the last
        iterate, which has the lowest cost found). None (default): the plain iteration.
    tol : float
        The iterated update has converged when its next step is at most ``tol`` posterior
        standard deviations (default 1e-4).
    jit : bool
        Compile the step and the whole-record scans (:meth:`filter`, the batched
        seeds of :func:`~estim.compare`) to machine code through the per-machine
        cache (a C compiler is needed; the first build takes a few tenths of a second
        per Function, later processes load the library in milliseconds): the same
        numbers, several times faster. Without a C compiler the filter stays
        interpreted, with an :class:`~estim.EstimationWarning`. Default False.

    Attributes
    ----------
    x : (nx,) array
        Current estimate :math:`\hat x_{k|k}`.
    P : (nx, nx) array
        Its covariance.

    References
    ----------
    D. Simon, *Optimal State Estimation*, Wiley 2006, ch. 13;
    R. S. Bucy, P. D. Joseph, *Filtering for Stochastic Processes*, 1968;
    B. M. Bell, F. W. Cathey, "The iterated Kalman filter update as a Gauss-Newton
    method", IEEE TAC 38(2), 1993.
    """

    name = "ekf"
    _checks_inf_itself = True
    _manifold_aware = True
    _adapt_start, _adapted, _sqrt_noise = start_statistics, adapted, sqrt_noise

    def __init__(self, model: Model, *, Q: ArrayLike | None = None, R: ArrayLike,
                 x0: ArrayLike, P0: ArrayLike, clip: bool = False,
                 lower: ArrayLike | None = None, upper: ArrayLike | None = None,
                 gate: float | None = None, form: str = "covariance", jit: bool = False,
                 iterations: int = 1, damping: str | None = None, tol: float = 1e-4,
                 Qc: ArrayLike | None = None, substeps: int = SUBSTEPS,
                 discretisation: str = "moments", noise: str = "gaussian",
                 dof: float | None = None, adapt: str | None = None,
                 forgetting: float = 0.98):
        Q, self.Qc, self.substeps = continuous_noise(model, Q, Qc, substeps)
        self.discretisation = as_choice(discretisation, DISCRETISATIONS, "discretisation")
        if self.discretisation != "moments" and self.Qc is None:
            raise ValueError("discretisation= carries a continuous noise (Qc=) over an "
                             "interval: give Qc, or leave discretisation at 'moments'")
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.form, self._sqrt = check_form(form)
        self.iterations = as_int(iterations, "iterations", minimum=1)
        self.damping, self.tol = check_iterated("ekf", self.iterations, damping, tol)
        self._update_iterations = self.iterations if self.iterations > 1 else 0
        if self.iterations > 1 and (self._sqrt or not model.manifold.trivial):
            raise ValueError(f"iterations={self.iterations}: the iterated EKF is built in the "
                             f"covariance form on vector states; use form='covariance' "
                             f"(and a model without quaternions or angles), or iterations=1")
        self.noise, self.dof = check_noise(noise, dof, self)
        self.adapt, self.forgetting, self._n_adapt = check_adapt(adapt, forgetting, self)
        self.clip = as_bool(clip, "clip")
        self.gate = self._gate(gate)
        self.lower, self.upper = self._bounds(lower, upper)
        check_manifold_options(model, self.form, self.clip, self.lower, self.upper)
        self.jit = as_bool(jit, "jit")
        self._compile()

    def _build(self, predict: bool) -> ca.Function:
        if self._sqrt:
            return ekf_step(self, predict)
        if not self.model.manifold.trivial:  # quaternions, angles: the multiplicative form
            return mekf_step(self, predict)
        m = self.model
        nx = m.nx
        s, x, P, u, y, tun, Q, R, p, mask, y_inf = self._symbols()
        a_prior = a_new = predicted_statistics(self, s[self._nP:]) if predict and self.adapt \
            else s[self._nP:]  # an adaptive filter's statistics (none without adapt)
        if predict and self.Qc is not None:  # the moments over the interval
            xb, Pb = ekf_prediction(self, x, P, u, p, Q)
        elif predict:
            xb = m.F(x, u, p)
            A = m.F_x(x, u, p)
            Pb = A @ P @ A.T + Q
        else:
            xb, Pb = x, P
        D = ca.diag(mask)
        uy = m.measurement_input(u)  # the input at this measurement
        Rm = D @ R @ D + ca.diag(1 - mask)
        e = ca.if_else(mask, y - m.H(xb, uy, p), 0)  # the innovation (and the NIS's)
        converged = None
        if self.iterations > 1:  # Gauss-Newton on the update, plain or damped
            xh, Ph, S, converged = ekf_update(m, xb, Pb, y, mask, Rm, uy, p, self.iterations,
                                              self.damping, self.tol)
        elif self.dof is not None or self.adapt:  # Student-t or adaptive noise
            C = D @ m.H_x(xb, uy, p)
            xh, Ph, S, a_new, _ = noise_update(self, xb, Pb, e, Pb @ C.T, C @ Pb @ C.T, Q, R,
                                               mask, a_prior)
        else:
            C = D @ m.H_x(xb, uy, p)
            S = C @ Pb @ C.T + Rm
            S = 0.5 * (S + S.T)
            K = ca.solve(S, C @ Pb).T
            xh = xb + K @ e
            IKC = ca.DM.eye(nx) - K @ C
            Ph = IKC @ Pb @ IKC.T + K @ Rm @ K.T
            Ph = 0.5 * (Ph + Ph.T)
        if self.clip:
            xh = ca.fmin(ca.fmax(xh, ca.DM(self.lower)), ca.DM(self.upper))
        nis = ca.dot(e, ca.solve(S, e))
        s_new = ca.vertcat(xh, ca.vec(Ph), a_new)
        s_prior = ca.vertcat(xb, ca.vec(Pb), a_prior)
        ok, ok_mean, ok_prior = ekf_checks(s_new, nis, Ph, xb, Pb)
        name = "ekf_predict_update" if predict else "ekf_update"
        return self._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                                    ok_mean, mask, s_prior, converged)

    def smooth(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None, iterations: int | None = None) -> SmoothResult:
        r"""Extended Rauch-Tung-Striebel smoother over a whole record.

        The filter runs forward over the record with :meth:`filter` (one compiled
        call, equal to :meth:`step` at every sample after a :meth:`reset`; inputs,
        missing outputs, gating and clipping as in :func:`~estim.replay`), then the
        backward pass from
        :math:`x^s_{T-1} = \hat x_{T-1}`, :math:`P^s_{T-1} = P_{T-1}`, with
        :math:`A_k = \partial F/\partial x` at the filtered :math:`\hat x_k`:

        .. math::
            \bar x_{k+1} = F(\hat x_k, u_k), \quad
            \bar P_{k+1} = A_k P_k A_k^\top + Q, \quad
            G_k = P_k A_k^\top \bar P_{k+1}^{-1}, \\
            x^s_k = \hat x_k + G_k (x^s_{k+1} - \bar x_{k+1}), \quad
            P^s_k = P_k + G_k (P^s_{k+1} - \bar P_{k+1}) G_k^\top .

        With ``clip``, each smoothed mean is projected on the bounds too. On a
        linear-Gaussian model this is the Kalman (RTS) smoother.

        Parameters
        ----------
        Y : (T, ny) array
            Measurements, NaN where missing.
        U : (T-1, nu) or (T, nu) array, optional
            ``U[k]`` acts from sample k to k+1 (with ``hold="foh"``: ``(T, nu)``,
            the input at each sample), as in ``FullInformation.fit``; required
            for a model with inputs (``U=0``: zero inputs, on purpose).
        t : (T,) array, optional
            Sample times, for a model built with ``variable_dt=True``.
        iterations : int, optional
            Passes of the iterated extended smoother (default: the filter's
            ``iterations``; 1: the extended smoother above). Each further pass is the
            Kalman filter and RTS smoother of the model linearised about the previous
            smoothed trajectory, a Gauss-Newton step on the record's MAP problem
            (:func:`~estim.estimators.kalman.smoothing.iterated`): converged, it is
            :meth:`FullInformation.fit <estim.FullInformation.fit>`'s optimum. It stops
            early when converged; ``result.iterations`` and ``result.converged`` say how
            it ended. Not with ``clip`` or ``gate`` (the passes are unconstrained and use
            every measurement), nor on quaternion or angle states.

        Returns
        -------
        SmoothResult
            ``x (T, nx)``, ``P (T, nx, nx)``, the filtered ``x_filtered``,
            ``P_filtered``, the predictions, gains and statuses. The filter is
            left at the end of the record.

        References
        ----------
        H. E. Rauch, F. Tung, C. T. Striebel (1965), AIAA J. 3(8);
        S. Särkkä, *Bayesian Filtering and Smoothing*, 2013, sec. 9.1.
        """
        predict = _extended_predictions(self)
        passes = smoothing_passes(self, iterations)
        clip = (lambda x: np.minimum(np.maximum(x, self.lower), self.upper)) if self.clip \
            else None
        if self.Qc is not None:  # the moment equations over each interval
            predict = smoother_prediction(self)
        first = rts(self, Y, U, t, predict, clip)
        return first if passes == 1 else iterated(self, first, Y, U, t, passes)

    @property
    def x(self) -> np.ndarray:
        """Current estimate (a view of the filter state)."""
        return self._s[: self.model.nx]

    @property
    def P(self) -> np.ndarray:
        """Current covariance (a view of the filter state; a new array, ``S S^T``, in the
        square-root form)."""
        nx = self.model.nx
        P = self._s[nx:self._nP].reshape(nx, nx, order="F")
        return covariances(P) if self._sqrt else P

    def _failure_texts(self, flags) -> tuple[str, str]:
        return ("failed: non-finite update (h or dh/dx at the prediction); kept the prediction",
                "non-finite " + ("update" if flags[2] else "Jacobian dF/dx" if flags[5]
                                 else "prediction F(x, u)"))


def _extended_predictions(ekf: EKF):
    """The extended smoother's predictions of every transition at once: ``(X, P, W) ->
    (x_bar, P_bar, D)``, :math:`D = P_k A_k^\top` (on quaternions and angles, the
    Jacobian along the retraction)."""
    m, Q = ekf.model, ekf.Q
    jacobian = None if m.manifold.euclidean_states else tangent_transition_jacobian(m)

    def predict(X, P, W):
        A = transitions(m, X, W, jacobian=True) if jacobian is None else \
            np.asarray(jacobian.map(len(X))(X.T, W.T, ca.DM(m.p))).reshape(
                m.ndx, len(X), m.ndx).transpose(1, 0, 2)
        D = P @ A.transpose(0, 2, 1)  # P_k A_k^T
        Pb = A @ D + Q
        return transitions(m, X, W), 0.5 * (Pb + Pb.transpose(0, 2, 1)), D

    return predict
