r"""Any filter in estim's loop: a filterpy filter object, or a plain step function.

:func:`from_filterpy` and :func:`from_function` wrap what is not an estim estimator into
one, so that :func:`~estim.simulate`, :func:`~estim.replay`, :func:`~estim.compare` and
:mod:`estim.testing` treat it as any other: a course's observer, a student's EKF, a
hand-written filter or a filterpy object is compared on equal terms (the same noise per
seed, the same metrics). ``compare`` copies the wrapped object for every run (a deep
copy), and :meth:`~estim.Estimator.reset` restores it as it was wrapped.

Each step is timed and logged as an estim estimator's: the estimate, the covariance when
the filter has one (filterpy's ``P``, or the second value a step function returns), and
for filterpy the normalised innovation squared :math:`y^\top S^{-1} y` from its ``y`` and
``S`` after the update. A non-finite estimate is a failed step (its status says so); an
exception in the wrapped code propagates (``simulate`` attaches the log of the steps
before it).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

import numpy as np

from estim._validate import as_vector
from estim.estimators.base import Estimator, StepInfo
from estim.model import Model

__all__ = ["FilterpyEstimator", "FunctionEstimator", "from_filterpy", "from_function"]



def _filterpy() -> tuple[Any, Any, Any]:
    """The filterpy classes :func:`from_filterpy` runs: ``KalmanFilter``,
    ``ExtendedKalmanFilter``, ``UnscentedKalmanFilter`` (imported on first use: filterpy
    brings scipy.stats, half a second that a step function's adapter does not need)."""
    from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter, UnscentedKalmanFilter

    return KalmanFilter, ExtendedKalmanFilter, UnscentedKalmanFilter


class _Wrapped(Estimator):
    """What both adapters share: no tuning of their own (the wrapped object has it)."""

    _manifold_aware = True  # the wrapped code handles its states as it does
    _requires_P0 = False  # (its prior is the wrapped filter's)

    def __init__(self, model: Model, x0: Any, name: str | None, default: str):
        if not isinstance(model, Model):
            raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
        # placeholders for the protocol's tuning: the wrapped filter has its own
        if x0 is None:  # (a unit quaternion where the model has one)
            x0 = np.zeros(model.nx)
            x0[[g[0] for g in model.manifold.quaternions]] = 1.0
        super().__init__(model, Q=0.0, R=1.0, x0=x0)
        if name is not None and not isinstance(name, str):
            raise TypeError(f"name must be a string, got {type(name).__name__}")
        self.name = default if name is None else name

    def set_tuning(self, **kwargs: Any) -> None:
        """Refused: the wrapped filter holds its own tuning (set it there)."""
        raise TypeError(f"{self.name} wraps a filter of its own: set its tuning on the "
                        f"wrapped object")

    def _estimate(self, x: Any, P: Any) -> tuple[np.ndarray, StepInfo]:
        """``x`` and ``P`` as the step's estimate and info (a failed step when ``x`` is
        not finite)."""
        m = self.model
        try:
            x = np.array(x, dtype=float).reshape(m.nx)
        except (TypeError, ValueError):
            raise ValueError(f"{self.name}: the estimate must be {m.nx} numbers, got "
                             f"{np.shape(x)}") from None
        cov = None
        if P is not None:
            cov = np.array(P, dtype=float)
            if cov.shape != (m.ndx, m.ndx):
                raise ValueError(f"{self.name}: the covariance must be ({m.ndx}, {m.ndx}), "
                                 f"got {cov.shape}")
        if not np.isfinite(x).all():
            return x, StepInfo(status="failed: the wrapped filter's estimate is not finite",
                               success=False, P=cov)
        return x, StepInfo._fast(P=cov)


class FunctionEstimator(_Wrapped):
    """A step function in the loop (see :func:`from_function`)."""

    def __init__(self, step: Callable, model: Model, name: str | None = None,
                 reset: Callable[[], Any] | None = None, x0: Any = None):
        if not callable(step):
            raise TypeError(f"step must be a function step(y, u) -> x_hat (or (x_hat, P)), "
                            f"got {type(step).__name__}")
        if reset is not None and not callable(reset):
            raise TypeError(f"reset must be a function reset() or None, got "
                            f"{type(reset).__name__}")
        super().__init__(model, x0, name, getattr(step, "__name__", "function"))
        self._fn, self._reset_fn = step, reset

    def _reset(self) -> None:
        if self._reset_fn is not None:
            self._reset_fn()

    def _step(self, y, u, first):
        out = self._fn(y.copy(), u.copy())
        x, P = out if isinstance(out, tuple) and len(out) == 2 else (out, None)
        return self._estimate(x, P)


class FilterpyEstimator(_Wrapped):
    """A filterpy filter in the loop (see :func:`from_filterpy`)."""

    _checks_inf_itself = False

    def __init__(self, filt: Any, model: Model, name: str | None = None,
                 hx: Callable | None = None, HJacobian: Callable | None = None):
        kinds = _filterpy()
        if not isinstance(filt, kinds):
            raise TypeError(f"filt must be a filterpy KalmanFilter, ExtendedKalmanFilter or "
                            f"UnscentedKalmanFilter, got {type(filt).__name__}")
        if not isinstance(model, Model):
            raise TypeError(f"model must be an estim.Model (the system the filter "
                            f"estimates), got {type(model).__name__}")
        if filt.x.size != model.nx:
            raise ValueError(f"filt has {filt.x.size} states but {model.name} has "
                             f"{model.nx} ({model.state_names})")
        if getattr(filt, "dim_z", model.ny) != model.ny:
            raise ValueError(f"filt measures {filt.dim_z} outputs (dim_z) but {model.name} "
                             f"has {model.ny} ({model.output_names})")
        if isinstance(filt, kinds[1]) and np.ndim(filt.x) != 2:
            raise ValueError(f"filt.x must be an ({model.nx}, 1) column for filterpy's "
                             f"ExtendedKalmanFilter (its update turns a 1-D x of shape "
                             f"({model.nx},) into ({model.nx}, {model.nx})); note that it "
                             f"predicts x = F x unless predict_x is overridden")
        for arg, fn in (("hx", hx), ("HJacobian", HJacobian)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{arg} must be a function (x, u) -> array, got "
                                f"{type(fn).__name__}")
        super().__init__(model, np.asarray(filt.x, dtype=float).ravel(), name,
                         f"filterpy {type(filt).__name__}")
        self._initial = copy.deepcopy(filt)
        self.filter = copy.deepcopy(filt)
        p = model.p
        self._hx = hx or (lambda x, u: np.asarray(model.H(np.ravel(x), u, p)))
        self._HJ = HJacobian or (lambda x, u: np.asarray(model.H_x(np.ravel(x), u, p)))
        x0, u0 = filt.x, np.zeros(model.nu)
        for arg, fn, shape in (("hx", hx, (model.ny,)), ("HJacobian", HJacobian,
                                                         (model.ny, model.nx))):
            if fn is None:
                continue
            try:  # called once here, so that a wrong one says so now, by name
                out = np.asarray(fn(x0, u0), dtype=float)
            except Exception as exc:  # noqa: BLE001 - re-raised naming the argument
                raise TypeError(f"{arg}: calling {arg}(x, u) at filt.x failed: "
                                f"{type(exc).__name__}: {exc}") from exc
            if out.size != int(np.prod(shape)):
                raise ValueError(f"{arg}(x, u) must give {shape} values, got shape "
                                 f"{out.shape}")

    def _reset(self) -> None:
        self.filter = copy.deepcopy(self._initial)

    def _step(self, y, u, first):
        f = self.filter
        _, ExtendedKalmanFilter, UnscentedKalmanFilter = _filterpy()
        missing = np.isnan(y)
        if missing.any() and not missing.all():
            raise ValueError(f"{self.name}: filterpy's filters update with every output; "
                             f"y has NaN in {np.flatnonzero(missing).tolist()} only (use an "
                             f"estim filter, or records without partly missing samples)")
        if first and isinstance(f, UnscentedKalmanFilter):  # the update from the prior
            f.sigmas_f = f.points_fn.sigma_points(f.x, f.P)
        if not first:
            if isinstance(f, UnscentedKalmanFilter):
                f.predict(**({"u": u} if u.size else {}))
            elif isinstance(f, ExtendedKalmanFilter):
                f.predict(u=u if u.size else 0)
            else:
                f.predict(u=u if u.size and f.B is not None else None)
        nis = float("nan")
        if not missing.all():
            if isinstance(f, ExtendedKalmanFilter):
                f.update(y.reshape(-1, 1) if np.ndim(f.x) == 2 else y,
                         lambda x: self._HJ(x, u), lambda x: self._hx(x, u))
            else:
                f.update(y)
            e, S = np.ravel(f.y), np.asarray(f.S, dtype=float)
            try:
                nis = float(e @ np.linalg.solve(S, e))
            except np.linalg.LinAlgError:
                pass
        x, info = self._estimate(f.x, f.P)
        if info.success:
            info.__dict__.update(nis=nis, innovation=np.ravel(f.y).copy()
                                 if not missing.all() else np.zeros(self.model.ny))
        return x, info


def from_filterpy(filt: Any, model: Model, *, name: str | None = None,
                  hx: Callable | None = None, HJacobian: Callable | None = None
                  ) -> FilterpyEstimator:
    r"""Run a filterpy filter in estim's loop.

    The first sample updates the prior (the unscented filter from its sigma points);
    at every sample after the first the filter predicts (``KalmanFilter.predict(u)`` with
    the input when it has a ``B``; ``ExtendedKalmanFilter.predict(u)``, its own
    ``predict_x``; ``UnscentedKalmanFilter.predict(u=u)``, passed to its ``fx`` when the
    model has inputs), then updates with ``y`` (the extended filter with the model's
    output and its Jacobian unless ``hx``/``HJacobian`` are given, each ``(x, u)``).
    A sample with every output missing (NaN) skips the update; filterpy cannot drop some
    outputs only, so a partly missing sample is an error.

    Parameters
    ----------
    filt : filterpy.kalman.KalmanFilter, ExtendedKalmanFilter or UnscentedKalmanFilter
        Set up with its tuning and initial state (copied: the original is not changed).
    model : Model
        The system it estimates (dimensions, names, and for the extended filter its
        output map).
    name : str, optional
        The label in logs and tables (default ``"filterpy <class>"``).
    hx, HJacobian : callable ``(x, u) -> array``, optional
        The extended filter's output map and its Jacobian (default the model's).

    Returns
    -------
    FilterpyEstimator
        An estimator: ``simulate``, ``replay``, ``compare``, :mod:`estim.testing`.
    """
    return FilterpyEstimator(filt, model, name=name, hx=hx, HJacobian=HJacobian)


def from_function(step: Callable, model: Model, *, name: str | None = None,
                  reset: Callable[[], Any] | None = None, x0: Any = None
                  ) -> FunctionEstimator:
    """Run any ``step(y, u) -> x_hat`` (or ``-> (x_hat, P)``) in estim's loop.

    Parameters
    ----------
    step : callable
        Called with the measurement ``y`` (ny,) (NaN where missing) and the input ``u``
        (nu,) of every sample, as :meth:`~estim.Estimator.step` is; returns the estimate
        (nx,), or the estimate and its covariance (ndx, ndx).
    model : Model
        The system (dimensions and names for the log).
    name : str, optional
        The label in logs and tables (default the function's name).
    reset : callable, optional
        Called by :meth:`~estim.Estimator.reset` (``simulate`` resets before a run): put
        the wrapped filter back at its start. Without it, keep the filter's state in
        the function's closure and build a new adapter per run.
    x0 : (nx,) array, optional
        Reported as the estimator's ``x0`` (not used by the loop).
    """
    return FunctionEstimator(step, model, name=name, reset=reset,
                             x0=None if x0 is None else as_vector(x0, model.nx, "x0"))
