"""A pendulum in Cartesian coordinates: a differential-algebraic model."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def pendulum(g: float = 9.81, damping: float = 0.0, dt: float = 0.05,
             integrator: str = "collocation", substeps: int = 2) -> Model:
    r"""A point mass on a rigid rod, in Cartesian coordinates, with the rod's tension as
    an algebraic state (an index-1 DAE).

    .. math::
        \dot p_x = v_x, \quad \dot p_y = v_y, \quad
        \dot v_x = -\lambda p_x - c v_x, \quad \dot v_y = -\lambda p_y - g - c v_y,

        0 = \lambda (p_x^2 + p_y^2) - (v_x^2 + v_y^2) + g p_y + c (p_x v_x + p_y v_y),

    the constraint :math:`p_x^2 + p_y^2 = L^2` differentiated twice, which gives the
    tension per unit mass :math:`\lambda` (index 1:
    :math:`\partial g / \partial \lambda = p_x^2 + p_y^2 \ne 0`). Measured: the position
    ``(p_x, p_y)``. Radau IIA collocation (``substeps`` elements of degree 3) by default.
    The rod's length :math:`L` is that of the initial state: started on a circle with a
    tangent velocity, the state stays on it to the integrator's accuracy (the index-1
    form does not enforce the position constraint itself, it drifts by the order of the
    integration error).

    References
    ----------
    E. Hairer, G. Wanner, *Solving Ordinary Differential Equations II*, Springer 1996,
    sec. VII.1 (the pendulum in Cartesian coordinates and its index reduction).
    """
    def ode(s, z, u, p):
        lam, c = z[0], p["damping"]
        return ca.vertcat(s[2], s[3], -lam * s[0] - c * s[2], -lam * s[1] - p["g"] - c * s[3])

    def alg(s, z, u, p):
        return z[0] * (s[0] ** 2 + s[1] ** 2) - (s[2] ** 2 + s[3] ** 2) + p["g"] * s[1] \
            + p["damping"] * (s[0] * s[2] + s[1] * s[3])

    return Model(states=["px", "py", "vx", "vy"], algebraic=["tension"],
                 outputs=["px_m", "py_m"], ode=ode, alg=alg,
                 output=lambda s, z, u, p: s[:2], z0=[g], dt=dt, integrator=integrator,
                 substeps=substeps, params={"g": g, "damping": damping},
                 name="pendulum")
