r"""The :class:`Model`: a system's equations, written once.

A model is either continuous,

.. math:: \dot x = f(x, u; p), \qquad y = h(x, u; p),

discretised over one sample ``dt`` by a fixed-step integrator (RK4 by
default) with the input held constant (zero-order hold), or discrete,

.. math:: x_{k+1} = F(x_k, u_k; p), \qquad y_k = h(x_k, u_k; p).

The equations are CasADi expressions built once at construction. Every
estimator, the simulator and the observability analysis use the resulting
CasADi Functions and their algorithmic-differentiation Jacobians.
"""

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._fast import FastFunction
from estim._validate import (
    as_bool,
    as_bounds,
    as_choice,
    as_float,
    as_int,
    as_names,
    as_vector,
    check_keywords,
)

Equation = Callable[[ca.SX, ca.SX, Mapping[str, ca.SX]], object]

INTEGRATORS = ("rk4", "euler", "cvodes")


def _as_column(expr, size: int, argname: str) -> ca.SX:
    """Turn what a user equation returned into a ``(size, 1)`` expression."""
    if isinstance(expr, list | tuple):
        expr = ca.vertcat(*expr)
    elif isinstance(expr, np.ndarray):
        expr = ca.SX(expr) if expr.dtype != object else ca.vertcat(*expr.ravel().tolist())
    elif isinstance(expr, int | float):
        expr = ca.SX(expr)
    if not isinstance(expr, ca.SX | ca.MX | ca.DM):
        raise TypeError(
            f"{argname} must return a CasADi expression or a list of them, "
            f"got {type(expr).__name__}"
        )
    if expr.shape == (1, size) and size > 1:
        expr = expr.T
    if expr.shape != (size, 1):
        raise ValueError(f"{argname} must return {size} entries (a ({size}, 1) column), "
                         f"got shape {expr.shape}")
    return ca.SX(expr) if isinstance(expr, ca.DM) else expr


def _check_constants(expr, names: Sequence[str], argname: str) -> None:
    """Refuse entries of an equation that are a constant NaN or inf.

    Such an entry is what ``math.sqrt(x[0])`` and friends produce: the math
    module converts the symbol to a float (NaN) instead of building an
    expression. Only constant entries are checked; an expression that is NaN
    in parts of the state space is legitimate.
    """
    if not isinstance(expr, ca.SX):
        return
    for i, label in enumerate(names):
        entry = expr[i]
        if entry.is_constant():
            value = float(ca.evalf(entry))
            if not np.isfinite(value):
                raise ValueError(
                    f"{argname} entry {i} ({label}) is the constant {value}: use casadi "
                    f"functions (ca.sqrt, ca.exp, ...) or numpy ufuncs on symbols, not the "
                    f"math module")


def _input_at(u, s: float):
    """The input at the fraction ``s`` of the sample: ``u(s)`` for an interpolated
    input (a callable), else ``u`` (held)."""
    return u(s) if callable(u) else u


def rk4_step(f: Callable, x, u, p, h: float, substeps: int = 1):
    r"""Classic fourth-order Runge-Kutta over ``substeps`` steps of size ``h / substeps``.

    .. math::
        k_1 = f(x, u_0), k_2 = f(x + \tfrac{h}{2} k_1, u_{1/2}),
        k_3 = f(x + \tfrac{h}{2} k_2, u_{1/2}), k_4 = f(x + h k_3, u_1), \quad
        x^+ = x + \tfrac{h}{6}(k_1 + 2k_2 + 2k_3 + k_4)

    ``u`` is the input held over the sample, or a callable giving it at a fraction
    ``s`` of the sample (:math:`u_s = u(s)`, e.g. linear between two samples).
    """
    dt = h / substeps
    for i in range(substeps):
        s0, sm, s1 = i / substeps, (i + 0.5) / substeps, (i + 1) / substeps
        um = _input_at(u, sm)
        k1 = f(x, _input_at(u, s0), p)
        k2 = f(x + dt / 2 * k1, um, p)
        k3 = f(x + dt / 2 * k2, um, p)
        k4 = f(x + dt * k3, _input_at(u, s1), p)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def euler_step(f: Callable, x, u, p, h: float, substeps: int = 1):
    r"""Explicit Euler, :math:`x^+ = x + h f(x, u)`, over ``substeps`` steps (``u``
    held, or a callable of the fraction of the sample as for :func:`rk4_step`)."""
    dt = h / substeps
    for i in range(substeps):
        x = x + dt * f(x, _input_at(u, i / substeps), p)
    return x


HOLDS = ("zoh", "foh")


class Model:
    r"""A dynamical system with outputs, parameters and state bounds.

    Parameters
    ----------
    states : list of str or int
        State names (or their number, giving ``x1, x2, ...``).
    outputs : list of str or int
        Output names (or their number).
    ode : callable ``f(x, u, p)``, optional
        Continuous right-hand side :math:`\dot x = f(x, u; p)`. ``x`` is a
        ``(nx, 1)`` CasADi column, ``u`` a ``(nu, 1)`` column, ``p`` a dict
        mapping each parameter name to a CasADi symbol. Return a column or a
        list of ``nx`` expressions. Exactly one of ``ode``/``dynamics``.
    dynamics : callable ``F(x, u, p)``, optional
        Discrete map :math:`x_{k+1} = F(x_k, u_k; p)`.
    output : callable ``h(x, u, p)``
        Output map returning ``ny`` expressions.
    dt : float
        Sample time. Required for ``ode``; defaults to 1 for ``dynamics``.
    inputs : list of str or int, optional
        Input names (or their number). Inputs are held over each sample.
    params : dict, optional
        Parameter names and nominal values. Inside the equations they are
        symbols, so :meth:`augment` can turn them into states and
        :meth:`with_params` can change them without rebuilding.
    integrator : {"rk4", "euler", "cvodes"}
        Discretisation of ``ode``: fixed-step RK4 (default), explicit Euler,
        or CasADi's adaptive CVODES (SUNDIALS) with tolerances 1e-10.
    substeps : int
        Fixed integrator steps per sample (rk4/euler).
    lower, upper : float, sequence or dict, optional
        State bounds (``-inf``/``inf`` where absent), used by MHE/FIE
        constraints, the clipped EKF and plant clipping.
    hold : {"zoh", "foh"} or dict, optional
        How a continuous model sees its inputs between samples. ``"zoh"``
        (default): held; the input given with a sample is the one that acted
        since the previous sample (``step(y_k, u_{k-1})``). ``"foh"``: linear
        between the input's values at consecutive samples (a first-order hold,
        the reconstruction of a sampled smooth signal); the input given with a
        sample is its value *at* that sample (``step(y_k, u_k)``), and the
        transition from sample k to k+1 integrates with ``u`` going from
        ``u_k`` to ``u_{k+1}``. A dict gives the hold per input name (then
        ``"zoh"`` inputs are held at their value at the start of each sample);
        any ``"foh"`` input makes the model take inputs at the samples. Needs
        ``ode=``, and known inputs (not a feedback controller) in
        :func:`~estim.simulate`.
    variable_dt : bool
        The sample interval is data: each transition integrates over its own
        interval (irregular time stamps), given to ``est.step(y, u, dt=...)``,
        or as time stamps ``t`` to :func:`~estim.replay` and
        ``FullInformation.fit``; ``dt`` is the default interval. The transition's
        input ``w`` then ends with the interval (``nw`` is one more; see
        :meth:`transition`). Needs ``ode=``; the shooting observer does not take
        such a model.
    name : str
        Label for reprs and plots.
    time_unit : str
        Unit of time, for the time axes of plots (``"s"``, ``"min"``,
        ``"dimensionless"``; empty when unknown).

    Attributes
    ----------
    nx, nu, ny : int
        Dimensions.
    state_names, output_names, input_names, param_names : list of str
    p : (np,) array
        Current parameter values in ``param_names`` order.
    F, H : casadi.Function
        ``F(x, u, p) -> x_next`` and ``H(x, u, p) -> y``.
    F_x, H_x : casadi.Function
        Their Jacobians with respect to ``x`` (by algorithmic differentiation).
    f_c : casadi.Function or None
        The continuous right-hand side ``f(x, u, p)`` for continuous models.

    Examples
    --------
    >>> import casadi as ca, estim
    >>> vdp = estim.Model(
    ...     states=["x1", "x2"], outputs=["y1", "y2"],
    ...     ode=lambda x, u, p: ca.vertcat(x[1], p["mu"] * (1 - x[0]**2) * x[1] - x[0]),
    ...     output=lambda x, u, p: x, params={"mu": 1.0}, dt=0.1)
    >>> vdp.f([1.0, 0.0]).round(4)
    array([ 0.9951, -0.0973])
    """

    @check_keywords(owner="Model")
    def __init__(
        self,
        states: Sequence[str] | int,
        outputs: Sequence[str] | int,
        *,
        ode: Equation | None = None,
        dynamics: Equation | None = None,
        output: Equation | None = None,
        dt: float | None = None,
        inputs: Sequence[str] | int | None = None,
        params: Mapping[str, float] | None = None,
        integrator: str = "rk4",
        substeps: int = 1,
        lower: ArrayLike | None = None,
        upper: ArrayLike | None = None,
        name: str = "model",
        hold: str | Mapping[str, str] = "zoh",
        variable_dt: bool = False,
        time_unit: str = "",
    ):
        self.state_names = as_names(states, "states", "x")
        self.output_names = as_names(outputs, "outputs", "y")
        self.input_names = as_names(inputs, "inputs", "u")
        if not self.state_names:
            raise ValueError("states must name at least one state")
        if (ode is None) == (dynamics is None):
            raise ValueError("give exactly one of ode= (continuous) or dynamics= (discrete)")
        for argname, fn in (("ode", ode), ("dynamics", dynamics), ("output", output)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{argname} must be callable f(x, u, p), got {type(fn).__name__}")
        if output is None:
            raise ValueError("output= is required: a callable h(x, u, p)")
        as_choice(integrator, INTEGRATORS, "integrator")
        substeps = as_int(substeps, "substeps", minimum=1)
        if dt is None:
            if ode is not None:
                raise ValueError("dt is required for a continuous model (ode=)")
            dt = 1.0
        dt = as_float(dt, "dt", positive=True)
        if params is not None and not isinstance(params, Mapping):
            raise TypeError(f"params must be a dict {{name: value}}, got {type(params).__name__}")
        params = dict(params or {})
        for key, val in params.items():
            if not isinstance(key, str):
                raise TypeError(f"params keys must be strings, got {key!r}")
            params[key] = as_float(val, f"params[{key!r}]")
        if not isinstance(name, str):
            raise TypeError(f"name must be a string, got {type(name).__name__}")
        clash = set(params) & set(self.state_names)
        if clash:
            raise ValueError(f"params and states share names {sorted(clash)}")

        self.name = name
        if not isinstance(time_unit, str):
            raise TypeError(f"time_unit must be a string, got {type(time_unit).__name__}")
        self.time_unit = time_unit
        self.dt = float(dt)
        self.integrator = integrator
        self.substeps = int(substeps)
        self.param_names = list(params)
        self.p = np.array([float(v) for v in params.values()])
        self.lower = as_bounds(lower, self.state_names, "lower", -np.inf)
        self.upper = as_bounds(upper, self.state_names, "upper", np.inf)
        if np.any(self.lower > self.upper):
            raise ValueError("lower must not exceed upper")
        self.augmented: dict[str, float] = {}
        self._ode, self._dynamics, self._output = ode, dynamics, output
        self.hold = self._holds(hold)
        if self.sampled and ode is None:
            raise ValueError("hold='foh' needs a continuous model (ode=): a discrete map "
                             "(dynamics=) already says what happens between samples")
        self.variable_dt = as_bool(variable_dt, "variable_dt")
        if self.variable_dt and ode is None:
            raise ValueError("variable_dt=True needs a continuous model (ode=): a discrete "
                             "map (dynamics=) has no sample interval to vary")
        self._build()

    def _holds(self, hold) -> dict[str, str]:
        """``hold`` as ``{input name: "zoh" or "foh"}``."""
        if isinstance(hold, str):
            return dict.fromkeys(self.input_names, as_choice(hold, HOLDS, "hold"))
        if not isinstance(hold, Mapping):
            raise TypeError(f"hold must be 'zoh', 'foh' or a dict {{input: hold}}, "
                            f"got {type(hold).__name__}")
        unknown = sorted(set(hold) - set(self.input_names))
        if unknown:
            raise ValueError(f"hold names unknown inputs {unknown}; inputs are "
                             f"{self.input_names}")
        return {n: as_choice(hold.get(n, "zoh"), HOLDS, f"hold[{n!r}]")
                for n in self.input_names}

    @property
    def sampled(self) -> bool:
        """True when some input is interpolated between samples (``hold="foh"``): the
        model then takes each input's value *at* the samples, and a transition needs
        the values at both ends (see :meth:`transition`)."""
        return "foh" in self.hold.values()

    @property
    def nw(self) -> int:
        """Length of a transition's input ``w`` (``F(x, w, p)``): ``nu``, or ``2 nu``
        (the values at both ends of the sample) for a sampled-input model, plus one
        (the interval) with ``variable_dt``."""
        return (2 * self.nu if self.sampled else self.nu) + int(self.variable_dt)

    def input_path(self, w: ca.SX | ca.MX, reverse: bool = False) -> Any:
        """The input along a transition whose input is ``w``: ``w`` itself (held), or
        for a sampled model a function of the fraction ``s`` of the sample, linear
        from the start value to the end value for ``"foh"`` inputs (``reverse``:
        from the end back to the start, for integrating backward in time)."""
        if not self.sampled:
            return w
        nu = self.nu
        ramp = ca.DM([float(self.hold[n] == "foh") for n in self.input_names])
        u0, u1 = (w[nu:], w[:nu]) if reverse else (w[:nu], w[nu:])
        held = u1 if reverse else u0  # "zoh" inputs keep the value at the start

        def u_of(s):
            return held + ramp * (u0 + s * (u1 - u0) - held)
        return u_of

    def transition(self, u_prev: ArrayLike, u: ArrayLike, dt: float | None = None) -> np.ndarray:
        """The input ``w`` of the transition into the sample whose input is ``u``, the
        previous sample's being ``u_prev``: ``u`` (held), or ``[u_prev; u]``; with
        ``variable_dt``, followed by the interval ``dt`` (default the model's)."""
        w = np.concatenate([u_prev, u]) if self.sampled else u
        if self.variable_dt:
            w = np.append(w, self.dt if dt is None else dt)
        return w

    def transitions(self, U_prev: np.ndarray | None, U: np.ndarray,
                    dts: np.ndarray | None = None) -> np.ndarray:
        """:meth:`transition` of many transitions at once, ``(n, nw)``: row ``k`` from
        ``U_prev[k]`` (read by sampled models only), ``U[k]`` (both ``(n, nu)``) and
        ``dts[k]`` (``(n,)``; default the model's ``dt``)."""
        U = np.asarray(U, dtype=float)
        W = np.hstack([np.asarray(U_prev, dtype=float), U]) if self.sampled else U
        if self.variable_dt:
            d = np.full(len(U), self.dt) if dts is None else np.asarray(dts, dtype=float)
            W = np.hstack([W, d[:, None]])
        return W

    def step_transitions(self, U_step: np.ndarray, dts: np.ndarray | None = None
                         ) -> np.ndarray:
        """The transitions' inputs ``(n, nw)`` an estimator's ``step`` forms from the
        inputs ``U_step (n, nu)`` it is given at ``n`` consecutive samples after a reset:
        each with the previous step's input (zero before the first) and ``dts``."""
        U_step = np.asarray(U_step, dtype=float)
        previous = np.vstack([np.zeros((1, self.nu)), U_step[:-1]])
        return self.transitions(previous, U_step, dts)

    def measurement_input(self, w: ArrayLike) -> np.ndarray:
        """The input at the end of a transition whose input is ``w`` (what ``h`` sees
        at the next sample)."""
        nu = self.nu
        return w[nu:2 * nu] if self.sampled else w[:nu]

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        # numpy functions on CasADi symbols (np.sin(x[0])) give CasADi expressions
        # (CasADi's legacy behaviour, which the equations rely on); CasADi 3.7's
        # 20-line FutureWarning about them says nothing about the model
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"\s*casadi: a numpy function",
                                    category=FutureWarning)
            self._build_graphs()

    def _build_graphs(self) -> None:
        nx, nu, ny, nw = self.nx, self.nu, self.ny, self.nw
        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", nu)
        w = ca.SX.sym("w", nw)  # a transition's input (the two ends for a sampled model)
        # the interval: the last entry of w with variable_dt, else the model's
        h = w[nw - 1] if self.variable_dt else self.dt
        u_of = self.input_path(w[:nw - 1] if self.variable_dt else w)
        psym = [ca.SX.sym(n) for n in self.param_names]
        p = ca.vertcat(*psym) if psym else ca.SX(0, 1)
        pdict = dict(zip(self.param_names, psym, strict=True))

        y = _as_column(self._output(x, u, pdict), ny, "output")
        _check_constants(y, self.output_names, "output")
        self.H = ca.Function("h", [x, u, p], [y], ["x", "u", "p"], ["y"])
        if self._ode is not None:
            xdot = _as_column(self._ode(x, u, pdict), nx, "ode")
            _check_constants(xdot, self.state_names, "ode")
            self.f_c = ca.Function("f_c", [x, u, p], [xdot], ["x", "u", "p"], ["xdot"])
            if self.integrator == "cvodes":
                self.F = self._cvodes(x, w, p, u_of, h)
                xm, wm, pm = ca.MX.sym("x", nx), ca.MX.sym("w", nw), ca.MX.sym("p", p.numel())
                xn = self.F(xm, wm, pm)
                self.F_x = ca.Function("F_x", [xm, wm, pm], [ca.jacobian(xn, xm)],
                                       ["x", "u", "p"], ["A"])
            else:
                step = rk4_step if self.integrator == "rk4" else euler_step
                xn = step(self.f_c, x, u_of, p, h, self.substeps)
                self.F = ca.Function("F", [x, w, p], [xn], ["x", "u", "p"], ["x_next"])
                self.F_x = ca.Function("F_x", [x, w, p], [ca.jacobian(xn, x)],
                                       ["x", "u", "p"], ["A"])
        else:
            self.f_c = None
            xn = _as_column(self._dynamics(x, u, pdict), nx, "dynamics")
            _check_constants(xn, self.state_names, "dynamics")
            self.F = ca.Function("F", [x, u, p], [xn], ["x", "u", "p"], ["x_next"])
            self.F_x = ca.Function("F_x", [x, u, p], [ca.jacobian(xn, x)],
                                   ["x", "u", "p"], ["A"])
        self.H_x = ca.Function("H_x", [x, u, p], [ca.jacobian(y, x)], ["x", "u", "p"], ["C"])
        self._local = threading.local()

    def _cvodes(self, x, w, p, u_of, h) -> ca.Function:
        t = ca.SX.sym("t")
        # variable_dt: over the fraction s = t of the interval h, dx/ds = h f
        tf = 1.0 if self.variable_dt else self.dt
        ode = self.f_c(x, _input_at(u_of, t / tf), p)
        dae = {"x": x, "t": t, "p": ca.vertcat(w, p), "ode": h * ode if self.variable_dt else ode}
        integ = ca.integrator("F_cvodes", "cvodes", dae, 0.0, tf,
                              {"abstol": 1e-10, "reltol": 1e-10})
        xm = ca.MX.sym("x", self.nx)
        wm = ca.MX.sym("w", self.nw)
        pm = ca.MX.sym("p", p.numel())
        xf = integ(x0=xm, p=ca.vertcat(wm, pm))["xf"]
        return ca.Function("F", [xm, wm, pm], [xf], ["x", "u", "p"], ["x_next"])

    # ------------------------------------------------------------ properties
    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def nu(self) -> int:
        return len(self.input_names)

    @property
    def ny(self) -> int:
        return len(self.output_names)

    @property
    def continuous(self) -> bool:
        """True for models given by ``ode=``."""
        return self._ode is not None

    @property
    def params(self) -> dict[str, float]:
        """Parameter names and current values."""
        return dict(zip(self.param_names, self.p.tolist(), strict=True))

    @property
    def has_bounds(self) -> bool:
        return bool(np.any(np.isfinite(self.lower)) or np.any(np.isfinite(self.upper)))

    # --------------------------------------------------------------- numeric
    def _xu(self, x, u) -> tuple[np.ndarray, np.ndarray]:
        x = as_vector(x, self.nx, "x")
        u = np.zeros(self.nu) if u is None else as_vector(u, self.nu, "u")
        return x, u

    def _fast(self, key: str) -> FastFunction:
        """This thread's buffered evaluator of ``F`` or ``H`` (``key``): a buffer holds
        its arguments and results between filling and reading, so threads never share
        one."""
        fun = getattr(self._local, key, None)
        if fun is None:
            fun = FastFunction(getattr(self, key))
            setattr(self._local, key, fun)
        return fun

    def _w(self, u, u_next, dt=None) -> np.ndarray:
        """A transition's input from the sample's input, (sampled models) the next
        one's (default: the same) and (``variable_dt``) the interval."""
        if dt is not None:
            if not self.variable_dt:
                raise ValueError(f"dt is given but {self.name} integrates over its fixed "
                                 f"dt = {self.dt:g}; build it with variable_dt=True")
            dt = as_float(dt, "dt", positive=True)
        nxt = u if u_next is None or not self.sampled else as_vector(u_next, self.nu,
                                                                     "u_next")
        return self.transition(u, nxt, dt)

    def f(self, x: ArrayLike, u: ArrayLike | None = None, u_next: ArrayLike | None = None,
          dt: float | None = None) -> np.ndarray:
        """Next state ``F(x, u; p)``: ``x`` (nx,), ``u`` (nu,) or None (zero input).

        For a sampled-input model (``hold="foh"``) ``u`` is the input at this
        sample and ``u_next`` at the next one (default: ``u``); with
        ``variable_dt``, ``dt`` is the interval (default the model's). Safe to call
        from several threads at once.
        """
        x, u = self._xu(x, u)
        return self._fast("F")(x, self._w(u, u_next, dt), self.p)[0].copy()

    def h(self, x: ArrayLike, u: ArrayLike | None = None) -> np.ndarray:
        """Output ``h(x, u; p)`` as a (ny,) array (safe from several threads)."""
        x, u = self._xu(x, u)
        return self._fast("H")(x, u, self.p)[0].copy()

    def jacobians(self, x: ArrayLike, u: ArrayLike | None = None,
                  u_next: ArrayLike | None = None, dt: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """``(A, C) = (dF/dx, dh/dx)`` at ``(x, u)``: (nx, nx) and (ny, nx) arrays
        (``u_next``, ``dt`` as for :meth:`f`)."""
        x, u = self._xu(x, u)
        return (self.F_x(x, self._w(u, u_next, dt), self.p).full(),
                self.H_x(x, u, self.p).full())

    def clip(self, x: np.ndarray) -> np.ndarray:
        """Project ``x`` onto ``[lower, upper]``."""
        return np.minimum(np.maximum(x, self.lower), self.upper)

    # -------------------------------------------------------------- variants
    def _copy(self, **changes) -> Model:
        new = object.__new__(Model)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def with_params(self, **values: float) -> Model:
        """Return a copy with some parameter values changed (nothing is rebuilt)."""
        p = self.p.copy()
        for key, val in values.items():
            if key not in self.param_names:
                raise ValueError(f"unknown parameter {key!r}; parameters are {self.param_names}")
            p[self.param_names.index(key)] = as_float(val, f"parameter {key!r}")
        return self._copy(p=p, _local=threading.local())

    def augment(self, *names: str, lower: ArrayLike | None = None,
                upper: ArrayLike | None = None) -> Model:
        r"""Append parameters to the state with constant dynamics.

        The new state is :math:`[x; \theta]` with :math:`\dot\theta = 0`
        (continuous) or :math:`\theta_{k+1} = \theta_k` (discrete), so any
        estimator identifies :math:`\theta` along with :math:`x`.

        Parameters
        ----------
        *names : str
            Parameters to estimate, in the order they are appended.
        lower, upper : float, sequence or dict, optional
            Bounds on the new states (default unbounded).

        Returns
        -------
        Model
            A new model; ``model.augmented`` maps each appended name to its
            nominal value (the truth for simulation).
        """
        if not names:
            raise ValueError("augment needs at least one parameter name")
        for n in names:
            if n not in self.param_names:
                raise ValueError(f"cannot augment unknown parameter {n!r}; "
                                 f"parameters are {self.param_names}")
        if len(set(names)) != len(names):
            raise ValueError(f"augment got duplicate names {names}")
        nx0 = self.nx
        names = list(names)
        base_ode, base_dyn, base_out = self._ode, self._dynamics, self._output

        def split(x, p):
            q = dict(p)
            for i, n in enumerate(names):
                q[n] = x[nx0 + i]
            return x[:nx0], q

        def output(x, u, p):
            xs, q = split(x, p)
            return base_out(xs, u, q)

        kwargs = {}
        if base_ode is not None:
            def ode(x, u, p):
                xs, q = split(x, p)
                return ca.vertcat(_as_column(base_ode(xs, u, q), nx0, "ode"),
                                  ca.SX.zeros(len(names)))
            kwargs["ode"] = ode
        else:
            def dynamics(x, u, p):
                xs, q = split(x, p)
                return ca.vertcat(_as_column(base_dyn(xs, u, q), nx0, "dynamics"),
                                  x[nx0:])
            kwargs["dynamics"] = dynamics

        values = self.params
        new_lower = as_bounds(lower, names, "lower", -np.inf)
        new_upper = as_bounds(upper, names, "upper", np.inf)
        model = Model(
            states=self.state_names + names,
            outputs=self.output_names,
            output=output,
            dt=self.dt,
            inputs=self.input_names,
            params={k: v for k, v in values.items() if k not in names},
            integrator=self.integrator,
            substeps=self.substeps,
            lower=np.concatenate([self.lower, new_lower]),
            upper=np.concatenate([self.upper, new_upper]),
            name=self.name,
            hold=self.hold,
            variable_dt=self.variable_dt,
            time_unit=self.time_unit,
            **kwargs,
        )
        model.augmented = {**self.augmented, **{n: values[n] for n in names}}
        return model

    def __repr__(self) -> str:
        kind = f"ode, {self.integrator}" if self.continuous else "discrete"
        return (f"Model({self.name!r}: nx={self.nx} {self.state_names}, ny={self.ny} "
                f"{self.output_names}, nu={self.nu}, {kind}, "
                f"dt={self.dt:g}{' (variable)' if self.variable_dt else ''})")

    def __getstate__(self):
        state = dict(self.__dict__)
        for key in ("F", "H", "F_x", "H_x", "f_c", "_local"):
            state.pop(key, None)
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self.__dict__.setdefault("variable_dt", False)  # models pickled before these
        self.__dict__.setdefault("time_unit", "")
        self.__dict__.setdefault("hold", dict.fromkeys(self.input_names, "zoh"))
        self._build()
