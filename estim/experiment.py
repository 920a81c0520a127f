"""What an experiment is: :class:`Scenario` (a model, its plant and an estimator's
tuning) and :class:`Record` (recorded data with the truth).

:func:`~estim.simulate` runs a Scenario; :mod:`estim.scenarios` builds those of the
source documents. The classes live here, below both, so that the simulation loop
does not depend on the catalogue of experiments; ``estim.Scenario`` and
``estim.scenarios.Scenario`` are these.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import (
    as_bool,
    as_choice,
    as_covariance,
    as_float,
    as_input_table,
    as_int,
    as_vector,
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


def check_sampling(sampling, model: Model, name: str = "sampling") -> dict[str, tuple[int, int]]:
    """``{output: every}`` or ``{output: (every, first)}`` checked against ``model``'s
    outputs; returns ``{output: (every, first)}`` (``first`` 0 when not given)."""
    if sampling is None:
        return {}
    if not isinstance(sampling, Mapping):
        raise TypeError(f"{name} must be a dict {{output name: every}} or {{output name: "
                        f"(every, first)}}, got {type(sampling).__name__}")
    out = {}
    for key, value in sampling.items():
        if key not in model.output_names:
            raise ValueError(f"{name} names {key!r}, not an output of {model.name}; its "
                             f"outputs are {model.output_names}"
                             f"{did_you_mean(str(key), model.output_names)}")
        pair = isinstance(value, tuple | list) and len(value) == 2
        every, first = value if pair else (value, 0)
        out[key] = (as_int(every, f"{name}[{key!r}] every", minimum=1),
                    as_int(first, f"{name}[{key!r}] first", minimum=0))
    return out


def silent_outputs(sampling: Mapping[str, tuple[int, int]], model: Model, T: int
                   ) -> np.ndarray | None:
    """``(T, ny)`` bool: True where an output of ``sampling`` (checked by
    :func:`check_sampling`) is not reported (sample ``k`` reports when ``k >= first`` and
    ``(k - first) % every == 0``); None without ``sampling``."""
    if not sampling:
        return None
    mask = np.zeros((T, model.ny), dtype=bool)
    k = np.arange(T)
    for key, (every, first) in sampling.items():
        mask[:, model.output_names.index(key)] = (k < first) | ((k - first) % every != 0)
    return mask


@dataclass(init=False)
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
        Plant process-noise covariance (may be zero); ``(ndx, ndx)``, in the tangent
        space, for a model with quaternions.
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
    sampling : dict, optional
        Outputs reported at their own rates, ``{output: every}`` or ``{output: (every,
        first)}``: sample ``k`` reports the output when ``k >= first`` and
        ``(k - first) % every == 0``, else it is NaN (a sensor that was silent); the
        outputs not named are reported at every sample. Asynchronous sensors on the
        grid of the fastest one (see :func:`estim.records.merge` for streams with
        time stamps of their own).
    """

    name: str
    model: Model
    x0: np.ndarray
    n_steps: int
    Q: np.ndarray
    R: np.ndarray
    tuning: dict
    inputs: ArrayLike | Callable[[float], ArrayLike] | None = None
    controller: Callable[[float, np.ndarray], ArrayLike] | None = None
    feedback: str = "estimate"
    clip: bool = False
    plant_changes: list[tuple[float, dict[str, float]]] = field(default_factory=list)
    description: str = ""
    remarks: dict[str, str] = field(default_factory=dict)
    sampling: dict[str, tuple[int, int]] = field(default_factory=dict)

    def __init__(self, name: str, model: Model, x0: ArrayLike, n_steps: int,
                 Q: ArrayLike, R: ArrayLike, tuning: dict,
                 inputs: ArrayLike | Callable[[float], ArrayLike] | None = None,
                 controller: Callable[[float, np.ndarray], ArrayLike] | None = None,
                 feedback: str = "estimate", clip: bool = False,
                 plant_changes: Iterable[tuple[float, Mapping[str, float]]] | None = None,
                 description: str = "", remarks: Mapping[str, str] | None = None,
                 sampling: Mapping[str, int | tuple[int, int]] | None = None) -> None:
        # written out, not generated: x0, Q and R are taken in any array form (a list,
        # a scalar variance) and kept as arrays; the other fields are checked
        if not isinstance(name, str):
            raise TypeError(f"name must be a string, got {type(name).__name__}")
        if not isinstance(model, Model):
            raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
        self.name, self.model, m = name, model, model
        self.x0 = as_vector(x0, m.nx, "x0")
        self.Q = as_covariance(Q, m.ndx, "Q", definite=False)  # in the tangent space
        self.R = as_covariance(R, m.ny, "R", definite=True)
        self.feedback = as_choice(feedback, ("estimate", "truth"), "feedback")
        self.n_steps = as_int(n_steps, "n_steps", minimum=1)
        self.clip = as_bool(clip, "clip")
        if not isinstance(tuning, Mapping):
            raise TypeError(f"tuning must be a dict of estimator arguments, "
                            f"got {type(tuning).__name__}")
        for key in tuning:
            if not isinstance(key, str):
                raise TypeError(f"tuning keys must be argument names, got {key!r}")
        self.tuning = tuning
        if controller is not None and not callable(controller):
            raise TypeError(f"controller must be callable (t, x) -> u, "
                            f"got {type(controller).__name__}")
        if inputs is not None and controller is not None:
            raise ValueError("give inputs= or controller=, not both")
        if inputs is not None and not callable(inputs):
            as_input_table(inputs, self.n_steps, m.nu, names=m.input_names)
        self.inputs, self.controller = inputs, controller
        self.plant_changes = check_plant_changes(plant_changes, m)
        self.description = description
        remarks = {} if remarks is None else remarks
        if not isinstance(remarks, Mapping) or not all(
                isinstance(k, str) and isinstance(v, str) for k, v in remarks.items()):
            raise TypeError("remarks must be a dict {estimator class name: text}")
        self.remarks = dict(remarks)
        self.sampling = check_sampling(sampling, m)

    def replace(self, **changes: Any) -> Scenario:
        """A copy with some fields changed (e.g. ``n_steps``)."""
        from dataclasses import replace

        return replace(self, **changes)

    def __repr__(self) -> str:
        return (f"Scenario({self.name!r}, model={self.model.name}, n_steps={self.n_steps}, "
                f"dt={self.model.dt:g})")


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
