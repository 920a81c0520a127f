r"""Robust costs by iteratively reweighted least squares on the windowed problem.

With a robust loss :math:`\rho` (:mod:`estim.solvers.least_squares.robust`) on the whitened
measurement residuals :math:`r_{j,i}`, the cost
:math:`\sum \rho(r_{j,i}) + (\text{arrival and process terms})` is minimised as a
sequence of least-squares problems whose measurement weights are
:math:`\sqrt{w(r)}` times the Gaussian ones, :math:`w = \rho'(r)/r` at the current
point (Holland and Welsch, "Robust regression using iteratively reweighted
least-squares", Commun. Statist. A6(9), 1977). The structured Gauss-Newton solver
reweights at every accepted iterate; the NLP solvers solve each weighted problem and
reweight at its solution until no weight moves by more than :data:`IRLS_WTOL`.

**Process weights linearised at the estimate** (:class:`Relinearised`): with a continuous
noise each transition has its own weight :math:`M_j`, :math:`M_j^\top M_j =
Q_d(\Delta t_j)^{-1}`, from the drift linearised at :math:`x_j`. The weights are
parameters: evaluated at the start, then at each solution and solved again until they
settle (:data:`RELINEARISED`), the same fixed point as the robust weights'.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim.solvers.least_squares.robust import OUTLIER_SIGMA
from estim.solvers.least_squares.solution import Solution

if TYPE_CHECKING:
    from estim.model import Model
    from estim.solvers.least_squares.gauss_newton import StructuredGaussNewton
    from estim.solvers.least_squares.robust import RobustLoss

__all__ = ["IRLS_MAX", "IRLS_WTOL", "RELINEARISATIONS", "RELINEARISED", "Relinearised",
           "Reweighted", "weight_map"]

#: A robust fit's reweighted solves stop when no weight moves by more than
#: ``IRLS_WTOL`` between two of them, or after ``IRLS_MAX`` solves.
IRLS_WTOL = 1e-6
IRLS_MAX = 100
#: How many times at most a solve with each transition's own weight is repeated with the
#: weights linearised at its solution
RELINEARISATIONS = 4
#: the change of a transition's weight (relative to its largest entry) below which the
#: weights have settled: the estimate then moves by about as much of its defects'
#: standard deviations, far below its own
RELINEARISED = 1e-4


class Reweighted:
    """The robust solves of :class:`~estim.solvers.least_squares.nlp.LeastSquaresNLP` (a mixin): it
    provides the model, the number of slots ``N``, the parameter layout ``_slices``,
    the bounds ``lbx``, ``ubx``, the structured solver ``gn``, the ``loss`` and the
    solves :meth:`_solve` and :meth:`_solve_gn`."""

    model: Model
    N: int
    lbx: np.ndarray
    ubx: np.ndarray
    gn: StructuredGaussNewton
    loss: RobustLoss | None
    solver_name: str
    weights: np.ndarray | None
    _slices: dict[str, slice]
    _complete: bool
    _whitened: tuple | None

    def _solve(self, X0, p, Y, n, arrival: bool, robust: bool, same_window: bool = False
               ) -> Solution:
        raise NotImplementedError

    def _solve_gn(self, X0, p, reweight=None) -> Solution:
        raise NotImplementedError

    def _residuals(self, X: np.ndarray, p: np.ndarray, wy: np.ndarray) -> np.ndarray:
        """Whitened measurement residuals :math:`W_{y,j}(y_j - h(x_j))`, (N, ny), for
        the data in ``p`` and the weights ``wy`` (laid out as ``p``'s; zero rows where
        not measured)."""
        if self._whitened is None:
            m, s = self.model, self._slices
            x, y = ca.SX.sym("x", m.nx), ca.SX.sym("y", m.ny)
            w, up = ca.SX.sym("wy", m.ny * m.ny), ca.SX.sym("up", m.nu)
            e = y - m.H(x, up, ca.DM(m.p))
            one = ca.Function("whitened", [x, y, w, up], [ca.reshape(w, m.ny, m.ny) @ e])
            fun = FastFunction(one.map(self.N))
            self._whitened = (fun, s["y"], s["up"])
        fun, sy, sup = self._whitened
        with np.errstate(invalid="ignore", over="ignore"):
            r = fun(np.asarray(X, float).ravel(), p[sy], wy, p[sup])[0]
        return r.reshape(self.N, self.model.ny)

    def _solve_reweighted(self, X0, p, Y, n, arrival, robust) -> Solution:
        """Iteratively reweighted least squares for the robust loss (see
        :mod:`estim.solvers.least_squares.robust`), from weights at ``X0``.

        Gauss-Newton (and every ``robust`` solve): new weights at every accepted
        iterate, inside the solver. The NLP solvers: a weighted solve, new weights at
        its solution, until no weight moves by more than ``IRLS_WTOL`` (at most
        ``IRLS_MAX`` solves)."""
        loss, s, ny = self.loss, self._slices, self.model.ny
        self._complete = False  # the weights differ between slots
        base = p[s["wy"]].copy()

        def weights(x):
            r = self._residuals(x, p, base)
            w = loss.weight(r)
            return np.where(np.isfinite(w), w, 1.0)  # a non-finite residual stays so

        def scaled(w):
            return base * np.repeat(np.sqrt(w), ny, axis=0).ravel()

        if self.solver_name == "gauss-newton" or robust:
            used: list[np.ndarray] = []

            def reweight(x):
                used[:] = [weights(x)]
                self.gn._pbuf[s["wy"]] = scaled(used[0])

            sol = self._solve_gn(X0, p, reweight)
            p[s["wy"]] = self.gn._pbuf[s["wy"]]  # the final weights (covariance)
            return self._robust_summary(sol, p, base, used[0])
        X = np.clip(np.asarray(X0, float).reshape(self.N, -1), self.lbx.reshape(self.N, -1),
                    self.ubx.reshape(self.N, -1))
        w = weights(X)
        iters, elapsed, build, status = 0, 0.0, 0.0, None
        for solves in range(1, IRLS_MAX + 1):
            p[s["wy"]] = scaled(w)
            sol = self._solve(X, p, Y, n, arrival, robust, same_window=solves > 1)
            iters, elapsed = iters + sol.iterations, elapsed + sol.solve_time
            build += sol.build_time
            if not sol.usable:
                return Solution(sol.X, False, sol.status, iters, sol.cost, elapsed, False,
                                build)
            X, w_used, w = sol.X, w, weights(sol.X)
            if not sol.success:
                status = sol.status
                break
            if np.max(np.abs(w - w_used), initial=0.0) <= IRLS_WTOL:
                break
        else:
            status = f"robust weights not settled after {IRLS_MAX} reweighted solves"
        sol = Solution(X, status is None, status or "ok", iters, sol.cost, elapsed, True, build)
        return self._robust_summary(sol, p, base, w_used)

    def _robust_summary(self, sol: Solution, p, base, w_used) -> Solution:
        """The robust cost of a reweighted solve (its weighted cost, computed with the
        weights ``w_used``, with the measurement part replaced by the loss), and its
        outliers: the components beyond ``OUTLIER_SIGMA`` standard deviations."""
        loss = self.loss
        assert loss is not None  # reweighted solves are those of a robust loss
        r = self._residuals(sol.X, p, base)
        rho = loss.rho(r)
        sol.cost = float(sol.cost - np.sum(w_used * r * r) + np.sum(rho))
        far = np.abs(r) > OUTLIER_SIGMA
        sol.outliers, sol.outlier_cost = int(far.sum()), float(rho[far].sum())
        self.weights = loss.weight(r)
        return sol


def weight_map(model: Model, N: int, process_weight) -> ca.Function | None:
    """``(X (nx, N), U (nw, N), vec W) -> (nx**2, N)``: each transition's weight factor
    ``process_weight(model, W, x_j, u_j)``, column-major (None without one)."""
    if process_weight is None:
        return None
    nx = model.nx
    x, w, W = ca.SX.sym("x", nx), ca.SX.sym("w", model.nw), ca.SX.sym("W", nx * nx)
    M = process_weight(model, ca.reshape(W, nx, nx), x, w)
    return ca.Function("weights", [x, w, W], [ca.vec(M)]).map(N)


class Relinearised:
    """Each transition's own process weight in the windowed problem (a mixin of
    :class:`~estim.solvers.least_squares.nlp.LeastSquaresNLP`; see the module): the weights
    follow each transition's input in the parameter ``u``, from :attr:`_weight_map`
    (None: one shared ``wq``)."""

    model: Model
    N: int
    _slices: dict[str, slice]
    _weight_map: ca.Function | None

    def _relinearised(self, solve, X0, p, Y, n, arrival: bool, robust: bool) -> Solution:
        """``solve`` (the least-squares or the robust one) with each transition's weight
        linearised at the start ``X0``, then at the solution until the weights settle
        (:data:`RELINEARISATIONS` re-solves at most); the iterations and times summed."""
        self._linearised(p, np.asarray(X0, float).reshape(self.N, -1))
        sol = solve(X0, p, Y, n, arrival, robust)
        iterations, elapsed = sol.iterations, sol.solve_time
        for _ in range(RELINEARISATIONS):
            if not (sol.usable and np.isfinite(sol.X).all()) or not self._linearised(p, sol.X):
                break
            sol = solve(sol.X, p, Y, n, arrival, robust)
            iterations, elapsed = iterations + sol.iterations, elapsed + sol.solve_time
        sol.iterations, sol.solve_time = iterations, elapsed
        return sol

    def _set_inputs(self, p: np.ndarray, U: np.ndarray) -> None:
        """The transitions' inputs ``U (N, nw)`` into ``p`` (before their weights, with
        a continuous noise)."""
        m, u = self.model, p[self._slices["u"]]
        if self._weight_map is None:
            u[:] = U.ravel()
        else:
            u.reshape(self.N, -1)[:, :m.nw] = U

    def _linearised(self, p: np.ndarray, X: np.ndarray) -> bool:
        """Each transition's weight at the states ``X (N, nx)`` into ``p`` (where it is
        finite); whether any changed by more than :data:`RELINEARISED` of its largest entry."""
        m = self.model
        assert self._weight_map is not None  # (called only with the weights in u)
        u = p[self._slices["u"]].reshape(self.N, -1)
        M = np.asarray(self._weight_map(X.T, u[:, :m.nw].T, p[self._slices["wq"]])).T
        ok = np.isfinite(M).all(axis=1)
        old = u[:, m.nw:]
        gap = np.abs(M[ok] - old[ok]).max(axis=1, initial=0.0)
        changed = bool((gap > RELINEARISED * np.abs(old[ok]).max(axis=1, initial=0.0)).any())
        old[ok] = M[ok]
        if not ok.all() and not np.isfinite(old).all():  # a first start not finite
            old[~ok] = 0.0
        return changed
