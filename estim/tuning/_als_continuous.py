r"""Autocovariance least squares of a continuous-time noise: the spectral density
:math:`Q_c` from a record, uniform or with irregular time stamps.

The noise a transition over :math:`\Delta t_k` receives is Van Loan's

.. math::
    Q_k = \int_0^{\Delta t_k} e^{A_k \tau} L Q_c L^\top e^{A_k^\top \tau}\, d\tau
        = \sum_i \theta_i \int_0^{\Delta t_k} e^{A_k \tau} L B_i L^\top
          e^{A_k^\top \tau}\, d\tau,

linear in the free entries :math:`\theta` of :math:`Q_c = \sum_i \theta_i B_i`
(:math:`A_k` the drift's Jacobian at the filter's estimate, ``L`` the model's
``noise_input``), so the autocovariance equations stay linear in :math:`\theta`: each
basis matrix :math:`B_i` of the structure becomes the per-transition basis
:math:`Q_d(\Delta t_k; L B_i L^\top)`. With uniform samples on a linear model it is one
constant basis (the time-invariant ALS); otherwise one per transition (the time-varying
ALS along the filter's estimates).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from estim.model import Model


def densities(model: Model, basis: list[np.ndarray]) -> list[np.ndarray]:
    r"""The densities :math:`L B_i L^\top` the states receive per unit of each free entry
    of :math:`Q_c` (``L`` the model's ``noise_input``, the identity without one)."""
    L = np.eye(model.nx) if model.noise_input is None else model.noise_input
    return [L @ B @ L.T for B in basis]


def interval_bases(model: Model, dens: list[np.ndarray], X: np.ndarray, W: np.ndarray
                   ) -> np.ndarray:
    r"""``(n, len(dens), nx, nx)``: :math:`Q_d(\Delta t_k; D_i)` of each transition
    ``k`` (from the state ``X[k]``, with the transition input ``W[k]``, its interval the
    last entry with ``variable_dt``) per density ``D_i``: Van Loan's exponential of the
    drift linearised at ``X[k]``
    (:func:`~estim.solvers.kalman.continuous.discretised_noises`), one mapped call per
    density."""
    from estim.solvers.kalman.continuous import discretised_noises

    out = np.empty((len(X), len(dens), model.nx, model.nx))
    for i, Di in enumerate(dens):
        out[:, i] = discretised_noises(model, Di, X, W)
    return out


def discretised(model: Model, Qc: np.ndarray, x: np.ndarray, w: np.ndarray) -> np.ndarray:
    r""":math:`Q_d(\Delta t)` of one transition (input ``w``) from the state ``x`` under
    the density :math:`L Q_c L^\top`."""
    return interval_bases(model, densities(model, [Qc]), x[None], w[None])[0, 0]


def start_density(model: Model, R0: np.ndarray, x0: np.ndarray, u: np.ndarray,
                  w: np.ndarray) -> np.ndarray:
    r"""A rough :math:`Q_c = s I` whose noise over a typical transition (input ``w``, from
    ``x0``) reaches the outputs with a tenth of ``R0``:
    :math:`s = 0.1 \operatorname{tr} R_0 / \operatorname{tr}(C Q_d(\Delta t; L L^	op)
    C^	op)`, ``C`` the output Jacobian at ``x0`` (the identity's scale where the noise
    does not reach the outputs within one interval)."""
    nq = model.nx if model.noise_input is None else model.noise_input.shape[1]
    C = np.asarray(model.H_x(x0, u, model.p).full())
    seen = float(np.trace(C @ discretised(model, np.eye(nq), x0, w) @ C.T))
    scale = 0.1 * float(np.trace(R0)) / seen if seen > 0 else 1.0
    return scale * np.eye(nq)


def check_options(model: Model, G: Any) -> None:
    """Refuse what a continuous noise does not take: a discrete model or states beyond
    ordinary differential equations on vectors, and ``G`` (the model's ``noise_input``
    shapes the noise)."""
    if not model.continuous or model.nz or not model.manifold.trivial:
        raise ValueError("continuous=True estimates the spectral density Qc of a "
                         "continuous-time noise: it needs a continuous model (ode=) on "
                         "vector states without algebraic equations")
    if G is not None:
        raise ValueError("G: with continuous=True the model's noise_input shapes the noise "
                         "(Qc is (nq, nq) for its nq columns); build the model with "
                         "noise_input= instead of giving G")
