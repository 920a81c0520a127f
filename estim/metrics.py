r"""Accuracy and consistency measures on a :class:`~estim.Log`, a fit or arrays."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from estim._validate import as_bool, as_float, as_int
from estim.estimators.filtering import Estimates

if TYPE_CHECKING:  # annotations only: a log is told by what it holds (see _is_log)
    from estim.log import Log

#: what the metrics read, for messages
ACCEPTED = ("an estim.Log, a result of a whole record (FilterResult, SmoothResult, "
            "ParticleFilterResult, ParticleSmoothResult, FitResult) with truth=, or an "
            "array of estimates (T, nx) with truth=")


class RMSE(float):
    """Root-mean-square error: a float (over all selected states) with ``per_state``.

    ``float(r)`` is :math:`\\sqrt{\\frac{1}{T' n}\\sum_{k,i} (\\hat x_{k,i} - x_{k,i})^2}`
    over the samples after burn-in and the selected states; ``r.per_state``
    maps each state name to its own RMSE.

    Parameters
    ----------
    value : float
        The overall RMSE.
    per_state : dict of str -> float
        RMSE of each state.
    """

    per_state: dict[str, float]

    def __init__(self, value: float, per_state: dict[str, float]) -> None:
        # the value is set by __new__ (float is immutable); this gives the signature
        pass

    def __new__(cls, value: float, per_state: dict[str, float]):
        obj = super().__new__(cls, value)
        obj.per_state = per_state
        return obj

    def __repr__(self) -> str:
        parts = ", ".join(f"{k}={v:.4g}" for k, v in self.per_state.items())
        return f"RMSE({float(self):.4g}; {parts})"

    def __reduce__(self):
        return (RMSE, (float(self), self.per_state))


def startup_samples(n: int) -> int:
    """Samples counted as the start-up transient of an ``n``-sample record: 10 %, at
    least one and at most ``n - 1`` (what comparison notes and error plots set apart)."""
    return min(max(1, n // 10), max(n - 1, 0))


def peak_location(state: str, t: float, seed: int) -> str:
    """Where a largest error is: ``"in C_C at t = 12.5 (seed 0)"``."""
    return f"in {state} at t = {t:g} (seed {seed})"


def _is_log(obj: object) -> bool:
    """Whether ``obj`` is a :class:`~estim.Log` (or anything that records series by name
    as one does): it has ``keys()`` and ``state_names``. Told by what it holds, so that
    the metrics sit below the log, which uses them."""
    return hasattr(obj, "state_names") and callable(getattr(obj, "keys", None)) \
        and hasattr(obj, "__contains__")


class _Series:
    """What the metrics read: ``x`` (truth), ``x_hat``, ``P``, ``nis``, ``t``, ``names``."""

    def __init__(self, estimate, truth, needs: Sequence[str]):
        if _is_log(truth):
            if "x" not in truth:
                raise ValueError(f"truth is a Log without the true state 'x' (it has "
                                 f"{truth.keys()})")
            truth_log, truth = truth, truth.x
        else:
            truth_log = None
        if _is_log(estimate):
            absent = [key for key in needs
                      if key not in estimate and not (key == "x" and truth is not None)]
            if absent:
                raise ValueError(f"log has no {', '.join(map(repr, absent))} series "
                                 f"(it has {estimate.keys()})")
            self.x_hat = estimate.x_hat if "x_hat" in estimate else None
            self.P = estimate.P if "P" in estimate else None
            self.nis = estimate.nis if "nis" in estimate else None
            self.t = estimate.t if "t" in estimate else None
            # states on a manifold (quaternions, angles): errors in its tangent space
            self.manifold = getattr(estimate, "manifold", None)
            names = estimate.state_names if self.manifold is None else \
                self.manifold.tangent_names
            x = estimate.x if truth is None and "x" in estimate else truth
        else:
            # a result of a whole record (the Estimates protocol), or bare estimates
            self.nis, self.t, self.manifold = None, None, None
            names = truth_log.state_names if truth_log is not None else []
            x_hat: object
            if isinstance(estimate, Estimates):
                x_hat, self.P = estimate.x, getattr(estimate, "P", None)
                self.t, self.manifold = estimate.t, estimate.manifold
                self.nis = getattr(estimate, "nis", None)  # a filter's result has it
                names = list(estimate.state_names) or names
                if self.manifold is not None:
                    names = self.manifold.tangent_names
            elif isinstance(estimate, (list, tuple, np.ndarray)):
                x_hat, self.P = estimate, None
            else:
                raise TypeError(f"estimate must be {ACCEPTED}, got {type(estimate).__name__}")
            self.x_hat = _as_states(x_hat, "estimate")
            if "nis" in needs and self.nis is None:
                raise ValueError(f"nis needs a Log or a filter's result (FilterResult): "
                                 f"a {type(estimate).__name__} has no innovations")
            if "P" in needs and self.P is None:
                raise ValueError("nees needs covariances: a Log with 'P', or a result with "
                                 "'P' (an array carries none, nor a fit that failed)")
            if truth is None and "x" in needs:
                raise ValueError(f"truth is required with a {type(estimate).__name__}: the "
                                 f"true states (T, nx), or a Log that has them")
            x = truth
        if x is not None and "x" in needs:
            x = _as_states(x, "truth")
            if self.x_hat is not None and x.shape != self.x_hat.shape:
                raise ValueError(f"truth has shape {x.shape} but the estimates have "
                                 f"{self.x_hat.shape}")
        self.x = x
        if self.t is None and truth_log is not None and "t" in truth_log:
            self.t = truth_log.t
        if self.x_hat is not None:
            n = len(self.x_hat)
        else:  # a log read for its innovations only (nis), which it has
            assert self.nis is not None
            n = len(self.nis)
        if self.t is None:
            self.t = np.arange(n, dtype=float)
        width = self.x_hat.shape[1] if self.x_hat is not None else 0
        if self.manifold is not None:
            width = self.manifold.ndx
        self.names = list(names) if len(names) == width else \
            [f"x{i + 1}" for i in range(width)]
        self.n = n


    def errors(self, burn_in: int) -> np.ndarray:
        r"""The errors :math:`\hat x_k - x_k` from ``burn_in`` on, ``(T', nx)``; on a
        manifold :math:`\hat x_k \ominus x_k`, ``(T', ndx)`` (a quaternion's as a
        rotation vector, angles wrapped)."""
        assert self.x is not None and self.x_hat is not None  # what _select asked for
        if self.manifold is not None:
            return self.manifold.errors(self.x_hat[burn_in:], self.x[burn_in:])
        return self.x_hat[burn_in:] - self.x[burn_in:]


def _as_states(values, name: str) -> np.ndarray:
    """A (T, nx) float array of states (a 1-D array is one state)."""
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be numeric states (T, nx), got "
                        f"{type(values).__name__}") from None
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name} must have shape (T, nx), got {arr.shape}")
    return arr


def _select(estimate, burn_in: int, states: Sequence[str] | None,
            needs: Sequence[str] = ("x", "x_hat"), truth=None):
    """The series the metrics read, and the indices of the selected states."""
    data = _Series(estimate, truth, needs)
    burn_in = as_int(burn_in, "burn_in", minimum=0)
    if isinstance(states, str):
        states = [states]
    if states is not None:
        if not hasattr(states, "__iter__"):
            raise TypeError(f"states must be a list of state names, got {type(states).__name__}")
        states = list(states)
        for s in states:
            if not isinstance(s, str):
                raise TypeError(f"states must be a list of state names, got item {s!r}")
    if burn_in >= data.n:
        raise ValueError(f"burn_in ({burn_in}) must be shorter than the log ({data.n} samples)")
    names = data.names
    if states is None:
        idx = list(range(len(names)))
    else:
        unknown = [s for s in states if s not in names]
        if unknown:
            raise ValueError(f"states {unknown} are not in the log; states are {names}")
        idx = [names.index(s) for s in states]
    return data, idx


def errors(estimate: Log | Estimates | np.ndarray, burn_in: int = 0, *,
           truth: np.ndarray | Log | None = None) -> np.ndarray:
    """Estimation error :math:`\\hat x_k - x_k`, shape ``(T - burn_in, nx)``.

    Parameters
    ----------
    estimate : Log, result or (T, nx) array
        The estimates: a :class:`~estim.Log` (with its truth ``x`` unless
        ``truth`` is given), a result of a whole record (any
        :class:`~estim.estimators.filtering.Estimates`: ``filter``, ``smooth``, ``fit``)
        or an array.
    burn_in : int
        Samples to skip at the start.
    truth : (T, nx) array or Log, optional
        The true states; required unless ``estimate`` is a Log that has them.
    """
    data, _ = _select(estimate, burn_in, None, truth=truth)
    return data.errors(burn_in)


def rmse(estimate: Log | Estimates | np.ndarray, burn_in: int = 0,
         states: Sequence[str] | None = None, *,
         truth: np.ndarray | Log | None = None) -> RMSE:
    """RMSE of the estimate against the truth, overall and per state.

    ``estim.rmse(log)`` after :func:`~estim.simulate`; ``estim.rmse(fit,
    truth=x_true)`` for a :meth:`FullInformation.fit`; ``estim.rmse(x_hat,
    truth=x_true)`` for plain arrays.

    Parameters
    ----------
    estimate : Log, result or (T, nx) array
        The estimates: a :class:`~estim.Log` (with its truth ``x`` unless
        ``truth`` is given), a result of a whole record (any
        :class:`~estim.estimators.filtering.Estimates`: ``filter``, ``smooth``, ``fit``)
        or an array.
    burn_in : int
        Samples to skip at the start.
    states : list of str, optional
        States to include (default all).
    truth : (T, nx) array or Log, optional
        The true states; required unless ``estimate`` is a Log that has them.
    """
    data, idx = _select(estimate, burn_in, states, truth=truth)
    err = data.errors(burn_in)[:, idx]
    per = {data.names[j]: float(np.sqrt(np.mean(err[:, i] ** 2))) for i, j in enumerate(idx)}
    return RMSE(float(np.sqrt(np.mean(err**2))), per)


def nees(estimate: Log | Estimates, burn_in: int = 0, *,
         truth: np.ndarray | Log | None = None) -> np.ndarray:
    r"""Normalised estimation error squared per sample, :math:`e_k^\top P_k^{-1} e_k`, (T',).

    NaN where the estimator reported no covariance. For a consistent filter
    its expectation is :math:`n_x`.

    Parameters
    ----------
    estimate : Log or result
        Estimates with covariances ``P`` (T, nx, nx) (a Log with ``P``, a
        ``FullInformation.fit`` result, or the result of ``EKF.smooth`` /
        ``UKF.smooth``), and the truth unless ``truth`` is given.
    burn_in : int
        Samples to skip at the start.
    truth : (T, nx) array or Log, optional
        The true states; required unless ``estimate`` is a Log that has them.
    """
    data, _ = _select(estimate, burn_in, None, ("x", "x_hat", "P"), truth=truth)
    return nees_values(data.errors(burn_in), np.asarray(data.P, dtype=float)[burn_in:])


#: up to this many states :func:`nees_values` factors all covariances at once, entry by
#: entry (a batched ``numpy.linalg.solve`` calls LAPACK once per matrix: ten times slower
#: on 2x2 matrices)
NEES_ENTRYWISE_STATES = 6


def nees_values(err: np.ndarray, P: np.ndarray) -> np.ndarray:
    r""":math:`e^\top P^{-1} e` of errors ``(..., nx)`` and covariances ``(..., nx, nx)``
    (any leading shape, e.g. seeds × samples), NaN where ``P`` is not finite.

    With at most :data:`NEES_ENTRYWISE_STATES` states, :math:`|L^{-1} e|^2` with the
    Cholesky factor :math:`P = L L^\top` computed for all samples at once, entry by entry;
    a covariance without a Cholesky factor (not positive definite) is solved by LU, as
    with more states, so that its NEES still shows (negative or huge) instead of NaN."""
    ok = np.isfinite(P).all(axis=(-2, -1))
    if ok.all():
        e, C = err.reshape(-1, err.shape[-1]), P.reshape(-1, *P.shape[-2:])
    elif ok.any():
        e, C = err[ok], P[ok]
    else:
        return np.full(err.shape[:-1], np.nan)
    n = e.shape[-1]
    if n > NEES_ENTRYWISE_STATES:
        total = _solved(e, C)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            L: dict[tuple[int, int], np.ndarray] = {}
            z: list[np.ndarray] = []
            total = np.zeros(len(e))
            for i in range(n):
                for j in range(i):
                    acc = C[:, i, j]
                    for k in range(j):
                        acc = acc - L[i, k] * L[j, k]
                    L[i, j] = acc / L[j, j]
                d = C[:, i, i]
                for k in range(i):
                    d = d - L[i, k] * L[i, k]
                L[i, i] = np.sqrt(d)
                zi = e[:, i]
                for k in range(i):
                    zi = zi - L[i, k] * z[k]
                z.append(zi / L[i, i])
                total += z[i] * z[i]
        bad = ~np.isfinite(total)
        if bad.any():  # not positive definite: LU
            total[bad] = _solved(e[bad], C[bad])
    if ok.all():
        return total.reshape(err.shape[:-1])
    out = np.full(err.shape[:-1], np.nan)
    out[ok] = total
    return out


def _solved(e: np.ndarray, C: np.ndarray) -> np.ndarray:
    """:math:`e^\top C^{-1} e` per row by LU (``numpy.linalg.solve``); inf for a singular
    ``C`` (a covariance that claims no uncertainty in some direction)."""
    try:
        sol = np.linalg.solve(C, e[..., None])[..., 0]
    except np.linalg.LinAlgError:  # some are singular: one by one
        out = np.empty(len(e))
        for k in range(len(e)):
            try:
                out[k] = e[k] @ np.linalg.solve(C[k], e[k])
            except np.linalg.LinAlgError:
                out[k] = np.inf
        return out
    return np.einsum("ki,ki->k", e, sol)


def nis(log: Log | Estimates, burn_in: int = 0) -> np.ndarray:
    r"""Normalised innovation squared per sample, :math:`e_k^\top S_k^{-1} e_k`, (T',).

    Parameters
    ----------
    log : Log or FilterResult
        Needs ``nis``: recorded by :func:`estim.simulate` from ``info.nis``, or the
        ``nis`` of a filter's whole-record result (``EKF.filter``, ``UKF.filter``).
    burn_in : int
        Samples to skip at the start.
    """
    data, _ = _select(log, burn_in, None, ("nis",))
    return np.asarray(data.nis[burn_in:], dtype=float)


def chi2_bounds(dof: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    r"""Two-sided interval for the mean of ``n`` independent :math:`\chi^2_{dof}` samples.

    A consistent filter's average NEES (dof = nx) or NIS (dof = ny) over
    ``n`` samples or runs should fall inside with the given confidence
    (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4).

    Parameters
    ----------
    dof : int
        Degrees of freedom of one sample (nx for NEES, ny for NIS).
    n : int
        Number of independent samples averaged.
    confidence : float
        Probability mass inside the interval.
    """
    dof, n = as_int(dof, "dof", minimum=1), as_int(n, "n", minimum=1)
    confidence = as_float(confidence, "confidence", expected="a probability in (0, 1)")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be a probability in (0, 1), got {confidence!r}")
    from scipy import stats  # ~0.3 s to import: on first use, not with estim

    alpha = 1.0 - confidence
    lo = stats.chi2.ppf(alpha / 2, dof * n) / n
    hi = stats.chi2.ppf(1 - alpha / 2, dof * n) / n
    return float(lo), float(hi)


def convergence_time(estimate: Log | Estimates | np.ndarray, tol: float,
                     states: Sequence[str] | None = None, relative: bool = False, *,
                     truth: np.ndarray | Log | None = None) -> float:
    """First time after which every selected error stays within ``tol`` (inf if never).

    Parameters
    ----------
    estimate : Log, result or (T, nx) array
        The estimates: a :class:`~estim.Log` (with its truth ``x`` unless
        ``truth`` is given), a result of a whole record (any
        :class:`~estim.estimators.filtering.Estimates`: ``filter``, ``smooth``, ``fit``)
        or an array.
    tol : float
        Error bound.
    states : list of str, optional
        States to check (default all).
    relative : bool
        Bound the error relative to ``|x|`` instead of absolutely.
    truth : (T, nx) array or Log, optional
        The true states; required unless ``estimate`` is a Log that has them.
    """
    data, idx = _select(estimate, 0, states, truth=truth)
    tol = as_float(tol, "tol", minimum=0.0)
    relative = as_bool(relative, "relative")
    if relative and data.manifold is not None:
        raise ValueError("relative=True: the errors of states with quaternions or angles "
                         "are tangent vectors, not relative to the states; give tol in "
                         "radians and state units")
    err = np.abs(data.errors(0)[:, idx])
    if relative:
        err = err / np.maximum(np.abs(data.x[:, idx]), 1e-300)
    bad = np.flatnonzero((err > tol).any(axis=1))
    if len(bad) == 0:
        return float(data.t[0])
    if bad[-1] == len(err) - 1:
        return float("inf")
    return float(data.t[bad[-1] + 1])
