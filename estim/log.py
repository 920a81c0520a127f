"""Time-major record of one simulation run."""

from __future__ import annotations

import html
from collections.abc import Sequence
from os import PathLike
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_bool, as_float, as_names, check_keywords

if TYPE_CHECKING:
    import pandas as pd
    import xarray as xr
    from matplotlib.figure import Figure

#: Fields :func:`estim.simulate` fills, with their per-sample shape names.
FIELDS = ("t", "x", "y", "u", "x_hat", "P", "solve_time", "status", "iterations", "success",
          "nis", "cost", "diagnostics")
#: Series of Python objects (one dict a step), left out of the array exports.
OBJECT_FIELDS = ("diagnostics",)


class Log:
    """Arrays of one run, time first and never squeezed.

    Fields written by :func:`estim.simulate`: ``t (T,)``, ``x (T, nx)``,
    ``y (T, ny)`` (NaN where not measured), ``u (T, nu)`` (the input applied
    after sample k), ``x_hat (T, nx)``, ``P (T, nx, nx)`` (NaN where the
    estimator has no covariance), ``solve_time (T,)`` in seconds,
    ``status (T,)`` strings, ``iterations (T,)``, ``success (T,)``,
    ``nis (T,)``, ``cost (T,)`` and ``diagnostics (T,)``, each step's
    ``info.extra`` dict (see :meth:`diagnostic`).

    On a model with quaternions or angles (``Model(quaternions=..., angles=...)``),
    ``P`` is ``(T, ndx, ndx)``: the covariance of the error in the tangent space
    (:attr:`manifold`; a quaternion's error is its 3-dof rotation vector), and the
    metrics (:func:`~estim.rmse`, :func:`~estim.nees`) use that error.

    A status other than ``"ok"`` says what happened at that step (see
    :mod:`estim.estimators.base`): :attr:`failures` counts the steps that
    failed, :attr:`flagged` the ``"inexact"`` and ``"suspect"`` ones, and the
    repr shows both.

    A ``Log`` is also the course-style logger: ``log("x", value)`` appends a
    sample to the named series, and ``log.x`` returns it stacked as an array
    of shape ``(T, ...)``.

    Parameters
    ----------
    state_names, output_names, input_names : list of str, optional
        Labels used by :meth:`plot` and the exports.
    dt : float, optional
        Sample time.
    estimator : str
        Name of the estimator that produced the estimates.
    output_state : dict, optional
        ``{output index: state index}`` for outputs that measure a state
        directly (drawn on that state's axes by :meth:`plot`).
    model_name : str
        Name of the model (for reprs and titles).
    time_unit : str
        Unit of ``t`` (the model's :attr:`~estim.Model.time_unit`; empty when unknown).
    """

    # the series that simulate and replay write (looked up by __getattr__)
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    u: np.ndarray
    x_hat: np.ndarray
    P: np.ndarray
    solve_time: np.ndarray
    status: np.ndarray
    iterations: np.ndarray
    success: np.ndarray
    nis: np.ndarray
    cost: np.ndarray
    diagnostics: np.ndarray

    @check_keywords(owner="Log")
    def __init__(self, state_names: Sequence[str] | None = None,
                 output_names: Sequence[str] | None = None,
                 input_names: Sequence[str] | None = None, dt: float | None = None,
                 estimator: str = "", output_state: dict | None = None, model_name: str = "",
                 time_unit: str = ""):
        self.state_names = as_names(state_names, "state_names", "x")
        self.output_names = as_names(output_names, "output_names", "y")
        self.input_names = as_names(input_names, "input_names", "u")
        self.dt = as_float(dt, "dt", positive=True, allow_none=True)
        for name, value in (("estimator", estimator), ("model_name", model_name),
                            ("time_unit", time_unit)):
            if not isinstance(value, str):
                raise TypeError(f"{name} must be a string, got {type(value).__name__}")
        if output_state is not None and not isinstance(output_state, dict):
            raise TypeError(f"output_state must be a dict {{output index: state index}}, "
                            f"got {type(output_state).__name__}")
        self.estimator = estimator
        self.model_name = model_name
        self.time_unit = time_unit
        self.output_state = dict(output_state or {})
        #: the states' manifold (estim._manifold.Manifold) when they have quaternions or
        #: angles: errors and covariances are in its tangent space; None otherwise
        self.manifold: Any = None
        self._series: dict[str, list] = {}
        self._arrays: dict[str, np.ndarray] = {}

    @classmethod
    def from_estimates(cls, result, truth: Log | ArrayLike | None = None, *,
                       name: str = "") -> Log:
        """A log of a result of a whole record (``filter``, ``smooth``, ``fit``: any
        :class:`~estim.estimators.filtering.Estimates`), for what takes logs: ``t``,
        ``x_hat``, ``P`` and ``status`` where the result has them, the truth ``x`` from
        ``truth`` (a log of the same record, or the true states ``(T, nx)``), and
        ``name`` as :attr:`estimator`."""
        return _from_estimates(cls, result, truth, name)

    # ----------------------------------------------------------- recording
    def __call__(self, key: str, value: ArrayLike) -> None:
        """Append ``value`` to the series ``key``."""
        if not isinstance(key, str) or not key.isidentifier():
            raise ValueError(f"key must be an identifier string, got {key!r}")
        if key in self._arrays:
            self._series[key] = list(self._arrays.pop(key))
        self._series.setdefault(key, []).append(np.array(value, copy=True))
        self.__dict__.pop("_cache_" + key, None)

    def set(self, key: str, array: np.ndarray) -> None:
        """Store a whole time-major array under ``key``."""
        if not isinstance(key, str) or not key.isidentifier():
            raise ValueError(f"key must be an identifier string, got {key!r}")
        self._series.pop(key, None)
        self._arrays[key] = np.asarray(array)

    def __getattr__(self, key: str) -> Any:
        if key.startswith("_"):
            raise AttributeError(key)
        arrays = self.__dict__.get("_arrays", {})
        if key in arrays:
            return arrays[key]
        series = self.__dict__.get("_series", {})
        if key in series:
            cached = self.__dict__.get("_cache_" + key)
            if cached is None:
                cached = np.stack(series[key]) if series[key] else np.empty(0)
                self.__dict__["_cache_" + key] = cached
            return cached
        raise AttributeError(f"Log has no series {key!r}; it has {self.keys()}")

    def keys(self) -> list[str]:
        """Names of the recorded series."""
        return list(self._arrays) + [k for k in self._series if k not in self._arrays]

    def __contains__(self, key: str) -> bool:
        return key in self._arrays or key in self._series

    def __len__(self) -> int:
        for key in ("t", "x", "x_hat", "y"):
            if key in self:
                return len(getattr(self, key))
        return 0

    # ------------------------------------------------------------- exports
    def to_pandas(self) -> pd.DataFrame:
        """One row a sample: ``t``, ``x:<name>``, ``x_hat:<name>``, ``y:<name>``, ``u:<name>``, ...

        Series of another length than the log (logged at another rate) and
        ``P`` (3-D) are left out.

        Requires pandas (``pip install estim[data]``).
        """
        try:
            import pandas as pd
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError("to_pandas needs pandas: pip install 'estim[data]'") from exc
        cols: dict[str, np.ndarray] = {}
        T = len(self)
        for key in self.keys():
            arr = getattr(self, key)
            if len(arr) != T or key in OBJECT_FIELDS:  # another rate, or objects
                continue
            if arr.ndim == 1:
                cols[key] = arr
            elif arr.ndim == 2:
                names = self._labels(key, arr.shape[1])
                for j, n in enumerate(names):
                    cols[f"{key}:{n}"] = arr[:, j]
        frame = pd.DataFrame(cols)
        return frame.set_index("t") if "t" in frame else frame

    def to_xarray(self) -> xr.Dataset:
        """An ``xarray.Dataset`` with dimensions ``time``, ``state``, ``output``, ``input``."""
        try:
            import xarray as xr
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError("to_xarray needs xarray: pip install xarray") from exc
        dims = {"x": ("time", "state"), "x_hat": ("time", "state"), "y": ("time", "output"),
                "u": ("time", "input"), "P": ("time", "state", "state_")}
        data = {}
        for key in self.keys():
            if key == "t" or key in OBJECT_FIELDS:
                continue
            arr = getattr(self, key)
            data[key] = (dims.get(key, ("time",) + tuple(f"{key}_{i}" for i in
                                                          range(arr.ndim - 1))), arr)
        coords: dict[str, np.ndarray | list[str]] = {
            "time": self.t if "t" in self else np.arange(len(self))}
        if self.state_names:
            coords["state"] = self.state_names
            coords["state_"] = self.state_names
        if self.output_names:
            coords["output"] = self.output_names
        if self.input_names:
            coords["input"] = self.input_names
        return xr.Dataset(data, coords=coords)

    # ------------------------------------------------------------ failures
    @property
    def failures(self) -> int:
        """Steps whose ``success`` is False (the estimator fell back and re-anchored)."""
        return int(np.count_nonzero(~self.success)) if "success" in self else 0

    @property
    def flagged(self) -> int:
        """Successful steps whose status is not ``"ok"`` (``"inexact"``, ``"suspect"``)."""
        if "status" not in self or "success" not in self:
            return 0
        return int(np.count_nonzero(self.success & (self.status != "ok")))

    def problems(self) -> str:
        """One line on the failed and flagged steps ("" when every step was ok)."""
        parts, failures, flagged = [], self.failures, self.flagged
        if failures:
            first = int(np.flatnonzero(~self.success)[0])
            parts.append(f"{failures} of {len(self)} steps failed (first at step {first}: "
                         f"{self.status[first]})")
        if flagged:
            kinds = sorted({str(s).split(":")[0] for s in self.status[self.success]} - {"ok"})
            parts.append(f"{flagged} flagged ({', '.join(kinds)})")
        return "; ".join(parts)

    def diagnostic(self, key: str) -> np.ndarray:
        """The estimator's per-step diagnostic ``info.extra[key]`` stacked time-major (NaN
        where a step did not report it), e.g. ``log.diagnostic("condition")`` of a
        :class:`~estim.ShootingObserver`.

        Raises ``KeyError`` when no step reported ``key``.
        """
        extra: np.ndarray | list[dict] = self.diagnostics if "diagnostics" in self else []
        values = [e.get(key) if isinstance(e, dict) else None for e in extra]
        present = [np.asarray(v, dtype=float) for v in values if v is not None]
        if not present:
            known = sorted({k for e in extra if isinstance(e, dict) for k in e})
            raise KeyError(f"no step reported {key!r}; the steps reported {known}")
        shape = present[0].shape
        out = np.full((len(values),) + shape, np.nan)
        for k, v in enumerate(values):
            if v is not None and np.shape(v) == shape:
                out[k] = v
        return out

    def _labels(self, key: str, n: int) -> list[str]:
        names = {"x": self.state_names, "x_hat": self.state_names, "y": self.output_names,
                 "u": self.input_names}.get(key, [])
        return names if len(names) == n else [str(i) for i in range(n)]

    # ---------------------------------------------------------------- plot
    def plot(self, path: str | PathLike[str] | None = None, states: Sequence[str] | None = None,
             sigma: bool = True) -> Figure:
        """Truth vs estimate per state, with the measurement where it is a state.

        Parameters
        ----------
        path : str or Path, optional
            Write the figure there (PNG by extension).
        states : list of str, optional
            Which states to draw (default all).
        sigma : bool
            Shade :math:`\\pm 2\\sigma` around the estimate where ``P`` exists.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from estim._figures import plot_log

        sigma = as_bool(sigma, "sigma")
        if isinstance(states, str):
            states = [states]
        unknown = [s for s in states or [] if s not in self.state_names]
        if unknown and self.state_names:
            raise ValueError(f"states {unknown} are not in the log; states are "
                             f"{self.state_names}")
        return plot_log(self, path=path, states=states, sigma=sigma)

    def _repr_html_(self) -> str:
        rows = "".join(f"<tr><td>{k}</td><td>{getattr(self, k).shape}</td></tr>"
                       for k in self.keys())
        title = f"Log {self.estimator}" + (f" on {self.model_name}" if self.model_name else "")
        extra = ""
        if "x" in self and "x_hat" in self and np.isfinite(self.x).all():
            from estim.metrics import rmse

            extra = f"<p>{html.escape(repr(rmse(self)))}</p>"
        problems = self.problems()
        if problems:
            extra += f"<p><b>Warning</b>: {html.escape(problems)}</p>"
        return (f"<p><b>{title}</b>: T = {len(self)}</p>{extra}"
                f"<table><tr><th>series</th><th>shape</th></tr>{rows}</table>")

    def __repr__(self) -> str:
        fields = ", ".join(f"{k} {getattr(self, k).shape}" for k in self.keys()
                           if getattr(self, k).ndim > 1 or k == "t")
        who = f" {self.estimator}" if self.estimator else ""
        on = f" on {self.model_name}" if self.model_name else ""
        problems = self.problems()
        return f"<Log{who}{on}: T={len(self)}; {fields}{'; ' + problems if problems else ''}>"


def _from_estimates(cls, result, truth, name: str) -> Log:
    """:meth:`Log.from_estimates`."""
    from estim.estimators.filtering import Estimates

    if isinstance(result, Log):
        return result
    if not isinstance(result, Estimates):
        raise TypeError(f"result must be an estim.Log or a result of a whole record "
                        f"(FilterResult, SmoothResult, ParticleFilterResult, "
                        f"ParticleSmoothResult, FitResult), got {type(result).__name__}")
    T = len(result.x)
    src = truth if isinstance(truth, Log) else None
    log = cls(state_names=list(result.state_names) or None, estimator=name,
              model_name=src.model_name if src is not None else "",
              time_unit=src.time_unit if src is not None else "",
              output_names=src.output_names if src is not None else None,
              output_state=src.output_state if src is not None else None)
    log.manifold = result.manifold
    log.set("t", result.times())
    if truth is not None:
        x = src.x if src is not None else np.asarray(truth, dtype=float)
        if src is not None and "x" not in src:
            raise ValueError(f"truth is a Log without the true state 'x' (it has "
                             f"{src.keys()})")
        if x.ndim == 1:
            x = x[:, None]
        if x.shape != result.x.shape:
            raise ValueError(f"truth has shape {x.shape} but the estimates have "
                             f"{result.x.shape}")
        log.set("x", x)
        if src is not None and "y" in src and len(src.y) == T:
            log.set("y", src.y)
    log.set("x_hat", result.x)
    P = getattr(result, "P", None)
    if P is not None:
        log.set("P", P)
    status = getattr(result, "status", None)
    if isinstance(status, tuple) and len(status) == T:
        log.set("status", np.array(status))
        log.set("success", np.array([not s.startswith("failed") for s in status]))
    return log

