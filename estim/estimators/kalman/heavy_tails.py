r"""Heavy-tailed measurement noise in the fused filters: the variational Bayes Student-t
update (``EKF/UKF(..., noise="student-t", dof=nu)``).

The measurement noise is Student's :math:`t` with :math:`\nu` degrees of freedom and scale
:math:`R`, written as a Gaussian scale mixture, :math:`v \mid \lambda \sim
N(0, R/\lambda)`, :math:`\lambda \sim \mathrm{Gamma}(\nu/2, \nu/2)`. The variational
Bayes update (Piché, Särkkä & Hartikainen 2012) alternates between the Kalman update with
:math:`R/\lambda` and the scale's posterior mean

.. math::
    \lambda = \frac{\nu + m}{\nu + \Delta}, \qquad
    \Delta = \mathbb E_q\!\left[(y - h(x))^\top R^{-1} (y - h(x))\right]
           = r^\top R^{-1} r + \operatorname{tr}\!\left(R^{-1} (H \hat P H^\top +
           \Omega)\right),

with the measurement linearised at the prediction, :math:`h(x) \approx h(\bar x) + H(x -
\bar x) + N(0, \Omega)` (the EKF's Jacobian with :math:`\Omega = 0`; the UKF's statistical
linear regression :math:`H = P_{xz}^\top \bar P^{-1}`,
:math:`\Omega = P_{zz} - H \bar P H^\top`), :math:`r = e - H(\hat x - \bar x)` and
:math:`m` the measured outputs. A measurement far in the tails gets a small
:math:`\lambda`: its noise is inflated and its pull on the estimate shrinks, smoothly,
where a gate drops it whole. :data:`ITERATIONS` fixed-point iterations, unrolled in the
compiled step; as :math:`\nu \to \infty`, :math:`\lambda \to 1` and the update is the
Kalman filter's.

``noise="student-t-roth"`` is the Student's t filter of Roth, Özkan & Gustafsson (2013):
the state, the process noise and the measurement noise all Student's t with :math:`\nu`
degrees of freedom (``Q`` and ``R`` their covariances, the scales :math:`(\nu-2)/\nu`
times them), the joint of state and measurement a t, conditioned in closed form and its
degrees of freedom :math:`\nu + m` brought back to :math:`\nu` by matching the
covariance. In covariance terms the mean is the Kalman filter's and the covariance is
scaled by how surprising the measurement was:

.. math::
    \hat P = \frac{\nu - 2 + e^\top S^{-1} e}{\nu + m - 2} (\bar P - K S K^\top),

larger after an outlier (the filter then trusts its prediction less), smaller after a
measurement that fits; it resists heavy-tailed *process* noise (a jump of the state)
where the variational update resists measurement outliers.

References
----------
R. Piché, S. Särkkä, J. Hartikainen, "Recursive outlier-robust filtering and smoothing for
nonlinear systems using the multivariate Student-t distribution", IEEE MLSP 2012;
M. Roth, E. Özkan, F. Gustafsson, "A Student's t filter for heavy-tailed process and
measurement noise", IEEE ICASSP 2013.
"""

from __future__ import annotations

from typing import Any

import casadi as ca

from estim._validate import as_choice
from estim.solvers.least_squares.robust import as_dof

__all__ = ["ITERATIONS", "NOISES", "check_noise", "gain_update", "roth_update",
           "student_t_update"]

#: The noises' distributions: Gaussian, Student-t measurement noise (the variational
#: update), or every noise and the state Student-t (Roth et al.'s filter).
NOISES = ("gaussian", "student-t", "student-t-roth")
#: Fixed-point iterations of the variational update (unrolled in the compiled step).
ITERATIONS = 10


def check_noise(noise: object, dof: object, est: Any) -> tuple[str, float | None]:
    """``(noise, dof)`` of the filter ``est`` checked: a Student-t noise needs ``dof``
    above 2 (a finite variance) and vector states, without the iterated update."""
    noise = as_choice(noise, NOISES, "noise")
    if noise == "gaussian":
        if dof is not None:
            raise ValueError("dof is the Student-t noise's degrees of freedom: give "
                             "noise='student-t' with it")
        return noise, None
    if dof is None:
        raise TypeError(f"noise={noise!r} needs dof= (its degrees of freedom, above 2; 5 "
                        f"to 10 for outliers)")
    nu = as_dof(dof)
    if not est.model.manifold.trivial or est.iterations > 1 \
            or (noise == "student-t-roth" and est._sqrt):
        raise ValueError(f"noise={noise!r} is built in the {est.name.upper()} on vector "
                         f"states, with iterations=1"
                         + (" (and 'student-t-roth' in the covariance form)" if est._sqrt
                            else ""))
    return noise, nu


def gain_update(xb: Any, Pb: Any, e: Any, Pxz: Any, S: Any) -> tuple[Any, Any, Any]:
    r"""The Kalman update of ``(xb, Pb)`` by the innovation ``e`` with its covariance ``S``
    and the cross-covariance ``Pxz``: ``(x_hat, P_hat, S)``, :math:`K = P_{xz} S^{-1}`,
    :math:`\hat P = \bar P - K S K^\top` (``S`` and :math:`\hat P` symmetrised)."""
    S = 0.5 * (S + S.T)
    K = ca.solve(S, Pxz.T).T
    Ph = Pb - K @ S @ K.T
    return xb + K @ e, 0.5 * (Ph + Ph.T), S


def roth_update(xb: Any, Pb: Any, e: Any, Pxz: Any, Pzz: Any, R: Any, mask: Any,
                dof: float) -> tuple[Any, Any, Any]:
    r"""Roth et al.'s Student's t update in covariance terms (see the module): ``(x_hat,
    P_hat, S)``."""
    D, E = ca.diag(mask), ca.diag(1 - mask)
    xh, Ph, S = gain_update(xb, Pb, e, Pxz, Pzz + D @ R @ D + E)
    scale = (dof - 2 + ca.dot(e, ca.solve(S, e))) / (dof + ca.sum1(mask) - 2)
    return xh, scale * Ph, S


def student_t_update(xb: Any, Pb: Any, e: Any, Pxz: Any, Pzz: Any, R: Any, mask: Any,
                     dof: float, iterations: int = ITERATIONS) -> tuple[Any, Any, Any, Any]:
    r"""The variational Student-t update (see the module) of the prediction ``(xb, Pb)``
    with the innovation ``e`` (0 where not measured), the cross- and output covariances
    ``Pxz``, ``Pzz`` of the linearisation (their unmeasured rows 0), the scale ``R`` and
    the measured ``mask``: ``(x_hat, P_hat, S, lambda)``, ``S`` the innovation covariance
    :math:`P_{zz} + R/\lambda` the update used (the identity on unmeasured rows) and
    ``lambda`` the scale it used."""
    D = ca.diag(mask)
    E = ca.diag(1 - mask)
    m = ca.sum1(mask)
    RD = D @ R @ D + E
    Rinv = D @ ca.solve(RD, ca.DM.eye(RD.shape[0])) @ D  # R^-1 on the measured rows
    H = ca.solve(Pb, Pxz).T  # P_xz^T Pb^-1 (the EKF's C)
    Omega = Pzz - H @ Pb @ H.T
    lam = used = ca.SX(1)
    xh, Ph, S = xb, Pb, Pzz + RD
    for _ in range(iterations):  # the update with lambda, then lambda from it
        used = lam
        xh, Ph, S = gain_update(xb, Pb, e, Pxz, Pzz + D @ R @ D / lam + E)
        r = e - H @ (xh - xb)
        delta = ca.dot(r, Rinv @ r) + ca.trace(Rinv @ (H @ Ph @ H.T + Omega))
        lam = (dof + m) / (dof + delta)
    return xh, Ph, S, used
