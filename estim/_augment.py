"""Parameters as states: :meth:`Model.augment`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._discretise import as_column
from estim._validate import as_bounds

__all__ = ["augmented"]


def augmented(model: Any, names: tuple[str, ...], lower: ArrayLike | None,
               upper: ArrayLike | None) -> Any:
    """:meth:`Model.augment`: ``model`` with the parameters ``names`` appended to the
    state, with constant dynamics."""
    if not names:
        raise ValueError("augment needs at least one parameter name")
    for n in names:
        if n not in model.param_names:
            raise ValueError(f"cannot augment unknown parameter {n!r}; "
                             f"parameters are {model.param_names}")
    if len(set(names)) != len(names):
        raise ValueError(f"augment got duplicate names {names}")
    appended = list(names)
    values = model.params
    new_lower = as_bounds(lower, appended, "lower", -np.inf)
    new_upper = as_bounds(upper, appended, "upper", np.inf)
    augmented = type(model)(
        states=model.state_names + appended,
        outputs=model.output_names,
        dt=model.dt,
        inputs=model.input_names,
        params={k: v for k, v in values.items() if k not in appended},
        integrator=model.integrator,
        substeps=model.substeps,
        lower=np.concatenate([model.lower, new_lower]),
        upper=np.concatenate([model.upper, new_upper]),
        name=model.name,
        hold=model.hold,
        variable_dt=model.variable_dt,
        time_unit=model.time_unit,
        **model.manifold.declared,
        **_augmented_equations(model, appended),
    )
    augmented.augmented = {**model.augmented, **{n: values[n] for n in appended}}
    return augmented


def _augmented_equations(model: Any, names: list[str]) -> dict[str, Any]:
    """The equations of ``model`` on the state ``[x; theta]``, ``theta`` the parameters
    ``names`` (constant): ``output`` and ``ode`` or ``dynamics`` (and ``alg`` for a
    model with algebraic states: every equation then takes ``(x, z, u, p)``), by
    keyword."""
    nx0 = model.nx
    base_ode, base_dyn, base_out, base_alg = (model._ode, model._dynamics, model._output,
                                              model._alg)

    def split(x: ca.SX, p: Mapping[str, ca.SX]) -> tuple[ca.SX, dict[str, ca.SX]]:
        q = dict(p)
        for i, n in enumerate(names):
            q[n] = x[nx0 + i]
        return x[:nx0], q

    # (x, u, p), or (x, z, u, p) with algebraic states: p last, the rest passed on
    def output(x: ca.SX, *rest: Any) -> object:
        xs, q = split(x, rest[-1])
        return base_out(xs, *rest[:-1], q)

    out: dict[str, Any] = {"output": output}
    if base_alg is not None:
        def alg(x: ca.SX, *rest: Any) -> object:
            xs, q = split(x, rest[-1])
            return base_alg(xs, *rest[:-1], q)
        out.update(alg=alg, algebraic=model.algebraic_names, z0=model.z0)
    if base_ode is not None:
        def ode(x: ca.SX, *rest: Any) -> object:
            xs, q = split(x, rest[-1])
            return ca.vertcat(as_column(base_ode(xs, *rest[:-1], q), nx0, "ode"),
                              ca.SX.zeros(len(names)))
        return {**out, "ode": ode}
    assert base_dyn is not None  # a model has exactly one of ode and dynamics

    def dynamics(x: ca.SX, u: ca.SX, p: Mapping[str, ca.SX]) -> object:
        xs, q = split(x, p)
        return ca.vertcat(as_column(base_dyn(xs, u, q), nx0, "dynamics"), x[nx0:])
    return {**out, "dynamics": dynamics}
