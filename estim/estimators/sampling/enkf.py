r"""Ensemble Kalman filter on any :class:`~estim.Model`: perturbed observations or the
ensemble transform (square-root) analysis.

The filtered density :math:`p(x_k \mid y_{0:k})` is carried by :math:`N` equally
weighted members :math:`x^i_k` whose mean is the estimate and whose sample covariance
(``ddof=1``) its covariance (Evensen 1994, 2003). The first step draws
:math:`x^i_0 \sim N(x_0, P_0)` and analyses :math:`y_0` (no forecast), as the other
filters update from :math:`(x_0, P_0)` alone. Every later step forecasts each member
with its own process noise,

.. math::
    x^i_k = F(x^i_{k-1}, u_{k-1}) + L_Q v^i, \quad v^i \sim N(0, I), \quad
    L_Q L_Q^\top = Q

(:math:`L_Q` the Cholesky factor, or :math:`V \Lambda^{1/2}` from the symmetric
eigen-decomposition when :math:`Q` is singular), then inflates the forecast anomalies
multiplicatively (Anderson, Anderson 1999) by :math:`\lambda` = ``inflation``
:math:`\ge 1`,

.. math::
    x^i_k \leftarrow \bar x_k + \lambda\, (x^i_k - \bar x_k),

which multiplies the forecast covariance by :math:`\lambda^2` (``inflation=1.05``
inflates it by 10.25 %). With the anomalies :math:`A = [x^i - \bar x] / \sqrt{N-1}`,
the predicted outputs :math:`y^i = h(x^i)` of the measured components (NaN rows of
:math:`y_k` dropped, with their rows and columns of :math:`R`) and their anomalies
:math:`S = [y^i - \bar y] / \sqrt{N-1}`,

.. math::
    e = y_k - \bar y, \quad P_{xy} = A S^\top, \quad P_{yy} = S S^\top, \quad
    K = P_{xy} (P_{yy} + R)^{-1}

(by a linear solve), and the analysis is one of

``"stochastic"``
    Perturbed observations (Burgers, van Leeuwen, Evensen 1998):

    .. math::
        x^i_k \leftarrow x^i_k + K (y_k + \epsilon^i - y^i), \quad
        \epsilon^i \sim N(0, R).

    The gain uses the exact :math:`R`; the perturbations are drawn and then centred
    (their ensemble mean subtracted), so the mean moves by exactly :math:`K e` and
    the analysis covariance is right in expectation.
``"etkf"``
    The ensemble transform Kalman filter with the symmetric square root (Bishop,
    Etherton, Majumdar 2001; Hunt, Kostelich, Szunyogh 2007): with
    :math:`\tilde S = L_R^{-1} S` (:math:`L_R L_R^\top = R`) and
    :math:`T = (I + \tilde S^\top \tilde S)^{-1}` (:math:`N \times N`),

    .. math::
        \bar x_k \leftarrow \bar x_k + A\, T \tilde S^\top L_R^{-1} e, \qquad
        A \leftarrow A\, T^{1/2},

    :math:`T^{1/2}` the symmetric square root. Both come from the eigen-decomposition
    :math:`\tilde S^\top \tilde S = V \Sigma^2 V^\top`, taken as the thin singular value
    decomposition :math:`\tilde S = U \Sigma V^\top` (so the :math:`N \times N` matrix
    is never formed): :math:`T^{1/2} = I + V [(I + \Sigma^2)^{-1/2} - I] V^\top`. The
    transform keeps the anomalies' mean at zero and, for a linear :math:`h(x) = H x`,
    makes the analysis covariance exactly :math:`(I - K H) P_f`, :math:`P_f` the
    forecast ensemble's covariance (no sampling of the measurement noise).

The innovation reported is :math:`e` (0 for missing outputs) and its normalised square
:math:`e^\top (P_{yy} + R)^{-1} e`, tested against :math:`\chi^2` as for the other
filters (:func:`~estim.consistency.consistency_status`). A forecast, analysis or
ensemble covariance that is not finite fails the step: the ensemble is drawn again from
:math:`N(\hat x, P + P_0)` around the last trusted estimate (:meth:`Estimator._anchor`;
the last step reported ``"ok"``) and analyses the same measurement; if that analysis
is not finite either, the new ensemble is kept without an update.

The forecast and the outputs of all members are one call each per step of a function
generated from the model's CasADi graph with one numpy operation per instruction over
all members (:mod:`estim._vectorised`), or CasADi's ``map`` for a model whose graph
calls other Functions (an integrator).

References
----------
G. Evensen, "Sequential data assimilation with a nonlinear quasi-geostrophic model
using Monte Carlo methods to forecast error statistics", J. Geophys. Res. 99(C5), 1994;
G. Evensen, "The Ensemble Kalman Filter: theoretical formulation and practical
implementation", Ocean Dynamics 53, 2003;
G. Burgers, P. J. van Leeuwen, G. Evensen, "Analysis scheme in the ensemble Kalman
filter", Mon. Weather Rev. 126, 1998;
C. H. Bishop, B. J. Etherton, S. J. Majumdar, "Adaptive sampling with the ensemble
transform Kalman filter. Part I", Mon. Weather Rev. 129, 2001;
B. R. Hunt, E. J. Kostelich, I. Szunyogh, "Efficient data assimilation for
spatiotemporal chaos: a local ensemble transform Kalman filter", Physica D 230, 2007;
J. L. Anderson, S. L. Anderson, "A Monte Carlo implementation of the nonlinear
filtering problem to produce ensemble assimilations and forecasts", Mon. Weather Rev.
127, 1999.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._manifold import NP
from estim._validate import as_choice, as_float, as_int, as_seed
from estim.consistency import consistency_status
from estim.estimators.base import Estimator, StepInfo
from estim.estimators.filtering import FilterResult, stamped
from estim.estimators.sampling.ensembles import (
    deviations,
    draw_about,
    moved,
    over_points,
    run_record,
    square_root,
)
from estim.model import Model

__all__ = ["VARIANTS", "EnKF"]

#: The analysis schemes of :class:`EnKF`.
VARIANTS = ("stochastic", "etkf")


def _graphs(model: Model) -> tuple[ca.Function, ca.Function]:
    """``measure(x, w) -> h(x)`` and ``advance(x, v, w, LQ) -> F(x, w) + LQ v`` for one
    member, ``LQ`` the flattened (column-major) square root of ``Q`` (on a manifold
    ``F(x, w) (+) LQ v``, ``v`` in the tangent space)."""
    nx, nw, nd = model.nx, model.nw, model.ndx
    p = ca.DM(model.p)
    x, v, w = ca.SX.sym("x", nx), ca.SX.sym("v", nd), ca.SX.sym("w", nw)
    LQ = ca.SX.sym("LQ", nd * nd)
    measure = ca.Function("enkf_measure", [x, w],
                          [model.H(x, model.measurement_input(w), p)])
    noise = ca.reshape(LQ, nd, nd) @ v
    moved = model.F(x, w, p) + noise if model.manifold.euclidean_states else \
        model.manifold.retract(model.F(x, w, p), noise)
    advance = ca.Function("enkf_advance", [x, v, w, LQ], [moved])
    return measure, advance


def _stochastic(A: np.ndarray, B: np.ndarray, D: np.ndarray, e: np.ndarray, R: np.ndarray
                ) -> tuple[np.ndarray, float]:
    """Perturbed-observation analysis from the members' anomalies ``A`` (nx, N), their
    measured outputs' anomalies ``B`` (m, N), the perturbed innovations ``D`` (m, N) and
    the innovation ``e`` (m,): the members' increments and the NIS."""
    N = A.shape[1]
    S = B @ B.T / (N - 1) + R
    S = 0.5 * (S + S.T)
    W = np.linalg.solve(S, np.column_stack([D, e]))  # (P_yy + R)^-1 [D, e]
    return (A @ (B.T / (N - 1))) @ W[:, :N], float(e @ W[:, N])


def _etkf(A: np.ndarray, B: np.ndarray, e: np.ndarray, LR: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray, float]:
    """Ensemble transform analysis (symmetric square root) from the members' anomalies
    ``A`` (nx, N), their measured outputs' anomalies ``B`` and the innovation ``e``: the
    mean's increment, the new anomalies and the NIS."""
    N = A.shape[1]
    c = np.sqrt(N - 1.0)
    Sw = np.linalg.solve(LR, B) / c  # L_R^-1 S
    ew = np.linalg.solve(LR, e)
    U, s, Vt = np.linalg.svd(Sw, full_matrices=False)
    s2 = s * s
    g = U.T @ ew
    w = Vt.T @ (s / (1.0 + s2) * g)  # T S~^T L_R^-1 e
    Aa = A + ((A @ Vt.T) * (1.0 / np.sqrt(1.0 + s2) - 1.0)) @ Vt  # A T^(1/2)
    # e^T (S S^T + R)^-1 e = |ew|^2 - sum s^2 / (1 + s^2) (U^T ew)^2
    nis = float(ew @ ew - (s2 / (1.0 + s2) * g * g).sum())
    return A @ w / c, Aa, nis


def _moments(model: Model, X: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The mean and covariance (``ddof=1``) of members ``X`` (nx, N) (on a manifold: the
    mean there and the covariance of the tangent deviations); None when they are not
    finite (members finite but too far apart)."""
    with np.errstate(all="ignore"):
        x, A = deviations(model, X)
        P = A @ A.T / (X.shape[1] - 1)
    if not (np.isfinite(P).all() and np.isfinite(x).all()):
        return None
    return x, 0.5 * (P + P.T)


class EnKF(Estimator):
    r"""Ensemble Kalman filter (stochastic or ensemble transform; see the module).

    Parameters
    ----------
    model : Model
    Q, R, x0, P0 :
        Process-noise covariance (additive, may be singular), measurement-noise
        covariance, initial guess and its covariance.
    n_ensemble : int
        Number of members :math:`N` (at least 2).
    variant : {"stochastic", "etkf"}
        The analysis: perturbed observations, or the ensemble transform Kalman filter
        (deterministic symmetric square root).
    inflation : float
        Multiplicative inflation :math:`\lambda \ge 1` of the forecast anomalies (the
        forecast covariance is multiplied by :math:`\lambda^2`); 1: none.
    seed : int
        Seed of the filter's random numbers (``numpy.random.default_rng``); every
        :meth:`reset` starts the same stream again, so a run is reproducible
        bit for bit. Over the seeds of :func:`~estim.compare` each run draws its own
        stream, from this seed and the run's.

    Notes
    -----
    ``info.P`` is the ensemble covariance after the analysis (``ddof=1``);
    ``info.innovation`` the measurement less the forecast members' mean output, its
    NIS taken against :math:`P_{yy} + R`. A missing output (NaN) drops its row from
    the analysis; with nothing measured the forecast is kept. :attr:`ensemble` gives
    the current members.
    """

    name = "enkf"
    _manifold_aware = True
    _randomised = True

    def __init__(self, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                 P0: ArrayLike, n_ensemble: int = 50, variant: str = "stochastic",
                 inflation: float = 1.0, seed: int = 0):
        super().__init__(model, Q=Q, R=R, x0=x0, P0=P0)
        self.n_ensemble = as_int(n_ensemble, "n_ensemble", minimum=2,
                                 expected="an integer >= 2")
        self.variant = as_choice(variant, VARIANTS, "variant")
        self.inflation = as_float(inflation, "inflation", minimum=1.0,
                                  expected="a number >= 1 (1: no inflation)")
        seed_ = as_seed(seed)
        self.seed = 0 if seed_ is None else seed_
        self._build()
        self._tuning_changed()
        self._reset()

    def _build(self) -> None:
        measure, advance = _graphs(self.model)
        self._measure, self._advance = over_points(measure), over_points(advance)

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        del state["_measure"], state["_advance"]  # generated functions: built again
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._build()

    # ------------------------------------------------------------ tuning
    def _tuning_changed(self) -> None:
        self._LQ = square_root(self.Q).ravel(order="F")
        self._blocks: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def _measured(self, observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The block of ``R`` of the measured outputs and its Cholesky factor (kept by
        pattern)."""
        key = observed.tobytes()
        if key not in self._blocks:
            idx = np.flatnonzero(observed)
            Ro = self.R[np.ix_(idx, idx)]
            self._blocks[key] = (Ro, np.linalg.cholesky(Ro))
        return self._blocks[key]

    def _reset(self) -> None:
        self._rng = np.random.default_rng(self.seed)
        self._X: np.ndarray | None = None
        self._trusted = (self.x0.copy(), None if self.P0 is None else self.P0.copy())

    @property
    def ensemble(self) -> np.ndarray | None:
        """The current members, ``(nx, n_ensemble)`` (a copy; None before the first step)."""
        return None if self._X is None else self._X.copy()

    # -------------------------------------------------------------- step
    def _step(self, y, u, first):
        m, N, nd = self.model, self.n_ensemble, self.model.ndx
        observed = ~np.isnan(y)
        w = self._transition(u) if m.nw else np.zeros(0)
        status, success = "ok", True
        if first or self._X is None:
            X = draw_about(m, self._rng, self.x0, self.P0, N)
        else:
            V = self._rng.standard_normal((nd, N))
            X = self._advance(self._X, V, w, self._LQ, n=N)[0]
            if self.inflation != 1.0:
                with np.errstate(all="ignore"):
                    xb, A = deviations(m, X)
                    X = moved(m, xb[:, None], self.inflation * A)
        Xa, e, nis = self._analyse(X, y, observed, w)
        moments = None if Xa is None else _moments(m, Xa)
        if moments is None:  # a forecast or analysis that is not finite: re-anchor
            x_t, P_t = self._anchor(*self._trusted)
            X = draw_about(m, self._rng, x_t, P_t, N)
            Xa, e, nis = self._analyse(X, y, observed, w)
            moments = None if Xa is None else _moments(m, Xa)
            status, success = ("failed: non-finite ensemble; re-anchored on the last "
                               "trusted estimate with P + P0"), False
            if moments is None:
                Xa, e, nis, moments = (X, np.zeros(m.ny), float("nan"),
                                       _moments(m, X) or (x_t, P_t))
                status += " (no update: the new ensemble's analysis is not finite either)"
        x_hat, P = moments
        if success and observed.any():
            status = consistency_status(nis, int(observed.sum()))
        if status == "ok":
            self._trusted = (x_hat, P)
        self._X = Xa
        info = StepInfo._fast(status=status, success=success, P=P, innovation=e, nis=nis)
        return x_hat, info

    def _analyse(self, X, y, observed, w):
        """The analysis ensemble, the innovation (ny,) and its NIS; ``(None, ...)`` when
        the members, their outputs or the analysis are not finite."""
        ny, N = self.model.ny, self.n_ensemble
        e = np.zeros(ny)
        if not np.isfinite(X).all():
            return None, e, float("nan")
        if not observed.any():
            return X, e, float("nan")
        Yo = self._measure(X, w, n=N)[0][observed]
        if not np.isfinite(Yo).all():
            return None, e, float("nan")
        Ro, LR = self._measured(observed)
        try:
            with np.errstate(all="ignore"):
                Xa, eo, nis = self._analysis(X, Yo, y[observed], observed, Ro, LR)
        except np.linalg.LinAlgError:
            return None, e, float("nan")
        if not (np.isfinite(Xa).all() and np.isfinite(nis)):
            return None, e, float("nan")
        e[observed] = eo
        return Xa, e, nis

    def _analysis(self, X, Yo, yo, observed, Ro, LR):
        """The analysis of members ``X`` (nx, N) with measured outputs ``Yo`` (m, N) and
        measurement ``yo`` (m,): anomalies and increments in the tangent space of a
        manifold (quaternions, angles; output angles wrapped), else plain differences."""
        m = self.model
        M, rows = m.manifold, np.flatnonzero(observed)
        xb, A = deviations(m, X)
        if M.trivial:
            yb = Yo.mean(axis=1)
            B, e = Yo - yb[:, None], yo - yb
        else:  # output anomalies wrapped about the first member's outputs
            dy = M.output_difference(Yo.T, Yo[:, 0], NP, rows).T
            yb = Yo[:, 0] + dy.mean(axis=1)
            B = dy - dy.mean(axis=1, keepdims=True)
            e = M.output_difference(yo, yb, NP, rows)
        if self.variant == "etkf":
            shift, Aa, nis = _etkf(A, B, e, LR)
            if M.trivial:
                return (xb + shift)[:, None] + Aa, e, nis
            return moved(m, xb[:, None], shift[:, None] + Aa), e, nis
        E = LR @ self._rng.standard_normal(Yo.shape)
        E -= E.mean(axis=1, keepdims=True)
        D = yo[:, None] + E - Yo if M.trivial else \
            M.output_difference((yo[:, None] + E).T, Yo.T, NP, rows).T
        dX, nis = _stochastic(A, B, D, e, Ro)
        return moved(m, X, dX), e, nis

    # ------------------------------------------------------------ record
    def filter(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None) -> FilterResult:
        """Filter a whole record (after a :meth:`reset`): what :func:`~estim.replay` gives.

        Parameters
        ----------
        Y : (T, ny) array
            Measurements, NaN where missing.
        U : (T-1, nu) or (T, nu) array, optional
            ``U[k]`` acts from sample k to k+1 (with ``hold="foh"``: ``(T, nu)``,
            the input at each sample), as in :meth:`EKF.filter <estim.EKF.filter>`.
        t : (T,) array, optional
            Sample times, kept in the result (default :math:`k\\,\\Delta t`).

        Returns
        -------
        FilterResult
            Ensemble means after each analysis, their ensemble covariances
            (``ddof=1``), innovations (the measurements less the forecast members' mean
            output), NIS, statuses and ``success``.
        """
        X, P, infos = run_record(self, Y, U)
        status = tuple(info.status for info in infos)
        res = FilterResult(x=X, P=P, innovation=np.array([info.innovation for info in infos]),
                           nis=np.array([info.nis for info in infos]), status=status,
                           success=not any(s.startswith("failed") for s in status))
        return stamped(res, self.model, t, fixed_dt=True)
