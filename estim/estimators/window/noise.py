r"""Process noise of the windowed estimators: definite, singular (noise on some
directions only) or continuous (a spectral density, ``Qc=``), and the solver each form
needs.

A positive definite ``Q`` weighs the defects :math:`x_{j+1} - F(x_j)` by
:math:`Q^{-1}` (:mod:`estim.solvers.least_squares.nlp`); a singular one makes the
dynamics exact in the directions without noise, a constrained problem with the noise
variables sized by the noise (:class:`~estim.solvers.least_squares.nlp.SingularNoiseNLP`), solved
by Ipopt (what ``solver="auto"`` becomes) or fatrop. A continuous noise weighs each
defect by the inverse of its own interval's :math:`Q_d(\Delta t_j)`
(:func:`~estim.solvers.kalman.continuous.interval_weight`), definite whenever the noise
reaches every state, whatever the rank of :math:`L Q_c L^\top`: every solver applies.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from estim.solvers.kalman.continuous import discretised_noise, interval_weight
from estim.solvers.least_squares.nlp import SINGULAR_SOLVERS, LeastSquaresNLP, SingularNoiseNLP
from estim.solvers.weights import is_singular, noise_factor, pseudo_weight_factor

__all__ = ["check_new_q", "check_reach", "check_tuning_noise", "noise_rank", "noise_solver",
           "noise_weight", "window_problem"]


def noise_rank(Q: np.ndarray) -> int | None:
    """The rank of a singular ``Q`` (None when it is positive definite)."""
    return noise_factor(Q).shape[1] if is_singular(Q) else None


def noise_solver(Q: np.ndarray, requested: str, resolved: str, *, who: str, model,
                 loss=None, rti: bool = False, continuous: bool = False,
                 x0: np.ndarray | None = None) -> tuple[str, int | None]:
    """The solver and the noise rank of an estimator with process noise ``Q``:
    ``resolved`` (what ``requested`` became) for a definite ``Q``; for a singular one,
    Ipopt when the solver was left to ``"auto"``, and a ``ValueError`` naming what does
    not apply (another solver, a robust loss, the real-time iteration, a manifold).
    ``continuous``: ``Q`` is the density of a continuous noise (``Qc=``), whose
    transitions have definite covariances :math:`Q_d(\\Delta t)` (checked at ``x0`` by
    :func:`check_reach`) whatever its rank."""
    if continuous:
        check_reach(model, Q, np.zeros(model.nx) if x0 is None else x0)
        return resolved, None
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
                   full: bool = False, continuous: bool = False) -> LeastSquaresNLP:
    """The windowed problem of ``N`` slots for process noise of ``rank`` (None: a
    definite ``Q``); ``diagonal``: whether ``Q`` and ``R`` are diagonal; ``continuous``:
    the noise is continuous, each transition weighed by the inverse of its own
    :math:`Q_d(\\Delta t)` (:func:`~estim.solvers.kalman.continuous.interval_weight`)."""
    if continuous:
        return LeastSquaresNLP(model, N, lower, upper, solver, options,
                               diagonal_R=diagonal["R"], full=full, loss=loss,
                               process_weight=interval_weight)
    if rank is None:
        return LeastSquaresNLP(model, N, lower, upper, solver, options,
                               diagonal_Q=diagonal["Q"], diagonal_R=diagonal["R"], full=full,
                               loss=loss)
    return SingularNoiseNLP(model, N, lower, upper, solver, options, rank,
                            diagonal_R=diagonal["R"], full=full)


def noise_weight(estimator, Q: np.ndarray, rank: int | None) -> np.ndarray:
    r"""The weight factor of the process term: :math:`W^\top W = Q^{-1}` for a definite
    ``Q``; the pseudo-inverse factor for a singular one (the constrained problem
    recovers :math:`G` from it); a continuous noise's density itself (each transition's
    weight is made from it in the problem)."""
    if getattr(estimator, "Qc", None) is not None:
        return np.asarray(Q, float)
    new = noise_rank(Q)
    if new != rank:
        n = Q.shape[0]
        raise ValueError(f"Q must keep the rank it had when {type(estimator).__name__} was "
                         f"built ({n if rank is None else rank} of {n}, now "
                         f"{n if new is None else new}): a definite and a singular Q are "
                         f"different problems; build a new estimator for another")
    return estimator._weight_factor(Q) if rank is None else pseudo_weight_factor(Q)


def check_reach(model, W: np.ndarray, x: np.ndarray) -> None:
    r"""A ``ValueError`` unless the continuous noise of density ``W`` reaches every state
    over the model's interval: :math:`Q_d(\Delta t)` of the linearisation at ``x``
    definite (the windowed estimators weigh each transition by its inverse). A noise
    input that leaves a state untouched whatever the interval (a constant parameter as
    a state, a decoupled channel) fails it."""
    w = np.zeros(model.nw)
    if model.variable_dt:
        w[-1] = model.dt
    Qd = np.asarray(ca.DM(discretised_noise(model, ca.DM(W), ca.DM(x), ca.DM(w))))
    lam = np.linalg.eigvalsh(0.5 * (Qd + Qd.T))
    if not np.isfinite(lam).all() or lam[0] <= 1e-12 * max(lam[-1], 0.0):
        raise ValueError(f"Qc: the noise through noise_input does not reach every state of "
                         f"{model.name} over an interval (Q_d(dt) at x0 has eigenvalues "
                         f"down to {lam[0]:.3g}), and the windowed estimators weigh each "
                         f"transition by its inverse: give the unreached states a "
                         f"noise_input column, or a per-transition Q")


def check_tuning_noise(estimator, Q: np.ndarray, rank: int | None) -> None:
    """A new ``Q`` for ``estimator`` (``set_tuning``): refused where its noise is a
    continuous density (``Qc=``), else of the rank it was built for
    (:func:`noise_weight`)."""
    if getattr(estimator, "Qc", None) is not None:
        raise ValueError(f"this {type(estimator).__name__}'s process noise is a spectral "
                         f"density (Qc=): build a new estimator with the new Qc")
    noise_weight(estimator, Q, rank)


def check_new_q(estimator, new: dict) -> None:
    """An estimator's ``_check_tuning`` of a new ``Q`` (:func:`check_tuning_noise`)."""
    if "Q" in new:
        check_tuning_noise(estimator, new["Q"], estimator._rank)
