r"""The particle filter's compiled path (``ParticleFilter(..., jit=True)``).

The steps run in :class:`estim.solvers.sampling.particle_kernel.ParticleKernel`: a whole
record (:meth:`~estim.ParticleFilter.filter`) in one call of compiled code, a step
(:meth:`~estim.ParticleFilter.step`) in one call each. What is judged in Python is
the same as on the interpreted path: the innovation and its NIS against the
particles' predicted output covariance plus ``R`` (from the moments the kernel
returns), the status (a collapse of the weights, the chi-square tail), the last
trusted estimate. A step that leaves no weight is handed back and re-anchored by
the interpreted step's rule; the kernel goes on from the new particles.

The random numbers are the kernel's, not numpy's: a seed gives the same run bit for
bit on the compiled path, and another run than on the interpreted one (the same
distribution).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np

from estim.consistency import chi2_limit, consistency_status
from estim.estimators.base import Estimator, StepInfo
from estim.estimators.sampling.ensembles import prepared_record, square_root
from estim.estimators.sampling.particle_graphs import Graphs, prior_tuning
from estim.exceptions import CompilerUnavailable, EstimationWarning
from estim.solvers.sampling.particle_kernel import KernelRecord, ParticleKernel

__all__ = ["CompiledParticles", "innovations", "measured_patterns", "step_status"]

#: an effective sample size below this fraction of the particles (and below 2) is a
#: collapse of the weights, reported as ``"suspect: ..."``
COLLAPSE = 0.01
#: fewer distinct particles than this fraction of them is a collapse of the cloud (copies
#: of a few ancestors that a transition without noise never spreads), ``"suspect: ..."``
DISTINCT = 0.1


def step_status(ess: float, nis: float, dof: int, N: int, distinct: int | None = None
                ) -> str:
    """A particle filter step's status: a collapse of the weights (an effective sample
    size ``ess`` below 1 % of the ``N`` particles and below 2) or of the cloud (fewer
    than 10 % ``distinct`` particles, whatever their weights), else the measurement
    against the particles' prediction (its ``nis`` beyond the chi-square tail)."""
    if ess < max(2.0, COLLAPSE * N):
        return f"suspect: effective sample size {ess:.1f} of {N}"
    if distinct is not None and distinct < DISTINCT * N:
        return (f"suspect: only {distinct} distinct particles of {N}, the cloud collapsed "
                f"(copies of a few ancestors that no process noise spreads)")
    return consistency_status(nis, dof) if nis == nis else "ok"


def measured_patterns(observed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``observed (T, ny)`` and the index of each row among them."""
    if observed.all():  # (the usual record: one pattern)
        return observed[:1], np.zeros(len(observed), dtype=np.intp)
    patterns, which = np.unique(observed, axis=0, return_inverse=True)
    return patterns, which.ravel()


def innovations(Y: np.ndarray, observed: np.ndarray, yb: np.ndarray, Syy: np.ndarray,
                R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Y (T, ny)`` less the particles' mean predicted outputs ``yb (T, ny)`` on the
    measured rows (0 elsewhere), and their NIS against the predicted output covariances
    ``Syy (T, ny, ny)`` plus the measured rows' block of ``R`` (NaN without a measured
    output or a finite prediction), one batched solve per pattern of measured outputs."""
    E, nis = np.zeros_like(Y), np.full(len(Y), np.nan)
    patterns, which = measured_patterns(observed)
    for p, obs in enumerate(patterns):
        rows = np.flatnonzero(which == p)
        if not obs.any():
            continue
        eo = Y[np.ix_(rows, obs)] - yb[np.ix_(rows, obs)]
        good = np.isfinite(eo).all(axis=1)
        rows, eo = rows[good], eo[good]
        S = Syy[rows][:, obs][:, :, obs] + R[np.ix_(obs, obs)]
        E[np.ix_(rows, obs)] = eo
        if S.shape[1] == 1:  # one measured output: a division
            with np.errstate(divide="ignore", invalid="ignore"):
                nis[rows] = np.where(S[:, 0, 0] > 0, eo[:, 0] ** 2 / S[:, 0, 0], np.nan)
            continue
        try:
            nis[rows] = np.einsum("ti,ti->t", eo, np.linalg.solve(S, eo[:, :, None])[:, :, 0])
        except np.linalg.LinAlgError:  # (a singular one among them: one by one)
            for r, e_r, S_r in zip(rows, eo, S, strict=True):
                try:
                    nis[r] = float(e_r @ np.linalg.solve(S_r, e_r))
                except np.linalg.LinAlgError:
                    pass
    return E, nis


class CompiledParticles(Estimator):
    """What :class:`~estim.ParticleFilter` adds for ``jit=True``: it reads the filter's
    tuning, measured-output patterns and re-anchoring step."""

    _kernel: ParticleKernel | None = None
    # (given by ParticleFilter)
    lower: np.ndarray
    upper: np.ndarray
    n_particles: int
    resampling: str
    ess_threshold: float
    proposal: str
    loglik: Any
    _trace: list | None
    _X: np.ndarray | None
    _W: np.ndarray | None
    _trusted: tuple[np.ndarray, np.ndarray | None]
    _p: np.ndarray

    def _measured(self, observed: np.ndarray
                  ) -> tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _anchor_step(self, y: np.ndarray, w: np.ndarray, observed: np.ndarray
                     ) -> tuple[np.ndarray, StepInfo]:
        raise NotImplementedError

    def _compile(self, graphs: Graphs) -> None:
        """Build the kernel (the support: the filter's ``lower``, ``upper``), or stay
        interpreted with one warning saying why."""
        self._kernel = None
        if not self.model.manifold.trivial:
            why = ("the model has quaternion or angle states or outputs, whose means the "
                   "compiled path does not take")
        else:
            try:
                self._kernel = ParticleKernel(graphs.first, graphs.advance,
                                              n=self.n_particles, lower=self.lower,
                                              upper=self.upper)
                return
            except CompilerUnavailable as exc:
                why = str(exc)
        warnings.warn(f"ParticleFilter(jit=True) stays interpreted: {why}",
                      EstimationWarning, stacklevel=4)

    def _kernel_state(self) -> tuple[np.ndarray, ...] | None:
        """The compiled path's particles, weights and random streams (for pickling)."""
        k = self._kernel
        if k is None:
            return None
        return k.X.copy(), k.lw.copy(), k.W.copy(), k._equal.copy(), k.rng.copy()

    def _kernel_restore(self, state: tuple[np.ndarray, ...] | None) -> None:
        k = self._kernel
        if k is None or state is None:
            return
        for buffer, value in zip((k.X, k.lw, k.W, k._equal, k.rng), state, strict=True):
            buffer[...] = value
        if self._X is not None:
            self._published()

    def _kernel_reset(self, seed: int) -> None:
        if self._kernel is not None:
            self._kernel.seed(seed)

    def _constant(self, const: float) -> float:
        """The Gaussian log-density's constant, added to the log-likelihood's terms (a
        user's log-density is the whole density)."""
        return const if self.loglik is None else 0.0

    def _first_tuning(self, tun: np.ndarray) -> np.ndarray:
        """The first step's tuning: ``L_0``, or the linearised proposal's with ``P0``."""
        assert self.P0 is not None  # (the particle filter requires it)
        if self.proposal == "bootstrap":
            return square_root(self.P0).ravel(order="F")
        return prior_tuning(self.P0, tun)

    def _kernel_rows(self, Y: np.ndarray, W: np.ndarray) -> dict[str, np.ndarray]:
        """The kernel's step data for the measurements ``Y (T, ny)`` and transition
        inputs ``W (T, nw)``, with each step's measured pattern."""
        observed = ~np.isnan(Y)
        rows: dict[str, Any] = {"observed": observed, "w": W}
        patterns, which = measured_patterns(observed)
        parts = [self._measured(obs) for obs in patterns]  # (kept by pattern)
        for key, i in (("WR", 0), ("const", 1), ("tun", 3), ("miss", 4)):
            rows[key] = np.array([np.ravel(part[i]) for part in parts])[which]
        rows["const"] = rows["const"][:, 0]
        rows["y0"] = np.where(observed, Y, 0.0)
        rows["measured"] = observed.any(axis=1).astype(np.int64)
        return rows

    def _kernel_run(self, rows: dict[str, Any], start: int, first: bool,
                    stop: int | None = None,
                    prior: tuple[np.ndarray, np.ndarray] | None = None) -> KernelRecord:
        """The kernel over the steps ``start:stop`` (default: to the end; the particles and
        weights of each onto the smoother's trace when it is kept); ``prior``: the first
        step's ``(x0, tun0)`` instead of the filter's own (a parameter particle's)."""
        k = self._kernel
        assert k is not None
        stop = len(rows["measured"]) if stop is None else stop
        sl = slice(start, stop)
        T, N = stop - start, self.n_particles
        trace = (np.empty((T, self.model.nx, N)), np.empty((T, N))) \
            if self._trace is not None else None
        x0, tun0 = prior if prior is not None else \
            (self.x0, self._first_tuning(rows["tun"][start]) if first else k._zero)
        rec = k.run(first=first, x0=x0, tun0=tun0 if first else k._zero,
                    w=rows["w"][sl], tun=rows["tun"][sl], y0=rows["y0"][sl],
                    WR=rows["WR"][sl], miss=rows["miss"][sl], measured=rows["measured"][sl],
                    scheme=self.resampling, threshold=self.ess_threshold, trace=trace)
        if trace is not None and self._trace is not None:
            self._trace.extend((trace[0][j], trace[1][j], rows["w"][start + j])
                               for j in range(rec.done))
        return rec

    def _judged(self, Y: np.ndarray, rows: dict[str, Any], start: int, rec: KernelRecord
                ) -> tuple[list[str], np.ndarray, StepInfo]:
        """The steps of a kernel run from sample ``start`` as the interpreted step reports
        them: their statuses, log-likelihood terms and the last one's
        :class:`~estim.StepInfo` (the last trusted estimate kept)."""
        N, done = self.n_particles, rec.done
        sl = slice(start, start + done)
        observed = rows["observed"][sl]
        E, nis = innovations(Y[sl], observed, rec.yb[:done], rec.Syy[:done], self.R)
        inc = rec.inc[:done] + self._constant(rows["const"][sl])
        dof = observed.sum(axis=1)
        limit = np.array([chi2_limit(int(d)) for d in dof]) if len(set(dof)) > 1 else \
            np.full(done, chi2_limit(int(dof[0])))
        collapsed = (rec.ess[:done] < max(2.0, COLLAPSE * N)) | \
            (rec.distinct[:done] < DISTINCT * N)
        beyond = ~collapsed & (nis > limit)  # (NaN: not beyond)
        status = ["ok"] * done
        for j in np.flatnonzero(collapsed | beyond):
            status[j] = step_status(float(rec.ess[j]), float(nis[j]), int(dof[j]), N,
                                    int(rec.distinct[j]))
        ok = np.flatnonzero(~(collapsed | beyond))
        if ok.size:
            self._trusted = (rec.x[ok[-1]], rec.P[ok[-1]])
        last = done - 1
        info = StepInfo._fast(status=status[last], success=True, P=rec.P[last],
                              innovation=E[last], nis=float(nis[last]))
        info.extra.update(ess=float(rec.ess[last]), log_likelihood=float(inc[last]),
                          resampled=bool(rec.resampled[last]))
        return status, inc, info

    def _published(self) -> None:
        """The kernel's particles as the filter's (:attr:`particles`)."""
        k = self._kernel
        assert k is not None
        self._X, self._W = k.X, None if k.equal else k.W

    def _compiled_step(self, y: np.ndarray, w: np.ndarray, first: bool
                       ) -> tuple[np.ndarray, StepInfo]:
        observed = ~np.isnan(y)
        WR, const, Ro, tun, miss = self._measured(observed)
        k = self._kernel
        assert k is not None
        first = first or self._X is None
        rec = k.step(first=first, x0=self.x0, tun0=self._first_tuning(tun) if first else k._zero,
                     w=w, tun=tun, y0=np.where(observed, y, 0.0), WR=WR, miss=miss,
                     measured=bool(observed.any()), scheme=self.resampling,
                     threshold=self.ess_threshold)
        if rec.done == 0:
            return self._reanchored(y, w, observed)
        self._published()
        # the step's status, as _judged gives it for a record
        e = np.zeros_like(y)
        nis = float("nan")
        if observed.any():
            e[observed] = y[observed] - rec.yb[0, observed]
            S = rec.Syy[0][np.ix_(observed, observed)] + Ro
            if np.isfinite(e).all() and np.isfinite(S).all():
                try:
                    nis = float(e[observed] @ np.linalg.solve(S, e[observed]))
                except np.linalg.LinAlgError:
                    pass
        ess = float(rec.ess[0])
        status = step_status(ess, nis, int(observed.sum()), self.n_particles,
                             int(rec.distinct[0]))
        if status == "ok":
            self._trusted = (rec.x[0], rec.P[0])
        info = StepInfo._fast(status=status, success=True, P=rec.P[0], innovation=e, nis=nis)
        info.extra.update(ess=ess, log_likelihood=float(rec.inc[0]) + self._constant(const),
                          resampled=bool(rec.resampled[0]))
        return rec.x[0], info

    def _reanchored(self, y: np.ndarray, w: np.ndarray, observed: np.ndarray
                    ) -> tuple[np.ndarray, StepInfo]:
        """A step that left no weight, re-anchored by the interpreted rule; the kernel
        goes on from its particles."""
        x_hat, info = self._anchor_step(y, w, observed)
        k = self._kernel
        assert k is not None and self._X is not None
        k.set_particles(self._X, self._W)
        self._published()
        return x_hat, info

    def _record_inputs(self, Y: Any, U: Any) -> tuple[np.ndarray, np.ndarray]:
        """The record checked, ``Y (T, ny)``, and the per-particle Functions' input of
        every step ``(T, nw + np)``: the transition input, then the parameters (the
        filter reset to run it)."""
        m = self.model
        Y, steps_u = prepared_record(self, Y, U)
        T = Y.shape[0]
        W = np.empty((T, m.nw + m.p.size))
        W[:, m.nw:] = self._p
        if m.nw or self._sampled:
            for k in range(T):
                if m.nw:
                    W[k, :m.nw] = self._transition(steps_u[k])
                if self._sampled:
                    self._u_last = steps_u[k].copy()
        return Y, W

    def _compiled_filter(self, Y: Any, U: Any
                         ) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray,
                                    np.ndarray]:
        """A whole record through the kernel: estimates, covariances, statuses, ESS and
        log-likelihood increments (the filter's state as after :func:`~estim.replay`)."""
        m = self.model
        Y, W = self._record_inputs(Y, U)
        T = Y.shape[0]
        rows = self._kernel_rows(Y, W)
        X, P = np.empty((T, m.nx)), np.empty((T, m.nx, m.nx))
        status: list[str] = []
        ess, inc = np.empty(T), np.empty(T)
        k, info = 0, StepInfo()
        while k < T:
            rec = self._kernel_run(rows, k, k == 0)
            done = rec.done
            if done:
                status_run, inc[k:k + done], info = self._judged(Y, rows, k, rec)
                status += status_run
                X[k:k + done], P[k:k + done], ess[k:k + done] = \
                    rec.x[:done], rec.P[:done], rec.ess[:done]
                k += done
            self._published()
            if k < T:  # no weight left: re-anchored, then on from its particles
                X[k], info = self._reanchored(Y[k], W[k], rows["observed"][k])
                P[k] = info.P
                status.append(info.status)
                ess[k], inc[k] = info.extra["ess"], info.extra["log_likelihood"]
                k += 1
        self._first, self._k, self._info = False, T, info
        return X, P, status, ess, inc
