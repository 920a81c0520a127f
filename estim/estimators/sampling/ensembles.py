"""What the particle filter and the ensemble Kalman filter share: square roots of
covariances for drawing noise, points drawn about an estimate and their mean and
deviations (in the tangent space of a model with quaternions or angles), and a model's
Functions evaluated over many points.

Both carry their distribution by ``N`` points stored as the columns of an
``(nx, N)`` array and evaluate the model at all of them in one call: through
:func:`estim._vectorised.vectorised` (one numpy operation per instruction of the
SX graph, over all points), or CasADi's ``map`` for a graph that calls other
Functions (an integrator).
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from estim._manifold import NP
from estim._progress import bar as progress_bar
from estim._validate import as_inputs, as_record
from estim._vectorised import vectorised

__all__ = ["deviations", "draw_about", "moved", "over_points", "prepared_record", "run_record",
           "square_root"]


def square_root(M: np.ndarray) -> np.ndarray:
    """A square root ``L`` with ``L L^T = M`` of a positive semi-definite ``M`` (Cholesky,
    or the symmetric eigen-decomposition when ``M`` is singular)."""
    try:
        return np.linalg.cholesky(M)
    except np.linalg.LinAlgError:
        lam, V = np.linalg.eigh(0.5 * (M + M.T))
        return V * np.sqrt(np.clip(lam, 0.0, None))


def draw_about(model, rng: np.random.Generator, x: np.ndarray, P: np.ndarray, N: int
               ) -> np.ndarray:
    """``N`` points drawn about ``x`` with covariance ``P`` (in the tangent space of the
    model's manifold: ``x (+) L xi``), ``(nx, N)``."""
    d = square_root(P) @ rng.standard_normal((model.ndx, N))
    return moved(model, x[:, None], d)


def moved(model, X: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Points ``X`` ``(nx, N)`` moved by tangent vectors ``D`` ``(ndx, N)``: ``X + D``, or
    the retraction on a manifold."""
    M = model.manifold
    return X + D if M.euclidean_states else M.retract(X.T, D.T, NP).T


def deviations(model, X: np.ndarray, W: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The (``W``-weighted; default equal) mean of points ``X`` ``(nx, N)`` and their
    deviations from it, ``(ndx, N)``: on a manifold its Karcher mean and the tangent
    vectors (:meth:`estim._manifold.Manifold.mean`)."""
    M = model.manifold
    if M.euclidean_states:
        x = X.mean(axis=1) if W is None else (X * W).sum(axis=1)
        return x, X - x[:, None]
    x, dev = M.mean(X.T, W)
    return x, dev.T


def over_points(fun: ca.Function) -> Callable[..., list[np.ndarray]]:
    """``fun`` evaluated on column-stacked points, ``g(*args, n=N)``: inputs ``(n_i, N)``
    (one column per point) or ``(n_i,)`` (the same at every point), outputs
    ``(n_o, N)``; vectorised, or CasADi's ``map``."""
    fast = vectorised(fun)
    if fast is not None:
        return fast

    def mapped(*args: np.ndarray, n: int) -> list[np.ndarray]:
        out = fun.map(n)(*[a if a.ndim == 2 else a[:, None] for a in args])
        out = out if isinstance(out, tuple | list) else [out]
        return [np.asarray(o, dtype=float).reshape(fun.nnz_out(i), n)
                for i, o in enumerate(out)]

    return mapped


def prepared_record(est, Y, U) -> tuple[np.ndarray, np.ndarray]:
    """The record checked, ``Y (T, ny)``, and the input of each step ``(T, nu)`` (``U[k]``
    acts from sample k to k+1, a held or sampled input at each sample for ``(T, nu)``),
    with ``est`` reset to filter it."""
    m = est.model
    Y = as_record(Y, m.ny, "Y", names=m.output_names, what="outputs")
    U = as_inputs(U, Y.shape[0], m)
    steps_u = U if m.sampled else np.vstack([np.zeros((1, m.nu)), U[:-1]])
    est.reset()
    est._dt = None
    return Y, steps_u


def run_record(est, Y, U) -> tuple[np.ndarray, np.ndarray, list]:
    """``est.step`` over a whole record after a reset, what :func:`~estim.replay` does:
    ``Y (T, ny)`` (NaN where missing) and ``U`` as for :meth:`EKF.filter
    <estim.EKF.filter>` (``U[k]`` acts from sample k to k+1; ``(T, nu)`` for a held or
    sampled input at each sample). Returns the estimates ``(T, nx)``, their
    covariances ``(T, ndx, ndx)`` and every step's :class:`~estim.StepInfo`."""
    m = est.model
    Y, steps_u = prepared_record(est, Y, U)
    T = Y.shape[0]
    X, P, infos = np.empty((T, m.nx)), np.empty((T, m.ndx, m.ndx)), []
    with progress_bar(T, f"{type(est).__name__}.filter", "sample") as bar:
        for k in range(T):  # (the record is checked: rows go to the step unchecked)
            X[k] = est._checked_step(Y[k], steps_u[k])
            infos.append(est.info)
            P[k] = est.info.P
            bar.update(1)
    return X, P, infos
