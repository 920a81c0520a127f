r"""Maximum-likelihood noise covariances: the prediction-error likelihood of the EKF or UKF.

A Kalman filter run with covariances :math:`Q, R` (and model parameters :math:`p`) turns
a record :math:`y_0, \dots, y_{T-1}` into innovations :math:`e_k = y_k - \hat y_{k|k-1}`
with covariances :math:`S_k`. For a linear-Gaussian model they are independent Gaussians,
and the likelihood of the record factorises into theirs (Schweppe 1965):

.. math::
    -\log L(\theta) = \tfrac12 \sum_{k \ge b} \left( \log\det S_k + e_k^\top S_k^{-1} e_k
    + m_k \log 2\pi \right)

(:math:`m_k` outputs measured at sample :math:`k`, the first :math:`b` samples left out
by ``burn``). For a nonlinear model the EKF (UKF) gives the same expression with its
approximate innovations: the prediction-error likelihood (Ljung 1999, ch. 7). The whole
recursion is one CasADi graph (the filter step scanned over the record), so the gradient
of :math:`-\log L` with respect to :math:`\theta` is exact, by algorithmic
differentiation through every step of the filter (and so is the Hessian on request).
"""

from __future__ import annotations

import time
import weakref
from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._scan import blocked_scan
from estim._validate import (
    as_choice,
    as_covariance,
    as_float,
    as_inputs,
    as_int,
    as_record,
    as_seed,
    as_vector,
)
from estim.model import Model
from estim.tuning._result import TuningResult, innovation_check

ESTIMATORS = ("ekf", "ukf")
STRUCTURES = ("diagonal", "full", "scalar", "fixed")
#: Variance of the approximate diffuse prior used when ``P0`` is not given (as statsmodels).
DIFFUSE_VARIANCE = 1e6
_LOG_2PI = float(np.log(2.0 * np.pi))


# ---------------------------------------------------------------- symbolic algebra
def _cholesky(S) -> list[list]:
    """Lower Cholesky factor of a small symbolic matrix, as rows of scalar expressions."""
    n = S.shape[0]
    L: list[list] = [[0] * n for _ in range(n)]
    for j in range(n):
        d = S[j, j] - sum((L[j][k] ** 2 for k in range(j)), 0)
        L[j][j] = ca.sqrt(d)
        for i in range(j + 1, n):
            L[i][j] = (S[i, j] - sum((L[i][k] * L[j][k] for k in range(j)), 0)) / L[j][j]
    return L


def _lower(L: list[list], sym):
    """The factor as a matrix."""
    n = len(L)
    return ca.vertcat(*[ca.horzcat(*[L[i][j] if j <= i else sym(0) for j in range(n)])
                        for i in range(n)]) if n else sym(0, 0)


def _forward(L: list[list], b) -> list:
    """Solve :math:`L z = b` for a vector ``b`` by forward substitution."""
    z: list = []
    for i in range(len(L)):
        z.append((b[i] - sum((L[i][k] * z[k] for k in range(i)), 0)) / L[i][i])
    return z


def _filter_step(model: Model, kind: str, predict: bool, ukf: tuple[float, float, float]
                 ) -> ca.Function:
    r"""One step of the filter with the covariances and parameters as symbols:
    ``(s, w, y, mask, q, r, p) -> (s_new, term, whitened)``.

    ``s = [x; vec P]``, ``q = vec Q``, ``r = vec R``; ``mask`` is 1 where ``y`` is measured
    (``y`` holds 0 elsewhere); ``term`` is :math:`\frac12(\log\det S + e^\top S^{-1} e +
    m \log 2\pi)` and ``whitened`` :math:`L^{-1} e` (:math:`LL^\top = S`).
    """
    sym = ca.MX if model.integrator == "cvodes" else ca.SX
    nx, ny, nw, npar = model.nx, model.ny, model.nw, model.p.size
    s = sym.sym("s", nx + nx * nx)
    w, y, mask = sym.sym("w", nw), sym.sym("y", ny), sym.sym("mask", ny)
    q, r, p = sym.sym("q", nx * nx), sym.sym("r", ny * ny), sym.sym("p", npar)
    x, P = s[:nx], ca.reshape(s[nx:], nx, nx)
    Q, R = ca.reshape(q, nx, nx), ca.reshape(r, ny, ny)
    uy = model.measurement_input(w)
    D = ca.diag(mask)
    if kind == "ekf":
        if predict:
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
    else:  # Van der Merwe's scaled sigma points, as filterpy's UnscentedKalmanFilter
        alpha, beta, kappa = ukf
        lam = alpha**2 * (nx + kappa) - nx
        c = nx + lam
        wm = [lam / c] + [0.5 / c] * (2 * nx)
        wc = [lam / c + 1 - alpha**2 + beta] + [0.5 / c] * (2 * nx)

        def sigma_points(x, P):
            G = _lower(_cholesky(c * P), sym)
            return [x] + [x + G[:, i] for i in range(nx)] + [x - G[:, i] for i in range(nx)]

        if predict:
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


# compiled likelihoods per model, filter and record length (built once, reused by every
# start, iteration and later fit of a record of that length)
_CORES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _core(model: Model, kind: str, T: int, ukf: tuple[float, float, float]) -> ca.Function:
    r"""The whole-record recursion ``(q, r, p, x0, P0, Y, M, W, wt) -> (nll, whitened)``:
    the first step an update, then the predict-update step scanned over ``T - 1``
    samples (``mapaccum``); ``nll`` :math:`= \sum_k wt_k \, term_k`."""
    key = (kind, T, ukf if kind == "ukf" else None)
    cache = _CORES.setdefault(model, {})
    if key in cache:
        return cache[key]
    nx, ny, nw, npar = model.nx, model.ny, model.nw, model.p.size
    first = _filter_step(model, kind, False, ukf)
    scan = _scan(_filter_step(model, kind, True, ukf), T - 1)
    q, r, p = ca.MX.sym("q", nx * nx), ca.MX.sym("r", ny * ny), ca.MX.sym("p", npar)
    x0, P0 = ca.MX.sym("x0", nx), ca.MX.sym("P0", nx * nx)
    Y, M = ca.MX.sym("Y", ny, T), ca.MX.sym("M", ny, T)
    W, wt = ca.MX.sym("W", nw, T), ca.MX.sym("wt", 1, T)
    s1, t0, e0 = first(ca.vertcat(x0, P0), W[:, 0], Y[:, 0], M[:, 0], q, r, p)
    _, terms, E = scan(s1, W[:, 1:], Y[:, 1:], M[:, 1:], q, r, p)
    nll = wt[0] * t0 + ca.dot(wt[1:], terms)
    fun = ca.Function(f"ml_{kind}_{T}", [q, r, p, x0, P0, Y, M, W, wt],
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


# ------------------------------------------------------------------ the record
class _Record:
    """A checked record as the compiled likelihood takes it."""

    def __init__(self, model: Model, Y, U, x0, P0, burn):
        Y = as_record(Y, model.ny, "Y", names=model.output_names, what="outputs")
        T = Y.shape[0]
        if T < 2:
            raise ValueError(f"Y must hold at least 2 samples, got {T}")
        if model.variable_dt:
            raise ValueError("model has variable_dt=True: the likelihood integrates over the "
                             "model's fixed dt (build the model without variable_dt)")
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
        self.W = model.step_transitions(steps_u).T
        self.measured = measured
        if not measured[burn:].any():
            raise ValueError("Y has no measured output after the burn-in samples")

    def data(self) -> list:
        return [self.x0, self.P0.ravel(order="F"), self.Y, self.M, self.W, self.wt]


# ----------------------------------------------------------- the parametrisation
def _structures(structure) -> dict[str, str]:
    if isinstance(structure, str):
        s = as_choice(structure, STRUCTURES, "structure")
        return {"Q": s, "R": s}
    if isinstance(structure, Mapping):
        unknown = sorted(set(structure) - {"Q", "R"})
        if unknown:
            raise ValueError(f"structure as a dict takes the keys 'Q' and 'R', got {unknown}")
        return {k: as_choice(structure.get(k, "diagonal"), STRUCTURES, f"structure[{k!r}]")
                for k in ("Q", "R")}
    raise TypeError(f"structure must be one of {STRUCTURES} or a dict {{'Q': ..., 'R': ...}}, "
                    f"got {type(structure).__name__}")


def _covariance_of(theta, kind: str, n: int, fixed):
    """The covariance of its parameters: ``(matrix expression, number used)``; ``fixed``
    is the (symbolic) matrix a ``"fixed"`` structure holds."""
    if kind == "fixed":
        return fixed, 0
    if kind == "scalar":
        return ca.exp(theta[0]) * ca.SX.eye(n), 1
    if kind == "diagonal":
        return ca.diag(ca.exp(theta[:n])), n
    L = ca.SX(n, n)  # log-Cholesky: L_ii = exp(theta), L_ij = theta below the diagonal
    i = 0
    for col in range(n):
        for row in range(col, n):
            L[row, col] = ca.exp(theta[i]) if row == col else theta[i]
            i += 1
    return L @ L.T, i


def _initial(kind: str, C: np.ndarray, name: str) -> np.ndarray:
    """The parameters of a starting covariance."""
    if kind == "fixed":
        return np.zeros(0)
    d = np.diag(C)
    if kind in ("scalar", "diagonal") and not (d > 0).all():
        raise ValueError(f"{name} must have a positive diagonal for structure {kind!r} "
                         f"(use 'fixed' to hold it), got diagonal {d}")
    if kind == "scalar":
        return np.array([np.log(d.mean())])
    if kind == "diagonal":
        return np.log(d)
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} must be positive definite for structure 'full'") from None
    n = C.shape[0]
    return np.array([np.log(L[r, c]) if r == c else L[r, c]
                     for c in range(n) for r in range(c, n)])


def _params_spec(model: Model, params) -> dict[str, float]:
    """``params`` (None, names, or ``{name: start}``) as ``{name: start}``."""
    if params is None:
        return {}
    if isinstance(params, str):
        params = [params]
    if isinstance(params, Mapping):
        spec = {k: as_float(v, f"params[{k!r}]") for k, v in params.items()}
    elif isinstance(params, Sequence):
        spec = {k: float(model.params[k]) if k in model.params else np.nan for k in params}
    else:
        raise TypeError(f"params must be a list of parameter names or a dict {{name: start}}, "
                        f"got {type(params).__name__}")
    unknown = [k for k in spec if not isinstance(k, str) or k not in model.param_names]
    if unknown:
        raise ValueError(f"params names unknown parameters {unknown}; the model's parameters "
                         f"are {model.param_names}")
    return spec


class _Parametrisation:
    r"""``(theta, fixed) -> (vec Q, vec R, p)``: log-variances (diagonal, scalar) or the
    log-Cholesky factor (full), then the estimated model parameters; ``fixed = [vec Q0;
    vec R0; p]`` holds what is not estimated (data, so that the compiled objective serves
    any start and record of the same length)."""

    def __init__(self, model: Model, structures: dict, Q0: np.ndarray, R0: np.ndarray,
                 spec: dict[str, float]):
        nx, ny = model.nx, model.ny
        self.structures = structures
        self.names = list(spec)
        index = [model.param_names.index(k) for k in spec]
        t0 = [_initial(structures["Q"], Q0, "Q0"), _initial(structures["R"], R0, "R0")]
        self.n_noise = sum(len(t) for t in t0)
        # the parameters that are logs: (theta index, matrix, diagonal entry or None for
        # a scalar, 1 for a log-variance or 2 for a log-Cholesky diagonal)
        self.logs: list[tuple[int, str, int | None, int]] = []
        offset = 0
        for name, n in (("Q", nx), ("R", ny)):
            kind = structures[name]
            if kind == "scalar":
                self.logs.append((offset, name, None, 1))
            elif kind == "diagonal":
                self.logs += [(offset + i, name, i, 1) for i in range(n)]
            elif kind == "full":
                k = 0
                for col in range(n):
                    for row in range(col, n):
                        if row == col:
                            self.logs.append((offset + k, name, col, 2))
                        k += 1
            offset += len(t0[0]) if name == "Q" else 0
        self.theta0 = np.concatenate(t0 + [np.array(list(spec.values()), dtype=float)])
        self.fixed = np.concatenate([Q0.ravel(order="F"), R0.ravel(order="F"), model.p])
        self.key = (structures["Q"], structures["R"], tuple(index))
        theta = ca.SX.sym("theta", self.theta0.size)
        fixed = ca.SX.sym("fixed", self.fixed.size)
        Q, nq = _covariance_of(theta, structures["Q"], nx, ca.reshape(fixed[:nx * nx], nx, nx))
        R, nr = _covariance_of(theta[nq:], structures["R"], ny,
                               ca.reshape(fixed[nx * nx:nx * nx + ny * ny], ny, ny))
        p = fixed[nx * nx + ny * ny:]
        for j, i in enumerate(index):
            p[i] = theta[nq + nr + j]
        out = ca.vertcat(ca.vec(Q), ca.vec(R), p[index] if index else ca.SX(0, 1))
        self.unpack = ca.Function("unpack", [theta, fixed], [ca.vec(Q), ca.vec(R), p])
        self._entries = ca.Function("entries", [theta, fixed], [out, ca.jacobian(out, theta)])

    def entries(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The estimated entries ``[vec Q; vec R; params]`` and their Jacobian."""
        out, J = self._entries(theta, self.fixed)
        return np.asarray(out, dtype=float).ravel(), np.asarray(J, dtype=float)

    def matrices(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``vec Q``, ``vec R`` and the model's parameter vector at ``theta``."""
        return tuple(np.asarray(v, dtype=float).ravel() for v in self.unpack(theta, self.fixed))


# ------------------------------------------------------------------- public API
def log_likelihood(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
                   Q: ArrayLike, R: ArrayLike, x0: ArrayLike | None = None,
                   P0: ArrayLike | None = None, params: Mapping[str, float] | None = None,
                   estimator: str = "ekf", burn: int | None = None, alpha: float = 0.1,
                   beta: float = 2.0, kappa: float = 0.0) -> float:
    r"""The prediction-error log-likelihood of a record under the EKF or UKF.

    .. math::
        \log L = -\tfrac12 \sum_{k=b}^{T-1} \left( \log\det S_k
        + e_k^\top S_k^{-1} e_k + m_k \log 2\pi \right),

    with the innovations :math:`e_k = y_k - \hat y_{k|k-1}` and their covariances
    :math:`S_k` of the filter (``estim.EKF`` or ``estim.UKF`` with the same ``Q, R, x0,
    P0``; the first sample is an update of the prior ``x0, P0``), over the :math:`m_k`
    outputs measured at sample :math:`k` (NaN in ``Y``: missing).

    Parameters
    ----------
    model : Model
    Y : (T, ny) array
        Measurements, NaN where missing (``T >= 2``).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as :func:`~estim.replay` takes them (``U[k]`` acts after sample ``k``).
    Q, R : float, vector of variances or matrix
        Process- and measurement-noise covariances.
    x0, P0 : optional
        Prior of the first state; default the approximate diffuse prior
        :math:`x_0 = 0`, :math:`P_0 = 10^6 I`.
    params : dict, optional
        Model parameter values to use instead of the model's.
    estimator : {"ekf", "ukf"}
    burn : int, optional
        Number :math:`b` of first samples whose terms are left out (the filter still
        uses them). Default 0, or ``nx`` with the diffuse prior (statsmodels'
        ``loglikelihood_burn``).
    alpha, beta, kappa : float
        The UKF's sigma-point parameters (as :class:`~estim.UKF`).

    Returns
    -------
    float
        :math:`\log L` (``-inf`` where the filter breaks down).

    References
    ----------
    F. C. Schweppe, "Evaluation of likelihood functions for Gaussian signals", IEEE
    Trans. Inf. Theory 11(1), 1965; J. Durbin, S. J. Koopman, *Time Series Analysis by
    State Space Methods*, 2nd ed., Oxford 2012, sec. 7.2.
    """
    model, kind, ukf = _check_common(model, estimator, alpha, beta, kappa)
    rec = _Record(model, Y, U, x0, P0, burn)
    Qm = as_covariance(Q, model.nx, "Q", definite=False)
    Rm = as_covariance(R, model.ny, "R", definite=True)
    p = model.p.copy()
    for k, v in _params_spec(model, params or {}).items():
        p[model.param_names.index(k)] = v
    core = _core(model, kind, rec.T, ukf)
    nll = float(core(Qm.ravel(order="F"), Rm.ravel(order="F"), p, *rec.data())[0])
    return -nll if np.isfinite(nll) else -np.inf


def _check_common(model, estimator, alpha, beta, kappa):
    if not isinstance(model, Model):
        raise TypeError(f"model must be an estim.Model, got {type(model).__name__}")
    kind = as_choice(estimator, ESTIMATORS, "estimator")
    ukf = (as_float(alpha, "alpha", positive=True), as_float(beta, "beta"),
           as_float(kappa, "kappa"))
    return model, kind, ukf


class _Objective:
    """``-log L(theta)`` with its exact gradient and its Hessian for one record."""

    def __init__(self, model: Model, kind: str, T: int, ukf: tuple, par: _Parametrisation,
                 data: list, hessian: str):
        key = ("objective", kind, T, ukf if kind == "ukf" else None, par.key)
        cache = _CORES.setdefault(model, {})
        if key not in cache:
            core = _core(model, kind, T, ukf)
            theta = ca.MX.sym("theta", par.theta0.size)
            fixed = ca.MX.sym("fixed", par.fixed.size)
            args = [ca.MX.sym(n, core.size_in(i)) for i, n in enumerate(core.name_in())][3:]
            nll, eps = core(*par.unpack(theta, fixed), *args)
            inputs = [theta, fixed, *args]
            cache[key] = {
                "fg": ca.Function("nll_grad", inputs, [nll, ca.gradient(nll, theta)]),
                "whitened": ca.Function("whitened", inputs, [eps]),
                "hessian": lambda: ca.Function("nll_hess", inputs,  # built when first used
                                               [ca.hessian(nll, theta)[0]])}
        self._funs = cache[key]
        self._fg, self._eps = self._funs["fg"], self._funs["whitened"]
        self._data = [par.fixed, *data]
        # 1 / the number of measured outputs in the likelihood
        self.scale = 1.0 / max(1.0, float(np.sum(data[3] * data[5])))
        self.exact = hessian == "exact"
        self.evaluations = 0

    def __call__(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        self.evaluations += 1
        f, g = self._fg(theta, *self._data)
        f, g = float(f), np.asarray(g, dtype=float).ravel()
        if not (np.isfinite(f) and np.isfinite(g).all()):
            return np.inf, np.zeros_like(g)
        return f, g

    def hessian(self, theta: np.ndarray) -> np.ndarray:
        r"""The exact Hessian (AD, forward over reverse), or central differences of the
        exact gradient, :math:`(\nabla\ell(\theta + h e_i) - \nabla\ell(\theta - h e_i))
        / 2h` with :math:`h = 10^{-4}\max(1, |\theta_i|)`."""
        theta = np.asarray(theta, dtype=float)
        if self.exact:
            if callable(self._funs["hessian"]) and not isinstance(self._funs["hessian"],
                                                                  ca.Function):
                self._funs["hessian"] = self._funs["hessian"]()
            H = np.asarray(self._funs["hessian"](theta, *self._data), dtype=float)
        else:
            n = theta.size
            H = np.empty((n, n))
            for i in range(n):
                h = 1e-4 * max(1.0, abs(theta[i]))
                step = np.zeros(n)
                step[i] = h
                gp = np.asarray(self._fg(theta + step, *self._data)[1], dtype=float).ravel()
                gm = np.asarray(self._fg(theta - step, *self._data)[1], dtype=float).ravel()
                H[:, i] = (gp - gm) / (2 * h)
        return 0.5 * (H + H.T) if np.isfinite(H).all() else np.full_like(H, np.nan)

    def whitened(self, theta: np.ndarray) -> np.ndarray:
        return np.asarray(self._eps(theta, *self._data), dtype=float).T


def maximum_likelihood(model: Model, Y: ArrayLike, U: ArrayLike | None = None, *,
                       estimator: str = "ekf", Q0: ArrayLike | None = None,
                       R0: ArrayLike | None = None, x0: ArrayLike | None = None,
                       P0: ArrayLike | None = None,
                       params: Sequence[str] | Mapping[str, float] | None = None,
                       structure: str | Mapping[str, str] = "diagonal", starts: int = 5,
                       seed: int | None = 0, spread: float = 1.0, burn: int | None = None,
                       method: str = "BFGS", hessian: str = "differences", tol: float = 1e-8,
                       max_iter: int = 200,
                       alpha: float = 0.1, beta: float = 2.0, kappa: float = 0.0
                       ) -> TuningResult:
    r"""Noise covariances (and model parameters) that maximise the likelihood of a record.

    Minimises the prediction-error negative log-likelihood of the EKF (or UKF)

    .. math::
        \ell(\theta) = -\log L(\theta) = \tfrac12 \sum_{k=b}^{T-1} \left( \log\det S_k(\theta)
        + e_k(\theta)^\top S_k(\theta)^{-1} e_k(\theta) + m_k \log 2\pi \right)

    (see :func:`log_likelihood`) over :math:`\theta`: the noise covariances, kept
    positive definite by their parametrisation, and optionally model parameters.

    * ``structure="diagonal"``: :math:`\theta` holds the log-variances,
      :math:`Q = \operatorname{diag}(e^{\theta_1}, \dots)`; ``"full"``: the
      log-Cholesky factor, :math:`Q = LL^\top` with :math:`L_{ii} = e^{\theta_{ii}}`
      and :math:`L_{ij} = \theta_{ij}` below the diagonal (Pinheiro & Bates 1996);
      ``"scalar"``: :math:`Q = e^{\theta} I`; ``"fixed"``: held at ``Q0``. A dict
      ``{"Q": ..., "R": ...}`` sets each matrix's structure.
    * The filter recursion over the whole record is one compiled CasADi graph (the
      filter step scanned with ``mapaccum``, built once per model, filter and record
      length), so :math:`\nabla\ell` is exact (algorithmic differentiation through
      every step); :math:`\nabla^2\ell` is its central differences, or exact by AD
      (``hessian``). Each start runs scipy's BFGS with the exact
      gradient (on :math:`\ell` per measured output, whose steps are of order one
      whatever the record's length) into the basin of Newton's method; the best optimum
      is then polished by Newton steps with the Hessian and a backtracking line search,
      and declared converged when the Hessian is positive definite and the gain a Newton
      step still predicts, :math:`\frac12 \nabla\ell^\top (\nabla^2\ell)^{-1}
      \nabla\ell`, is below ``tol`` (or the rounding level of :math:`\ell`).
    * Multi-start: the first start is ``Q0, R0`` (and the parameters' starts), the
      others perturb the noise parameters by :math:`\mathcal N(0, \text{spread}^2)` on
      the log scale (seeded); the best optimum is returned.
    * Standard errors: the inverse observed information
      :math:`\operatorname{cov}\hat\theta \approx \nabla^2\ell(\hat\theta)^{-1}`, taken to
      the entries of ``Q``, ``R`` by the delta method,
      :math:`\operatorname{cov} g(\hat\theta) \approx J \nabla^2\ell^{-1} J^\top`,
      :math:`J = \partial g / \partial\theta`.

    Parameters
    ----------
    model : Model
    Y : (T, ny) array
        Measurements, NaN where missing (``T >= 2``).
    U : (T, nu) or (T-1, nu) array, optional
        Inputs as :func:`~estim.replay` takes them.
    estimator : {"ekf", "ukf"}
        The filter whose likelihood is maximised.
    Q0, R0 : float, vector of variances or matrix, optional
        Starting covariances (and the values held by ``"fixed"``). Default: ``R0`` half
        the sample variance of each output, ``Q0`` :math:`10^{-2}` times the diagonal of
        ``P0``.
    x0, P0 : optional
        Prior of the first state, as for the filters; default the approximate diffuse
        prior :math:`x_0 = 0`, :math:`P_0 = 10^6 I`.
    params : list of str or dict, optional
        Model parameters estimated along, by name (starting at the model's values), or
        ``{name: start}``.
    structure : {"diagonal", "full", "scalar", "fixed"} or dict
        Parametrisation of ``Q`` and ``R``.
    starts : int
        Number of starts (>= 1); one when nothing is perturbed (every covariance
        ``"fixed"``, or ``spread=0``).
    seed : int, optional
        Seed of the perturbed starts.
    spread : float
        Standard deviation of the perturbations of the log-variances (natural log).
    burn : int, optional
        Number of first samples whose terms are left out of the likelihood. Default 0,
        or ``nx`` with the diffuse prior (statsmodels' ``loglikelihood_burn``).
    method : str
        The scipy.optimize.minimize method of each start: ``"BFGS"`` (default),
        ``"L-BFGS-B"``, ``"CG"``, ``"TNC"``, ``"SLSQP"`` (exact gradient, then the Newton
        polish), or ``"trust-exact"``, ``"trust-krylov"``, ``"trust-ncg"``,
        ``"trust-constr"``, ``"Newton-CG"``, ``"dogleg"`` (the Hessian at every
        iteration, no polish).
    hessian : {"differences", "exact"}
        The Hessian of the polish and of the standard errors: central differences of the
        exact gradient (:math:`2 n_\theta` gradients; they agree with the exact Hessian to
        about :math:`10^{-9}`), or ``"exact"``, by algorithmic differentiation (forward
        over reverse through the scan), whose graph takes longer to build than a fit of a
        short record lasts (0.14 s at 100 samples, 0.8 s at 1000, 1.3 s at 2000; once per
        model and record length).
    tol : float
        The largest gain of :math:`\log L` a Newton step may still predict at a
        converged optimum (and the gradient tolerance ``gtol`` of the Hessian methods,
        on :math:`\ell` per measured output).
    max_iter : int
        Iterations per start.
    alpha, beta, kappa : float
        The UKF's sigma-point parameters.

    Returns
    -------
    TuningResult
        ``method="maximum likelihood"``, ``Q``, ``R``, ``params``, ``stderr`` (NaN for
        entries the structure holds fixed), ``check`` (the innovations of the filter with
        the estimates), ``objective`` :math:`\ell(\hat\theta)`, and ``details`` with
        ``"starts"`` (each start's objective), ``"iterations"`` (per start),
        ``"polish_iterations"``, ``"evaluations"`` (of :math:`\ell` and its gradient),
        ``"theta"``, ``"covariance"`` (of :math:`\hat\theta`), ``"log_likelihood"``,
        ``"compile_time"`` and ``"fit_time"`` (seconds).

    Notes
    -----
    The likelihood assumes Gaussian noises, independent in time, and (for a nonlinear
    model) that the filter's innovations are close to Gaussian with covariance
    :math:`S_k`; the standard errors are asymptotic (large :math:`T`, an interior
    optimum). A variance whose estimate runs to zero (the likelihood largest without that
    noise) has a log going to :math:`-\infty`: the status then starts with
    ``"boundary: "``, names the entry, and its standard errors are NaN.

    References
    ----------
    F. C. Schweppe, "Evaluation of likelihood functions for Gaussian signals", IEEE
    Trans. Inf. Theory 11(1), 1965; R. K. Mehra, "On the identification of variances
    and adaptive Kalman filtering", IEEE Trans. Autom. Control 15(2), 1970;
    J. Durbin, S. J. Koopman, *Time Series Analysis by State Space Methods*, 2nd ed.,
    Oxford 2012, ch. 7; J. C. Pinheiro, D. M. Bates, "Unconstrained parametrizations for
    variance-covariance matrices", Statistics and Computing 6, 1996.
    """
    t_start = time.perf_counter()
    model, kind, ukf = _check_common(model, estimator, alpha, beta, kappa)
    rec = _Record(model, Y, U, x0, P0, burn)
    structures = _structures(structure)
    starts = as_int(starts, "starts", minimum=1)
    seed = as_seed(seed)
    spread = as_float(spread, "spread", minimum=0.0)
    tol = as_float(tol, "tol", positive=True)
    max_iter = as_int(max_iter, "max_iter", minimum=1)
    method = _check_method(method)
    hessian = as_choice(hessian, ("differences", "exact"), "hessian")
    spec = _params_spec(model, params)
    for k, v in spec.items():
        if not np.isfinite(v):
            raise ValueError(f"params[{k!r}] needs a finite start")
    if R0 is None:
        var = np.array([np.nanvar(rec.Y[i][rec.measured[:, i]]) for i in range(model.ny)])
        R0 = np.maximum(0.5 * var, 1e-12)
    if Q0 is None:
        Q0 = 1e-2 * np.diag(rec.P0)
    Q0 = as_covariance(Q0, model.nx, "Q0", definite=False)
    R0 = as_covariance(R0, model.ny, "R0", definite=True)
    if structures["Q"] == "fixed" and structures["R"] == "fixed" and not spec:
        raise ValueError("nothing to estimate: structure holds Q and R fixed and params is "
                         "empty")
    par = _Parametrisation(model, structures, Q0, R0, spec)

    t0 = time.perf_counter()
    obj = _Objective(model, kind, rec.T, ukf, par, rec.data(), hessian)
    f0 = obj(par.theta0)  # the first evaluation builds the derivative graphs
    compile_time = time.perf_counter() - t0

    rng = np.random.default_rng(seed)
    thetas = [par.theta0]
    for _ in range(starts - 1 if par.n_noise and spread > 0 else 0):  # else all the same
        th = par.theta0.copy()
        th[:par.n_noise] += spread * rng.standard_normal(par.n_noise)
        thetas.append(th)
    runs = []
    for th in thetas:
        if th is par.theta0 and not np.isfinite(f0[0]):
            runs.append(None)
            continue
        # quasi-Newton to the basin of Newton's method, which the polish then finishes
        res = _minimize(obj, th, method, tol if method in _HESSIAN_METHODS else
                        max(tol, 1e-5), max_iter)
        runs.append(res if np.isfinite(res.fun) else None)
    good = [i for i, r in enumerate(runs) if r is not None]
    if not good:
        raise ValueError("the filter breaks down (a non-finite likelihood) at every start: "
                         "check Q0, R0, x0, P0 and the model")
    best = min(good, key=lambda i: runs[i].fun)
    res = runs[best]
    polish, H = 0, None
    theta = np.asarray(res.x, dtype=float)
    if method not in _HESSIAN_METHODS:  # Newton steps with the Hessian from the best
        theta, H, polish = _newton(obj, theta, tol, max_iter)
        if H is None:  # not positive definite on the way: a trust region copes
            fine = _minimize(obj, theta, "trust-exact", tol, max_iter)
            polish += int(fine.nit)
            if np.isfinite(fine.fun) and fine.fun <= obj(theta)[0]:
                theta = np.asarray(fine.x, dtype=float)
    nll, grad = obj(theta)

    H = obj.hessian(theta) if H is None else H
    values, J = par.entries(theta)
    cov_theta = np.full_like(H, np.nan)
    decrement = np.inf  # the gain of log L a Newton step predicts
    definite = bool(np.isfinite(H).all() and np.linalg.eigvalsh(H)[0] > 0)
    if definite:
        cov_theta = np.linalg.inv(H)
        decrement = 0.5 * float(grad @ cov_theta @ grad)
    success = definite and decrement <= _limit(tol, nll)
    if success:
        status = "ok"
    elif not definite:
        status = ("not converged: the Hessian of -log L is not positive definite at the "
                  "optimum (a variance on its boundary, or parameters the record does not "
                  "identify): no standard errors")
    else:
        status = (f"not converged: a Newton step would still gain {decrement:.3g} in log L "
                  f"({res.message})")
    cov_entries = J @ cov_theta @ J.T
    se = np.sqrt(np.abs(np.diag(cov_entries)))
    free = np.abs(J).sum(axis=1) > 0
    se = np.where(free, se, np.nan)
    nx, ny = model.nx, model.ny
    # variances run to zero: a log far below the others of its matrix, or one the
    # likelihood hardly bounds (standard error of the log above 3, a factor 20)
    boundary = []
    for idx, name, i, power in par.logs:
        top = max(pw * theta[j] for j, other, _, pw in par.logs if other == name)
        loose = np.isfinite(cov_theta[idx, idx]) and np.sqrt(cov_theta[idx, idx]) > 3
        if power * theta[idx] < top - np.log(1e8) or loose:
            n = nx if name == "Q" else ny
            rows = range(n) if i is None else [i]
            offset = 0 if name == "Q" else nx * nx
            for row in rows:
                for col in range(n):
                    se[offset + row + n * col] = se[offset + col + n * row] = np.nan
            boundary.append(f"{name}[{i},{i}]" if i is not None else name)
    if boundary and status == "ok":
        status = (f"boundary: {', '.join(boundary)} "
                  f"{'runs' if len(boundary) == 1 else 'run'} to zero (the likelihood is "
                  f"largest without that noise); no standard error")
    q, r, _ = par.matrices(theta)
    Qh, Rh = q.reshape(nx, nx, order="F"), r.reshape(ny, ny, order="F")
    Qh, Rh = 0.5 * (Qh + Qh.T), 0.5 * (Rh + Rh.T)
    stderr = {"Q": se[:nx * nx].reshape(nx, nx, order="F"),
              "R": se[nx * nx:nx * nx + ny * ny].reshape(ny, ny, order="F"),
              "params": {k: float(s) for k, s in zip(par.names, se[nx * nx + ny * ny:],
                                                     strict=True)}}
    est_params = {k: float(v) for k, v in zip(par.names, values[nx * nx + ny * ny:].ravel(),
                                              strict=True)}
    eps = obj.whitened(theta)
    eps[~rec.measured] = np.nan
    eps[:rec.burn] = np.nan
    details = {
        "starts": [float(r.fun) if r is not None else float("inf") for r in runs],
        "best_start": best,
        "iterations": [int(getattr(r, "nit", 0)) if r is not None else 0 for r in runs],
        "evaluations": obj.evaluations,
        "theta": theta,
        "covariance": cov_theta,
        "gradient": grad,
        "log_likelihood": -float(nll),
        "optimizer": method,
        "hessian": "exact" if obj.exact else "differences",
        "polish_iterations": polish,
        "newton_decrement": decrement,
        "message": str(res.message),
        "compile_time": compile_time,
        "fit_time": time.perf_counter() - t_start,
        "structure": structures,
        "burn": rec.burn,
        "estimator": kind,
    }
    return TuningResult(method="maximum likelihood", Q=Qh, R=Rh, params=est_params,
                        stderr=stderr, check=innovation_check(eps), objective=float(nll),
                        success=success, status=status, details=details)


_HESSIAN_METHODS = ("trust-exact", "trust-krylov", "trust-ncg", "trust-constr", "Newton-CG",
                    "dogleg")
_GRADIENT_METHODS = ("L-BFGS-B", "BFGS", "CG", "TNC", "SLSQP")


def _limit(tol: float, f: float) -> float:
    """The Newton gain below which an optimum is converged: ``tol``, or the rounding
    level of the objective's value when that is larger."""
    return max(tol, 1e3 * np.finfo(float).eps * abs(f))


def _newton(obj: _Objective, theta: np.ndarray, tol: float, max_iter: int
            ) -> tuple[np.ndarray, np.ndarray | None, int]:
    r"""Newton steps :math:`d = -H^{-1} g` with a backtracking (Armijo) line search until
    the predicted gain :math:`\frac12 g^\top H^{-1} g` is below the limit of
    :func:`_limit`. Returns the point, its Hessian (None if it is not positive
    definite, NaN if it is not finite) and the number of steps."""
    f, g = obj(theta)
    for it in range(max_iter):
        H = obj.hessian(theta)
        if not np.isfinite(H).all():  # the filter breaks down next to theta: stop here
            return theta, H, it
        try:
            L = np.linalg.cholesky(H)
        except np.linalg.LinAlgError:
            return theta, None, it
        d = -np.linalg.solve(L.T, np.linalg.solve(L, g))
        gain = -0.5 * float(g @ d)
        if gain <= _limit(tol, f):  # converged: the last full step costs one evaluation
            fn, _ = obj(theta + d)
            return (theta + d if fn <= f + _limit(tol, f) else theta), H, it
        t = 1.0
        while t > 1e-10:
            fn, gn = obj(theta + t * d)
            if fn <= f - 1e-4 * t * 2 * gain:
                break
            t *= 0.5
        else:
            return theta, H, it
        theta, f, g = theta + t * d, fn, gn
    return theta, obj.hessian(theta), max_iter


def _minimize(obj: _Objective, theta: np.ndarray, method: str, tol: float, max_iter: int):
    """One local minimisation with scipy, the exact gradient (and Hessian where used)."""
    from scipy.optimize import minimize

    options: dict = {"maxiter": max_iter, "gtol": tol}
    if method == "L-BFGS-B":  # no stop on a small relative decrease: flat likelihoods
        options["ftol"] = 1e-15
    elif method == "TNC":
        options = {"maxfun": 20 * max_iter, "gtol": tol, "ftol": 0.0}
    elif method == "Newton-CG":
        options = {"maxiter": max_iter, "xtol": tol}
    elif method == "SLSQP":
        options = {"maxiter": max_iter, "ftol": tol}
    c = obj.scale  # -log L per measured output: O(1) values and steps for any record

    def fun(th):
        f, g = obj(th)
        return f * c, g * c

    hess = (lambda th: obj.hessian(th) * c) if method in _HESSIAN_METHODS else None
    res = minimize(fun, theta, jac=True, hess=hess, method=method, options=options)
    res.fun = res.fun / c
    return res


def _check_method(method) -> str:
    return as_choice(method, _HESSIAN_METHODS + _GRADIENT_METHODS, "method")
