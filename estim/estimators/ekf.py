r"""Extended Kalman filter with AD Jacobians, fused into one compiled call per step."""

from __future__ import annotations

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._scan import blocked_scan
from estim._validate import as_bool, as_inputs, as_intervals, as_record
from estim.estimators.base import SUSPECT_TAIL, StepInfo, chi2_limit
from estim.estimators.filtering import FilterResult
from estim.estimators.fused import FusedKalman, matrix
from estim.estimators.nlp import is_diagonal
from estim.estimators.smoothing import SmoothResult, rts, transitions
from estim.model import Model

#: :meth:`EKF.filter` keeps its compiled Function for this many record lengths.
_RECORD_LENGTHS_KEPT = 8


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
    _checks_inf_itself = True

    def __init__(self, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                 P0: ArrayLike, clip: bool = False, lower: ArrayLike | None = None,
                 upper: ArrayLike | None = None, gate: float | None = None):
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.clip = as_bool(clip, "clip")
        self.gate = self._gate(gate)
        self.lower, self.upper = self._bounds(lower, upper)
        nx = model.nx
        # the filter state [x; vec(P)] lives where both compiled functions read it
        self._s = np.zeros(nx + nx * nx)
        self._u = np.zeros(model.nw)  # the transition's input (both ends if sampled)
        self._y = np.zeros(model.ny)
        self._tun = np.zeros(nx * nx + model.ny ** 2)  # Q and R, read by both functions
        self._diagonal = {"Q": is_diagonal(self.Q), "R": is_diagonal(self.R)}
        bound = [self._s, self._u, self._y, self._tun]
        self._update = FastFunction(self._build(predict=False), bound)
        self._predict_update = FastFunction(self._build(predict=True), bound)
        self._tuning_changed()
        self._reset()

    def _build(self, predict: bool) -> ca.Function:
        m = self.model
        nx, ny = m.nx, m.ny
        s = ca.SX.sym("s", nx + nx * nx)
        x, P = s[:nx], ca.reshape(s[nx:], nx, nx)
        u = ca.SX.sym("u", m.nw)
        y = ca.SX.sym("y", ny)
        tun = ca.SX.sym("tuning", nx * nx + ny * ny)  # the tuning is data (set_tuning)
        Q, R = (matrix(tun[:nx * nx], nx, self._diagonal["Q"]),
                matrix(tun[nx * nx:], ny, self._diagonal["R"]))
        p = ca.DM(m.p)
        mask = ca.fabs(y) < ca.inf  # 0 for NaN (missing) and for +-inf (rejected)
        y_inf = ca.sum1(ca.fabs(y) == ca.inf) if ny else ca.SX(0)
        if predict:
            xb = m.F(x, u, p)
            A = m.F_x(x, u, p)
            Pb = A @ P @ A.T + Q
        else:
            xb, Pb = x, P
        D = ca.diag(mask)
        uy = m.measurement_input(u)  # the input at this measurement
        C = D @ m.H_x(xb, uy, p)
        e = ca.if_else(mask, y - m.H(xb, uy, p), 0)
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
        s_new = ca.vertcat(xh, ca.vec(Ph))
        s_prior = ca.vertcat(xb, ca.vec(Pb))
        # finite, and a covariance with a positive diagonal (lost in overflowing updates)
        ok = ca.logic_and(ca.fabs(ca.sum1(s_new) + nis) < ca.inf, ca.mmin(ca.diag(Ph)) > 0)
        ok_mean = ca.fabs(ca.sum1(xb)) < ca.inf
        ok_prior = ca.logic_and(ok_mean, ca.fabs(ca.sum1(ca.vec(Pb))) < ca.inf)
        measured = ca.sum1(mask) if ny else ca.SX(0)
        # beyond the chi-square tail for the number of outputs measured (see SUSPECT_TAIL)
        onehot = ca.vertcat(*[measured == k for k in range(1, ny + 1)])

        def beyond(tail):  # NIS beyond the tail of chi2(outputs measured)
            if not ny or tail is None:
                return ca.SX(0)
            limits = ca.DM([chi2_limit(k, tail) for k in range(1, ny + 1)])
            return ca.logic_and(measured > 0, nis > ca.dot(limits, onehot))

        suspect, gated = beyond(SUSPECT_TAIL), beyond(self.gate)
        name = "ekf_predict_update" if predict else "ekf_update"
        return ca.Function(name, [s, u, y, tun], [s_new, e, ca.vertcat(nis, ok, ok_prior, y_inf,
                                                                  measured, ok_mean, suspect,
                                                                  gated),
                                             s_prior],
                           ["s", "u", "y", "tuning"], ["s_new", "innovation", "flags", "s_prior"])

    def smooth(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None) -> SmoothResult:
        r"""Extended Rauch-Tung-Striebel smoother over a whole record.

        The filter runs forward over the record with :meth:`step` (after a
        :meth:`reset`; inputs, missing outputs, gating and clipping as in
        :func:`~estim.replay`), then the backward pass from
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
        H. E. Rauch, F. Tung, C. T. Striebel (1965), AIAA J. 3(8);
        S. Särkkä, *Bayesian Filtering and Smoothing*, 2013, sec. 9.1.
        """
        m, Q = self.model, self.Q

        def predict(X, P, W):
            A = transitions(m, X, W, jacobian=True)
            D = P @ A.transpose(0, 2, 1)  # P_k A_k^T
            Pb = A @ D + Q
            return transitions(m, X, W), 0.5 * (Pb + Pb.transpose(0, 2, 1)), D

        clip = (lambda x: np.minimum(np.maximum(x, self.lower), self.upper)) if self.clip \
            else None
        return rts(self, Y, U, t, predict, clip)

    def filter(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None) -> FilterResult:
        r"""Filter a whole record in one compiled call.

        The fused step (prediction, Jacobians, update, clipping, the NIS and its
        flags) is scanned over the record by one CasADi Function (``mapaccum`` in
        blocks of about :math:`\sqrt T` steps, built once per record length and
        kept), which gives what :func:`~estim.replay` or :meth:`step` at every sample
        gives, to rounding: the same inputs (held or sampled), missing outputs (NaN)
        and ``t``. A suspect step keeps its update; a step beyond ``gate`` keeps the
        prediction with ``P0`` added, inside the scan too. A non-finite update (the
        model or its Jacobian not finite where it is evaluated), whose recovery
        depends on the filter's history, ends the compiled part: the filter
        restarts from the state before that step as the step loop left it (its
        last trusted estimate included) and finishes the record step by step.

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
        FilterResult
            ``x (T, nx)``, ``P (T, nx, nx)``, ``innovation (T, ny)``, ``nis (T,)``,
            ``status`` and ``success``. The filter is left at the end of the record
            (after a :meth:`reset` at its start), as by the step loop.
        """
        m = self.model
        nx, ny = m.nx, m.ny
        Y = as_record(Y, ny, "Y", names=m.output_names, what="outputs")
        T = Y.shape[0]
        U = as_inputs(U, T, m)
        dts = as_intervals(t, T, m)
        # step's input u at every sample (the input since the previous sample, or at this
        # one for sampled inputs) and the transitions' inputs w as step makes them
        before = np.vstack([np.zeros((1, m.nu)), U[:-1]])
        steps_u = U if m.sampled else before
        W = np.hstack([before, U]) if m.sampled else before
        if m.variable_dt:
            W = np.hstack([W, np.concatenate([[m.dt], dts])[:, None]])
        self.reset()
        S, E, F = (a.reshape(T, -1).T for a in self._whole_record(T)(
            self._s, Y.T, W.T, self._tun, self.P0.ravel(order="F")))
        failed = np.flatnonzero(F[1] == 0)
        n = int(failed[0]) if failed.size else T  # the samples filtered in the graph
        X, P = np.empty((T, nx)), np.full((T, nx, nx), np.nan)
        X[:n] = S[:nx, :n].T
        P[:n] = S[nx:, :n].T.reshape(n, nx, nx).transpose(0, 2, 1)  # column-major
        innovation, nis = np.full((T, ny), np.nan), np.full(T, np.nan)
        innovation[:n] = E[:, :n].T
        measured = F[4, :n] > 0
        nis[:n][measured] = F[0, :n][measured]
        suspect = (F[6, :n] + F[7, :n]) > 0
        status = np.full(n, "ok", dtype=object)
        for k in np.flatnonzero(suspect):
            status[k] = self._consistency(float(F[0, k]), int(F[4, k]), bool(F[7, k]))
        status = status.tolist()
        if n:  # the filter as the step loop leaves it after sample n - 1
            trusted = np.flatnonzero(~suspect)
            self._s[:] = S[:, n - 1]
            if trusted.size:
                self._s_trusted[:] = S[:, trusted[-1]]
            self._trusted = not suspect[-1]
            self._first, self._k = False, n
            if m.sampled:
                self._u_last = U[n - 1].copy()
            self._info = StepInfo._fast(P=P[n - 1].copy(), innovation=innovation[n - 1].copy(),
                                        nis=float(nis[n - 1]), status=status[-1])
        success = True
        for k in range(n, T):  # from a non-finite update on: the step loop
            dt = None if dts is None or k == 0 else float(dts[k - 1])
            X[k] = self.step(Y[k].copy(), steps_u[k].copy(), dt=dt)
            info = self.info
            if info.P is not None:
                P[k] = info.P
            if info.innovation is not None:
                innovation[k] = info.innovation
            nis[k] = info.nis
            status.append(info.status)
            success = success and info.success
        return FilterResult(x=X, P=P, innovation=innovation, nis=nis, status=tuple(status),
                            success=success)

    def _whole_record(self, T: int) -> FastFunction:
        """``(s0, Y, W, tuning, P0) -> (S, E, flags)``: the fused step over ``T`` samples
        (the first an update), the filter state, innovation and flags of every sample
        side by side; a gated step keeps the prediction with ``P0`` added. Kept for the
        last :data:`_RECORD_LENGTHS_KEPT` record lengths."""
        cache = self.__dict__.setdefault("_whole_records", {})
        if T in cache:
            return cache[T]
        m = self.model
        nx, ny, nw = m.nx, m.ny, m.nw

        def scanned(predict: bool) -> ca.Function:
            s, w = ca.SX.sym("s", nx + nx * nx), ca.SX.sym("w", nw)
            y, tun = ca.SX.sym("y", ny), ca.SX.sym("tuning", nx * nx + ny * ny)
            P0 = ca.SX.sym("P0", nx * nx)
            s_new, e, flags, s_prior = self._build(predict)(s, w, y, tun)
            s_next = ca.if_else(flags[7], s_prior + ca.vertcat(ca.SX(nx, 1), P0), s_new)
            return ca.Function("ekf_record_step" if predict else "ekf_record_first",
                               [s, w, y, tun, P0], [s_next, s_next, e, flags],
                               ["s", "w", "y", "tuning", "P0"],
                               ["s_next", "s_out", "innovation", "flags"])

        s0 = ca.MX.sym("s0", nx + nx * nx)
        Y, W = ca.MX.sym("Y", ny, T), ca.MX.sym("W", nw, T)
        tun, P0 = ca.MX.sym("tuning", nx * nx + ny * ny), ca.MX.sym("P0", nx * nx)
        s1, _, e0, f0 = scanned(False)(s0, W[:, 0], Y[:, 0], tun, P0)
        S, E, F = s1, e0, f0
        if T > 1:
            scan = blocked_scan(scanned(True), T - 1, (1, 2))
            _, S1, E1, F1 = scan(s1, W[:, 1:], Y[:, 1:], tun, P0)
            S, E, F = ca.horzcat(s1, S1), ca.horzcat(e0, E1), ca.horzcat(f0, F1)
        fun = FastFunction(ca.Function(f"ekf_record_{T}", [s0, Y, W, tun, P0], [S, E, F],
                                       ["s0", "Y", "W", "tuning", "P0"],
                                       ["S", "innovation", "flags"]))
        if len(cache) >= _RECORD_LENGTHS_KEPT:  # the oldest length goes
            del cache[next(iter(cache))]
        cache[T] = fun
        return fun

    @property
    def x(self) -> np.ndarray:
        """Current estimate (a view of the filter state)."""
        return self._s[: self.model.nx]

    @property
    def P(self) -> np.ndarray:
        """Current covariance (a view of the filter state)."""
        nx = self.model.nx
        return self._s[nx:].reshape(nx, nx, order="F")

    def _failure_texts(self, flags) -> tuple[str, str]:
        return ("failed: non-finite update (h or dh/dx at the prediction); kept the prediction",
                "non-finite " + ("update" if flags[2] else "Jacobian dF/dx" if flags[5]
                                 else "prediction F(x, u)"))
