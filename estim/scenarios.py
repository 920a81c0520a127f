"""Experiments: a model plus everything needed to run an estimator on it.

Each function reproduces one experiment of the source documents; the values
are those of ``models.md`` (and, where a source is silent, chosen and stated
in the docstring). ``scenario.tuning`` is the ``{Q, R, x0, P0}`` dict an
estimator takes, so ``estim.EKF(sc.model, **sc.tuning)`` is the whole set-up.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from estim import models
from estim._validate import (
    as_bool,
    as_choice,
    as_covariance,
    as_float,
    as_input_table,
    as_int,
    as_vector,
    check_call,
    did_you_mean,
)
from estim.model import Model


def check_plant_changes(changes, model: Model, name: str = "plant_changes") -> list:
    """``[(time, {param: value}), ...]`` checked against ``model``; returns a list of
    ``(float, dict)`` pairs."""
    if changes is None:
        return []
    if isinstance(changes, Mapping | str) or not hasattr(changes, "__iter__"):
        raise TypeError(f"{name} must be a list of (time, {{param: value}}) pairs, "
                        f"got {type(changes).__name__}")
    out = []
    for i, entry in enumerate(changes):
        if not isinstance(entry, tuple | list) or len(entry) != 2:
            raise TypeError(f"{name}[{i}] must be a (time, {{param: value}}) pair, "
                            f"got {entry!r}")
        t, values = entry
        t = as_float(t, f"{name}[{i}] time")
        if not isinstance(values, Mapping):
            raise TypeError(f"{name}[{i}] must map parameter names to values, "
                            f"got {type(values).__name__}")
        unknown = [k for k in values if k not in model.param_names]
        if unknown:
            raise ValueError(f"{name}[{i}] names unknown parameters {unknown}; the model's "
                             f"parameters are {model.param_names}")
        values = {k: as_float(v, f"{name}[{i}][{k!r}]") for k, v in values.items()}
        out.append((t, values))
    return out


@dataclass
class Scenario:
    """One experiment.

    Attributes
    ----------
    name : str
    model : Model
        The plant, and the model the estimators are given.
    x0 : (nx,) array
        True initial state.
    n_steps : int
        Number of samples.
    Q : (nx, nx) array
        Plant process-noise covariance (may be zero).
    R : (ny, ny) array
        Plant measurement-noise covariance.
    tuning : dict
        ``{"Q", "R", "x0", "P0"}`` for the estimator (``x0`` is its guess).
    inputs : (n_steps, nu) array or callable ``t -> u``, optional
        Open-loop input signal.
    controller : callable ``(t, x) -> u``, optional
        Feedback law; gets the estimate (``feedback="estimate"``) or the true
        state (``feedback="truth"``, e.g. an attitude sensor the estimator
        does not use).
    feedback : {"estimate", "truth"}
    clip : bool
        Clip the true state to the model bounds after each step (the KU
        Leuven course does ``x+ = max(F(x) + w, 0)``).
    plant_changes : list of (time, {param: value})
        Parameter changes of the plant at given times (faults).
    description : str
    remarks : dict of str -> str
        What is known about an estimator class on this experiment, keyed by the
        class name (``"EKF"``, ``"MHE"``, ...): shown under a comparison's table
        when such an estimator is inconsistent or far behind the best.
    """

    name: str
    model: Model
    x0: np.ndarray
    n_steps: int
    Q: np.ndarray
    R: np.ndarray
    tuning: dict
    inputs: np.ndarray | Callable | None = None
    controller: Callable | None = None
    feedback: str = "estimate"
    clip: bool = False
    plant_changes: list = field(default_factory=list)
    description: str = ""
    remarks: dict = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.name, str):
            raise TypeError(f"name must be a string, got {type(self.name).__name__}")
        if not isinstance(self.model, Model):
            raise TypeError(f"model must be an estim.Model, got {type(self.model).__name__}")
        m = self.model
        self.x0 = as_vector(self.x0, m.nx, "x0")
        self.Q = as_covariance(self.Q, m.nx, "Q", definite=False)
        self.R = as_covariance(self.R, m.ny, "R", definite=True)
        as_choice(self.feedback, ("estimate", "truth"), "feedback")
        self.n_steps = as_int(self.n_steps, "n_steps", minimum=1)
        self.clip = as_bool(self.clip, "clip")
        if not isinstance(self.tuning, Mapping):
            raise TypeError(f"tuning must be a dict of estimator arguments, "
                            f"got {type(self.tuning).__name__}")
        for key in self.tuning:
            if not isinstance(key, str):
                raise TypeError(f"tuning keys must be argument names, got {key!r}")
        if self.controller is not None and not callable(self.controller):
            raise TypeError(f"controller must be callable (t, x) -> u, "
                            f"got {type(self.controller).__name__}")
        if self.inputs is not None and self.controller is not None:
            raise ValueError("give inputs= or controller=, not both")
        if self.inputs is not None and not callable(self.inputs):
            as_input_table(self.inputs, self.n_steps, m.nu, names=m.input_names)
        self.plant_changes = check_plant_changes(self.plant_changes, m)
        if not isinstance(self.remarks, Mapping) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in self.remarks.items()):
            raise TypeError("remarks must be a dict {estimator class name: text}")
        self.remarks = dict(self.remarks)

    def replace(self, **changes: Any) -> Scenario:
        """A copy with some fields changed (e.g. ``n_steps``)."""
        from dataclasses import replace

        return replace(self, **changes)

    def __repr__(self) -> str:
        return (f"Scenario({self.name!r}, model={self.model.name}, n_steps={self.n_steps}, "
                f"dt={self.model.dt:g})")


def lorenz(n_steps: int = 100) -> Scenario:
    """OpEn's Lorenz estimation example (seed 000).

    ``x0 = (-10, -12, 27)``, 100 samples at 0.02 s (Euler map), process noise
    std 0.02 and measurement noise std 0.1 on every component. The estimator
    tuning is the true noise; its guess ``(-9, -11, 26)`` with ``P0 = I`` is
    chosen (the source solves without a prior).
    """
    m = models.lorenz()
    return Scenario("lorenz", m, x0=[-10.0, -12.0, 27.0], n_steps=n_steps, Q=0.02**2, R=0.1**2,
                    tuning={"Q": 0.02**2, "R": 0.1**2, "x0": [-9.0, -11.0, 26.0], "P0": 1.0},
                    description="Lorenz, Euler map, nonlinear 3-output sensor (OpEn)")


def van_der_pol(n_steps: int = 120) -> Scenario:
    """MPCTools' NMHE example (seed 001).

    ``x0 = (1.5, 1.5)``, 120 steps of 0.1 s, process noise std 0.1, both
    states measured with noise std 1. The estimator's guess ``(0, 0)`` with
    ``P0 = I`` is chosen (the source leaves it open).
    """
    m = models.van_der_pol()
    return Scenario("van_der_pol", m, x0=[1.5, 1.5], n_steps=n_steps, Q=0.1**2, R=1.0,
                    tuning={"Q": 0.1**2, "R": 1.0, "x0": [0.0, 0.0], "P0": 1.0},
                    description="van der Pol, RK4 at 0.1 s, both states measured (MPCTools)")


_REACTOR_KALMAN = (
    "from the guess (1, 0, 4) the filter settles on a wrong, partly negative state that "
    "explains the one measured sum of concentrations as well as the truth: a bias its "
    "covariance does not describe, decaying slowly (docs/ekf.md); the MHE's bound x >= 0 "
    "rules that state out")


def batch_reactor(n_steps: int = 400) -> Scenario:
    """KU Leuven MPC course, session 5 (seed 002).

    True ``x0 = (0.5, 0.05, 0)``, guess ``(1, 0, 4)`` with ``P0 = 0.5² I``,
    ``σ_w = 0.002``, ``σ_v = 0.25``, 400 steps of 0.25 s, and the plant
    clipped to ``x ≥ 0`` as in the course simulator.
    """
    m = models.batch_reactor()
    return Scenario("batch_reactor", m, x0=[0.5, 0.05, 0.0], n_steps=n_steps, Q=0.002**2,
                    R=0.25**2, clip=True,
                    tuning={"Q": 0.002**2, "R": 0.25**2, "x0": [1.0, 0.0, 4.0], "P0": 0.5**2},
                    description="batch reactor A <-> B + C, 2B <-> C, y = 32.84 sum(C) (KU Leuven)",
                    remarks={kind: _REACTOR_KALMAN for kind in ("EKF", "UKF")})


def runaway(n_steps: int = 6000, gamma: float = 0.5, gamma1: float = 2.5) -> Scenario:
    """Runaway electrons with ``(gamma, gamma1)`` identified (seed 004, sec. 2.5).

    The model is augmented with ``gamma, gamma1`` (state
    ``(x1, x2, gamma, gamma1) >= 0``); truth ``(0, 0.001, 0.5, 2.5)``, the
    report's guess ``(-0.0001, 0.0006, 0.5004, 2.4886)``, measurement noise
    std 1e-4 on ``y = x2``, no process noise, ``dt = 5e-4`` s, 3 s (6000
    steps). Estimator covariances (chosen): ``Q = diag(1e-10, 1e-10, 1e-12,
    1e-12)`` and ``P0 = diag(1e-6, 1e-6, 1e-4, 1e-4)``.
    """
    m = models.runaway(gamma=gamma, gamma1=gamma1).augment("gamma", "gamma1", lower=0.0)
    return Scenario(
        "runaway", m, x0=[0.0, 0.001, gamma, gamma1], n_steps=n_steps, Q=0.0, R=1e-4**2,
        tuning={"Q": [1e-10, 1e-10, 1e-12, 1e-12], "R": 1e-4**2,
                "x0": [-0.0001, 0.0006, 0.5004, 2.4886], "P0": [1e-6, 1e-6, 1e-4, 1e-4]},
        description="runaway electrons, bursts every 0.2865 s, (gamma, gamma1) as states",
    )


def satellite(excitation: bool = True, fault: bool = True, n_steps: int = 400,
              fault_time: float = 200.0, fault_factor: float = 0.4) -> Scenario:
    """Small satellite with a gyro, PD attitude control and an inertia fault (seed 004).

    ``I = diag(0.50, 0.40, 0.26)``, circular 7000 km orbit, ``q0 = (1,0,0,0)``,
    ``omega0 = (0.02, -0.015, 0.01)`` rad/s, gyro noise std 1e-3 rad/s,
    ``dt = 1`` s, 400 s. With ``excitation`` the PD law
    (``Kp = 0.01``, ``Kd = 0.09``, fed by the true attitude) tracks the
    persistently exciting target of :func:`estim.models.reference_attitude`;
    without it no torque acts (the report's "no input" case). With ``fault``
    the plant inertia drops to ``0.4 I`` at 200 s. Estimator tuning
    (chosen): ``Q = diag(1e-10 (q), 1e-8 (omega), 1e-12 (theta))``, guess
    ``omega = 0`` with ``P0 = diag(1e-4, 1e-3, 1e-8)`` blocks.
    """
    excitation, fault = as_bool(excitation, "excitation"), as_bool(fault, "fault")
    fault_time = as_float(fault_time, "fault_time")
    fault_factor = as_float(fault_factor, "fault_factor", positive=True)
    m = models.satellite()
    x0 = np.array([1.0, 0.0, 0.0, 0.0, 0.02, -0.015, 0.01, 0.0])
    changes = []
    if fault:
        changes.append((fault_time, {k: fault_factor * v for k, v in m.params.items()
                                     if k in ("I1", "I2", "I3")}))
    controller = models.PDAttitudeController(excitation=True) if excitation else None
    guess = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    return Scenario(
        "satellite" if excitation else "satellite_no_excitation", m, x0=x0, n_steps=n_steps,
        Q=0.0, R=1e-3**2, controller=controller, feedback="truth", plant_changes=changes,
        tuning={"Q": [1e-10] * 4 + [1e-8] * 3 + [1e-12], "R": 1e-3**2, "x0": guess,
                "P0": [1e-4] * 4 + [1e-3] * 3 + [1e-8]},
        description="satellite attitude, gyro only, PD control"
                    + (" with exciting target" if excitation else " off") +
                    (f", inertia x{fault_factor} at {fault_time:g} s" if fault else ""),
    )


@dataclass
class Record:
    """A recorded experiment for :func:`estim.replay`: measurements, known inputs, truth.

    Attributes
    ----------
    name : str
    model : Model
        The model an estimator uses on this record.
    t : (T,) array
    y : (T, ny) array
    u : (T, nu) array
        ``u[k]`` acts after sample ``k``.
    x : (T, nx) array
        True states of ``model``.
    tuning : dict
        ``{"R", "x0", "P0"}`` suggestions for an estimator.
    description : str
    """

    name: str
    model: Model
    t: np.ndarray
    y: np.ndarray
    u: np.ndarray
    x: np.ndarray
    tuning: dict
    description: str = ""


def satellite_inertia(excitation: bool = True, fault: bool = True, n_steps: int = 400,
                      seed: int = 0, guess: Sequence[float] = (0.40, 0.50, 0.20)) -> Record:
    """Inertia identification record (Oliva & Carnevale, sec. 2.1-2.4).

    The full attitude plant of :func:`satellite` (PD control on the true
    attitude, exciting target or no torque, inertia x0.4 at 200 s) is
    simulated; the record holds the gyro, the known inputs of
    :func:`estim.models.satellite_rates` (torque and nadir direction in body
    axes, from the known attitude) and the truth ``(omega, I1, I2, I3)``. The
    model is ``satellite_rates().augment("I1", "I2", "I3")`` with inertias
    bounded to [0.01, 10]; the suggested guess keeps ``omega`` at the first
    gyro sample and the inertias at ``guess`` (chosen, 20-25 % off).
    """
    from estim.estimators.ekf import EKF
    from estim.simulate import simulate

    guess = as_vector(guess, 3, "guess")
    sc = satellite(excitation=excitation, fault=fault, n_steps=n_steps)
    log = simulate(sc, EKF(sc.model, **sc.tuning), seed=seed)
    nadir = np.array([models.nadir_in_body(x) for x in log.x])
    u = np.hstack([log.u, nadir])
    inertia = np.tile([sc.model.params[k] for k in ("I1", "I2", "I3")], (n_steps, 1))
    for t_change, values in sc.plant_changes:
        inertia[log.t >= t_change - 1e-12] = [values[k] for k in ("I1", "I2", "I3")]
    model = models.satellite_rates().augment("I1", "I2", "I3", lower=0.01, upper=10.0)
    x_true = np.hstack([log.x[:, 4:7], inertia])
    guess = np.r_[log.y[0], np.asarray(guess, float)]
    return Record(
        name=sc.name + "_inertia", model=model, t=log.t, y=log.y, u=u, x=x_true,
        tuning={"R": 1e-3**2, "x0": guess, "P0": None},
        description=sc.description + "; omega and inertia identification on gyro data",
    )


#: Scenario factories by name (used by the command line and comparisons).
SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "lorenz": lorenz,
    "van_der_pol": van_der_pol,
    "batch_reactor": batch_reactor,
    "runaway": runaway,
    "satellite": satellite,
}


def get(name: str, **kwargs: Any) -> Scenario:
    """Build a scenario by name, e.g. ``estim.scenarios.get("batch_reactor")``.

    Parameters
    ----------
    name : str
        One of :data:`SCENARIOS`.
    **kwargs
        Arguments of that scenario's function (e.g. ``n_steps``).
    """
    if not isinstance(name, str):
        raise TypeError(f"name must be a scenario name (str), got {type(name).__name__}")
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; known: {sorted(SCENARIOS)}"
                         f"{did_you_mean(name, SCENARIOS)}")
    check_call(SCENARIOS[name], kwargs, f"scenario {name!r}")
    return SCENARIOS[name](**kwargs)
