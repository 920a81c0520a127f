r"""Interacting multiple model filter over EKF and UKF modes.

A system that switches between :math:`M` modes (a target that manoeuvres, a valve
that sticks) with Markov transition probabilities :math:`\Pi_{ij} = P(m_k = j \mid
m_{k-1} = i)` is filtered by one Kalman-type filter per mode, mixed at every step
(Blom, Bar-Shalom 1988; Bar-Shalom, Li, Kirubarajan 2001, ch. 11). With the mode
probabilities :math:`\mu_i` after the last step,

.. math::
    \bar c_j = \sum_i \Pi_{ij} \mu_i, \qquad
    \mu_{i \mid j} = \Pi_{ij} \mu_i / \bar c_j, \\
    x^0_j = \sum_i \mu_{i \mid j} \hat x_i, \qquad
    P^0_j = \sum_i \mu_{i \mid j} \left(P_i + (\hat x_i - x^0_j)(\hat x_i - x^0_j)^\top
    \right),

each mode's filter predicts from :math:`(x^0_j, P^0_j)` and updates with :math:`y_k`;
its measurement likelihood :math:`\Lambda_j = N(e_j; 0, S_j)` (innovation and its
covariance, computed from the mode's prediction as the mode's own update computes
them) gives :math:`\mu_j \propto \Lambda_j \bar c_j`, and the output is the mixture

.. math::
    \hat x = \sum_j \mu_j \hat x_j, \qquad
    P = \sum_j \mu_j \left(P_j + (\hat x_j - \hat x)(\hat x_j - \hat x)^\top\right).

The first step updates each mode from its own ``x0, P0`` (no prediction) and weighs
the modes by :math:`\bar c = \Pi^\top \mu_0`, as filterpy's ``IMMEstimator`` does
when its first call is an update.

References
----------
H. A. P. Blom, Y. Bar-Shalom, "The interacting multiple model algorithm for systems
with Markovian switching coefficients", IEEE TAC 33(8), 1988;
Y. Bar-Shalom, X. R. Li, T. Kirubarajan, *Estimation with Applications to Tracking
and Navigation*, Wiley 2001, ch. 11.
"""

from __future__ import annotations

from collections.abc import Mapping

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_choice, as_float
from estim.estimators.base import Estimator, StepInfo
from estim.estimators.kalman.ekf import EKF
from estim.estimators.kalman.fused import FusedKalman
from estim.estimators.kalman.square_root import P0_data, covariance
from estim.estimators.kalman.ukf import UKF, _cholesky
from estim.estimators.manifold_steps import output_jacobian, unscented_innovation
from estim.model import Model

__all__ = ["IMM"]


def _likelihood(est: FusedKalman) -> ca.Function:
    r"""``(s_prior, u, y, tuning) -> log N(e; 0, S)`` of a mode's filter: the innovation
    and its covariance from the filter's prediction ``s_prior`` (its factor in the
    square-root form), over the measured outputs."""
    m = est.model
    nx, ny, nd, M = m.nx, m.ny, m.ndx, m.manifold
    s, _, _, u, y, tun, _, R, p, mask, _ = est._symbols()
    xb, Pb = s[:nx], ca.reshape(s[nx:], nd, nd)
    if est._sqrt:
        Pb, R = Pb @ Pb.T, R @ R.T
    uy = m.measurement_input(u)
    D = ca.diag(mask)
    Rm = D @ R @ D + ca.diag(1 - mask)  # missing rows: identity, no contribution
    if isinstance(est, UKF) and not M.trivial:  # as the mode's update on the manifold
        _, _, S, e, _ = unscented_innovation(est, xb, Pb, u, y, R, p, mask, _cholesky)
    elif isinstance(est, UKF):  # the sigma points of the prediction
        sig, _ = est._sigma_points(xb, Pb)
        Z = [ca.if_else(mask, m.H(v, uy, p), 0) for v in sig]
        zp = sum((float(w) * z for w, z in zip(est._Wm, Z, strict=True)), ca.SX.zeros(ny))
        S = sum((float(w) * (z - zp) @ (z - zp).T for w, z in zip(est._Wc, Z, strict=True)),
                ca.SX.zeros(ny, ny)) + Rm
        e = ca.if_else(mask, y - zp, 0)
    else:  # EKF: the output linearised at the prediction (along the retraction)
        C = D @ output_jacobian(m, xb, uy, p)
        S = C @ Pb @ C.T + Rm
        e = ca.if_else(mask, M.output_difference(y, m.H(xb, uy, p)), 0)
    L = ca.chol(0.5 * (S + S.T)).T
    z = ca.solve(L, e)
    logl = -0.5 * (ca.sumsqr(z) + ca.sum1(mask) * np.log(2 * np.pi)) - \
        ca.sum1(ca.log(ca.diag(L)))
    return ca.Function(f"{est.name}_likelihood", [s, u, y, tun], [logl])


class IMM(Estimator):
    r"""Interacting multiple model filter (see the module) over EKF and UKF modes.

    Parameters
    ----------
    estimators : dict of str to EKF or UKF
        One filter per mode, built on models with the same states and outputs (their
        dynamics, outputs and tuning may differ); the IMM drives them: do not step
        them yourself.
    transition : (M, M) array
        Mode transition probabilities, ``transition[i, j]`` the probability of mode
        ``j`` after mode ``i`` (rows sum to 1), in the order of ``estimators``.
    mu0 : (M,) array, optional
        Mode probabilities before the first measurement (default equal).

    Notes
    -----
    ``info.P`` is the mixture's covariance; ``info.extra["mode_probabilities"]`` maps
    each mode's name to its probability after the step and ``info.extra["modes"]`` to
    its filter's own :class:`~estim.StepInfo`. The status is ``"ok"`` unless a mode's
    step was not (then that mode's status, with its name); ``success`` is False when
    every mode failed.
    """

    name = "imm"
    _manifold_aware = True  # as its modes: the mixtures are Karcher means

    def __init__(self, estimators: Mapping[str, FusedKalman], *, transition: ArrayLike,
                 mu0: ArrayLike | None = None):
        if not isinstance(estimators, Mapping) or not estimators:
            raise TypeError("estimators must be a dict of mode name to EKF or UKF")
        if len(estimators) < 2:
            raise ValueError("estimators must hold at least two modes")
        for key, est in estimators.items():
            if not isinstance(est, FusedKalman):
                raise TypeError(f"estimators[{key!r}] must be an estim.EKF or estim.UKF, "
                                f"got {type(est).__name__}")
            if est._n_adapt:
                raise ValueError(f"estimators[{key!r}] adapts its noise (adapt=): the modes "
                                 f"of an IMM mix their Gaussians only")
        modes = list(estimators.values())
        first = modes[0]
        for key, est in estimators.items():
            for what in ("state_names", "output_names", "input_names"):
                if list(getattr(est.model, what)) != list(getattr(first.model, what)):
                    raise ValueError(
                        f"estimators[{key!r}] has other {what.replace('_', ' ')} than "
                        f"the first mode: {list(getattr(est.model, what))} against "
                        f"{list(getattr(first.model, what))}")
            # what every mode's prediction must share: the interval it predicts over, the
            # inputs' hold and the tangent space the covariances live in
            for what, mine, theirs in (
                    ("dt", est.model.dt, first.model.dt),
                    ("variable_dt", est.model.variable_dt, first.model.variable_dt),
                    ("hold", est.model.hold, first.model.hold),
                    ("quaternion and angle states", est.model.manifold.declared,
                     first.model.manifold.declared)):
                if mine != theirs:
                    raise ValueError(
                        f"estimators[{key!r}]: its model's {what} is {mine!r}, the first "
                        f"mode's {theirs!r}; the modes of an IMM predict over the same "
                        f"interval from the same inputs, on the same states")
        if len({id(est) for est in modes}) != len(modes):
            raise ValueError("estimators must be distinct objects (one filter per mode)")
        super().__init__(first.model, Q=first.Q, R=first.R, x0=first.x0, P0=first.P0)
        M = len(modes)
        self.transition = _stochastic(transition, (M, M), "transition")
        self.mu0 = np.full(M, 1.0 / M) if mu0 is None else _stochastic(mu0, (M,), "mu0")
        self.estimators = dict(estimators)
        self._names = list(estimators)
        self._modes = modes
        self._loglik = [FastFunction(_likelihood(est)) for est in modes]
        self._reset()

    @classmethod
    def noise_levels(cls, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                     P0: ArrayLike, high: float = 100.0, stay: float = 0.95,
                     kind: str = "ekf") -> IMM:
        r"""Two-mode IMM on one model: quiet and agile process noise.

        The classic IMM of tracking (Bar-Shalom, Li, Kirubarajan 2001, sec. 11.7):
        one filter with the nominal ``Q`` and one with ``high * Q`` (a target that
        manoeuvres, a plant whose disturbance comes in bursts), switching with
        probability ``1 - stay`` per step. The modes are named ``"quiet"`` and
        ``"agile"``; what ``estim run`` builds for ``imm``.

        Parameters
        ----------
        model : Model
        Q, R, x0, P0 :
            The nominal tuning, as for :class:`~estim.EKF`.
        high : float
            The agile mode's process noise, as a multiple of ``Q`` (> 0).
        stay : float in (0, 1)
            The probability of staying in a mode at each step.
        kind : {"ekf", "ukf"}
            The filter of both modes.

        Returns
        -------
        IMM
        """
        high = as_float(high, "high", positive=True)
        stay = as_float(stay, "stay", positive=True, maximum=1.0,
                        expected="a probability in (0, 1)")
        if stay >= 1.0:
            raise ValueError(f"stay must be a probability in (0, 1), got {stay!r}")
        make = {"ekf": EKF, "ukf": UKF}[as_choice(kind, ("ekf", "ukf"), "kind")]
        quiet = make(model, Q=Q, R=R, x0=x0, P0=P0)
        agile = make(model, Q=high * quiet.Q, R=R, x0=x0, P0=P0)
        return cls({"quiet": quiet, "agile": agile},
                   transition=[[stay, 1.0 - stay], [1.0 - stay, stay]])

    def _reset(self) -> None:
        for est in self._modes:
            est.reset()
        self.mu = self.mu0.copy()

    def _mixture(self, xs: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The weighted mean of the modes' estimates ``xs`` and their deviations from it
        (on a manifold the weighted Karcher mean and tangent deviations)."""
        M = self.model.manifold
        if M.euclidean_states:
            mean = weights @ xs
            return mean, xs - mean
        return M.mean(xs, weights)

    def _step(self, y, u, first):
        nx, nd, T = self.model.nx, self.model.ndx, self.transition
        cbar = self.mu @ T
        if not first:  # mix the modes' estimates into each mode's starting point
            omega = T * self.mu[:, None] / np.where(cbar > 0, cbar, 1.0)[None, :]
            xs = np.array([est._s[:nx] for est in self._modes])
            Ps = [covariance(est._s[nx:], nd, est._sqrt) for est in self._modes]
            for j, est in enumerate(self._modes):
                x0, dev = self._mixture(xs, omega[:, j])
                P0 = sum(omega[i, j] * (Ps[i] + np.outer(dev[i], dev[i]))
                         for i in range(len(xs)))
                est._s[:nx] = x0
                est._s[nx:] = P0_data(0.5 * (P0 + P0.T), est._sqrt)
        logl, infos = np.empty(len(self._modes)), []
        for j, est in enumerate(self._modes):
            est.step(y, u)
            infos.append(est.info)
            prior = (est._update if first else est._predict_update).out[3]
            logl[j] = self._loglik[j](prior, est._u, est._y, est._tun)[0][0]
        with np.errstate(divide="ignore"):  # an unreachable mode: log 0 = -inf
            a = np.log(cbar) + np.where(np.isnan(logl), -np.inf, logl)
        if np.isfinite(a.max()):
            mu = np.exp(a - a.max())
            self.mu = mu / mu.sum()
        xs = np.array([est._s[:nx] for est in self._modes])
        x_hat, dev = self._mixture(xs, self.mu)
        P = sum(mu_j * (covariance(est._s[nx:], nd, est._sqrt) + np.outer(d, d))
                for mu_j, est, d in zip(self.mu, self._modes, dev, strict=True))
        status, success = "ok", any(info.success for info in infos)
        for name, info in zip(self._names, infos, strict=True):
            if info.status != "ok":
                status = f"{info.status.split(':')[0]}: mode {name!r}: " + \
                    info.status.partition(": ")[2]
                break
        out = StepInfo._fast(status=status, success=success, P=0.5 * (P + P.T))
        out.extra.update(mode_probabilities=dict(zip(self._names, self.mu.tolist(), strict=True)),
                         modes=dict(zip(self._names, infos, strict=True)))
        return x_hat, out


def _stochastic(value: ArrayLike, shape: tuple[int, ...], name: str) -> np.ndarray:
    """Probabilities: non-negative, finite, each row summing to 1 (to 1e-9)."""
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be an array of probabilities, got "
                        f"{type(value).__name__}") from None
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all() or (arr < 0).any():
        raise ValueError(f"{name} must hold finite, non-negative probabilities")
    if not np.allclose(arr.sum(axis=-1), 1.0, rtol=0, atol=1e-9):
        what = "each row of " + name if arr.ndim == 2 else name
        raise ValueError(f"{what} must sum to 1" + (" (row-stochastic)" if arr.ndim == 2 else "")
                         + f", got sums {np.round(arr.sum(axis=-1), 12)}")
    return arr
