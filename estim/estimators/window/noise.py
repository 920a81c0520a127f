"""Process noise of the windowed estimators: definite, or singular (noise on some
directions only), and the solver each form needs.

A positive definite ``Q`` weighs the defects :math:`x_{j+1} - F(x_j)` by
:math:`Q^{-1}` (:mod:`estim.solvers.least_squares.nlp`); a singular one makes the
dynamics exact in the directions without noise, a constrained problem with the noise
variables sized by the noise (:class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`), solved
by Ipopt (what ``solver="auto"`` becomes) or fatrop.
"""

from __future__ import annotations

import numpy as np

from estim.solvers.least_squares.nlp import SINGULAR_SOLVERS, LeastSquaresNLP, SingularNoiseNLP
from estim.solvers.weights import is_singular, noise_factor, pseudo_weight_factor

__all__ = ["noise_rank", "noise_solver", "noise_weight", "window_problem"]


def noise_rank(Q: np.ndarray) -> int | None:
    """The rank of a singular ``Q`` (None when it is positive definite)."""
    return noise_factor(Q).shape[1] if is_singular(Q) else None


def noise_solver(Q: np.ndarray, requested: str, resolved: str, *, who: str, model,
                 loss=None, rti: bool = False) -> tuple[str, int | None]:
    """The solver and the noise rank of an estimator with process noise ``Q``:
    ``resolved`` (what ``requested`` became) for a definite ``Q``; for a singular one,
    Ipopt when the solver was left to ``"auto"``, and a ``ValueError`` naming what does
    not apply (another solver, a robust loss, the real-time iteration, a manifold)."""
    rank = noise_rank(Q)
    if rank is None:
        return resolved, None
    if rank == 0:
        raise ValueError(f"Q is zero: {who} with exact dynamics is the estimation of the "
                         f"initial state alone; give the noise a variance somewhere")
    where = (f"Q is singular (rank {rank} of {Q.shape[0]}: no noise along some "
             f"directions), which {who} solves as a constrained problem")
    if requested == "auto":
        resolved = "ipopt"
    if resolved not in SINGULAR_SOLVERS:
        raise ValueError(f"{where} by {' or '.join(SINGULAR_SOLVERS)}; solver={resolved!r} "
                         f"does not apply (leave solver='auto')")
    if loss is not None:
        raise ValueError(f"{where}, without a robust loss: use loss='squared', or give "
                         f"every direction a variance")
    if rti:
        raise ValueError(f"{where}; the real-time iteration (rti=True) is a Gauss-Newton "
                         f"step of the unconstrained one: use rti=False")
    if not model.manifold.euclidean_states:
        raise ValueError(f"{where}, on vector states only; {model.name} has quaternions "
                         f"or angles: give every direction a variance")
    return resolved, rank


def window_problem(model, N: int, lower: np.ndarray, upper: np.ndarray, solver: str,
                   options: dict, rank: int | None, diagonal: dict, loss=None,
                   full: bool = False) -> LeastSquaresNLP:
    """The windowed problem of ``N`` slots for process noise of ``rank`` (None: a
    definite ``Q``); ``diagonal``: whether ``Q`` and ``R`` are diagonal."""
    if rank is None:
        return LeastSquaresNLP(model, N, lower, upper, solver, options,
                               diagonal_Q=diagonal["Q"], diagonal_R=diagonal["R"], full=full,
                               loss=loss)
    return SingularNoiseNLP(model, N, lower, upper, solver, options, rank,
                            diagonal_R=diagonal["R"], full=full)


def noise_weight(estimator, Q: np.ndarray, rank: int | None) -> np.ndarray:
    r"""The weight factor of the process term: :math:`W^\top W = Q^{-1}` for a definite
    ``Q``; the pseudo-inverse factor for a singular one (the constrained problem
    recovers :math:`G` from it)."""
    new = noise_rank(Q)
    if new != rank:
        n = Q.shape[0]
        raise ValueError(f"Q must keep the rank it had when {type(estimator).__name__} was "
                         f"built ({n if rank is None else rank} of {n}, now "
                         f"{n if new is None else new}): a definite and a singular Q are "
                         f"different problems; build a new estimator for another")
    return estimator._weight_factor(Q) if rank is None else pseudo_weight_factor(Q)
