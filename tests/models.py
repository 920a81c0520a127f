"""Test models used by several test files (imported as ``from models import ...``)."""

from __future__ import annotations

import casadi as ca

import estim


def two_tanks(hold: str = "zoh") -> estim.Model:
    r"""Two tanks in series with square-root outflows, the lower one's level measured.

    .. math::
        \dot h_1 = q - \tfrac12\sqrt{h_1}, \qquad
        \dot h_2 = \tfrac12\sqrt{h_1} - \tfrac12\sqrt{h_2}, \qquad y = h_2,

    sampled at 0.5 s, the levels bounded below by 0 (``lower=0.0``): ``dF/dx`` is
    infinite at an empty tank. ``hold``: the input's hold (``Model(..., hold=)``).
    """
    return estim.Model(
        states=["h1", "h2"], outputs=["h2"], inputs=["q"],
        ode=lambda x, u, p: ca.vertcat(u[0] - 0.5 * ca.sqrt(x[0]),
                                       0.5 * ca.sqrt(x[0]) - 0.5 * ca.sqrt(x[1])),
        output=lambda x, u, p: x[1], dt=0.5, lower=0.0, hold=hold, name="two tanks")
