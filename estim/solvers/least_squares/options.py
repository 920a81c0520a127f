"""Which NLP solver an optimisation-based estimator uses, and the checks of its options.

The estimators' ``solver=`` names one of :data:`SOLVERS` (or ``"auto"``: the structured
Gauss-Newton solver) and ``solver_options=`` its options: Gauss-Newton's are checked by
name and type here, the CasADi solvers' (Ipopt, CasADi's ``sqpmethod`` with ``qrqp``,
fatrop) by CasADi itself on a one-variable problem before anything is built, its
refusal turned into a ``ValueError`` that names the option. The defaults below are
merged under the user's options.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import casadi as ca

from estim._validate import as_bool, as_choice, as_float, as_int, unknown_keywords_message

__all__ = ["SOLVERS", "SOLVER_CHOICES", "casadi_reason", "check_solver_options", "jit_options",
           "merge",
           "nlpsol", "resolve_solver"]

SOLVERS = ("gauss-newton", "ipopt", "sqp", "fatrop")
#: What the estimators' ``solver=`` accepts: a solver by name, or ``"auto"``.
SOLVER_CHOICES = ("auto", *SOLVERS)

_IPOPT_DEFAULTS = {
    "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
    "ipopt.tol": 1e-10, "ipopt.acceptable_tol": 1e-7, "ipopt.max_iter": 200,
    "ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-4,
    "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
    "show_eval_warnings": False,
}
_SQP_DEFAULTS = {
    "qpsol": "qrqp",
    "qpsol_options": {"print_iter": False, "print_header": False, "print_info": False,
                      "error_on_fail": False},
    "print_header": False, "print_iteration": False, "print_status": False,
    "print_time": False, "max_iter": 100, "tol_pr": 1e-9, "tol_du": 1e-9,
    "min_step_size": 1e-12, "error_on_fail": False, "show_eval_warnings": False,
}
_FATROP_DEFAULTS = {
    "print_time": False, "structure_detection": "auto", "expand": True,
    "fatrop.print_level": 0, "fatrop.tol": 1e-10, "fatrop.max_iter": 200,
    "error_on_fail": False, "show_eval_warnings": False,
}


#: The options of the Gauss-Newton solver and their checks.
_GN_OPTIONS: dict[str, Callable[[Any, str], Any]] = {
    "max_iter": lambda v, n: as_int(v, n, minimum=1),
    "xtol": lambda v, n: as_float(v, n, positive=True),
    "ftol": lambda v, n: as_float(v, n, positive=True),
    "newton": as_bool,
    "jit": as_bool,
    "mode": lambda v, n: as_choice(v, ("auto", "unrolled", "mapped"), n),
}
_PLUGINS = {"ipopt": "ipopt", "sqp": "sqpmethod", "fatrop": "fatrop"}
_CASADI_TYPES = {"double": "a number", "int": "an integer", "string": "a string",
                 "bool": "a bool", "dict": "a dict"}


def casadi_reason(exc: Exception) -> str:
    """The useful part of a CasADi error message (source locations and banners removed)."""
    lines = []
    for line in str(exc).splitlines():
        line = re.sub(r"^\S*\.(?:cpp|hpp):\d+:\s*", "", line.strip())
        if not line or line.startswith(("Error calling", "Error in Function::call", ">",
                                        "Did you mean", "Use print_options")):
            continue
        lines.append(line)
    text = " ".join(lines[:2]) or str(exc).strip()
    text = re.sub(r'Assertion "is_(\w+)\(\)" failed:\s*type mismatch',
                  lambda m: f"type mismatch (expected {_CASADI_TYPES.get(m[1], m[1])})", text)
    return re.sub(r'Assertion "[^"]*" failed:\s*', "", text)


def _dry_run(solver: str, options: dict) -> None:
    """Build (and for fatrop, which reads its options late, solve) a one-variable problem
    with ``options`` merged over the defaults; CasADi's exceptions pass through."""
    x, w, z = ca.SX.sym("x"), ca.SX.sym("w"), ca.SX.sym("z")
    if solver == "fatrop":
        opts = merge(_FATROP_DEFAULTS, options)
        opts.setdefault("equality", [True])
        opts["fatrop.print_level"] = 0
        nlp = {"x": ca.vertcat(x, w, z), "f": x**2 + w**2 + z**2, "g": z - x - w}
        ca.nlpsol("options_check", "fatrop", nlp, opts)(x0=0, lbg=0, ubg=0)
        return
    defaults = _IPOPT_DEFAULTS if solver == "ipopt" else _SQP_DEFAULTS
    ca.nlpsol("options_check", _PLUGINS[solver], {"x": x, "f": x**2},
              merge(defaults, options))


def jit_options(jit, options) -> tuple[Any, bool]:
    """``solver_options`` with compiled code when ``jit=True`` (the estimators' common
    spelling, the filters' ``jit=True``; ``solver_options={"jit": True}`` stays an alias),
    and whether the code is compiled. A contradiction between the two is an error."""
    jit = as_bool(jit, "jit")
    if not isinstance(options, Mapping):  # None, or refused by check_solver_options
        return ({"jit": True} if jit and options is None else options), jit
    if not jit:
        return options, options.get("jit") is True
    if "jit" in options and options["jit"] is not True:
        raise ValueError(f"jit=True contradicts solver_options['jit'] = {options['jit']!r}: "
                         f"give one of them")
    return {**options, "jit": True}, True


def resolve_solver(solver, options) -> str:
    """The solver ``solver=`` names; ``"auto"`` is the fastest one for the problem.

    Moving horizon and full-information estimation pose nonlinear least-squares
    problems with box bounds, which the structured Gauss-Newton solver
    (:mod:`estim.solvers.least_squares.gauss_newton`) solves to the same optimum as Ipopt
    in a fraction of the time (van der Pol MHE, N = 15: 0.26 against 2.3 ms per
    step), so ``"auto"`` is ``"gauss-newton"``. Options of another solver with
    ``"auto"`` are an error that says which solver to name.
    """
    solver = as_choice(solver, SOLVER_CHOICES, "solver")
    if solver != "auto":
        return solver
    if isinstance(options, Mapping):
        foreign = sorted(k for k in options if isinstance(k, str) and k not in _GN_OPTIONS)
        if foreign:
            raise ValueError(f"solver='auto' is the Gauss-Newton solver, and solver_options "
                             f"{foreign} are not its options: name the solver they belong "
                             f"to, e.g. solver='ipopt'")
    return "gauss-newton"


def check_solver_options(solver: str, options) -> dict:
    """Check ``solver_options`` for ``solver`` before anything is built; return a copy.

    Gauss-Newton's options are checked by name and type; the CasADi solvers'
    (``"ipopt"``, ``"sqp"``, ``"fatrop"``) by CasADi itself on a one-variable
    problem, its refusal turned into a ``ValueError`` naming the option.
    """
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise TypeError(f"solver_options must be a dict, got {type(options).__name__}")
    options = dict(options)
    for key in options:
        if not isinstance(key, str):
            raise TypeError(f"solver_options keys must be strings, got {key!r}")
    if solver == "gauss-newton":
        unknown = [k for k in options if k not in _GN_OPTIONS]
        if unknown:
            raise ValueError(unknown_keywords_message(
                "solver_options for solver 'gauss-newton'", unknown, list(_GN_OPTIONS)))
        return {k: _GN_OPTIONS[k](v, f"solver_options[{k!r}]") for k, v in options.items()}
    only_gn = sorted(set(options) & {"xtol", "ftol", "newton", "mode"})
    if only_gn:
        raise ValueError(f"solver_options {only_gn} apply to solver='gauss-newton' only "
                         f"(solver is {solver!r})")
    if not options:
        return options
    try:
        _dry_run(solver, options)
    except (RuntimeError, NotImplementedError) as exc:
        # name the option: the first one CasADi refuses on its own
        for key, value in options.items():
            try:
                _dry_run(solver, {key: value})
            except (RuntimeError, NotImplementedError) as one:
                reason = casadi_reason(one)
                if solver in ("ipopt", "fatrop") and reason.startswith("Unknown option") \
                        and not key.startswith(solver + "."):
                    reason += (f" ({solver}'s own options are given as '{solver}.<name>', "
                               f"e.g. '{solver}.max_iter')")
                raise ValueError(f"solver_options for solver {solver!r} were refused by "
                                 f"CasADi: solver_options[{key!r}]: {reason}") from None
        raise ValueError(f"solver_options for solver {solver!r} were refused by CasADi: "
                         f"{casadi_reason(exc)}") from None
    return options


def nlpsol(name: str, solver: str, nlp: dict, opts: dict, user: dict):
    """``ca.nlpsol`` with CasADi's refusal of the user's options as a ``ValueError``."""
    try:
        return ca.nlpsol(name, _PLUGINS[solver], nlp, opts)
    except (RuntimeError, NotImplementedError) as exc:
        if not user:
            raise
        raise ValueError(f"solver_options for solver {solver!r} were refused by CasADi: "
                         f"{casadi_reason(exc)}") from None


def merge(defaults: dict, user: dict) -> dict:
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in defaults.items()}
    for k, v in user.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k].update(v)
        else:
            out[k] = v
    return out
