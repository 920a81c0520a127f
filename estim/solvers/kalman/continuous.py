r"""Process noise in continuous time: a spectral density :math:`Q_c` entering through a
noise input matrix :math:`L`,

.. math::
    dx = f(x, u)\,dt + L\, d\beta, \qquad E[d\beta\, d\beta^\top] = Q_c\, dt,

so that the noise a transition receives grows with its interval, where a per-transition
covariance ``Q`` is the same for 1 ms and for 1 s. Two ways to carry a Gaussian over an
interval :math:`\Delta t` (Särkkä & Svensson, *Bayesian Filtering and Smoothing*, 2nd ed.,
2023, ch. 10):

* **The exact discretisation of a linear (or linearised) model**
  (:func:`van_loan`): :math:`\Phi = e^{A \Delta t}` and
  :math:`Q_d(\Delta t) = \int_0^{\Delta t} e^{A\tau} W e^{A^\top \tau}\, d\tau`,
  :math:`W = L Q_c L^\top`, from one matrix exponential (Van Loan 1978).
* **The moment equations integrated beside the mean** (:func:`moment_step`,
  :func:`sigma_moment_step`): for the extended filter
  :math:`\dot m = f(m, u)`, :math:`\dot P = A P + P A^\top + W` with
  :math:`A = \partial f / \partial x` at :math:`m`; for the sigma-point filter
  (Särkkä 2007) :math:`\dot m = \sum_i W^m_i f(\mathcal X_i)`,
  :math:`\dot P = \sum_i W^c_i \left[(\mathcal X_i - m)(f_i - \bar f)^\top +
  (f_i - \bar f)(\mathcal X_i - m)^\top\right] + W`, the sigma points :math:`\mathcal X_i`
  drawn from :math:`(m, P)` at every stage; both by classic Runge-Kutta sub-steps, in
  CasADi expressions (one compiled step, no Python per step).

On a linear model :math:`\dot P` is a polynomial of degree 3 in time when :math:`A` is
nilpotent (the Wiener velocity), which Runge-Kutta integrates exactly; otherwise the
sub-steps' error is that of RK4.

References
----------
C. F. Van Loan, "Computing integrals involving the matrix exponential", IEEE TAC 23(3),
1978; A. H. Jazwinski, *Stochastic Processes and Filtering Theory*, 1970;
S. Särkkä, "On unscented Kalman filtering for state estimation of continuous-time
nonlinear systems", IEEE TAC 52(9), 2007.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from typing import Any

import casadi as ca
import numpy as np

__all__ = ["DOUBLINGS", "discretised_noise", "discretised_noises", "drift_jacobian",
           "interval", "interval_weight", "moment_step", "noise_density", "sigma_moment_step",
           "sqrt_moment_step", "sqrt_sigma_moment_step", "van_loan"]

#: The squarings of :func:`van_loan`'s scaling: the exponent is taken of the matrix divided
#: by :math:`2^{32}`, then doubled back; with the Taylor series of degree
#: :data:`TAYLOR_DEGREE` this is exact to rounding for :math:`\|M \Delta t\|` up to about
#: :math:`10^8`.
DOUBLINGS = 32
TAYLOR_DEGREE = 8


def _exponential(X: Any, symbolic: bool) -> tuple[Any, Any]:
    r""":math:`(e^X - I,\ e^X)` by scaling and doubling, exact to rounding over a wide
    range of :math:`\|X\|`: the Taylor series of :math:`E = e^Y - I` at
    :math:`Y = X / 2^{D}` (``D`` = :data:`DOUBLINGS`), then ``D`` doublings. While the
    entries of :math:`E` are small they double as :math:`E \leftarrow 2E + E^2`
    (:math:`e^{2Y} - I`), which keeps their relative precision where squaring
    :math:`I + E` would lose it (an interval of 1e-3 on a slow model); once an entry
    passes 1/2 the matrix :math:`F = I + E` is squared instead, which keeps the precision of
    a decaying exponential that :math:`I + E` with :math:`E \to -I` would cancel (an
    interval of 10 time constants). The switch is per evaluation (``if_else`` in an
    expression). Returns both: the caller takes the form that does not cancel."""
    n = X.shape[0]
    eye = ca.DM.eye(n) if symbolic else np.eye(n)
    Y = X / 2.0 ** DOUBLINGS
    term, E = Y, Y
    for k in range(2, TAYLOR_DEGREE + 1):
        term = (term @ Y) / k
        E = E + term
    F, switched = eye + E, 0
    for _ in range(DOUBLINGS):
        if symbolic:
            E_next = 2 * E + E @ E
            big = ca.mmax(ca.fabs(E_next)) > 0.5
            F = ca.if_else(switched, F @ F, eye + E_next)
            E = ca.if_else(switched, E, E_next)
            switched = ca.logic_or(switched, big)
        elif switched:
            F = F @ F
        else:
            E = 2 * E + E @ E
            F = eye + E
            switched = np.abs(E).max() > 0.5
    if symbolic:
        return ca.if_else(switched, F - eye, E), F
    return (F - eye, F) if switched else (E, F)


def van_loan(A: Any, W: Any, dt: Any) -> tuple[Any, Any]:
    r"""The exact discretisation over ``dt`` of :math:`\dot x = A x + w`,
    :math:`E[w w^\top] = W \delta(t - s)`: :math:`\Phi = e^{A\,\Delta t}` and
    :math:`Q_d = \int_0^{\Delta t} e^{A\tau} W e^{A^\top\tau}\, d\tau`, from the exponential
    of :math:`M = \begin{bmatrix} -A & W \\ 0 & A^\top \end{bmatrix} \Delta t`,
    :math:`e^M = \begin{bmatrix} \cdot & G \\ 0 & \Phi^\top \end{bmatrix}`,
    :math:`Q_d = \Phi G` (Van Loan 1978). Works on numbers (numpy) and on CasADi
    expressions (``dt`` a symbol: a variable interval); :math:`Q_d` is symmetrised.

    Parameters
    ----------
    A : (n, n) array or expression
        The (linearised) drift.
    W : (n, n) array or expression
        :math:`L Q_c L^\top`, the noise's spectral density through its input matrix.
    dt : float or scalar expression
        The interval (positive).

    Returns
    -------
    Phi, Qd : (n, n)
    """
    symbolic = any(isinstance(v, (ca.SX, ca.MX)) for v in (A, W, dt))
    n = A.shape[0]
    if symbolic:
        Z = ca.SX(n, n) if not isinstance(A, ca.MX) else ca.MX(n, n)
        M = ca.vertcat(ca.horzcat(-A, W), ca.horzcat(Z, A.T)) * dt
    else:
        A, W = np.asarray(A, float), np.asarray(W, float)
        M = np.block([[-A, W], [np.zeros((n, n)), A.T]]) * float(dt)
    E, F = _exponential(M, symbolic)
    # Phi = F22^T, Q_d = Phi G with G = F12: from E (= F - I) while it is small, where
    # Phi G = G + E22^T G keeps G's digits, else from F itself
    G, Phi = F[:n, n:], F[n:, n:].T
    if symbolic:
        small = ca.mmax(ca.fabs(E[n:, n:])) <= 0.5
        Qd = ca.if_else(small, E[:n, n:] + E[n:, n:].T @ E[:n, n:], Phi @ G)
    else:
        Qd = E[:n, n:] + E[n:, n:].T @ E[:n, n:] if np.abs(E[n:, n:]).max() <= 0.5 \
            else Phi @ G
    return Phi, 0.5 * (Qd + Qd.T)


def interval(model: Any, w: Any) -> tuple[Any, Any]:
    """The input along a transition's interval (a callable of its fraction, or held) and
    the interval's length, from the transition's input ``w`` (the length its last entry
    with ``variable_dt``, else the model's ``dt``)."""
    if model.variable_dt:
        return model.input_path(w[:w.numel() - 1]), w[w.numel() - 1]
    return model.input_path(w), model.dt


def drift_jacobian(model: Any) -> ca.Function:
    """``(x, u, p) -> df/dx`` of a continuous model's right-hand side."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    p = ca.SX.sym("p", model.p.size)
    return ca.Function("f_x", [x, u, p], [ca.jacobian(model.f_c(x, u, p), x)])


def noise_density(model: Any, Q: Any, Qc: Any) -> tuple[Any, np.ndarray | None]:
    """``(the Q an estimator stores, Qc)``: ``Q`` itself, or with ``Qc`` (a spectral density
    per unit time) the density :math:`W = L Q_c L^\\top` it enters the states with, ``L``
    the model's ``noise_input`` (the identity without one). Checked: exactly one of the
    two, and ``Qc`` on a continuous model (``ode=``) on vector states."""
    from estim._validate import as_covariance

    if Qc is None:
        if Q is None:  # (a missing required argument, as Python says it)
            raise TypeError("missing the process noise: 'Q' (a covariance per transition) "
                            "or, for a continuous model, 'Qc' (a spectral density per unit "
                            "time)")
        return Q, None
    if Q is not None:
        raise ValueError("give Q= (per transition) or Qc= (a spectral density, per unit "
                         "time), not both")
    if not model.continuous:
        raise ValueError(f"Qc= is a spectral density per unit time: it needs a continuous "
                         f"model (ode=); {model.name} is discrete: give a per-transition Q")
    if model.nz or not model.manifold.trivial:
        raise ValueError("Qc= is built for ordinary differential equations on vector states "
                         "(no algebraic states, quaternions or angles) for now: give Q=")
    L = np.eye(model.nx) if model.noise_input is None else model.noise_input
    Qc = as_covariance(Qc, L.shape[1], "Qc", definite=False)
    W = L @ Qc @ L.T
    return 0.5 * (W + W.T), Qc


def discretised_noise(model: Any, W: Any, x: Any, w: Any) -> Any:
    r""":math:`Q_d(\Delta t)` of one transition: :func:`van_loan` of the drift linearised at
    ``x`` (the input at the interval's start) with the density ``W`` over the interval of
    the transition input ``w`` (see :func:`interval`); an interval that is not positive
    (the unused slots of a window, whose input is a placeholder) is taken as 1. Exact on a
    linear model; on a nonlinear one, the discretisation of the linearisation at the
    estimate."""
    from estim._discretise import input_at

    u_of, h = interval(model, w)
    if isinstance(h, ca.SX):
        h = ca.if_else(h > 0, h, 1.0)
    A = drift_jacobian(model)(x, input_at(u_of, 0.0), ca.DM(model.p))
    return van_loan(A, W, h)[1]


#: the mapped Functions of :func:`discretised_noises`, per model and number of transitions
_MAPPED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def discretised_noises(model: Any, W: np.ndarray, X: np.ndarray, Wt: np.ndarray
                       ) -> np.ndarray:
    r"""``(n, nx, nx)``: :func:`discretised_noise` of every transition ``k`` at once, from
    the state ``X[k]`` with the transition input ``Wt[k]`` (``X (n, nx)``, ``Wt (n, nw)``)
    under the density ``W`` ``(nx, nx)``; one mapped call (its Function built once per
    model and ``n``)."""
    n, nx = len(X), model.nx
    if not n:
        return np.empty((0, nx, nx))
    cache = _MAPPED.setdefault(model, {})
    if n not in cache:
        x, w, D = ca.SX.sym("x", nx), ca.SX.sym("w", model.nw), ca.SX.sym("D", nx, nx)
        cache[n] = ca.Function("q_d", [x, w, ca.vec(D)],
                               [ca.vec(discretised_noise(model, D, x, w))]).map(n)
    q = np.asarray(cache[n](X.T, Wt.T, np.repeat(np.reshape(W, (-1, 1), order="F"), n,
                                                 axis=1)))
    return q.T.reshape(n, nx, nx).transpose(0, 2, 1)


def interval_weight(model: Any, W: Any, x: Any, w: Any) -> Any:
    r"""The weight factor :math:`M` of a transition's defect
    :math:`x_{k+1} - F(x_k, u_k)` under a continuous noise of density ``W``
    (:math:`L Q_c L^\top`): :math:`M = C^{-1}`, :math:`C C^\top = Q_d(\Delta t_k)`
    (:func:`discretised_noise` at ``x``), so that :math:`\|M d\|^2 = d^\top Q_d^{-1} d`,
    the windowed estimators' process term with the noise of each transition's own
    interval. Expressions of ``x`` and ``w`` (``(nx, nx)``); not finite where
    :math:`Q_d` is not definite (a noise input that does not reach every state)."""
    from estim.solvers.kalman.triangular import cholesky, solve_lower

    n = x.numel()
    return solve_lower(cholesky(discretised_noise(model, W, x, w)), ca.SX.eye(n))


def moment_step(f: Callable, jac: Callable, x: Any, P: Any, u_of: Any, p: Any, W: Any,
                h: Any, substeps: int) -> tuple[Any, Any]:
    r"""The extended filter's prediction over an interval ``h``: :math:`\dot m = f(m)`,
    :math:`\dot P = A P + P A^\top + W` (:math:`A` = ``jac(m, u, p)``) by ``substeps`` classic
    Runge-Kutta steps of the pair, the input along the interval ``u_of`` (a callable of
    the fraction of the interval, or the held input). Returns :math:`(m, P)` at the end
    (:math:`P` symmetrised)."""
    n = x.numel()

    def rhs(z, u):
        m, S = z[:n], ca.reshape(z[n:], n, n)
        A = jac(m, u, p)
        Pdot = A @ S + S @ A.T + W
        return ca.vertcat(f(m, u, p), ca.vec(Pdot))

    return _integrated(rhs, x, P, u_of, h, substeps)


def sqrt_moment_step(f: Callable, jac: Callable, x: Any, S: Any, u_of: Any, p: Any,
                     LW: Any, h: Any, substeps: int) -> tuple[Any, Any]:
    r"""The extended filter's prediction in square-root form: the lower factor :math:`S`
    of :math:`P = S S^\top` carried by :math:`\dot S = S\, \Phi(S^{-1} \dot P S^{-\top})`,
    :math:`S^{-1}\dot P S^{-\top} = C + C^\top + B B^\top`, :math:`C = S^{-1} A S`,
    :math:`B = S^{-1} L_W` (:math:`L_W L_W^\top = W`), where :math:`\Phi` keeps the lower
    triangle and halves the diagonal: :math:`\dot S S^\top + S \dot S^\top = \dot P` and
    :math:`S` stays lower triangular (Morf, Lévy & Kailath 1978; Särkkä 2007), by
    ``substeps`` Runge-Kutta steps of the pair. Returns :math:`(m, S)` at the end."""
    from estim._discretise import rk4_step
    from estim.solvers.kalman.triangular import solve_lower

    n = x.numel()
    lower = ca.DM(np.tril(np.ones((n, n))) - 0.5 * np.eye(n))  # Phi's mask

    def rhs(z, u, _):
        m, F = z[:n], ca.reshape(z[n:], n, n)
        A = jac(m, u, p)
        C = solve_lower(F, A @ F)
        B = solve_lower(F, LW)
        return ca.vertcat(f(m, u, p), ca.vec(F @ ((C + C.T + B @ B.T) * lower)))

    z = rk4_step(rhs, ca.vertcat(x, ca.vec(S)), u_of, None, h, substeps)
    return z[:n], ca.reshape(z[n:], n, n)


def sqrt_sigma_moment_step(f: Callable, offsets: Callable, Wm: np.ndarray, Wc: np.ndarray,
                           x: Any, S: Any, u_of: Any, p: Any, LW: Any, h: Any,
                           substeps: int) -> tuple[Any, Any]:
    r"""The sigma-point filter's prediction in square-root form: the points
    :math:`\mathcal X_i = m + d_i`, their offsets ``offsets(S) -> list`` drawn from the
    lower factor :math:`S` itself (no Cholesky factorisation), and
    :math:`\dot S = S\, \Phi(S^{-1} \dot P S^{-\top})` with the sigma-point
    :math:`\dot P = C + C^\top + W`,
    :math:`C = \sum_i W^c_i (\mathcal X_i - m)(f_i - \bar f)^\top`, so that
    :math:`S^{-1}\dot P S^{-\top} = K + K^\top + B B^\top`,
    :math:`K = S^{-1} C S^{-\top}`, :math:`B = S^{-1} L_W` (:math:`\Phi` as in
    :func:`sqrt_moment_step`; Särkkä 2007, sec. V), by ``substeps`` Runge-Kutta steps of
    the pair. Negative weights (fifth-degree rules) enter :math:`C` as they are: no
    downdate is needed. Returns :math:`(m, S)` at the end, :math:`S` lower triangular."""
    from estim._discretise import rk4_step
    from estim.solvers.kalman.triangular import solve_lower

    n = x.numel()
    lower = ca.DM(np.tril(np.ones((n, n))) - 0.5 * np.eye(n))  # Phi's mask

    def rhs(z, u, _):
        m, F = z[:n], ca.reshape(z[n:], n, n)
        offs = offsets(F)
        fs = [f(m + d, u, p) for d in offs]
        fbar = sum((float(w) * v for w, v in zip(Wm, fs, strict=True)), ca.SX.zeros(n))
        C = sum((float(w) * (d @ (g - fbar).T) for w, d, g in zip(Wc, offs, fs,
                                                                  strict=True)),
                ca.SX.zeros(n, n))
        K = solve_lower(F, solve_lower(F, C).T).T
        B = solve_lower(F, LW)
        return ca.vertcat(fbar, ca.vec(F @ ((K + K.T + B @ B.T) * lower)))

    z = rk4_step(rhs, ca.vertcat(x, ca.vec(S)), u_of, None, h, substeps)
    return z[:n], ca.reshape(z[n:], n, n)


def sigma_moment_step(f: Callable, points: Callable, Wm: np.ndarray, Wc: np.ndarray,
                      x: Any, P: Any, u_of: Any, p: Any, W: Any, h: Any,
                      substeps: int) -> tuple[Any, Any, Any]:
    r"""The sigma-point filter's prediction over ``h`` (Särkkä 2007; see the module), the
    points ``points(m, P) -> (list of columns, definite)`` drawn at every Runge-Kutta
    stage; returns :math:`(m, P)` at the end and whether every stage's covariance had its
    sigma points (positive definite)."""
    n = x.numel()
    ok = ca.SX(1)

    def rhs(z, u):
        nonlocal ok
        m, S = z[:n], ca.reshape(z[n:], n, n)
        S = 0.5 * (S + S.T)
        sig, definite = points(m, S)
        ok = ca.logic_and(ok, definite)
        fs = [f(v, u, p) for v in sig]
        fbar = sum((float(w) * v for w, v in zip(Wm, fs, strict=True)), ca.SX.zeros(n))
        C = sum((float(w) * ((v - m) @ (g - fbar).T) for w, v, g in zip(Wc, sig, fs,
                                                                        strict=True)),
                ca.SX.zeros(n, n))
        return ca.vertcat(fbar, ca.vec(C + C.T + W))

    m, Pn = _integrated(rhs, x, P, u_of, h, substeps)
    return m, Pn, ok


def _integrated(rhs: Callable, x: Any, P: Any, u_of: Any, h: Any, substeps: int
                ) -> tuple[Any, Any]:
    """The pair ``(m, P)`` from ``(x, P)`` over ``h`` by ``substeps`` classic Runge-Kutta
    steps of ``rhs(z, u)`` on :math:`z = [m; \\operatorname{vec} P]` (the input along the
    interval ``u_of``); :math:`P` symmetrised."""
    from estim._discretise import rk4_step

    n = x.numel()
    z = rk4_step(lambda zz, u, _: rhs(zz, u), ca.vertcat(x, ca.vec(P)), u_of, None, h,
                 substeps)
    Pn = ca.reshape(z[n:], n, n)
    return z[:n], 0.5 * (Pn + Pn.T)
