"""Batch chemical reactor of the KU Leuven MPC course (session 5)."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def batch_reactor(k1: float = 0.5, km1: float = 0.05, k2: float = 0.2, km2: float = 0.01,
                  gain: float = 32.84, dt: float = 0.25, integrator: str = "rk4",
                  feed: bool = False) -> Model:
    r"""Reversible reactions :math:`A \rightleftharpoons B + C`, :math:`2B \rightleftharpoons C`.

    .. math::
        r_1 = k_1 C_A - k_{-1} C_B C_C, \quad r_2 = k_2 C_B^2 - k_{-2} C_C, \\
        \dot x = \begin{bmatrix} -r_1 \\ r_1 - 2 r_2 \\ r_1 + r_2 \end{bmatrix},
        \qquad y = 32.84 (C_A + C_B + C_C)

    with state :math:`x = (C_A, C_B, C_C) \ge 0`, RK4 at ``dt = 0.25``. With
    ``feed=True`` the reactor is semi-batch: an input ``feed`` (concentration of A
    fed per unit time) adds to :math:`\dot C_A` (the disturbance-model scenario).

    References
    ----------
    KU Leuven, Model Predictive Control (H0E76A), exercise session 5;
    J. B. Rawlings & B. R. Bakshi (2006), Particle filtering and moving horizon
    estimation, Comput. Chem. Eng. 30, 1529-1541.
    """
    def ode(x, u, p):
        r1 = p["k1"] * x[0] - p["km1"] * x[1] * x[2]
        r2 = p["k2"] * x[1] ** 2 - p["km2"] * x[2]
        return ca.vertcat(-r1 + (u[0] if feed else 0), r1 - 2 * r2, r1 + r2)

    return Model(states=["C_A", "C_B", "C_C"], outputs=["y"], ode=ode,
                 inputs=["feed"] if feed else None,
                 output=lambda x, u, p: p["gain"] * (x[0] + x[1] + x[2]),
                 dt=dt, integrator=integrator, lower=0.0,
                 params={"k1": k1, "km1": km1, "k2": k2, "km2": km2, "gain": gain},
                 name="batch_reactor")
