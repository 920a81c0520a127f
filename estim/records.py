r"""Asynchronous sensor streams merged into one record.

An IMU at 100 Hz, a GNSS receiver at 1 Hz and a barometer at 20 Hz each come with
their own time stamps. :func:`merge` puts them on one time line: the union of the
stamps, one row per distinct stamp, each output NaN where its sensor was silent.
Every estimator already treats a NaN output as missing (its row of the update
drops out) and, with a model built with ``variable_dt=True``, integrates over each
interval, so the merged record goes to :func:`~estim.replay`,
``FullInformation.fit``, ``filter`` and ``smooth`` as it is::

    rec = estim.records.merge({"imu": (t_imu, Y_imu, ["acc"]),
                               "gnss": (t_gnss, Y_gnss, ["h_gnss"]),
                               "baro": (t_baro, Y_baro, ["h_baro"])},
                              outputs=model.output_names)
    R = rec.R({"imu": 0.05**2, "gnss": 2.0**2, "baro": 0.5**2})
    log = estim.replay(estim.EKF(model, Q=Q, R=R, x0=x0, P0=P0), rec.Y, t=rec.t)

With a block-diagonal ``R`` (sensors independent), updating with all the outputs of
one stamp at once is the same as updating sensor by sensor (the measurements of
different sensors are conditionally independent given the state): the result
equals a Kalman filter that processes each sensor's measurement as it comes.
Stamps that coincide exactly are one row; the same output reported twice at one
stamp (two sensors, or a repeated row) is kept once if the values agree, refused
otherwise.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import as_covariance

__all__ = ["MergedRecord", "merge"]


@dataclass(frozen=True)
class MergedRecord:
    """Streams merged by :func:`merge`.

    Attributes
    ----------
    t : (T,) array
        The distinct time stamps of all the streams, increasing.
    Y : (T, ny) array
        The outputs in the order of ``outputs``, NaN where no sensor reported.
    dt : (T,) array
        The interval from the previous stamp (``dt[0]`` is NaN): what a model with
        ``variable_dt=True`` integrates over.
    outputs : list of str
    sensors : dict of str to list of str
        Each sensor's outputs.
    reported : dict of str to (T,) bool array
        Where each sensor reported.
    """

    t: np.ndarray
    Y: np.ndarray
    dt: np.ndarray
    outputs: list[str]
    sensors: dict[str, list[str]]
    reported: dict[str, np.ndarray]

    def R(self, covariances: Mapping[str, ArrayLike]) -> np.ndarray:
        """The measurement covariance ``(ny, ny)``, block-diagonal: each sensor's
        covariance (a variance, a vector of variances or a matrix over its outputs,
        in the order it lists them) in the rows and columns of its outputs."""
        if not isinstance(covariances, Mapping):
            raise TypeError(f"covariances must be a dict of sensor name to covariance, got "
                            f"{type(covariances).__name__}")
        missing = [s for s in self.sensors if s not in covariances]
        unknown = [s for s in covariances if s not in self.sensors]
        if unknown or missing:
            raise ValueError(f"covariances must give one covariance per sensor "
                             f"{list(self.sensors)}" + (f"; unknown: {unknown}" if unknown
                                                        else "") +
                             (f"; missing: {missing}" if missing else ""))
        seen: dict[str, str] = {}
        for sensor, names in self.sensors.items():
            for n in names:
                if n in seen:
                    raise ValueError(f"sensors {seen[n]!r} and {sensor!r} both measure "
                                     f"{n!r}: a per-sensor R needs each output measured by "
                                     f"one sensor")
                seen[n] = sensor
        R = np.zeros((len(self.outputs), len(self.outputs)))
        for sensor, names in self.sensors.items():
            idx = [self.outputs.index(n) for n in names]
            R[np.ix_(idx, idx)] = as_covariance(covariances[sensor], len(idx),
                                                f"covariances[{sensor!r}]", definite=True)
        return R


def seconds(t: Any) -> np.ndarray:
    """Time stamps as float seconds: numbers as they are; ``numpy.datetime64`` (and pandas
    timestamps) as seconds since 1970-01-01, ``numpy.timedelta64`` as seconds, whatever
    their unit (read as numbers, milliseconds or nanoseconds would pass for seconds)."""
    t = np.asarray(t)
    if np.issubdtype(t.dtype, np.datetime64):
        return (t - np.datetime64(0, "s")) / np.timedelta64(1, "s")
    if np.issubdtype(t.dtype, np.timedelta64):
        return t / np.timedelta64(1, "s")
    return np.asarray(t, dtype=float)


def _stream(sensor: str, stream: Any, outputs: list[str], time: str
            ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """One stream as ``(t (k,), Y (k, m), names)``, checked."""
    where = f"streams[{sensor!r}]"
    names: list[str] | None = None
    if hasattr(stream, "columns") and hasattr(stream, "to_numpy"):  # a DataFrame
        if time not in stream.columns:
            raise ValueError(f"{where}: a DataFrame needs a time column {time!r} (time=...)")
        t = stream[time].to_numpy()
        names = [str(c) for c in stream.columns if c != time]
        Y = stream[names].to_numpy(dtype=float)
    elif isinstance(stream, tuple | list) and len(stream) in (2, 3):
        t, Y = stream[0], stream[1]
        if len(stream) == 3:
            names = [stream[2]] if isinstance(stream[2], str) else list(stream[2])
        elif hasattr(Y, "columns") and hasattr(Y, "to_numpy"):
            names, Y = [str(c) for c in Y.columns], Y.to_numpy(dtype=float)
        elif isinstance(Y, Mapping):
            names = [str(k) for k in Y]
            Y = np.column_stack([np.asarray(v, dtype=float) for v in Y.values()])
        elif sensor in outputs:
            names = [sensor]
        else:
            raise ValueError(f"{where}: say which outputs it measures, (t, Y, names), or "
                             f"name the sensor after its one output (outputs are {outputs})")
    else:
        raise TypeError(f"{where} must be (t, Y), (t, Y, names) or a DataFrame with a "
                        f"{time!r} column, got {type(stream).__name__}")
    try:
        t = seconds(t)
        Y = np.asarray(Y, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{where}: t and Y must be numeric arrays") from None
    if t.ndim != 1:
        raise ValueError(f"{where}: t must be a vector of time stamps, got shape {t.shape}")
    if Y.ndim == 1:
        Y = Y[:, None]
    if Y.shape != (len(t), len(names)):
        raise ValueError(f"{where}: Y must have shape ({len(t)}, {len(names)}) (one row per "
                         f"time stamp, one column per output {names}), got {Y.shape}")
    unknown = [n for n in names if n not in outputs]
    if unknown:
        raise ValueError(f"{where} measures {unknown}, which are not outputs of the model "
                         f"{outputs}")
    if len(set(names)) != len(names):
        raise ValueError(f"{where} names an output twice: {names}")
    if not np.isfinite(t).all():
        raise ValueError(f"{where}: the time stamps must be finite")
    if np.isinf(Y).any():
        raise ValueError(f"{where}: Y must not contain inf (NaN marks a missing value)")
    steps = np.diff(t)
    if (steps <= 0).any():
        k = int(np.flatnonzero(steps <= 0)[0])
        raise ValueError(f"{where}: the time stamps must be increasing; t[{k + 1}] = "
                         f"{float(t[k + 1])!r} follows t[{k}] = {float(t[k])!r}")
    return t, Y, names


def merge(streams: Mapping[str, Any], outputs: Sequence[str], *,
          time: str = "t") -> MergedRecord:
    """Merge asynchronous sensor streams into one record (see the module).

    Parameters
    ----------
    streams : dict of str to stream
        Per sensor: ``(t, Y, names)`` (time stamps ``(k,)``, values ``(k,)`` or
        ``(k, m)``, the ``m`` output names), ``(t, Y)`` with ``Y`` a DataFrame or a
        dict of output name to values, ``(t, Y)`` for a sensor named after its one
        output, or a pandas DataFrame with a time column ``time`` and a column per
        output. Time stamps strictly increasing within a stream.
    outputs : list of str
        The model's outputs (``model.output_names``), the columns of the record.
    time : str
        The time column of DataFrame streams.

    Returns
    -------
    MergedRecord
    """
    if not isinstance(streams, Mapping) or not streams:
        raise TypeError("streams must be a non-empty dict of sensor name to stream")
    if isinstance(outputs, str) or not all(isinstance(n, str) for n in outputs):
        raise TypeError("outputs must be a list of output names (model.output_names)")
    outputs = list(outputs)
    twice = sorted({n for n in outputs if outputs.count(n) > 1})
    if twice:
        raise ValueError(f"outputs names {twice} more than once: one column per output")
    parts = {str(s): _stream(str(s), stream, outputs, time) for s, stream in streams.items()}
    t = np.unique(np.concatenate([p[0] for p in parts.values()]))
    Y = np.full((len(t), len(outputs)), np.nan)
    source = np.full((len(t), len(outputs)), "", dtype=object)  # who wrote each entry
    reported = {}
    for sensor, (ts, Ys, names) in parts.items():
        rows = np.searchsorted(t, ts)
        reported[sensor] = np.zeros(len(t), dtype=bool)
        reported[sensor][rows] = True
        for j, n in enumerate(names):
            col = outputs.index(n)
            new = Ys[:, j]
            old = Y[rows, col]
            clash = ~np.isnan(old) & ~np.isnan(new) & (old != new)
            if clash.any():
                k = int(np.flatnonzero(clash)[0])
                raise ValueError(f"output {n!r} at t = {float(ts[k])!r}: "
                                 f"{source[rows[k], col]!r} reports {float(old[k])!r} and "
                                 f"{sensor!r} {float(new[k])!r}; merge "
                                 f"one value per output and time stamp")
            take = ~np.isnan(new)
            Y[rows[take], col] = new[take]
            source[rows[take], col] = sensor
    dt = np.concatenate([[np.nan], np.diff(t)])
    return MergedRecord(t=t, Y=Y, dt=dt, outputs=outputs,
                        sensors={s: p[2] for s, p in parts.items()}, reported=reported)
