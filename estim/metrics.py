r"""Accuracy and consistency measures on a :class:`~estim.Log`."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from estim._validate import as_bool, as_float, as_int
from estim.log import Log


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


def _select(log, burn_in: int, states: Sequence[str] | None,
            needs: Sequence[str] = ("x", "x_hat")):
    if not isinstance(log, Log):
        raise TypeError(f"log must be an estim.Log, got {type(log).__name__}")
    absent = [key for key in needs if key not in log]
    if absent:
        raise ValueError(f"log has no {', '.join(map(repr, absent))} series "
                         f"(it has {log.keys()})")
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
    if burn_in >= len(log):
        raise ValueError(f"burn_in ({burn_in}) must be shorter than the log ({len(log)} samples)")
    names = log.state_names or [f"x{i + 1}" for i in range(log.x.shape[1])]
    if states is None:
        idx = list(range(len(names)))
    else:
        unknown = [s for s in states if s not in names]
        if unknown:
            raise ValueError(f"states {unknown} are not in the log; states are {names}")
        idx = [names.index(s) for s in states]
    return idx, names


def errors(log, burn_in: int = 0) -> np.ndarray:
    """Estimation error :math:`\\hat x_k - x_k`, shape ``(T - burn_in, nx)``.

    Parameters
    ----------
    log : Log
        Needs ``x`` and ``x_hat``.
    burn_in : int
        Samples to skip at the start.
    """
    _select(log, burn_in, None)
    return log.x_hat[burn_in:] - log.x[burn_in:]


def rmse(log, burn_in: int = 0, states: Sequence[str] | None = None) -> RMSE:
    """RMSE of the estimate against the truth, overall and per state.

    Parameters
    ----------
    log : Log
        Needs ``x`` and ``x_hat``.
    burn_in : int
        Samples to skip at the start.
    states : list of str, optional
        States to include (default all).
    """
    idx, names = _select(log, burn_in, states)
    err = (log.x_hat[burn_in:] - log.x[burn_in:])[:, idx]  # errors(), checked once
    per = {names[j]: float(np.sqrt(np.mean(err[:, i] ** 2))) for i, j in enumerate(idx)}
    return RMSE(float(np.sqrt(np.mean(err**2))), per)


def nees(log, burn_in: int = 0) -> np.ndarray:
    r"""Normalised estimation error squared per sample, :math:`e_k^\top P_k^{-1} e_k`, (T',).

    NaN where the estimator reported no covariance. For a consistent filter
    its expectation is :math:`n_x`.

    Parameters
    ----------
    log : Log
        Needs ``x``, ``x_hat`` and ``P``.
    burn_in : int
        Samples to skip at the start.
    """
    _select(log, burn_in, None, ("x", "x_hat", "P"))
    err = log.x_hat[burn_in:] - log.x[burn_in:]
    P = log.P[burn_in:]
    out = np.full(len(err), np.nan)
    ok = np.isfinite(P).all(axis=(1, 2))
    if ok.any():
        sol = np.linalg.solve(P[ok], err[ok][..., None])[..., 0]
        out[ok] = np.einsum("ki,ki->k", err[ok], sol)
    return out


def nis(log, burn_in: int = 0) -> np.ndarray:
    r"""Normalised innovation squared per sample, :math:`e_k^\top S_k^{-1} e_k`, (T',).

    Parameters
    ----------
    log : Log
        Needs ``nis`` (recorded by :func:`estim.simulate` from ``info.nis``).
    burn_in : int
        Samples to skip at the start.
    """
    _select(log, burn_in, None, ("nis",))
    return np.asarray(log.nis[burn_in:], dtype=float)


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


def convergence_time(log, tol: float, states: Sequence[str] | None = None,
                     relative: bool = False) -> float:
    """First time after which every selected error stays within ``tol`` (inf if never).

    Parameters
    ----------
    log : Log
    tol : float
        Error bound.
    states : list of str, optional
        States to check (default all).
    relative : bool
        Bound the error relative to ``|x|`` instead of absolutely.
    """
    idx, _ = _select(log, 0, states)
    tol = as_float(tol, "tol", minimum=0.0)
    relative = as_bool(relative, "relative")
    err = np.abs(log.x_hat[:, idx] - log.x[:, idx])
    if relative:
        err = err / np.maximum(np.abs(log.x[:, idx]), 1e-300)
    bad = np.flatnonzero((err > tol).any(axis=1))
    if len(bad) == 0:
        return float(log.t[0])
    if bad[-1] == len(err) - 1:
        return float("inf")
    return float(log.t[bad[-1] + 1])
