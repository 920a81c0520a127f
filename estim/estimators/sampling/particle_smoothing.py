r"""Forward-filtering backward-simulation: smoothed trajectories of a particle filter.

After a forward pass that keeps, at every sample :math:`t`, the particles
:math:`x^i_t` and their normalised weights :math:`W^i_t` (after the update, before
resampling), each of ``n_paths`` trajectories is drawn backwards (Godsill, Doucet,
West 2004): :math:`\tilde x_{T-1}` from the last weights, then for
:math:`t = T-2, \dots, 0`

.. math::
    P(\tilde x_t = x^i_t) \propto W^i_t \,
    N\!\left(\tilde x_{t+1};\, F(x^i_t, u_t),\, Q\right),

so that the paths are draws from the particle approximation of the joint
smoothing distribution :math:`p(x_{0:T-1} \mid y_{0:T-1})`. The cost is
:math:`O(T\, N\, n_\text{paths})`; the transition density needs a positive
definite ``Q``.

References
----------
S. J. Godsill, A. Doucet, M. West, "Monte Carlo smoothing for nonlinear time
series", J. Am. Stat. Assoc. 99(465), 2004; N. Chopin, O. Papaspiliopoulos,
*An Introduction to Sequential Monte Carlo*, Springer 2020, ch. 12.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from estim._manifold import NP, Manifold
from estim.solvers.sampling.resampling import resample

__all__ = ["ParticleSmoothResult", "backward_simulation"]

#: at most this many (path, particle) pairs of transition densities at once
_BLOCK = 4_000_000


@dataclass(frozen=True)
class ParticleSmoothResult:
    """A record smoothed by :meth:`ParticleFilter.smooth <estim.ParticleFilter.smooth>`.

    Attributes
    ----------
    paths : (n_paths, T, nx) array
        Trajectories drawn from the particle approximation of
        :math:`p(x_{0:T-1} \\mid y_{0:T-1})`.
    x : (T, nx) array
        Their mean, the smoothed estimate of every state.
    P : (T, nx, nx) array
        Their covariance at every sample.
    """

    paths: np.ndarray
    x: np.ndarray
    P: np.ndarray


def backward_simulation(transit: Callable[..., list[np.ndarray]], LQ_inv: np.ndarray,
                        trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                        rng: np.random.Generator, n_paths: int,
                        manifold: Manifold | None = None) -> ParticleSmoothResult:
    r"""``n_paths`` backward draws (see the module) from ``trace``: per sample the
    particles ``(nx, N)``, their weights ``(N,)`` and the transition's input into that
    sample; ``transit(X, w, n=N)`` gives ``[F(X, w)]`` column by column, ``LQ_inv`` is
    the inverse of the Cholesky factor of ``Q``. On a ``manifold`` the transition
    density is that of the tangent vector :math:`\tilde x_{t+1} \ominus F(x^i_t)`, and
    the smoothed estimates are the paths' Karcher means with their tangent spreads."""
    T = len(trace)
    nx, N = trace[-1][0].shape
    paths = np.empty((n_paths, T, nx))
    X, W, _ = trace[-1]
    paths[:, -1] = X[:, resample(W, "multinomial", rng, n=n_paths)].T
    nd = LQ_inv.shape[0]
    block = max(1, _BLOCK // (N * (1 if manifold is None else nd)))
    with np.errstate(divide="ignore"):
        for t in range(T - 2, -1, -1):
            X, W, _ = trace[t]
            FX = transit(X, trace[t + 1][2], n=N)[0]  # (nx, N) the predictions
            logW = np.log(W)
            if manifold is None:  # whitened predictions
                Z = LQ_inv @ FX
                logW = logW - 0.5 * (Z * Z).sum(axis=0)
            for lo in range(0, n_paths, block):
                succ = paths[lo:lo + block, t + 1]  # (m, nx) the successors
                if manifold is None:  # log W_i - |z_j - Z_i|^2 / 2 up to a constant
                    a = logW[None, :] + (LQ_inv @ succ.T).T @ Z
                else:
                    d = manifold.local(FX.T[None, :, :], succ[:, None, :], NP) @ LQ_inv.T
                    a = logW[None, :] - 0.5 * (d * d).sum(axis=-1)
                a = np.exp(a - a.max(axis=1, keepdims=True))
                c = np.cumsum(a, axis=1)
                u = rng.random(len(c))[:, None] * c[:, -1:]
                pick = np.minimum((c <= u).sum(axis=1), N - 1)
                paths[lo:lo + block, t] = X[:, pick].T
    if manifold is None:
        x = paths.mean(axis=0)
        D = paths - x[None]
    else:
        means = [manifold.mean(paths[:, t]) for t in range(T)]
        x = np.array([m for m, _ in means])
        D = np.stack([d for _, d in means], axis=1)  # (n_paths, T, ndx)
    P = np.einsum("pti,ptj->tij", D, D) / max(n_paths - 1, 1)
    return ParticleSmoothResult(paths=paths, x=x, P=P)
