"""Runaway-electron burst model (Oliva & Carnevale observer report, sec. 2.5)."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def runaway(gamma: float = 0.5, gamma1: float = 2.5, nu: float = 0.5, source: float = 1.0,
            S: float = 0.0, W_t: float = 0.1, eps: float = 50.0, dt: float = 5e-4,
            integrator: str = "rk4") -> Model:
    r"""Two-state runaway-electron model with bursting limit cycle.

    .. math::
        \dot x_1 = \varepsilon(-2 x_1 x_2 - 2 S + Q), \quad
        \dot x_2 = \varepsilon\Big(-\nu x_2 + \gamma (x_1 x_2 + S)
                   - \gamma_1 \frac{x_2}{1 + x_2 / W_t}\Big), \quad y = x_2

    ``source`` is the report's :math:`Q`. The time-scale factor
    :math:`\varepsilon = 50` is absent from the report but present in the
    authors' code; without it there are no bursts. With the defaults the
    equilibrium (2.79, 0.179) is unstable and :math:`x_2` bursts every
    0.2865 s with peak 1.38. States are bounded below by 0.

    References
    ----------
    F. Oliva, D. Carnevale, "Optimisation based observer", report, 2020.
    """
    def ode(x, u, p):
        x1, x2 = x[0], x[1]
        return ca.vertcat(
            p["eps"] * (-2 * x1 * x2 - 2 * p["S"] + p["source"]),
            p["eps"] * (-p["nu"] * x2 + p["gamma"] * (x1 * x2 + p["S"])
                        - p["gamma1"] * x2 / (1 + x2 / p["W_t"])),
        )

    return Model(states=["x1", "x2"], outputs=["y"], ode=ode,
                 output=lambda x, u, p: x[1], dt=dt, integrator=integrator,
                 lower=0.0, name="runaway", time_unit="s",
                 params={"gamma": gamma, "gamma1": gamma1, "nu": nu, "source": source,
                         "S": S, "W_t": W_t, "eps": eps})
