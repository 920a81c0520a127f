r"""Discretisation of a continuous model over one sample, and the input of a transition.

A continuous model :math:`\dot x = f(x, u; p)` becomes the map

.. math:: x_{k+1} = F(x_k, w_k; p)

over one sample. The transition's input ``w`` holds what the integration needs to
know about the input between the samples:

* zero-order hold (``"zoh"``, the default): ``w = u``, held over the sample;
* first-order hold (``"foh"`` on some input): ``w = [u_k; u_{k+1}]``, the values at
  both ends, the ``"foh"`` inputs linear in between and the ``"zoh"`` ones held at
  their value at the start (:func:`input_path`);
* a variable interval (``variable_dt``): ``w`` ends with the interval :math:`h`,
  and the integration runs over the fraction :math:`s = t / h` of the sample.

The integrators: classic fourth-order Runge-Kutta (:func:`rk4_step`) and explicit
Euler (:func:`euler_step`), both over a fixed number of substeps per sample, and
CasADi's adaptive CVODES (SUNDIALS) with tolerances 1e-10 (:func:`discretise`).
:class:`TransitionInputs` forms ``w`` from the inputs at the samples, for one
transition or a whole record.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import casadi as ca
import numpy as np

from estim._validate import as_choice

#: A CasADi symbolic expression (SX or MX); where noted, also a number.
Sym = Any
#: A right-hand side ``f(x, u, p)`` of symbolic expressions (e.g. a ``casadi.Function``).
RightHandSide = Callable[[Sym, Sym, Sym], Sym]

INTEGRATORS = ("rk4", "euler", "cvodes")
HOLDS = ("zoh", "foh")

_CVODES_OPTIONS = {"abstol": 1e-10, "reltol": 1e-10}


def as_column(expr, size: int, argname: str) -> ca.SX:
    """Turn what a user equation returned into a ``(size, 1)`` expression."""
    if isinstance(expr, list | tuple):
        for i, entry in enumerate(expr):
            if not isinstance(entry, ca.SX | ca.MX | ca.DM | int | float | np.number) and \
                    not (isinstance(entry, np.ndarray) and entry.size == 1):
                raise TypeError(f"{argname} must return a CasADi expression or a list of "
                                f"them: its entry {i} is {type(entry).__name__} "
                                f"({entry!r:.40})")
        expr = ca.vertcat(*expr)
    elif isinstance(expr, np.ndarray):
        if expr.dtype.kind not in "iufbO" or expr.ndim > 2:
            raise TypeError(f"{argname} must return a CasADi expression or a list of them, "
                            f"got a numpy array of {expr.ndim} dimensions and dtype "
                            f"{expr.dtype} (real numbers, at most 2 dimensions)")
        expr = ca.SX(expr.astype(float)) if expr.dtype != object else \
            as_column(expr.ravel().tolist(), size, argname)
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


#: Hints for errors raised inside a user's equation: (what the message contains, hint).
_EQUATION_HINTS = (
    ("truth value", "a Python if/and/or/max/min on a symbol: the equations are built once "
                    "with symbols, so branch with ca.if_else(cond, a, b), ca.fmax/ca.fmin, "
                    "or the smooth helpers of estim.soft"),
    ("must be real number", "a math.* function on a symbol: use ca.* (ca.sqrt, ca.exp, "
                            "ca.log, ...) or numpy ufuncs"),
    ("Wrong number or type of arguments", "an entry that is not a number or a CasADi "
                                          "expression (None? a list inside the list?)"),
    ("division by zero", "a division by a Python zero"),
    ("stop<=len", "an index beyond a vector: x has nx entries, u has nu, p is a dict by "
                  "parameter name"),
    ("index out of range", "an index beyond a vector: x has nx entries, u has nu, p is a "
                           "dict by parameter name"),
)


def equation(model: Any, which: str, fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(*args)``, the model's equation ``which`` (``"ode"``, ``"output"``, ...) called
    on symbols; an exception inside it is raised again (the same type where it can be,
    else ``ValueError``) with the model's name, the equation and a hint for the common
    causes, the original chained."""
    try:
        return fn(*args)
    except Exception as exc:  # noqa: BLE001 - re-raised with what was being built
        text = str(exc).strip().splitlines()
        first = text[0] if text else type(exc).__name__
        hint = next((h for key, h in _EQUATION_HINTS if key in str(exc)), "")
        message = (f"{getattr(model, 'name', 'model')}: building the equation {which}= "
                   f"failed: {type(exc).__name__}: {first}" + (f" ({hint})" if hint else ""))
        try:
            new = type(exc)(message)
        except Exception:  # noqa: BLE001 - an exception type that takes other arguments
            new = ValueError(message)
        raise new from exc


def input_at(u: Sym | Callable[[Sym], Sym], s: float | Sym) -> Sym:
    """The input at the fraction ``s`` of the sample: ``u(s)`` for an interpolated
    input (a callable), else ``u`` (held)."""
    return u(s) if callable(u) else u


def rk4_step(f: RightHandSide, x: Sym, u: Sym | Callable[[Sym], Sym], p: Sym, h: float | Sym,
             substeps: int = 1) -> Sym:
    r"""Classic fourth-order Runge-Kutta over ``substeps`` steps of size ``h / substeps``.

    .. math::
        k_1 = f(x, u_0), k_2 = f(x + \tfrac{h}{2} k_1, u_{1/2}),
        k_3 = f(x + \tfrac{h}{2} k_2, u_{1/2}), k_4 = f(x + h k_3, u_1), \quad
        x^+ = x + \tfrac{h}{6}(k_1 + 2k_2 + 2k_3 + k_4)

    ``u`` is the input held over the sample, or a callable giving it at a fraction
    ``s`` of the sample (:math:`u_s = u(s)`, e.g. linear between two samples). ``h``
    is a number or a symbol (a variable interval).
    """
    dt = h / substeps
    for i in range(substeps):
        s0, sm, s1 = i / substeps, (i + 0.5) / substeps, (i + 1) / substeps
        um = input_at(u, sm)
        k1 = f(x, input_at(u, s0), p)
        k2 = f(x + dt / 2 * k1, um, p)
        k3 = f(x + dt / 2 * k2, um, p)
        k4 = f(x + dt * k3, input_at(u, s1), p)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def euler_step(f: RightHandSide, x: Sym, u: Sym | Callable[[Sym], Sym], p: Sym,
               h: float | Sym, substeps: int = 1) -> Sym:
    r"""Explicit Euler, :math:`x^+ = x + h f(x, u)`, over ``substeps`` steps (``u``
    held, or a callable of the fraction of the sample as for :func:`rk4_step`)."""
    dt = h / substeps
    for i in range(substeps):
        x = x + dt * f(x, input_at(u, i / substeps), p)
    return x


def as_holds(hold: str | Mapping[str, str], input_names: Sequence[str]) -> dict[str, str]:
    """A model's ``hold=`` argument as ``{input name: "zoh" or "foh"}``; ``"foh"`` on a
    model without inputs is refused (it would be ignored)."""
    if isinstance(hold, str):
        choice = as_choice(hold, HOLDS, "hold")
        if choice == "foh" and not input_names:
            raise ValueError("hold='foh' interpolates inputs between samples, but the "
                             "model has none (inputs=...)")
        return dict.fromkeys(input_names, choice)
    if not isinstance(hold, Mapping):
        raise TypeError(f"hold must be 'zoh', 'foh' or a dict {{input: hold}}, "
                        f"got {type(hold).__name__}")
    unknown = sorted(set(hold) - set(input_names))
    if unknown:
        raise ValueError(f"hold names unknown inputs {unknown}; inputs are "
                         f"{list(input_names)}")
    return {n: as_choice(hold.get(n, "zoh"), HOLDS, f"hold[{n!r}]") for n in input_names}


def input_path(w: Sym, ramp: ca.DM, reverse: bool = False) -> Callable[[Sym], Sym]:
    """The input along a sample whose two ends' inputs are ``w = [u_0; u_1]``, as a
    function of the fraction ``s`` of the sample: linear from ``u_0`` to ``u_1`` for
    the inputs where ``ramp`` (``(nu,)``) is 1, held at ``u_0`` where it is 0
    (``reverse``: from ``u_1`` back to ``u_0``, held at ``u_1``, for integrating
    backward in time)."""
    nu = ramp.numel()
    u0, u1 = (w[nu:], w[:nu]) if reverse else (w[:nu], w[nu:])
    held = u1 if reverse else u0  # "zoh" inputs keep the value at the start

    def u_of(s: float | Sym) -> Sym:
        return held + ramp * (u0 + s * (u1 - u0) - held)
    return u_of


def discretise(f_c: ca.Function, x: ca.SX, w: ca.SX, p: ca.SX,
               u_of: Sym | Callable[[Sym], Sym], *, integrator: str, substeps: int,
               dt: float, variable_dt: bool) -> tuple[ca.Function, ca.Function]:
    """The sampled map ``F(x, w, p) -> x_next`` of ``f_c`` and its Jacobian ``F_x``.

    Parameters
    ----------
    f_c : casadi.Function
        The right-hand side ``f(x, u, p)``.
    x, w, p : casadi.SX
        The symbols of the state ``(nx, 1)``, the transition's input ``(nw, 1)`` and
        the parameters.
    u_of : expression or callable
        The input along the sample (:func:`input_path`), from ``w``.
    integrator : {"rk4", "euler", "cvodes"}
    substeps : int
        Steps per sample of the fixed-step integrators.
    dt : float
        The sample interval; with ``variable_dt`` the interval is the last entry of
        ``w`` instead.

    Returns
    -------
    F, F_x : casadi.Function
        Named inputs ``x, u, p``; outputs ``x_next`` and ``A`` (by algorithmic
        differentiation).
    """
    h = w[w.numel() - 1] if variable_dt else dt
    if integrator == "cvodes":
        F = _cvodes(f_c, x, w, p, u_of, h, variable_dt, dt)
        xm, wm, pm = ca.MX.sym("x", x.numel()), ca.MX.sym("w", w.numel()), \
            ca.MX.sym("p", p.numel())
        xn_mx = F(xm, wm, pm)
        return F, ca.Function("F_x", [xm, wm, pm], [ca.jacobian(xn_mx, xm)],
                              ["x", "u", "p"], ["A"])
    step = rk4_step if integrator == "rk4" else euler_step
    xn = step(f_c, x, u_of, p, h, substeps)
    return (ca.Function("F", [x, w, p], [xn], ["x", "u", "p"], ["x_next"]),
            ca.Function("F_x", [x, w, p], [ca.jacobian(xn, x)], ["x", "u", "p"], ["A"]))


def _cvodes(f_c: ca.Function, x: ca.SX, w: ca.SX, p: ca.SX,
            u_of: Sym | Callable[[Sym], Sym], h: float | Sym, variable_dt: bool,
            dt: float) -> ca.Function:
    """``F(x, w, p)`` integrated by CVODES (an MX Function around CasADi's integrator)."""
    t = ca.SX.sym("t")
    # variable_dt: over the fraction s = t of the interval h, dx/ds = h f
    tf = 1.0 if variable_dt else dt
    ode = f_c(x, input_at(u_of, t / tf), p)
    dae = {"x": x, "t": t, "p": ca.vertcat(w, p), "ode": h * ode if variable_dt else ode}
    integ = ca.integrator("F_cvodes", "cvodes", dae, 0.0, tf, _CVODES_OPTIONS)
    xm = ca.MX.sym("x", x.numel())
    wm = ca.MX.sym("w", w.numel())
    pm = ca.MX.sym("p", p.numel())
    xf = integ(x0=xm, p=ca.vertcat(wm, pm))["xf"]
    return ca.Function("F", [xm, wm, pm], [xf], ["x", "u", "p"], ["x_next"])


class TransitionInputs:
    """The input ``w`` of a model's transitions (``F(x, w, p)``), from the inputs given
    at the samples: the methods :class:`~estim.Model` shares with everything that
    runs a model over a record."""

    input_names: list[str]
    hold: dict[str, str]
    variable_dt: bool
    dt: float

    @property
    def nu(self) -> int:
        return len(self.input_names)

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

    def input_path(self, w: Sym, reverse: bool = False) -> Any:
        """The input along a transition whose input is ``w``: ``w`` itself (held), or
        for a sampled model a function of the fraction ``s`` of the sample, linear
        from the start value to the end value for ``"foh"`` inputs (``reverse``:
        from the end back to the start, for integrating backward in time)."""
        if not self.sampled:
            return w
        ramp = ca.DM([float(self.hold[n] == "foh") for n in self.input_names])
        return input_path(w, ramp, reverse)

    def transition(self, u_prev: np.ndarray | None, u: np.ndarray,
                   dt: float | None = None) -> np.ndarray:
        """The input ``w`` of the transition into the sample whose input is ``u``
        ``(nu,)``, the previous sample's being ``u_prev`` ``(nu,)`` (read by sampled
        models only; None otherwise): ``u`` (held), or ``[u_prev; u]``; with
        ``variable_dt``, followed by the interval ``dt`` (default the model's)."""
        if self.sampled:
            if u_prev is None:
                raise ValueError("a sampled-input model's transition needs the previous "
                                 "sample's input u_prev")
            w = np.concatenate([u_prev, u])
        else:
            w = u
        if self.variable_dt:
            wd = np.empty(len(w) + 1)
            wd[:-1] = w
            wd[-1] = self.dt if dt is None else dt
            return wd
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

    def measurement_input(self, w: np.ndarray | Sym) -> np.ndarray | Sym:
        """The input at the end of a transition whose input is ``w`` (what ``h`` sees
        at the next sample): an array, or a CasADi expression for building graphs."""
        nu = self.nu
        return w[nu:2 * nu] if self.sampled else w[:nu]


def as_noise_input(L: Any, nx: int, continuous: bool) -> np.ndarray | None:
    """``noise_input=`` checked: None, or a finite ``(nx, nq)`` matrix of a continuous
    model (a vector: one column)."""
    if L is None:
        return None
    if not continuous:
        raise ValueError("noise_input= says how a continuous-time noise enters the states: "
                         "it needs a continuous model (ode=); a discrete model takes a "
                         "per-transition Q")
    try:
        M = np.array(L, dtype=float)
    except (TypeError, ValueError):
        raise TypeError(f"noise_input must be an (nx, nq) matrix of numbers, got "
                        f"{type(L).__name__}") from None
    if M.ndim == 1:
        M = M[:, None]
    if M.ndim != 2 or M.shape[0] != nx or M.shape[1] < 1:
        raise ValueError(f"noise_input must be an (nx, nq) matrix with nx = {nx} rows and at "
                         f"least one column, got shape {np.shape(L)}")
    if not np.isfinite(M).all():
        raise ValueError("noise_input must be finite")
    return M


def check_equations(ode: Any, dynamics: Any, output: Any) -> Any:
    """Check that exactly one of ``ode``/``dynamics`` is given and that the equations are
    callables; returns ``output``."""
    if (ode is None) == (dynamics is None):
        raise ValueError("give exactly one of ode= (continuous) or dynamics= (discrete)")
    for argname, fn in (("ode", ode), ("dynamics", dynamics), ("output", output)):
        if fn is not None and not callable(fn):
            raise TypeError(f"{argname} must be callable f(x, u, p), got {type(fn).__name__}")
    if output is None:
        raise ValueError("output= is required: a callable h(x, u, p)")
    return output
