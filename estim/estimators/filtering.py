"""Results that hold estimates over time, and the one they share.

Every result of a whole record (:class:`FilterResult` of :meth:`EKF.filter
<estim.EKF.filter>`, :meth:`UKF.filter <estim.UKF.filter>` and :meth:`EnKF.filter
<estim.EnKF.filter>`; the smoothers' :class:`~estim.estimators.kalman.smoothing.SmoothResult`
and :class:`~estim.estimators.sampling.particle_smoothing.ParticleSmoothResult`; the
particle filter's result; :class:`~estim.estimators.window.fie.FitResult`) is an
:class:`Estimates`: means ``x (T, nx)``, covariances ``P (T, nd, nd)`` (``nd`` is
``nx``, or the tangent dimension on a model with quaternions or angles; None where
there is none), the sample times ``t (T,)`` and the ``state_names``. The metrics
(:func:`~estim.rmse`, :func:`~estim.nees`, :func:`~estim.errors`, with ``truth=``),
the plots of :mod:`estim.plotting` and :meth:`~estim.Log.from_estimates` read any of
them as they read a :class:`~estim.Log`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from estim._validate import as_intervals

if TYPE_CHECKING:
    import pandas as pd


@dataclass(frozen=True, repr=False)
class Estimates:
    """Estimates over time, with their covariances, times and state names.

    Subclasses (frozen dataclasses) hold ``x (T, nx)``, ``P (T, nd, nd)`` or None,
    ``t (T,)`` (the sample times: the record's, or :math:`k\\,\\Delta t`),
    ``state_names`` and ``manifold`` (the states' manifold on a model with quaternions
    or angles, else None).
    """

    if TYPE_CHECKING:  # each result declares its own estimates among its fields
        x: np.ndarray

    t: np.ndarray | None = field(default=None, kw_only=True, repr=False, compare=False)
    state_names: tuple[str, ...] = field(default=(), kw_only=True, repr=False,
                                         compare=False)
    manifold: Any = field(default=None, kw_only=True, repr=False, compare=False)

    @property
    def sd(self) -> np.ndarray | None:
        """Standard deviations :math:`\\sqrt{P_{k,ii}}`, ``(T, nd)`` (None without ``P``)."""
        P = getattr(self, "P", None)
        if P is None:
            return None
        return np.sqrt(np.maximum(np.diagonal(P, axis1=1, axis2=2), 0.0))

    def times(self) -> np.ndarray:
        """``t``, or the sample indices where the result was made without times."""
        return np.arange(len(self.x), dtype=float) if self.t is None else self.t

    def names(self) -> list[str]:
        """The state names (``x1, x2, ...`` where the result has none)."""
        n = self.x.shape[1]
        return list(self.state_names) if len(self.state_names) == n else \
            [f"x{i + 1}" for i in range(n)]

    def __repr__(self) -> str:
        """One line: the kind, its length and states, and what went wrong where anything
        did (the arrays are the attributes)."""
        parts = [f"T={len(self.x)}", f"states {', '.join(self.names())}"]
        status = getattr(self, "status", None)
        if isinstance(status, tuple):
            kinds: dict[str, int] = {}
            for one in status:
                kinds[one.split(":")[0]] = kinds.get(one.split(":")[0], 0) + 1
            parts.append(", ".join(f"{n} {k}" for k, n in kinds.items()))
        elif isinstance(status, str):
            parts.append(f"status {status!r}")
        for key in ("cost", "log_likelihood"):
            value = getattr(self, key, None)
            if value is not None:
                parts.append(f"{key} {value:.6g}")
        return f"<{type(self).__name__}: {'; '.join(parts)}>"

    def to_pandas(self) -> pd.DataFrame:
        """One row a sample, indexed by ``t``: ``x_hat:<name>`` for every state and
        ``sd:<name>`` for the standard deviations (where ``P`` exists and is per state,
        i.e. not on a manifold's tangent space of another size).

        Requires pandas (``pip install estim[data]``).
        """
        try:
            import pandas as pd
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError("to_pandas needs pandas: pip install 'estim[data]'") from exc
        names = self.names()
        cols = {f"x_hat:{n}": self.x[:, j] for j, n in enumerate(names)}
        sd = self.sd
        if sd is not None and sd.shape[1] == len(names):
            cols.update({f"sd:{n}": sd[:, j] for j, n in enumerate(names)})
        frame = pd.DataFrame(cols, index=pd.Index(self.times(), name="t"))
        return frame


def stamped(result, model, t=None, *, fixed_dt: bool = False):
    """``result`` with the sample times (``t``, or :math:`k\\,\\Delta t` of the model),
    the model's state names and its manifold (where it has quaternions or angles).

    ``t`` is checked as :func:`~estim.replay` checks it; an estimator that integrates
    over the model's fixed ``dt`` only (``fixed_dt``) refuses the times of a model built
    with ``variable_dt=True``, which it would not follow."""
    T = len(result.x)
    if t is not None and as_intervals(t, T, model) is not None and fixed_dt:
        raise ValueError(f"t: this estimator integrates {model.name} over its fixed dt = "
                         f"{model.dt:g}; run it with replay(..., t=t) to follow the "
                         f"intervals of a variable_dt model")
    times = np.arange(T, dtype=float) * model.dt if t is None else \
        np.asarray(t, dtype=float).reshape(-1)
    manifold = None if model.manifold.euclidean_states else model.manifold
    return dataclasses.replace(result, t=times, state_names=tuple(model.state_names),
                               manifold=manifold)



@dataclass(frozen=True, repr=False)
class FilterResult(Estimates):
    """A record filtered by :meth:`EKF.filter <estim.EKF.filter>`,
    :meth:`UKF.filter <estim.UKF.filter>` or :meth:`EnKF.filter <estim.EnKF.filter>`:
    what :func:`~estim.replay` (``step`` at every sample) gives, sample by sample (for
    the EnKF: ensemble means and covariances).

    Attributes
    ----------
    x : (T, nx) array
        The estimates :math:`\\hat x_{k|k}`.
    P : (T, nx, nx) array
        Their covariances.
    innovation : (T, ny) array
        The innovations :math:`y_k - h(\\bar x_k)` (for the UKF, :math:`y_k` less the
        sigma-point mean of :math:`h`; 0 where an output is missing, NaN at a failed step).
    nis : (T,) array
        Normalised innovations squared (NaN without any output measured, or at a
        failed step).
    status : tuple of str
        The status of every sample (``"ok"``, ``"suspect: ..."``, ``"rejected: ..."``,
        ``"failed: ..."``).
    success : bool
        Every step succeeded.
    converged : (T,) bool array or None
        For a filter whose update iterates (``iterations`` > 1): whether each sample's
        update converged (:mod:`estim.estimators.kalman.iterated_updates`); None otherwise.
    R, Q : (T, ny, ny) and (T, nx, nx) arrays or None
        For an adaptive filter (``adapt=``): the measurement noise covariance it has
        learnt after each sample and, with ``adapt="QR"``, the process noise it implied
        (:mod:`estim.estimators.kalman.adaptive`); None otherwise.
    t, state_names, manifold :
        Sample times, state names and the states' manifold (see :class:`Estimates`).
    """

    x: np.ndarray
    P: np.ndarray
    innovation: np.ndarray
    nis: np.ndarray
    status: tuple[str, ...]
    success: bool
    converged: np.ndarray | None = None
    R: np.ndarray | None = None
    Q: np.ndarray | None = None
