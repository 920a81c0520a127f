"""A vehicle's vertical channel seen by sensors at different rates (sensor fusion)."""

from __future__ import annotations

import casadi as ca

from estim.model import Model


def vertical_channel(dt: float = 0.01, variable_dt: bool = False) -> Model:
    r"""Height :math:`h`, climb rate :math:`v` and vertical acceleration :math:`a` (a random
    walk: a manoeuvre is a change of acceleration),

    .. math::
        \dot h = v, \quad \dot v = a, \quad \dot a = 0,

    measured by three sensors: an accelerometer (``acc`` :math:`= a`), a satellite
    receiver (``h_gnss`` :math:`= h`) and a barometer (``h_baro`` :math:`= h`), each at
    its own rate (the outputs a sensor does not report at a sample are NaN; see
    :func:`estim.records.merge` and ``Scenario(sampling=...)``). RK4, exact for these
    nilpotent dynamics. ``variable_dt=True`` integrates over the interval between the
    time stamps of a merged record (``dt`` is then the nominal interval).
    """
    return Model(states=["h", "v", "a"], outputs=["acc", "h_gnss", "h_baro"],
                 ode=lambda x, u, p: ca.vertcat(x[1], x[2], 0),
                 output=lambda x, u, p: ca.vertcat(x[2], x[0], x[0]), dt=dt,
                 variable_dt=variable_dt, name="vertical channel")
