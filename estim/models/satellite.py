r"""Rigid satellite attitude dynamics on a circular orbit with gravity-gradient torque.

Quaternions are scalar first, :math:`q = (q_0, \vec q)`, and map body to
inertial coordinates: :math:`v_I = q \otimes v_B \otimes q^*`.
"""

from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np

from estim._validate import as_bool, as_float
from estim.model import Model

MU_EARTH = 3.986004418e14  # m^3 s^-2


def quat_mul(a, b):
    r"""Hamilton product :math:`a \otimes b` (scalar first); CasADi or numpy 4-vectors."""
    a0, av = a[0], _vec(a)
    b0, bv = b[0], _vec(b)
    cat = ca.vertcat if isinstance(a, ca.SX | ca.MX) or isinstance(b, ca.SX | ca.MX) else _np_cat
    s = a0 * b0 - _dot(av, bv)
    v = a0 * bv + b0 * av + _cross(av, bv)
    return cat(s, v)


def quat_rotate_to_body(q, v):
    r"""Components in body axes of an inertial vector: :math:`R(q)^\top v`."""
    q0, qv = q[0], _vec(q)
    t = 2 * _cross(qv, v)
    # R^T v = v - 2 q0 (qv x v) + 2 qv x (qv x v)
    return v - q0 * t + _cross(qv, t)


def _vec(q):
    return q[1:4]


def _np_cat(s, v):
    return np.concatenate([np.atleast_1d(s), np.ravel(v)])


def _dot(a, b):
    if isinstance(a, ca.SX | ca.MX) or isinstance(b, ca.SX | ca.MX):
        return ca.dot(a, b)
    return float(np.dot(a, b))


def _cross(a, b):
    if isinstance(a, ca.SX | ca.MX) or isinstance(b, ca.SX | ca.MX):
        return ca.cross(a, b)
    return np.cross(a, b)


def satellite(I1: float = 0.50, I2: float = 0.40, I3: float = 0.26,
              mu: float = MU_EARTH, r: float = 7.0e6, dt: float = 1.0,
              integrator: str = "rk4", quaternion: bool = False) -> Model:
    r"""Attitude kinematics and Euler's equations with gravity gradient, gyro output.

    State :math:`x = (q_0, q_1, q_2, q_3, \omega_x, \omega_y, \omega_z, \theta)`,
    input the body torque :math:`\tau` (N m, held over each sample), output the
    gyro :math:`y = \omega` (rad/s).

    .. math::
        \dot q = \tfrac12 q \otimes (0, \omega), \qquad
        I \dot\omega = -\omega \times I\omega
            + \frac{3\mu}{r^3} n_B \times I n_B + \tau, \qquad
        \dot\theta = \sqrt{\mu / r^3}

    where :math:`I = \mathrm{diag}(I_1, I_2, I_3)`, :math:`\theta` is the
    argument of latitude on the circular equatorial orbit of radius ``r`` and
    :math:`n_B = R(q)^\top (-\cos\theta, -\sin\theta, 0)` the nadir direction
    in body axes. The orbit angle is carried as a state so the model stays
    autonomous; it is deterministic and not measured.

    With ``quaternion=True`` the model declares :math:`q` a unit quaternion
    (``quaternions=[("q0", "q1", "q2", "q3")]``): the transition keeps it unit, and the
    EKF and UKF estimate it with a 3-dof attitude error (``model.ndx = 7``; their ``Q``
    and ``P0`` are then 7 x 7, see docs/attitude.md).

    Facts worth knowing: with zero torque the gyro signal is unchanged by
    :math:`I \to cI` (gravity gradient included), so the inertia is only
    identifiable up to scale; the attitude is practically unobservable from
    the gyro alone.

    References
    ----------
    F. Oliva, D. Carnevale, "Optimisation based observer", report, 2020, sec. 2.1;
    M. D. Shuster, "A survey of attitude representations", J. Astronaut. Sci. 41, 1993.
    """
    def ode(x, u, p):
        q = x[0:4]
        w = x[4:7]
        theta = x[7]
        inertia = ca.vertcat(p["I1"], p["I2"], p["I3"])
        n_orbit2 = p["mu"] / p["r"] ** 3
        nadir_inertial = ca.vertcat(-ca.cos(theta), -ca.sin(theta), 0)
        n_b = quat_rotate_to_body(q, nadir_inertial)
        torque_gg = 3 * n_orbit2 * ca.cross(n_b, inertia * n_b)
        w_dot = (-ca.cross(w, inertia * w) + torque_gg + u) / inertia
        q_dot = 0.5 * quat_mul(q, ca.vertcat(0, w))
        return ca.vertcat(q_dot, w_dot, ca.sqrt(n_orbit2))

    return Model(
        states=["q0", "q1", "q2", "q3", "wx", "wy", "wz", "theta"],
        outputs=["gyro_x", "gyro_y", "gyro_z"],
        inputs=["tau_x", "tau_y", "tau_z"],
        ode=ode, output=lambda x, u, p: x[4:7], dt=dt, integrator=integrator,
        params={"I1": I1, "I2": I2, "I3": I3, "mu": mu, "r": r}, name="satellite", time_unit="s",
        quaternions=[("q0", "q1", "q2", "q3")] if quaternion else None,
    )


def satellite_rates(I1: float = 0.50, I2: float = 0.40, I3: float = 0.26,
                    mu: float = MU_EARTH, r: float = 7.0e6, dt: float = 1.0,
                    integrator: str = "rk4") -> Model:
    r"""Euler's equations alone, the attitude entering as a known input.

    State :math:`\omega`; input :math:`u = (\tau, n_B)`, the body torque and
    the nadir direction in body axes (from a known attitude), both held over
    the sample; output the gyro :math:`y = \omega`:

    .. math:: I \dot\omega = -\omega \times I\omega
              + \frac{3\mu}{r^3} n_B \times I n_B + \tau

    ``satellite_rates().augment("I1", "I2", "I3")`` identifies the principal
    inertias (Oliva & Carnevale, sec. 2.1-2.4). With zero torque the output
    is unchanged by :math:`I \to cI`; a known torque fixes the scale.
    """
    def ode(x, u, p):
        inertia = ca.vertcat(p["I1"], p["I2"], p["I3"])
        tau, n_b = u[0:3], u[3:6]
        torque_gg = 3 * p["mu"] / p["r"] ** 3 * ca.cross(n_b, inertia * n_b)
        return (-ca.cross(x, inertia * x) + torque_gg + tau) / inertia

    return Model(
        states=["wx", "wy", "wz"], outputs=["gyro_x", "gyro_y", "gyro_z"],
        inputs=["tau_x", "tau_y", "tau_z", "nadir_x", "nadir_y", "nadir_z"],
        ode=ode, output=lambda x, u, p: x, dt=dt, integrator=integrator,
        params={"I1": I1, "I2": I2, "I3": I3, "mu": mu, "r": r}, name="satellite_rates",
        time_unit="s",
    )


def nadir_in_body(x: np.ndarray) -> np.ndarray:
    """Nadir direction in body axes from the full satellite state ``(q, omega, theta)``."""
    q, theta = np.asarray(x[:4], float), float(x[7])
    return quat_rotate_to_body(q, np.array([-np.cos(theta), -np.sin(theta), 0.0]))


def reference_attitude(t: float, amplitude: float = 0.4,
                       periods: Sequence[float] = (100.0, 73.0, 131.0),
                       phases: Sequence[float] = (0.0, 1.0, 2.0)) -> np.ndarray:
    r"""Persistently exciting target :math:`q_{ref}(t) = \exp(\phi(t)/2)`.

    :math:`\phi_i(t) = a \sin(2\pi t / P_i + c_i)` is a rotation vector; the
    exponential map gives :math:`(\cos(|\phi|/2), \sin(|\phi|/2)\,\phi/|\phi|)`.
    """
    phi = amplitude * np.sin(2 * np.pi * t / np.asarray(periods) + np.asarray(phases))
    angle = float(np.linalg.norm(phi))
    if angle < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * phi / angle])


class PDAttitudeController:
    r"""Quaternion PD law :math:`\tau = -K_p\,\mathrm{sign}(q_{e,0})\,\vec q_e - K_d\,\omega`.

    :math:`q_e = q_{ref}^* \otimes q`. With ``excitation=False`` the target
    is the identity attitude held still; with ``excitation=True`` it follows
    :func:`reference_attitude`.

    Parameters
    ----------
    kp : float
        Proportional gain (N m).
    kd : float
        Rate gain (N m s).
    excitation : bool
        Track the persistently exciting target.
    """

    def __init__(self, kp: float = 0.01, kd: float = 0.09, excitation: bool = True):
        self.kp, self.kd = as_float(kp, "kp"), as_float(kd, "kd")
        self.excitation = as_bool(excitation, "excitation")

    def __call__(self, t: float, x: np.ndarray) -> np.ndarray:
        q = np.asarray(x[0:4], dtype=float)
        w = np.asarray(x[4:7], dtype=float)
        q_ref = reference_attitude(t) if self.excitation else np.array([1.0, 0, 0, 0])
        q_ref_conj = q_ref * np.array([1.0, -1.0, -1.0, -1.0])
        q_e = quat_mul(q_ref_conj, q)
        sign = 1.0 if q_e[0] >= 0 else -1.0
        return -self.kp * sign * q_e[1:4] - self.kd * w
