r"""Local identifiability of an initial state from one window of data.

Along a trajectory from :math:`x_0` the stacked outputs of the window have the
sensitivity :math:`S = \partial (y_0, \dots, y_N) / \partial x_0`, whitened by
:math:`R^{-1/2}` when the output covariance is known. Its singular values say which
combinations of :math:`x_0` the window determines; :math:`S^\top S` is the Fisher
information, whose inverse bounds the covariance of any unbiased estimate of
:math:`x_0` (Cramér-Rao).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._validate import (
    as_covariance,
    as_float,
    as_input_table,
    as_int,
    as_vector,
    check_keywords,
)
from estim.model import Model


@dataclass
class WindowReport:
    """Local identifiability of ``x0`` from one window of data (:func:`window`).

    Attributes
    ----------
    sensitivity : (m, nx) array
        ``R^{-1/2} d(y_0 .. y_N) / d x_0`` (whitened if ``R`` is given).
    singular_values : (nx,) array
    rank : int
    condition : float
        ``s_max / s_min`` (inf when singular).
    fisher : (nx, nx) array or None
        ``S^T S`` with the whitened sensitivity (given ``R``).
    crb_std : (nx,) array or None
        Cramer-Rao lower bound on the standard deviation of each state of
        ``x0`` (inf where not identifiable).
    """

    sensitivity: np.ndarray
    singular_values: np.ndarray
    rank: int
    condition: float
    fisher: np.ndarray | None
    crb_std: np.ndarray | None


@check_keywords
def window(model: Model, x0: ArrayLike, n_steps: int, inputs: ArrayLike | None = None,
           R: ArrayLike | None = None, every: int = 1, rtol: float = 1e-9) -> WindowReport:
    """Identifiability of the initial state from ``n_steps`` samples along a trajectory.

    Parameters
    ----------
    model : Model
        Continuous or discrete (the sampled map ``F`` is used either way).
    x0 : (nx,) array
        Initial state of the window.
    n_steps : int
        Steps of the window (samples ``0, every, 2 every, ...`` up to it).
    inputs : (n_steps, nu) array, optional
        Inputs applied after each step (zero if omitted).
    R : float, (ny,) or (ny, ny), optional
        Output covariance: whitens the sensitivity and gives the Fisher
        information and the Cramer-Rao bound.
    every : int
        Keep every ``every``-th sample (a downsampled buffer).
    rtol : float
        Singular values below ``rtol`` times the largest count as zero.
    """
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    x_start = as_vector(x0, model.nx, "x0")
    n_steps = as_int(n_steps, "n_steps", minimum=0)
    every = as_int(every, "every", minimum=1)
    rtol = as_float(rtol, "rtol", positive=True, expected="a number in (0, 1)")
    if rtol >= 1:
        raise ValueError(f"rtol must be a number in (0, 1), got {rtol!r}")
    U = np.zeros((n_steps, model.nu)) if inputs is None else \
        as_input_table(inputs, n_steps, model.nu)
    Rm = None if R is None else as_covariance(R, model.ny, "R")
    x = ca.SX.sym("x", model.nx)
    p = ca.DM(model.p)
    xs, ys = x, []
    u_prev = ca.DM.zeros(model.nu)
    for k in range(n_steps + 1):
        if k % every == 0:
            ys.append(model.H(xs, u_prev, p))
        if k < n_steps:
            # the transition's input: with variable_dt, the input and the model's interval
            w = U[k] if model.sampled else model.transition(None, U[k])
            xs = model.F(xs, ca.DM(w), p)
            u_prev = ca.DM(U[k])
    S = np.asarray(ca.Function("S", [x], [ca.jacobian(ca.vertcat(*ys), x)])(x_start))
    fisher = crb = None
    if Rm is not None:
        W = np.linalg.cholesky(np.linalg.inv(Rm)).T
        S = (np.kron(np.eye(len(ys)), W)) @ S
        fisher = S.T @ S
    s = np.linalg.svd(S, compute_uv=False)
    rank = int(np.sum(s > rtol * max(float(s[0]), 1e-300)))
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    if fisher is not None:
        try:
            crb = np.sqrt(np.diag(np.linalg.inv(fisher))) if rank == model.nx else \
                np.full(model.nx, np.inf)
        except np.linalg.LinAlgError:
            crb = np.full(model.nx, np.inf)
    return WindowReport(S, s, rank, cond, fisher, crb)
