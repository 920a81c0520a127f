"""Lorenz system with the nonlinear output of the OpEn state-estimation example."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def lorenz(sigma: float = 10.0, rho: float = 28.0, beta: float = 8.0 / 3.0,
           dt: float = 0.02, integrator: str = "euler") -> Model:
    r"""Lorenz attractor, Euler-discretised as in OpEn's estimation example.

    .. math::
        \dot x = \begin{bmatrix} \sigma (x_2 - x_1) \\ x_1(\rho - x_3) - x_2 \\
        x_1 x_2 - \beta x_3 \end{bmatrix}, \qquad
        y = \begin{bmatrix} 2 x_1 \\ x_2 + x_3 \\ x_3^2/10 - x_1 \end{bmatrix}

    and :math:`x_{k+1} = x_k + t_s \dot x_k` with ``integrator="euler"``.

    References
    ----------
    P. Sopasakis et al., OpEn, "Nonlinear State Estimation" Python example.
    """
    def ode(x, u, p):
        return ca.vertcat(p["sigma"] * (x[1] - x[0]),
                          x[0] * (p["rho"] - x[2]) - x[1],
                          x[0] * x[1] - p["beta"] * x[2])

    def output(x, u, p):
        return ca.vertcat(2.0 * x[0], x[1] + x[2], x[2] ** 2 / 10.0 - x[0])

    return Model(states=["x1", "x2", "x3"], outputs=["y1", "y2", "y3"], ode=ode,
                 output=output, dt=dt, integrator=integrator,
                 params={"sigma": sigma, "rho": rho, "beta": beta}, name="lorenz",
                 time_unit="dimensionless")
