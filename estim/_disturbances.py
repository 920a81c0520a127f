r"""Disturbance models for offset-free estimation: :meth:`Model.with_disturbances`.

A plant that differs from its model by a constant (an unmeasured load on an input,
a drifting sensor, a feed that is not what the recipe says) leaves every estimator
of the model with a steady-state offset. The classic remedy of offset-free model
predictive control (Muske, Badgwell 2002; Pannocchia, Rawlings 2003) augments the
model with integrating disturbances, states with random-walk dynamics that the
estimator identifies:

.. math::
    x_{k+1} = F(x_k,\, u_k + E_u d_k), \qquad d_{k+1} = d_k, \qquad
    y_k = h(x_k,\, u_k + E_u d_k) + E_y p_k, \qquad p_{k+1} = p_k,

with :math:`d` on the named inputs (:math:`E_u` selects them) and :math:`p` on the
named outputs (continuous models: :math:`\dot d = 0`, :math:`\dot p = 0`). How fast
the estimates follow a disturbance is their process noise, entries of the tuning
``Q`` like any state's.

The augmented model is detectable only if the disturbances can be told apart from
the states at steady state. With :math:`A = \partial F / \partial x`,
:math:`B_d = \partial F / \partial d`, :math:`C = \partial h / \partial x` and
:math:`C_d = \partial y / \partial (d, p)` at a linearisation point, and the model
itself detectable, the augmented one is detectable if and only if

.. math::
    \operatorname{rank} \begin{bmatrix} I - A & -B_d \\ C & C_d \end{bmatrix}
    = n_x + n_d

(Pannocchia, Rawlings 2003, Lemma 1), which needs :math:`n_d \le n_y`. The null
vectors of that matrix are the steady states :math:`(x, d)` that no output sees;
the disturbances with a component in them are the ones named when it fails.

References
----------
K. R. Muske, T. A. Badgwell, "Disturbance modeling for offset-free linear model
predictive control", J. Process Control 12(5), 2002;
G. Pannocchia, J. B. Rawlings, "Disturbance models for offset-free model-predictive
control", AIChE J. 49(2), 2003.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from estim._discretise import as_column
from estim._validate import as_bool, as_choice, as_vector

__all__ = ["KINDS", "augment", "detectability"]

#: The kinds of disturbance model.
KINDS = ("integrating",)
#: Singular values below this fraction of the largest count as zero in the rank test.
RANK_TOL = 1e-9


def _names(value: Sequence[str] | None, known: list[str], what: str, arg: str) -> list[str]:
    """The names ``value`` (a list of strings among ``known``), checked."""
    if value is None:
        return []
    if isinstance(value, str):
        value = [value]
    try:
        names = list(value)
    except TypeError:
        raise TypeError(f"{arg} must be a list of {what} names, got "
                        f"{type(value).__name__}") from None
    for n in names:
        if not isinstance(n, str):
            raise TypeError(f"{arg} must be a list of {what} names, got {n!r}")
        if n not in known:
            raise ValueError(f"{arg}: {n!r} is not an {what} of the model; its {what}s are "
                             f"{known}")
    if len(set(names)) != len(names):
        raise ValueError(f"{arg} names an {what} twice: {names}")
    return names


def _state_names(model: Any, inputs: list[str], outputs: list[str]) -> list[str]:
    """``d_<name>`` for each disturbance; ``d_u_``/``d_y_`` where an input and an output
    share a name; an error if a name is taken by a state."""
    both = set(inputs) & set(outputs)
    names = [f"d_u_{n}" if n in both else f"d_{n}" for n in inputs] + \
        [f"d_y_{n}" if n in both else f"d_{n}" for n in outputs]
    taken = [n for n in names if n in model.state_names]
    if taken:
        raise ValueError(f"the disturbance states {taken} would take the names of states of "
                         f"the model; rename those states")
    return names


def _equations(model: Any, E_u: np.ndarray, E_y: np.ndarray) -> dict[str, Any]:
    """The model's equations on the state ``[x; d; p]`` (see the module), by keyword;
    each takes ``(x, u, p)``, or ``(x, z, u, p)`` with algebraic states."""
    nx, n_in = model.nx, E_u.shape[1]
    nd = n_in + E_y.shape[1]
    base_ode, base_dyn, base_out = model._ode, model._dynamics, model._output
    base_alg = getattr(model, "_alg", None)
    Eu, Ey = ca.DM(E_u), ca.DM(E_y)

    def split(x: ca.SX, u: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX]:
        u_eff = u + Eu @ x[nx:nx + n_in] if n_in else u
        return x[:nx], u_eff, x[nx + n_in:]

    def output(x: ca.SX, *rest: Any) -> ca.SX:
        *z, u, p = rest
        xs, ue, py = split(x, u)
        y = as_column(base_out(xs, *z, ue, p), model.ny, "output")
        return y + Ey @ py if E_y.shape[1] else y

    out: dict[str, Any] = {"output": output}
    if base_alg is not None:
        def alg(x: ca.SX, *rest: Any) -> object:
            *z, u, p = rest
            xs, ue, _ = split(x, u)
            return base_alg(xs, *z, ue, p)
        out.update(alg=alg, algebraic=model.algebraic_names, z0=model.z0)
    if base_ode is not None:
        def ode(x: ca.SX, *rest: Any) -> ca.SX:
            *z, u, p = rest
            xs, ue, _ = split(x, u)
            return ca.vertcat(as_column(base_ode(xs, *z, ue, p), nx, "ode"), ca.SX.zeros(nd))
        return {**out, "ode": ode}

    def dynamics(x: ca.SX, u: ca.SX, p: Mapping[str, ca.SX]) -> ca.SX:
        xs, ue, _ = split(x, u)
        return ca.vertcat(as_column(base_dyn(xs, ue, p), nx, "dynamics"), x[nx:])
    return {**out, "dynamics": dynamics}


def augment(model: Any, inputs: Sequence[str] | None, outputs: Sequence[str] | None,
            kind: str, check: bool, at: tuple[ArrayLike, ArrayLike] | None) -> Any:
    """:meth:`Model.with_disturbances` (see there and the module)."""
    kind = as_choice(kind, KINDS, "kind")
    check = as_bool(check, "check")
    ins = _names(inputs, model.input_names, "input", "inputs")
    outs = _names(outputs, model.output_names, "output", "outputs")
    if not ins and not outs:
        raise ValueError("with_disturbances needs at least one input or output to disturb "
                         "(inputs=[...] or outputs=[...])")
    names = _state_names(model, ins, outs)
    E_u = np.zeros((model.nu, len(ins)))
    for j, n in enumerate(ins):
        E_u[model.input_names.index(n), j] = 1.0
    E_y = np.zeros((model.ny, len(outs)))
    for j, n in enumerate(outs):
        E_y[model.output_names.index(n), j] = 1.0
    nd = len(names)
    new = type(model)(
        states=model.state_names + names, outputs=model.output_names, dt=model.dt,
        inputs=model.input_names, params=model.params, integrator=model.integrator,
        substeps=model.substeps, lower=np.concatenate([model.lower, np.full(nd, -np.inf)]),
        upper=np.concatenate([model.upper, np.full(nd, np.inf)]), name=model.name,
        hold=model.hold, variable_dt=model.variable_dt, time_unit=model.time_unit,
        **model.manifold.declared, **_equations(model, E_u, E_y))
    new.augmented = dict(model.augmented)
    old = model.disturbances  # a model that has disturbances already keeps them
    new.disturbances = {
        "inputs": {**old.get("inputs", {}), **dict(zip(ins, names[:len(ins)], strict=True))},
        "outputs": {**old.get("outputs", {}),
                    **dict(zip(outs, names[len(ins):], strict=True))},
        "kind": kind}
    if at is None:
        x_at, u_at = np.zeros(model.nx), np.zeros(model.nu)
    else:
        if not isinstance(at, tuple | list) or len(at) != 2:
            raise TypeError("at must be a pair (x, u): the state and input at which the "
                            "rank condition is checked")
        x_at = as_vector(at[0], model.nx, "at[0] (x)")
        u_at = as_vector(at[1], model.nu, "at[1] (u)")
    problem = detectability(new, x_at, u_at)
    if problem:
        message = f"{problem} (with_disturbances(..., at=(x, u)) sets the linearisation " \
            "point; check=False keeps the model with a warning)"
        if check:
            raise ValueError(message)
        warnings.warn(message, stacklevel=3)
    return new


def detectability(model: Any, x: np.ndarray, u: np.ndarray) -> str:
    """Why the disturbance model ``model`` (from :func:`augment`) is not detectable at
    ``(x, u)`` (the model's own state and input), or an empty string: the count
    :math:`n_d \\le n_y` and the rank condition of the module."""
    dist = model.disturbances
    d_names = list(dist["inputs"].values()) + list(dist["outputs"].values())
    nd, ny = len(d_names), model.ny
    n = model.nx - nd
    if nd > ny:
        outputs = "1 output" if ny == 1 else f"{ny} outputs"
        return (f"{nd} disturbances {d_names} but {outputs}: at most as many "
                f"disturbances as outputs can be detected")
    z = np.concatenate([np.asarray(x, float), np.zeros(nd)])
    w = model.transition(np.asarray(u, float), np.asarray(u, float))  # held at u
    J = np.asarray(model.F_x(z, w, model.p))  # [[A, B_d], [0, I]]
    C = np.asarray(model.H_x(z, model.measurement_input(w), model.p))
    M = np.vstack([np.hstack([np.eye(n) - J[:n, :n], -J[:n, n:]]), C])
    if not np.isfinite(M).all():
        return f"the linearisation at x = {np.asarray(x).tolist()} is not finite"
    _, s, Vt = np.linalg.svd(M)
    tol = RANK_TOL * max(s.max(initial=0.0), 1.0)
    rank = int((s > tol).sum())
    if rank == n + nd:
        return ""
    null = Vt[rank:]  # the steady states (x, d) no output sees
    weight = np.abs(null[:, n:]).max(axis=0)
    culprits = [d for d, v in zip(d_names, weight, strict=True) if v > 1e-6] or d_names
    return (f"the disturbances {culprits} are not detectable: rank [[I - A, -B_d], "
            f"[C, C_d]] = {rank} < n_x + n_d = {n + nd} at x = "
            f"{np.round(np.asarray(x, float), 6).tolist()} (a steady state with these "
            f"disturbances leaves every output unchanged)")
