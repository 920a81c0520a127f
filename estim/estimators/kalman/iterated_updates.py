r"""The iterated measurement updates of the fused filters: Gauss-Newton (the iterated EKF)
and iterated posterior linearisation (the IPLF), plain or damped, with their test of
convergence.

Both minimise, or approximately minimise, the update's MAP cost

.. math::
    V(x) = (x - \bar x)^\top \bar P^{-1} (x - \bar x)
         + (y - h(x))^\top R^{-1} (y - h(x))

(the rows of missing outputs left out). A plain iteration takes every step it computes,
as the textbooks do; on a strongly nonlinear output it can overshoot, oscillate or
diverge. The damped iterations of the iterated EKF keep the cost from rising:

* ``damping="line-search"``: the Gauss-Newton step :math:`d` from the current iterate
  :math:`x_i` is shortened to the first of :math:`1, \tfrac12, \dots, 2^{-(J-1)}`
  (:data:`LINE_SEARCH_STEPS` trials) that lowers :math:`V`; if none does, the iterate
  stays (Skoglund, Hendeby & Axehill 2015);
* ``damping="levenberg-marquardt"``: the Gauss-Newton step is taken
  with the extra term :math:`\lambda (x - x_i)^\top \bar P^{-1} (x - x_i)` in the cost,
  that is the linearised update from the prior
  :math:`((\bar x + \lambda x_i)/(1 + \lambda),\ \bar P/(1 + \lambda))`; a step that lowers
  :math:`V` is taken and :math:`\lambda` divided by 10, else the iterate stays and
  :math:`\lambda` is multiplied by 10 (from :data:`LM_START`; Marquardt's scaling by the
  prior's metric, so that :math:`\lambda` has no units).

The posterior linearisation's fixed point is not the minimum of :math:`V` (nor of any
cost it descends), so a line search on :math:`V` stalls short of it. Its damped form,
``damping="relaxed"`` (the UKF), moves the mean and the covariance by a fixed fraction
:data:`RELAXATION` of each iteration, :math:`x_{i+1} = x_i + \gamma (x^* - x_i)`,
:math:`P_{i+1} = P_i + \gamma (P^* - P_i)` (a convex combination: positive definite),
the UKF's update included: the same fixed point, reached more slowly (give it more
iterations), but without the oscillation of the plain iteration where the output is
strongly nonlinear in the prior's spread (damping the posterior linearisation as
Raitoharju et al. 2018 propose, with a fixed step). On bearing-only triangulation from
200 random priors (``tests/test_iterated.py``) 30 relaxed iterations end within 0.1 of
the truth where 10 or 30 plain ones fail on 13.

Every trial is unrolled in the one compiled step: a fixed count of evaluations of
:math:`h`, selected by ``if_else``.

**Convergence.** After the last iteration one more undamped step :math:`d` is computed
from the final iterate (for the EKF: the Gauss-Newton step, whose linearisation also
gives the damped filters' covariance; for the IPLF: the next posterior linearisation); the
update has converged when :math:`\sqrt{d^\top P^{-1} d} \le` ``tol``, the step that
remained is below ``tol`` posterior standard deviations. Converged or not goes in the
step's ``info.extra["converged"]`` (and ``FilterResult.converged``); a damped iteration
that has not converged makes the step ``"suspect"``: a damped filter promises a converged
update, a plain one iterates a fixed number of times by design.

References
----------
B. M. Bell, F. W. Cathey, "The iterated Kalman filter update as a Gauss-Newton method",
IEEE TAC 38(2), 1993;
M. A. Skoglund, G. Hendeby, D. Axehill, "Extended Kalman filter modifications based on an
optimization view point", FUSION 2015;
M. Raitoharju, L. Svensson, Á. F. García-Fernández, R. Piché, "Damped posterior
linearization filter", IEEE Signal Processing Letters 25(4), 2018;
Á. F. García-Fernández, L. Svensson, M. R. Morelande, S. Särkkä, "Posterior linearization
filter: principles and implementation using sigma points", IEEE TSP 63(20), 2015.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import casadi as ca

from estim._validate import as_float

#: The damped iterations: by name, and which filters have them.
DAMPING = {"line-search": ("ekf",), "levenberg-marquardt": ("ekf",), "relaxed": ("ukf",)}
#: The step of the relaxed posterior linearisation: this fraction of each iteration's move.
RELAXATION = 0.5
#: Trial steps of the line search: 1, 1/2, ..., 2^-(J-1).
LINE_SEARCH_STEPS = 8
#: The Levenberg-Marquardt parameter of the first iteration, and its factor.
LM_START, LM_FACTOR = 1e-3, 10.0

__all__ = ["DAMPING", "LINE_SEARCH_STEPS", "LM_START", "RELAXATION", "check_iterated",
           "ekf_update", "posterior_linearised_update"]


def check_iterated(filter_name: str, iterations: int, damping: object, tol: object
                   ) -> tuple[str | None, float]:
    """``(damping, tol)`` checked: a known damping the filter has, with more than one
    iteration, and a positive tolerance."""
    if damping is not None:
        if not isinstance(damping, str) or damping not in DAMPING \
                or filter_name not in DAMPING[damping]:
            names = [k for k, v in DAMPING.items() if filter_name in v]
            raise ValueError(f"damping must be None or one of "
                             f"{', '.join(map(repr, names))}, got {damping!r}")
        if iterations < 2:
            raise ValueError(f"damping={damping!r} damps the iterations of the update: give "
                             f"iterations > 1 (got {iterations})")
    return damping, as_float(tol, "tol", positive=True)


def _map_cost(x, xb, Pb, y, mask, Rm, h: Callable) -> ca.SX:
    """:math:`V(x)` of the module (missing rows of the residual zero)."""
    d = x - xb
    r = ca.if_else(mask, y - h(x), 0)
    return ca.dot(d, ca.solve(Pb, d)) + ca.dot(r, ca.solve(Rm, r))


def _line_search(x, step, cost: Callable, V0) -> ca.SX:
    """The fraction :math:`\\alpha` of ``step`` the line search takes from ``x`` (0: none
    lowers the cost below ``V0``)."""
    alpha = ca.SX(0)
    for j in reversed(range(LINE_SEARCH_STEPS)):  # the longest decreasing trial wins
        a = 0.5 ** j
        alpha = ca.if_else(cost(x + a * step) < V0, a, alpha)
    return alpha


def _standard_deviations(step, P) -> ca.SX:
    """:math:`\\sqrt{d^\\top P^{-1} d}`: a step in standard deviations of ``P``."""
    return ca.sqrt(ca.fmax(ca.dot(step, ca.solve(P, step)), 0))


def ekf_update(model: Any, xb, Pb, y, mask, Rm, uy, p, iterations: int,
               damping: str | None, tol: float) -> tuple:
    r"""The iterated EKF's update of the prediction ``(xb, Pb)`` by ``y`` (``Rm``: the
    measurement noise with unit rows for missing outputs): ``iterations`` Gauss-Newton
    iterations, plain or damped (see the module), then the Joseph covariance. Returns
    ``(x, P, S0, converged)``: ``S0`` the innovation covariance at the prediction (the
    NIS's), ``converged`` the test of the module."""
    D = ca.diag(mask)

    def h(x):
        return model.H(x, uy, p)

    def linearised(x, prior_x, prior_P):  # the Kalman update linearised at x
        C = D @ model.H_x(x, uy, p)
        S = C @ prior_P @ C.T + Rm
        S = 0.5 * (S + S.T)
        K = ca.solve(S, C @ prior_P).T
        r = ca.if_else(mask, y - h(x) - C @ (prior_x - x), 0)
        return prior_x + K @ r, K, C, S

    def cost(x):
        return _map_cost(x, xb, Pb, y, mask, Rm, h)

    x, lam, S0 = xb, ca.SX(LM_START), None
    for i in range(iterations):
        if damping == "levenberg-marquardt":
            if i == 0:
                S0 = linearised(xb, xb, Pb)[3]
            cand, K, C, _ = linearised(x, (xb + lam * x) / (1 + lam), Pb / (1 + lam))
            better = cost(cand) < cost(x)
            x = ca.if_else(better, cand, x)
            lam = ca.if_else(better, lam / LM_FACTOR, lam * LM_FACTOR)
            continue
        cand, K, C, S = linearised(x, xb, Pb)
        if i == 0:
            S0 = S
        if damping is None:
            x = cand
        else:
            x = x + _line_search(x, cand - x, cost, cost(x)) * (cand - x)
    final, Kf, Cf, _ = linearised(x, xb, Pb)  # the next step, undamped
    if damping is not None:  # the covariance of the damped iterate: its linearisation
        K, C = Kf, Cf
    IKC = ca.DM.eye(xb.numel()) - K @ C
    P = IKC @ Pb @ IKC.T + K @ Rm @ K.T
    P = 0.5 * (P + P.T)
    return x, P, S0, _standard_deviations(final - x, P) <= tol


def posterior_linearised_update(ukf: Any, xb, Pb, x1, P1, y, mask, Rm, uy, p,
                                mean: Callable, cov: Callable) -> tuple:
    r"""Iterations 2 to :math:`K` of the iterated posterior linearisation filter
    (García-Fernández, Svensson, Morelande & Särkkä 2015) from the UKF's update
    ``(x1, P1)``: the statistical linear regression of :math:`h` on the sigma points of
    the current posterior :math:`N(x_i, P_i)`,

    .. math::
        \bar z = \sum_j W^m_j h(\mathcal X_j), \quad
        \Psi = \sum_j W^c_j (\mathcal X_j - x_i)(h(\mathcal X_j) - \bar z)^\top, \quad
        \Phi = \sum_j W^c_j (h(\mathcal X_j) - \bar z)(\cdot)^\top, \\
        H = \Psi^\top P_i^{-1}, \quad b = \bar z - H x_i, \quad
        \Omega = \Phi - H P_i H^\top,

    then the Kalman update of the prediction :math:`(\bar x, \bar P)` by
    :math:`y = H x + b + v`, :math:`v \sim N(0, R + \Omega)`; relaxed with
    ``ukf.damping`` (the first iteration, the UKF's update, too; see the module).
    ``mean``, ``cov``: the sigma-point sums of :mod:`~estim.estimators.kalman.ukf`. Returns
    the last posterior, whether every :math:`P_i` had its sigma points (positive
    definite), and the test of convergence (one more regression from the last
    posterior)."""
    m, Wm, Wc = ukf.model, ukf._Wm, ukf._Wc
    definite = ca.SX(1)

    def regressed(xi, Pi):  # the update by the regression about N(xi, Pi)
        sig, ok = ukf._sigma_points(xi, Pi)
        Z = [ca.if_else(mask, m.H(v, uy, p), 0) for v in sig]
        zb = mean(Z, Wm)
        dZ = [z - zb for z in Z]
        Psi = cov([v - xi for v in sig], dZ, Wc)
        H = ca.solve(Pi, Psi).T
        S = H @ Pb @ H.T + cov(dZ, dZ, Wc) - H @ Pi @ H.T + Rm
        S = 0.5 * (S + S.T)
        K = ca.solve(S, H @ Pb).T
        x = xb + K @ ca.if_else(mask, y - H @ xb - (zb - H @ xi), 0)
        P = Pb - K @ S @ K.T
        return x, 0.5 * (P + P.T), ok

    gamma = 1.0 if ukf.damping is None else RELAXATION
    xi, Pi = (x1, P1) if ukf.damping is None else \
        (xb + gamma * (x1 - xb), Pb + gamma * (P1 - Pb))  # the UKF's update relaxed too
    for _ in range(ukf.iterations - 1):
        x, P, ok = regressed(xi, Pi)
        definite = ca.logic_and(definite, ok)
        xi, Pi = (x, P) if ukf.damping is None else (xi + gamma * (x - xi),
                                                     Pi + gamma * (P - Pi))
    x, _, ok = regressed(xi, Pi)  # the next iteration, undamped: the test
    return xi, Pi, definite, ca.logic_and(ok, _standard_deviations(x - xi, Pi) <= ukf.tol)

