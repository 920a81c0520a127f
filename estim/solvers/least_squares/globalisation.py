r"""Globalisation of the structured Gauss-Newton iterations: line search, rollout, switches.

:class:`Globalised` is the iteration loop of
:class:`~estim.solvers.least_squares.gauss_newton.StructuredGaussNewton`, which supplies the
compiled functions (cost, gradient and directions at a point; the cost alone; the
rollout) over shared input buffers. From a point it takes

- the projected Gauss-Newton direction, and Newton's (exact Hessian blocks) once the
  Gauss-Newton steps contract slowly (a step more than :data:`SWITCH_RATIO` of the
  previous one, both at a large residual) or stop descending;
- an Armijo backtracking line search along the projection arc
  :math:`X(\alpha) = \Pi[X + \alpha d]` (Bertsekas 1982), or along the same step taken
  through the dynamics (the nonlinear rollout of differential dynamic programming,
  which avoids the Maratos effect of heavily weighted defects at small process noise);
- Levenberg-Marquardt damping :math:`\lambda\,\mathrm{diag}(H)` when no direction
  decreases the cost, relaxed after full steps, and a ridge once a block is singular;

and stops on Deuflhard's contraction estimate of what is left after the next step.

References
----------
D. P. Bertsekas, "Projected Newton methods for optimization problems with
simple constraints", SIAM J. Control Optim. 20(2), 1982;
P. Deuflhard, *Newton Methods for Nonlinear Problems*, Springer, 2004, ch. 2 and 4;
J. Nocedal, S. J. Wright, *Numerical Optimization*, 2nd ed., ch. 3 and 10.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["SWITCH_RATIO", "Globalised"]

#: Gauss-Newton steps that shrink by less than this factor switch to Newton steps.
SWITCH_RATIO = 0.8
#: iteration function by (Newton, damped or with the ridge)
_ITERATIONS = {(False, False): "gn", (False, True): "gn_lam", (True, False): "newton",
               (True, True): "newton_lam"}


class Globalised:
    """The iterations of a structured least-squares solver (a mixin).

    The solver provides the bounds' projection ``_project`` and ``_bounded``, the
    tolerances ``max_iter``, ``xtol`` and ``ftol``, ``newton`` (start with Newton steps), the
    number of slots ``N``, the input buffers ``_xbuf`` (the point), ``_pbuf`` (the
    parameters), ``_lbuf`` (the damping), ``_dbuf`` and ``_abuf`` (a rollout's
    direction and step length), and :meth:`_function`, its compiled functions by key
    (``"cost"``, ``"roll"`` and the iterations of :data:`_ITERATIONS`, the latter as
    pairs with separate output buffers).
    """

    #: a progress bar the iterations update (one a step, the cost), set by a caller whose
    #: solve may be long (``FullInformation.fit``); None: no report
    progress: Any = None
    N: int
    max_iter: int
    xtol: float
    ftol: float
    newton: bool
    build_seconds: float
    last_build: float
    _bounded: bool
    _project: Callable[[np.ndarray], np.ndarray]
    _xbuf: np.ndarray
    _pbuf: np.ndarray
    _lbuf: np.ndarray
    _dbuf: np.ndarray
    _abuf: np.ndarray
    _ridge: bool
    _complete: bool
    _prefer_roll: bool
    #: the states move on a manifold: steps in the (padded) tangent space
    _tangent: bool = False

    def _function(self, key: str, complete: bool | None = None) -> Any:
        """The compiled function ``key`` (see the class)."""
        raise NotImplementedError

    def _set_parameters(self, p: np.ndarray) -> None:
        """Write the parameters ``p`` into :attr:`_pbuf` (a solver refreshes here what it
        derives from them)."""
        self._pbuf[:] = p

    def solve(self, X0: np.ndarray, p: np.ndarray, complete: bool = False, reweight=None):
        r"""Minimise from ``X0`` (N, nx).

        Gauss-Newton iterations first (cheap: no second derivatives). When
        they contract slowly (a step more than ``SWITCH_RATIO`` = 0.8 of the
        previous one, both full steps that lowered the cost by less than half, as on
        large-residual problems) or stop descending, the iterations
        switch to Newton steps with the exact Hessian blocks, falling back to
        the Gauss-Newton direction where the Newton one does not descend. If
        no direction decreases the cost, Levenberg-Marquardt damping
        :math:`\lambda\,\mathrm{diag}(H)` is raised until one does (and
        relaxed after full steps).

        Converged when what is left after the next projected Gauss-Newton
        step :math:`d_k` is negligible: the step itself moves no variable by
        more than :math:`\epsilon = ` ``xtol * (1 + max|x|)``, or (without
        bounds) the steps contract, :math:`\rho = \|d_k\|_\infty /
        \|d_{k-1}\|_\infty < 1` after a full step, and the geometric bound on
        the rest, :math:`\rho/(1-\rho)\,\|d_k\|_\infty`, is below
        :math:`\epsilon` (Deuflhard's contraction estimate), or the decrease
        it predicts, :math:`-g^\top d_k` (the Gauss-Newton model's, exact for
        the step that minimises it), is at most ``ftol`` times the cost (MINPACK's
        relative-reduction test; large-residual problems, where Gauss-Newton
        converges linearly, stop there instead of creeping on to the step
        tolerance; what is left after that step is about
        :math:`\rho^2` ``ftol`` of the cost).
        That last step is taken when the cost, evaluated alone without
        derivatives, confirms it (MINPACK likewise returns the last accepted
        step without a new Jacobian). On the Lorenz FIE of seed 000 this stops
        within 3e-8 of the optimum Ipopt finds at tolerance 1e-12.

        ``complete``: every slot holds every output with the weights given at
        construction (``p`` carries the same values); constant-weight graphs
        are used.

        ``reweight(x)``: called at the start and at every accepted point; it may
        change the measurement weights in :attr:`_pbuf` (a robust loss's
        iteratively reweighted least squares, see :mod:`estim.solvers.least_squares.robust`).
        Each step then decreases the cost of the weights of its starting point,
        and a negligible step is a stationary point of the robust cost (only the
        step test then stops the iterations).

        Returns ``(x, success, status, iterations, cost, seconds)``, ``x`` flat.
        """
        # far from the data the iterates may overflow: the line search rejects such
        # points (inf and NaN fail its test) without a numpy warning
        with np.errstate(over="ignore", invalid="ignore"):
            return self._minimise(X0, p, complete, reweight)

    def _minimise(self, X0, p, complete, reweight):
        """:meth:`solve`'s iterations."""
        t0, b0 = time.perf_counter(), self.build_seconds
        proj, bounded, xtol = self._project, self._bounded, self.xtol
        x = proj(np.array(X0, dtype=float).ravel())
        self._complete = bool(complete)
        self._set_parameters(p)  # fixed for the whole solve (but for reweight): written once
        if reweight is not None:
            reweight(x)
        lam, newton, last_step, last_full, last_alpha = 0.0, self.newton, np.inf, np.inf, 0.0
        last_little = False  # the last accepted step gained little (see below)
        self._prefer_roll = False
        # two output buffers: the current point's, and the one a trial point writes
        slot, pair = 0, self._iteration(newton, lam)
        f, g, dirs = self._evaluate(pair[slot], x, lam)
        if not np.isfinite(f):
            return x, False, "non-finite cost at the initial guess", 0, f, self._elapsed(t0, b0)
        status, steps = "max_iter", 0
        xmax = np.abs(x).max()  # an upper bound of max|x|, made exact when it matters
        while steps < self.max_iter:
            # judged on the Gauss-Newton direction, a descent direction (J^T J is positive
            # semi-definite) where the Newton one may not be: converged when the rest
            # after the next step is negligible or the decrease it predicts is at rounding
            # level (an ascending one means the near-singular solve lost accuracy: not
            # converged; the line search rejects it and the damping below regularises)
            d_gn = dirs[-1]
            move = self._delta(self._step_to(x, d_gn), x) if bounded or self._tangent \
                else d_gn
            decrease = -float(g @ move)
            if decrease != decrease and not (lam or self._ridge):
                # a singular block: from now on with the ridge (see _damp)
                self._ridge = True
                slot, pair = 1 - slot, self._iteration(newton, lam)
                f, g, dirs = self._evaluate(pair[slot], x, lam)
                continue
            size = np.abs(move).max()
            # contraction rate of unbounded iterations (with bounds, a tiny step can
            # precede a change of the active set and a large one)
            rho = size / last_full if 0 < last_full < np.inf and not bounded else np.inf
            rest = min(size, rho * size / (1.0 - rho) if rho < 1.0 else np.inf)
            if rest <= xtol * (1.0 + xmax):
                xmax = np.abs(x).max()
            # (reweighted: a small decrease of this iteration's weighted cost is no
            # proof, IRLS converges linearly in directions the weights flatten)
            if rest <= xtol * (1.0 + xmax) or (
                    0.0 <= decrease <= self.ftol * abs(f) and reweight is None):
                status = "ok"
                xn = self._step_to(x, d_gn) if self._tangent else x + move
                self._xbuf[:] = xn
                fn = float(self._function("cost").evaluate()[0][0])
                if fn <= f - 1e-4 * max(decrease, 0.0):  # the last step, confirmed by the cost
                    x, f, steps = xn, fn, steps + 1
                break
            new = None
            for d in dirs:
                slope = -decrease if d is d_gn and not bounded else None
                new = self._line_search(x, f, g, d, pair[1 - slot], lam, slope)
                if new is not None:
                    break
            if new is None:
                if not newton:
                    newton = True
                else:  # no decrease along either direction: damp
                    lam = max(1e-3, 10.0 * lam)
                    if lam > 1e10:
                        status = "line search failed"
                        break
                slot, pair = 1 - slot, self._iteration(newton, lam)
                f, g, dirs = self._evaluate(pair[slot], x, lam)
                last_full = np.inf
                continue
            xn, alpha, evaluated, fn = new
            step = np.abs(self._delta(xn, x)).max()
            # Gauss-Newton's linear rate near a large-residual optimum: full steps that
            # shrink slowly and gain little, the previous one too (not the steps far from
            # it, which halve the cost or are damped: the ratio of two steps is the local
            # rate only when neither is one of them)
            little = fn > 0.5 * f
            switch = not newton and alpha == 1.0 == last_alpha and little and last_little \
                and step > SWITCH_RATIO * last_step
            x, steps, last_step, xmax, last_alpha = xn, steps + 1, step, xmax + step, alpha
            last_little = little
            last_full = step if alpha == 1.0 and not lam else np.inf  # for the rate rho
            if alpha == 1.0 and lam:
                lam = lam / 10.0 if lam > 1e-8 else 0.0
                evaluated, pair = None, self._iteration(newton, lam)
            if switch:
                newton, evaluated, pair = True, None, self._iteration(True, lam)
            if reweight is not None:  # new weights at the new point: evaluated afresh
                reweight(x)
                evaluated = None
            slot = 1 - slot  # the trial's buffer, or a new evaluation there
            f, g, dirs = evaluated if evaluated is not None else \
                self._evaluate(pair[slot], x, lam)
            if self.progress is not None:  # a long fit's bar (set by its caller)
                self.progress.update(1)
                self.progress.set_postfix_str(f"cost {f:.6g}")
        ok = status == "ok" and bool(np.isfinite(x).all()) and np.isfinite(f)
        return x, ok, status, steps, f, self._elapsed(t0, b0)

    def _elapsed(self, t0: float, b0: float) -> float:
        """Seconds since ``t0`` without the building since then (kept in
        :attr:`last_build`)."""
        self.last_build = self.build_seconds - b0
        return time.perf_counter() - t0 - self.last_build

    def _line_search(self, x, f, g, d, fun, lam, slope=None):
        """Armijo backtracking along one of two paths: the step ``x + alpha d``
        (projected on the bounds), or the same step taken through the dynamics
        (:meth:`_rolled`).

        The path that gave the last accepted step is tried first, its full step
        evaluated by the iteration function ``fun`` (reused by the next iteration
        when accepted); then the other path's full step, by the cost alone; then
        shorter steps along the path whose full step was cheaper, by the cost alone.
        ``slope``: ``g @ d`` if known. Returns ``(x_new, alpha, evaluation or None,
        cost at x_new)``, or None on failure.
        """
        if slope is None:
            slope = float(g @ self._delta(self._step_to(x, 1e-8 * d), x)) if \
                self._bounded else float(g @ d)
        if not slope < 0.0:
            return None  # not a descent direction (or not finite)
        paths = ("line",) if self.N == 1 or self._tangent else ("roll", "line") \
            if self._prefer_roll else ("line", "roll")
        cost = self._function("cost")
        full = {}
        for path in paths:
            xn = self._point(path, x, d, 1.0)
            if path == paths[0]:
                ev = self._evaluate(fun, xn, lam)
                fn = ev[0]
            else:
                ev, self._xbuf[:] = None, xn
                fn = float(cost.evaluate()[0][0])
            # Armijo test (False for NaN); the gradient of f is 2 g
            if fn <= f + 2e-4 * float(g @ self._delta(xn, x)):
                self._prefer_roll = path == "roll"
                return xn, 1.0, ev, fn
            full[path] = fn if fn == fn else np.inf
        path = min(full, key=full.get)
        alpha = 0.5
        while alpha > 1e-8:
            xn = self._point(path, x, d, alpha)
            self._xbuf[:] = xn
            fn = float(cost.evaluate()[0][0])
            if fn <= f + 2e-4 * float(g @ self._delta(xn, x)):
                self._prefer_roll = path == "roll"
                return xn, alpha, None, fn
            alpha *= 0.5
        return None

    def _point(self, path: str, x, d, alpha: float) -> np.ndarray:
        """The point ``alpha`` along ``path`` (see :meth:`_line_search`)."""
        if path == "roll":
            return self._rolled(x, d, alpha)
        return self._step_to(x, alpha * d)

    def _step_to(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The point ``x`` moved by the step ``d`` (flat, slot-major), projected on the
        bounds: ``x + d`` (on a manifold, the retraction)."""
        return self._project(x + d) if self._bounded else x + d

    def _delta(self, xn: np.ndarray, x: np.ndarray) -> np.ndarray:
        """The step from ``x`` to ``xn``: ``xn - x`` (on a manifold, in the tangent space)."""
        return xn - x

    def _rolled(self, x, d, alpha: float) -> np.ndarray:
        """The step ``alpha d`` from ``x`` taken through the dynamics (projected)."""
        self._xbuf[:] = x
        self._dbuf[:] = d
        self._abuf[0] = alpha
        out = self._function("roll").evaluate()[0]
        return self._project(out.copy()) if self._bounded else out.copy()

    def _iteration(self, newton, lam):
        """The pair of iteration functions (two output buffers) for the current state."""
        return self._function(_ITERATIONS[newton, bool(lam) or self._ridge])

    def _evaluate(self, fun, x, lam):
        """Cost, gradient and direction(s) at ``x`` by the iteration function ``fun``
        (the parameters already in place), as views of its output buffers."""
        self._xbuf[:] = x
        self._lbuf[0] = lam
        out = fun.evaluate()
        return float(out[0][0]), out[1], tuple(out[2:])
