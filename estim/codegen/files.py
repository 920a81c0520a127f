"""The files an export writes: CasADi's generated code of the step functions, and the
driver's C header and source, the ``Makefile`` and the ``README.md`` filled in from the
templates shipped with the package (``estim/codegen/templates/*.in``).

A template is the file's text with placeholders ``@key@``, which :func:`fill` replaces,
in this order:

``@name@``, ``@NAME@``
    The C identifier that prefixes every file and symbol, and its upper case.
``@filter@``, ``@model@``, ``@version@``
    What the estimator is (e.g. ``EKF, clip=True``), the model's name, estim's version.
``@CFLAGS@``, ``@TAIL@``
    The Makefile's compiler flags (:data:`CFLAGS`) and the tail probability of the
    suspect flag (:data:`estim.consistency.SUSPECT_TAIL`).
``@states@``, ``@outputs@``, ``@inputs@``
    The model's names of each, comma-separated (``none`` without inputs).
values, then dimensions
    What the exporter computes: C literals (``@Q@``, ``@LOWER@``, ...) and text
    (the MHE's ``@FIELDS@``), then integers (``@NX@``, ``@SZ_W@``, ``@BYTES@``, ...).

Before that, the template's sections are chosen (:func:`sections`): lines between a
line ``@if <switch>@`` and a line ``@else@`` (or ``@end@``) are kept where the switch
is on, those between ``@else@`` and ``@end@`` where it is off, and the three marker
lines go (e.g. the square-root form's driver, ``@if sqrt@``).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._version import __version__
from estim.consistency import SUSPECT_TAIL

if TYPE_CHECKING:
    from estim.model import Model

#: Flags of the Makefile: optimised, position-independent, and no contraction of
#: products and sums into fused multiply-adds, so that the code computes what CasADi's
#: interpreter computes in Python, operation for operation.
CFLAGS = "-O2 -fPIC -fno-fast-math -ffp-contract=off"

#: The optimisation level of each ``optimize`` choice of :func:`estim.codegen.export`: for
#: the step's speed (the default) or for the library's size (the same results: no flag
#: that changes the arithmetic)
OPTIMIZE = {"speed": "-O2", "size": "-Os"}


def cflags(optimize: str) -> str:
    """The Makefile's flags for ``optimize`` (``"speed"`` or ``"size"``)."""
    return CFLAGS.replace("-O2", OPTIMIZE[optimize])


def check_model(m: Model) -> None:
    """Refuse a model whose step CasADi's code generator cannot write as plain C (a
    ``variable_dt`` model is exported with the interval an argument of the drivers'
    ``step(y, u, dt)``).

    Raises
    ------
    ValueError
        Integration by CVODES (which needs the CasADi runtime) or algebraic states.
    """
    if getattr(m, "integrator", None) == "cvodes":
        raise ValueError(f"{m.name} is integrated by CVODES, which needs the CasADi "
                         f"runtime: build the model with integrator='rk4' to export")
    if getattr(m, "nz", 0):
        raise ValueError(f"{m.name} has algebraic states {m.algebraic_names}: the C step "
                         f"would need their Newton solve and CasADi's integrators, which "
                         f"generate no plain C; export a model without algebraic states")


def sections(text: str, switches: Mapping[str, bool]) -> str:
    """``text`` with its conditional sections chosen by ``switches`` (see the module's
    docstring; sections nest); a text without markers is returned unchanged.

    Raises
    ------
    ValueError
        A marker without its ``@if``, an ``@if`` without its ``@end``.
    """
    if "@if " not in text:
        return text
    kept: list[str] = []
    stack: list[tuple[bool, bool]] = []  # (the enclosing section is kept, the switch)
    keep = True
    for line in text.splitlines(keepends=True):
        marker = line.strip()
        if marker.startswith("@if ") and marker.endswith("@"):
            stack.append((keep, bool(switches[marker[4:-1]])))
            keep = keep and stack[-1][1]
        elif marker in ("@else@", "@end@"):
            if not stack:
                raise ValueError(f"{marker} without @if")
            outer, on = stack[-1]
            if marker == "@else@":
                keep = outer and not on
            else:
                stack.pop()
                keep = outer
        elif keep:
            kept.append(line)
    if stack:
        raise ValueError("@if without @end")
    return "".join(kept)


@functools.cache
def template(filename: str) -> str:
    """The text of ``templates/<filename>`` (package data)."""
    return (resources.files("estim.codegen") / "templates" / filename).read_text(encoding="utf-8")


def fill(text: str, name: str, model: Model, description: str, values: Mapping[str, str],
         dims: Mapping[str, int], switches: Mapping[str, bool] | None = None,
         flags: str = CFLAGS) -> str:
    """``text`` with its sections chosen and its placeholders ``@key@`` replaced (see the
    module's docstring).

    Parameters
    ----------
    text : str
        A template.
    name : str
        The C identifier of the export.
    model : Model
        The estimator's model (its name and the names of states, outputs, inputs).
    description : str
        What the estimator is, for ``@filter@``.
    values : mapping of str to str
        Text by placeholder, replaced after the fixed ones.
    dims : mapping of str to int
        Integers by placeholder, replaced last.
    switches : mapping of str to bool, optional
        The switches of the template's sections (none by default).
    flags : str
        The Makefile's compiler flags (``@CFLAGS@``).
    """
    text = sections(text, switches or {})
    text = (text.replace("@name@", name).replace("@NAME@", name.upper())
            .replace("@filter@", description).replace("@model@", model.name)
            .replace("@version@", __version__).replace("@CFLAGS@", flags)
            .replace("@TAIL@", f"{SUSPECT_TAIL:g}")
            .replace("@states@", ", ".join(model.state_names))
            .replace("@outputs@", ", ".join(model.output_names))
            .replace("@inputs@", ", ".join(model.input_names) or "none"))
    for key, value in values.items():
        text = text.replace(f"@{key}@", value)
    for key, size in dims.items():
        text = text.replace(f"@{key}@", str(size))
    return text


def write_driver(paths: Mapping[str, Path], kind: str, name: str, model: Model,
                 description: str, values: Mapping[str, str], dims: Mapping[str, int],
                 switches: Mapping[str, bool] | None = None, flags: str = CFLAGS) -> None:
    """Write the driver's header and source, the Makefile, the README and the example
    program of ``kind`` (``"kalman"`` or ``"mhe"``: the templates ``<kind>.h.in``,
    ``<kind>.c.in``, ``<kind>.README.md.in`` and the shared ``Makefile.in`` and
    ``example.c.in``, their sections chosen by ``switches``) to ``paths["h"]``,
    ``paths["c"]``, ``paths["makefile"]``, ``paths["readme"]`` and ``paths["example"]``;
    ``flags``: the Makefile's compiler flags."""
    files = {"h": f"{kind}.h.in", "c": f"{kind}.c.in", "makefile": "Makefile.in",
             "readme": f"{kind}.README.md.in", "example": "example.c.in"}
    tangent = model.state_names if model.manifold.euclidean_states else \
        model.manifold.tangent_names
    values = {**values, **example_text(model, tangent)}
    switches = {"variable_dt": model.variable_dt, **(switches or {}), "mhe": kind == "mhe"}
    for key, filename in files.items():
        paths[key].write_text(fill(template(filename), name, model, description, values,
                                   dims, switches, flags))


def example_text(model: Model, tangent: Sequence[str]) -> dict[str, str]:
    """The example program's file formats: the record's and the estimates' header lines
    and what the record's inputs are."""
    u_note = ")" if not model.nu else \
        (f"), then the {model.nu} input(s) that acted since the previous sample (with "
         f"hold=\"foh\": the input at this sample)")
    stamp = ["t"] if model.variable_dt else []
    t_note = "\n *   the time stamp t first (the model's variable_dt: each interval from it)," \
        if model.variable_dt else ""
    return {"record_header": ",".join([*stamp, *model.output_names, *model.input_names]),
            "estimate_header": ",".join(["status", *model.state_names,
                                         *(f"sd_{n}" for n in tangent)]),
            "u_note": u_note, "t_note": t_note}


def c_double(v: float) -> str:
    """A double as C reads it back exactly (shortest round trip)."""
    v = float(v)
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(v)


def c_array(a: ArrayLike) -> str:
    """An initializer ``{...}`` of the doubles of ``a`` in column-major order
    (``{0.0}`` for an empty ``a``: C has no empty initializer)."""
    a = np.asarray(a, dtype=float).ravel(order="F")
    return "{" + ", ".join(c_double(v) for v in a) + "}" if a.size else "{0.0}"


def renamed(fun: ca.Function, name: str, names_in: list[str] | None = None) -> ca.Function:
    """``fun`` under another name, every output dense (an MX Function stays one, so
    that the Functions it calls are generated once)."""
    args: Any = fun.mx_in() if fun.is_a("MXFunction") else fun.sx_in()
    return ca.Function(name, args, [ca.densify(o) for o in fun.call(args)],
                       names_in or fun.name_in(), fun.name_out())


def work_sizes(funs: Sequence[ca.Function]) -> dict[str, int]:
    """CasADi's work memory that serves every one of ``funs``: the largest number of
    argument pointers, result pointers, integers and doubles (each at least 1)."""
    return {k: max(1, *(int(getattr(f, f"sz_{k}")()) for f in funs))
            for k in ("arg", "res", "iw", "w")}


def generate(funs: Sequence[ca.Function], directory: Path, name: str) -> None:
    """CasADi's C code of ``funs``: ``<name>_functions.c`` and ``<name>_functions.h``
    in ``directory``."""
    gen = ca.CodeGenerator(f"{name}_functions.c", {"with_header": True})
    for fun in funs:
        gen.add(fun)
    gen.generate(str(directory) + "/")
