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
smoothing distribution :math:`p(x_{0:T-1} \mid y_{0:T-1})`. Drawn directly, this costs
:math:`O(T\, N\, n_\text{paths})`. With a definite ``Q`` on vector states each draw is
made by rejection first (Douc, Garivier, Moulines & Olsson 2011): a candidate
:math:`i` drawn from the weights :math:`W_t` alone is accepted with probability
:math:`\exp(-\tfrac12 \|L_Q^{-1}(\tilde x_{t+1} - F(x^i_t))\|^2) \le 1` (the
transition density over its maximum), which gives exactly the distribution above; the
paths not accepted after :data:`REJECTION_ROUNDS` rounds (an informative transition
against a wide cloud) are drawn directly. The expected cost per path and sample is then
a few candidates instead of :math:`N`.

A singular ``Q`` (process noise on some states only, or along some directions) makes
the transition density degenerate: with :math:`Q = V_r \Lambda_r V_r^\top`
(:math:`\Lambda_r > 0`) and :math:`N_0` an orthonormal basis of its null space,
:math:`x_{t+1} = F(x_t) + w` with :math:`N_0^\top w = 0`, so

.. math::
    p(x_{t+1} \mid x_t) = \delta\!\left(N_0^\top (x_{t+1} - F(x_t))\right)
    N\!\left(V_r^\top (x_{t+1} - F(x_t));\, 0,\, \Lambda_r\right),

a density on the noise-driven coordinates times a point mass on the others. The
backward draw is then exact on it: only the particles whose prediction agrees with
the successor in the noise-free coordinates (to rounding, :math:`10^{-9}` of the
values' scale) are candidates, weighted by the density of the noise-driven ones.
With ``Q = 0`` in some coordinates the candidates are the successor's ancestor and
its copies, and the smoothed paths follow the filter's genealogy there, as the exact
particle approximation does.

References
----------
S. J. Godsill, A. Doucet, M. West, "Monte Carlo smoothing for nonlinear time
series", J. Am. Stat. Assoc. 99(465), 2004; R. Douc, A. Garivier, E. Moulines,
J. Olsson, "Sequential Monte Carlo smoothing for general state space hidden Markov
models", Ann. Appl. Probab. 21(6), 2011; N. Chopin, O. Papaspiliopoulos,
*An Introduction to Sequential Monte Carlo*, Springer 2020, ch. 12.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from estim._manifold import NP, Manifold
from estim._progress import bar as progress_bar
from estim.estimators.filtering import Estimates
from estim.solvers.sampling.resampling import resample

__all__ = ["ParticleSmoothResult", "backward_simulation"]

#: at most this many (path, particle) pairs of transition densities at once
_BLOCK = 4_000_000
#: Rounds of candidates per sample before the paths still pending are drawn directly.
REJECTION_ROUNDS = 16


@dataclass(frozen=True, repr=False)
class ParticleSmoothResult(Estimates):
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
    x_filtered, P_filtered : arrays
        The particle filter's weighted means and covariances (its forward pass).
    filtered : ParticleFilterResult or None
        The forward pass's whole result (its log-likelihood estimate, ESS, statuses).
    t, state_names, manifold :
        Sample times, state names and the states' manifold (see
        :class:`~estim.estimators.filtering.Estimates`).
    """

    paths: np.ndarray
    x: np.ndarray
    P: np.ndarray
    x_filtered: np.ndarray | None = None
    P_filtered: np.ndarray | None = None
    filtered: Any = None


class Transition:
    r"""The factors of a transition density :math:`N(0, Q)`, ``Q`` ``(nd, nd)`` positive
    semi-definite: ``whiten`` ``(r, nd)`` maps a difference to standard normal
    coordinates of the noise-driven subspace (the inverse Cholesky factor when ``Q`` is
    definite, :math:`\Lambda_r^{-1/2} V_r^\top` otherwise) and ``null`` ``(nd - r, nd)``
    is an orthonormal basis of the noise-free directions (None when ``Q`` is definite).
    """

    def __init__(self, Q: np.ndarray) -> None:
        Q = np.asarray(Q, dtype=float)
        try:
            self.whiten = np.linalg.inv(np.linalg.cholesky(Q))
            self.null: np.ndarray | None = None
            return
        except np.linalg.LinAlgError:
            pass
        lam, V = np.linalg.eigh(0.5 * (Q + Q.T))
        keep = lam > 1e-12 * max(float(lam[-1]), 0.0)
        self.whiten = (V[:, keep] / np.sqrt(lam[keep])).T
        self.null = V[:, ~keep].T
        self.scale = float(np.sqrt(max(float(lam[-1]), 0.0)))


def backward_simulation(transit: Callable[..., list[np.ndarray]], Q: np.ndarray,
                        trace: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                        rng: np.random.Generator, n_paths: int,
                        manifold: Manifold | None = None,
                        filtered: Estimates | None = None) -> ParticleSmoothResult:
    r"""``n_paths`` backward draws (see the module) from ``trace``: per sample the
    particles ``(nx, N)``, their weights ``(N,)`` and the transition's input into that
    sample; ``transit(X, w, n=N)`` gives ``[F(X, w)]`` column by column, ``Q`` is the
    process noise's covariance (singular: see the module). On a ``manifold`` the transition
    density is that of the tangent vector :math:`\tilde x_{t+1} \ominus F(x^i_t)`, and
    the smoothed estimates are the paths' Karcher means with their tangent spreads. The
    result keeps the ``filtered`` estimates (the forward pass), their times and names."""
    T = len(trace)
    nx, N = trace[-1][0].shape
    paths = np.empty((n_paths, T, nx))
    X, W, _ = trace[-1]
    paths[:, -1] = X[:, resample(W, "multinomial", rng, n=n_paths)].T
    density = Transition(Q)
    LQ_inv = density.whiten
    nd = LQ_inv.shape[1]
    exact = density.null is None and manifold is None  # whitened predictions, no deltas
    block = max(1, _BLOCK // (N * (1 if exact else nd)))
    with np.errstate(divide="ignore"), progress_bar(
            T - 1, f"particle smoother, {n_paths} paths", "sample") as bar:
        for t in range(T - 2, -1, -1):
            bar.update(1)
            X, W, _ = trace[t]
            FX = transit(X, trace[t + 1][2], n=N)[0]  # (nx, N) the predictions
            logW = np.log(W)
            pending = np.arange(n_paths)
            if exact:  # whitened predictions; most paths drawn by rejection
                Z = LQ_inv @ FX
                pending = _rejection(paths, t, X, W, Z, LQ_inv, rng)
                logW = logW - 0.5 * (Z * Z).sum(axis=0)
            for lo in range(0, len(pending), block):
                rows = pending[lo:lo + block]
                succ = paths[rows, t + 1]  # (m, nx) the successors
                if exact:  # log W_i - |z_j - Z_i|^2 / 2 up to a constant
                    a = logW[None, :] + (LQ_inv @ succ.T).T @ Z
                else:
                    a = _log_density(density, FX, succ, logW, manifold)
                a = np.exp(a - a.max(axis=1, keepdims=True))
                c = np.cumsum(a, axis=1)
                u = rng.random(len(c))[:, None] * c[:, -1:]
                pick = np.minimum((c <= u).sum(axis=1), N - 1)
                paths[rows, t] = X[:, pick].T
    if manifold is None:
        x = paths.mean(axis=0)
        D = paths - x[None]
    else:
        means = [manifold.mean(paths[:, t]) for t in range(T)]
        x = np.array([m for m, _ in means])
        D = np.stack([d for _, d in means], axis=1)  # (n_paths, T, ndx)
    P = np.einsum("pti,ptj->tij", D, D) / max(n_paths - 1, 1)
    if filtered is None:
        return ParticleSmoothResult(paths=paths, x=x, P=P)
    return ParticleSmoothResult(paths=paths, x=x, P=P, x_filtered=filtered.x,
                                P_filtered=getattr(filtered, "P", None), filtered=filtered,
                                t=filtered.t, state_names=filtered.state_names,
                                manifold=filtered.manifold)


def _rejection(paths: np.ndarray, t: int, X: np.ndarray, W: np.ndarray, Z: np.ndarray,
               LQ_inv: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Draw ``paths[:, t]`` by rejection (see the module): candidates from the weights
    ``W``, accepted with the transition density of the successor over its maximum, in
    at most :data:`REJECTION_ROUNDS` vectorised rounds; returns the paths still pending."""
    cumulative = np.cumsum(W)
    cumulative /= cumulative[-1]
    pending = np.arange(len(paths))
    target = paths[:, t + 1] @ LQ_inv.T  # (n_paths, r) the successors, whitened
    for _ in range(REJECTION_ROUNDS):
        cand = np.minimum(np.searchsorted(cumulative, rng.random(len(pending)), "right"),
                          len(W) - 1)
        d = target[pending] - Z[:, cand].T
        accept = rng.random(len(pending)) < np.exp(-0.5 * (d * d).sum(axis=1))
        paths[pending[accept], t] = X[:, cand[accept]].T
        pending = pending[~accept]
        if not pending.size:
            break
    return pending


def _log_density(density: Transition, FX: np.ndarray, succ: np.ndarray, logW: np.ndarray,
                 manifold: Manifold | None) -> np.ndarray:
    """``log W_i + log p(succ_j | x_i)`` up to a constant per successor, ``(m, N)``, from
    the predictions ``FX (nx, N)``: on the manifold's tangent space where there is one,
    and with the point mass of a singular ``Q`` (candidates only where the noise-free
    coordinates agree; where rounding left none, the nearest in them)."""
    if manifold is None:
        d = succ[:, None, :] - FX.T[None, :, :]
    else:
        d = manifold.local(FX.T[None, :, :], succ[:, None, :], NP)
    z = d @ density.whiten.T
    a = logW[None, :] - 0.5 * (z * z).sum(axis=-1)
    if density.null is not None and len(density.null):
        off = np.abs(d @ density.null.T).max(axis=-1)  # (m, N) distance from the delta
        scale = np.abs(succ).max(axis=1, keepdims=True) + density.scale + 1e-300
        a = np.where(off <= 1e-9 * scale, a, -np.inf)
        lost = ~np.isfinite(a).any(axis=1)
        if lost.any():
            nearest = off[lost].argmin(axis=1)
            a[lost] = -np.inf
            a[lost, nearest] = 0.0
    return a
