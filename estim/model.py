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

# long class Model: a third of it is its docstring, the reference of every model option;
# the derived models (augment, with_params, with_disturbances) delegate to functions.

from __future__ import annotations

import threading
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._dae import DAE_INTEGRATORS, dae_functions
from estim._discretise import (
    HOLDS,
    INTEGRATORS,
    TransitionInputs,
    as_column,
    as_holds,
    as_noise_input,
    check_equations,
    discretise,
    equation,
    euler_step,
    rk4_step,
)
from estim._fast import FastFunction
from estim._manifold import Manifold, on_manifold
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

__all__ = ["HOLDS", "INTEGRATORS", "Equation", "Model", "euler_step", "rk4_step"]

#: A user's equation ``f(x, u, p)``: ``x`` and ``u`` CasADi columns, ``p`` a dict of
#: parameter symbols; it returns a column or a list of expressions.
#: a model equation: ``f(x, u, p)``, or ``f(x, z, u, p)`` with algebraic states
Equation = Callable[..., object]


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


class Model(TransitionInputs):
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
    integrator : {"rk4", "euler", "cvodes", "collocation", "idas"}
        Discretisation of ``ode``: fixed-step RK4 (default), explicit Euler,
        or CasADi's adaptive CVODES (SUNDIALS) with tolerances 1e-10; with
        algebraic states also Radau IIA collocation (``substeps`` finite elements
        of 3 stages, order 5) or IDAS (see :mod:`estim._dae`).
    substeps : int
        Fixed integrator steps per sample (rk4/euler), or finite elements (collocation).
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
    algebraic : list of str or int, optional
        Names of algebraic states :math:`z` (a semi-explicit index-1 DAE:
        :math:`\dot x = f(x, z, u)`, :math:`0 = g(x, z, u)` with
        :math:`\partial g / \partial z` nonsingular). ``ode``, ``alg`` and ``output``
        then take ``(x, z, u, p)``; :math:`z` is solved from :math:`x` by Newton's
        method from ``z0`` wherever it is needed (:meth:`z`), and every estimator sees
        the model through ``F`` and ``H``. A structurally singular
        :math:`\partial g / \partial z` (index 2 or higher) is refused.
    alg : callable ``g(x, z, u, p)``, optional
        The algebraic equations (one per algebraic state), with ``algebraic``.
    z0 : sequence of float, optional
        The starting guess of the Newton solve for :math:`z` (default zeros).
    quaternions : list of four state names each, optional
        Unit quaternions (scalar first) among the states: ``F`` keeps them on the unit
        sphere, and the estimators that know manifolds use a 3-dof error
        :math:`q = \hat q \otimes \exp(\delta\theta / 2)` and an ``ndx x ndx``
        covariance (:mod:`estim._manifold`, docs/attitude.md).
    angles, output_angles : list of str, optional
        States and outputs that are angles in radians: errors and innovations are
        wrapped onto :math:`(-\pi, \pi]` (``F`` wraps the angle states too).
    noise_input : (nx, nq) array, optional
        :math:`L` in :math:`dx = f\,dt + L\,d\beta`; the estimators' ``Qc=`` is the density of
        :math:`\beta` (default :math:`L = I`; continuous models; docs/continuous_noise.md).

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

    state_names: list[str]
    output_names: list[str]
    input_names: list[str]
    param_names: list[str]
    p: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    F: ca.Function
    F_x: ca.Function
    H: ca.Function
    H_x: ca.Function
    f_c: ca.Function | None
    Z: ca.Function | None

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
        algebraic: Sequence[str] | int | None = None,
        alg: Equation | None = None,
        z0: ArrayLike | None = None,
        quaternions: Sequence[Sequence[str]] | None = None,
        angles: Sequence[str] | None = None,
        output_angles: Sequence[str] | None = None,
        noise_input: ArrayLike | None = None,
    ):
        self.state_names = as_names(states, "states", "x")
        self.algebraic_names = as_names(algebraic, "algebraic", "z")
        self.output_names = as_names(outputs, "outputs", "y")
        self.input_names = as_names(inputs, "inputs", "u")
        if not self.state_names:
            raise ValueError("states must name at least one state")
        self._output = check_equations(ode, dynamics, output)
        self._alg = _check_algebraic(self.algebraic_names, ode, alg, z0, integrator)
        self.z0 = as_vector(0.0 if z0 is None and self.nz == 1 else
                            [0.0] * self.nz if z0 is None else z0, self.nz, "z0")
        self.integrator = as_choice(integrator, DAE_INTEGRATORS if self.nz else INTEGRATORS,
                                    "integrator")
        self.substeps = as_int(substeps, "substeps", minimum=1)
        self.dt = _sample_time(dt, continuous=ode is not None)
        values = _parameters(params, self.state_names)
        for other, names in (("states", self.state_names), ("params", list(values))):
            clash = sorted(set(self.algebraic_names) & set(names))
            if clash:
                raise ValueError(f"algebraic and {other} share names {clash}: each name "
                                 f"must stand for one quantity")
        self.name = _text(name, "name")
        self.time_unit = _text(time_unit, "time_unit")
        self.param_names = list(values)
        self.p = np.array(list(values.values()))
        self.lower = as_bounds(lower, self.state_names, "lower", -np.inf)
        self.upper = as_bounds(upper, self.state_names, "upper", np.inf)
        if np.any(self.lower > self.upper):
            raise ValueError("lower must not exceed upper")
        self.augmented: dict[str, float] = {}
        #: disturbed inputs and outputs to their states' names (see with_disturbances)
        self.disturbances: dict[str, Any] = {}
        self._ode, self._dynamics = ode, dynamics
        self.hold = as_holds(hold, self.input_names)
        if self.sampled and ode is None:
            raise ValueError("hold='foh' needs a continuous model (ode=): a discrete map "
                             "(dynamics=) already says what happens between samples")
        self.variable_dt = as_bool(variable_dt, "variable_dt")
        if self.variable_dt and ode is None:
            raise ValueError("variable_dt=True needs a continuous model (ode=): a discrete "
                             "map (dynamics=) has no sample interval to vary")
        self.manifold = Manifold(self.state_names, self.output_names, quaternions, angles,
                                 output_angles)
        self.noise_input = as_noise_input(noise_input, self.nx, ode is not None)
        self._build()

    # ------------------------------------------------------------------ build
    def _build(self) -> None:
        # numpy functions on CasADi symbols (np.sin(x[0])) give CasADi expressions
        # (CasADi's legacy behaviour, which the equations rely on); CasADi 3.7's
        # 20-line FutureWarning about them says nothing about the model
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r"\s*casadi: a numpy function",
                                    category=FutureWarning)
            if self.nz:
                (self.f_c, self.F, self.F_x, self.H, self.H_x,
                 self.Z) = dae_functions(self)
            else:
                self.f_c, self.F, self.F_x, self.H, self.H_x = _functions(self)
                self.Z = None
            #: the transition before the manifold's normalisation (whose wrap of the
            #: angles is not a switch the estimators should be warned about)
            self._F_vector = self.F
            if not self.manifold.euclidean_states:  # quaternions kept unit, angles wrapped
                self.F, self.F_x = on_manifold(self.manifold, self.F)
        self._local = threading.local()

    # ------------------------------------------------------------ properties
    @property
    def nx(self) -> int:
        return len(self.state_names)

    @property
    def ndx(self) -> int:
        """Tangent directions of the state (``nx`` less 1 per quaternion)."""
        return self.manifold.ndx

    @property
    def ny(self) -> int:
        return len(self.output_names)

    @property
    def nz(self) -> int:
        """Number of algebraic states (0 for an ODE or a discrete map)."""
        return len(self.algebraic_names)

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
    def _xu(self, x: ArrayLike, u: ArrayLike | None) -> tuple[np.ndarray, np.ndarray]:
        xv = as_vector(x, self.nx, "x")
        uv = np.zeros(self.nu) if u is None else as_vector(u, self.nu, "u")
        return xv, uv

    def _fast(self, key: str) -> FastFunction:
        """This thread's buffered evaluator of ``F`` or ``H`` (``key``): a buffer holds
        its arguments and results between filling and reading, so threads never share
        one."""
        fun = getattr(self._local, key, None)
        if fun is None:
            fun = FastFunction(getattr(self, key))
            setattr(self._local, key, fun)
        return fun

    def _w(self, u: np.ndarray, u_next: ArrayLike | None, dt: float | None = None
           ) -> np.ndarray:
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

    def z(self, x: ArrayLike, u: ArrayLike | None = None) -> np.ndarray:
        """The algebraic states ``Z(x, u; p)`` consistent with ``x`` (a Newton solve of
        ``0 = g(x, z, u)`` from ``z0``), ``(nz,)``; a ``ValueError`` when it does not
        converge."""
        if self.Z is None:
            raise ValueError(f"{self.name} has no algebraic states (algebraic=...)")
        x, u = self._xu(x, u)
        out = np.asarray(self.Z(x, u, self.p), dtype=float).ravel()
        if not np.isfinite(out).all():
            raise ValueError(f"no consistent algebraic state at x = {x.tolist()}: the Newton "
                             f"solve of alg from z0 = {self.z0.tolist()} did not converge "
                             f"(a better z0, or an x where the algebraic equations have a "
                             f"solution)")
        return out

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
    def _copy(self, **changes: Any) -> Model:
        new = object.__new__(Model)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def euclidean(self) -> Model:
        """This model with its quaternions and angles as ordinary states and outputs
        (additive errors, an ``nx x nx`` covariance), for an estimator that does not
        handle manifolds; ``F`` still keeps the quaternions unit."""
        return self._copy(manifold=Manifold(self.state_names, self.output_names),
                          _local=threading.local())

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
        from estim._augment import augmented

        return augmented(self, names, lower, upper)

    def with_disturbances(self, inputs: Sequence[str] | None = None,
                          outputs: Sequence[str] | None = None, *,
                          kind: str = "integrating", check: bool = True,
                          at: tuple[ArrayLike, ArrayLike] | None = None) -> Model:
        r"""This model with integrating disturbances: states ``d_<name>`` added to the
        named ``inputs`` (wherever the model sees them) and ``outputs``, constant in the
        model (their process noise, in ``Q``, sets how fast they are followed). With
        ``check``, an augmented model that is not detectable (more disturbances than
        outputs, or :math:`\operatorname{rank}[[I - A, -B_d], [C, C_d]] < n_x + n_d`
        at ``at = (x, u)``, default zeros) is refused with a ``ValueError`` naming the
        disturbances no output sees; ``check=False`` warns instead. ``kind``:
        ``"integrating"``. The new model's ``disturbances`` maps each disturbed input
        and output to its state. See :mod:`estim._disturbances` (Pannocchia, Rawlings
        2003)."""
        from estim._disturbances import augment

        return augment(self, inputs, outputs, kind, check, at)

    def __repr__(self) -> str:
        kind = f"ode, {self.integrator}" if self.continuous else "discrete"
        return (f"Model({self.name!r}: nx={self.nx} {self.state_names}, ny={self.ny} "
                f"{self.output_names}, nu={self.nu}, {kind}, "
                f"dt={self.dt:g}{' (variable)' if self.variable_dt else ''})")

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        for key in ("F", "H", "F_x", "H_x", "f_c", "_local", "_F_vector"):
            state.pop(key, None)
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self.__dict__.setdefault("variable_dt", False)  # models pickled before these
        self.__dict__.setdefault("time_unit", "")
        self.__dict__.setdefault("disturbances", {})
        self.__dict__.setdefault("hold", dict.fromkeys(self.input_names, "zoh"))
        self.__dict__.setdefault("manifold", Manifold(self.state_names, self.output_names))
        self.__dict__.setdefault("noise_input", None)
        self._build()


# ------------------------------------------------------------ the Functions
def _functions(model: Model) -> tuple[ca.Function | None, ca.Function, ca.Function,
                                      ca.Function, ca.Function]:
    """``(f_c, F, F_x, H, H_x)`` of ``model`` from its equations (``f_c`` None for a
    discrete model)."""
    nx, nu, ny, nw = model.nx, model.nu, model.ny, model.nw
    x = ca.SX.sym("x", nx)
    u = ca.SX.sym("u", nu)
    w = ca.SX.sym("w", nw)  # a transition's input (the two ends for a sampled model)
    u_of = model.input_path(w[:nw - 1] if model.variable_dt else w)
    psym = [ca.SX.sym(n) for n in model.param_names]
    p = ca.vertcat(*psym) if psym else ca.SX(0, 1)
    pdict = dict(zip(model.param_names, psym, strict=True))

    y = as_column(equation(model, "output", model._output, x, u, pdict), ny, "output")
    _check_constants(y, model.output_names, "output")
    H = ca.Function("h", [x, u, p], [y], ["x", "u", "p"], ["y"])
    H_x = ca.Function("H_x", [x, u, p], [ca.jacobian(y, x)], ["x", "u", "p"], ["C"])
    if model._ode is not None:
        xdot = as_column(equation(model, "ode", model._ode, x, u, pdict), nx, "ode")
        _check_constants(xdot, model.state_names, "ode")
        f_c = ca.Function("f_c", [x, u, p], [xdot], ["x", "u", "p"], ["xdot"])
        F, F_x = discretise(f_c, x, w, p, u_of, integrator=model.integrator,
                            substeps=model.substeps, dt=model.dt,
                            variable_dt=model.variable_dt)
        return f_c, F, F_x, H, H_x
    assert model._dynamics is not None  # a model has exactly one of ode and dynamics
    xn = as_column(equation(model, "dynamics", model._dynamics, x, u, pdict), nx, "dynamics")
    _check_constants(xn, model.state_names, "dynamics")
    F = ca.Function("F", [x, u, p], [xn], ["x", "u", "p"], ["x_next"])
    F_x = ca.Function("F_x", [x, u, p], [ca.jacobian(xn, x)], ["x", "u", "p"], ["A"])
    return None, F, F_x, H, H_x


# ------------------------------------------------------------ the arguments
def _check_algebraic(names: list[str], ode: Equation | None, alg: Equation | None,
                     z0: ArrayLike | None, integrator: str) -> Equation | None:
    """``alg=`` checked against ``algebraic=``: both or neither, with ``ode=``."""
    if not names:
        if alg is not None or z0 is not None:
            raise ValueError("alg= and z0= need algebraic=[...] (the algebraic states' names)")
        if integrator in ("collocation", "idas"):
            raise ValueError(f"integrator={integrator!r} is for models with algebraic states "
                             f"(algebraic=, alg=); an ODE takes 'rk4', 'euler' or 'cvodes'")
        return None
    if ode is None:
        raise ValueError("algebraic= needs a continuous model (ode=f(x, z, u, p))")
    if alg is None or not callable(alg):
        raise TypeError("algebraic= needs alg=g(x, z, u, p), a callable returning the "
                        "algebraic equations 0 = g (one per algebraic state)")
    if integrator == "cvodes":
        raise ValueError("integrator='cvodes' integrates ODEs only: a model with algebraic "
                         "states takes 'idas', 'collocation', 'rk4' or 'euler'")
    return alg


def _sample_time(dt: float | None, continuous: bool) -> float:
    """The sample time: required for a continuous model, 1 by default for a discrete one."""
    if dt is None:
        if continuous:
            raise ValueError("dt is required for a continuous model (ode=)")
        dt = 1.0
    return as_float(dt, "dt", positive=True)


def _parameters(params: Mapping[str, float] | None, state_names: Sequence[str]
                ) -> dict[str, float]:
    """``params=`` as ``{name: float}``, its names distinct from the states'."""
    if params is not None and not isinstance(params, Mapping):
        raise TypeError(f"params must be a dict {{name: value}}, got {type(params).__name__}")
    values = dict(params or {})
    for key, val in values.items():
        if not isinstance(key, str):
            raise TypeError(f"params keys must be strings, got {key!r}")
        values[key] = as_float(val, f"params[{key!r}]")
    clash = set(values) & set(state_names)
    if clash:
        raise ValueError(f"params and states share names {sorted(clash)}")
    return values


def _text(value: str, argname: str) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{argname} must be a string, got {type(value).__name__}")
    return value


# ------------------------------------------------------------ augmentation
