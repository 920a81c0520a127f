r"""Autocovariance least squares: ``Q`` and ``R`` from the innovations of any stable filter.

A filter run with a gain that is not optimal leaves innovations that are correlated in
time, and their autocovariances are linear in the noise covariances (Mehra 1970;
Odelson, Rajamani & Rawlings 2006). With the state error
:math:`\varepsilon_k = x_k - \bar x_k` of the prediction and the filter gain
:math:`K_k` (:math:`\hat x_k = \bar x_k + K_k e_k`),

.. math::
    \varepsilon_{k+1} = \bar A_k \varepsilon_k + w_k - A_k K_k v_k, \qquad
    e_k = C_k \varepsilon_k + v_k, \qquad \bar A_k = A_k (I - K_k C_k),

so :math:`\mathbb E[e_{k+j} e_k^\top]` is linear in ``(Q, R)``. Stacking the lags
``0..N-1`` of the sample autocovariances gives the least-squares problem
:math:`\min_\theta \lVert \mathcal A \theta - \hat b \rVert_W^2` over the free entries
:math:`\theta` of ``Q`` and ``R``, with :math:`Q, R \succeq 0`.

The pieces: the structures of ``Q`` and ``R`` (:mod:`~estim.tuning._als_structure`), the
filter runs giving the innovations (:mod:`~estim.tuning._als_filters`), the
autocovariance equations and Bartlett's covariance (:mod:`~estim.tuning._als_equations`)
and the positive-semidefinite least squares (:mod:`~estim.tuning._als_solve`).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike

from estim._validate import (
    as_bool,
    as_choice,
    as_covariance,
    as_inputs,
    as_int,
    as_intervals,
    as_record,
    as_vector,
)
from estim.model import Model
from estim.tuning._als_continuous import (
    check_options,
    densities,
    discretised,
    interval_bases,
    start_density,
)
from estim.tuning._als_equations import _design, _rows, _stack
from estim.tuning._als_filters import _inputs, _is_linear, _run_filter, _whitened
from estim.tuning._als_solve import _fit
from estim.tuning._als_structure import STRUCTURES, _qbasis, _structures
from estim.tuning._result import TuningResult, innovation_check

__all__ = ["DEFAULT_ALS_LAGS", "STRUCTURES", "WEIGHTINGS", "als"]

WEIGHTINGS = ("identity", "optimal")

#: Default number of lags of the stacked autocovariances.
DEFAULT_ALS_LAGS = 15


def _floored(M: np.ndarray, previous: np.ndarray) -> np.ndarray:
    """``M`` with its eigenvalues raised to a millionth of its mean variance (positive
    definite, for the filter of the next ALS pass); an ``M`` of zero (every variance at
    its boundary) to a hundredth of the ``previous`` filter's, where a zero would give
    that filter a degenerate gain."""
    own = float(np.trace(M)) / len(M)
    floor = 1e-6 * own if own > 0 else 1e-2 * float(np.trace(previous)) / len(previous)
    floor = max(floor, 1e-300)
    lam, V = np.linalg.eigh(0.5 * (M + M.T))
    return (V * np.maximum(lam, floor)) @ V.T


def _identifiable(A_als: np.ndarray, lags: int) -> None:
    """Refuse equations that do not determine every free entry (``A_als`` without full
    column rank)."""
    d = np.linalg.norm(A_als, axis=0)
    if np.any(d == 0):
        raise ValueError("structure: some free entries do not affect the innovations: "
                         "Q and R are not identifiable with this structure")
    sv = np.linalg.svd(A_als / d, compute_uv=False)
    if sv[-1] < 1e-9 * sv[0]:
        raise ValueError(f"structure: Q and R are not identifiable from these outputs with "
                         f"this structure and lags={lags} (the stacked autocovariance "
                         f"equations have rank {int(np.sum(sv > 1e-9 * sv[0]))} < "
                         f"{A_als.shape[1]} free entries); use a diagonal or scalar "
                         f"structure, a noise-shaping matrix G, or more lags")


def als(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
        gain: ArrayLike | object | None = None, Q0: ArrayLike | None = None,
        R0: ArrayLike | None = None, x0: ArrayLike | None = None,
        P0: ArrayLike | None = None, lags: int = DEFAULT_ALS_LAGS,
        structure: str | Mapping | ArrayLike = "diagonal", G: ArrayLike | None = None,
        weighting: str = "identity", burn_in: int | None = None,
        iterations: int = 1, continuous: bool = False,
        t: ArrayLike | None = None) -> TuningResult:
    r"""Autocovariance least squares: estimate ``Q`` and ``R`` from a record.

    A filter with a stable gain runs over the record; the sample autocovariances of its
    innovations :math:`e_k` at lags :math:`0..N-1`,
    :math:`\hat C_j = \frac1n \sum_k e_{k+j} e_k^\top`, are matched to their values
    predicted from the model, which are linear in the free entries :math:`\theta` of
    ``Q`` and ``R``. With the filter's prediction error
    :math:`\varepsilon_{k+1} = \bar A_k \varepsilon_k + w_k - A_k K_k v_k`,
    :math:`e_k = C_k \varepsilon_k + v_k`, :math:`\bar A_k = A_k (I - K_k C_k)` and
    its covariance :math:`P_{k+1} = \bar A_k P_k \bar A_k^\top + Q
    + A_k K_k R K_k^\top A_k^\top`,

    .. math::
        \mathbb E[e_k e_k^\top] = C_k P_k C_k^\top + R, \qquad
        \mathbb E[e_{k+j} e_k^\top] = C_{k+j} \Phi_{k+j,k} P_k C_k^\top
        - C_{k+j} \Phi_{k+j,k+1} A_k K_k R \quad (j \ge 1),

    :math:`\Phi_{k+j,k} = \bar A_{k+j-1} \cdots \bar A_k`. Averaged over the samples and
    stacked (lag 0 by its lower triangle) these give
    :math:`\mathcal A \theta \approx \hat b`, solved as

    .. math::
        \hat\theta = \operatorname{arg\,min}_\theta\, (\mathcal A\theta - \hat b)^\top W
        (\mathcal A\theta - \hat b) \quad \text{s.t.} \quad Q(\theta) \succeq 0,\;
        R(\theta) \succeq 0.

    A linear model with a constant gain is the classic time-invariant ALS (Odelson,
    Rajamani & Rawlings 2006): :math:`P` is the stationary solution of the Lyapunov
    equation. Otherwise (a nonlinear model, or an EKF's time-varying gain) the
    Jacobians are taken along the filter's estimates (the time-varying ALS of Lima &
    Rawlings 2011), an approximation for a nonlinear model that is good while the
    estimation errors are small compared with the model's curvature.

    With ``continuous=True`` the estimate is the spectral density :math:`Q_c` of a
    continuous-time noise entering through the model's ``noise_input`` :math:`L`: the
    noise of the transition over :math:`\Delta t_k` is Van Loan's
    :math:`Q_k = \int_0^{\Delta t_k} e^{A_k\tau} L Q_c L^\top e^{A_k^\top\tau} d\tau`
    (:math:`A_k` the drift's Jacobian at the filter's estimate), linear in the entries of
    :math:`Q_c`, so each basis matrix of its structure becomes a basis per transition and
    the equations stay linear; the default filter is ``EKF(Qc=...)``. A uniform record of
    a linear model is the time-invariant ALS with the discretised basis; irregular time
    stamps (``t``, a model with ``variable_dt=True``) take the time-varying equations,
    the autocovariances averaged over the samples as for a nonlinear model.

    Parameters
    ----------
    model : Model
        The model of the record (with ``variable_dt=True``, the times ``t``).
    Y : (T, ny) array
        Measurements; every output at every sample (no NaN).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as for :func:`estim.replay` (required for a model with inputs).
    gain : None, (nx, ny) array or EKF, optional
        The filter whose innovations are used. None (default): for a linear model the
        steady-state Kalman gain of ``(Q0, R0)``, for a nonlinear one an
        :class:`~estim.EKF` with ``Q0, R0, x0, P0``. An array: the constant filter gain
        :math:`L` of :math:`\hat x_k = \bar x_k + L e_k` (it must stabilise the
        filter). An ``EKF`` (without ``clip`` and ``gate``): replayed over the record
        with its own tuning.
    Q0, R0 : float, (n,) or (n, n), optional
        The rough covariances of the default filter. Default: ``R0`` the variances of
        the first differences of ``Y`` halved (an upper bound of the noise when the
        outputs change slowly) and ``Q0 = 0.1 C⁺ R0 C⁺ᵀ`` (its diagonal, floored),
        ``C = ∂h/∂x`` at ``x0``.
    x0, P0 : optional
        Initial guess of the filter and its covariance (default zeros and the
        identity).
    lags : int
        Number :math:`N` of lags ``0..N-1`` stacked (default 15). More lags than the
        filter's error takes to decay (:math:`\rho(\bar A)^N \ll 1`) add little.
    structure : "diagonal", "full", "scalar", bool mask or dict
        Free entries of ``Q`` (of ``Q_w`` with ``G``) and ``R``: the diagonal
        (default), all entries, a multiple of the identity, a symmetric ``(n, n)``
        boolean mask of the free entries (the diagonal free), or a dict
        ``{"Q": ..., "R": ...}`` of these (a missing key is "diagonal").
    G : (nx, ng) array, optional
        Noise-shaping matrix: ``Q = G Q_w Gᵀ`` with ``Q_w`` ``(ng, ng)`` of the given
        structure (``Q_w`` is in ``details["Q_w"]``). Identifiability of ``Q`` needs
        few enough free entries: with ``ny < nx`` a full ``Q`` is not identifiable.
    weighting : "identity" or "optimal"
        :math:`W = I`, or the inverse of the estimated covariance of :math:`\hat b`
        (evaluated at the identity-weighted estimate; Rajamani & Rawlings 2009), the
        minimum-variance weight.
    burn_in : int, optional
        Samples left out at the start, where the filter forgets its initial guess.
        Default: the samples the error dynamics take to decay to 1e-3
        (:math:`\rho(\bar A)^{k} \le 10^{-3}`, from ``lags`` to ``T/4``).
    continuous : bool
        Estimate the spectral density :math:`Q_c` (``(nq, nq)`` for the ``nq`` columns
        of the model's ``noise_input``; ``Q0`` then starts it, default
        :math:`\operatorname{diag}(L^+ Q_0 L^{+\top})/\overline{\Delta t}` of the
        default per-transition ``Q0``). Not with ``G``.
    t : (T,) array, optional
        Sample times, for a model built with ``variable_dt=True``.
    iterations : int
        With ``gain=None``: run ALS this many times, each with the filter of the
        previous estimates (``Q0, R0`` for the first). ALS is consistent for any stable
        gain, but its variance grows with the gain's distance from the optimal one: a
        second pass from a badly tuned filter often shrinks the standard errors several
        times (``details["Q0"]``, ``details["R0"]`` are the last filter's).

    Returns
    -------
    TuningResult
        ``method="als"``; ``Q (nx, nx)`` (:math:`Q_c` ``(nq, nq)`` with
        ``continuous=True``), ``R (ny, ny)``; ``status`` "ok", or
        "poorly determined: ..." naming the variances whose standard error exceeds ten
        times the largest variance of their matrix (the record hardly tells them apart);
        ``stderr["Q"]``, ``stderr["R"]`` (NaN for entries held at zero by the
        structure); ``check`` the :func:`innovation_check` of a filter run with the
        estimates (after the burn-in; the steady-state Kalman filter for a linear model,
        else an EKF);
        ``objective`` :math:`(\mathcal A\hat\theta - \hat b)^\top W (\mathcal A
        \hat\theta - \hat b)`; ``details``: ``lags``, ``weighting``, ``burn_in``,
        ``samples`` (:math:`n`), ``linearization`` ("time-invariant" or
        "time-varying"), ``gain`` (what filter), ``spectral_radius`` of
        :math:`\bar A` (median over samples), ``constraint_active``, ``unconstrained``
        (``{"Q", "R"}`` of the unconstrained least squares), ``theta`` and
        ``theta_cov``, ``autocovariance`` :math:`\hat C_j` ``(N, ny, ny)``,
        ``equations`` the unweighted :math:`(\mathcal A, \hat b)`, ``Q0`` and
        ``R0`` of the default filter, ``iterations``, ``noise`` (per transition or
        continuous), ``Q_w`` with ``G``, and with the
        optimal weight ``overidentification``: ``(statistic, dof, p_value)`` of
        :math:`n\,r^\top \hat S^{-1} r \sim \chi^2` (a small p-value says the model does
        not explain the autocovariances).

    Notes
    -----
    Standard errors are asymptotic: :math:`\hat b` is a mean over :math:`n` samples,
    its covariance :math:`S/n` is given by Bartlett's formula for a stationary Gaussian
    sequence evaluated with the innovation autocovariances of the fitted model (up to
    the lag where they vanish), and the estimate's covariance is the sandwich
    :math:`(\mathcal A^\top W \mathcal A)^{-1} \mathcal A^\top W S W \mathcal A
    (\mathcal A^\top W \mathcal A)^{-1}/n` (:math:`(\mathcal A^\top S^{-1}
    \mathcal A)^{-1}/n` with the optimal weight; Rajamani & Rawlings 2009). They are
    those of the unconstrained estimate: where the PSD constraint is active they
    overstate the uncertainty of the constrained one. For a nonlinear model the
    sequence is treated as stationary with the time-averaged autocovariances.

    ``Q`` and ``R`` are identifiable when :math:`\mathcal A` has full column rank
    (Odelson et al. 2006, Rajamani & Rawlings 2009); otherwise a ``ValueError`` says
    so (use a diagonal or scalar structure, ``G``, or more lags).

    References
    ----------
    B. J. Odelson, M. R. Rajamani, J. B. Rawlings, "A new autocovariance least-squares
    method for estimating noise covariances", *Automatica* 42(2), 303-308, 2006.
    M. R. Rajamani, J. B. Rawlings, "Estimation of the disturbance structure from data
    using semidefinite programming and optimal weighting", *Automatica* 45(1),
    142-148, 2009.
    F. V. Lima, J. B. Rawlings, "Nonlinear stochastic modeling to improve state
    estimation in process monitoring and control", *AIChE J.* 57(4), 996-1007, 2011.
    R. K. Mehra, "On the identification of variances and adaptive Kalman filtering",
    *IEEE Trans. Automatic Control* 15(2), 175-184, 1970.
    """
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    iterations = as_int(iterations, "iterations", minimum=1)
    if iterations > 1:
        if gain is not None:
            raise ValueError("iterations > 1 re-tunes the default filter with each estimate: "
                             "give gain=None")

        def once(Q: ArrayLike | None, R: ArrayLike | None) -> TuningResult:
            return als(model, Y, U, Q0=Q, R0=R, x0=x0, P0=P0, lags=lags, structure=structure,
                       G=G, weighting=weighting, burn_in=burn_in, continuous=continuous,
                       t=t)

        res = once(Q0, R0)
        for _ in range(iterations - 1):
            res = once(_floored(res.Q, res.details["Qc0" if continuous else "Q0"]),
                       _floored(res.R, res.details["R0"]))
        res.details["iterations"] = iterations
        return res
    continuous = as_bool(continuous, "continuous")
    if continuous:
        check_options(model, G)
    nx, ny = model.nx, model.ny
    Y = as_record(Y, ny, "Y", missing=False, names=model.output_names, what="outputs")
    T = Y.shape[0]
    dts = as_intervals(t, T, model)
    times = None if t is None else np.asarray(t, dtype=float)
    if not continuous and dts is not None and np.ptp(dts) > 1e-9 * dts.max():
        raise ValueError(f"t: the intervals run from {dts.min():g} to {dts.max():g}; one "
                         f"per-transition Q cannot be the noise of all of them: estimate "
                         f"the spectral density with continuous=True (a model with "
                         f"noise_input=)")
    U = as_inputs(U, T, model, "U")
    lags = as_int(lags, "lags", minimum=1)
    weighting = as_choice(weighting, WEIGHTINGS, "weighting")
    burn_in = as_int(burn_in, "burn_in", minimum=0, allow_none=True)
    if continuous:  # the structure is Qc's: (nq, nq)
        Gm = np.eye(nx if model.noise_input is None else model.noise_input.shape[1])
    elif G is None:
        Gm = np.eye(nx)
    else:
        Gm = np.asarray(G, dtype=float)
        if Gm.ndim == 1:
            Gm = Gm[:, None]
        if Gm.ndim != 2 or Gm.shape[0] != nx or not np.isfinite(Gm).all():
            raise ValueError(f"G must be a finite ({nx}, ng) array, got shape {Gm.shape}")
    qblock, rblock = _structures(structure, Gm.shape[1], ny)
    W, Uh = _inputs(model, U, dts)
    w1 = W[min(1, T - 1)]  # a transition's input (the first)

    # ---- the filter
    from estim.estimators.kalman.ekf import EKF

    ekf = gain if isinstance(gain, EKF) else None
    L = None
    if gain is not None and ekf is None:
        if hasattr(gain, "step"):
            raise TypeError(f"gain must be None, an (nx, ny) gain array or an estim.EKF, "
                            f"got {type(gain).__name__}")
        L = np.asarray(gain, dtype=float)
        if L.shape != (nx, ny) or not np.isfinite(L).all():
            raise ValueError(f"gain must be a finite ({nx}, {ny}) array, got shape {L.shape}")
    if ekf is not None:
        if ekf.model is not model:
            raise ValueError("gain: the EKF must be built on the same model")
        if ekf.clip or ekf.gate is not None:
            raise ValueError("gain: the EKF must run without clip and gate (its innovations "
                             "must follow the linearised filter)")
        x0 = ekf.x0
    x0v = np.zeros(nx) if x0 is None else as_vector(x0, nx, "x0")
    P0m = np.eye(nx) if P0 is None else as_covariance(P0, nx, "P0")
    linear = _is_linear(model, W, Uh, x0v)
    if R0 is None:
        R0 = np.diag(np.maximum(np.var(np.diff(Y, axis=0), axis=0) / 2 if T > 2 else
                                np.ones(ny), 1e-12))
    R0m = as_covariance(R0, ny, "R0")
    Qc0 = None
    if Q0 is None and continuous:  # its effect on the outputs a tenth of R0's
        Q0 = start_density(model, R0m, x0v, Uh[0], w1 if dts is None else
                           np.median(W[1:], axis=0))
    elif Q0 is None:
        Cp = np.linalg.pinv(np.asarray(model.H_x(x0v, Uh[0], model.p).full()))
        q = 0.1 * np.diag(Cp @ R0m @ Cp.T)
        Q0 = np.diag(np.maximum(q, 1e-3 * max(q.max(), 1e-12)))
    if continuous:  # Q0 starts Qc; the steady-state gain takes its Q_d
        Qc0 = as_covariance(Q0, Gm.shape[0], "Q0", definite=False)
        Q0m = discretised(model, Qc0, x0v, w1)
    else:
        Q0m = as_covariance(Q0, nx, "Q0", definite=False)
    constant = [model.output_names[i] for i in range(ny) if np.ptp(Y[:, i]) == 0]
    if len(constant) == ny:
        raise ValueError(f"Y is constant in every output {constant}: its autocovariances "
                         f"hold no information about Q and R")
    try:
        filt = _run_filter(model, Y, U, W, Uh, ekf, L, x0v, P0m, Q0m, R0m, linear, Qc0, times)
        rho = filt.rho

        # ---- burn-in and samples
        decay = int(np.ceil(np.log(1e-3) / np.log(rho))) if 0 < rho < 1 else 1
        if burn_in is None:
            burn_in = int(min(max(decay, lags), T // 4))
        k_lo, k_hi = burn_in, T - lags  # the products e_{k+j} e_k^T, j < lags
        n = k_hi - k_lo + 1
        if n < max(20, 2 * lags):
            raise ValueError(f"Y has too few samples ({T}) for lags={lags} and burn_in={burn_in}: "
                             f"{n} products per lag; give a longer record or fewer lags")
        e = filt.run.e
        rows = _rows(lags, ny)
        Chat = np.stack([e[k_lo + j:k_hi + j + 1].T @ e[k_lo:k_hi + 1] / n for j in range(lags)])
        b = _stack(Chat, rows)

        # ---- the design and the least squares
        QB: list[np.ndarray] | np.ndarray = _qbasis(qblock, Gm)
        if continuous:  # each free entry's Q_d: one basis, or one per interval
            dens = densities(model, list(qblock.basis))
            QB = list(interval_bases(model, dens, x0v[None], w1[None])[0]) \
                if filt.invariant is not None else interval_bases(model, dens,
                                                                  filt.run.xh[:-1], W[1:])
        RB = list(rblock.basis)
        nq = len(qblock.basis)
        coef, coef_all, M = _design(filt, QB, RB, lags, k_lo, k_hi, T)
        A_als = _stack(coef, rows)  # (rows, params)
        _identifiable(A_als, lags)
        fit = _fit(A_als, b, coef_all, rows, M, [qblock, rblock],
                   [slice(0, nq), slice(nq, nq + len(RB))], weighting == "optimal", n)
        theta, cov = fit.theta, fit.cov

        # ---- the estimates and their standard errors
        def mats(th: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            Qw = qblock.matrix(th[:nq])
            return Gm @ Qw @ Gm.T, rblock.matrix(th[nq:]), Qw

        Qh, Rh, Qw = mats(theta)
        Qh, Rh = 0.5 * (Qh + Qh.T), 0.5 * (Rh + Rh.T)
        JQ = np.stack([mats(np.eye(len(theta))[i])[0] for i in range(len(theta))], axis=-1)
        JR = np.stack([mats(np.eye(len(theta))[i])[1] for i in range(len(theta))], axis=-1)

        def se(J: np.ndarray) -> np.ndarray:
            v = np.sqrt(np.maximum(np.einsum("abi,ij,abj->ab", J, cov, J), 0.0))
            return np.where(np.any(J != 0, axis=-1), v, np.nan)

        se_Q, se_R = se(JQ), se(JR)
        Qu, Ru, _ = mats(fit.theta_u)

        # ---- the check: a filter with the estimates, after the burn-in
        if continuous:  # the check's filter: EKF(Qc=), or the stationary one of its Q_d
            check = innovation_check(_whitened(
                model, Y, U, W, Uh, filt, discretised(model, Qh, x0v, w1), Rh,
                x0v, Qh, times)[burn_in:])
        else:
            check = innovation_check(_whitened(model, Y, U, W, Uh, filt, Qh, Rh,
                                               x0v)[burn_in:])

        details = {"lags": lags, "weighting": weighting, "burn_in": burn_in, "samples": n,
                   "linearization": "time-invariant" if filt.invariant else "time-varying",
                   "gain": filt.what, "spectral_radius": rho, "constraint_active": fit.active,
                   "unconstrained": {"Q": Qu, "R": Ru}, "theta": theta, "theta_cov": cov,
                   "autocovariance": Chat, "equations": (A_als, b), "Q0": Q0m, "R0": R0m,
                   "iterations": 1, "Qc0": Qc0,
                   "noise": "continuous (Q is the spectral density Qc)" if continuous else
                   "per transition"}
        if G is not None:
            details["Q_w"] = Qw
        if weighting == "optimal":
            from scipy import stats

            dof = len(rows) - len(theta)
            stat = n * fit.objective
            details["overidentification"] = (stat, dof, float(stats.chi2.sf(stat, dof)))
        # variances the record hardly determines: a standard error beyond ten times the
        # largest variance of their matrix
        vague = [f"{name}[{i},{i}]" for name, V, s in (("Q", Qh, se_Q), ("R", Rh, se_R))
                 for i in range(len(V)) if s[i, i] > 10 * max(float(np.max(np.diag(V))), 1e-300)]
        status = "ok" if not vague else (f"poorly determined: {', '.join(vague)} (standard error "
                                         f"above ten times the largest variance of its matrix)")
        return TuningResult(method="als", Q=Qh, R=Rh, stderr={"Q": se_Q, "R": se_R, "params": {}},
                            check=check, objective=fit.objective, status=status, details=details)
    except np.linalg.LinAlgError as exc:  # the filter diverged on this record
        return TuningResult(method="als", Q=Q0m, R=R0m, success=False,
                            status=f"failed: the filter with Q0, R0 diverged on this record "
                                   f"({exc}); give Q0 and R0 closer to the noise, or a "
                                   f"stabilising gain",
                            details={"Q0": Q0m, "R0": R0m})
