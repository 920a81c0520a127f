"""Van der Pol oscillator, both states measured (MPCTools NMHE example)."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def van_der_pol(mu: float = 1.0, dt: float = 0.1, integrator: str = "rk4") -> Model:
    r"""Van der Pol oscillator with full-state measurement.

    .. math:: \dot x_1 = x_2, \quad \dot x_2 = \mu (1 - x_1^2) x_2 - x_1, \quad y = x

    discretised by one RK4 step of ``dt = 0.1``.

    References
    ----------
    A. Sirmatel, "Implementing nonlinear moving horizon estimation in MATLAB
    with MPCTools", 2019.
    """
    def ode(x, u, p):
        return ca.vertcat(x[1], p["mu"] * (1 - x[0] ** 2) * x[1] - x[0])

    return Model(states=["x1", "x2"], outputs=["y1", "y2"], ode=ode,
                 output=lambda x, u, p: x, dt=dt, integrator=integrator,
                 params={"mu": mu}, name="van_der_pol", time_unit="dimensionless")
