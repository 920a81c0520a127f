"""Linear-Gaussian systems on which the covariance form of a Kalman filter loses
definiteness, for the square-root form's tests and benchmark.

Each case is a linear model ``x+ = A(u) x + w``, ``y = C x + v`` with ``w ~ N(0, Q)``
(``Q`` may be singular), ``v ~ N(0, R)``, the initial state drawn from the filter's
prior ``N(x0, P0)``; ``A(u) = A + sum_j u_j A_j`` with a known input record ``U``
where the case has inputs (unknown constant gains of known inputs, carried as states:
the model is linear in the state for the given inputs). The filters are then exact:
at every sample the normalised estimation error squared ``e_k' P_k^-1 e_k`` is
chi-square with ``nx`` degrees of freedom, independent across runs.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np
from scipy import linalg, stats

import estim


@dataclass
class Case:
    name: str
    A: np.ndarray
    C: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    T: int
    #: ``(nu, nx, nx)``: the input matrices ``A_j`` of ``A(u)``, None without inputs.
    Au: np.ndarray | None = None
    #: ``(T - 1, nu)``: the known inputs, ``U[k]`` acting from sample k to k+1.
    U: np.ndarray | None = None

    def model(self) -> estim.Model:
        Ad, Cd = ca.DM(self.A), ca.DM(self.C)
        if self.Au is None:
            return estim.Model(states=len(self.A), outputs=len(self.C),
                               dynamics=lambda x, u, p: Ad @ x,
                               output=lambda x, u, p: Cd @ x, name=self.name)
        Aj = [ca.DM(M) for M in self.Au]
        return estim.Model(states=len(self.A), outputs=len(self.C), inputs=len(Aj),
                           dynamics=lambda x, u, p: (Ad + sum(u[j] * M for j, M in
                                                            enumerate(Aj))) @ x,
                           output=lambda x, u, p: Cd @ x, name=self.name)

    def transition(self, k: int) -> np.ndarray:
        """``A(U[k])``, the transition from sample k to k+1."""
        if self.Au is None:
            return self.A
        return self.A + np.tensordot(self.U[k], self.Au, axes=1)

    def record(self, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """The true states ``(T, nx)`` and measurements ``(T, ny)`` of one run."""
        rng = np.random.default_rng(seed)
        nx, ny = len(self.A), len(self.C)
        GQ, GR, G0 = (_root(M) for M in (self.Q, self.R, self.P0))
        x = self.x0 + G0 @ rng.standard_normal(nx)
        X, Y = np.empty((self.T, nx)), np.empty((self.T, ny))
        for k in range(self.T):
            X[k] = x
            Y[k] = self.C @ x + GR @ rng.standard_normal(ny)
            if k + 1 < self.T:
                x = self.transition(k) @ x + GQ @ rng.standard_normal(nx)
        return X, Y

    def records(self, n: int, seed: int = 0, T: int | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """The true states ``(n, T, nx)`` and measurements ``(n, T, ny)`` of ``n`` runs
        at once (one random stream for all, drawn across the runs at every sample: not
        the runs of :meth:`record`); ``T`` defaults to the case's."""
        T = self.T if T is None else T
        rng = np.random.default_rng(seed)
        nx, ny = len(self.A), len(self.C)
        GQ, GR, G0 = (_root(M) for M in (self.Q, self.R, self.P0))
        x = self.x0 + rng.standard_normal((n, nx)) @ G0.T
        X, Y = np.empty((n, T, nx)), np.empty((n, T, ny))
        block = max(1, 2 ** 20 // (n * (nx + ny)))  # noise drawn a block of samples at once
        AT = self.A.T
        for k0 in range(0, T, block):
            k1 = min(T, k0 + block)
            V = rng.standard_normal((k1 - k0, n, ny)) @ GR.T
            W = rng.standard_normal((k1 - k0, n, nx)) @ GQ.T
            for k in range(k0, k1):
                X[:, k] = x
                if k + 1 < T:
                    x = x @ (AT if self.Au is None else self.transition(k).T) + W[k - k0]
            Y[:, k0:k1] = X[:, k0:k1] @ self.C.T + V.transpose(1, 0, 2)
        return X, Y


def _root(M: np.ndarray) -> np.ndarray:
    """A square root of a semi-definite matrix, for drawing its noise."""
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.maximum(w, 0.0))


def cases(T: int = 40) -> list[Case]:
    """The three hard cases, ``T`` samples each: a constant-velocity target whose position
    is measured almost exactly (``R = 1e-12``, ``Q = 0``, ``P0 = 1e6 I``), a badly scaled
    state (components of about 1e6 and 1e-6, measured through their sum) and a joint
    state/parameter estimate (a constant acceleration with noise variance 1e-20)."""
    dt = 1.0
    cv = np.array([[1.0, dt], [0.0, 1.0]])
    exact = Case("nearly exact position", cv, np.array([[1.0, 0.0]]), np.zeros((2, 2)),
                 np.array([[1e-12]]), np.zeros(2), 1e6 * np.eye(2), T)
    scaled = Case("badly scaled state", np.diag([0.99, 0.99]), np.array([[1.0, 1e12]]),
                  np.diag([1e6, 1e-18]), np.array([[1e-6]]), np.zeros(2),
                  np.diag([1e12, 1e-12]), T)
    # position, velocity and a constant acceleration (the parameter), position measured
    A3 = np.array([[1.0, dt, dt ** 2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    joint = Case("joint parameter", A3, np.array([[1.0, 0.0, 0.0]]),
                 np.diag([0.0, 0.0, 1e-20]), np.array([[1e-12]]), np.zeros(3),
                 np.diag([1e6, 1e6, 1e2]), T)
    return [exact, scaled, joint]


def run(case: Case, cls: type, form: str, seed: int, **options) -> dict:
    r"""One run of ``cls(..., form=form)`` step by step: the failed steps (not
    ``info.success``), the steps whose covariance is not positive definite, the NEES of
    every sample (NaN where the covariance is not definite) and the mean seconds of a
    step. The NEES :math:`\|L^{-1} e\|^2` uses the Cholesky factor of ``info.P`` in
    the covariance form and the filter's own factor in the square-root form (forming
    :math:`P = S S^\top` first would square its condition number)."""
    X, Y = case.record(seed)
    nx = len(case.A)
    est = cls(case.model(), Q=case.Q, R=case.R, x0=case.x0, P0=case.P0, form=form,
              **options)
    failed = indefinite = 0
    nees = np.full(case.T, np.nan)
    seconds = 0.0
    for k in range(case.T):
        t0 = time.perf_counter()
        x = est.step(Y[k], None if case.U is None or k == 0 else case.U[k - 1])
        seconds += time.perf_counter() - t0
        info = est.info
        failed += not info.success
        if form == "sqrt":
            L = est._s[nx:].reshape(nx, nx, order="F")  # the filter state [x; vec(S)]
            definite = bool(np.all(np.diag(L) > 0))
        else:
            try:
                L, definite = np.linalg.cholesky(info.P), True
            except np.linalg.LinAlgError:
                definite = False
        if not definite:
            indefinite += 1
            continue
        z = linalg.solve_triangular(L, x - X[k], lower=True)
        nees[k] = z @ z
    return {"failed": failed, "indefinite": indefinite, "nees": nees,
            "seconds": seconds / case.T}


def nees_band(n_runs: int, nx: int, n_samples: int, level: float = 0.95
              ) -> tuple[float, float]:
    """The band the NEES summed over ``n_runs`` independent runs stays in at every one
    of ``n_samples`` samples with probability at least ``level``: at each sample that sum
    is chi-square with ``n_runs * nx`` degrees of freedom, and each sample's two-sided
    interval has the tail ``(1 - level) / n_samples`` (Bonferroni: the estimation errors
    of successive samples are correlated, so the samples are not independent)."""
    dof = n_runs * nx
    tail = (1 - level) / n_samples / 2
    return float(stats.chi2.ppf(tail, dof)), float(stats.chi2.ppf(1 - tail, dof))


def suite_cases(T: int = 100) -> list[Case]:
    r"""The failure suite, ``T`` samples each (the long run: ``10 T``; pass its ``T``
    with :func:`dataclasses.replace`):

    * ``R = 1e-12 I``: the constant-velocity target of :func:`cases` whose position is
      measured almost exactly (``Q = 0``, ``P0 = 1e6 I``);
    * rank-deficient ``Q``: a random walk and two constants (``Q = diag(1, 0, 0)``)
      measured through ``y = [x1 + x2, x2 + x3]`` with ``R = 1e-12 I``: the constants'
      variances fall towards 0 while the walk's stays near 1;
    * five parameters: a damped cart whose velocity is driven by five known inputs
      through five unknown constant gains, the gains carried as states with the
      random-walk variances ``1e-14 .. 1e-12`` (the plant's gains walk with the same
      variances, so that the filters are exact), position and velocity measured with
      ``R = 1e-12 I``, ``P0 = 1e4 I``;
    * long run: a target whose velocity reverts to 0 (``v+ = 0.99 v``) under white-noise
      acceleration (``Q`` of rank one, variance ``1e-6``), its position measured with
      ``R = 1e-12``, ``P0 = 1e6 I``. With a free velocity (a constant-velocity target)
      the position of a long run grows to about 1e9, 1e15 times its standard deviation,
      where double precision cannot hold the estimate to its own uncertainty (the
      UKF's sigma points lose every digit of their spread): the reverting velocity
      keeps the position within about 1e5;
    * badly scaled state: the case of :func:`cases` (components of about 1e6 and 1e-6).
    """
    dt = 1.0
    exact, scaled, _ = cases(T)
    walk = Case("rank-deficient Q", np.eye(3), np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]]),
                np.diag([1.0, 0.0, 0.0]), 1e-12 * np.eye(2), np.zeros(3), 1e2 * np.eye(3), T)
    A = np.zeros((7, 7))
    A[0, :2] = [1.0, dt]
    A[1, 1] = 0.9
    A[2:, 2:] = np.eye(5)
    Au = np.zeros((5, 7, 7))
    Au[np.arange(5), 1, 2 + np.arange(5)] = dt
    gains = Case("five parameters", A, np.eye(2, 7),
                 np.diag([0.0, 0.0, *np.logspace(-14, -12, 5)]), 1e-12 * np.eye(2),
                 np.zeros(7), 1e4 * np.eye(7), T, Au=Au,
                 U=np.random.default_rng(12345).standard_normal((T - 1, 5)))
    g = np.array([dt ** 2 / 2, dt])
    long = Case("long run", np.array([[1.0, dt], [0.0, 0.99]]), np.array([[1.0, 0.0]]),
                1e-6 * np.outer(g, g), np.array([[1e-12]]), np.zeros(2), 1e6 * np.eye(2),
                10 * T)
    return [dataclasses.replace(exact, name="R = 1e-12 I"), walk, gains, long, scaled]


def failed(status: tuple[str, ...]) -> int:
    """The failed steps of a record's statuses (kept predictions and re-anchorings)."""
    return sum(s.startswith("failed") for s in status)


def scan_function(est: estim.Estimator, Y: np.ndarray, U: np.ndarray | None
                  ) -> tuple:
    """The compiled scan that :meth:`~estim.EKF.filter` runs over a record, and its
    arguments after a :meth:`~estim.EKF.reset`: ``fun(*args)`` gives the filter states
    ``[x; vec(P)]`` (``[x; vec(S)]`` in the square-root form) of every sample side by
    side, valid up to the first failed step (where ``filter`` goes on step by step).
    For a model with held inputs, without ``t``."""
    m = est.model
    T = len(Y)
    held = np.zeros((T, m.nu)) if U is None else np.vstack([U, np.zeros((1, m.nu))])
    W = m.step_transitions(np.vstack([np.zeros((1, m.nu)), held[:-1]]))
    est.reset()
    return est._whole_record(T), [est._s.copy(), Y.T, W.T, est._tun.copy(),
                                  est._P0_data.copy()]


def scan(est: estim.Estimator, Y: np.ndarray, U: np.ndarray | None) -> np.ndarray:
    """The filter states ``(T, nx + nx^2)`` of a record by :func:`scan_function`."""
    fun, args = scan_function(est, Y, U)
    return np.array(fun(*args)[0]).reshape(len(Y), -1)


def factors(est: estim.Estimator, Y: np.ndarray, U: np.ndarray | None) -> np.ndarray:
    """The factors ``S_k`` ``(T, nx, nx)`` of a square-root filter over a record, from
    :func:`scan` (:meth:`~estim.EKF.filter` returns ``S_k S_k^T``: where the condition
    number of ``P`` reaches 1/eps, forming it loses the factor)."""
    nx, T = est.model.nx, len(Y)
    return scan(est, Y, U)[:, nx:].reshape(T, nx, nx).transpose(0, 2, 1)  # column-major


def cholesky(P: np.ndarray) -> np.ndarray:
    """Lower Cholesky factors of a stack ``(..., n, n)``, NaN columns from the first
    pivot that is not positive (a matrix that is not positive definite)."""
    n = P.shape[-1]
    L = np.zeros_like(P)
    for j in range(n):
        d = P[..., j, j] - np.sum(L[..., j, :j] ** 2, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            L[..., j, j] = np.where(d > 0, np.sqrt(np.where(d > 0, d, 1.0)), np.nan)
            L[..., j + 1:, j] = (P[..., j + 1:, j] - np.einsum(
                "...ik,...k->...i", L[..., j + 1:, :j], L[..., j, :j])) / L[..., j, j, None]
    return L


def normalised_errors(L: np.ndarray, e: np.ndarray) -> np.ndarray:
    r"""The NEES :math:`\|L_k^{-1} e_k\|^2` of every sample, by forward substitution
    (``L (..., n, n)`` lower, ``e (..., n)``); NaN where ``L`` is not finite or has a
    diagonal entry that is not positive."""
    n = e.shape[-1]
    z = np.zeros_like(e)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        for i in range(n):
            z[..., i] = (e[..., i] - np.sum(L[..., i, :i] * z[..., :i], axis=-1)) / L[..., i, i]
    ok = np.isfinite(L).all(axis=(-1, -2)) & (np.diagonal(L, axis1=-2, axis2=-1) > 0).all(-1)
    return np.where(ok, np.sum(z * z, axis=-1), np.nan)


def filter_runs(case: Case, cls: type, form: str, n: int, seed: int = 0,
                records: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    r"""``n`` runs of ``cls(..., form=form).filter`` on the records of
    :meth:`Case.records` (or ``records``, ``(X, Y)`` of that shape): the failed steps
    of every run (:func:`failed`), the NEES ``(n, T)`` (NaN where the covariance is not
    positive definite: its Cholesky factor in the covariance form, the filter's own
    factor in the square-root form, see :func:`factors`), the seconds of every
    ``filter`` call, after one call that builds the record's Function, and the
    filter."""
    X, Y = case.records(n, seed) if records is None else records
    est = cls(case.model(), Q=case.Q, R=case.R, x0=case.x0, P0=case.P0, form=form)
    est.filter(Y[0], case.U)  # builds the whole-record Function of this length
    fails, seconds = np.zeros(n, dtype=int), np.zeros(n)
    nees = np.full(Y.shape[:2], np.nan)
    for i in range(n):
        t0 = time.perf_counter()
        res = est.filter(Y[i], case.U)
        seconds[i] = time.perf_counter() - t0
        fails[i] = failed(res.status)
        if form == "sqrt":
            L = factors(est, Y[i], case.U)
            n_ok = next((k for k, s in enumerate(res.status) if s.startswith("failed")),
                        len(Y[i]))
            L[n_ok:] = cholesky(res.P[n_ok:])
        else:
            L = cholesky(res.P)
        nees[i] = normalised_errors(L, res.x - X[i])
    return {"failed": fails, "nees": nees, "seconds": seconds, "estimator": est}


def step_runs(case: Case, cls: type, form: str, n: int, seed: int = 0,
              records: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """What :func:`filter_runs` gives, from ``step`` at every sample instead of one
    ``filter`` call per record (for records too long to build the whole-record
    Function of): the seconds are those of the steps, the filter state
    ``[x; vec(P)]`` (``[x; vec(S)]``) of every sample is read after its step."""
    X, Y = case.records(n, seed) if records is None else records
    est = cls(case.model(), Q=case.Q, R=case.R, x0=case.x0, P0=case.P0, form=form)
    T, nx = Y.shape[1], len(case.A)
    fails, seconds = np.zeros(n, dtype=int), np.zeros(n)
    nees = np.full(Y.shape[:2], np.nan)
    states = np.empty((T, nx + nx * nx))
    for i in range(n):
        est.reset()
        steps, bad = est.step, 0
        t0 = time.perf_counter()
        for k in range(T):
            steps(Y[i, k], None if case.U is None or k == 0 else case.U[k - 1])
            bad += est.info.status.startswith("failed")
            states[k] = est._s  # the filter state after the step
        seconds[i] = time.perf_counter() - t0
        fails[i] = bad
        M = states[:, nx:].reshape(T, nx, nx).transpose(0, 2, 1)  # column-major
        L = M if form == "sqrt" else cholesky(M)
        nees[i] = normalised_errors(L, states[:, :nx] - X[i])
    return {"failed": fails, "nees": nees, "seconds": seconds, "estimator": est}


def mean_nees_band(n_runs: int, nx: int, level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` band of the NEES averaged over ``n_runs`` independent
    runs and over time: :math:`\\chi^2(n_\\text{runs} n_x) / n_\\text{runs}`, the band of
    one sample's average over the runs. The time average has the same mean and at most
    the variance of one sample (the samples of a run are correlated, the runs not), so
    the band is conservative."""
    tail = (1 - level) / 2
    dof = n_runs * nx
    return (float(stats.chi2.ppf(tail, dof)) / n_runs,
            float(stats.chi2.ppf(1 - tail, dof)) / n_runs)
