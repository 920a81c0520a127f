"""Mobile-robot models of Martinelli (2010), the observability examples of PyNOA.

Each factory returns an :class:`estim.Model`; :func:`estim.observability.analyze`
on them reproduces (and corrects) the notebooks of PyNOA.

References
----------
A. Martinelli, "Continuous symmetries and observability properties in
autonomous navigation", INRIA RR-7049, 2010.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from estim.model import Model


def martinelli_simple() -> Model:
    """Martinelli 2010, simple localisation: (D, phi_R, theta_R), inputs (v, omega)."""
    return Model(
        states=["D", "phi_R", "theta_R"], outputs=["beta"], inputs=["v", "omega"],
        ode=lambda x, u, p: ca.vertcat(u[0] * ca.cos(x[2] - x[1]),
                                       u[0] * ca.sin(x[2] - x[1]) / x[0], u[1]),
        output=lambda x, u, p: ca.pi - x[2] + x[1], dt=0.1,
        lower=[0.5, -np.inf, -np.inf], upper=[5.0, np.inf, np.inf], name="martinelli_simple")


def odometry_noncircular() -> Model:
    """Martinelli 2010 odometry calibration (PyNOA notebook), wheel speeds as inputs."""
    def ode(x, u, p):
        mu, g, phi, psi, eta, delta, xi = (x[i] for i in range(7))
        f1 = ca.vertcat(-mu**2 * eta * ca.cos(g - phi), xi - mu * eta * ca.sin(g - phi),
                        0, 0, 0, 0, 0)
        f2 = ca.vertcat(-mu**2 * eta * delta * ca.cos(g - phi),
                        -xi * delta - mu * eta * delta * ca.sin(g - phi), 0, 0, 0, 0, 0)
        return f1 * u[0] + f2 * u[1]

    return Model(
        states=["mu", "gamma", "phi", "psi", "eta", "delta", "xi"], outputs=["beta"],
        inputs=["omega_R", "omega_L"], ode=ode, dt=0.1, name="odometry_noncircular",
        output=lambda x, u, p: -ca.atan2(ca.sin(x[1]), x[0] + ca.cos(x[1])) - x[3],
        lower=[0.2, -np.inf, -np.inf, -np.inf, 0.2, 0.2, 0.2], upper=[3, np.inf, np.inf,
                                                                       np.inf, 3, 3, 3])


def odometry_circular() -> Model:
    """The same robot on a circular trajectory (PyNOA notebook's 5-state model)."""
    def ode(x, u, p):
        mu, g, eta, xi, phi = (x[i] for i in range(5))
        return ca.vertcat(-mu**2 * eta * ca.cos(g - phi), xi - mu * eta * ca.sin(g - phi),
                          0, 0, 0) * u[0]

    return Model(
        states=["mu", "gamma", "eta_q", "xi_q", "phi"], outputs=["y"], inputs=["nu"], ode=ode,
        output=lambda x, u, p: ca.sin(x[1]) / (x[0] + ca.cos(x[1])), dt=0.1,
        lower=[0.2, -np.inf, 0.2, 0.2, -np.inf], upper=[3, np.inf, 3, 3, np.inf],
        name="odometry_circular")


QUADROTOR_SENSORS = ("imu_gnss_baro", "baro_gnss", "imu", "imu_baro")


def quadrotor_ko2019(sensors: str = "imu_gnss_baro") -> Model:
    r"""Quadrotor model-aided inertial navigation of Ko et al. (2019), as in PyNOA's notebook.

    States (33, parameter estimation): position :math:`r`, velocity :math:`v`
    (world), attitude quaternion :math:`q` (scalar first), body rate
    :math:`\omega`; mass, principal inertias, gravity vector; drag coefficient
    :math:`\lambda`, rotor-arm distances :math:`d_{12}, d_{23}, d_{34}, d_{14}`,
    thrust and torque coefficients :math:`k_{fi}, k_{mi}`. Inputs: rotor speeds
    :math:`\omega_1..\omega_4`. With ``sensors="imu_baro"`` the 20 parameters
    are fixed (13 navigation states).

    .. math::
        \dot r = v,\quad \dot v = g + \sum_i \omega_i\Big(\frac{k_{fi}}{m} R e_z
        - \frac{\lambda}{m} R P_{xy} R^\top v\Big),\quad
        \dot q = \tfrac12 q \otimes (0, \omega),\quad
        \dot\omega = -I^{-1}(\omega \times I\omega)
        + \sum_i \omega_i I^{-1}(k_{mi} e_z + r_{Ri} \times k_{fi} e_z)

    with :math:`R = R(q)` the (unnormalised) Hamilton rotation matrix. The
    IMU measures the specific force :math:`\frac1m(\sum k_{fi}\omega_i^2 e_z -
    \lambda \sum\omega_i\, P_{xy} R^\top v)` and :math:`\omega`; the barometer
    :math:`r_z`, GNSS :math:`(r_x, r_y)`. The rotor speeds enter the process
    linearly and the thrust measurement quadratically: reproduced as coded in
    the source notebook.

    References
    ----------
    N. Y. Ko, I. H. Choi, G. Song, W. Youn, "Three-dimensional dynamic-model-aided
    navigation of multirotor unmanned aerial vehicles", IEEE Access 7, 2019.
    """
    if sensors not in QUADROTOR_SENSORS:
        raise ValueError(f"sensors must be one of {QUADROTOR_SENSORS}, got {sensors!r}")
    nav = ["r_x", "r_y", "r_z", "v_x", "v_y", "v_z", "q_w", "q_x", "q_y", "q_z",
           "w_x", "w_y", "w_z"]
    inertial = ["m", "i_xx", "i_yy", "i_zz", "g_x", "g_y", "g_z"]
    rotor = ["lambda_l", "d_12", "d_23", "d_34", "d_14", "k_f1", "k_f2", "k_f3", "k_f4",
             "k_m1", "k_m2", "k_m3", "k_m4"]
    nominal = {"m": 1.2, "i_xx": 0.012, "i_yy": 0.013, "i_zz": 0.022, "g_x": 0.0, "g_y": 0.0,
               "g_z": -9.81, "lambda_l": 0.01, "d_12": 0.12, "d_23": 0.12, "d_34": 0.12,
               "d_14": 0.12, "k_f1": 1e-5, "k_f2": 1e-5, "k_f3": 1e-5, "k_f4": 1e-5,
               "k_m1": 1e-7, "k_m2": 1e-7, "k_m3": 1e-7, "k_m4": 1e-7}
    estimate_params = sensors != "imu_baro"
    names = nav + (inertial + rotor if estimate_params else [])

    def unpack(x, p):
        vals = {n: x[i] for i, n in enumerate(nav)}
        for n in inertial + rotor:
            vals[n] = x[names.index(n)] if estimate_params else p[n]
        return vals

    def rotation(qw, qx, qy, qz):
        return ca.vertcat(
            ca.horzcat(qw**2 + qx**2 - qy**2 - qz**2, 2 * qx * qy - 2 * qw * qz,
                       2 * qx * qz + 2 * qw * qy),
            ca.horzcat(2 * qx * qy + 2 * qw * qz, qw**2 - qx**2 + qy**2 - qz**2,
                       2 * qy * qz - 2 * qw * qx),
            ca.horzcat(2 * qx * qz - 2 * qw * qy, 2 * qy * qz + 2 * qw * qx,
                       qw**2 - qx**2 - qy**2 + qz**2))

    def ode(x, u, p):
        s = unpack(x, p)
        v = ca.vertcat(s["v_x"], s["v_y"], s["v_z"])
        q = [s["q_w"], s["q_x"], s["q_y"], s["q_z"]]
        w = ca.vertcat(s["w_x"], s["w_y"], s["w_z"])
        inertia = ca.vertcat(s["i_xx"], s["i_yy"], s["i_zz"])
        R = rotation(*q)
        ez = ca.DM([0, 0, 1])
        Pxy = ca.diag(ca.DM([1, 1, 0]))
        drag = s["lambda_l"] / s["m"] * (R @ Pxy @ R.T @ v)
        arms = [ca.vertcat(s["d_12"], -s["d_14"], 0), ca.vertcat(s["d_12"], s["d_23"], 0),
                ca.vertcat(-s["d_34"], s["d_23"], 0), ca.vertcat(-s["d_34"], -s["d_14"], 0)]
        v_dot = ca.vertcat(s["g_x"], s["g_y"], s["g_z"])
        w_dot = -ca.cross(w, inertia * w) / inertia
        for i in range(4):
            kf, km = s[f"k_f{i + 1}"], s[f"k_m{i + 1}"]
            v_dot += u[i] * (kf / s["m"] * (R @ ez) - drag)
            w_dot += u[i] * (km * ez + ca.cross(arms[i], kf * ez)) / inertia
        qw, qx, qy, qz = q
        wx, wy, wz = w[0], w[1], w[2]
        q_dot = 0.5 * ca.vertcat(-(qx * wx + qy * wy + qz * wz), qw * wx + qy * wz - qz * wy,
                                 qw * wy - qx * wz + qz * wx, qw * wz + qx * wy - qy * wx)
        rows = [v, v_dot, q_dot, w_dot]
        if estimate_params:
            rows.append(ca.DM.zeros(20))
        return ca.vertcat(*rows)

    def output(x, u, p):
        s = unpack(x, p)
        v = ca.vertcat(s["v_x"], s["v_y"], s["v_z"])
        R = rotation(s["q_w"], s["q_x"], s["q_y"], s["q_z"])
        kl = s["lambda_l"] * (u[0] + u[1] + u[2] + u[3])
        body_v = R.T @ v
        thrust = sum(s[f"k_f{i + 1}"] * u[i] ** 2 for i in range(4))
        imu = ca.vertcat(-kl * body_v[0] / s["m"], -kl * body_v[1] / s["m"], thrust / s["m"],
                         s["w_x"], s["w_y"], s["w_z"])
        baro, gnss = s["r_z"], ca.vertcat(s["r_x"], s["r_y"])
        return {"imu_gnss_baro": ca.vertcat(imu, gnss, baro), "baro_gnss": ca.vertcat(baro, gnss),
                "imu": imu, "imu_baro": ca.vertcat(imu, baro)}[sensors]

    outputs = {"imu_gnss_baro": 9, "baro_gnss": 3, "imu": 6, "imu_baro": 7}[sensors]
    return Model(states=names, outputs=outputs, inputs=["omega_1", "omega_2", "omega_3", "omega_4"],
                 ode=ode, output=output, dt=0.01, name=f"quadrotor_{sensors}",
                 params={} if estimate_params else nominal)
