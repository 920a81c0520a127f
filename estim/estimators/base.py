"""The protocol every estimator follows, and the information it reports.

An estimator is built once from a :class:`~estim.Model` and tuning
(``Q, R, x0, P0`` as covariances), then fed one measurement at a time:

>>> x_hat = est.step(y, u)          # doctest: +SKIP

``step`` takes the measurement :math:`y_k` and the input :math:`u_{k-1}`
that acted since the previous measurement (ignored on the first call) and
returns the filtered estimate :math:`\\hat x_{k|k}`. NaN entries of ``y``
mark outputs not measured at this sample. What the estimator knows after a
step is in ``est.info`` (a frozen :class:`StepInfo`).

Subclasses implement :meth:`Estimator._step` (the mathematics) and, where they
hold more state, :meth:`Estimator._reset`; the base class owns argument
checking, timing and bookkeeping.

Failures and recovery
---------------------
``info.status`` is ``"ok"``, or starts with one of

``"failed: "``
    the step could not use this measurement as intended (a non-finite
    prediction or update, a covariance that lost definiteness, a solver that
    failed or stopped early at a cost the data do not support);
    ``info.success`` is False. The estimator never keeps a non-finite value: it
    *re-anchors* on its last trusted estimate (the last one reported ``"ok"``
    or ``"inexact"``), projected on the bounds, with the covariance inflated by
    ``P0`` (the arrival covariance for MHE, a new prior for full-information
    estimation), and applies the measurement to that.
``"inexact: "``
    a solver stopped early (e.g. ``max_iter``) at a finite point no worse than
    its warm start, at a cost the data support; that point is the estimate
    (``success`` is True).
``"suspect: "``
    the step succeeded, but the normalised innovation squared (filters) or the
    weighted cost (MHE, full information) lies beyond the :data:`SUSPECT_TAIL`
    tail of its chi-square distribution: an outlier, a fault, or an estimate
    that lost track (``success`` is True).
``"rejected: "``
    a filter with ``gate`` rejected the measurement (``success`` is True).

A returned estimate is always finite.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._manifold import unit_quaternions
from estim._smoothness import advice, nonsmooth_operations
from estim._validate import (
    as_bounds,
    as_covariance,
    as_float,
    as_seed,
    as_vector,
    check_keywords,
)
from estim.consistency import consistency_status
from estim.exceptions import EstimationWarning
from estim.model import Model
from estim.solvers.weights import weight_factor

#: The protocol's names, and the consistency test and warning class it reports with.
__all__ = ["EstimationWarning", "Estimator", "StepInfo", "consistency_status"]


@dataclass(frozen=True)
class StepInfo:
    """What an estimator reports after one step.

    Attributes
    ----------
    status : str
        ``"ok"`` or a short description of what went wrong
        (``"failed: ..."``); a failed step still returns an estimate.
    success : bool
        False when the step could not do its update and fell back.
    iterations : int
        Solver iterations (0 for recursive filters).
    solve_time : float
        Wall time of the step in seconds.
    P : (nx, nx) array or None
        Error covariance of the returned estimate, where the method has one.
    cost : float
        Optimal cost for optimisation-based estimators (NaN otherwise).
    innovation : (ny,) array or None
        Measurement residual before the update (0 for missing outputs).
    nis : float
        Normalised innovation squared :math:`e^\\top S^{-1} e` (NaN if none).
    extra : dict
        Method-specific data (window trajectory, multipliers, ...).
    """

    status: str = "ok"
    success: bool = True
    iterations: int = 0
    solve_time: float = 0.0
    P: np.ndarray | None = None
    cost: float = float("nan")
    innovation: np.ndarray | None = None
    nis: float = float("nan")
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        # plain Python values, whatever a solver handed over (np.bool_, np.str_, 0-d arrays)
        for name, kind in (("status", str), ("success", bool), ("iterations", int),
                           ("solve_time", float), ("cost", float), ("nis", float)):
            value = getattr(self, name)
            if type(value) is not kind:
                object.__setattr__(self, name, kind(value))

    @classmethod
    def _fast(cls, **fields) -> StepInfo:
        """Build without the frozen-dataclass ``__setattr__`` cost (hot paths only)."""
        obj = object.__new__(cls)
        obj.__dict__.update(_DEFAULTS)
        obj.__dict__["extra"] = {}
        obj.__dict__.update(fields)
        return obj


_DEFAULTS = {f: getattr(StepInfo, f) for f in ("status", "success", "iterations", "solve_time",
                                               "P", "cost", "innovation", "nis")}

class Estimator:
    """Base class: tuning, argument checks and the ``step``/``reset`` protocol.

    Parameters
    ----------
    model : Model
        The system.
    Q : float, (nx,) or (nx, nx)
        Process-noise covariance (positive semi-definite).
    R : float, (ny,) or (ny, ny)
        Measurement-noise covariance (positive definite).
    x0 : (nx,) array
        Initial guess :math:`\\bar x_0` (the prior mean of the first state).
    P0 : float, (nx,) or (nx, nx), optional
        Covariance of the initial guess (positive definite).
    """

    #: Short name used by the command line and comparison tables.
    name = "estimator"
    _requires_P0 = True
    #: Subclasses that detect inf in ``y`` inside their compiled step set this.
    _checks_inf_itself = False
    #: Whether the estimator handles the model's quaternions and angles (its errors and
    #: covariances in the tangent space, ``model.ndx``); others refuse such a model.
    _manifold_aware = False
    #: Whether the estimator draws random numbers from its ``seed`` (particles,
    #: ensembles): :func:`~estim.compare` then gives each seed's run its own stream.
    _randomised = False

    def __init_subclass__(cls, **kwargs):
        """Every estimator's constructor checks its keyword names before it runs: an
        unknown option (with a suggestion) or a missing required one is a ``TypeError``."""
        super().__init_subclass__(**kwargs)
        if "__init__" in cls.__dict__:
            cls.__init__ = check_keywords(cls.__dict__["__init__"])

    def __init__(self, model: Model, *, Q: ArrayLike, R: ArrayLike, x0: ArrayLike,
                 P0: ArrayLike | None = None):
        if not isinstance(model, Model):
            raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
        if not (self._manifold_aware or model.manifold.trivial):
            raise ValueError(
                f"{type(self).__name__} does not handle the quaternions and angles "
                f"declared in {model.name} yet (the EKF, the UKF, the EnKF, the particle "
                f"filter, the IMM, MHE and full information do): give it "
                f"model.euclidean(), which treats them as ordinary states")
        self.model = model
        nd = model.ndx  # covariances live in the tangent space
        self.Q = as_covariance(Q, nd, "Q", definite=False)
        self.R = as_covariance(R, model.ny, "R", definite=True)
        self.x0 = unit_quaternions(model.manifold, as_vector(x0, model.nx, "x0"), "x0")
        if P0 is None and self._requires_P0:
            raise ValueError(f"P0 is required by {type(self).__name__}")
        self.P0 = None if P0 is None else as_covariance(P0, nd, "P0", definite=True)
        self._first = True
        self._k = 0
        self._info = StepInfo()
        self._u_zero = np.zeros(model.nu)
        self._sampled = model.sampled
        self._plain = not (model.sampled or model.variable_dt)  # the transition is u
        self._u_last = self._u_zero.copy()  # the previous input (sampled-input models)
        self._dt: float | None = None  # the interval of the current step (variable_dt)

    # -------------------------------------------------------------- protocol
    def step(self, y: ArrayLike, u: ArrayLike | None = None,
             dt: float | None = None) -> np.ndarray:
        """Process measurement ``y`` (ny,) after input ``u`` (nu,); return x̂ (nx,).

        ``u`` is the input that acted since the previous measurement, or, for a
        model with ``hold="foh"``, the input's value at this measurement (the
        transition then interpolates from the previous one). ``dt``: the time since
        the previous measurement, for a model built with ``variable_dt=True``
        (default the model's ``dt``); refused by other models.
        """
        y = self._check_y(y)
        u = self._check_u(u)
        self._dt = None if dt is None else self._check_dt(dt)
        return self._checked_step(y, u)

    def _checked_step(self, y: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`step` with ``y``, ``u`` (and ``_dt``) already checked: a whole record
        checked at once (``filter``) steps through here."""
        t0 = time.perf_counter()
        x_hat, info = self._step(y, u, self._first)
        elapsed = time.perf_counter() - t0
        if not info.solve_time:  # fresh, unpublished object: set the measured time
            info.__dict__["solve_time"] = elapsed
        self._info = info
        self._first = False
        self._k += 1
        if self._sampled:
            self._u_last = u.copy()
        return x_hat

    def _transition(self, u: np.ndarray) -> np.ndarray:
        """The input of the transition into this step (see :meth:`Model.transition`):
        the held input, both ends of a sampled one, and with ``variable_dt`` the
        interval given to :meth:`step`."""
        if self._plain:
            return u
        return self.model.transition(self._u_last, u, self._dt)

    def _check_dt(self, dt) -> float:
        if not self.model.variable_dt:
            raise ValueError(f"dt is given but {self.model.name} integrates over its fixed "
                             f"dt = {self.model.dt:g}: build the model with "
                             f"variable_dt=True for irregular time stamps")
        return as_float(dt, "dt", positive=True)

    def reset(self, x0: ArrayLike | None = None, P0: ArrayLike | None = None) -> None:
        """Forget all data; optionally replace the initial guess and its covariance."""
        if x0 is not None:
            self.x0 = as_vector(x0, self.model.nx, "x0")
        if P0 is not None:
            self.P0 = as_covariance(P0, self.model.nx, "P0", definite=True)
        self._first = True
        self._k = 0
        self._info = StepInfo()
        self._u_last = self._u_zero.copy()
        self._reset()

    def set_tuning(self, *, Q: ArrayLike | None = None, R: ArrayLike | None = None,
                   P0: ArrayLike | None = None, x0: ArrayLike | None = None) -> None:
        """Change the tuning; nothing is rebuilt (every compiled graph takes it as data).

        Parameters
        ----------
        Q, R : float, (nx,)/(ny,) or matrix, optional
            New process and measurement covariances, used from the next step on.
            An estimator built with a diagonal ``Q`` (``R``) uses only the diagonal in
            its graphs, so it takes a diagonal one only (build it with the full
            matrix to tune the correlations).
        P0, x0 : optional
            New prior of the first state: used from the next :meth:`reset` (which
            :func:`~estim.simulate` and :func:`~estim.replay` call), and at once by
            the terms that use ``P0`` at every step (the fixed MHE arrival cost,
            :meth:`FullInformation.fit`).
        """
        self.__dict__.update(self._validated_tuning(Q=Q, R=R, P0=P0, x0=x0))
        self._tuning_changed()

    def _validated_tuning(self, *, Q=None, R=None, P0=None, x0=None) -> dict:
        """The given tuning, checked as :meth:`set_tuning` does, as a dict."""
        m = self.model
        new = {}
        if Q is not None:
            new["Q"] = as_covariance(Q, m.ndx, "Q", definite=False)
        if R is not None:
            new["R"] = as_covariance(R, m.ny, "R", definite=True)
        if P0 is not None:
            new["P0"] = as_covariance(P0, m.ndx, "P0", definite=True)
        if x0 is not None:
            new["x0"] = unit_quaternions(m.manifold, as_vector(x0, m.nx, "x0"), "x0")
        for name in ("Q", "R"):
            if name in new and self._diagonal.get(name) and \
                    not np.array_equal(new[name], np.diag(np.diag(new[name]))):
                raise ValueError(f"{name} must be diagonal: {type(self).__name__} was built "
                                 f"with a diagonal {name} and its graphs use the diagonal "
                                 f"only (build it with a full {name} to tune correlations)")
        self._check_tuning(new)
        return new

    @property
    def caveat(self) -> str:
        """A known limitation of this configuration, for comparison tables (empty if none).

        A filter with ``clip=True`` projects its estimate onto the bounds after each
        update and leaves the covariance as it was: the gain no longer matches the
        estimate, so a clipped state can swing far off before the data pull it back.
        """
        if getattr(self, "clip", False):
            return ("clip=True projects each estimate onto the bounds but leaves the "
                    "covariance as it was, so gain and covariance no longer match the "
                    "estimate: a clipped state can swing far off before the data pull it "
                    "back, and its NEES and NIS are meaningless until then (docs/ekf.md)")
        return ""

    @property
    def info(self) -> StepInfo:
        """What the last :meth:`step` reported."""
        return self._info

    # ----------------------------------------------------------- subclasses
    def _step(self, y: np.ndarray, u: np.ndarray, first: bool) -> tuple[np.ndarray, StepInfo]:
        raise NotImplementedError

    def _reset(self) -> None:
        """Reset method-specific state (called by :meth:`reset`)."""

    #: Tuning matrices whose graphs use the diagonal only (set by subclasses).
    _diagonal: dict = {}

    def _check_tuning(self, new: dict) -> None:
        """Refuse tuning this estimator cannot use (``new``: the validated values)."""

    def _tuning_changed(self) -> None:
        """Write the tuning where the compiled graphs read it."""

    # -------------------------------------------------------------- helpers
    @staticmethod
    def _gate(gate) -> float | None:
        """The ``gate`` option of the filters: None or a tail probability in (0, 1)."""
        if gate is None:
            return None
        gate = as_float(gate, "gate", expected="a tail probability in (0, 1) or None")
        if not 0.0 < gate < 1.0:
            raise ValueError(f"gate must be a tail probability in (0, 1) or None, got {gate!r}")
        return gate

    def _warn_if_not_smooth(self) -> None:
        """Warn (at construction) when the model has switches (``fmin``, ``if_else``,
        ...) in what an optimisation-based estimator differentiates."""
        text = advice(nonsmooth_operations(self.model))
        if text:
            warnings.warn(f"{type(self).__name__} on {self.model.name}: {text}",
                          EstimationWarning, stacklevel=4)  # here, __init__, its check, caller

    @staticmethod
    def _failure(usable: bool, status: str, cost: float) -> str:
        """Why an optimisation-based step failed: an unusable solve, or an early stop at
        a cost the data do not support."""
        return status if not usable else f"{status} at cost {cost:.3g}"

    @staticmethod
    def _solve_status(failure: str | None, usable: bool, success: bool, status: str,
                      check: str, what: str) -> str:
        """The status of an optimisation-based step (MHE, full information): failed and
        re-anchored on its ``what`` (window, record), inexact, or the consistency
        ``check`` (``"ok"`` or ``"suspect: ..."``) of a converged solve."""
        if failure is not None:
            return f"failed: {failure}; re-anchored on the last trusted estimate" + (
                "" if usable else f" (no update: the restarted {what} failed too)")
        if success:
            return check
        return f"inexact: {status}" + ("" if check == "ok" else f"; {check}")

    def _weight_factor(self, P: np.ndarray) -> np.ndarray:
        """The weight factor :math:`W` with :math:`W^\top W = P^{-1}` of a state
        covariance ``P`` (ndx x ndx); on a manifold padded to the windowed solvers'
        ``nx x nx`` blocks (:meth:`Manifold.padded_matrix
        <estim._manifold.Manifold.padded_matrix>`)."""
        M = self.model.manifold
        W = weight_factor(P)
        return W if M.euclidean_states else M.padded_matrix(W)

    def _anchor(self, x: np.ndarray, P: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray | None]:
        """Where a failed step re-anchors: ``x`` (finite) projected on the estimator's
        bounds, and the covariance ``P + P0`` (``P0`` where ``P`` is missing or not
        finite; None without either)."""
        lower = getattr(self, "lower", self.model.lower)
        upper = getattr(self, "upper", self.model.upper)
        x = np.minimum(np.maximum(x, lower), upper)
        if P is None or not np.isfinite(P).all():
            return x, None if self.P0 is None else self.P0.copy()
        return x, P if self.P0 is None else P + self.P0

    def _bounds(self, lower, upper) -> tuple[np.ndarray, np.ndarray]:
        """State bounds given to an estimator (scalar, sequence or dict), default the model's."""
        m = self.model
        lo = m.lower.copy() if lower is None else as_bounds(lower, m.state_names, "lower",
                                                           -np.inf)
        up = m.upper.copy() if upper is None else as_bounds(upper, m.state_names, "upper",
                                                           np.inf)
        if np.any(lo > up):
            raise ValueError("lower must not exceed upper")
        return lo, up

    def _check_y(self, y) -> np.ndarray:
        ny = self.model.ny
        if type(y) is np.ndarray and y.shape == (ny,) and y.dtype == np.float64:
            if not self._checks_inf_itself and np.isinf(y).any():
                raise ValueError(f"y must not contain inf, got {y}")
            return y
        return as_vector(y, ny, "y", allow_nan=True)

    def _check_u(self, u) -> np.ndarray:
        nu = self.model.nu
        if u is None:
            return self._u_zero
        if type(u) is np.ndarray and u.shape == (nu,) and u.dtype == np.float64:
            # (a few inputs: Python's isfinite on a list is 5x faster than the ufunc)
            if not (all(map(math.isfinite, u.tolist())) if nu <= 16 else np.isfinite(u).all()):
                raise ValueError(f"u must be finite, got {u}")
            return u
        return as_vector(u, nu, "u")

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.model.name}, nx={self.model.nx})"


def seeded(est: Estimator, seed: object, run: Callable[[], Any]) -> Any:
    """``run()`` with a randomised estimator's random numbers from ``seed`` (checked: an
    int >= 0 or None), its constructor's seed back afterwards (the next reset starts
    that stream again)."""
    seed = as_seed(seed)
    before = est.seed  # type: ignore[attr-defined]
    est.seed = 0 if seed is None else seed  # type: ignore[attr-defined]
    try:
        return run()
    finally:
        est.seed = before  # type: ignore[attr-defined]
