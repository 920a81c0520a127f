"""A target moving at a nearly constant velocity in the plane, its position measured."""

from __future__ import annotations

import numpy as np

from estim.model import Model


def constant_velocity(dt: float = 0.1) -> Model:
    r"""Position :math:`(x, y)` and velocity :math:`(v_x, v_y)` of a target in the plane,
    sampled every ``dt``:

    .. math::
        x_{k+1} = \begin{bmatrix} I & \Delta t\, I \\ 0 & I \end{bmatrix} x_k + q_k,
        \qquad y_k = (x, y) + r_k

    (discrete, exact). The process noise of a white acceleration of spectral density
    :math:`q` per axis is
    :math:`Q = q \begin{bmatrix} \Delta t^3/3\, I & \Delta t^2/2\, I \\
    \Delta t^2/2\, I & \Delta t\, I \end{bmatrix}`
    (``estim.solvers.kalman.continuous.van_loan`` of the continuous model). The car of
    Särkkä & Svensson, *Bayesian Filtering and Smoothing* (2nd ed., 2023, example 4.3:
    ``dt = 0.1``, ``q = 1``, position noise :math:`\sigma = 0.5`)."""
    A = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    H = np.eye(2, 4)
    return Model(states=["x", "y", "vx", "vy"], outputs=["px", "py"],
                 dynamics=lambda x, u, p: A @ x, output=lambda x, u, p: H @ x,
                 dt=dt, name="constant velocity")
