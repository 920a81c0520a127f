r"""Single-shooting optimisation-based observer (Oliva & Carnevale).

Measurements enter a buffer of ``w`` samples taken every ``N_Ts`` steps.
Whenever the full buffer receives a new sample, the (augmented) state at the
start of the window (``direction="forward"``) or at the current time
(``direction="backward"``) is chosen so that the outputs predicted by the
model match the buffer,

.. math::
    J(\hat\xi) = \sum_{i=1}^{w} W_1 \|Y_i - h(\hat\xi_i)\|^2_{R^{-1}}
                 + W_2 \|\dot Y_i - \tfrac{d}{dt} h(\hat\xi_i)\|^2_{R^{-1}},

where :math:`\hat\xi_i` is the propagation of the optimised state to the
i-th buffer time, :math:`\dot Y_i` a numerical derivative of the measured
output and :math:`\frac{d}{dt}h = \frac{\partial h}{\partial x} f(x, u)`
its exact counterpart from the model. Between optimisations the estimate is
propagated open loop, so :meth:`step` returns :math:`\hat x_{k|k}` at every
sample.

References
----------
F. Oliva, D. Carnevale, "Optimisation based observer", report, 2020;
H. K. Khalil, *Nonlinear Systems*, 3rd ed., 2002 (sensitivity equations).
"""

from __future__ import annotations

import time
from collections import deque

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import as_choice, as_float, as_int
from estim.estimators.base import Estimator, StepInfo, consistency_status
from estim.model import Model, euler_step, rk4_step
from estim.solvers.nlp import _casadi_reason, measurement_weights, weight_factor

METHODS = ("bfgs", "lbfgsb", "ipopt", "nelder-mead", "gradient")


def scipy_minimize(fun, x0, **options):
    """:func:`scipy.optimize.minimize`, imported on the first solve rather than with
    estim (scipy.optimize takes a third of a second to import)."""
    from scipy.optimize import minimize

    return minimize(fun, x0, **options)


def derivative_filter(samples: np.ndarray, dt: float) -> np.ndarray:
    r"""Derivative at the newest sample from a least-squares quadratic fit.

    Fits :math:`y(t) \approx c_0 + c_1 t + c_2 t^2` to the last ``m`` samples
    (times :math:`-(m-1)\,dt, \dots, 0`) and returns :math:`c_1 = \dot y(0)`:
    a causal Savitzky-Golay differentiator, exact for quadratics, whose
    noise gain falls as :math:`m^{-3/2}`.

    Parameters
    ----------
    samples : (m, ny) array, oldest first, m >= 3
    dt : float
    """
    m = samples.shape[0]
    t = (np.arange(m) - (m - 1)) * dt
    V = np.vander(t, 3, increasing=True)
    coef = np.linalg.lstsq(V, samples, rcond=None)[0]
    return coef[1]


class _Cost:
    """The shooting cost and gradient at ``start + T z``, evaluated once at the start."""

    def __init__(self, start, J, args):
        self.start, self.J, self.args = start, J, args
        J0, g0 = J(start, *args)  # views of J's output buffers: copy what is kept
        self.J0, self.g0 = float(J0[0]), g0.copy()

    def __call__(self, z, T):
        if not z.any():
            return self.J0, T.T @ self.g0
        J, g = self.J(self.start + T @ z, *self.args)
        return float(J[0]), T.T @ g


class ShootingObserver(Estimator):
    r"""Optimisation-based observer on a downsampled measurement buffer.

    Parameters
    ----------
    model : Model
        Usually ``model.augment(...)`` so that parameters are estimated.
    window : int
        ``w``, the number of buffered samples (>= 1).
    every : int
        ``N_Ts``, steps between buffered samples (>= 1).
    derivative_weight : float or None
        :math:`W_2/W_1`. ``None`` (default) sets it on the first full buffer
        so that both terms have the same magnitude (report sec. 1.2.1); 0
        removes the derivative term. Requires a continuous model.
    derivative_samples : int
        Samples of the quadratic differentiator (:func:`derivative_filter`).
    method : {"bfgs", "lbfgsb", "ipopt", "nelder-mead", "gradient"}
        ``"bfgs"`` (default): scipy's BFGS (fminunc's analogue) with the AD gradient,
        in Gauss-Newton-whitened coordinates (see ``resolution``);
        ``"lbfgsb"``/``"ipopt"``: with the bounds (fmincon's analogue);
        ``"nelder-mead"``: the simplex method (fminsearch's analogue);
        ``"gradient"``: gradient descent :math:`\xi_0 \leftarrow \xi_0 -
        \alpha\, \partial J/\partial \xi_0` with the gradient from the forward
        sensitivity equations (report eqs. 1.8-1.10) and a backtracking step.
    direction : {"forward", "backward"}
        Optimise the state at the window's start and propagate forward, or
        the current state and propagate backward (the report's Figure 2).
    Q : accepted for interchangeability (unused).
    R : float, (ny,) or (ny, ny)
        Output covariance: the residuals are weighted by :math:`R^{-1}`.
    x0 : (nx,) array
        Initial guess.
    P0 : optional
        If given, a prior :math:`\|\xi_0 - \bar\xi\|^2_{P_0^{-1}}` on the
        optimised state around its propagated previous estimate
        (regularisation; none by default).
    lower, upper : optional
        Bounds for ``lbfgsb``/``ipopt`` (default: the model's).
    max_iter : int
        Iterations per optimisation.
    tol : float
        Smallest significant decrease of the cost. The cost is weighted by
        :math:`R^{-1}`, a :math:`\chi^2` statistic in the noise, so a decrease
        far below 1 is not information; the methods stop when the decrease
        they can still predict is below ``tol`` (in the Gauss-Newton-scaled
        variables the gradient tolerance is :math:`\sqrt{2\,tol}`).
    resolution : float or None
        ``"bfgs"`` and ``"nelder-mead"`` optimise along the eigen-directions of
        the window's Gauss-Newton Hessian (whitened, so the Hessian there is the
        identity). ``None`` (default) keeps every direction the Hessian resolves
        numerically: the method reaches the window's least-squares optimum. A number
        keeps only the directions the window determines to a relative standard error
        below it (a truncated Gauss-Newton subspace, see :meth:`_subspace`, relative to
        the magnitudes of :meth:`_scales`, which do not need a non-zero start); the others
        keep the propagated previous estimate, so windows with little information
        (between bursts, without excitation) do not push the estimate around (the
        report's examples use 0.003 and 0.05). The bounded methods use the full space.
    history_length : int or None
        Optimisations kept in :attr:`history` (the oldest are dropped, so memory
        stays flat over long runs); None keeps all.

    Notes
    -----
    Statuses of an optimising step (:mod:`estim.estimators.base`): ``"ok"`` only when
    the method converged (its own test: the gradient test of BFGS and L-BFGS-B,
    Ipopt's ``Solve_Succeeded``, the simplex's tolerances, a vanishing gradient or
    decrease for ``"gradient"``) with no direction left out; ``"inexact: <reason>"``
    when the estimate is usable (finite, no worse than the start) but not converged:
    ``max_iter`` reached, a line search that stalled or lost precision before the
    gradient test, or directions left out because the window does not determine them to the
    resolution (``"k of n directions left out"``; ``"no direction determined to the
    resolution ... (0 of n)"`` when the estimate is kept as it is); ``"failed: ..."``
    when nothing usable came out (a non-finite point or cost, or a cost above the
    start's; the propagated estimate is kept). ``"suspect: ..."``
    is appended when the output cost lies beyond :data:`~estim.estimators.base.SUSPECT_TAIL`.

    Attributes
    ----------
    info : StepInfo
        After an optimisation: ``iterations``, ``cost``, ``status`` and
        ``extra`` with ``optimised=True``, ``singular_values`` and
        ``condition`` of the output sensitivity to relative changes,
        :math:`R^{-1/2}\,\partial (Y_1..Y_w)/\partial \xi_0\,\mathrm{diag}(|\xi_0|)`
        (the identifiability diagnostic: a huge condition number means the
        window carries no information on some direction; the Fisher
        information's condition number is its square), ``derivative_weight``
        and ``window_start``.
    history : collections.deque of dict
        One record per optimisation since the last reset, the last
        ``history_length`` of them: ``k`` (sample), ``condition``, ``cost``,
        ``iterations``, ``solve_time``, ``success``, ``derivative_weight``.
    """

    name = "shooting"
    _requires_P0 = False

    def __init__(self, model: Model, *, window: int, every: int, R: ArrayLike, x0: ArrayLike,
                 Q: ArrayLike | None = None, P0: ArrayLike | None = None,
                 derivative_weight: float | None = None, derivative_samples: int = 5,
                 method: str = "bfgs", direction: str = "forward",
                 lower: ArrayLike | None = None, upper: ArrayLike | None = None,
                 max_iter: int = 100, tol: float = 1e-3, resolution: float | None = None,
                 history_length: int | None = 1000):
        super().__init__(model, Q=0.0 if Q is None else Q, R=R, x0=x0, P0=P0)
        if model.variable_dt:
            raise ValueError("ShootingObserver needs samples at the model's fixed dt (its "
                             "buffer and derivative term are built on that grid); model "
                             f"{model.name} was built with variable_dt=True")
        for name, val, least in (("window", window, 1), ("every", every, 1),
                                 ("derivative_samples", derivative_samples, 3),
                                 ("max_iter", max_iter, 1)):
            as_int(val, name, minimum=least, expected=f"an integer >= {least}")
        as_choice(method, METHODS, "method")
        as_choice(direction, ("forward", "backward"), "direction")
        derivative_weight = as_float(derivative_weight, "derivative_weight", minimum=0.0,
                                     allow_none=True, expected=">= 0 or None")
        tol = as_float(tol, "tol", positive=True)
        resolution = as_float(resolution, "resolution", positive=True, allow_none=True)
        if not model.continuous and derivative_weight != 0:
            if derivative_weight is not None:
                raise ValueError("derivative_weight needs a continuous model (ode=): the "
                                 "output derivative comes from dh/dx f(x, u)")
            derivative_weight = 0.0
        if direction == "backward" and not model.continuous:
            raise ValueError("direction='backward' needs a continuous model (ode=)")
        self.window, self.every = int(window), int(every)
        self.derivative_samples = int(derivative_samples)
        self.method, self.direction = method, direction
        self.max_iter = int(max_iter)
        self.tol, self.resolution = tol, resolution
        self.history_length = None if history_length is None else \
            as_int(history_length, "history_length", minimum=1)
        self.lower, self.upper = self._bounds(lower, upper)
        self._fixed_w2 = derivative_weight
        self._tuning_changed()
        self._span = (self.window - 1) * self.every  # steps from first to last sample
        self._F = FastFunction(model.F)  # this estimator's own buffers (thread safety)
        self._build()
        self._reset()
        self._warn_if_not_smooth()

    def _tuning_changed(self) -> None:
        """The output weights of the windows (``R`` is data: the graphs take them per
        window)."""
        self._WR = weight_factor(self.R)  # W^T W = R^-1

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        """Cost, gradient and sensitivity Functions of the shooting problem."""
        m, w, n = self.model, self.window, self.every
        nx, nu, ny = m.nx, m.nu, m.ny
        p = ca.DM(m.p)
        steps = self._span
        x0 = ca.SX.sym("xi0", nx)
        U = ca.SX.sym("U", m.nw, max(steps, 1))  # the transitions' inputs
        Y = ca.SX.sym("Y", ny, w)
        Yd = ca.SX.sym("Yd", ny, w)
        W2 = ca.SX.sym("W2")
        xbar = ca.SX.sym("xbar", nx)
        Wp = ca.SX.sym("Wp", nx, nx)
        # per-sample output weights, W_i^T W_i = R^-1 on the measured rows (0 elsewhere)
        WY = ca.SX.sym("WY", ny * ny, w)
        Ws = [ca.reshape(WY[:, i], ny, ny) for i in range(w)]
        sign = 1.0 if self.direction == "forward" else -1.0
        F = self._stepper(sign)
        # states at every step from the optimised one, and at the buffer times
        # (oldest first); backward propagation uses the inputs in reverse order
        traj = [x0]
        for k in range(steps):
            uk = U[:, k] if self.direction == "forward" else U[:, steps - 1 - k]
            traj.append(F(traj[-1], uk, p))
        if self.direction == "backward":
            traj = traj[::-1]
        xs = traj[::n]
        # the input at each sample: held, the one that acted just before it; sampled,
        # the end of the transition into it (the start of the first for the first)
        def u_at(i):
            if nu == 0 or steps == 0:
                return ca.SX.zeros(nu, 1)
            k = min(max(i * n - 1, 0), steps - 1)
            if m.sampled:
                return U[:nu, 0] if i * n == 0 else U[nu:, k]
            return U[:, k]
        yhat = ca.horzcat(*[m.H(xs[i], u_at(i), p) for i in range(w)])
        E = Y - yhat
        cost = sum(ca.sumsqr(Ws[i] @ E[:, i]) for i in range(w))
        if m.continuous:
            ydot = ca.horzcat(*[m.H_x(xs[i], u_at(i), p) @ m.f_c(xs[i], u_at(i), p)
                                for i in range(w)])
            Ed = Yd - ydot
            cost_d = sum(ca.sumsqr(Ws[i] @ Ed[:, i]) for i in range(w))
        else:
            cost_d = ca.SX(0)
        prior = ca.sumsqr(Wp @ (x0 - xbar))
        J = cost + W2 * cost_d + prior
        args = [x0, U, Y, Yd, W2, xbar, ca.vec(Wp), WY]
        self._J = FastFunction(ca.Function("J", args, [J, ca.gradient(J, x0)]))
        self._terms = FastFunction(ca.Function("terms", args, [cost, cost_d]))
        # gradient of the terms outside report eqs. 1.8-1.10 (derivative term, prior)
        self._grad_other = FastFunction(ca.Function("grad_other", args, [
            ca.gradient(W2 * cost_d + prior, x0)]))
        sens = ca.jacobian(ca.vertcat(*[Ws[i] @ yhat[:, i] for i in range(w)]), x0)
        self._sens = FastFunction(ca.Function("sens", [x0, U, WY], [sens]))
        self._traj = FastFunction(ca.Function("traj", [x0, U], [ca.horzcat(*traj)]))
        if self.method == "gradient":
            self._build_sensitivity_gradient(sign, steps, U, Y, Ws, p, args, u_at)
        if self.method == "ipopt":
            nlp = {"x": x0, "p": ca.vertcat(*[ca.vec(a) for a in args[1:]]), "f": J}
            try:
                self._ipopt = ca.nlpsol("shooting_ipopt", "ipopt", nlp, {
                    "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
                    "ipopt.max_iter": self.max_iter, "ipopt.tol": 1e-10})
            except (RuntimeError, NotImplementedError) as exc:
                raise ValueError(f"method='ipopt': CasADi refused to build the solver "
                                 f"(max_iter={self.max_iter}): {_casadi_reason(exc)}") from None

    def _stepper(self, sign: float):
        """One sample of the dynamics, forward or backward in time."""
        m = self.model
        if not m.continuous:
            return m.F
        x, w = ca.SX.sym("x", m.nx), ca.SX.sym("w", m.nw)
        p = ca.SX.sym("p", m.p.size)
        step = rk4_step if m.integrator != "euler" else euler_step
        xn = step(m.f_c, x, m.input_path(w, reverse=sign < 0), p, sign * m.dt, m.substeps)
        return ca.Function("F_dir", [x, w, p], [xn])

    def _build_sensitivity_gradient(self, sign, steps, U, Y, Ws, p, args, u_at) -> None:
        r"""Gradient of the output term by the forward sensitivity equations.

        The pair :math:`(\xi_1, \xi_2)` with :math:`\dot\xi_1 = f(\xi_1)`,
        :math:`\dot\xi_2 = \partial f/\partial x\, \xi_2`, :math:`\xi_2(0) = I`
        is integrated with the same RK4 step as the state (report eqs.
        1.8-1.10), then :math:`\partial J/\partial\xi_0 = -2\sum_i E_i^\top
        W_i^\top W_i\, \partial h/\partial x\, \xi_2(t_i)` (:math:`W_i^\top W_i = R^{-1}`
        on the measured rows).
        """
        m, nx, n, w = self.model, self.model.nx, self.every, self.window
        if self.direction != "forward":
            raise ValueError("method='gradient' is implemented for direction='forward'")
        xi = ca.SX.sym("xi", nx + nx * nx)
        u = ca.SX.sym("u", m.nw)
        pp = ca.SX.sym("p", m.p.size)

        if m.continuous:
            xs_, us_, ps_ = ca.SX.sym("x", nx), ca.SX.sym("u", m.nu), ca.SX.sym("p", m.p.size)
            f_x = ca.Function("f_x", [xs_, us_, ps_],
                              [ca.jacobian(m.f_c(xs_, us_, ps_), xs_)])

        def aug(z, uu, q):  # (xi_1, xi_2) of report eq. 1.10
            x1 = z[:nx]
            X2 = ca.reshape(z[nx:], nx, nx)
            return ca.vertcat(m.f_c(x1, uu, q), ca.vec(f_x(x1, uu, q) @ X2))

        if m.continuous:
            step = rk4_step if m.integrator != "euler" else euler_step
            zn = step(aug, xi, m.input_path(u), pp, sign * m.dt, m.substeps)
        else:  # discrete model: the sensitivity map is the Jacobian of F
            x1 = xi[:nx]
            X2 = ca.reshape(xi[nx:], nx, nx)
            zn = ca.vertcat(m.F(x1, u, pp), ca.vec(m.F_x(x1, u, pp) @ X2))
        Fz = ca.Function("F_sens", [xi, u, pp], [zn])
        x0 = args[0]
        z = ca.vertcat(x0, ca.vec(ca.DM.eye(nx)))
        zs = [z]
        for k in range(steps):
            z = Fz(z, U[:, k], p)
            if (k + 1) % n == 0:
                zs.append(z)
        grad = ca.SX.zeros(nx, 1)
        for i in range(w):
            ui = u_at(i)
            xi_i = zs[i][:nx]
            Phi = ca.reshape(zs[i][nx:], nx, nx)
            e = Y[:, i] - m.H(xi_i, ui, p)
            grad += -2 * (m.H_x(xi_i, ui, p) @ Phi).T @ (Ws[i].T @ (Ws[i] @ e))
        self._grad_sens = FastFunction(ca.Function("grad_sens", args[:3] + [args[-1]], [grad]))

    # ------------------------------------------------------------------ state
    def _reset(self) -> None:
        keep = self._span + self.derivative_samples + 1
        self._ys: deque = deque(maxlen=keep)       # every sample's y
        self._us: deque = deque(maxlen=keep)       # input acting after each sample
        self._xs: deque = deque(maxlen=self._span + 1)  # estimates, oldest first
        self._x = self.x0.copy()                   # estimate at the current time
        self._w2 = self._fixed_w2
        self.history: deque = deque(maxlen=self.history_length)

    # ------------------------------------------------------------------- step
    def _step(self, y, u, first):
        t0 = time.perf_counter()
        failure = None
        if not first:
            w = self._transition(u)
            self._us.append(w.copy())
            x = self._F(self._x, w, self.model.p)[0]  # open-loop propagation
            if np.isfinite(x).all():
                self._x = x.copy()
            else:  # re-anchor on the last estimate, projected on the bounds
                self._x = self._anchor(self._x)[0]
                failure = "failed: non-finite prediction F(x, u); re-anchored on the last estimate"
        self._ys.append(y.copy())
        self._xs.append(self._x.copy())
        k = self._k  # index of this sample (Estimator increments after the step)
        ready = k >= self._span and k % self.every == 0 and np.isfinite(y).any()
        if not ready:
            return self._x.copy(), StepInfo(
                status=failure or "ok", success=failure is None,
                solve_time=time.perf_counter() - t0, extra={"optimised": False})
        x, info = self._optimise(t0)
        if failure is not None:
            info.__dict__.update(status=failure + f" ({info.status})", success=False)
        return x, info

    def _window_data(self):
        """Buffer samples Y (ny, w) (0 where missing), derivatives Yd, inputs U (nu, span),
        oldest first, and the output weights WY (ny * ny, w) (zero rows where missing)."""
        ys = np.array(self._ys)
        n, w, span = self.every, self.window, self._span
        idx = [len(ys) - 1 - span + i * n for i in range(w)]
        Y = ys[idx].T
        WY = measurement_weights(np.isfinite(Y.T), self.R, self._WR)  # (w, ny, ny)
        WY = WY.transpose(1, 2, 0).reshape(-1, w, order="F")
        self._measured = int(np.isfinite(Y).sum())  # outputs in the window
        Y = np.where(np.isfinite(Y), Y, 0.0)
        Yd = np.zeros_like(Y)
        ms = self.derivative_samples
        for c, j in enumerate(idx):
            lo = j - ms + 1
            if lo >= 0 and np.isfinite(ys[lo:j + 1]).all():
                Yd[:, c] = derivative_filter(ys[lo:j + 1], self.model.dt)
            else:
                Yd[:, c] = np.nan
        us = np.array(self._us).reshape(len(self._us), self.model.nw)
        U = us[len(us) - span:].T if span else np.zeros((self.model.nw, 1))
        if U.shape[1] == 0:
            U = np.zeros((self.model.nw, 1))
        return Y, Yd, U, WY

    def _optimise(self, t0):
        m, nx = self.model, self.model.nx
        Y, Yd, U, WY = self._window_data()
        use_d = m.continuous and self._w2 != 0 and np.isfinite(Yd).all()
        Yd = np.where(np.isfinite(Yd), Yd, 0.0)
        # warm start: the propagated previous estimate at the optimised time
        forward = self.direction == "forward"
        start = self._xs[0].copy() if forward else self._x.copy()
        if self._w2 is None and use_d:  # set on the first window with derivatives
            self._w2 = self._balanced_weight(start, U, Y, Yd, WY)
        w2 = self._w2 if use_d and self._w2 else 0.0
        Wp = np.zeros((nx, nx)) if self.P0 is None else np.linalg.cholesky(
            np.linalg.inv(self.P0)).T
        args = (U, Y, Yd, w2, start, Wp.ravel(order="F"), WY)
        x_opt, cost, iters, ok, status = self._minimise(start, args)
        if ok:  # the whole window re-propagated from the optimum
            traj = self._traj(x_opt, U)[0].reshape(nx, -1, order="F").T
            if np.isfinite(traj).all():
                self._xs = deque((row.copy() for row in traj), maxlen=self._span + 1)
                self._x = traj[-1].copy()
            else:  # keep the propagated previous estimate
                ok, status = False, "non-finite propagation from the optimum"
        anchor = x_opt if ok else start
        if ok:  # the output term is chi-square in the noise: flag what the data contradict
            check = consistency_status(float(self._terms(x_opt, *args)[0][0]), self._measured,
                                       "output cost")
            if check != "ok":
                status = check if status == "ok" else f"{status}; {check}"
        # relative sensitivity (columns scaled by |xi|): states span many decades
        scale = np.maximum(np.abs(anchor), 1e-3 * max(float(np.abs(anchor).max()), 1e-300))
        S = self._sens(anchor, U, WY)[0].reshape(-1, nx, order="F") * scale
        if np.isfinite(S).all():
            sv = np.linalg.svd(S, compute_uv=False)
            cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
        else:
            sv, cond = np.full(min(S.shape), np.nan), float("inf")
        elapsed = time.perf_counter() - t0
        self.history.append({"k": self._k, "condition": cond, "cost": cost,
                             "iterations": iters, "solve_time": elapsed, "success": ok,
                             "derivative_weight": w2})
        return self._x.copy(), StepInfo(
            status=status if ok else f"failed: {status}", success=ok, iterations=iters,
            solve_time=elapsed, cost=cost,
            extra={"optimised": True, "singular_values": sv, "condition": cond,
                   "derivative_weight": w2, "window_start": anchor.copy()})

    def _balanced_weight(self, start, U, Y, Yd, WY) -> float:
        """W2/W1 making both terms equal at the starting point (report sec. 1.2.1)."""
        Wp = np.zeros(self.model.nx ** 2)
        c1, c2 = (float(v[0]) for v in self._terms(start, U, Y, Yd, 1.0, start, Wp, WY))
        if not (np.isfinite(c1) and np.isfinite(c2)) or c2 <= 0 or c1 <= 0:
            return 0.0
        return c1 / c2

    def _hessian(self, start, args) -> np.ndarray | None:
        """Gauss-Newton Hessian of the output term (and prior) at ``start``."""
        nx = self.model.nx
        S = self._sens(start, args[0], args[-1])[0].reshape(-1, nx, order="F")
        with np.errstate(over="ignore", invalid="ignore"):  # not finite: None
            H = 2.0 * S.T @ S
        if self.P0 is not None:
            H += 2.0 * np.linalg.inv(self.P0)
        return H if np.isfinite(H).all() else None

    def _scales(self, H, start, g) -> np.ndarray:
        r"""The magnitude :math:`D_i` of each component, to which ``resolution`` is relative.

        Where the start (the propagated previous estimate) carries a magnitude, it is that
        one: :math:`D_i = \max(|\xi_{0,i}|,\ 10^{-3} \max_j |\xi_{0,j}|,\ \sqrt{P_{0,ii}})`
        -- the start, floored at 1e-3 of its largest component (a tiny state next to large
        ones is not asked for a relative precision it cannot have), and the prior's
        standard deviation where ``P0`` is given (the user's own scale of the component).

        A start carries no magnitude when it lies within its own standard error of zero,
        :math:`D_i^2 H_{ii} < 2` (a guess of 0, or a value the window cannot tell from 0):
        a relative precision of it would be meaningless, and the old scale (the 1e-3
        floor, or 0) dropped such a component whatever the window held. Its magnitude is
        then the one the window itself gives it, :math:`|\xi^{GN}_i|` with
        :math:`\xi^{GN} = \xi_0 - H^{+} g` the window's Gauss-Newton estimate (the
        Jacobi-scaled pseudo-inverse of the Gauss-Newton Hessian :math:`H` applied to the
        gradient :math:`g` at the start), provided the window determines it to the
        resolution there: :math:`\sigma_i \le` ``resolution`` :math:`|\xi^{GN}_i|`, with
        :math:`\sigma_i = \sqrt{2 (H^{+})_{ii}}` its marginal standard error. The
        component is then judged as it would be from a start at that value; one the window
        does not determine (its estimate is noise, :math:`|\xi^{GN}_i| \sim \sigma_i`)
        keeps the small scale, and so its start. Other absolute scales were rejected:
        :math:`1/\sqrt{H_{ii}}` makes every relative error about 1 whatever the window
        holds, and bounds give a range, not a magnitude. With a non-finite ``g`` the
        start's scale is returned.
        """
        D = np.abs(start)
        D = np.maximum(D, 1e-3 * float(D.max()))
        if self.P0 is not None:
            D = np.maximum(D, np.sqrt(np.diag(self.P0)))
        if not np.isfinite(g).all():
            return D
        h = np.maximum(np.diag(H), 0.0)
        tiny = D * D * h < 2.0  # the start is within its own standard error of 0
        seen = h > 0
        if not (tiny & seen).any():
            return D
        s = np.sqrt(h[seen])
        Hs_inv = np.linalg.pinv(H[np.ix_(seen, seen)] / np.outer(s, s), rcond=1e-12,
                                hermitian=True)
        step, sigma = np.zeros_like(start), np.full_like(start, np.inf)
        step[seen] = -(Hs_inv @ (g[seen] / s)) / s
        sigma[seen] = np.sqrt(2.0 * np.maximum(np.diag(Hs_inv), 0.0)) / s
        target = np.abs(start + step)
        use = tiny & np.isfinite(target)
        if self.resolution is not None:
            use &= sigma <= self.resolution * target
        D[use] = np.maximum(D[use], target[use])
        return D

    def _subspace(self, H, start, g):
        r"""Coordinates ``xi = start + T z`` spanning the directions this window determines.

        In relative coordinates (``xi_i = start_i + D_i e_i``, with the magnitudes
        :math:`D_i` of :meth:`_scales`) the Gauss-Newton Hessian is
        :math:`H_r = D H D = V \Lambda V^\top`; as the weighted residuals have unit
        noise, eigen-direction :math:`i` is determined to the relative standard
        error :math:`\sqrt{2/\lambda_i}`. Directions known better than
        ``resolution`` span the optimisation, with :math:`T = D V_r
        \Lambda_r^{-1/2}` so the Hessian in ``z`` is the identity; the others
        keep the warm start (the propagated previous estimate). With ``resolution=None``
        every direction the Hessian resolves numerically is kept. Returns an
        ``(nx, 0)`` matrix when the window determines nothing.
        """
        nx = self.model.nx
        if H is None:
            return np.zeros((nx, 0))
        D = self._scales(H, start, g)
        Hr = H * np.outer(D, D)
        lam, V = np.linalg.eigh(0.5 * (Hr + Hr.T))
        if self.resolution is None:
            keep = lam > nx * np.finfo(float).eps * max(float(lam.max()), 0.0)
        else:
            keep = lam >= 2.0 / self.resolution**2
        return (D[:, None] * V[:, keep]) / np.sqrt(lam[keep])

    @property
    def _undetermined(self) -> str:
        """Why the subspace methods leave a direction out (for the status)."""
        if self.resolution is None:
            return "not determined numerically"
        return f"not determined to the resolution {self.resolution:g}"

    def _minimise(self, start, args):
        """Run the chosen method; returns ``(x, cost, iterations, ok, status)``.

        ``ok`` with status ``"ok"``: converged; with ``"inexact: ..."``: not converged
        (see :meth:`_run_method`) at a finite point no worse than ``start``, which is
        used; not ``ok`` (status without prefix, ``"failed: "`` is added by the caller):
        nothing usable.
        """
        self._start_cost = None  # set by the methods that evaluate it anyway
        x, cost, iters, converged, message = self._run_method(start, args)
        finite = bool(np.isfinite(x).all() and np.isfinite(cost))
        if finite and converged:
            return x, cost, iters, True, "ok"
        if self._start_cost is None:
            self._start_cost = float(self._J(start, *args)[0][0])
        if finite and not cost > self._start_cost:
            return x, cost, iters, True, f"inexact: {message}"
        if not finite:
            message = f"non-finite cost at the method's point ({message})"
        return x, cost, iters, False, message

    def _run_method(self, start, args):
        """The chosen method from ``start``: ``(x, cost, iterations, converged, message)``.

        ``converged`` only when the method's own convergence test passed (the gradient test
        for BFGS and L-BFGS-B, Ipopt's ``Solve_Succeeded``, the simplex's tolerances) and,
        for the subspace methods, no direction was left out; ``message`` says why not.
        """
        if self.method == "gradient":
            return self._gradient_descent(start, args)
        gtol = np.sqrt(2.0 * self.tol)
        H = None if self.method == "ipopt" else self._hessian(start, args)  # ipopt: its own
        n = len(start)
        try:
            if self.method == "ipopt":
                pvec = np.concatenate([np.ravel(a, order="F") for a in args])
                sol = self._ipopt(x0=np.clip(start, self.lower, self.upper), p=pvec,
                                  lbx=self.lower, ubx=self.upper)
                st = self._ipopt.stats()
                x = np.asarray(sol["x"]).ravel()
                converged = st["return_status"] == "Solve_Succeeded"
                return x, float(sol["f"]), int(st["iter_count"]), converged, st["return_status"]
            cost = _Cost(start, self._J, args)
            self._start_cost = cost.J0
            if self.method == "lbfgsb":
                # diagonal Gauss-Newton scaling keeps the bounds as boxes
                diag = np.ones(n) if H is None else np.diag(H)
                T = np.diag(1.0 / np.sqrt(diag + 1e-9 * max(float(diag.max()), 1e-300)))
                lo, up = (self.lower - start) / np.diag(T), (self.upper - start) / np.diag(T)
                res = scipy_minimize(lambda z: cost(z, T), np.zeros(n), jac=True,
                                     method="L-BFGS-B", bounds=list(zip(lo, up, strict=True)),
                                     options={"maxiter": self.max_iter, "gtol": gtol,
                                              "ftol": 0.0})
                # converged: the projected (scaled) gradient passes the gradient test; L-BFGS-B
                # also stops when the cost no longer decreases (ftol=0) or its line search fails
                z = np.clip(res.x, lo, up)
                pg = np.clip(z - res.jac, lo, up) - z
                converged = bool(np.isfinite(pg).all() and np.abs(pg).max() <= gtol)
                why = "converged" if converged else (
                    f"max_iter ({self.max_iter}) reached" if res.status == 1 else
                    f"line search stalled before the gradient test ({str(res.message).strip()})")
                x = np.clip(start + T @ z, self.lower, self.upper)
                return x, float(res.fun), int(res.nit), converged, why
            T = self._subspace(H, start, cost.g0)
            kept = T.shape[1]
            if kept == 0:  # nothing determined to the resolution: keep the start
                return (start, cost.J0, 0, False,
                        f"no direction {self._undetermined[4:]} (0 of {n})")
            z0 = np.zeros(kept)
            if self.method == "bfgs":
                res = scipy_minimize(lambda z: cost(z, T), z0, jac=True,
                                     method="BFGS",
                                     options={"maxiter": self.max_iter, "gtol": gtol})
                # scipy's BFGS stops with status 0 only on its gradient test; 1: max_iter,
                # 2: precision loss (the line search found no decrease) before it
                converged = res.status == 0
                why = {1: f"max_iter ({self.max_iter}) reached",
                       2: "line search stalled (precision loss) before the gradient test"
                       }.get(res.status, str(res.message).strip())
            else:
                res = scipy_minimize(lambda z: cost(z, T)[0], z0, method="Nelder-Mead",
                                     options={"maxiter": self.max_iter * n,
                                              "xatol": 1e-3 * gtol, "fatol": self.tol})
                converged = res.status == 0
                why = f"{str(res.message).strip()} (max_iter {self.max_iter} per variable)"
            if kept < n:  # optimal in the subspace at best
                out = f"{n - kept} of {n} directions left out ({self._undetermined})"
                why = out if converged else f"{why}; {out}"
                converged = False
            return start + T @ res.x, float(res.fun), int(res.nit), converged, why
        except (ValueError, RuntimeError, np.linalg.LinAlgError) as exc:
            return start, float("nan"), 0, False, str(exc)[:120]

    def _gradient_descent(self, start, args):
        """Report eq. 1.11 with an Armijo backtracking step size."""
        U, Y = args[0], args[1]
        x = start.copy()
        J = float(self._J(x, *args)[0][0])
        alpha = 1.0
        for it in range(1, self.max_iter + 1):
            g = self._grad_sens(x, U, Y, args[-1])[0] + self._grad_other(x, *args)[0]
            if not np.isfinite(g).all():
                return x, J, it, False, "non-finite gradient"
            gg = float(g @ g)
            if gg <= 1e-30 * max(J, 1e-300):
                return x, J, it, True, "gradient vanished"
            while alpha > 1e-30:
                xn = x - alpha * g
                Jn = float(self._J(xn, *args)[0][0])
                if np.isfinite(Jn) and Jn <= J - 1e-4 * alpha * gg:
                    break
                alpha *= 0.5
            else:
                return x, J, it, False, "line search stalled (step below 1e-30)"
            converged = abs(J - Jn) <= 1e-12 * max(abs(J), 1e-300)
            x, J = xn, Jn
            alpha *= 2.0
            if converged:
                return x, J, it, True, "converged"
        return x, J, self.max_iter, False, f"max_iter ({self.max_iter}) reached"
