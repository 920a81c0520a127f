"""A pendulum whose angle is seen only through its sine: the classic hostile case of the
extended Kalman filter."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def sine_pendulum(g: float = 9.81, length: float = 1.0, dt: float = 0.01,
                  integrator: str = "rk4") -> Model:
    r"""A frictionless pendulum, its angle :math:`\theta` measured through
    :math:`y = \sin\theta`.

    .. math::
        \dot\theta = \omega, \quad \dot\omega = -\frac{g}{L} \sin\theta, \qquad
        y = \sin\theta + v,

    RK4 at ``dt`` (``integrator="euler"``: Euler steps, the book's discretisation). The
    sine folds :math:`\theta` and :math:`\pi - \theta` onto one
    measurement, so a linearised filter that loses the swing near
    :math:`|\theta| = \pi/2` can lock onto the mirror image and diverge (Särkkä 2013,
    example 5.1, is the same pendulum).

    References
    ----------
    S. Särkkä, *Bayesian Filtering and Smoothing*, Cambridge University Press 2013,
    example 5.1 (the pendulum), sec. 5.2 (the extended Kalman filter).
    """
    return Model(states=["theta", "omega"], outputs=["sin_theta"],
                 ode=lambda x, u, p: ca.vertcat(x[1], -p["g"] / p["length"] * ca.sin(x[0])),
                 output=lambda x, u, p: ca.sin(x[0]), params={"g": g, "length": length},
                 dt=dt, integrator=integrator, name="sine_pendulum")
