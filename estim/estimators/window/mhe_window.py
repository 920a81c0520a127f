r"""The window of moving horizon estimation (:class:`~estim.MHE`): its data, how it moves
on by one sample, and the arrival cost that summarises what left it.

The window holds the last :math:`N` samples, oldest first: the measurements
``_Y (N, ny)`` (NaN where missing), the transitions' inputs ``_U (N, nw)`` (``_U[j]``
from slot :math:`j` to :math:`j + 1`), the inputs ``_Uprev (N, nu)`` held when each
measurement was taken and the estimated trajectory ``_X (N, nx)``; its ``_n`` newest
slots are used (fewer than :math:`N` while it fills). When a full window moves on, the
oldest sample leaves it and the arrival cost
:math:`\|x_s - \bar x_s\|^2_{\bar P_s^{-1}}` moves to the next time: :math:`\bar P` by
one EKF covariance step along the MHE's own estimate of the leaving time (an update
with its measured outputs, then a prediction), :math:`\bar x` by the model's prediction
of that estimate (``"filtering"``) or the previous window's estimate of the new first
time (``"smoothing"``, ``"fixed"``).
"""

from __future__ import annotations

from collections import deque

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim.estimators.base import Estimator
from estim.estimators.manifold_steps import output_jacobian, transition_jacobian
from estim.solvers.kalman.continuous import discretised_noise
from estim.solvers.least_squares.nlp import LeastSquaresNLP
from estim.solvers.least_squares.solution import Solution


class MovingWindow(Estimator):
    """The window's bookkeeping, the base of :class:`~estim.MHE`: its state
    (:meth:`_reset`), the arrival covariance's step (:meth:`_build_cov_step`), making room
    for a sample (:meth:`_shift`, :meth:`_slide`), solving the window (:meth:`_solve`),
    restarting it after a failed solve (:meth:`_reanchor`) and saving and restoring it for
    a late measurement (:meth:`_state`, :meth:`_restore`).

    The attributes below are set by :class:`~estim.MHE`'s constructor and reset.
    """

    horizon: int
    arrival_cost: str
    max_lag: int
    lower: np.ndarray
    upper: np.ndarray
    _nlp: LeastSquaresNLP
    _cov_step: FastFunction
    _F: FastFunction
    _WQ: np.ndarray
    _WR: np.ndarray
    _W0: np.ndarray | None
    _Y: np.ndarray
    _U: np.ndarray
    _Uprev: np.ndarray
    _X: np.ndarray
    _n: int
    _xbar: np.ndarray
    _Pbar: np.ndarray | None
    _history: list[np.ndarray]
    _trusted: tuple[np.ndarray, np.ndarray | None]
    _past: deque
    #: a continuous noise's spectral density (Q then holds L Qc L^T), or None
    Qc: np.ndarray | None = None

    # ------------------------------------------------------------------ state
    def _reset(self) -> None:
        """An empty window at the prior ``x0, P0``."""
        m, N = self.model, self.horizon
        # (reset may change P0)
        self._W0 = None if self.P0 is None else self._weight_factor(self.P0)
        self._Y = np.full((N, m.ny), np.nan)      # window measurements, oldest first
        self._U = np.zeros((N, m.nw))             # _U[j]: input from slot j to j+1
        self._Uprev = np.zeros((N, m.nu))         # input held when y of slot j was taken
        self._X = np.tile(self.x0, (N, 1))        # current/previous window solution
        self._n = 0                               # measurements in the window
        self._xbar = self.x0.copy()
        self._Pbar = None if self.P0 is None else self.P0.copy()
        self._history = []                        # MHE estimates of the window's times
        # the last estimate (and covariance) of a step reported "ok" or "inexact":
        # where a failed step re-anchors
        self._trusted = (self.x0.copy(), None if self.P0 is None else self.P0.copy())
        self._nlp.reset()
        # the state before each of the last max_lag steps, with the step's data
        self._past = deque(maxlen=self.max_lag)

    # ------------------------------------------------------------------ build
    def _build_cov_step(self) -> ca.Function:
        """EKF covariance step at x: update with the measured rows, then predict (with a
        continuous noise, ``Q`` is its density and the prediction adds the transition's
        :math:`Q_d(\\Delta t)` at x)."""
        m = self.model
        nx, nu, ny = m.ndx, m.nu, m.ny  # the covariance's size: the tangent space's
        x, u, up = ca.SX.sym("x", m.nx), ca.SX.sym("u", m.nw), ca.SX.sym("u_prev", nu)
        mask = ca.SX.sym("mask", ny)
        P = ca.SX.sym("P", nx, nx)
        Q, R = ca.SX.sym("Q", nx, nx), ca.SX.sym("R", ny, ny)  # the tuning is data
        p = ca.DM(m.p)
        D = ca.diag(mask)
        # (on a manifold the Jacobians along the retraction, as the multiplicative EKF's)
        C, A = D @ output_jacobian(m, x, up, p), transition_jacobian(m, x, u, p)
        Rm = D @ R @ D + ca.diag(1 - mask)
        S = C @ P @ C.T + Rm
        K = ca.solve(0.5 * (S + S.T), C @ P).T
        IKC = ca.DM.eye(nx) - K @ C
        Pu = IKC @ P @ IKC.T + K @ Rm @ K.T
        Qd = Q if getattr(self, "Qc", None) is None else discretised_noise(m, Q, x, u)
        Pn = A @ Pu @ A.T + Qd
        return ca.Function("mhe_cov_step", [x, u, up, mask, ca.vec(P), ca.vec(Q), ca.vec(R)],
                           [ca.vec(0.5 * (Pn + Pn.T)), ca.vec(0.5 * (Pu + Pu.T))])

    # ------------------------------------------------------------------- move
    def _slide(self, u: np.ndarray) -> None:
        """Drop the oldest measurement and move the arrival cost to the next time."""
        y_old, u_old, up_old = self._Y[0].copy(), self._U[0].copy(), self._Uprev[0].copy()
        x_est = self._history[0]  # MHE estimate of the time that leaves the window
        if self.arrival_cost in ("filtering", "smoothing"):
            Pbar = self._Pbar
            assert Pbar is not None  # an arrival cost has one (its P0 is required)
            mask = np.isfinite(y_old).astype(float)
            Pn, _ = self._cov_step(x_est, u_old, up_old, mask, Pbar.ravel(order="F"),
                                   self.Q, self.R)
            Pn = Pn.reshape(self.model.ndx, self.model.ndx, order="F")
            # a non-finite linearisation: the covariance grows as for a random walk
            self._Pbar = Pn.copy() if np.isfinite(Pn).all() else Pbar + self.Q
        # the previous window's estimate of the new first time (a one-sample window has
        # none: its arrival mean is the prediction, whatever the arrival cost)
        xbar = self._X[1].copy() if self.horizon > 1 else self._X[0].copy()
        if self.arrival_cost == "filtering" or self.horizon == 1:
            pred = self._F(x_est, u_old, self.model.p)[0]
            xbar = pred.copy() if np.isfinite(pred).all() else xbar
        if self.arrival_cost != "none":
            self._xbar = xbar
        for arr in (self._Y, self._U, self._Uprev, self._X):
            arr[:-1] = arr[1:]
        self._history.pop(0)
        self._n -= 1

    def _shift(self, u: np.ndarray) -> None:
        """Make room for the arriving sample: the window's data one slot left (the
        arrival cost moved on when the window was full) and the new slot's warm start,
        the prediction of the previous estimate."""
        m, N = self.model, self.horizon
        self._U[N - 1] = self._transition(u)  # from the newest slot to the one arriving
        if self._n == N:
            self._slide(u)
        else:  # window still growing: shift the data one slot left
            for arr in (self._Y, self._U, self._Uprev, self._X):
                arr[:-1] = arr[1:]
        pred = self._F(self._X[N - 2], self._U[N - 2], m.p)[0]
        self._X[N - 1] = pred if np.isfinite(pred).all() else self._X[N - 2]

    # ------------------------------------------------------------------ solve
    def _arrival_weight(self) -> np.ndarray | None:
        """The arrival weight factor :math:`W` with :math:`W^\\top W = \\bar P^{-1}`."""
        if self.arrival_cost == "none":
            return None
        if self.arrival_cost == "fixed":
            return self._W0  # P0 is constant: factored at reset, not every step
        Pbar, P0 = self._Pbar, self.P0
        assert Pbar is not None and P0 is not None  # an arrival cost needs P0
        W: np.ndarray | None
        try:
            W = self._weight_factor(Pbar)
        except np.linalg.LinAlgError:  # lost definiteness: back to the prior's spread
            self._Pbar, W = P0.copy(), self._W0
        return W

    def _solve(self, robust: bool = False) -> tuple[Solution, str]:
        """Solve the current window (``robust``: by Gauss-Newton, see
        :meth:`LeastSquaresNLP.solve`); the solution and the consistency of its cost."""
        nlp, weight = self._nlp, self._arrival_weight()
        sol = nlp.solve(self._X, self._Y, self._U, self._Uprev, self._n, self._xbar,
                        weight, self._WQ, self._WR, self.R, robust=robust)
        measured = nlp.measured(self._Y, self._n)
        dof = measured + (self.model.ndx if weight is not None else 0)
        return sol, sol.consistency(dof, measured)

    def _reanchor(self, y: np.ndarray, u: np.ndarray) -> None:
        """Restart the window after a failed solve: only this measurement, the arrival
        cost on the last trusted estimate with its covariance inflated by ``P0``."""
        N = self.horizon
        self._anchor_window()
        self._Y[N - 1] = y
        self._Uprev[N - 1] = u
        self._n = 1

    def _anchor_window(self) -> None:
        """An empty window at the last trusted estimate (:meth:`_anchor`), the arrival
        cost on it with its covariance inflated by ``P0``."""
        x, P = self._anchor(*self._trusted)
        self._Y[:] = np.nan
        self._X[:] = x
        self._n = 0
        self._history.clear()
        if self.arrival_cost != "none":
            self._xbar = x
        if self.arrival_cost in ("filtering", "smoothing"):
            self._Pbar = P

    # ------------------------------------------------------- late measurements
    def _state(self) -> dict:
        """Everything a step reads and changes (copies of what it changes in place)."""
        nlp = self._nlp
        return {"_Y": self._Y.copy(), "_U": self._U.copy(), "_Uprev": self._Uprev.copy(),
                "_X": self._X.copy(), "_n": self._n, "_xbar": self._xbar.copy(),
                "_Pbar": None if self._Pbar is None else self._Pbar.copy(),
                "_history": list(self._history), "_trusted": self._trusted,
                "_first": self._first, "_k": self._k, "_u_last": self._u_last.copy(),
                "_info": self._info,
                "nlp": (nlp._lam_x, nlp.gn._ridge, nlp.weights)}

    def _restore(self, state: dict) -> None:
        """Go back to a :meth:`_state`."""
        state = dict(state)
        self._nlp._lam_x, self._nlp.gn._ridge, self._nlp.weights = state.pop("nlp")
        for key, value in state.items():
            setattr(self, key, value.copy() if isinstance(value, np.ndarray) else value)
        self._history = list(self._history)
