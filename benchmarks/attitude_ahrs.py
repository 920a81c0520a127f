"""``estim.EKF`` on a unit-quaternion state (the multiplicative EKF) and ``estim.UKF``
(tangent-space sigma points) against the ``ahrs`` package's ``EKF`` on a gyroscope,
accelerometer and magnetometer record: the attitude error and the wall time per step.

The record (numpy, one per seed) is a rigid body turning at a smooth angular velocity
(body axes) ``omega(t) = c + A sin(2 pi f t + phi)``, ``A`` 25, 20 and 35 deg/s, ``c`` 3,
-2 and 5 deg/s, ``f`` 0.031, 0.047 and 0.023 Hz, the phases ``phi`` and the initial
attitude drawn from the seed; ``--seconds`` at ``FS = 100 Hz``. The truth is
``q_{k+1} = q_k (x) Exp(omega_k dt)`` with ``omega_k = omega(t_k + dt/2)`` held over the
interval (Hamilton product, scalar first, ``R(q)`` body to NED). The sensors, in the
conventions and units ``ahrs.filters.EKF`` documents (checked below):

* gyroscope (rad/s, white noise, no bias): the sample at ``t_k`` is the rate over
  ``[t_{k-1}, t_k]`` plus noise, ``sigma_g = 0.3 deg/s`` (ahrs's ``update(q, gyr[t], ...)``
  propagates from ``t - 1`` to ``t``; estim's input ``U[k]`` acts from ``k`` to
  ``k + 1``, so ``U[k] = gyr[k + 1]``: both filters integrate the same numbers);
* accelerometer (m/s^2): ``g0 R(q)^T [0, 0, 1]`` plus noise ``sigma_a = 0.05 m/s^2``,
  ``g0 = 9.81`` (static vehicle; the gravity vector along NED's Down axis in body axes,
  ahrs's ``a_ref = [0, 0, 1]`` for ``frame="NED"``, as its own ``ahrs.Sensors`` simulator
  generates it);
* magnetometer (nT): ``B0 R(q)^T [cos I, 0, sin I]`` plus noise ``sigma_m = 300 nT``,
  ``B0 = 48 000 nT``, inclination ``I = 64 deg``.

ahrs's EKF normalises both vectors before its update, so its measurement variances are
those of the unit vectors: ``noises = [sigma_g^2, (sigma_a/g0)^2, (sigma_m/B0)^2]``,
``frame="NED"``, ``frequency = FS``, ``magnetic_ref = [cos I, 0, sin I]``. estim's model
(states ``q0..q3`` declared ``quaternions=``, gyro rates as inputs,
``q+ = q (x) Exp(omega dt)``, outputs the two unit vectors ``R(q)^T r``) gets the same
normalised vectors with ``R = diag((sigma_a/g0)^2 I3, (sigma_m/B0)^2 I3)`` and
``Q = (sigma_g dt)^2 I3`` in the tangent space. Both start from the truth turned by
5 deg about a random axis, with ``P0 = (5 deg)^2 I3`` (tangent; for ahrs's 4 x 4
covariance its image ``G P0 G^T + 1e-12 I4``, ``G = 0.5 [-q_v^T; q_w I + [q_v x]]`` at
the initial guess; ahrs's default ``P0 = I4`` is a further row). ahrs starts its loop at
sample 1 (``Q[0] = q0``), estim updates at sample 0 as well; the error is taken after the
first ``--startup`` seconds.

Two further estim rows run the additive EKF on ``model.euclidean()`` (the same model
without the declaration: a 4 x 4 covariance, the transition still normalising ``q``),
to show what the multiplicative form costs per step: with ``Q4 = G Q G^T + 1e-12 I4``
(``G`` at the initial guess; ``P0`` likewise) and with ``Q4 = (sigma_g dt / 2)^2 I4``.
The first is less accurate: a constant ``Q4`` puts the gyro noise on the tangent plane
at the initial guess only, and once the attitude has turned away from it, part of that
noise falls along ``q`` (removed by the normalisation) and one tangent direction gets
none (at 180 deg from the guess, the direction of the guess itself). Since
``G G^T = (I4 - q q^T) / 4`` for every unit ``q``, the isotropic ``Q4`` puts the right
noise on the tangent plane at every ``q`` (ahrs recomputes its ``W W^T`` at every step
to the same effect).

Before the comparison the script checks ahrs's conventions: its ``Quaternion.to_DCM``
is ``R(q)`` above (scalar first, body to global); its prediction ``(I + dt/2 Omega(w)) q``
normalised is ``q (x) Exp(w dt)`` to third order (body rates multiplied on the right);
on a noise-free record it tracks the truth to about 1e-3 deg (the drift of its
first-order prediction; estim's EKF, with the exact ``Exp``, to rounding), and told
``frame="ENU"`` on the same NED record it is off by up to 180 deg; its loop ``update``
equals its batch mode. It also checks that estim's step loop equals ``estim.replay``
and that ``estim.errors`` gives the error angle computed here.

Reported: the RMSE of the attitude error angle ``2 acos(|q_hat . q|)`` after start-up,
median and range over ``--seeds`` records; the wall time per step (``update`` /
``step``, Python overhead included, garbage collector off), median over each record,
then median and range over the records; estim both interpreted and with ``jit=True``
(when a C compiler exists); the largest ``| |q_hat| - 1 |`` of each filter.

ahrs is a benchmark reference only (``pip install ahrs``), not a dependency of estim.

Run from the repository root::

    python benchmarks/attitude_ahrs.py [--seeds 20] [--seconds 60] [--startup 2]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import gc
import os
import platform
import statistics
import sys
import time
import warnings
from collections.abc import Callable

import casadi as ca
import numpy as np

import estim
from estim import _compile

FS = 100.0
DT = 1.0 / FS
G0, B0, DIP = 9.81, 48_000.0, np.deg2rad(64.0)
SIGMA_G, SIGMA_A, SIGMA_M = np.deg2rad(0.3), 0.05, 300.0  # rad/s, m/s^2, nT
DOWN = np.array([0.0, 0.0, 1.0])  # ahrs's a_ref for frame="NED"
MAG_DIR = np.array([np.cos(DIP), 0.0, np.sin(DIP)])  # NED, unit
RATE_AMP = np.deg2rad([25.0, 20.0, 35.0])
RATE_MEAN = np.deg2rad([3.0, -2.0, 5.0])
RATE_FREQ = np.array([0.031, 0.047, 0.023])
GUESS_ANGLE = np.deg2rad(5.0)
ADDITIVE = "estim EKF additive, Q4 = G(q0) Q G(q0)^T"
ISOTROPIC = "estim EKF additive, Q4 = (sg dt/2)^2 I4"
VAR_UNIT = np.r_[np.full(3, (SIGMA_A / G0) ** 2), np.full(3, (SIGMA_M / B0) ** 2)]


# ------------------------------------------------------------------ quaternions (numpy)
def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product, scalar first."""
    aw, av, bw, bv = a[0], a[1:], b[0], b[1:]
    return np.r_[aw * bw - av @ bv, aw * bv + bw * av + np.cross(av, bv)]


def qexp(phi: np.ndarray) -> np.ndarray:
    """``Exp(phi)``: the unit quaternion of the rotation vector ``phi`` (3,)."""
    n = np.linalg.norm(phi)
    if n == 0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.r_[np.cos(n / 2), np.sin(n / 2) * phi / n]


def skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def rotation(q: np.ndarray) -> np.ndarray:
    """``R(q)`` (3, 3), body to NED, of a unit quaternion."""
    vx = skew(q[1:])
    return np.eye(3) + 2 * q[0] * vx + 2 * vx @ vx


def tangent_map(q: np.ndarray) -> np.ndarray:
    """``G`` (4, 3) with ``q (x) Exp(d) = q + G d + O(d^2)``."""
    return 0.5 * np.vstack([-q[1:], q[0] * np.eye(3) + skew(q[1:])])


def error_angle(q_hat: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The error angle ``2 acos(|q_hat . q|)`` (T,) in rad, of the estimates ``q_hat``
    (T, 4) normalised, against ``q`` (T, 4); computed as ``2 atan2(|e_v|, |e_w|)`` of
    ``e = q^-1 (x) q_hat``, the same angle without ``acos``'s rounding floor near 0
    (about 3e-8 rad)."""
    q_hat = q_hat / np.linalg.norm(q_hat, axis=1, keepdims=True)
    w = np.abs(np.sum(q_hat * q, axis=1))
    v = q[:, :1] * q_hat[:, 1:] - q_hat[:, :1] * q[:, 1:] - np.cross(q[:, 1:], q_hat[:, 1:])
    return 2 * np.arctan2(np.linalg.norm(v, axis=1), w)


# -------------------------------------------------------------------------- the record
def make_record(seed: int, T: int, noise: bool = True) -> dict[str, np.ndarray]:
    """The true quaternions ``q`` (T, 4), the sensors ``gyr`` (rad/s), ``acc`` (m/s^2),
    ``mag`` (nT), each (T, 3), in ahrs's conventions, and the initial guess ``q0`` (4,)
    (the truth at sample 0 turned by ``GUESS_ANGLE`` about a random axis)."""
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 3)
    q = np.empty((T, 4))
    start = rng.standard_normal(4)
    q[0] = start / np.linalg.norm(start) * np.sign(start[0])
    t_mid = (np.arange(T - 1) + 0.5) * DT
    omega = RATE_MEAN + RATE_AMP * np.sin(2 * np.pi * RATE_FREQ * t_mid[:, None] + phase)
    for k in range(T - 1):
        q[k + 1] = qmul(q[k], qexp(omega[k] * DT))
        q[k + 1] /= np.linalg.norm(q[k + 1])
    gyr = np.vstack([omega[:1], omega])  # gyr[k]: the rate over [t_{k-1}, t_k]
    A = np.transpose([rotation(qk) for qk in q], (0, 2, 1))  # NED to body
    acc, mag = G0 * A @ DOWN, B0 * A @ MAG_DIR
    noises = rng.standard_normal((3, T, 3))
    if noise:
        gyr, acc, mag = gyr + SIGMA_G * noises[0], acc + SIGMA_A * noises[1], \
            mag + SIGMA_M * noises[2]
    axis = rng.standard_normal(3)
    q0 = qmul(q[0], qexp(GUESS_ANGLE * axis / np.linalg.norm(axis)))
    return dict(q=q, gyr=gyr, acc=acc, mag=mag, q0=q0)


def estim_data(rec: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """estim's measurements ``Y`` (T, 6), the unit vectors as ahrs normalises them, and
    inputs ``U`` (T, 3), ``U[k] = gyr[k + 1]`` (the rate from sample k to k + 1)."""
    acc, mag = rec["acc"], rec["mag"]
    Y = np.hstack([acc / np.linalg.norm(acc, axis=1, keepdims=True),
                   mag / np.linalg.norm(mag, axis=1, keepdims=True)])
    U = np.vstack([rec["gyr"][1:], np.zeros((1, 3))])
    return Y, U


# ----------------------------------------------------------------------- estim's model
def _qmul_ca(a, b):
    aw, ax, ay, az = (a[i] for i in range(4))
    bw, bx, by, bz = (b[i] for i in range(4))
    return ca.vertcat(aw * bw - ax * bx - ay * by - az * bz,
                      aw * bx + ax * bw + ay * bz - az * by,
                      aw * by - ax * bz + ay * bw + az * bx,
                      aw * bz + ax * by - ay * bx + az * bw)


def attitude_model() -> estim.Model:
    """Gyro-driven attitude, ``q+ = q (x) Exp(omega dt)`` (the gyro rates the inputs);
    outputs the NED Down and magnetic directions in body axes, ``q* (x) r (x) q``."""
    def step(q, w, p):
        n = ca.sqrt(ca.sumsqr(w)) * DT
        half = ca.if_else(n > 0, ca.sin(n / 2) / ca.if_else(n > 0, n, 1), 0.5)
        return _qmul_ca(q, ca.vertcat(ca.cos(n / 2), half * w * DT))

    def body(q, r):
        qc = ca.vertcat(q[0], -q[1], -q[2], -q[3])
        return _qmul_ca(_qmul_ca(qc, ca.vertcat(0, *r)), q)[1:]

    return estim.Model(states=["q0", "q1", "q2", "q3"], inputs=["wx", "wy", "wz"],
                       outputs=["ax", "ay", "az", "mx", "my", "mz"], dynamics=step,
                       output=lambda q, u, p: ca.vertcat(body(q, DOWN), body(q, MAG_DIR)),
                       quaternions=[("q0", "q1", "q2", "q3")], dt=DT, name="attitude")


# ----------------------------------------------------------------------------- runners
def _timed(step: Callable[[int], np.ndarray], T: int) -> tuple[np.ndarray, np.ndarray]:
    """Estimates (T, 4) and the wall time of every step, garbage collector off."""
    x_hat, times = np.empty((T, 4)), np.empty(T)
    enabled = gc.isenabled()
    gc.disable()
    try:
        for k in range(T):
            t0 = time.perf_counter()
            x_hat[k] = step(k)
            times[k] = time.perf_counter() - t0
    finally:
        if enabled:
            gc.enable()
    return x_hat, times


def ahrs_ekf(rec: dict[str, np.ndarray], P0: np.ndarray | None, frame: str = "NED",
             noises: np.ndarray | None = None):
    """ahrs's EKF for the loop: ``mag`` given (so that its measurement model has the
    magnetometer rows) without ``gyr``/``acc`` (so that it does not run the record)."""
    from ahrs.filters import EKF

    kw = {} if P0 is None else dict(P=P0)
    if noises is None:
        noises = np.array([SIGMA_G**2, VAR_UNIT[0], VAR_UNIT[3]])
    return EKF(mag=rec["mag"], frequency=FS, frame=frame, magnetic_ref=MAG_DIR.copy(),
               noises=noises, q0=rec["q0"], **kw)


def run_ahrs(rec: dict[str, np.ndarray], P0: np.ndarray | None, frame: str = "NED"
             ) -> tuple[np.ndarray, np.ndarray]:
    """``q = ekf.update(q, gyr[t], acc[t], mag[t])`` for t >= 1 from ``Q[0] = q0``."""
    ekf = ahrs_ekf(rec, P0, frame)
    gyr, acc, mag = rec["gyr"], rec["acc"], rec["mag"]
    state = [np.array(rec["q0"], dtype=float)]

    def step(k: int) -> np.ndarray:
        if k:
            state[0] = ekf.update(state[0], gyr[k], acc[k], mag[k])
        return state[0]

    return _timed(step, len(gyr))


def run_estim(est, Y: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``est.step(y_k, u_{k-1})`` over the record, from a reset."""
    est.reset()
    u_prev = np.vstack([np.zeros((1, 3)), U[:-1]])
    return _timed(lambda k: est.step(Y[k], u_prev[k]), len(Y))


# ------------------------------------------------------------------- convention checks
def check_conventions(T: int, startup: int) -> None:
    """ahrs's quaternion, rotation and propagation conventions, its tracking of a
    noise-free record (NED right, ENU wrong), its loop against its batch mode; estim's
    step loop against ``estim.replay``."""
    from ahrs.common.quaternion import Quaternion
    from ahrs.filters import EKF

    rng = np.random.default_rng(123)
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w = np.deg2rad([30.0, -20.0, 45.0])
    d_dcm = np.abs(Quaternion(q).to_DCM() - rotation(q)).max()
    f = ahrs_ekf(make_record(0, 3), None).f(q, w, DT)
    d_f = np.abs(f / np.linalg.norm(f) - qmul(q, qexp(w * DT))).max()
    print("conventions of ahrs.filters.EKF (scalar-first Hamilton, R(q) body to NED):")
    print(f"  Quaternion.to_DCM - R(q): {d_dcm:.1e};  prediction (I + dt/2 Omega(w)) q "
          f"normalised - q (x) Exp(w dt): {d_f:.1e} (|w| dt = "
          f"{np.linalg.norm(w) * DT:.1e}, third order)")
    clean = make_record(0, T, noise=False)
    Y, U = estim_data(clean)
    late = slice(max(startup, (3 * T) // 4), None)
    print(f"  noise-free record, max error angle after {startup * DT:g} s / over the "
          f"last quarter:")
    for label, frame, q0 in (("ahrs, NED, from the truth", "NED", clean["q"][0]),
                             ("ahrs, NED, from the 5 deg guess", "NED", clean["q0"]),
                             ("ahrs, ENU (wrong frame), from the truth", "ENU",
                              clean["q"][0]),
                             ("estim EKF, from the truth", "", clean["q"][0]),
                             ("estim EKF, from the 5 deg guess", "", clean["q0"])):
        if frame:
            x, _ = run_ahrs(dict(clean, q0=q0), None, frame)
        else:
            x, _ = run_estim(estim.EKF(attitude_model(), Q=(SIGMA_G * DT) ** 2,
                                       R=np.diag(VAR_UNIT), x0=q0, P0=GUESS_ANGLE**2), Y, U)
        err = np.rad2deg(error_angle(x, clean["q"]))
        print(f"    {label:40s} {err[startup:].max():.1e} / {err[late].max():.1e} deg")
    rec = make_record(0, min(T, 1000))
    loop, _ = run_ahrs(rec, None)
    batch = EKF(gyr=rec["gyr"], acc=rec["acc"], mag=rec["mag"], frequency=FS, frame="NED",
                magnetic_ref=MAG_DIR.copy(),
                noises=[SIGMA_G**2, VAR_UNIT[0], VAR_UNIT[3]], q0=rec["q0"]).Q
    print(f"  ahrs loop update - ahrs batch EKF(gyr=, acc=, mag=).Q: "
          f"{np.abs(loop - batch).max():.1e}")
    Y, U = estim_data(rec)
    est = estim.EKF(attitude_model(), Q=(SIGMA_G * DT) ** 2, R=np.diag(VAR_UNIT),
                    x0=rec["q0"], P0=GUESS_ANGLE**2)
    x, _ = run_estim(est, Y, U)
    log = estim.replay(est, Y, U, x=rec["q"])
    angle = np.linalg.norm(estim.errors(log), axis=1)
    print(f"  estim step loop - estim.replay: {np.abs(x - log.x_hat).max():.1e};  "
          f"|estim.errors| - 2 acos|q_hat . q|: "
          f"{np.abs(angle - error_angle(x, rec['q'])).max():.1e}")


# -------------------------------------------------------------------------------- main
def _us(values: list[float]) -> str:
    return (f"{1e6 * statistics.median(values):8.1f} us [{1e6 * min(values):.1f}, "
            f"{1e6 * max(values):.1f}]")


def _deg(values: list[float]) -> str:
    return (f"{statistics.median(values):.4f} deg [{min(values):.4f}, "
            f"{max(values):.4f}]")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="records (seeds 0..S-1)")
    parser.add_argument("--seconds", type=float, default=60.0, help="record length")
    parser.add_argument("--startup", type=float, default=2.0,
                        help="seconds left out of the RMSE")
    args = parser.parse_args(argv)
    try:
        import ahrs
    except ImportError:
        print("attitude_ahrs.py compares estim with the ahrs package, which is not "
              "installed: pip install ahrs", file=sys.stderr)
        sys.exit(2)

    T = int(round(args.seconds * FS)) + 1
    startup = int(round(args.startup * FS))
    cc = _compile.compiler()
    print(f"python {platform.python_version()}, estim {estim.__version__}, ahrs "
          f"{ahrs.__version__}, casadi {ca.__version__}, numpy {np.__version__}, "
          f"{os.cpu_count()} cores, {cc[1] if cc else 'no C compiler'}")
    print(f"{args.seconds:g} s at {FS:g} Hz (T = {T}), {args.seeds} seeds; sigma_g = "
          f"{np.rad2deg(SIGMA_G):g} deg/s, sigma_a = {SIGMA_A:g} m/s^2, sigma_m = "
          f"{SIGMA_M:g} nT (|B| = {B0:g} nT, inclination {np.rad2deg(DIP):g} deg); "
          f"initial error {np.rad2deg(GUESS_ANGLE):g} deg; RMSE after {args.startup:g} s\n")
    check_conventions(T, startup)

    model = attitude_model()
    euclid = model.euclidean()
    Q3, P03 = (SIGMA_G * DT) ** 2 * np.eye(3), GUESS_ANGLE**2 * np.eye(3)
    R = np.diag(VAR_UNIT)
    variants: dict[str, Callable[[dict], object]] = {}
    jits = [False, True] if cc else [False]
    for jit in jits:
        tag = ", jit" if jit else ""
        variants[f"estim EKF (multiplicative){tag}"] = (
            lambda rec, jit=jit: estim.EKF(model, Q=Q3, R=R, x0=rec["q0"], P0=P03, jit=jit))
        variants[f"estim UKF (tangent sigma){tag}"] = (
            lambda rec, jit=jit: estim.UKF(model, Q=Q3, R=R, x0=rec["q0"], P0=P03, jit=jit))
    for jit in jits:
        def additive(rec, jit=jit):
            G = tangent_map(rec["q0"])
            return estim.EKF(euclid, Q=G @ Q3 @ G.T + 1e-12 * np.eye(4), R=R, x0=rec["q0"],
                             P0=G @ P03 @ G.T + 1e-12 * np.eye(4), jit=jit)
        variants[ADDITIVE + (", jit" if jit else "")] = additive

    def isotropic(rec):
        G = tangent_map(rec["q0"])
        return estim.EKF(euclid, Q=(SIGMA_G * DT / 2) ** 2 * np.eye(4), R=R, x0=rec["q0"],
                         P0=G @ P03 @ G.T + 1e-12 * np.eye(4))
    variants[ISOTROPIC] = isotropic

    names = ["ahrs EKF", "ahrs EKF, its default P0 = I4", *variants]
    rmse: dict[str, list[float]] = {n: [] for n in names}
    step_time: dict[str, list[float]] = {n: [] for n in names}
    norm_dev: dict[str, float] = {n: 0.0 for n in names}
    builds: dict[str, list[float]] = {n: [] for n in variants}
    jit_vs_plain = 0.0
    t_start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", estim.EstimationWarning)
        for seed in range(args.seeds):
            rec = make_record(seed, T)
            Y, U = estim_data(rec)
            G = tangent_map(rec["q0"])
            runs = {"ahrs EKF": lambda rec=rec, G=G: run_ahrs(
                        rec, G @ P03 @ G.T + 1e-12 * np.eye(4)),
                    "ahrs EKF, its default P0 = I4": lambda rec=rec: run_ahrs(rec, None)}
            estimates = {}
            for name in names:
                if name in variants:
                    t0 = time.perf_counter()
                    est = variants[name](rec)
                    builds[name].append(time.perf_counter() - t0)
                    x, times = run_estim(est, Y, U)
                else:
                    x, times = runs[name]()
                estimates[name] = x
                err = error_angle(x, rec["q"])[startup:]
                rmse[name].append(float(np.rad2deg(np.sqrt(np.mean(err**2)))))
                step_time[name].append(float(np.median(times[1:])))
                norm_dev[name] = max(norm_dev[name],
                                     float(np.abs(np.linalg.norm(x, axis=1) - 1).max()))
            for name in estimates:
                if name.endswith(", jit"):
                    jit_vs_plain = max(jit_vs_plain, float(np.abs(
                        estimates[name] - estimates[name[:-5]]).max()))
    wall = time.perf_counter() - t_start

    print(f"\nattitude error angle RMSE after {args.startup:g} s: median [range] over "
          f"{args.seeds} seeds;  wall time per step: median over each record, median "
          f"[range] over the records;  max | |q_hat| - 1 |")
    print(f"  {'filter':46s} {'RMSE':>28s}   {'per step':>26s}   norm dev.")
    for name in names:
        print(f"  {name:46s} {_deg(rmse[name]):>28s}   {_us(step_time[name]):>26s}   "
              f"{norm_dev[name]:.1e}")
    if cc:
        print(f"  (jit against interpreted, max |x_hat difference|: {jit_vs_plain:.1e})")
    print("  (the additive rows are not normalised after the update; the others are unit)")
    print("paired by seed, RMSE difference to estim's EKF: median [range]")
    ref = np.array(rmse["estim EKF (multiplicative)"])
    for name in ("ahrs EKF", "estim UKF (tangent sigma)", ADDITIVE, ISOTROPIC):
        d = np.array(rmse[name]) - ref
        print(f"  {name:46s} {np.median(d):+.1e} deg [{d.min():+.1e}, {d.max():+.1e}]")
    base = statistics.median(step_time["ahrs EKF"])
    print("\nper-step ratio ahrs EKF / estim (> 1: estim faster); construction (median)")
    for name in variants:
        print(f"  {name:46s} {base / statistics.median(step_time[name]):6.2f}x   "
              f"build {1e3 * statistics.median(builds[name]):8.1f} ms")
    mult = statistics.median(step_time["estim EKF (multiplicative)"])
    add = statistics.median(step_time[ADDITIVE])
    print(f"\nmultiplicative / additive EKF per step: {mult / add:.2f}x interpreted", end="")
    if cc:
        mult = statistics.median(step_time["estim EKF (multiplicative), jit"])
        add = statistics.median(step_time[ADDITIVE + ", jit"])
        print(f", {mult / add:.2f}x with jit", end="")
    print(f"\nwall time of the comparison {wall:.1f} s; load average "
          + ", ".join(f"{v:.2f}" for v in os.getloadavg()) + " (1, 5, 15 min)")


if __name__ == "__main__":
    main()
