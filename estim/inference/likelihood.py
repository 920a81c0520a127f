r"""The likelihood of a parameter vector, as the samplers of :mod:`estim.inference` call it.

A parameter vector :math:`\theta` (named by the priors) sets the model's parameters of a
:class:`~estim.ParticleFilter` (:meth:`~estim.ParticleFilter.set_params`: data of the
compiled steps, nothing rebuilt) and, through the user's ``tuning(theta) -> {"Q": ...,
"R": ..., "x0": ..., "P0": ...}``, its noise covariances and prior; the filter's estimate
:math:`\hat p(y_{0:T-1} \mid \theta)` (unbiased, Andrieu, Doucet & Holenstein 2010) is
then one call of its kernel for the whole record (:class:`ParticleLikelihood`).

With ``correlation`` :math:`\rho > 0` (the correlated pseudo-marginal method of
Deligiannidis, Doucet & Pitt 2018) the estimate is a deterministic function of auxiliary
standard normals :math:`z` (the particles' draws, one per step for the resampling's
uniform :math:`\Phi(z)`), and the chain proposes :math:`z' = \rho z + \sqrt{1-\rho^2}\,
\varepsilon` together with :math:`\theta'`: the two estimates' errors are then correlated
and their ratio varies far less, so that far fewer particles suffice. For the errors to
stay correlated through the resampling, the particles are sorted along a Hilbert curve
(:func:`hilbert_order`; in one dimension, by value) and resampled systematically at every
step. That path runs the filter's vectorised Functions in numpy (the kernel draws its
own random numbers).

An estimate without weight left (every particle's density zero) or a ``tuning`` that fails
at :math:`\theta` (a covariance that is not positive definite) is a likelihood of zero:
the point is rejected, and counted (:attr:`ParticleLikelihood.failures`).

References
----------
C. Andrieu, A. Doucet, R. Holenstein, "Particle Markov chain Monte Carlo methods",
J. R. Stat. Soc. B 72(3), 2010; G. Deligiannidis, A. Doucet, M. K. Pitt, "The correlated
pseudo-marginal method", J. R. Stat. Soc. B 80(5), 2018; J. Skilling, "Programming the
Hilbert curve", AIP Conf. Proc. 707, 2004; M. Gerber, N. Chopin, "Sequential quasi Monte
Carlo", J. R. Stat. Soc. B 77(3), 2015.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from estim.estimators.sampling.ensembles import square_root
from estim.estimators.sampling.particle import ParticleFilter, _update
from estim.estimators.sampling.particle_graphs import prior_tuning

__all__ = ["ParticleLikelihood", "hilbert_order", "run_log_likelihood"]

#: the keys a ``tuning(theta)`` may give
TUNING_KEYS = ("Q", "R", "x0", "P0")


def _hilbert_keys(Q: np.ndarray, bits: int) -> np.ndarray:
    """The index along the Hilbert curve of the integer points ``Q (d, N)`` (``bits`` bits
    per coordinate): Skilling's transform to the curve's transposed index, then its bits
    interleaved."""
    X = Q.astype(np.uint64)
    d = X.shape[0]
    one = np.uint64(1)
    q = one << np.uint64(bits - 1)
    while q > one:  # undo the excess work
        P = q - one
        for i in range(d):
            hit = (X[i] & q) != 0
            X[0] = np.where(hit, X[0] ^ P, X[0])
            t = np.where(hit, np.uint64(0), (X[0] ^ X[i]) & P)
            X[0] ^= t
            X[i] ^= t
        q >>= one
    for i in range(1, d):  # Gray encoding
        X[i] ^= X[i - 1]
    t = np.zeros(X.shape[1], dtype=np.uint64)
    q = one << np.uint64(bits - 1)
    while q > one:
        t = np.where((X[d - 1] & q) != 0, t ^ (q - one), t)
        q >>= one
    X ^= t
    key = np.zeros(X.shape[1], dtype=np.uint64)
    for b in range(bits - 1, -1, -1):
        for i in range(d):
            key = (key << one) | ((X[i] >> np.uint64(b)) & one)
    return key


def hilbert_order(X: np.ndarray) -> np.ndarray:
    r"""The order of the particles ``X (d, N)`` along a Hilbert curve (by value for
    :math:`d = 1`): each coordinate standardised and mapped to :math:`(0, 1)` by the
    normal distribution function (Gerber & Chopin 2015), cut into :math:`2^b` cells
    (:math:`b = \lfloor 63 / d \rfloor`, at most 20), ordered by the cells' index along
    the curve (Skilling 2004), which keeps particles that are close in the state space
    close in the order."""
    d, N = X.shape
    if d == 1:
        return np.argsort(X[0], kind="stable")
    sd = X.std(axis=1)
    Z = (X - X.mean(axis=1)[:, None]) / np.where(sd > 0, sd, 1.0)[:, None]
    bits = min(20, 63 // d)
    cells = np.minimum(special.ndtr(Z) * 2.0 ** bits, 2.0 ** bits - 1).astype(np.uint64)
    return np.argsort(_hilbert_keys(cells, bits), kind="stable")


def _quick_tuning(pf: ParticleFilter, values: Mapping) -> dict[str, np.ndarray]:
    """The tuning ``values`` as :meth:`~estim.Estimator.set_tuning` takes them (a scalar,
    variances or a matrix), checked only for what the filter needs: finite, and ``R``,
    ``P0`` (and ``Q`` for a linearised proposal) with a Cholesky factor, ``Q``
    positive semi-definite. A ``ValueError`` or ``LinAlgError`` otherwise."""
    m = pf.model
    out: dict[str, np.ndarray] = {}
    for key, value in values.items():
        arr = np.asarray(value, dtype=float)
        if not np.isfinite(arr).all():
            raise ValueError(f"{key} must be finite")
        if key == "x0":
            out[key] = arr.reshape(m.nx)
            continue
        n = m.ny if key == "R" else m.ndx
        mat = arr * np.eye(n) if arr.ndim == 0 else np.diag(arr) if arr.ndim == 1 else \
            arr.reshape(n, n)
        mat = 0.5 * (mat + mat.T)
        if key != "Q" or pf.proposal != "bootstrap":
            np.linalg.cholesky(mat)
        elif np.linalg.eigvalsh(mat)[0] < -1e-12 * max(1.0, float(np.abs(mat).max())):
            raise ValueError("Q must be positive semi-definite")
        out[key] = mat
    return out


def run_log_likelihood(pf: ParticleFilter, rows: dict, start: int, stop: int,
                       prior: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> tuple[float, Any]:
    """The compiled filter over the kernel rows ``start:stop`` (from the prior, its
    ``(x0, tun0)`` given or the filter's, when ``start`` is 0; else from the kernel's
    particles): the log-likelihood of those samples (``-inf`` where no weight is left or
    it is not finite) and the kernel record."""
    rec = pf._kernel_run(rows, start, start == 0, stop, prior)
    if rec.done < stop - start:
        return -np.inf, rec
    value = float(rec.inc.sum()) + (float(rows["const"][start:stop].sum())
                                    if pf.loglik is None else 0.0)
    return (value if np.isfinite(value) else -np.inf), rec


class ParticleLikelihood:
    r"""The particle filter's estimate :math:`\log \hat p(y \mid \theta)` of a record, as a
    function of the named parameters (see the module).

    Parameters
    ----------
    pf : ParticleFilter
        The filter (its particles, proposal, resampling; its compiled kernel with
        ``jit=True``).
    Y, U, t :
        The record, as for :meth:`ParticleFilter.filter <estim.ParticleFilter.filter>`.
    names : sequence of str
        The parameters, in the order of :math:`\theta`: the model's parameters
        (``model.param_names``) and any others that ``tuning`` reads.
    tuning : callable, optional
        ``tuning(theta: dict) -> dict`` with some of ``"Q"``, ``"R"``, ``"x0"``, ``"P0"``
        (the noise and prior as functions of the parameters).

    Attributes
    ----------
    failures : dict
        How many points had no likelihood, by cause (``"tuning"``: with its first
        message under ``"tuning_error"``; ``"no weight"``).
    """

    def __init__(self, pf: ParticleFilter, Y: ArrayLike, U: ArrayLike | None = None, *,
                 names: Sequence[str], tuning: Callable[[dict], Mapping] | None = None,
                 t: ArrayLike | None = None):
        if not isinstance(pf, ParticleFilter):
            raise TypeError(f"pf must be an estim.ParticleFilter, got {type(pf).__name__}")
        if tuning is not None and not callable(tuning):
            raise TypeError(f"tuning must be a function theta -> dict of Q, R, x0, P0 or "
                            f"None, got {type(tuning).__name__}")
        m = pf.model
        self.pf, self.names, self.tuning, self.t = pf, list(names), tuning, t
        unknown = [n for n in self.names if n not in m.param_names]
        if unknown and tuning is None:
            raise ValueError(f"priors: {unknown} are not parameters of the model "
                             f"({m.param_names}); give tuning=lambda theta: {{'Q': ..., "
                             f"'R': ...}} for parameters of the noise or the prior")
        self._index = [(i, m.param_names.index(n)) for i, n in enumerate(self.names)
                       if n in m.param_names]
        self.Y, self.W = pf._record_inputs(Y, U)
        self.U = U
        self._p0 = pf._p.copy()
        self._base = {k: None if v is None else np.array(v, dtype=float) for k, v in
                      (("Q", pf.Q), ("R", pf.R), ("x0", pf.x0), ("P0", pf.P0))}
        self.failures: dict[str, Any] = {"tuning": 0, "no weight": 0}
        self._applied: np.ndarray | None = None  # (the point the filter is set to)
        self._checked = False

    def restore(self) -> None:
        """Give the filter back its own parameters and tuning (a sampler leaves the
        user's filter as it found it)."""
        pf = self.pf
        pf._p = self._p0.copy()
        pf.__dict__.update({k: v for k, v in self._base.items() if v is not None})
        pf._tuning_changed()
        self._applied = None

    @property
    def T(self) -> int:
        return self.Y.shape[0]

    def dict(self, theta: ArrayLike) -> dict[str, float]:
        """``theta`` as ``{name: value}``."""
        return dict(zip(self.names, np.asarray(theta, float).tolist(), strict=True))

    def apply(self, theta: ArrayLike) -> bool:
        """Set the filter to ``theta`` (its parameters and tuning); False when ``tuning``
        refused it (counted)."""
        pf, theta = self.pf, np.asarray(theta, float)
        if self._applied is not None and np.array_equal(self._applied, theta):
            return True  # (the filter is at theta already)
        self._applied = None
        p = self._p0.copy()
        for i, j in self._index:
            p[j] = theta[i]
        pf._p = p
        self.W[:, pf.model.nw:] = p
        if self.tuning is None:
            self._applied = theta.copy()
            return True
        try:
            new = dict(self.tuning(self.dict(theta)))
            bad = [k for k in new if k not in TUNING_KEYS]
            if bad:
                raise ValueError(f"tuning returned {bad}; it may give {TUNING_KEYS}")
            values = {**self._base, **new}
            if self._checked:  # (the first point checked by name, the next ones quickly)
                pf.__dict__.update(_quick_tuning(pf, values))
            else:
                pf.__dict__.update(pf._validated_tuning(**values))
                self._checked = True
            pf._tuning_changed()
        except (ValueError, np.linalg.LinAlgError) as exc:
            if "tuning returned" in str(exc):
                raise
            self.failures["tuning"] += 1
            self.failures.setdefault("tuning_error", f"{type(exc).__name__}: {exc}")
            return False
        self._applied = theta.copy()
        return True

    def __call__(self, theta: ArrayLike, seed: int) -> float:
        """:math:`\\log \\hat p(y \\mid \\theta)` with the random numbers of ``seed``
        (``-inf`` where there is none, counted)."""
        if not self.apply(theta):
            return -np.inf
        pf = self.pf
        if pf._kernel is None:
            res = pf.filter(self.Y, self.U, seed=seed)
            if not res.success or not np.isfinite(res.log_likelihood):
                self.failures["no weight"] += 1
                return -np.inf
            return res.log_likelihood
        pf._kernel.seed(seed)
        rows = pf._kernel_rows(self.Y, self.W)
        value = run_log_likelihood(pf, rows, 0, self.T)[0]
        if value == -np.inf:
            self.failures["no weight"] += 1
        return value

    # ------------------------------------------------- correlated pseudo-marginal
    def auxiliary_size(self) -> tuple[int, int, int]:
        """The shape ``(T, ndx + 1, N)`` of the auxiliary normals of :meth:`correlated`:
        per step the particles' draws and, in the last row's first column, the
        resampling's normal."""
        pf = self.pf
        return self.T, pf.model.ndx + 1, pf.n_particles

    def correlated(self, theta: ArrayLike, z: np.ndarray) -> float:
        r""":math:`\log \hat p(y \mid \theta)` as a deterministic function of the
        auxiliary normals ``z`` (:meth:`auxiliary_size`): the particles drawn with
        ``z[k, :ndx]``, sorted along the Hilbert curve and resampled systematically at
        every step with the uniform :math:`\Phi(z_{k, ndx, 0})`."""
        if not self.apply(theta):
            return -np.inf
        pf, m = self.pf, self.pf.model
        if not m.manifold.euclidean_states:
            raise ValueError("correlation > 0 needs a model without quaternion or angle "
                             "states")
        N, total, X = pf.n_particles, 0.0, None
        nd, P0 = m.ndx, pf.P0
        assert P0 is not None  # (the particle filter requires it)
        support = pf._support
        for k in range(self.T):
            y = self.Y[k]
            observed = ~np.isnan(y)
            WR, const, Ro, tun, miss = pf._measured(observed)
            y0 = np.where(observed, y, 0.0)
            V, w = z[k, :nd], self.W[k]
            if X is None and pf._start is not None:
                X, _, ell = pf._start(pf.x0, V, w, prior_tuning(P0, tun), y0, WR, miss,
                                      n=N)
            elif X is None:
                X = pf.x0[:, None] + square_root(P0) @ V
                _, ell = pf._weigh(X, w, y0, WR, miss, n=N)
            else:
                X, _, ell = pf._advance(X, V, w, tun, y0, WR, miss, n=N)
            Wn, inc, X = _update(X, ell[0], observed, pf._constant(const), None, support)
            if Wn is None or not np.isfinite(inc):
                self.failures["no weight"] += 1
                return -np.inf
            total += inc
            if k + 1 < self.T:  # sorted systematic resampling
                order = hilbert_order(X)
                c = np.cumsum(Wn[order])
                c[-1] = 1.0
                u = (np.arange(N) + special.ndtr(z[k, nd, 0])) / N
                X = X[:, order[np.searchsorted(c, u, side="right").clip(0, N - 1)]]
        return total
