r"""The Silverbox's Duffing grey-box in sample time: its simulation and its two fits.

``examples/silverbox_identification.py`` fits and validates it;
``benchmarks/silverbox.py`` measures the two fits against each other.

Model. The circuit obeys :math:`m\ddot y + d\dot y + k y + k_3 y^3 = u`. It
is written with time in samples, :math:`\tau = f_s t`, the state
:math:`x = (y, v)`, :math:`v = dy/d\tau` (volts per sample), and five
parameters :math:`\theta = (b, a_1, a_0, a_3, u_0)`:

.. math::
    \frac{dy}{d\tau} = v, \qquad
    \frac{dv}{d\tau} = b\,(u - u_0) - a_1 v - a_0 y - a_3 y^3,

i.e. :math:`b = 1/(m f_s^2)`, :math:`a_1 = d/(m f_s)`, :math:`a_0 =
k/(m f_s^2)`, :math:`a_3 = k_3/(m f_s^2)`, and :math:`u_0` an offset of the
measured input (in mV in :math:`\theta`, volts in the equation). Why this
parametrisation:

* Scaling. In seconds :math:`a_0 = \omega_0^2 \approx 1.9\cdot10^5`,
  :math:`a_1 \approx 41`, :math:`b \approx 1.9\cdot10^5`; per sample they are
  0.50, 0.067 and 0.52, :math:`a_3 \approx 2` V⁻² (with :math:`|y| \le 0.3`
  V), :math:`u_0 \approx 5` mV: every unknown is O(0.05-5), so the
  Jacobian's columns are commensurate and ``least_squares``' default
  ``x_scale=1`` works (``x_scale="jac"`` changes neither the optimum nor the
  iteration count here). RK4 is invariant under the time scaling: the
  discrete model equals RK4 in seconds at :math:`h = 1/f_s`.
* Identifiability. :math:`(b, a_1, a_0, a_3)` are the four ratios the
  input-output data determine (the Duffing equation divided by :math:`m`;
  :math:`m, d, k, k_3` follow since :math:`u` is measured in volts). The
  fifth parameter has to carry the data's offsets: the input rests at
  6.2 mV, the output at 0.9 mV. Measured on 10 000 samples (FOH): an input
  offset fits best (train 0.950 mV, arrow 1.003 mV); an output offset
  :math:`y = x_1 + c` gives 1.075 / 1.179 mV; both offsets (six parameters)
  0.931 / 0.971 mV.
* Initial state. The training record starts inside the multisine, so
  :math:`x_0` is estimated too (7 unknowns); the arrow starts at rest
  (after a decaying transient of about 2 mV), so its simulation starts from
  :math:`(y_0, y_1 - y_0)` (:func:`start_state`).

Discretisation: one RK4 step per sample (the parameters absorb its error:
the FOH optimum simulated with 4 substeps gives 2.7 mV instead of 1.0 mV),
the input held (ZOH: stage inputs :math:`u_k, u_k, u_k, u_k`) or linear
between samples (FOH: :math:`u_k, \bar u, \bar u, u_{k+1}`, :math:`\bar u =
(u_k + u_{k+1})/2`). The step is one SX Function ``F(x, (u_k, u_{k+1}),
theta)`` (:func:`duffing_model`) whatever the hold.

Simulation-error least squares (:func:`fit_least_squares`, what a CasADi user
writes without estim): the simulation is ``F.mapaccum(N - 1)``, the residual
:math:`r(z) = \hat y(z) - y`, :math:`z = (\theta, x_0)`, one MX Function, its
Jacobian ``ca.jacobian(r, z)`` (N × 7, CasADi's AD through the map) another;
the data are baked in as constants. ``scipy.optimize.least_squares(fun, z0,
jac=...)`` (``method="trf"`` or ``"lm"``), default tolerances (1e-8), started
from a linear ARX(2, 2) fit converted to :math:`(b, a_1, a_0, u_0)` with
:math:`a_3 = 0` (:func:`initial_guess`).

Full-information estimation (:func:`fit_estim`): ``estim.Model`` of the same
equations with the five parameters as ``params`` (:func:`estim_model`; ZOH:
``ode=`` in seconds, RK4 at :math:`1/f_s`, identical to the least-squares
step). FOH is written two ways: "workaround", a hand-written RK4
``dynamics=`` whose input vector is :math:`(u_k, u_{k+1})` (two inputs,
``U[k] = (u_k, u_{k+1})``), all that estim's Model allowed before ``hold=``;
and "native", the ZOH model's ``ode=`` with ``Model(..., hold="foh")`` and
``U`` the input at the samples (estim from commit 97efe41 on; detected, see
:func:`native_foh`). Then ``model.augment(*PARAMS)`` and
``estim.FullInformation(aug, Q=..., R=..., x0=(0, 0, θ_ARX),
solver=...).fit(Y, U, guess=...)``, from one of three initial trajectories
(:func:`estim_guess`): "measured" (the measured :math:`y`, its central
difference for :math:`v`, the ARX parameters: the same start as
least_squares), "simulated" (the model's simulation under the ARX
parameters, 10-14 mV off the data), "constant" (estim's default: ``x0``
repeated). ``Q = diag(q σ_y², q σ_v², q_θ s_θ²)`` (:func:`estim_Q`) with
:math:`σ` the standard deviations of the training :math:`y` and of its
central difference and :math:`s_θ = (0.5, 0.07, 0.5, 2, 5)` the parameters'
magnitudes; ``R`` the output-error variance of each hold's optimum: (1 mV)²
for FOH (the least-squares output error on the training record is 0.95 mV
RMS; the sensor noise cannot be separated from the model error on these
data), (13.4 mV)² for ZOH. With :math:`Q \to 0` the full-information
problem becomes the simulation-error problem (the states follow the model
exactly from a free :math:`x_0`), so the parameters should approach the
least-squares ones; the reported θ is the mean of the augmented states over
the record. The first fit (construction, graphs built) and a second one
(same estimator) are timed separately.
"""

from __future__ import annotations

import inspect
import time
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

import estim

FS = 1e7 / 2**14                 # sampling frequency [Hz]
PARAMS = ("b", "a1", "a0", "a3", "u0")
U0_SCALE = 1e-3                  # u0 is in mV inside theta
HOLDS = ("zoh", "foh")
FOH_MODELS = ("workaround", "native")  # how the estim model writes the first-order hold
#: magnitudes of the parameters (for the process-noise covariance of the estim fit)
PARAM_SCALE = np.array([0.5, 0.07, 0.5, 2.0, 5.0])
#: R of the estim fit: the output-error variance of each hold's optimum, (1 mV)^2 with
#: the first-order hold, (13.4 mV)^2 with the zero-order hold
R_ESTIM = {"foh": 1e-3**2, "zoh": 13.4e-3**2}


# --------------------------------------------------------------------------------- model
def rhs(x, u, theta):
    """Duffing right-hand side in sample time: ``(v, b (u - u0) - a1 v - a0 y - a3 y^3)``."""
    b, a1, a0, a3, u0 = (theta[i] for i in range(5))
    y, v = x[0], x[1]
    return ca.vertcat(v, b * (u - U0_SCALE * u0) - a1 * v - a0 * y - a3 * y**3)


def rk4_step(x, u_k, u_next, theta, hold: str, f=rhs):
    """One RK4 step of ``f(x, u, theta)`` over one sample, the input held or linear."""
    if hold not in HOLDS:
        raise ValueError(f"hold must be one of {HOLDS}, got {hold!r}")
    if hold == "zoh":
        u_a = u_m = u_b = u_k
    else:
        u_a, u_m, u_b = u_k, (u_k + u_next) / 2, u_next
    k1 = f(x, u_a, theta)
    k2 = f(x + k1 / 2, u_m, theta)
    k3 = f(x + k2 / 2, u_m, theta)
    k4 = f(x + k3, u_b, theta)
    return x + (k1 + 2 * k2 + 2 * k3 + k4) / 6


def duffing_model(hold: str) -> ca.Function:
    """The discrete model ``F(x (2), (u_k, u_{k+1}), theta (5)) -> x_{k+1}`` (SX)."""
    x, uu, th = ca.SX.sym("x", 2), ca.SX.sym("u", 2), ca.SX.sym("theta", 5)
    return ca.Function(f"duffing_{hold}", [x, uu, th], [rk4_step(x, uu[0], uu[1], th, hold)],
                       ["x", "u", "theta"], ["x_next"])


def input_pairs(u: np.ndarray) -> np.ndarray:
    """``(2, N-1)``: the columns ``(u_k, u_{k+1})`` that drive the steps k -> k+1."""
    u = np.asarray(u, dtype=float)
    return np.vstack([u[:-1], u[1:]])


def rollout(F, x0, U, theta):
    """The states ``(2, N)`` from ``x0`` through the steps ``F`` driven by the columns
    ``U (2, N-1)`` (see :func:`input_pairs`), ``theta`` fixed: symbolic or numeric."""
    n = U.shape[1]
    return ca.horzcat(x0, F.mapaccum(n)(x0, U, ca.repmat(theta, 1, n)))


_SIMULATORS: dict[tuple[str, int], ca.Function] = {}


def simulate(theta, u: np.ndarray, hold: str, x0) -> np.ndarray:
    """Simulated output ``(N,)`` from ``x0`` under the input ``u (N,)``."""
    N = len(u)
    key = (hold, N)
    if key not in _SIMULATORS:
        F = duffing_model(hold)
        th, x0s, U = ca.MX.sym("theta", 5), ca.MX.sym("x0", 2), ca.MX.sym("U", 2, N - 1)
        _SIMULATORS[key] = ca.Function("sim", [th, x0s, U], [rollout(F, x0s, U, th)[0, :]])
    y = _SIMULATORS[key](np.asarray(theta, float), np.asarray(x0, float), input_pairs(u))
    return np.asarray(y).ravel()


def start_state(y: np.ndarray) -> np.ndarray:
    """A state to start a simulation at a measured record: ``(y_0, y_1 - y_0)``."""
    return np.array([y[0], y[1] - y[0]])


def rmse_mv(theta, u: np.ndarray, y: np.ndarray, hold: str) -> float:
    """RMSE in mV of the simulation of ``(u, y)`` from :func:`start_state`."""
    e = simulate(theta, u, hold, start_state(y)) - y
    return 1e3 * float(np.sqrt(np.mean(e**2)))


def initial_guess(u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``theta0, x0``: a linear ARX(2, 2) with a constant, converted; ``a3 = 0``.

    ``y_k = -α1 y_{k-1} - α2 y_{k-2} + β1 u_{k-1} + β2 u_{k-2} + c`` by linear
    least squares; its poles :math:`z = e^{s}` (per sample) give :math:`a_0 =
    |s|^2`, :math:`a_1 = -2\\,\\mathrm{Re}\\,s`; the static gain :math:`G` and
    offset give :math:`b = a_0 G` and :math:`u_0`.
    """
    Phi = np.column_stack([-y[1:-1], -y[:-2], u[1:-1], u[:-2], np.ones(len(y) - 2)])
    al1, al2, b1, b2, c = np.linalg.lstsq(Phi, y[2:], rcond=None)[0]
    s = np.log(np.roots([1.0, al1, al2]).astype(complex))[0]
    a0, a1 = abs(s) ** 2, -2 * s.real
    den = 1 + al1 + al2
    G = (b1 + b2) / den
    u0 = -(c / den) / G
    return np.array([a0 * G, a1, a0, 0.0, u0 / U0_SCALE]), start_state(y)


# ----------------------------------------------------------------------- least squares
@dataclass
class LeastSquaresFit:
    """A simulation-error fit: ``theta`` (b, a1, a0, a3, u0 [mV]) and ``x0``."""

    theta: np.ndarray
    x0: np.ndarray
    cost: float
    train_rmse: float           # volts
    nfev: int
    njev: int
    status: int
    message: str
    build_seconds: float        # CasADi Functions
    solve_seconds: float        # least_squares


def residual_functions(u: np.ndarray, y: np.ndarray, hold: str) -> tuple[ca.Function, ...]:
    """``r(z)`` and ``J(z) = dr/dz``, ``z = (theta, x0)``: the simulation error as Functions."""
    F = duffing_model(hold)
    z = ca.MX.sym("z", 7)
    th, x0 = z[:5], z[5:]
    r = rollout(F, x0, ca.DM(input_pairs(u)), th)[0, :].T - ca.DM(np.asarray(y, float))
    return ca.Function("r", [z], [r]), ca.Function("J", [z], [ca.jacobian(r, z)])


def fit_least_squares(u: np.ndarray, y: np.ndarray, hold: str, method: str = "trf",
                      theta0=None, x0=None, **options) -> LeastSquaresFit:
    """Fit ``theta`` and ``x0`` by ``scipy.optimize.least_squares`` on the simulation error."""
    u, y = np.asarray(u, float), np.asarray(y, float)
    t0 = time.perf_counter()
    r_fun, j_fun = residual_functions(u, y, hold)
    t1 = time.perf_counter()
    g_theta, g_x0 = initial_guess(u, y)
    z0 = np.concatenate([g_theta if theta0 is None else theta0, g_x0 if x0 is None else x0])
    res = least_squares(lambda z: r_fun(z).full().ravel(), z0,
                        jac=lambda z: j_fun(z).full(), method=method, **options)
    t2 = time.perf_counter()
    return LeastSquaresFit(
        theta=res.x[:5], x0=res.x[5:], cost=float(res.cost),
        train_rmse=float(np.sqrt(np.mean(res.fun**2))), nfev=int(res.nfev),
        njev=int(res.njev if res.njev is not None else 0), status=int(res.status),
        message=res.message, build_seconds=t1 - t0, solve_seconds=t2 - t1)


# -------------------------------------------------------------------------------- estim
def native_foh() -> bool:
    """Whether this estim's Model models the input between samples (``hold=``)."""
    return "hold" in inspect.signature(estim.Model).parameters


def estim_model(hold: str, theta=None, foh: str = "workaround"):
    """``estim.Model`` of the circuit with the parameters as ``params``, not augmented.

    ZOH: ``ode=`` in seconds (``fs`` times the sample-time right-hand side),
    RK4 at ``dt = 1/fs``. FOH, ``foh="workaround"``: a hand-written RK4
    ``dynamics=`` whose input is ``(u_k, u_{k+1})``; ``foh="native"``: the ZOH
    model's ``ode=`` with ``Model(..., hold="foh")`` (estim versions that have it).
    """
    params = dict(zip(PARAMS, PARAM_SCALE if theta is None else np.asarray(theta, float),
                      strict=True))

    def vec(p):
        return ca.vertcat(*(p[n] for n in PARAMS))

    def output(x, u, p):
        return x[0]

    common = dict(states=["y", "v"], outputs=["y"], output=output, params=params, dt=1.0 / FS,
                  name=f"silverbox_{hold}")
    if hold not in HOLDS or foh not in FOH_MODELS:
        raise ValueError(f"hold must be one of {HOLDS} and foh one of {FOH_MODELS}")
    if hold == "zoh" or foh == "native":
        extra = {"hold": hold} if hold == "foh" else {}
        return estim.Model(inputs=["u"], ode=lambda x, u, p: FS * rhs(x, u[0], vec(p)),
                           **common, **extra)
    return estim.Model(inputs=["u", "u_next"],
                       dynamics=lambda x, u, p: rk4_step(x, u[0], u[1], vec(p), "foh"),
                       **common)


def estim_inputs(u: np.ndarray, hold: str, foh: str = "workaround") -> np.ndarray:
    """``U (N, nu)`` for :func:`estim_model`: ``u``, or ``(u_k, u_{k+1})`` (FOH workaround)."""
    u = np.asarray(u, float)
    if hold == "zoh" or foh == "native":
        return u[:, None]
    return np.column_stack([u, np.append(u[1:], u[-1])])  # the last row is never used


def estim_Q(y: np.ndarray, q: float, q_param: float) -> np.ndarray:
    """Process-noise variances: ``q σ²`` for (y, v), ``q_param s_θ²`` for the parameters."""
    v = np.gradient(y)
    return np.concatenate([q * np.array([np.var(y), np.var(v)]), q_param * PARAM_SCALE**2])


GUESSES = ("measured", "simulated", "constant")


def estim_guess(u: np.ndarray, y: np.ndarray, hold: str, kind: str = "measured"):
    """The initial trajectory ``(N, 7)`` of a fit, or None for estim's default.

    ``"measured"``: the measured y, its central difference for v, the ARX
    parameters repeated; ``"simulated"``: the model's simulation under the
    ARX parameters from :func:`start_state` (process residuals zero);
    ``"constant"``: None, i.e. estim's default guess, ``x0 = (0, 0, theta_ARX)``
    repeated (what ``FullInformation(..., x0=...).fit(Y, U)`` does).
    """
    if kind not in GUESSES:
        raise ValueError(f"guess must be one of {GUESSES}, got {kind!r}")
    if kind == "constant":
        return None
    theta0, x0 = initial_guess(u, y)
    P = np.repeat(theta0[None, :], len(y), 0)
    if kind == "measured":
        return np.column_stack([y, np.gradient(y), P])
    X = rollout(duffing_model(hold), ca.DM(x0), ca.DM(input_pairs(u)), ca.DM(theta0))
    return np.column_stack([np.asarray(X).T, P])


@dataclass
class EstimFit:
    """One ``FullInformation.fit`` of the augmented model (two calls: build + fit, refit)."""

    theta: np.ndarray
    x0: np.ndarray
    theta_spread: float          # max over samples of |theta_k - theta_mean| / s_theta
    cost: float
    iterations: int
    status: str
    success: bool
    first_seconds: float         # construction + first fit (graphs built)
    second_seconds: float        # the same fit again
    solve_seconds: float         # FitResult.solve_time of the second fit
    build_seconds: float         # FitResult.build_time of the first fit (nan if absent)


def fit_estim(u: np.ndarray, y: np.ndarray, hold: str, solver: str = "gauss-newton",
              q: float = 1e-6, q_param: float = 1e-6, solver_options: dict | None = None,
              guess: str = "measured", refit: bool = True,
              foh: str = "native", collect: Callable[[], object] | None = None) -> EstimFit:
    """Full-information estimation of the augmented model over the record (``refit``:
    a second fit by the same estimator, timed apart; ``collect``, if given, is called
    untimed before it, e.g. ``gc.collect``)."""
    u, y = np.asarray(u, float), np.asarray(y, float)
    t0 = time.perf_counter()
    theta0 = initial_guess(u, y)[0]
    model = estim_model(hold, theta0, foh).augment(*PARAMS)
    fie = estim.FullInformation(model, Q=estim_Q(y, q, q_param), R=R_ESTIM[hold],
                                x0=np.concatenate([[0.0, 0.0], theta0]), solver=solver,
                                solver_options=solver_options)
    U, X0 = estim_inputs(u, hold, foh), estim_guess(u, y, hold, guess)
    res = fie.fit(y[:, None], U, guess=X0)
    first = time.perf_counter() - t0
    build = float(getattr(res, "build_time", float("nan")))
    second = float("nan")
    if refit:
        if collect is not None:
            collect()
        t1 = time.perf_counter()
        res = fie.fit(y[:, None], U, guess=X0)
        second = time.perf_counter() - t1
    P = res.x[:, 2:]
    theta = P.mean(axis=0)
    return EstimFit(theta=theta, x0=res.x[0, :2],
                    theta_spread=float(np.max(np.abs(P - theta) / PARAM_SCALE)),
                    cost=float(res.cost), iterations=int(res.iterations), status=res.status,
                    success=bool(res.success), first_seconds=first, second_seconds=second,
                    solve_seconds=float(res.solve_time), build_seconds=build)

