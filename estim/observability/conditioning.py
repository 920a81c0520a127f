r"""How well the state is observable, point by point: the observability matrix at given
states and its conditioning over a plane of two states.

The rank test of :func:`~estim.observability.analyze` says *whether* nearby states are
distinguishable; the singular values of the observability matrix say *how well*. With
the rows normalised (as the rank test takes them), the ratio of the smallest singular
value to the largest,

.. math::
    c(x) = \frac{\sigma_{\min}(\bar{\mathcal O}_k(x))}{\sigma_{\max}(\bar{\mathcal O}_k(x))}
    \in [0, 1],

is the inverse of the condition number (the rank test's rows and threshold,
:func:`estim.observability.lie.numeric_rank`, with the grid's largest row as the scale
of a zero row): 0 where the rank drops, small where some
direction of the state moves the outputs and their derivatives very little. A map of
:math:`\log_{10} c` over two states shows where an estimator will struggle (for the
pendulum seen through :math:`\sin\theta`: at :math:`\theta = \pm\pi/2`,
:math:`\omega = 0`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._figures import _finish, _pyplot
from estim._validate import _numeric_array, as_int, as_vector
from estim.model import Model
from estim.observability import lie

__all__ = ["Conditioning", "conditioning", "matrix"]


def _function(model: Model, order: int) -> ca.Function:
    rows, variables = lie.rows(model, order, "constant", None)
    return ca.Function("O", variables, [ca.densify(ca.vertcat(*rows))])


def matrix(model: Model, x: ArrayLike, order: int, u: ArrayLike | None = None) -> np.ndarray:
    r"""The observability matrix :math:`\mathcal O_k(x)` at the state(s) ``x``.

    For a continuous model the rows are the gradients of the output and of its first
    ``order`` Lie derivatives along the dynamics,
    :math:`\partial/\partial x\,[h;\ L_f h;\ \dots;\ L_f^k h]`; for a discrete one,
    of :math:`h(F^j(x))`, :math:`j = 0, \dots, k`. The inputs are held at the constant
    ``u`` (default zero), the parameters at the model's.

    Parameters
    ----------
    model : Model
    x : (nx,) or (m, nx) array
        The state, or ``m`` states.
    order : int
        The highest derivative (or sample) :math:`k \ge 0`.
    u : (nu,) array, optional

    Returns
    -------
    (ny (k + 1), nx) array, or (m, ny (k + 1), nx) for ``m`` states
    """
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    order = as_int(order, "order", minimum=0)
    X = _numeric_array(x, "x")
    if X.ndim not in (1, 2) or X.shape[-1] != model.nx:
        raise ValueError(f"x must have shape ({model.nx},) or (m, {model.nx}), got "
                         f"{X.shape}")
    uu = np.zeros(model.nu) if u is None else as_vector(u, model.nu, "u")
    fun = _function(model, order)
    pts = np.atleast_2d(X)
    args = [pts.T] + ([np.tile(uu[:, None], (1, len(pts)))] if fun.n_in() > 1 else [])
    rows = model.ny * (order + 1)
    # the mapped function puts the points' matrices side by side: (rows, m nx)
    out = np.asarray(fun.map(len(pts))(*args).full()).reshape(rows, len(pts), model.nx)
    out = np.transpose(out, (1, 0, 2))
    return out[0] if X.ndim == 1 else out


@dataclass
class Conditioning:
    r"""The conditioning :math:`c` of the observability matrix over a grid of two states
    (see the module).

    Attributes
    ----------
    states : (str, str)
        The two states of the grid.
    grid : (n1,) and (n2,) arrays
        Their values.
    values : (n2, n1) array
        :math:`c` at every point (rows: the second state).
    rank : (n2, n1) int array
        The numeric rank there (singular values above ``rtol`` times the largest).
    order : int
    at : (nx,) array
        The other states' values.
    """

    states: tuple[str, str]
    grid: tuple[np.ndarray, np.ndarray]
    values: np.ndarray
    rank: np.ndarray
    order: int
    at: np.ndarray
    model: str = ""

    def plot(self, path=None, *, floor: float = 1e-6, title: str | None = None):
        """The map of :math:`\\log_{10} c` (clipped at ``floor``), with the points of
        lost rank marked."""
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(7.0, 3.6), constrained_layout=True)
        a, b = self.grid
        shown = np.log10(np.clip(self.values, floor, 1.0))
        im = ax.pcolormesh(a, b, shown, shading="auto", cmap="viridis",
                           vmin=np.log10(floor), vmax=0.0)
        fig.colorbar(im, ax=ax, label=r"$\log_{10}\ \sigma_{min} / \sigma_{max}$")
        full = self.rank.max(initial=0)
        low = self.rank < full
        if low.any():
            B, A = np.nonzero(low)
            ax.plot(a[A], b[B], "x", color="C3", ms=5, label=f"rank < {full}")
            ax.legend(fontsize="small", loc="upper right")
        ax.set_xlabel(self.states[0])
        ax.set_ylabel(self.states[1])
        ax.set_title(title or f"{self.model}: conditioning of the observability matrix "
                              f"(order {self.order})", fontsize="medium")
        return _finish(fig, path)


def conditioning(model: Model, grid: Mapping[str, ArrayLike], order: int, *,
                 at: ArrayLike | None = None, u: ArrayLike | None = None,
                 rtol: float = 1e-9) -> Conditioning:
    """The conditioning of the observability matrix over a grid of two states.

    Parameters
    ----------
    model : Model
    grid : dict of two state names -> 1-D arrays
        The values of the two states (e.g. ``{"theta": np.linspace(-3, 3, 121),
        "omega": np.linspace(-4, 4, 81)}``).
    order : int
        The highest derivative of :func:`matrix`.
    at : (nx,) array, optional
        The other states' values (default zero).
    u : (nu,) array, optional
        The constant inputs (default zero).
    rtol : float
        The rank's threshold, as in :func:`~estim.observability.analyze`.

    Returns
    -------
    Conditioning
        Its ``plot()`` draws the map.
    """
    if not isinstance(grid, Mapping) or len(grid) != 2:
        raise ValueError("grid must be a dict of two state names to arrays of values")
    names = list(grid)
    for name in names:
        if name not in model.state_names:
            raise ValueError(f"grid: {name!r} is not a state of {model.name or 'the model'} "
                             f"(states: {model.state_names})")
    values = [np.asarray(grid[n], dtype=float).ravel() for n in names]
    for name, v in zip(names, values, strict=True):
        if v.size < 2 or not np.isfinite(v).all():
            raise ValueError(f"grid[{name!r}] must hold at least two finite values")
    base = np.zeros(model.nx) if at is None else as_vector(at, model.nx, "at")
    i, j = (model.state_names.index(n) for n in names)
    A, B = np.meshgrid(*values)
    X = np.tile(base, (A.size, 1))
    X[:, i], X[:, j] = A.ravel(), B.ravel()
    obs = matrix(model, X, order, u)
    scale = float(np.linalg.norm(obs, axis=2).max())
    ranks, c = np.zeros(len(obs), dtype=int), np.zeros(len(obs))
    for k, O_k in enumerate(obs):
        ranks[k], s, _, _ = lie.numeric_rank(O_k, rtol, scale)
        c[k] = s[model.nx - 1] / max(float(s[0]), 1e-300)
    return Conditioning(states=(names[0], names[1]), grid=(values[0], values[1]),
                        values=c.reshape(A.shape), rank=ranks.reshape(A.shape),
                        order=order, at=base, model=model.name)
