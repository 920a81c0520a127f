r"""What the fused Kalman filters (:class:`~estim.EKF`, :class:`~estim.UKF`) share.

Each filter compiles its prediction and update into one CasADi function per step,
``(s, u, y, tuning) -> (s_new, innovation, flags, s_prior)`` with the filter state
``s = [x; vec(P)]`` (column-major) and the tuning ``[vec(Q); vec(R)]`` as data. The
flags are ``(nis, ok, prediction usable, y has inf, outputs measured, prediction's
derivative usable, suspect, gated)``. This class turns them into the step's state
change and :class:`~estim.StepInfo`: a suspect step keeps its update, a gated one the
prediction with ``P0`` added, and a failed one keeps a trusted prediction or
re-anchors on the last trusted estimate with ``P + P0`` (see
:meth:`Estimator._anchor`). In the square-root form (``form="sqrt"``,
:mod:`estim.estimators.kalman.square_root`) the filter state holds the lower factor ``S`` of
``P = S S^T`` instead, the tuning the factors of ``Q`` and ``R``, and the sums with
``P0`` are factored by QR.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._locate import after_failure
from estim._validate import as_inputs, as_intervals, as_record
from estim.consistency import consistency_status
from estim.estimators.base import Estimator, StepInfo
from estim.estimators.filtering import FilterResult, stamped
from estim.estimators.kalman.fused_calls import filter_seeds, record_call, scan_record, step_calls
from estim.estimators.kalman.square_root import (
    P0_data,
    covariance,
    noise_factors,
    with_P0,
)
from estim.estimators.kalman.statuses import (
    BLOWN_UP,
    blown_up,
    overflowing,
    record_statuses,
    reported,
    state_trace,
    unconverged,
)
from estim.solvers.kalman.kalman import fused_function, step_symbols
from estim.solvers.weights import is_diagonal


def _recover(self, flags, s_prior):
    """A fused filter's failed update (its ``_recover``): keep the prediction of a
    trusted estimate, or re-anchor on the last trusted estimate with ``P + P0`` and
    update with this measurement (an adaptive filter's noise statistics as they were)."""
    why = overflowing(self.model, self._y)
    kept, what = (f"failed: {why}; kept the prediction", why) if why else \
        self._failure_texts(flags)
    where = after_failure(self.model, self._s[:self._nx], s_prior[:self._nx], self._u)
    if self._trusted:
        self._s_trusted[:] = self._s
    if flags[2] and self._trusted:  # the prediction is usable: it is the estimate
        self._s[:] = s_prior
        status = kept
    else:
        nx, nP = self.model.nx, self._nP
        if self._sqrt:  # the factor of S S^T + P0
            x = self._anchor(self._s_trusted[:nx])[0]
            self._s[nx:nP] = with_P0(self._s_trusted[nx:nP], self._P0_data, True)
        else:
            nd = self.model.ndx
            x, P = self._anchor(self._s_trusted[:nx],
                                self._s_trusted[nx:nP].reshape(nd, nd, order="F"))
            assert P is not None  # (a covariance given, a covariance returned)
            self._s[nx:nP] = P.ravel(order="F")
        self._s[:nx] = x
        s_new, _, flags, _ = self._update.evaluate()
        if flags[1]:
            self._s[:] = s_new
        status = (f"failed: {what}; re-anchored on the last trusted estimate "
                  f"with P + P0" + ("" if flags[1] else " (no update: non-finite)"))
    self._trusted = False
    nx = self.model.nx
    return self._s[:nx].copy(), StepInfo(status=status + where, success=False,
                                         P=covariance(self._s[nx:self._nP], self.model.ndx,
                                                      self._sqrt))



class FusedKalman(Estimator):
    """Step, reset and recovery of a filter compiled into one call per step.

    Subclasses give the step's Function (:meth:`_build`, which :meth:`filter` also
    scans over whole records) and say what a failed step was in :meth:`_failure_texts`;
    ``self._update`` and ``self._predict_update`` evaluate it on the buffers ``_s``,
    ``_u``, ``_y``, ``_tun`` (:mod:`estim.estimators.kalman.fused_calls`: compiled to machine
    code when :attr:`jit`).
    """

    #: The tail probability beyond which a measurement is rejected, or None (set by the
    #: subclass's constructor).
    gate: float | None
    #: The prior's covariance: every filter requires one.
    P0: np.ndarray
    #: ``"covariance"``, or ``"sqrt"`` (``_sqrt``): the filter state holds a factor of P.
    form, _sqrt = "covariance", False
    #: Whether the steps and the whole-record scans run compiled (``jit=True``).
    jit = False
    #: Iterations of the update and ``info.iterations``, their tolerance and damping; a
    #: continuous noise's density (``Qc``) and its moments' Runge-Kutta sub-steps
    iterations, _update_iterations, tol = 1, 0, 1e-4
    damping: str | None = None
    Qc: np.ndarray | None = None
    substeps = 4
    #: entries of the filter state after ``[x; vec P]``: an adaptive filter's statistics
    _n_adapt = 0

    def _build(self, predict: bool) -> ca.Function:
        """The step's Function: ``(s, u, y, tuning) -> (s_new, innovation, flags,
        s_prior)``, with the prediction when ``predict`` (see the module's notes)."""
        raise NotImplementedError

    def _compile(self) -> None:
        """The buffers both compiled steps read (filter state ``[x; vec(P)]``, the
        transition's input, ``y``, the tuning ``[vec(Q); vec(R)]``), the two steps
        (first: update only; later: predict and update), then tuning and reset."""
        m = self.model
        nx, nd = m.nx, m.ndx  # stored states, tangent directions (P is nd x nd)
        self._nP = nx + nd * nd  # the filter state: [x; vec P; adaptive statistics]
        self._s = np.zeros(self._nP + self._n_adapt)
        self._u = np.zeros(m.nw)  # the transition's input (both ends if sampled)
        self._y = np.zeros(m.ny)
        self._tun = np.zeros(nd * nd + m.ny ** 2)
        self._diagonal = {"Q": is_diagonal(self.Q), "R": is_diagonal(self.R)}
        self._update, self._predict_update = step_calls(
            self, [self._s, self._u, self._y, self._tun])
        # views of the buffers the hot path writes and reads: the covariance (or its
        # factor) in the filter state, and the transition input's parts (see _step)
        self._P_view = self._s[nx:self._nP].reshape(nd, nd, order="F")
        nu = m.nu
        self._u_now = self._u[nu:2 * nu] if m.sampled else self._u[:nu]
        self._u_prev = self._u[:nu] if m.sampled else None
        self._variable_dt, self._nx = m.variable_dt, nx
        self._diagonal_stride = nd + 1  # (of P's diagonal in the filter state)
        self._tuning_changed()
        self._reset()

    def _symbols(self):
        """The symbols of a step (:func:`estim.solvers.kalman.kalman.step_symbols`)."""
        return step_symbols(self.model, self._diagonal, self._n_adapt)

    def _fused_function(self, name: str, inputs: list, s_new, e, nis, ok, ok_prior, y_inf,
                        ok_mean, mask, s_prior, converged=None) -> ca.Function:
        """The step's Function with its flags (:func:`estim.solvers.kalman.kalman.fused_function`),
        the gate of this filter and the convergence of an iterated update included."""
        return fused_function(name, inputs, s_new, e, nis, ok, ok_prior, y_inf, ok_mean, mask,
                              s_prior, gate=self.gate, converged=converged)

    def _check_tuning(self, new: dict) -> None:
        if self.Qc is not None and "Q" in new:  # (Q holds L Qc L^T)
            raise ValueError("this filter's process noise is a spectral density (Qc=): build "
                             "a new filter with the new Qc")

    def _tuning_changed(self) -> None:
        nd = self.model.ndx
        self._blown = BLOWN_UP * float(max(np.trace(self.P0), np.trace(self.Q), 1e-300))
        Q, R = noise_factors(self.Q, self.R, self._diagonal) if self._sqrt else (self.Q, self.R)
        self._tun[:nd * nd] = Q.ravel(order="F")
        self._tun[nd * nd:] = R.ravel(order="F")
        self._P0_data = P0_data(self.P0, self._sqrt)  # vec(P0), or vec(chol(P0)) if sqrt

    def _reset(self) -> None:
        nx = self.model.nx
        self._s[:nx] = self.x0
        self._s[nx:self._nP] = self._P0_data = P0_data(self.P0, self._sqrt)  # (P0 may change)
        self._s[self._nP:] = self._adapt_start()
        # the anchor of a failed step: the state after the last step reported "ok" (the
        # prior at first), in _s while every step is ok, else saved in _s_trusted
        self._s_trusted = self._s.copy()
        self._trusted = True  # _s holds the anchor

    def _step(self, y, u, first):
        np.copyto(self._y, y)
        if self._u.size:  # the transition's input (Model.transition), in place
            if self._plain:
                np.copyto(self._u, u)
            else:
                np.copyto(self._u_now, u)
                if self._sampled:
                    np.copyto(self._u_prev, self._u_last)
                if self._variable_dt:
                    self._u[-1] = self.model.dt if self._dt is None else self._dt
        fun = self._update if first else self._predict_update
        s_new, e, flag_array, s_prior = fun.evaluate()
        flags = flag_array.tolist()
        if flags[3]:
            raise ValueError(f"y must not contain inf, got {y} (NaN marks a missing output)")
        if not flags[1]:
            return self._recover(flag_array, s_prior)
        nx = self._nx
        suspect = flags[6] or flags[7] or (self.damping is not None and not flags[8])
        trace = 0.0 if suspect else state_trace(s_new[:self._nP], nx, self._diagonal_stride,
                                                self._sqrt)
        untrusted = suspect or trace > self._blown  # (blown up: the filter lost the state)
        if untrusted and self._trusted:
            self._s_trusted[:] = self._s
        self._trusted = not untrusted
        if flags[7]:  # gated: the prediction, with P0 added
            self._s[:] = s_prior
            self._s[nx:self._nP] = with_P0(self._s[nx:self._nP], self._P0_data, self._sqrt)
        else:
            np.copyto(self._s, s_new)
        info = StepInfo._fast(P=reported(self._P_view, self._sqrt), innovation=e.copy(),
                              nis=flags[0] if flags[4] else float("nan"),  # no output
                              iterations=self._update_iterations)
        if self._update_iterations:
            info.extra["converged"] = bool(flags[8])
        if self._n_adapt:  # the noise the filter has learnt
            info.extra.update(self._adapted(self._s[self._nP:]))
        if suspect:
            info.__dict__["status"] = self._consistency(flags[0], int(flags[4]),
                                                        bool(flags[7]), bool(flags[8]))
        elif untrusted:
            info.__dict__["status"] = blown_up(trace)
        return self._s[:nx].copy(), info

    _recover = _recover

    def _failure_texts(self, flags) -> tuple[str, str]:
        """``(the kept-prediction status, what failed)`` of a failed step."""
        raise NotImplementedError

    @property
    def x(self) -> np.ndarray:
        """Current estimate."""
        return self._s[: self.model.nx].copy()

    def _adapt_start(self) -> np.ndarray:
        """The adaptive statistics at a reset (none: a filter that does not adapt)."""
        return np.zeros(self._n_adapt)

    def _adapted(self, a: np.ndarray) -> dict[str, np.ndarray]:
        """The covariances the statistics ``a`` stand for (``info.extra``)."""
        return {}

    def _consistency(self, nis: float, dof: int, rejected: bool, converged: bool = True
                     ) -> str:
        """Status of a filter step whose NIS is beyond the suspect or the gate limit, or
        whose damped iterated update did not converge."""
        if not converged and self.damping is not None and not rejected:
            return unconverged(self)
        if not rejected:
            return consistency_status(nis, dof)
        return (f"rejected: NIS {nis:.3g} beyond the {self.gate:g} tail of chi2({dof}); "
                f"kept the prediction with P + P0")

    def filter(self, Y: ArrayLike, U: ArrayLike | None = None, *,
               t: ArrayLike | None = None) -> FilterResult:
        r"""Filter a whole record in one compiled call.

        The fused step of :meth:`step` (prediction, update, clipping, the NIS and
        its flags) is scanned over the record by one CasADi Function (``mapaccum`` in
        blocks of about :math:`\sqrt T` steps, built once per record length and
        kept; a record longer than
        :data:`~estim.estimators.kalman.fused_calls.RECORD_WINDOW` samples in windows of that
        length, continued one from the other, two Functions whatever its length),
        which gives what :func:`~estim.replay` or :meth:`step` at every sample
        gives, to rounding: the same inputs (held or sampled), missing outputs (NaN)
        and ``t``. A suspect step keeps its update; a step beyond ``gate`` keeps the
        prediction with ``P0`` added, inside the scan too. A failed update (not
        finite; for the UKF also a covariance that is not positive definite), whose
        recovery depends on the filter's history, ends the compiled part: the filter
        restarts from the state before that step as the step loop left it (its
        last trusted estimate included) and finishes the record step by step.

        Parameters
        ----------
        Y : (T, ny) array
            Measurements, NaN where missing.
        U : (T-1, nu) or (T, nu) array, optional
            ``U[k]`` acts from sample k to k+1 (with ``hold="foh"``: ``(T, nu)``,
            the input at each sample), as in ``FullInformation.fit``; required
            for a model with inputs (``U=0``: zero inputs, on purpose).
        t : (T,) array, optional
            Sample times, for a model built with ``variable_dt=True``.

        Returns
        -------
        FilterResult
            ``x (T, nx)``, ``P (T, nx, nx)``, ``innovation (T, ny)``, ``nis (T,)``,
            ``status`` and ``success``. The filter is left at the end of the record
            (after a :meth:`reset` at its start), as by the step loop.
        """
        m = self.model
        nx, ny, nd = m.nx, m.ny, m.ndx
        Y = as_record(Y, ny, "Y", names=m.output_names, what="outputs")
        T = Y.shape[0]
        U = as_inputs(U, T, m)
        dts = as_intervals(t, T, m)
        # step's input u at every sample (the input since the previous sample, or at this
        # one for sampled inputs) and the transitions' inputs w as step makes them
        steps_u = U if m.sampled else np.vstack([np.zeros((1, m.nu)), U[:-1]])
        W = m.step_transitions(steps_u, None if dts is None else
                               np.concatenate([[m.dt], dts]))
        self.reset()
        S, E, F = (a.T for a in scan_record(self, Y, W))
        failed = np.flatnonzero(F[1] == 0)
        n = int(failed[0]) if failed.size else T  # the samples filtered in the graph
        X, P = np.empty((T, nx)), np.full((T, nd, nd), np.nan)
        X[:n] = S[:nx, :n].T
        P[:n] = S[nx:self._nP, :n].T.reshape(n, nd, nd).transpose(0, 2, 1)  # column-major
        if self._sqrt:
            P[:n] = reported(P[:n], True)
        innovation, nis = np.full((T, ny), np.nan), np.full(T, np.nan)
        innovation[:n] = E[:, :n].T
        measured = F[4, :n] > 0
        nis[:n][measured] = F[0, :n][measured]
        flagged, suspect = record_statuses(self, F[:, :n].T, P[:n])
        learnt = {k: np.concatenate([v, np.full((T - n,) + v.shape[1:], np.nan)])
                  for k, v in self._adapted(S[self._nP:, :n].T).items()}  # (adapt=)
        converged = None
        if self._update_iterations:
            converged = np.zeros(T, dtype=bool)
            converged[:n] = F[8, :n] > 0
        status = [flagged.get(k, "ok") for k in range(n)]
        if n:  # the filter as the step loop leaves it after sample n - 1
            trusted = np.flatnonzero(~suspect)
            self._s[:] = S[:, n - 1]
            if trusted.size:
                self._s_trusted[:] = S[:, trusted[-1]]
            self._trusted = not suspect[-1]
            self._first, self._k = False, n
            if m.sampled:
                self._u_last = U[n - 1].copy()
            self._info = StepInfo._fast(P=P[n - 1].copy(), innovation=innovation[n - 1].copy(),
                                        nis=float(nis[n - 1]), status=status[-1],
                                        iterations=self._update_iterations)
        success = True
        for k in range(n, T):  # from a failed update on: the step loop
            dt = None if dts is None or k == 0 else float(dts[k - 1])
            X[k] = self.step(Y[k].copy(), steps_u[k].copy(), dt=dt)
            info = self.info
            if info.P is not None:
                P[k] = info.P
            if info.innovation is not None:
                innovation[k] = info.innovation
            nis[k] = info.nis
            if converged is not None:
                converged[k] = info.extra.get("converged", False)
            for key, v in learnt.items():
                v[k] = info.extra[key]
            status.append(info.status)
            success = success and info.success
        return stamped(FilterResult(x=X, P=P, innovation=innovation, nis=nis,
                                    status=tuple(status), success=success,
                                    converged=converged, R=learnt.get("R"),
                                    Q=learnt.get("Q")), self.model, t)

    def _whole_record(self, T: int, expand: bool = True) -> FastFunction:
        """``(s0, Y, W, tuning, P0) -> (S, E, flags)``: the fused step over ``T`` samples
        (the first an update), the filter state, innovation and flags of every sample
        side by side; a gated step keeps the prediction with ``P0`` added
        (:func:`estim.estimators.kalman.fused_calls.record_call`: kept for the last few record
        lengths; compiled with :attr:`jit`). Not ``expand``: the step is called in loops
        instead of inlined (the form to compile to C)."""
        return record_call(self, T, expand)

    @classmethod
    def _batchable(cls) -> bool:
        """Whether a batch of records can stand for this class's :meth:`step`: its step,
        update and recovery are this module's (a subclass that changes any of them is
        run step by step)."""
        return all(getattr(cls, name) is getattr(FusedKalman, name)
                   for name in ("step", "_step", "_recover", "filter", "_whole_record",
                                "_filter_seeds"))

    def _filter_seeds(self, Y: np.ndarray, u_step: np.ndarray) -> dict:
        """Filter the records ``Y (S, T, ny)`` of several seeds at once, as :meth:`step` at
        every sample after a :meth:`reset` (the batched path of :func:`~estim.compare`;
        :func:`~estim.estimators.kalman.fused_calls.filter_seeds` says what it returns)."""
        return filter_seeds(self, Y, u_step)

