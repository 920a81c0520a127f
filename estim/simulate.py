r"""The one closed loop every estimator shares.

At sample :math:`k` (time :math:`t_k = k\,dt`):

1. measure :math:`y_k = h(x_k, u_{k-1}) + v_k`, :math:`v_k \sim N(0, R)`
   (NaN where an output is missing);
2. the estimator steps: :math:`\hat x_k = \text{est.step}(y_k, u_{k-1})`;
3. the input :math:`u_k` comes from the signal, or from the controller fed
   with :math:`\hat x_k` (or the true state);
4. the plant moves: :math:`x_{k+1} = F(x_k, u_k) + w_k`,
   :math:`w_k \sim N(0, Q)`, clipped to the bounds where asked.

All noise is drawn up front from ``numpy.random.default_rng(seed)``, so the
same seed gives the same noise whatever the estimator does.
"""

from __future__ import annotations

import numpy as np

from estim._fast import FastFunction
from estim._validate import as_covariance, as_vector
from estim.estimators.base import Estimator
from estim.log import Log
from estim.model import Model
from estim.scenarios import Scenario


def _sqrt_psd(M: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L L^T = M`` for a positive semi-definite ``M``."""
    if M.size == 0:
        return M
    if np.allclose(M, np.diag(np.diag(M))):
        return np.diag(np.sqrt(np.maximum(np.diag(M), 0.0)))
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.maximum(w, 0.0))


class _Recorder:
    """What an estimator reports at every step, stored time-major, and the final Log."""

    def __init__(self, T: int, nx: int):
        self.x_hat = np.empty((T, nx))
        self.P = np.full((T, nx, nx), np.nan)
        self.solve_time = np.empty(T)
        self.iterations = np.zeros(T, dtype=int)
        self.success = np.ones(T, dtype=bool)
        self.nis = np.full(T, np.nan)
        self.cost = np.full(T, np.nan)
        self.status = np.empty(T, dtype=object)

    def record(self, k: int, x_hat: np.ndarray, info) -> None:
        self.x_hat[k] = x_hat
        if info.P is not None:
            self.P[k] = info.P
        self.solve_time[k] = info.solve_time
        self.iterations[k] = info.iterations
        self.success[k] = info.success
        self.nis[k] = info.nis
        self.cost[k] = info.cost
        self.status[k] = info.status

    def log(self, model: Model, estimator: Estimator, t, x, y, u) -> Log:
        log = Log(model.state_names, model.output_names, model.input_names, dt=model.dt,
                  estimator=getattr(estimator, "name", type(estimator).__name__),
                  output_state=output_state_map(model), model_name=model.name)
        for key, arr in (("t", t), ("x", x), ("y", y), ("u", u), ("x_hat", self.x_hat),
                         ("P", self.P), ("solve_time", self.solve_time),
                         ("status", self.status.astype(str)), ("iterations", self.iterations),
                         ("success", self.success), ("nis", self.nis), ("cost", self.cost)):
            log.set(key, arr)
        return log


def output_state_map(model: Model) -> dict[int, int]:
    """Outputs that equal one state, ``y_i = x_j``: ``{i: j}`` (for plots)."""
    rng = np.random.default_rng(12345)
    out = {}
    pts = [rng.standard_normal(model.nx) for _ in range(2)]
    u = np.zeros(model.nu)
    ys = [model.H(x, u, model.p).full().ravel() for x in pts]
    Cs = [model.H_x(x, u, model.p).full() for x in pts]
    for i in range(model.ny):
        row = Cs[0][i]
        nz = np.flatnonzero(row)
        if len(nz) == 1 and row[nz[0]] == 1.0 and np.array_equal(Cs[1][i], row):
            j = int(nz[0])
            if all(abs(y[i] - x[j]) < 1e-12 for y, x in zip(ys, pts, strict=True)):
                out[i] = j
    return out


def simulate(target: Scenario | Model, estimator: Estimator, seed: int | None = 0, *,
             x0=None, n_steps: int | None = None, Q=None, R=None, inputs=None,
             controller=None, feedback: str | None = None, clip: bool | None = None,
             missing=None, plant_changes=None) -> Log:
    """Run ``estimator`` in closed loop on a scenario (or a bare model) and log everything.

    Parameters
    ----------
    target : Scenario or Model
        With a scenario, every keyword below defaults to the scenario's value.
        With a bare model, ``x0``, ``n_steps``, ``Q`` and ``R`` are required.
    estimator : Estimator
        Any estimator built for this model; it is :meth:`~Estimator.reset`
        first, so one instance can be simulated many times.
    seed : int or None
        Seed of the noise (and of missing-data draws).
    x0 : (nx,) array
        True initial state.
    n_steps : int
        Number of samples T.
    Q : float, (nx,) or (nx, nx)
        Process-noise covariance of the plant (zero allowed).
    R : float, (ny,) or (ny, ny)
        Measurement-noise covariance.
    inputs : (T, nu) array or callable ``t -> u``, optional
        Open-loop input.
    controller : callable ``(t, x) -> u``, optional
        Feedback law (mutually exclusive with ``inputs``).
    feedback : {"estimate", "truth"}
        What the controller sees.
    clip : bool
        Clip the true state to ``[model.lower, model.upper]`` after each step.
    missing : float, (T, ny) bool array or None
        Outputs not measured: a probability per output and sample, or a mask.
    plant_changes : list of (time, {param: value}), optional
        Plant parameter changes from the given time on.

    Returns
    -------
    Log
        Time-major arrays; see :class:`~estim.Log`.
    """
    if not isinstance(estimator, Estimator):
        raise TypeError(f"estimator must be an estim estimator, got {type(estimator).__name__}")
    if isinstance(target, Scenario):
        sc = target
        model = sc.model
        x0 = sc.x0 if x0 is None else x0
        n_steps = sc.n_steps if n_steps is None else n_steps
        Q = sc.Q if Q is None else Q
        R = sc.R if R is None else R
        if inputs is None and controller is None:
            inputs, controller = sc.inputs, sc.controller
        feedback = sc.feedback if feedback is None else feedback
        clip = sc.clip if clip is None else clip
        plant_changes = sc.plant_changes if plant_changes is None else plant_changes
    elif isinstance(target, Model):
        model = target
        for name, val in (("x0", x0), ("n_steps", n_steps), ("Q", Q), ("R", R)):
            if val is None:
                raise ValueError(f"{name} is required when simulating a bare Model")
    else:
        raise TypeError(f"target must be a Scenario or a Model, got {type(target).__name__}")
    if estimator.model.nx != model.nx or estimator.model.ny != model.ny \
            or estimator.model.nu != model.nu:
        raise ValueError("estimator was built for a model of other dimensions than the plant")
    if not isinstance(n_steps, int | np.integer) or n_steps < 1:
        raise ValueError(f"n_steps must be a positive integer, got {n_steps!r}")
    if inputs is not None and controller is not None:
        raise ValueError("give inputs= or controller=, not both")
    feedback = feedback or "estimate"
    if feedback not in ("estimate", "truth"):
        raise ValueError(f"feedback must be 'estimate' or 'truth', got {feedback!r}")
    nx, nu, ny, T = model.nx, model.nu, model.ny, int(n_steps)
    x = as_vector(x0, nx, "x0")
    Lq = _sqrt_psd(as_covariance(Q, nx, "Q", definite=False))
    Lr = _sqrt_psd(as_covariance(R, ny, "R", definite=False))
    U = _input_table(inputs, T, nu, model.dt)
    miss = _missing(missing, T, ny, seed)

    noise_rng = np.random.default_rng(seed)
    V = noise_rng.standard_normal((T, ny)) @ Lr.T
    W = noise_rng.standard_normal((T, nx)) @ Lq.T
    changes = sorted(plant_changes or [], key=lambda c: c[0])
    params = [model.with_params(**c[1]).p for c in changes]

    F, H = FastFunction(model.F), FastFunction(model.H)
    ts = np.arange(T) * model.dt
    X = np.empty((T, nx))
    Y = np.empty((T, ny))
    Uk = np.zeros((T, nu))
    rec = _Recorder(T, nx)

    estimator.reset()
    u_prev = np.zeros(nu) if U is None else U[0].copy()
    p = model.p
    next_change = 0
    for k in range(T):
        t = ts[k]
        while next_change < len(changes) and t >= changes[next_change][0] - 1e-12:
            p = params[next_change]
            next_change += 1
        y = H(x, u_prev, p)[0] + V[k]
        if miss is not None:
            y[miss[k]] = np.nan
        X[k], Y[k] = x, y
        xh = estimator.step(y.copy(), u_prev)
        rec.record(k, xh, estimator.info)
        if U is not None:
            u = U[k]
        elif controller is not None:
            u = as_vector(controller(t, x if feedback == "truth" else xh), nu, "controller output")
        else:
            u = u_prev
        Uk[k] = u
        x = F(x, u, p)[0] + W[k]
        if clip:
            x = np.minimum(np.maximum(x, model.lower), model.upper)
        if not np.isfinite(x).all():
            raise FloatingPointError(f"the plant state became non-finite at step {k} (t={t:g})")
        u_prev = u.copy()
    return rec.log(model, estimator, ts, X, Y, Uk)


def replay(estimator: Estimator, y, u=None, x=None, t=None) -> Log:
    """Run an estimator over recorded data (e.g. measurements from an experiment).

    Parameters
    ----------
    estimator : Estimator
        Reset first.
    y : (T, ny) array
        Measurements, NaN where missing.
    u : (T, nu) array, optional
        ``u[k]`` is the input applied after sample ``k`` (so ``u[k-1]`` is
        passed with ``y[k]``, as in :func:`simulate`); zero if omitted.
    x : (T, nx) array, optional
        The true states, where known (for :func:`~estim.rmse` and plots).
    t : (T,) array, optional
        Sample times (default ``k * model.dt``).

    Returns
    -------
    Log
        As from :func:`simulate`; ``x`` is NaN where not given.
    """
    if not isinstance(estimator, Estimator):
        raise TypeError(f"estimator must be an estim estimator, got {type(estimator).__name__}")
    model = estimator.model
    Y = np.asarray(y, dtype=float)
    if Y.ndim == 1 and model.ny == 1:
        Y = Y[:, None]
    if Y.ndim != 2 or Y.shape[1] != model.ny:
        raise ValueError(f"y must have shape (T, {model.ny}), got {Y.shape}")
    T = Y.shape[0]
    U = np.zeros((T, model.nu)) if u is None else _input_table(u, T, model.nu, model.dt)
    X = np.full((T, model.nx), np.nan) if x is None else np.asarray(x, dtype=float)
    if X.shape != (T, model.nx):
        raise ValueError(f"x must have shape ({T}, {model.nx}), got {X.shape}")
    ts = np.arange(T) * model.dt if t is None else np.asarray(t, dtype=float)
    if ts.shape != (T,):
        raise ValueError(f"t must have shape ({T},), got {ts.shape}")
    rec = _Recorder(T, model.nx)
    estimator.reset()
    for k in range(T):
        x_hat = estimator.step(Y[k].copy(), U[k - 1] if k else np.zeros(model.nu))
        rec.record(k, x_hat, estimator.info)
    return rec.log(model, estimator, ts, X, Y, U)


def _input_table(inputs, T: int, nu: int, dt: float) -> np.ndarray | None:
    if inputs is None:
        return None
    if callable(inputs):
        return np.array([as_vector(inputs(k * dt), nu, "inputs(t)") for k in range(T)]
                        ).reshape(T, nu)
    U = np.asarray(inputs, dtype=float)
    if U.ndim == 1 and nu == 1:
        U = U[:, None]
    if U.shape != (T, nu):
        raise ValueError(f"inputs must have shape ({T}, {nu}) = (n_steps, nu), got {U.shape}")
    if not np.isfinite(U).all():
        raise ValueError("inputs must be finite")
    return U


def _missing(missing, T: int, ny: int, seed) -> np.ndarray | None:
    if missing is None:
        return None
    if np.isscalar(missing):
        prob = float(missing)
        if not 0.0 <= prob < 1.0:
            raise ValueError(f"missing as a probability must be in [0, 1), got {missing!r}")
        rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
        return rng.random((T, ny)) < prob
    mask = np.asarray(missing, dtype=bool)
    if mask.shape != (T, ny):
        raise ValueError(f"missing must be a probability or a ({T}, {ny}) bool mask, "
                         f"got shape {mask.shape}")
    return mask
