r"""The one closed loop every estimator shares.

At sample :math:`k` (time :math:`t_k = k\,dt`):

1. measure :math:`y_k = h(x_k, u_{k-1}) + v_k`, :math:`v_k \sim N(0, R)`
   (NaN where an output is missing);
2. the estimator steps: :math:`\hat x_k = \text{est.step}(y_k, u_{k-1})`;
3. the input :math:`u_k` comes from the signal, or from the controller fed
   with :math:`\hat x_k` (or the true state);
4. the plant moves: :math:`x_{k+1} = F(x_k, u_k) + w_k`,
   :math:`w_k \sim N(0, Q)`, clipped to the bounds where asked.

A model whose inputs are interpolated between samples (``hold="foh"``) measures
:math:`y_k = h(x_k, u_k)`, gives :math:`u_k` (the input *at* sample k) to the
estimator and moves with the input going linearly from :math:`u_k` to
:math:`u_{k+1}`; its inputs are a signal known in advance.

All noise is drawn up front from ``numpy.random.default_rng(seed)``, so the
same seed gives the same noise whatever the estimator does.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import overload

import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._locate import first_located
from estim._manifold import NP, unit_quaternions
from estim._validate import (
    _numeric_array,
    as_bool,
    as_covariance,
    as_float,
    as_input_table,
    as_int,
    as_intervals,
    as_record,
    as_seed,
    as_vector,
    by_name,
    check_keywords,
)
from estim.estimators.base import Estimator, StepInfo
from estim.exceptions import EstimationWarning
from estim.experiment import Scenario, check_plant_changes, check_sampling, silent_outputs
from estim.log import Log
from estim.model import Model

#: :func:`simulate` and :func:`replay` warn when more than this fraction of the steps failed.
FAILED_FRACTION = 0.02


def _sqrt_psd(M: np.ndarray) -> np.ndarray:
    """A factor ``L`` with ``L L^T = M`` for a positive semi-definite ``M``."""
    if M.size == 0:
        return M
    if np.allclose(M, np.diag(np.diag(M))):
        return np.diag(np.sqrt(np.maximum(np.diag(M), 0.0)))
    w, V = np.linalg.eigh(M)
    return V * np.sqrt(np.maximum(w, 0.0))


def draw_noise(seeds: Sequence[int | None], T: int, Lr: np.ndarray, Lq: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """The measurement and process noise of each seed's run: ``V (S, T, ny)`` and
    ``W (S, T, nx)``, standard normal draws of ``numpy.random.default_rng(seed)`` (first
    ``V``'s, then ``W``'s) times the square roots ``Lr``, ``Lq`` of ``R`` and ``Q``. By a
    diagonal factor the product is taken elementwise: the same numbers as the matrix
    product, each entry having one nonzero term."""
    ny, nx = len(Lr), len(Lq)
    V, W = np.empty((len(seeds), T, ny)), np.empty((len(seeds), T, nx))
    for i, s in enumerate(seeds):
        rng = np.random.default_rng(s)
        rng.standard_normal(out=V[i])
        rng.standard_normal(out=W[i])

    def scaled(Z, L):
        return Z * np.diag(L) if np.array_equal(L, np.diag(np.diag(L))) else Z @ L.T

    return scaled(V, Lr), scaled(W, Lq)


class _PlantOnly:
    """What stands for the estimator of a plant-only run (``simulate(..., None)``): no
    estimate (NaN) and the status ``"no estimator"``."""

    name = "none"

    def __init__(self, model: Model):
        self.model = model
        self.info = StepInfo(status="no estimator")
        self._nan = np.full(model.nx, np.nan)  # the recorder copies it

    def reset(self) -> None:
        """Nothing to reset."""

    def step(self, y: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        return self._nan


class _Recorder:
    """What an estimator reports at every step, stored time-major, and the final Log."""

    def __init__(self, T: int, nx: int, nd: int | None = None):
        self.x_hat = np.empty((T, nx))
        nd = nx if nd is None else nd  # covariances in the tangent space (ndx)
        self.P = np.full((T, nd, nd), np.nan)
        self.solve_time = np.empty(T)
        self.iterations = np.zeros(T, dtype=int)
        self.success = np.ones(T, dtype=bool)
        self.nis = np.full(T, np.nan)
        self.cost = np.full(T, np.nan)
        self.status = np.empty(T, dtype=object)
        self.extra = np.empty(T, dtype=object)
        self.done = 0  # steps recorded completely

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
        self.extra[k] = info.extra

    def log(self, model: Model, estimator: Estimator | _PlantOnly, t, x, y, u) -> Log:
        """The Log of the steps recorded so far (all of them after a complete run)."""
        n = self.done
        log = Log(model.state_names, model.output_names, model.input_names, dt=model.dt,
                  estimator=getattr(estimator, "name", type(estimator).__name__),
                  output_state=output_state_map(model), model_name=model.name,
                  time_unit=model.time_unit)
        if not model.manifold.euclidean_states:
            log.manifold = model.manifold
        for key, arr in (("t", t), ("x", x), ("y", y), ("u", u), ("x_hat", self.x_hat),
                         ("P", self.P), ("solve_time", self.solve_time),
                         ("status", self.status.astype(str).astype(object)),  # Python str
                         ("iterations", self.iterations),
                         ("success", self.success), ("nis", self.nis), ("cost", self.cost),
                         ("diagnostics", self.extra)):
            log.set(key, arr[:n])
        if model.nz:  # the algebraic states of the truth and of the estimates
            for key, X in (("z", x[:n]), ("z_hat", self.x_hat[:n])):
                log.set(key, algebraic_states(model, X, u[:n]))
        return log

    @contextmanager
    def running(self, model: Model, estimator: Estimator | _PlantOnly, t, x, y, u
                ) -> Iterator[None]:
        """The loop's context: any exception leaving it carries the log of the completed
        steps as ``exc.log``."""
        try:
            yield
        except BaseException as exc:
            try:
                log = self.log(model, estimator, t, x, y, u)
            except Exception:  # noqa: BLE001 - never mask the original error
                raise exc from None
            # any exception carries it: an attribute its class does not declare
            setattr(exc, "log", log)  # noqa: B010
            if hasattr(exc, "add_note"):
                exc.add_note(f"estim: the log of the {self.done} steps completed before "
                             f"this is exc.log")
            raise

    def finish(self, model: Model, estimator: Estimator | _PlantOnly, t, x, y, u,
               warn: bool) -> Log:
        """The log of the run, with an :class:`EstimationWarning` (``warn``) when more than
        :data:`FAILED_FRACTION` of the steps failed."""
        log = self.log(model, estimator, t, x, y, u)
        if warn and log.failures > FAILED_FRACTION * len(log):
            name = getattr(estimator, "name", type(estimator).__name__)
            k = int(np.flatnonzero(~log.success)[0])
            first = str(log.status[k])
            hint = ""
            if "non-finite" in first and "(not finite:" not in first:
                where = _located(model, log, k)
                hint = (f" (not finite: {where})" if where else
                        " (the model or its Jacobian is not finite at the estimates: a sqrt, "
                        "log or division at the edge of its domain?)")
            warnings.warn(f"{name} on {log.model_name or 'the model'}: {log.problems()}; "
                          f"see log.status{hint}", EstimationWarning,
                          stacklevel=4)  # this method, simulate, its argument check, caller
        return log


def dimensions_message(what: str, est_model: Model, plant: Model) -> str:
    """Why an estimator's model and the plant do not fit, with the sizes and the fix."""
    def sizes(m: Model) -> str:
        return f"nx={m.nx} {m.state_names}, ny={m.ny}, nu={m.nu}"

    hint = ""
    extra = [n for n in est_model.state_names if n not in plant.state_names]
    if est_model.nx > plant.nx and extra:
        hint = (f"; the estimator's model has the states {extra} the plant lacks (augmented "
                f"parameters or disturbances?): simulate the plant with that model too, its "
                f"truth for them in x0 (Scenario(model=augmented, x0=[..., values]))")
    return (f"{what} was built for a model of other dimensions than the plant: "
            f"{sizes(est_model)} against the plant's {sizes(plant)}{hint}")


def _located(model: Model, log: Log, k: int) -> str:
    """What of the model is not finite around the first failed step ``k``: at the
    estimate before it (the transition into ``k``) or at ``k`` itself
    (:func:`estim._locate.first_located`); empty if nothing is found."""
    def point(j: int) -> tuple:
        u = log.u[j] if j < len(log.u) else np.zeros(model.nu)
        return log.x_hat[j], model.transition(None, u), u

    if model.sampled:
        return ""
    return first_located(model, (point(j) for j in (k - 1, k) if j >= 0))


def algebraic_states(model: Model, X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``Z(x_k, u)`` of a model with algebraic states at every row of ``X (T, nx)``, with
    the input the output sees at sample ``k`` (``U[k-1]``, zero at the first; ``U[k]``
    for a sampled-input model), ``(T, nz)``; NaN where ``x_k`` is not finite or the
    Newton solve fails."""
    T = len(X)
    assert model.Z is not None  # a model with algebraic states
    if T == 0:
        return np.empty((0, model.nz))
    Um = U if model.sampled else np.vstack([np.zeros((1, model.nu)), U[:-1]])
    ok = np.isfinite(X).all(axis=1)
    out = np.full((T, model.nz), np.nan)
    if ok.any():
        Z = model.Z.map(int(ok.sum()))(X[ok].T, Um[ok].T, model.p)
        out[ok] = np.asarray(Z, dtype=float).reshape(model.nz, -1).T
    return out


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


@check_keywords
def simulate(target: Scenario | Model, estimator: Estimator | None, seed: int | None = 0, *,
             x0: ArrayLike | None = None, n_steps: int | None = None,
             Q: ArrayLike | None = None, R: ArrayLike | None = None,
             inputs: ArrayLike | Callable[[float], ArrayLike] | None = None,
             controller: Callable[[float, np.ndarray], ArrayLike] | None = None,
             feedback: str | None = None, clip: bool | None = None,
             missing: float | ArrayLike | None = None,
             plant_changes: Sequence[tuple[float, Mapping[str, float]]] | None = None,
             sampling: Mapping[str, int | tuple[int, int]] | None = None,
             warn: bool = True) -> Log:
    """Run ``estimator`` in closed loop on a scenario (or a bare model) and log everything.

    Parameters
    ----------
    target : Scenario or Model
        With a scenario, every keyword below defaults to the scenario's value.
        With a bare model, ``x0``, ``n_steps``, ``Q`` and ``R`` are required.
    estimator : Estimator or None
        Any estimator built for this model; it is :meth:`~Estimator.reset`
        first, so one instance can be simulated many times. None simulates the
        plant alone (``log.x_hat`` is NaN, the status ``"no estimator"``): a
        controller then needs ``feedback="truth"``.
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
    sampling : dict, optional
        Outputs reported at their own rates, ``{output: every}`` or ``{output:
        (every, first)}`` (see :class:`~estim.Scenario`); NaN at the other samples,
        on top of ``missing``.
    warn : bool
        Emit an :class:`EstimationWarning` when more than :data:`FAILED_FRACTION`
        (2 %) of the steps failed.

    Returns
    -------
    Log
        Time-major arrays; see :class:`~estim.Log`.

    Raises
    ------
    FloatingPointError
        The plant's state or output became non-finite (a plant that blows up).
        Like any exception raised during the run (by the estimator, the
        controller, or a ``KeyboardInterrupt``), it carries the log of the steps
        completed before it as ``exc.log``.
    """
    if estimator is not None and not isinstance(estimator, Estimator):
        raise TypeError(f"estimator must be an estim estimator or None, "
                        f"got {type(estimator).__name__}")
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
        sampling = sc.sampling if sampling is None else sampling
    elif isinstance(target, Model):
        model = target
        for name, val in (("x0", x0), ("n_steps", n_steps), ("Q", Q), ("R", R)):
            if val is None:
                raise ValueError(f"{name} is required when simulating a bare Model")
    else:
        raise TypeError(f"target must be a Scenario or a Model, got {type(target).__name__}")
    est = _PlantOnly(model) if estimator is None else estimator
    if est.model.nx != model.nx or est.model.ny != model.ny or est.model.nu != model.nu:
        raise ValueError(dimensions_message("estimator", est.model, model))
    n_steps, seed, clip, plant_changes = _check_simulate(
        model, n_steps, seed, clip, inputs, controller, missing, plant_changes)
    warn = as_bool(warn, "warn")
    if inputs is not None and controller is not None:
        raise ValueError("give inputs= or controller=, not both")
    if model.sampled and controller is not None:
        raise ValueError("a model with hold='foh' interpolates its inputs between samples, "
                         "so it needs them in advance: give inputs=, not a controller")
    feedback = "estimate" if feedback is None else feedback
    if not isinstance(feedback, str) or feedback not in ("estimate", "truth"):
        raise ValueError(f"feedback must be 'estimate' or 'truth', got {feedback!r}")
    if estimator is None and controller is not None and feedback != "truth":
        raise ValueError("estimator=None simulates the plant alone: its controller needs "
                         "feedback='truth'")
    nx, nu, ny, T = model.nx, model.nu, model.ny, int(n_steps)
    x = unit_quaternions(model.manifold, as_vector(x0, nx, "x0"), "x0")
    Lq = _sqrt_psd(as_covariance(Q, model.ndx, "Q", definite=False))
    Lr = _sqrt_psd(as_covariance(R, ny, "R", definite=False))
    U = _input_table(inputs, T, model)
    miss = _missing(missing, T, ny, seed)
    silent = silent_outputs(check_sampling(sampling, model), model, T)
    if silent is not None:
        miss = silent if miss is None else miss | silent

    V, W = (a[0] for a in draw_noise([seed], T, Lr, Lq))
    changes = sorted(plant_changes or [], key=lambda c: c[0])
    params = [model.with_params(**c[1]).p for c in changes]

    F, H = FastFunction(model.F), FastFunction(model.H)
    ts = np.arange(T) * model.dt
    X = np.empty((T, nx))
    Y = np.empty((T, ny))
    Uk = np.zeros((T, nu))
    rec = _Recorder(T, nx, model.ndx)
    manifold = None if model.manifold.euclidean_states else model.manifold

    est.reset()
    u_prev = np.zeros(nu) if U is None else U[0].copy()
    if model.sampled and U is None:
        U = np.zeros((T, nu))
    sampled = U if model.sampled else None  # the inputs at the samples (hold="foh")
    p = model.p
    next_change = 0
    with rec.running(model, est, ts, X, Y, Uk):
        for k in range(T):
            t = ts[k]
            while next_change < len(changes) and t >= changes[next_change][0] - 1e-12:
                p = params[next_change]
                next_change += 1
            if sampled is not None:  # the input at this sample (held before, for "zoh")
                u_prev = sampled[k]
            y = H(x, u_prev, p)[0] + V[k]
            if np.isinf(y).any():
                raise FloatingPointError(f"the plant output became infinite at step {k} "
                                         f"(t={t:g}): y = {y}")
            if miss is not None:
                y[miss[k]] = np.nan
            X[k], Y[k] = x, y
            xh = est.step(y.copy(), u_prev)
            rec.record(k, xh, est.info)
            if U is not None:
                u = U[k]
            elif controller is not None:
                u = as_vector(controller(t, x if feedback == "truth" else xh), nu,
                              "controller output")
            else:
                u = u_prev
            Uk[k] = u
            rec.done = k + 1
            w = model.transition(u, sampled[min(k + 1, T - 1)]) if sampled is not None \
                else model.transition(None, u)
            # the noise in the tangent space: x+ = F(x) (+) w on a manifold
            x = F(x, w, p)[0] + W[k] if manifold is None else \
                manifold.retract(F(x, w, p)[0], W[k], NP)
            if clip:
                x = np.minimum(np.maximum(x, model.lower), model.upper)
            if not np.isfinite(x).all():
                raise FloatingPointError(f"the plant state became non-finite after step {k} "
                                         f"(t={t:g})")
            u_prev = u.copy()
    return rec.finish(model, est, ts, X, Y, Uk, warn)


@check_keywords
def replay(estimator: Estimator, y: ArrayLike, u: ArrayLike | None = None,
           x: ArrayLike | None = None, t: ArrayLike | None = None, *,
           warn: bool = True) -> Log:
    """Run an estimator over recorded data (e.g. measurements from an experiment).

    Parameters
    ----------
    estimator : Estimator
        Reset first.
    y : (T, ny) array
        Measurements, NaN where missing.
    u : (T, nu) array, optional
        ``u[k]`` is the input applied after sample ``k`` (so ``u[k-1]`` is
        passed with ``y[k]``, as in :func:`simulate`); for a model with
        ``hold="foh"`` the input's value at sample ``k`` (passed with ``y[k]``).
        Required for a model with inputs (``u=0``: zero inputs, on purpose).
    x : (T, nx) array, optional
        The true states, where known (for :func:`~estim.rmse` and plots).
    t : (T,) array, optional
        Sample times (default ``k * model.dt``). A model built with
        ``variable_dt=True`` integrates over each interval ``t[k] - t[k-1]``; a
        continuous model with a fixed ``dt`` refuses times at another spacing.
    warn : bool
        Emit an :class:`EstimationWarning` when more than 2 % of the steps failed.

    Returns
    -------
    Log
        As from :func:`simulate`; ``x`` is NaN where not given.

    Notes
    -----
    Every array is checked before the first step: ``y`` may hold NaN (a missing
    output) but not ±inf, which is refused with the row it is in. An exception
    raised during the run carries the log of the completed steps as ``exc.log``.
    """
    if not isinstance(estimator, Estimator):
        raise TypeError(f"estimator must be an estim estimator, got {type(estimator).__name__}")
    model = estimator.model
    value = u if isinstance(u, int | float) and not isinstance(u, bool) else None  # u=0
    Y, dts = _check_replay(model, y, None if value is not None else u, x, t)  # (variable_dt)
    warn = as_bool(warn, "warn")
    T = Y.shape[0]
    if value is not None:
        u = np.full((T, model.nu), float(value))
    elif u is None and model.nu:
        raise ValueError(f"u is required: {model.name} has nu = {model.nu} input(s) "
                         f"{model.input_names}; give u ({T}, {model.nu}), or u=0 to replay "
                         f"with zero inputs on purpose")
    U = np.zeros((T, model.nu)) if u is None else _input_table(u, T, model)
    X = np.full((T, model.nx), np.nan) if x is None else \
        np.asarray(by_name(x, model.state_names, "x", "states"), dtype=float)
    ts = np.arange(T) * model.dt if t is None else np.asarray(t, dtype=float)
    rec = _Recorder(T, model.nx, model.ndx)
    estimator.reset()
    with rec.running(model, estimator, ts, X, Y, U):
        for k in range(T):
            # the input since the previous sample (held), or at this one (sampled models)
            u = U[k] if model.sampled else U[k - 1] if k else np.zeros(model.nu)
            dt = None if dts is None or k == 0 else float(dts[k - 1])
            x_hat = estimator.step(Y[k].copy(), u, dt=dt)
            rec.record(k, x_hat, estimator.info)
            rec.done = k + 1
    return rec.finish(model, estimator, ts, X, Y, U, warn)


@overload
def _input_table(inputs: None, T: int, model: Model) -> None: ...


@overload
def _input_table(inputs: ArrayLike | Callable[[float], ArrayLike], T: int, model: Model
                 ) -> np.ndarray: ...


def _input_table(inputs: ArrayLike | Callable[[float], ArrayLike] | None, T: int,
                 model: Model) -> np.ndarray | None:
    """The inputs ``(T, nu)`` of a run: a table, or a function of time evaluated at
    the samples (None without inputs)."""
    if inputs is None:
        return None
    nu = model.nu
    if callable(inputs):
        return np.array([as_vector(inputs(k * model.dt), nu, "inputs(t)") for k in range(T)]
                        ).reshape(T, nu)
    return as_input_table(inputs, T, nu, names=model.input_names)


def _missing(missing, T: int, ny: int, seed) -> np.ndarray | None:
    if missing is None:
        return None
    if np.ndim(missing) == 0:  # a probability, as _check_simulate tells them apart
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


def _check_simulate(model: Model, n_steps, seed, clip, inputs, controller, missing,
                    plant_changes):
    """The arguments of :func:`simulate` that are not checked where they are used."""
    n_steps = as_int(n_steps, "n_steps", minimum=1)
    seed = as_seed(seed)
    clip = as_bool(clip, "clip", allow_none=True)
    if controller is not None and not callable(controller):
        raise TypeError(f"controller must be callable (t, x) -> u, "
                        f"got {type(controller).__name__}")
    if missing is not None:
        if isinstance(missing, bool | np.bool_) or np.ndim(missing) == 0:
            as_float(missing, "missing", expected="a probability in [0, 1) or a bool mask")
        else:
            mask = np.asarray(missing)
            if mask.dtype != bool and not (mask.dtype.kind in "iu"
                                           and np.isin(mask, (0, 1)).all()):
                raise TypeError(f"missing must be a probability or a (T, ny) bool mask, "
                                f"got an array of {mask.dtype}")
    return n_steps, seed, clip, check_plant_changes(plant_changes, model)


def _check_replay(model: Model, y, u, x, t) -> tuple[np.ndarray, np.ndarray | None]:
    """Check every array of :func:`replay` before the first step; return ``y`` as (T, ny)
    and the intervals of ``t`` for a ``variable_dt`` model (see :func:`as_intervals`)."""
    Y = as_record(y, model.ny, "y", names=model.output_names, what="outputs")
    T = Y.shape[0]
    if u is not None and not callable(u):
        U = as_record(u, model.nu, "u", missing=False, names=model.input_names,
                      what="inputs")
        if U.shape != (T, model.nu):
            raise ValueError(f"u must have shape ({T}, {model.nu}) = (T, nu), got {U.shape}")
    if x is not None:
        X = _numeric_array(by_name(x, model.state_names, "x", "states"), "x")
        if X.shape != (T, model.nx):
            raise ValueError(f"x must have shape ({T}, {model.nx}), got {X.shape}")
        if np.isinf(X).any():
            raise ValueError("x must not contain inf (use NaN where the state is unknown)")
    return Y, as_intervals(t, T, model)
