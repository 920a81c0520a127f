r"""The single-shooting problem of the :class:`~estim.ShootingObserver`.

The buffer holds ``w`` samples taken every ``N_Ts`` steps. The optimised (augmented)
state :math:`\hat\xi_0`, at the window's start (``direction="forward"``) or at its end
(``"backward"``), is propagated by the model to every buffer time, and the cost

.. math::
    J(\hat\xi_0) = \sum_{i=1}^{w} \|Y_i - h(\hat\xi_i)\|^2_{R^{-1}}
                 + W_2 \|\dot Y_i - \tfrac{d}{dt} h(\hat\xi_i)\|^2_{R^{-1}}
                 + \|\hat\xi_0 - \bar\xi\|^2_{P_0^{-1}}

compares the predicted outputs with the buffer (:func:`window_data`: the samples, the
output derivatives :math:`\dot Y_i` by :func:`derivative_filter` and the weights of the
measured rows); :math:`\frac{d}{dt}h = \frac{\partial h}{\partial x} f(x, u)` is the
model's exact output derivative. :func:`build_problem` builds the cost, its gradient, the
output sensitivity and the trajectory as CasADi Functions once; the buffer's values,
the weights and :math:`W_2` are their data.

References
----------
F. Oliva, D. Carnevale, "Optimisation based observer", report, 2020;
H. K. Khalil, *Nonlinear Systems*, 3rd ed., 2002 (sensitivity equations).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import casadi as ca
import numpy as np

from estim._fast import FastFunction
from estim.model import Model, euler_step, rk4_step
from estim.solvers.least_squares.options import casadi_reason
from estim.solvers.weights import measurement_weights


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


@dataclass(frozen=True)
class ShootingFunctions:
    r"""The compiled shooting problem of :func:`build_problem`.

    The Functions with the window's data take ``(xi0, U, Y, Yd, W2, xbar, vec(Wp), WY)``:
    the optimised state ``(nx,)``, the transitions' inputs ``(nw, span)``, the samples
    and their derivatives ``(ny, w)``, the derivative weight, the prior's mean and
    weight factor (:math:`W_p^\top W_p = P_0^{-1}`) and the per-sample output weight
    factors ``(ny * ny, w)`` (:math:`W_i^\top W_i = R^{-1}` on the measured rows).

    Attributes
    ----------
    J : FastFunction
        The cost and its gradient in ``xi0``.
    terms : FastFunction
        The output term and the (unweighted) derivative term.
    grad_other : FastFunction
        The gradient of the derivative term (weighted) and the prior.
    sens : FastFunction
        ``(xi0, U, WY) ->`` the weighted output sensitivity
        :math:`\partial (W_i \hat y_i)_{i} / \partial \xi_0`, ``(w ny, nx)``.
    traj : FastFunction
        ``(xi0, U) ->`` the state at every step of the window ``(nx, span + 1)``,
        oldest first.
    grad_sens : FastFunction or None
        ``method="gradient"``: ``(xi0, U, Y, WY) ->`` the output term's gradient by the
        forward sensitivity equations.
    ipopt : casadi.Function or None
        ``method="ipopt"``: the bounded problem's Ipopt solver (the data concatenated,
        column-major, as its parameter).
    """

    J: FastFunction
    terms: FastFunction
    grad_other: FastFunction
    sens: FastFunction
    traj: FastFunction
    grad_sens: FastFunction | None = None
    ipopt: ca.Function | None = None


def build_problem(model: Model, window: int, every: int, direction: str, method: str,
                  max_iter: int) -> ShootingFunctions:
    """Cost, gradient and sensitivity Functions of the shooting problem.

    Parameters
    ----------
    model : Model
    window, every : int
        ``w`` samples in the buffer, ``N_Ts`` steps apart.
    direction : {"forward", "backward"}
        Propagate from the window's first sample or back from its last.
    method : str
        The observer's method: ``"gradient"`` also builds the sensitivity equations'
        gradient, ``"ipopt"`` the Ipopt solver (with ``max_iter``).
    """
    m, w, n = model, window, every
    nx, nu, ny = m.nx, m.nu, m.ny
    p = ca.DM(m.p)
    steps = (window - 1) * every
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
    sign = 1.0 if direction == "forward" else -1.0
    F = _stepper(m, sign)
    # states at every step from the optimised one, and at the buffer times
    # (oldest first); backward propagation uses the inputs in reverse order
    traj = [x0]
    for k in range(steps):
        uk = U[:, k] if direction == "forward" else U[:, steps - 1 - k]
        traj.append(F(traj[-1], uk, p))
    if direction == "backward":
        traj = traj[::-1]
    xs = traj[::n]

    # the input at each sample: held, the one that acted just before it; sampled,
    # the end of the transition into it (the start of the first for the first)
    def u_at(i: int) -> ca.SX:
        if nu == 0 or steps == 0:
            return ca.SX.zeros(nu, 1)
        k = min(max(i * n - 1, 0), steps - 1)
        if m.sampled:
            return U[:nu, 0] if i * n == 0 else U[nu:, k]
        return U[:, k]

    yhat = ca.horzcat(*[m.H(xs[i], u_at(i), p) for i in range(w)])
    E = Y - yhat
    cost = sum(ca.sumsqr(Ws[i] @ E[:, i]) for i in range(w))
    f_c = m.f_c
    if f_c is not None:  # a continuous model: the outputs' derivatives dh/dx f
        ydot = ca.horzcat(*[m.H_x(xs[i], u_at(i), p) @ f_c(xs[i], u_at(i), p)
                            for i in range(w)])
        Ed = Yd - ydot
        cost_d = sum(ca.sumsqr(Ws[i] @ Ed[:, i]) for i in range(w))
    else:
        cost_d = ca.SX(0)
    prior = ca.sumsqr(Wp @ (x0 - xbar))
    J = cost + W2 * cost_d + prior
    args = [x0, U, Y, Yd, W2, xbar, ca.vec(Wp), WY]
    sens = ca.jacobian(ca.vertcat(*[Ws[i] @ yhat[:, i] for i in range(w)]), x0)
    grad_sens = None
    if method == "gradient":
        if direction != "forward":
            raise ValueError("method='gradient' is implemented for direction='forward'")
        grad_sens = _sensitivity_gradient(m, every, window, sign, steps, U, Y, Ws, p, args,
                                          u_at)
    ipopt = None
    if method == "ipopt":
        nlp = {"x": x0, "p": ca.vertcat(*[ca.vec(a) for a in args[1:]]), "f": J}
        try:
            ipopt = ca.nlpsol("shooting_ipopt", "ipopt", nlp, {
                "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
                "ipopt.max_iter": max_iter, "ipopt.tol": 1e-10})
        except (RuntimeError, NotImplementedError) as exc:
            raise ValueError(f"method='ipopt': CasADi refused to build the solver "
                             f"(max_iter={max_iter}): {casadi_reason(exc)}") from None
    return ShootingFunctions(
        J=FastFunction(ca.Function("J", args, [J, ca.gradient(J, x0)])),
        terms=FastFunction(ca.Function("terms", args, [cost, cost_d])),
        # gradient of the terms outside report eqs. 1.8-1.10 (derivative term, prior)
        grad_other=FastFunction(ca.Function("grad_other", args, [
            ca.gradient(W2 * cost_d + prior, x0)])),
        sens=FastFunction(ca.Function("sens", [x0, U, WY], [sens])),
        traj=FastFunction(ca.Function("traj", [x0, U], [ca.horzcat(*traj)])),
        grad_sens=grad_sens, ipopt=ipopt)


def _stepper(m: Model, sign: float) -> ca.Function:
    """One sample of the dynamics, forward or backward in time."""
    f_c = m.f_c
    if f_c is None:  # a discrete model
        return m.F
    x, w = ca.SX.sym("x", m.nx), ca.SX.sym("w", m.nw)
    p = ca.SX.sym("p", m.p.size)
    step = rk4_step if m.integrator != "euler" else euler_step
    xn = step(f_c, x, m.input_path(w, reverse=sign < 0), p, sign * m.dt, m.substeps)
    return ca.Function("F_dir", [x, w, p], [xn])


def _sensitivity_gradient(m: Model, n: int, w: int, sign: float, steps: int, U: ca.SX,
                          Y: ca.SX, Ws: Sequence[ca.SX], p: ca.DM, args: list,
                          u_at: Callable[[int], ca.SX]) -> FastFunction:
    r"""Gradient of the output term by the forward sensitivity equations.

    The pair :math:`(\xi_1, \xi_2)` with :math:`\dot\xi_1 = f(\xi_1)`,
    :math:`\dot\xi_2 = \partial f/\partial x\, \xi_2`, :math:`\xi_2(0) = I`
    is integrated with the same RK4 step as the state (report eqs.
    1.8-1.10), then :math:`\partial J/\partial\xi_0 = -2\sum_i E_i^\top
    W_i^\top W_i\, \partial h/\partial x\, \xi_2(t_i)` (:math:`W_i^\top W_i = R^{-1}`
    on the measured rows).
    """
    nx = m.nx
    xi = ca.SX.sym("xi", nx + nx * nx)
    u = ca.SX.sym("u", m.nw)
    pp = ca.SX.sym("p", m.p.size)

    f_c = m.f_c
    if f_c is not None:  # a continuous model: integrate the pair
        xs_, us_, ps_ = ca.SX.sym("x", nx), ca.SX.sym("u", m.nu), ca.SX.sym("p", m.p.size)
        f_x = ca.Function("f_x", [xs_, us_, ps_],
                          [ca.jacobian(f_c(xs_, us_, ps_), xs_)])

        def aug(z, uu, q):  # (xi_1, xi_2) of report eq. 1.10
            x1 = z[:nx]
            X2 = ca.reshape(z[nx:], nx, nx)
            return ca.vertcat(f_c(x1, uu, q), ca.vec(f_x(x1, uu, q) @ X2))

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
    return FastFunction(ca.Function("grad_sens", args[:3] + [args[-1]], [grad]))


def window_data(ys: np.ndarray, us: np.ndarray, model: Model, window: int, every: int,
                derivative_samples: int, R: np.ndarray, WR: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    r"""The data of the window ending at the newest sample.

    Parameters
    ----------
    ys : (K, ny) array
        Every sample's measurement, oldest first (NaN where missing), at least the
        window's span and as many before it as the differentiator can use.
    us : (K - 1, nw) array
        The transitions' inputs, oldest first.
    model : Model
    window, every, derivative_samples : int
    R, WR : (ny, ny) arrays
        The output covariance and its weight factor (:math:`W^\top W = R^{-1}`).

    Returns
    -------
    Y, Yd : (ny, w) arrays
        The buffer's samples (0 where missing) and their derivatives
        (:func:`derivative_filter`; NaN where the samples before are too few or missing).
    U : (nw, span) array
        The transitions' inputs over the window (a zero column for a window of one).
    WY : (ny * ny, w) array
        The output weight factors of the samples (zero rows where missing).
    measured : int
        The number of measured outputs in the window.
    """
    n, w, span = every, window, (window - 1) * every
    idx = [len(ys) - 1 - span + i * n for i in range(w)]
    Y = ys[idx].T
    WY = measurement_weights(np.isfinite(Y.T), R, WR)  # (w, ny, ny)
    WY = WY.transpose(1, 2, 0).reshape(-1, w, order="F")
    measured = int(np.isfinite(Y).sum())  # outputs in the window
    Y = np.where(np.isfinite(Y), Y, 0.0)
    Yd = np.zeros_like(Y)
    ms = derivative_samples
    for c, j in enumerate(idx):
        lo = j - ms + 1
        if lo >= 0 and np.isfinite(ys[lo:j + 1]).all():
            Yd[:, c] = derivative_filter(ys[lo:j + 1], model.dt)
        else:
            Yd[:, c] = np.nan
    U = us[len(us) - span:].T if span else np.zeros((model.nw, 1))
    if U.shape[1] == 0:
        U = np.zeros((model.nw, 1))
    return Y, Yd, U, WY, measured


def balanced_weight(terms: FastFunction, start: np.ndarray, U: np.ndarray, Y: np.ndarray,
                    Yd: np.ndarray, WY: np.ndarray) -> float:
    """:math:`W_2/W_1` making the output and derivative terms equal at ``start`` (report
    sec. 1.2.1); 0 where either is not positive and finite."""
    Wp = np.zeros(start.size ** 2)
    c1, c2 = (float(v[0]) for v in terms(start, U, Y, Yd, 1.0, start, Wp, WY))
    if not (np.isfinite(c1) and np.isfinite(c2)) or c2 <= 0 or c1 <= 0:
        return 0.0
    return c1 / c2
