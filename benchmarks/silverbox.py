r"""Silverbox (measured data): a Duffing grey-box by simulation-error least squares, and estim.

Data: ``examples/data/silverbox.npz``, the shipped part of ``SNLS80mV.csv``
(``examples/silverbox_identification.py`` documents and loads it): training on
the first ``--samples`` multisine samples (CSV rows from 40 650), validation
by simulating the "arrow" (CSV rows 100-40 574, 40 475 samples) from its first
measured sample, the error reported as an RMSE in mV.

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

Baseline (what a CasADi user writes without estim): the simulation is
``F.mapaccum(N - 1)``, the residual :math:`r(z) = \hat y(z) - y`,
:math:`z = (\theta, x_0)`, one MX Function, its Jacobian
``ca.jacobian(r, z)`` (N × 7, CasADi's AD through the map) another; the
data are baked in as constants. ``scipy.optimize.least_squares(fun, z0,
jac=...)`` with ``method="trf"`` and ``"lm"``, default tolerances
(1e-8), started from a linear ARX(2, 2) fit converted to :math:`(b, a_1,
a_0, u_0)` with :math:`a_3 = 0` (:func:`initial_guess`). Wall time includes
building the CasADi Functions; ``nfev``/``njev`` are scipy's counters.

estim rows ("estim FIE"): ``estim.Model`` of the same equations with the
five parameters as ``params`` (ZOH: ``ode=`` in seconds, RK4 at
:math:`1/f_s`, identical to the baseline's step). FOH is written two ways:
"workaround", a hand-written RK4 ``dynamics=`` whose input vector is
:math:`(u_k, u_{k+1})` (two inputs, ``U[k] = (u_k, u_{k+1})``), all that
estim's Model allowed before ``hold=``; and "native", the ZOH model's
``ode=`` with ``Model(..., hold="foh")`` and ``U`` the input at the samples
(estim from commit 97efe41 on; detected, see :func:`native_foh`). Then
``model.augment(*PARAMS)`` and ``estim.FullInformation(aug, Q=..., R=...,
x0=(0, 0, θ_ARX), solver=...).fit(Y, U, guess=...)``, from one of three
initial trajectories (:func:`estim_guess`): "measured" (the measured
:math:`y`, its central difference for :math:`v`, the ARX parameters: the
same start as least_squares), "simulated" (the model's simulation under the
ARX parameters, 10-14 mV off the data), "constant" (estim's default: ``x0``
repeated). ``Q = diag(q σ_y², q σ_v², q_θ s_θ²)`` with :math:`σ` the standard
deviations of the training :math:`y` and of its central difference and
:math:`s_θ = (0.5, 0.07, 0.5, 2, 5)` the parameters' magnitudes; ``R`` the
output-error variance of each hold's optimum: (1 mV)² for FOH (the
baseline's output error on the training record is 0.95 mV RMS; the sensor
noise cannot be separated from the model error on these data), (13.4 mV)²
for ZOH. With :math:`Q \to 0` the full-information problem
becomes the simulation-error problem (the states follow the model exactly
from a free :math:`x_0`), so the parameters should approach the baseline's;
the reported θ is the mean of the augmented states over the record. First
fit (construction, graphs built) and second fit (same estimator) are timed
separately.

Memory: each case runs in its own subprocess (this script with ``--case``);
"peak MB" is that process's ``VmHWM`` (peak resident set, CasADi's C++
allocations included); about 140 MB of it is python, numpy, scipy, casadi,
estim and the data, before the case.

Measured (2-CPU x86_64, casadi 3.8.2, scipy 1.17), q = 1e-8, q_θ = 1e-14, the
"measured" start, native FOH, each figure the median of three processes:

* least_squares reproduces the README's ZOH figure (13.35 mV against 13.4)
  but not quite its FOH one (1.003 mV against 0.96; see the parametrisation
  above: 0.971 needs a sixth parameter). 6 (FOH) / 8-9 (ZOH) evaluations;
  trf and lm give the same optimum to 1e-15.
* FOH, N = 10 000: estim 5 iterations, first fit 0.35 s (build 0.12 s),
  second 0.14 s, 224 MB; least_squares trf 0.37 s, lm 0.35 s, 192 MB.
  N = 40 000: estim 4 iterations, 0.88 s (build 0.18 s), second 0.46 s,
  282 MB; trf 1.90 s, lm 1.82 s, 354 MB. The parameters agree to 1.8e-5 and
  5.1e-5 (relative), the arrow RMSE to the last digit.
* ZOH (R = (13.4 mV)²): 10 and 11 iterations; 1.06 s (10 000, trf 0.48 s)
  and 1.65 s (40 000, trf 2.38 s); parameters within 3e-6 and 1.6e-5.
* q = 1e-6 is a different estimator: the states absorb model error (a3
  11-13 % off, arrow 2.2 mV with FOH); Ipopt reaches the same optimum there.
* Starts: "simulated" converges like "measured" at every q (5-6
  iterations). "constant" (x0 repeated) converges at q_θ <= 1e-10 (7-12
  iterations); with q_θ = 1e-6 (parameters free to drift 10 % over the
  record) or q = 1e-12 it stops at max_iter far off.
* Before the rollout step of the Gauss-Newton solver (9f5ee0b) the
  "simulated" start at q = 1e-12 and the "constant" start at every q hit
  max_iter (50 or 200) at wrong parameters; a converging first fit took
  2-10 s at N = 10 000 and peaked at 375-560 MB (730-1390 MB at 40 000).
* Ipopt (``--methods ipopt``): the same optima as Gauss-Newton at q >= 1e-8
  in 11-32 iterations, 22-25 s for a first fit at N = 10 000 (mostly
  building), 2.1 GB; at q = 1e-12 it stops at 200 iterations, far off.

Run from the repository root::

    python benchmarks/silverbox.py [--samples 10000 40000] [--hold foh zoh]
        [--methods trf lm gn ipopt] [--q 1e-6:1e-6 1e-8:1e-14 1e-12:1e-12]
        [--guess measured simulated constant] [--foh-model native workaround]
        [--gn-max-iter 200] [--ipopt-max-samples 10000]

There are no timing assertions; the numbers depend on the machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import scipy
from scipy.optimize import least_squares

import estim

ROOT = Path(__file__).resolve().parents[1]
FS = 1e7 / 2**14
PARAMS = ("b", "a1", "a0", "a3", "u0")
U0_SCALE = 1e-3                  # u0 is in mV inside theta
HOLDS = ("zoh", "foh")
FOH_MODELS = ("workaround", "native")  # estim rows: how the FOH model is written
#: magnitudes of the parameters (for the process-noise covariance of the estim rows)
PARAM_SCALE = np.array([0.5, 0.07, 0.5, 2.0, 5.0])
#: R of the estim rows: the output-error variance of each hold's optimum, (1 mV)^2 with
#: the first-order hold, (13.4 mV)^2 with the zero-order hold
R_ESTIM = {"foh": 1e-3**2, "zoh": 13.4e-3**2}
#: the dataset README's figures (10 000 training samples): arrow RMSE in mV
README_RMSE_MV = {"foh": 0.96, "zoh": 13.4}


# ---------------------------------------------------------------------------------- data
def _example():
    """``examples/silverbox_identification.py`` as a module (it owns the data)."""
    name = "silverbox_identification_example"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(
            name, ROOT / "examples" / "silverbox_identification.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def load(path=None):
    """The shipped Silverbox subset (``examples/silverbox_identification.load``)."""
    ex = _example()
    return ex.load(ex.DATA if path is None else path)


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
              foh: str = "native") -> EstimFit:
    """Full-information estimation of the augmented model over the record."""
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


# ------------------------------------------------------------------------------ cases
def _vm(key: str) -> float:
    """``VmHWM`` / ``VmRSS`` of this process in MB (Linux), else ru_maxrss."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run_case(case: dict) -> dict:
    """One measurement (in this process): fit, validate on the arrow, memory."""
    data = load()
    base_mb = _vm("VmRSS")
    n, hold, method = case["samples"], case["hold"], case["method"]
    u, y = data.u_train[:n], data.y_train[:n]
    t0 = time.perf_counter()
    out = dict(case)
    if method in ("trf", "lm"):
        fit = fit_least_squares(u, y, hold, method=method)
        out.update(theta=fit.theta.tolist(), x0=fit.x0.tolist(), iterations=fit.nfev,
                   njev=fit.njev, status=f"{fit.status}: {fit.message}", success=fit.status > 0,
                   cost=fit.cost, train_mv=1e3 * fit.train_rmse,
                   build_s=fit.build_seconds, solve_s=fit.solve_seconds)
    else:
        solver = {"gn": "gauss-newton", "ipopt": "ipopt"}[method]
        fit = fit_estim(u, y, hold, solver, case["q"], case["q_param"],
                        case.get("solver_options"), case.get("guess", "measured"),
                        foh=case.get("foh", "workaround"))
        out.update(theta=fit.theta.tolist(), x0=fit.x0.tolist(), iterations=fit.iterations,
                   status=fit.status, success=fit.success, cost=fit.cost,
                   train_mv=1e3 * float(np.sqrt(np.mean(
                       (simulate(fit.theta, u, hold, fit.x0) - y) ** 2))),
                   theta_spread=fit.theta_spread, first_s=fit.first_seconds,
                   second_s=fit.second_seconds, solve_s=fit.solve_seconds,
                   build_s=fit.build_seconds)
    out["wall_s"] = time.perf_counter() - t0
    theta = np.array(out["theta"])
    out["arrow_mv"] = rmse_mv(theta, data.u_test, data.y_test, hold) \
        if np.isfinite(theta).all() else float("nan")
    out["peak_mb"], out["base_mb"] = _vm("VmHWM"), base_mb
    return out


def run_isolated(case: dict) -> dict:
    """:func:`run_case` in a fresh subprocess (its own peak memory)."""
    proc = subprocess.run([sys.executable, __file__, "--case", json.dumps(case)], cwd=ROOT,
                          capture_output=True, text=True)
    if proc.returncode != 0:
        return dict(case, error=(proc.stderr.strip().splitlines() or ["?"])[-1])
    return json.loads(proc.stdout.strip().splitlines()[-1])


def label(r: dict) -> str:
    """The method column: least_squares trf/lm, or estim with solver, guess and Q."""
    if r["method"] in ("trf", "lm"):
        return f"least_squares {r['method']}"
    name = "gauss-newton" if r["method"] == "gn" else r["method"]
    opts = r.get("solver_options") or {}
    extra = f" it<={opts['max_iter']}" if "max_iter" in opts else ""
    foh = f" {r.get('foh', 'workaround')[:6]}" if r["hold"] == "foh" else ""
    return (f"estim FIE {name}{extra}{foh} {r.get('guess', 'measured')[:5]} "
            f"q={r['q']:.0e}/{r['q_param']:.0e}")


def _cell(value, fmt: str, width: int) -> str:
    return f"{value:>{width}{fmt}}" if value is not None and value == value else " " * width


def print_table(rows: list[dict], ref: dict) -> None:
    """Accuracy, iterations, time and memory per case."""
    head = (f"{'N':>6} {'hold':<4} {'method':<53} {'arrow mV':>8} {'train mV':>8} "
            f"{'iter':>6} {'wall s':>7} {'build':>6} {'2nd s':>6} {'peak MB':>7} {'rel Δθ':>8}"
            "  status")
    print(head)
    print("-" * len(head))
    for r in rows:
        if "error" in r:
            print(f"{r['samples']:>6} {r['hold']:<4} {label(r):<53} failed: {r['error']}")
            continue
        it = f"{r['iterations']}/{r['njev']}" if "njev" in r else str(r["iterations"])
        base = ref.get((r["samples"], r["hold"]))
        d = None if base is None or r["method"] == "trf" else \
            float(np.max(np.abs(np.array(r["theta"]) / base - 1)))
        status = r["status"] if len(r["status"]) <= 30 else r["status"][:27] + "..."
        arrow = f"{r['arrow_mv']:>8.3f}" if np.isfinite(r["arrow_mv"]) else f"{'unstable':>8}"
        print(f"{r['samples']:>6} {r['hold']:<4} {label(r):<53} {arrow} "
              f"{_cell(r.get('train_mv'), '.3f', 8)} {it:>6} "
              f"{r.get('first_s', r['wall_s']):>7.2f} {_cell(r.get('build_s'), '.2f', 6)} "
              f"{_cell(r.get('second_s'), '.2f', 6)} "
              f"{r['peak_mb']:>7.0f} {_cell(d, '.1e', 8)}  {status}")


def print_params(rows: list[dict]) -> None:
    """Fitted parameters and initial states per case (estim: record means), and the cost."""
    head = (f"{'N':>6} {'hold':<4} {'method':<53} " + " ".join(f"{n:>8}" for n in PARAMS)
            + f" {'y0':>8} {'v0':>8} {'cost':>10} {'θ drift':>8}")
    print(head)
    print("-" * len(head))
    for r in rows:
        if "error" in r:
            continue
        print(f"{r['samples']:>6} {r['hold']:<4} {label(r):<53} "
              + " ".join(f"{v:>8.5f}" if abs(v) < 100 else f"{v:>8.1f}"
                         for v in r["theta"] + r["x0"])
              + f" {r['cost']:>10.4g} {_cell(r.get('theta_spread'), '.1e', 8)}")


def parse_q(text: str) -> tuple[float, float]:
    """``"q:q_param"`` (or one number for both)."""
    q, _, qp = text.partition(":")
    return float(q), float(qp or q)


def cases_for(args) -> list[dict]:
    """Every case of the run, in order."""
    cases = []
    for n in args.samples:
        for hold in args.hold:
            cases += [dict(samples=n, hold=hold, method=m) for m in ("trf", "lm")
                      if m in args.methods]
            fohs = args.foh_model if hold == "foh" else ["workaround"]
            for q, qp in args.q:
                est = dict(samples=n, hold=hold, q=q, q_param=qp)
                if "gn" in args.methods:
                    for guess in args.guess:
                        for foh in fohs:
                            cases.append(dict(est, method="gn", guess=guess, foh=foh))
                            cases += [dict(est, method="gn", guess=guess, foh=foh,
                                           solver_options={"max_iter": k})
                                      for k in args.gn_max_iter]
                if "ipopt" in args.methods and n <= args.ipopt_max_samples:
                    cases += [dict(est, method="ipopt", guess=g, foh=fohs[0])
                              for g in args.ipopt_guess]
    return cases


def main(argv: list[str] | None = None) -> list[dict]:
    """Run every case in its own process; print the tables; return the rows."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, nargs="+", default=[10000, 40000])
    parser.add_argument("--hold", nargs="+", choices=HOLDS, default=["foh", "zoh"])
    parser.add_argument("--methods", nargs="+", choices=("trf", "lm", "gn", "ipopt"),
                        default=["trf", "lm", "gn", "ipopt"])
    parser.add_argument("--q", type=parse_q, nargs="+",
                        default=[(1e-8, 1e-14), (1e-6, 1e-6), (1e-12, 1e-12)],
                        help="estim process noise 'q:q_param' (variances relative to σ², s_θ²)")
    parser.add_argument("--guess", nargs="+", choices=GUESSES, default=["measured", "constant"],
                        help="initial trajectories of the gauss-newton rows")
    parser.add_argument("--gn-max-iter", type=int, nargs="*", default=[],
                        help="extra gauss-newton rows with this max_iter (default 50)")
    parser.add_argument("--foh-model", nargs="+", choices=FOH_MODELS,
                        default=["native"] if native_foh() else ["workaround"],
                        help="how the estim rows write the FOH model (ipopt: the first)")
    parser.add_argument("--ipopt-guess", nargs="*", choices=GUESSES, default=["measured"])
    parser.add_argument("--ipopt-max-samples", type=int, default=10000,
                        help="skip solver='ipopt' beyond this many samples (2 GB at 10000)")
    parser.add_argument("--case", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.case:
        print(json.dumps(run_case(json.loads(args.case))))
        return []
    if "native" in args.foh_model and not native_foh():
        parser.error("this estim's Model has no hold= (use --foh-model workaround)")
    if max(args.samples) > 40000 or min(args.samples) < 100:
        parser.error("--samples must be within 100..40000 (the shipped subset)")

    t_start = time.perf_counter()
    print(f"estim {estim.__version__}, casadi {ca.__version__}, scipy {scipy.__version__}, "
          f"numpy {np.__version__}, Python {platform.python_version()}, "
          f"{platform.machine()}, {os.cpu_count()} CPUs; estim from "
          f"{Path(estim.__file__).parent}")
    rows: list[dict] = []
    ref: dict[tuple[int, str], np.ndarray] = {}
    for case in cases_for(args):
        r = run_isolated(case)
        rows.append(r)
        if r["method"] == "trf" and "error" not in r:
            ref[r["samples"], r["hold"]] = np.array(r["theta"])
        print(f"  N={r['samples']} {r['hold']} {label(r)}: {r.get('wall_s', float('nan')):.1f} s",
              file=sys.stderr, flush=True)

    print("\nSilverbox, Duffing grey-box (b, a1, a0, a3, u0; x0 free) fitted on N multisine "
          "samples, validated by\nsimulating the arrow (40475 samples) from rest\n")
    print_table(rows, ref)
    base = [r["base_mb"] for r in rows if "base_mb" in r]
    print("\narrow / train mV: RMSE of the simulated output. iter: least_squares nfev/njev, "
          "estim FitResult.iterations.\nwall s: least_squares: CasADi Functions built + solve; "
          "estim: construction + first fit\n(graphs built); build: of which building "
          "(estim: FitResult.build_time, least_squares: the CasADi\nFunctions); "
          "2nd s: the same fit again. "
          "peak MB: VmHWM of the case's own process (of which "
          f"{np.median(base) if base else float('nan'):.0f} MB\nafter imports and data). "
          "rel Δθ: max_i |θ_i / θ_i(least_squares trf) - 1|. estim FIE: "
          f"FullInformation, R = {R_ESTIM['foh']:g} V² (FOH), {R_ESTIM['zoh']:g} V² (ZOH),"
          "\nQ = diag(q σ_y², q σ_v², q_θ s_θ²) shown "
          "as q=q/q_θ, guess 'measu(red)' / 'simul(ated)' / 'const(ant)', θ = record mean.")
    print()
    print_params(rows)
    print("\nb, a1, a0 per sample; a3 per V² per sample²; u0 in mV; y0 in V; v0 in V per sample. "
          "cost: least_squares\n0.5 Σ r², estim its weighted cost; θ drift: max over the "
          "record of |θ_k - mean| / s_θ.")
    trf = {(r["samples"], r["hold"]): r for r in rows
           if r["method"] == "trf" and "error" not in r}
    print()
    for hold in HOLDS:
        if (10000, hold) in trf:
            print(f"README, N = 10000, {hold.upper()}: {README_RMSE_MV[hold]} mV; measured here "
                  f"{trf[10000, hold]['arrow_mv']:.3f} mV")
    for n in args.samples:
        if (n, "foh") in trf and (n, "zoh") in trf:
            print(f"ZOH / FOH arrow RMSE at N = {n}: "
                  f"{trf[n, 'zoh']['arrow_mv'] / trf[n, 'foh']['arrow_mv']:.1f}×")
    for r in rows:
        if r["method"] == "gn" and r.get("second_s") and (r["samples"], r["hold"]) in trf:
            t = trf[r["samples"], r["hold"]]
            print(f"N={r['samples']} {r['hold']} {label(r)}: second fit / least_squares trf "
                  f"(build + solve) = {r['second_s'] / t['wall_s']:.2f}×, first fit "
                  f"{r['first_s'] / t['wall_s']:.1f}×")
    print(f"\nTotal run time {time.perf_counter() - t_start:.0f} s.")
    return rows


if __name__ == "__main__":
    main()
