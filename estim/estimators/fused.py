r"""What the fused Kalman filters (:class:`~estim.EKF`, :class:`~estim.UKF`) share.

Each filter compiles its prediction and update into one CasADi function per step,
``(s, u, y, tuning) -> (s_new, innovation, flags, s_prior)`` with the filter state
``s = [x; vec(P)]`` (column-major) and the tuning ``[vec(Q); vec(R)]`` as data. The
flags are ``(nis, ok, prediction usable, y has inf, outputs measured, prediction's
derivative usable, suspect, gated)``. This class turns them into the step's state
change and :class:`~estim.StepInfo`: a suspect step keeps its update, a gated one the
prediction with ``P0`` added, and a failed one keeps a trusted prediction or
re-anchors on the last trusted estimate with ``P + P0`` (see
:meth:`Estimator._anchor`).
"""

from __future__ import annotations

import casadi as ca

from estim.estimators.base import Estimator, StepInfo


def matrix(v, n: int, diagonal: bool):
    """The ``(n, n)`` matrix stored column-major in ``v`` (its diagonal only if asked)."""
    return ca.diag(v[[i * n + i for i in range(n)]]) if diagonal else ca.reshape(v, n, n)


class FusedKalman(Estimator):
    """Step, reset and recovery of a filter compiled into one call per step.

    Subclasses build ``self._update`` and ``self._predict_update`` (FastFunctions over
    the buffers ``_s``, ``_u``, ``_y``, ``_tun``) and say what a failed step was in
    :meth:`_failure_texts`.
    """

    def _tuning_changed(self) -> None:
        nx = self.model.nx
        self._tun[:nx * nx] = self.Q.ravel(order="F")
        self._tun[nx * nx:] = self.R.ravel(order="F")

    def _reset(self) -> None:
        nx = self.model.nx
        self._s[:nx] = self.x0
        self._s[nx:] = self.P0.ravel(order="F")
        # the anchor of a failed step: the filter state after the last step reported "ok"
        # (the prior to begin with), which is in _s while every step is ok and saved in
        # _s_trusted when a step is not
        self._s_trusted = self._s.copy()
        self._trusted = True  # _s holds the anchor

    def _step(self, y, u, first):
        self._y[:] = y
        if self._u.size:
            self._u[:] = self._transition(u)
        fun = self._update if first else self._predict_update
        s_new, e, flags, s_prior = fun.evaluate()
        if flags[3]:
            raise ValueError(f"y must not contain inf, got {y} (NaN marks a missing output)")
        if not flags[1]:
            return self._recover(flags, s_prior)
        nx = self.model.nx
        suspect = flags[6] or flags[7]
        if suspect and self._trusted:
            self._s_trusted[:] = self._s
        self._trusted = not suspect
        if flags[7]:  # gated: the prediction, with P0 added
            self._s[:] = s_prior
            self._s[nx:] += self.P0.ravel(order="F")
        else:
            self._s[:] = s_new
        info = StepInfo._fast(P=self._s[nx:].reshape(nx, nx, order="F").copy(),
                              innovation=e.copy(),
                              nis=float(flags[0]) if flags[4] else float("nan"))  # no output
        if suspect:
            info.__dict__["status"] = self._consistency(float(flags[0]), int(flags[4]),
                                                        bool(flags[7]))
        return self._s[:nx].copy(), info

    def _failure_texts(self, flags) -> tuple[str, str]:
        """``(the kept-prediction status, what failed)`` of a failed step."""
        raise NotImplementedError

    def _recover(self, flags, s_prior):
        """A failed update: keep the prediction of a trusted estimate, or re-anchor on
        the last trusted estimate with ``P + P0`` and update with this measurement."""
        kept, what = self._failure_texts(flags)
        if self._trusted:
            self._s_trusted[:] = self._s
        if flags[2] and self._trusted:  # the prediction is usable: it is the estimate
            self._s[:] = s_prior
            status = kept
        else:
            nx = self.model.nx
            x, P = self._anchor(self._s_trusted[:nx],
                                self._s_trusted[nx:].reshape(nx, nx, order="F"))
            self._s[:nx] = x
            self._s[nx:] = P.ravel(order="F")
            s_new, _, flags, _ = self._update.evaluate()
            if flags[1]:
                self._s[:] = s_new
            status = (f"failed: {what}; re-anchored on the last trusted estimate "
                      f"with P + P0" + ("" if flags[1] else " (no update: non-finite)"))
        self._trusted = False
        nx = self.model.nx
        return self._s[:nx].copy(), StepInfo(
            status=status, success=False,
            P=self._s[nx:].reshape(nx, nx, order="F").copy())
