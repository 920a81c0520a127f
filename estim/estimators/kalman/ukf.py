r"""Unscented Kalman filter, fused into one compiled call per step."""

from __future__ import annotations

import warnings
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._manifold import NP
from estim._validate import as_bool, as_float, as_int
from estim.estimators.base import EstimationWarning
from estim.estimators.kalman.adaptive import (
    adapted,
    check_adapt,
    noise_update,
    predicted_statistics,
    sqrt_noise,
    start_statistics,
)
from estim.estimators.kalman.continuous import (
    SUBSTEPS,
    continuous_noise,
    sigma_moments,
    ukf_prediction,
    unscented_smoother_prediction,
)
from estim.estimators.kalman.fused import FusedKalman
from estim.estimators.kalman.heavy_tails import check_noise
from estim.estimators.kalman.iterated_updates import check_iterated, posterior_linearised_update
from estim.estimators.kalman.smoothing import (
    SmoothResult,
    posterior_linearised,
    rts,
    smoothing_passes,
)
from estim.estimators.kalman.square_root import check_form, covariance, ukf_step
from estim.estimators.manifold_steps import check_manifold_options, usque_step
from estim.model import Model
from estim.solvers.kalman.kalman import finite
from estim.solvers.kalman.rts import transitions
from estim.solvers.kalman.triangular import checked_cholesky as _cholesky
from estim.solvers.quadrature import cubature5, gauss_hermite

#: The sigma-point sets of :class:`UKF` (see :func:`sigma_weights`).
POINTS = ("merwe", "julier", "cubature", "cubature5", "gauss-hermite")

#: Gauss-Hermite rules with more points than this are warned about (p^n grows fast)
MANY_POINTS = 10_000


def _symbolic_sigma_points(ukf: Any, x: Any, P: Any) -> tuple[list, ca.SX]:
    """A UKF's sigma points of ``(x, P)`` (columns) and whether ``P`` has a Cholesky
    factor (positive definite)."""
    L, definite = _cholesky(ukf._scale * P)
    if ukf._unit is not None:  # a rule given by its unit points: x + L xi
        return [x + L @ ca.DM(xi) for xi in ukf._unit.T], definite
    n = x.numel()
    offsets = [L[:, k] for k in range(n)]  # the rows of the upper factor L^T
    centre = [] if ukf.points == "cubature" else [x]
    return centre + [x + d for d in offsets] + [x - d for d in offsets], definite


class UKF(FusedKalman):
    r"""Unscented Kalman filter (discrete time, additive noise).

    Same constructor, ``step`` and ``reset`` as :class:`~estim.EKF`; the
    prediction and update propagate sigma points through the model's :math:`F`
    and :math:`h` instead of linearising. The sigma points of a mean :math:`x`
    and covariance :math:`P` are :math:`x` (except for the cubature set) and
    :math:`x \pm U_i`, with :math:`U_i` the rows of the upper Cholesky factor of
    :math:`cP` (:func:`sigma_weights` gives :math:`c` and the weights
    :math:`W^m, W^c`). The prediction, from the sigma points
    :math:`\mathcal X^{(i)}` of :math:`(\hat x_{k-1}, P_{k-1})`,

    .. math::
        \bar x_k = \sum_i W^m_i F(\mathcal X^{(i)}, u_{k-1}), \qquad
        \bar P_k = \sum_i W^c_i \,\delta F_i\, \delta F_i^\top + Q,

    then the update with the sigma points :math:`\mathcal X^{(i)}` of
    :math:`(\bar x_k, \bar P_k)` and :math:`\mathcal Z^{(i)} = h(\mathcal X^{(i)})`,

    .. math::
        \bar y = \sum_i W^m_i \mathcal Z^{(i)}, \quad
        S = \sum_i W^c_i\, \delta\mathcal Z_i\, \delta\mathcal Z_i^\top + R, \quad
        P_{xy} = \sum_i W^c_i (\mathcal X^{(i)} - \bar x_k)\, \delta\mathcal Z_i^\top, \\
        K = P_{xy} S^{-1}, \quad \hat x_k = \bar x_k + K (y_k - \bar y), \quad
        P_k = \bar P_k - K S K^\top

    (kept symmetric; :math:`K` from a linear solve). This is filterpy's
    :class:`~filterpy.kalman.UnscentedKalmanFilter`, step for step. On the
    first step there is no prediction. Missing outputs (NaN in ``y``) drop
    their rows of :math:`\mathcal Z`, :math:`y` and :math:`R` exactly.

    The sigma points, the propagation through :math:`F` and :math:`h`, the
    update, the checks and optional clipping are one CasADi Function evaluated
    on preallocated buffers, as in the :class:`~estim.EKF`. A step fails when
    a value is not finite or a covariance has no Cholesky factor (not
    positive definite); it then keeps the prediction of a trusted estimate or
    re-anchors, as the EKF does.

    Parameters
    ----------
    model : Model
    Q, R, x0, P0 :
        As for every estimator.
    Qc, substeps :
        Instead of ``Q``, on a continuous model: a continuous-time noise's spectral density
        (as for :class:`~estim.EKF`); the prediction integrates the sigma-point moment
        equations (Särkkä 2007) by ``substeps`` Runge-Kutta steps.
    noise, dof :
        ``"student-t"`` with ``dof`` (above 2): as for :class:`~estim.EKF`, linearised by
        the sigma points' statistical linear regression.
    adapt, forgetting :
        ``adapt="R"``, a measurement noise learnt online, as for :class:`~estim.EKF`.
    points : {"merwe", "julier", "cubature", "cubature5", "gauss-hermite"}
        Sigma-point set: Van der Merwe's scaled points (default), Julier's, the
        :math:`2n_x` equally weighted points of the cubature Kalman filter, the
        fifth-degree cubature rule (:func:`~estim.solvers.quadrature.cubature5`,
        :math:`2n_x^2 + 1` points), or the Gauss-Hermite rule of ``order`` :math:`p`
        (:func:`~estim.solvers.quadrature.gauss_hermite`: :math:`p^{n_x}` points
        :math:`x \oplus L\xi_i`, :math:`L L^\top = P`; the Gauss-Hermite Kalman filter),
        in both forms and on quaternion and angle states.
    order : int
        The Gauss-Hermite rule's points per dimension (default 3); warned above 10 000.
    iterations : int
        Iterations of the measurement update (default 1: the UKF). With :math:`K > 1`
        the iterated posterior linearisation filter (IPLF): the update is redone
        :math:`K - 1` times with :math:`h` linearised by statistical linear regression on
        the sigma points of the last posterior
        (:func:`~estim.estimators.kalman.iterated_updates.posterior_linearised_update`),
        unrolled in the one compiled step; ``info.iterations`` is :math:`K`,
        ``info.extra["converged"]`` whether the next iteration would move the mean by at
        most ``tol`` posterior standard deviations; :meth:`smooth` iterates too (the
        IPLS). Covariance form, vector states.
    damping : {None, "relaxed"}
        With ``iterations`` > 1: move the mean and covariance half-way to each new
        posterior (:mod:`~estim.estimators.kalman.iterated_updates`), the same fixed point
        without the plain iteration's oscillation on strongly nonlinear outputs (give it
        some 30 iterations); unconverged after ``iterations``: a ``"suspect"`` step.
    tol : float
        Convergence tolerance in posterior standard deviations (default 1e-4).
    alpha, beta, kappa : float
        Spread (:math:`\alpha`, merwe), prior knowledge (:math:`\beta = 2` for Gaussian,
        merwe), secondary scaling (:math:`\kappa`, merwe and julier; :math:`n_x + \kappa
        > 0`); the default, chosen on 13 cases: docs/gaussian_filters.md.
    clip : bool
        Project the estimate onto the model bounds after each update.
    gate : float, optional
        Reject a measurement whose normalised innovation squared lies beyond this
        tail probability of its chi-square distribution, as :class:`~estim.EKF` does.
    form : {"covariance", "sqrt"}
        ``"covariance"`` (default): the equations above. ``"sqrt"``: the square-root
        UKF of van der Merwe and Wan, which carries the Cholesky factor of :math:`P`,
        draws the sigma points from it and forms every factor by QR and rank-one
        downdates: the same estimates to rounding, and a covariance that stays
        positive semi-definite (:mod:`estim.estimators.kalman.square_root`, docs/ekf.md).
    jit : bool
        Compile the step and the whole-record scans (:meth:`filter`, the batched
        seeds of :func:`~estim.compare`) to machine code through the per-machine
        cache (a C compiler is needed; the first build takes a few tenths of a second
        per Function, later processes load the library in milliseconds): the same
        numbers, several times faster. Without a C compiler the filter stays
        interpreted, with an :class:`~estim.EstimationWarning`. Default False.

    References
    ----------
    R. van der Merwe, *Sigma-Point Kalman Filters for Probabilistic Inference
    in Dynamic State-Space Models*, PhD thesis, OGI 2004;
    E. A. Wan, R. van der Merwe, "The unscented Kalman filter for nonlinear
    estimation", IEEE AS-SPCC 2000;
    S. J. Julier, J. K. Uhlmann, "Unscented filtering and nonlinear estimation",
    Proc. IEEE 92(3), 2004;
    I. Arasaratnam, S. Haykin, "Cubature Kalman filters", IEEE TAC 54(6), 2009.
    """

    name = "ukf"
    _manifold_aware = True
    _checks_inf_itself = True
    _adapt_start, _adapted, _sqrt_noise = start_statistics, adapted, sqrt_noise

    def __init__(self, model: Model, *, Q: ArrayLike | None = None, R: ArrayLike,
                 x0: ArrayLike, P0: ArrayLike, points: str = "merwe", alpha: float = 1.0,
                 beta: float = 2.0, kappa: float = 0.0, clip: bool = False,
                 gate: float | None = None, form: str = "covariance", jit: bool = False,
                 order: int = 3, iterations: int = 1, damping: str | None = None,
                 tol: float = 1e-4, Qc: ArrayLike | None = None, substeps: int = SUBSTEPS,
                 noise: str = "gaussian", dof: float | None = None,
                 adapt: str | None = None, forgetting: float = 0.98):
        Q, self.Qc, self.substeps = continuous_noise(model, Q, Qc, substeps)
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.form, self._sqrt = check_form(form)
        self.gate = self._gate(gate)
        if not isinstance(points, str) or points not in POINTS:
            raise ValueError(f"points must be one of {', '.join(map(repr, POINTS))}, "
                             f"got {points!r}")
        self.points = points
        self.alpha = as_float(alpha, "alpha", positive=True, maximum=1e3)
        self.beta, self.kappa = as_float(beta, "beta"), as_float(kappa, "kappa")
        self.clip = as_bool(clip, "clip")
        self.lower, self.upper = model.lower, model.upper
        check_manifold_options(model, self.form, self.clip, self.lower, self.upper)
        self.order = as_int(order, "order", minimum=1)
        self.iterations = as_int(iterations, "iterations", minimum=1)
        self.damping, self.tol = check_iterated("ukf", self.iterations, damping, tol)
        if self.iterations > 1 and (self._sqrt or not model.manifold.trivial):
            raise ValueError(f"iterations={self.iterations}: the iterated posterior "
                             f"linearisation is built in the covariance form on vector "
                             f"states; use form='covariance', or iterations=1")
        self._update_iterations = self.iterations if self.iterations > 1 else 0
        self.noise, self.dof = check_noise(noise, dof, self)
        self.adapt, self.forgetting, self._n_adapt = check_adapt(adapt, forgetting, self)
        #: the spread, the weights, and the unit points (nx, N) of a rule given by its
        #: points or None (merwe, julier, cubature: the rows of the factor of c P)
        self._scale, self._Wm, self._Wc, self._unit = _rule(self, model)
        self.jit = as_bool(jit, "jit")
        self._compile()

    _sigma_points = _symbolic_sigma_points

    def _build(self, predict: bool) -> ca.Function:
        if self._sqrt:
            return ukf_step(self, predict)
        if not self.model.manifold.trivial:  # quaternions, angles: tangent sigma points
            return usque_step(self, predict, _cholesky)
        m = self.model
        Wm, Wc = self._Wm, self._Wc
        s, x, P, u, y, tun, Q, R, p, mask, y_inf = self._symbols()
        a_prior = a_new = predicted_statistics(self, s[self._nP:]) if predict and self.adapt \
            else s[self._nP:]  # an adaptive filter's statistics (none without adapt)
        if predict and self.Qc is not None:  # the sigma-point moments over the interval
            xb, Pb, definite = ukf_prediction(self, x, P, u, p, Q)
            ok_mean = ca.logic_and(definite, finite(ca.vertcat(xb, ca.vec(Pb))))
        elif predict:
            sig, definite = self._sigma_points(x, P)
            FX = [m.F(v, u, p) for v in sig]
            xb = _mean(FX, Wm)
            dF = [v - xb for v in FX]
            Pb = _cov(dF, dF, Wc) + Q
            ok_mean = ca.logic_and(definite, finite(ca.vertcat(*FX)))
        else:
            xb, Pb = x, P
            ok_mean = ca.SX(1)
        # the update draws the sigma points of the prediction again (as filterpy does)
        sig, definite = self._sigma_points(xb, Pb)
        ok_prior = ca.logic_and(ca.logic_and(ok_mean, definite),
                                finite(ca.vertcat(xb, ca.vec(Pb))))
        uy = m.measurement_input(u)  # the input at this measurement
        Z = [ca.if_else(mask, m.H(v, uy, p), 0) for v in sig]  # missing rows: 0
        zp = _mean(Z, Wm)
        dZ = [v - zp for v in Z]
        dX = [v - xb for v in sig]
        D = ca.diag(mask)
        S = _cov(dZ, dZ, Wc) + D @ R @ D + ca.diag(1 - mask)
        S = 0.5 * (S + S.T)
        Pxz = _cov(dX, dZ, Wc)
        e = ca.if_else(mask, y - zp, 0)
        K = ca.solve(S, Pxz.T).T
        xh = xb + K @ e
        Ph = Pb - K @ S @ K.T
        Ph = 0.5 * (Ph + Ph.T)
        converged = None
        if self.dof is not None or self.adapt:  # Student-t or adaptive noise
            xh, Ph, S, a_new, _ = noise_update(self, xb, Pb, e, Pxz, _cov(dZ, dZ, Wc), Q, R,
                                               mask, a_prior)
        if self.iterations > 1:  # iterated posterior linearisation (the first: the UKF)
            xh, Ph, posterior, converged = posterior_linearised_update(
                self, xb, Pb, xh, Ph, y, mask, D @ R @ D + ca.diag(1 - mask), uy, p,
                _mean, _cov)
            ok_prior = ca.logic_and(ok_prior, posterior)
        if self.clip:
            xh = ca.fmin(ca.fmax(xh, ca.DM(self.lower)), ca.DM(self.upper))
        nis = ca.dot(e, ca.solve(S, e))
        s_new = ca.vertcat(xh, ca.vec(Ph), a_new)
        s_prior = ca.vertcat(xb, ca.vec(Pb), a_prior)
        # finite, and a covariance the next sigma points can be drawn from
        ok = ca.logic_and(finite(ca.vertcat(s_new, nis)), _cholesky(Ph)[1])
        name = "ukf_predict_update" if predict else "ukf_update"
        return self._fused_function(name, [s, u, y, tun], s_new, e, nis, ok, ok_prior, y_inf,
                                    ok_mean, mask, s_prior, converged)

    def sigma_points(self, x: ArrayLike, P: ArrayLike) -> np.ndarray:
        """The sigma points of a mean ``x`` and covariance ``P``, one a row (``(n_sigma,
        nx)``; with a stack ``x (k, nx)``, ``P (k, nx, nx)``: ``(k, n_sigma, nx)``; see
        :func:`sigma_points`)."""
        return sigma_points(self, x, P)

    def smooth(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None, iterations: int | None = None) -> SmoothResult:
        r"""Unscented Rauch-Tung-Striebel smoother over a whole record (Särkkä 2008); with
        ``iterations`` above 1 (default: the filter's), the iterated posterior
        linearisation smoother from the filter's estimates
        (:func:`~estim.estimators.kalman.smoothing.posterior_linearised`; ``result.iterations``
        and ``result.converged`` say how it ended; not with ``clip`` or a gate).

        The filter runs forward over the record with :meth:`filter` (one compiled
        call, equal to :meth:`step` at every sample after a :meth:`reset`; inputs,
        missing outputs, gating and clipping as in :func:`~estim.replay`). Backwards
        from :math:`x^s_{T-1} = \hat x_{T-1}`, :math:`P^s_{T-1} = P_{T-1}`: the
        filter's sigma points
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
            the input at each sample), as in ``FullInformation.fit``; required
            for a model with inputs (``U=0``: zero inputs, on purpose).
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
        passes = smoothing_passes(self, iterations)
        predict = unscented_smoother_prediction(self) if self.Qc is not None else \
            _unscented_prediction(self)  # (the moment equations over each interval)
        first = rts(self, Y, U, t, predict,
                    self.model.clip if self.clip else None)
        return first if passes == 1 else posterior_linearised(
            self, first, Y, U, t, passes,
            moments=sigma_moments(self) if self.Qc is not None else None)

    @property
    def P(self) -> np.ndarray:
        """Current covariance."""
        return covariance(self._s[self.model.nx:self._nP], self.model.nx, self._sqrt)

    def _failure_texts(self, flags) -> tuple[str, str]:
        return ("failed: update non-finite or its covariance not positive definite; "
                "kept the prediction",
                "update non-finite or its covariance not positive definite" if flags[2]
                else "prediction F(x, u): covariance not positive definite" if flags[5]
                else "non-finite prediction F(x, u) at the sigma points")


def sigma_points(ukf: UKF, x: ArrayLike, P: ArrayLike) -> np.ndarray:
    r"""The sigma points of a mean ``x`` and covariance ``P``, one a row (``(n_sigma,
    nx)``; with a stack ``x (k, nx)``, ``P (k, nx, nx)``: ``(k, n_sigma, nx)``).

    The offsets are the rows of the upper Cholesky factor :math:`U` of
    :math:`c P` (:math:`U^\top U = c P`), as in filterpy."""
    x, P = np.asarray(x, dtype=float), np.asarray(P, dtype=float)
    L = np.linalg.cholesky(ukf._scale * P)
    xs = x[..., None, :]
    M = ukf.model.manifold
    if ukf._unit is not None:  # x (+) L xi for every unit point
        off = np.swapaxes(L @ ukf._unit, -1, -2)
        return xs + off if M.euclidean_states else M.retract(xs, off, NP)
    off = np.swapaxes(L, -1, -2)  # rows of U = L^T
    centre = [] if ukf.points == "cubature" else [xs]
    if not M.euclidean_states:  # x (+) the offsets, in the tangent space
        return np.concatenate(centre + [M.retract(xs, off, NP), M.retract(xs, -off, NP)],
                              axis=-2)
    return np.concatenate(centre + [xs + off, xs - off], axis=-2)


def sigma_weights(points: str, n: int, alpha: float = 1.0, beta: float = 2.0,
                  kappa: float = 0.0) -> tuple[float, np.ndarray, np.ndarray]:
    r"""The spread :math:`c` (the offsets are the rows of the Cholesky factor of
    :math:`c P`) and the mean and covariance weights of a sigma-point set.

    ``"merwe"``: :math:`c = \alpha^2 (n + \kappa)`, :math:`\lambda = c - n`,
    :math:`W^m_0 = \lambda / c`, :math:`W^c_0 = W^m_0 + 1 - \alpha^2 + \beta`,
    :math:`W_i = 1/(2c)` (filterpy's ``MerweScaledSigmaPoints``); ``"julier"``:
    :math:`c = n + \kappa`, :math:`W_0 = \kappa / c`, :math:`W_i = 1/(2c)`
    (``JulierSigmaPoints``); ``"cubature"``: :math:`c = n`, :math:`2n` points of
    weight :math:`1/(2n)`, no centre point (the cubature Kalman filter's).
    """
    if points == "cubature":
        W = np.full(2 * n, 0.5 / n)
        return float(n), W, W.copy()
    c = alpha ** 2 * (n + kappa) if points == "merwe" else n + kappa
    Wm = np.full(2 * n + 1, 0.5 / c)
    Wm[0] = (c - n) / c if points == "merwe" else kappa / c
    Wc = Wm.copy()
    if points == "merwe":
        Wc[0] += 1 - alpha ** 2 + beta
    return c, Wm, Wc


def _unscented_prediction(ukf: UKF):
    """The unscented smoother's prediction of every transition at once (see
    :meth:`UKF.smooth`): ``(X, P, W) -> (x_bar, P_bar, D)``."""
    m, Q = ukf.model, ukf.Q
    M = m.manifold

    def predict(X, P, W):
        n, ns, nx = len(X), len(ukf._Wm), m.nx
        sig = ukf.sigma_points(X, P)  # (n, ns, nx)
        Fs = transitions(m, sig.reshape(n * ns, nx), np.repeat(W, ns, axis=0)
                         ).reshape(n, ns, nx)
        if M.euclidean_states:
            xb = np.einsum("i,kij->kj", ukf._Wm, Fs)
            dF, dX = Fs - xb[:, None, :], sig - X[:, None, :]
        else:  # tangent deviations: the mean about F(x), as the filter's prediction
            ref = transitions(m, X, W)[:, None, :]
            xb = M.retract(ref[:, 0], np.einsum("i,kij->kj", ukf._Wm,
                                                M.local(ref, Fs, NP)), NP)
            dF, dX = M.local(xb[:, None, :], Fs, NP), M.local(X[:, None, :], sig, NP)
        Pb = np.einsum("i,kia,kib->kab", ukf._Wc, dF, dF) + Q
        D = np.einsum("i,kia,kib->kab", ukf._Wc, dX, dF)
        return xb, 0.5 * (Pb + Pb.transpose(0, 2, 1)), D

    return predict


def _mean(points: list, weights: np.ndarray) -> ca.SX:
    """:math:`\\sum_i w_i v_i` of the sigma points' images ``points``."""
    return sum((float(w) * v for w, v in zip(weights, points, strict=True)),
               ca.SX.zeros(points[0].numel()))


def _cov(a: list, b: list, weights: np.ndarray) -> ca.SX:
    """:math:`\\sum_i w_i a_i b_i^\\top` of deviations ``a``, ``b``."""
    return sum((float(w) * (da @ db.T) for w, da, db in zip(weights, a, b, strict=True)),
               ca.SX.zeros(a[0].numel(), b[0].numel()))


def _rule(ukf: UKF, model: Model) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`sigma_rule` of ``ukf``'s options in the tangent space of ``model``."""
    return sigma_rule(ukf.points, model.ndx, ukf.order, ukf.alpha, ukf.beta, ukf.kappa,
                      stacklevel=4)


def sigma_rule(points: str, n: int, order: int = 3, alpha: float = 1.0, beta: float = 2.0,
               kappa: float = 0.0, stacklevel: int = 2
               ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray | None]:
    """The sigma-point rule ``points`` for ``n`` dimensions: the spread :math:`c`, the mean
    and covariance weights, and the unit points ``(n, N)`` of a rule given by its points
    (Gauss-Hermite: the points of :math:`(x, P)` are :math:`x + L\\xi_i`, :math:`L L^\\top
    = P`), or None (merwe, julier, cubature: :func:`sigma_weights`), with each rule's
    checks; an :class:`~estim.EstimationWarning` with the count above
    :data:`MANY_POINTS` points."""
    if points not in POINTS:
        raise ValueError(f"points must be one of {', '.join(map(repr, POINTS))}, "
                         f"got {points!r}")
    if points == "cubature5":
        unit, W = cubature5(n)
        return 1.0, W, W.copy(), unit
    if points == "gauss-hermite":
        unit, W = gauss_hermite(n, order)
        if W.size > MANY_POINTS:
            warnings.warn(f"points='gauss-hermite' of order {order} on {n} states is "
                          f"{order}^{n} = {W.size} sigma points, each through F and h "
                          f"at every step", EstimationWarning, stacklevel=stacklevel)
        return 1.0, W, W.copy(), unit
    if points != "cubature" and n + kappa <= 0:
        raise ValueError(f"kappa must make nx + kappa positive (nx = {n}), got {kappa!r}")
    return (*sigma_weights(points, n, alpha, beta, kappa), None)
