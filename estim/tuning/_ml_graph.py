r"""The likelihood as one CasADi graph: the EKF or UKF step scanned over a record.

One step of the filter with ``Q``, ``R`` and the model parameters ``p`` as symbols
maps the state ``s = [x; vec P]`` and a sample to the next state, the sample's term

.. math::
    \tfrac12 \left( \log\det S_k + e_k^\top S_k^{-1} e_k + m_k \log 2\pi \right)

(with the Cholesky factor :math:`L_k L_k^\top = S_k`, :math:`\log\det S_k =
2\sum_i \log L_{k,ii}`) and the whitened innovation :math:`L_k^{-1} e_k`. The first
sample is an update of the prior, the others predict then update; the step scanned
over the record (:func:`~estim._scan.blocked_scan`) and the weighted sum of the terms
give :math:`-\log L` as a function of ``(q, r, p)`` whose derivatives CasADi takes by
algorithmic differentiation through every step (Schweppe 1965; Durbin & Koopman 2012,
sec. 7.2). Missing outputs are masked: their rows of :math:`S_k` become the identity
and their innovations zero. The graphs are compiled once per model, filter and record
length, and kept while the model lives.
"""

from __future__ import annotations

import weakref
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._scan import blocked_scan
from estim._validate import (
    as_covariance,
    as_inputs,
    as_int,
    as_intervals,
    as_record,
    as_vector,
)
from estim.estimators.kalman.ukf import sigma_rule
from estim.model import Model

#: A CasADi symbolic expression (SX or MX: MX when the model integrates with CVODES).
Sym = Any

#: Variance of the approximate diffuse prior used when ``P0`` is not given (as statsmodels).
DIFFUSE_VARIANCE = 1e6
_LOG_2PI = float(np.log(2.0 * np.pi))


def noise_dim(model: Model, kind: str) -> int:
    """The size of the likelihood's process-noise matrix: the columns of the model's
    ``noise_input`` with a continuous noise (``kind`` ``"ekf@4"``), else ``nx``."""
    if "@" in kind and model.noise_input is not None:
        return int(model.noise_input.shape[1])
    return model.nx


def _cholesky(S: Sym) -> list[list[Sym]]:
    """Lower Cholesky factor of a small symbolic matrix, as rows of scalar expressions."""
    n = S.shape[0]
    L: list[list[Sym]] = [[0] * n for _ in range(n)]
    for j in range(n):
        d = S[j, j] - sum((L[j][k] ** 2 for k in range(j)), 0)
        L[j][j] = ca.sqrt(d)
        for i in range(j + 1, n):
            L[i][j] = (S[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), 0)) / L[j][j]
    return L


def _lower(L: list[list[Sym]], sym: type[Sym]) -> Sym:
    """The factor as a matrix."""
    n = len(L)
    return ca.vertcat(*[ca.horzcat(*[L[i][j] if j <= i else sym(0) for j in range(n)])
                        for i in range(n)]) if n else sym(0, 0)


def _forward(L: list[list[Sym]], b: Sym) -> list[Sym]:
    """Solve :math:`L z = b` for a vector ``b`` by forward substitution."""
    z: list[Sym] = []
    for i in range(len(L)):
        z.append((b[i] - sum((L[i][k] * z[k] for k in range(i)), 0)) / L[i][i])
    return z


def _filter_step(model: Model, kind: str, predict: bool, ukf: tuple
                 ) -> ca.Function:
    r"""One step of the filter with the covariances and parameters as symbols:
    ``(s, w, y, mask, q, r, p) -> (s_new, term, whitened)``.

    ``s = [x; vec P]``, ``q = vec Q`` (with a continuous noise ``vec Qc``, ``(nq, nq)``
    for the ``nq`` columns of the model's ``noise_input``), ``r = vec R``; ``mask`` is 1
    where ``y`` is measured (``y`` holds 0 elsewhere); ``term`` is
    :math:`\frac12(\log\det S + e^\top S^{-1} e + m \log 2\pi)` and ``whitened``
    :math:`L^{-1} e` (:math:`LL^\top = S`).
    """
    kind, _, sub = kind.partition("@")  # "ekf@4": a continuous noise, 4 sub-steps
    substeps = int(sub) if sub else None
    sym: type[Sym] = ca.MX if model.integrator == "cvodes" and not substeps else ca.SX
    nx, ny, nw, npar = model.nx, model.ny, model.nw, model.p.size
    nq = noise_dim(model, f"{kind}@" if substeps else kind)
    s = sym.sym("s", nx + nx * nx)
    w, y, mask = sym.sym("w", nw), sym.sym("y", ny), sym.sym("mask", ny)
    q, r, p = sym.sym("q", nq * nq), sym.sym("r", ny * ny), sym.sym("p", npar)
    x, P = s[:nx], ca.reshape(s[nx:], nx, nx)
    Q, R = ca.reshape(q, nq, nq), ca.reshape(r, ny, ny)
    uy = model.measurement_input(w)
    D = ca.diag(mask)
    if substeps:  # q is the spectral density Qc: W = L Qc L^T, the moments integrated
        L = ca.DM(np.eye(nx) if model.noise_input is None else model.noise_input)
        Q = L @ Q @ L.T
    if kind == "ekf":
        if predict and substeps:
            xb, Pb = _moments(model, x, P, w, p, Q, substeps)
        elif predict:
            xb = model.F(x, w, p)
            A = model.F_x(x, w, p)
            Pb = A @ P @ A.T + Q
        else:
            xb, Pb = x, P
        C = D @ model.H_x(xb, uy, p)
        e = mask * (y - model.H(xb, uy, p))
        S = C @ Pb @ C.T + D @ R @ D + ca.diag(1 - mask)
        S = 0.5 * (S + S.T)
        K = ca.solve(S, C @ Pb).T
        IKC = sym.eye(nx) - K @ C
        Ph = IKC @ Pb @ IKC.T + K @ (D @ R @ D) @ K.T
    else:  # the UKF's sigma points (estim.UKF's rules: merwe, julier, cubature, Gauss-Hermite)
        points, order, alpha, beta, kappa = ukf
        c, Wm, Wc, unit = sigma_rule(points, nx, order, alpha, beta, kappa)
        wm, wc = [float(w) for w in Wm], [float(w) for w in Wc]

        def sigma_points(x: Sym, P: Sym) -> list[Sym]:
            G = _lower(_cholesky(c * P), sym)
            if unit is not None:
                return [x + G @ ca.DM(xi) for xi in unit.T]
            centre = [] if points == "cubature" else [x]
            return centre + [x + G[:, i] for i in range(nx)] + \
                [x - G[:, i] for i in range(nx)]

        if predict and substeps:
            xb, Pb = _moments(model, x, P, w, p, Q, substeps,
                              (lambda m, S: (sigma_points(m, S), ca.SX(1)), Wm, Wc))
        elif predict:
            chi = [model.F(ci, w, p) for ci in sigma_points(x, P)]
            xb = sum((wi * ci for wi, ci in zip(wm, chi, strict=True)), 0)
            Pb = sum((wi * (ci - xb) @ (ci - xb).T for wi, ci in zip(wc, chi, strict=True)),
                     0) + Q
        else:  # no prediction: the prior
            xb, Pb = x, P
        chi = sigma_points(xb, Pb)  # drawn again from the prediction, as filterpy does
        Z = [model.H(ci, uy, p) for ci in chi]
        zb = sum((wi * zi for wi, zi in zip(wm, Z, strict=True)), 0)
        Pzz = sum((wi * (zi - zb) @ (zi - zb).T for wi, zi in zip(wc, Z, strict=True)), 0)
        Pxz = sum((wi * (ci - xb) @ (zi - zb).T for wi, ci, zi in zip(wc, chi, Z, strict=True)),
                  0) @ D
        e = mask * (y - zb)
        S = D @ Pzz @ D + D @ R @ D + ca.diag(1 - mask)
        S = 0.5 * (S + S.T)
        K = ca.solve(S, Pxz.T).T
        Ph = Pb - K @ S @ K.T
    xh = xb + K @ e
    Ph = 0.5 * (Ph + Ph.T)
    Lf = _cholesky(S)
    z = _forward(Lf, e)
    eps = ca.vertcat(*z) if ny else sym(0, 1)
    logdet = 2 * sum((ca.log(Lf[i][i]) for i in range(ny)), 0)
    term = 0.5 * (logdet + ca.sumsqr(eps) + ca.sum1(mask) * _LOG_2PI)
    return ca.Function("ml_step" if predict else "ml_first", [s, w, y, mask, q, r, p],
                       [ca.vertcat(xh, ca.vec(Ph)), term, eps],
                       ["s", "w", "y", "mask", "q", "r", "p"], ["s_new", "term", "whitened"])


def _moments(model: Model, x: Sym, P: Sym, w: Sym, p: Sym, W: Sym, substeps: int,
             sigma: tuple | None = None) -> tuple[Sym, Sym]:
    """The continuous-discrete prediction over the interval of ``w`` (the moment equations
    of the extended filter, or with ``sigma = (points, Wm, Wc)`` of the sigma-point one;
    :mod:`estim.solvers.kalman.continuous`)."""
    from estim.solvers.kalman.continuous import (
        drift_jacobian,
        interval,
        moment_step,
        sigma_moment_step,
    )

    f = model.f_c
    assert f is not None  # (a continuous model, checked by the caller)
    u_of, h = interval(model, w)
    if sigma is None:
        return moment_step(f, drift_jacobian(model), x, P, u_of, p, W, h, substeps)
    points, Wm, Wc = sigma
    xb, Pb, _ = sigma_moment_step(f, points, Wm, Wc, x, P, u_of, p, W, h, substeps)
    return xb, Pb


# compiled likelihoods per model, filter and record length (built once, reused by every
# start, iteration and later fit of a record of that length)
_CORES: weakref.WeakKeyDictionary[Model, dict[tuple, Any]] = weakref.WeakKeyDictionary()


def _core(model: Model, kind: str, T: int, ukf: tuple) -> ca.Function:
    r"""The whole-record recursion ``(q, r, p, x0, P0, Y, M, W, wt) -> (nll, whitened)``:
    the first step an update, then the predict-update step scanned over ``T - 1``
    samples (``mapaccum``); ``nll`` :math:`= \sum_k wt_k \, term_k`."""
    key = (kind, T, ukf if kind.startswith("ukf") else None)
    cache = _CORES.setdefault(model, {})
    if key in cache:
        return cache[key]
    nx, ny, nw, npar = model.nx, model.ny, model.nw, model.p.size
    first = _filter_step(model, kind, False, ukf)
    scan = _scan(_filter_step(model, kind, True, ukf), T - 1)
    nq = noise_dim(model, kind)
    q, r, p = ca.MX.sym("q", nq * nq), ca.MX.sym("r", ny * ny), ca.MX.sym("p", npar)
    x0, P0 = ca.MX.sym("x0", nx), ca.MX.sym("P0", nx * nx)
    Y, M = ca.MX.sym("Y", ny, T), ca.MX.sym("M", ny, T)
    W, wt = ca.MX.sym("W", nw, T), ca.MX.sym("wt", 1, T)
    s1, t0, e0 = first(ca.vertcat(x0, P0), W[:, 0], Y[:, 0], M[:, 0], q, r, p)
    _, terms, E = scan(s1, W[:, 1:], Y[:, 1:], M[:, 1:], q, r, p)
    nll = wt[0] * t0 + ca.dot(wt[1:], terms)
    fun = ca.Function(f"ml_{kind.replace('@', '_cd')}_{T}", [q, r, p, x0, P0, Y, M, W, wt],
                      [nll, ca.horzcat(e0, E)],
                      ["q", "r", "p", "x0", "P0", "Y", "M", "W", "wt"], ["nll", "whitened"])
    cache[key] = fun
    return fun


def _scan(step: ca.Function, N: int) -> ca.Function:
    r"""``step`` (``(s, w, y, mask, q, r, p) -> (s_new, term, whitened)``) scanned over
    ``N`` samples: ``(s, W, Y, M, q, r, p) -> (s_N, terms, whitened)`` with ``W, Y, M``
    one column per sample and the outputs side by side (in blocks of about
    :math:`\sqrt N` steps, see :func:`~estim._scan.blocked_scan`)."""
    return blocked_scan(step, N, (1, 2, 3))


class _Record:
    """A checked record as the compiled likelihood takes it: the outputs ``Y`` and the
    mask ``M`` of the measured ones, ``(ny, T)`` (``Y`` 0 where missing), the transition
    inputs ``W (nw, T)``, the weights ``wt (1, T)`` of the terms (0 in the first ``burn``
    samples), and the prior ``x0, P0`` (the approximate diffuse prior by default)."""

    def __init__(self, model: Model, Y: ArrayLike, U: ArrayLike | None, x0: ArrayLike | None,
                 P0: ArrayLike | None, burn: int | None, t: ArrayLike | None = None):
        Y = as_record(Y, model.ny, "Y", names=model.output_names, what="outputs")
        T = Y.shape[0]
        if T < 2:
            raise ValueError(f"Y must hold at least 2 samples, got {T}")
        dts = as_intervals(t, T, model)  # the stamps of a variable_dt model
        U = as_inputs(U, T, model, "U")
        diffuse = P0 is None
        self.x0 = np.zeros(model.nx) if x0 is None else as_vector(x0, model.nx, "x0")
        self.P0 = DIFFUSE_VARIANCE * np.eye(model.nx) if diffuse else \
            as_covariance(P0, model.nx, "P0", definite=True)
        if burn is None:
            burn = model.nx if diffuse else 0
        burn = as_int(burn, "burn", minimum=0)
        if burn >= T:
            raise ValueError(f"burn must be smaller than the number of samples {T}, got {burn}")
        self.T, self.burn = T, burn
        measured = np.isfinite(Y)
        self.M = measured.T.astype(float)
        self.Y = np.where(measured, Y, 0.0).T
        self.wt = (np.arange(T) >= burn).astype(float)[None, :]
        # transition inputs as the filters' step sees them (replay's convention)
        steps_u = U if model.sampled else np.vstack([np.zeros((1, model.nu)), U[:-1]])
        self.W = model.step_transitions(steps_u, None if dts is None else
                                        np.concatenate([[model.dt], dts])).T
        self.measured = measured
        if not measured[burn:].any():
            raise ValueError("Y has no measured output after the burn-in samples")

    def data(self) -> list[np.ndarray]:
        """The record's arguments of :func:`_core`: ``x0, vec P0, Y, M, W, wt``."""
        return [self.x0, self.P0.ravel(order="F"), self.Y, self.M, self.W, self.wt]

