r"""States and outputs on manifolds: unit quaternions and angles.

A model may declare groups of four states as a unit quaternion (scalar first,
:math:`q = (q_w, q_x, q_y, q_z)`, Hamilton product) and single states or outputs as
angles in radians. Its state then lives on a manifold of dimension ``ndx`` (3 per
quaternion, 1 per other state), and an error between two states is a vector of its
tangent space:

.. math::
    x \oplus \delta: \quad q \otimes \operatorname{Exp}(\delta\theta), \quad
    \operatorname{wrap}(\psi + \delta\psi), \quad x_i + \delta_i;
    \qquad x_2 \ominus x_1: \quad \operatorname{Log}(q_1^{-1} \otimes q_2), \quad
    \operatorname{wrap}(\psi_2 - \psi_1), \quad x_{2,i} - x_{1,i},

with :math:`\operatorname{Exp}(\phi) = (\cos\tfrac{|\phi|}{2},
\sin\tfrac{|\phi|}{2}\, \phi / |\phi|)` (a rotation by :math:`|\phi|` about
:math:`\phi`, i.e. :math:`q = \hat q \otimes \exp(\delta\theta / 2)`), its inverse
:math:`\operatorname{Log}` taken on the hemisphere :math:`q_w \ge 0` (so
:math:`|\delta\theta| \le \pi`), and :math:`\operatorname{wrap}` onto
:math:`(-\pi, \pi]`. The tangent coordinates are ordered as the states, a quaternion's
three at the place of its first component. Output angles make the innovation
:math:`y \ominus \hat y` wrapped.

The formulas are written once on components (:class:`_Ops`): as CasADi expressions
for the estimators' graphs and on numpy arrays for the metrics. Near
:math:`\phi = 0` the ratios :math:`\sin(|\phi|/2)/|\phi|` and
:math:`\operatorname{atan2}(s, w)/s` are their Taylor series (exact to rounding, and
smooth, so the algorithmic derivatives at zero are exact).

References
----------
F. L. Markley, J. L. Crassidis, *Fundamentals of Spacecraft Attitude Determination
and Control*, Springer 2014, ch. 6; J. Solà, J. Deray, D. Atchuthan, "A micro Lie
theory for state estimation in robotics", arXiv:1812.01537, 2018.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np

from estim.exceptions import EstimationWarning

__all__ = ["Manifold", "on_manifold", "unit_quaternions", "wrap"]

#: Below this squared norm the Taylor series of the Exp/Log ratios are used.
_SMALL = 1e-8


@dataclass(frozen=True)
class _Ops:
    """The elementary functions of a backend (CasADi symbols or numpy arrays)."""

    sqrt: Any
    sin: Any
    cos: Any
    atan2: Any
    where: Any
    ceil: Any


CA = _Ops(ca.sqrt, ca.sin, ca.cos, ca.atan2, ca.if_else, ca.ceil)
NP = _Ops(np.sqrt, np.sin, np.cos, np.arctan2, np.where, np.ceil)


def wrap(a: Any, ops: _Ops = NP) -> Any:
    r"""``a`` wrapped onto :math:`(-\pi, \pi]`: :math:`a - 2\pi \lceil (a - \pi) / 2\pi
    \rceil` (derivative 1)."""
    return a - 2 * math.pi * ops.ceil((a - math.pi) / (2 * math.pi))


def _product(a: Sequence[Any], b: Sequence[Any]) -> list[Any]:
    """The Hamilton product ``a ⊗ b`` of scalar-first quaternions (components)."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return [aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw]


def _exp(phi: Sequence[Any], ops: _Ops) -> list[Any]:
    r""":math:`\operatorname{Exp}(\phi)`: the unit quaternion of the rotation vector
    ``phi`` (components)."""
    n2 = phi[0] ** 2 + phi[1] ** 2 + phi[2] ** 2
    small = n2 < _SMALL
    safe = ops.where(small, 1.0, n2)  # the other branch never sees 0 (nor its derivative)
    n = ops.sqrt(safe)
    c = ops.where(small, 1 - n2 / 8 + n2 ** 2 / 384, ops.cos(n / 2))
    s = ops.where(small, 0.5 - n2 / 48 + n2 ** 2 / 3840, ops.sin(n / 2) / n)
    return [c, s * phi[0], s * phi[1], s * phi[2]]


def _log(q: Sequence[Any], ops: _Ops) -> list[Any]:
    r""":math:`\operatorname{Log}(q)`: the rotation vector of the unit quaternion ``q``
    on the hemisphere :math:`q_w \ge 0` (components)."""
    sign = ops.where(q[0] < 0, -1.0, 1.0)
    w, v = sign * q[0], [sign * c for c in q[1:]]
    s2 = v[0] ** 2 + v[1] ** 2 + v[2] ** 2
    small = s2 < _SMALL
    safe_s = ops.sqrt(ops.where(small, 1.0, s2))
    safe_w = ops.where(small, w, 1.0)
    # 2 atan2(s, w) / s; its series about s = 0: (2 / w) (1 - s^2 / (3 w^2) + s^4 / (5 w^4))
    r = s2 / safe_w ** 2
    ratio = ops.where(small, 2 / safe_w * (1 - r / 3 + r ** 2 / 5),
                      2 * ops.atan2(safe_s, w) / safe_s)
    return [ratio * c for c in v]


class Manifold:
    """The layout of a model's states and outputs on their manifolds.

    Parameters
    ----------
    state_names, output_names : list of str
    quaternions : list of four state names each
    angles : list of state names
    output_angles : list of output names

    Attributes
    ----------
    nx, ndx : int
        Stored states and tangent directions.
    quaternions : list of tuple of int
        The state indices of each quaternion.
    angles, output_angles : list of int
    tangent_names : list of str
        The tangent coordinates: ``theta_x, theta_y, theta_z`` (suffixed ``_1``,
        ``_2``, ... for several quaternions) at the place of a quaternion, else the
        state's name.
    """

    def __init__(self, state_names: Sequence[str], output_names: Sequence[str],
                 quaternions: Any = None, angles: Any = None,
                 output_angles: Any = None) -> None:
        names = list(state_names)
        groups = _groups(quaternions, names)
        #: the declaration by names (``Model(**manifold.declared)`` on a derived model)
        self.declared = {"quaternions": groups,
                         "angles": _names(angles, names, "angles", "states"),
                         "output_angles": _names(output_angles, list(output_names),
                                                 "output_angles", "outputs")}
        self.quaternions = [tuple(names.index(n) for n in g) for g in groups]
        in_quaternion = {i for g in self.quaternions for i in g}
        self.angles = [names.index(n) for n in _names(angles, names, "angles", "states")]
        bad = [names[i] for i in self.angles if i in in_quaternion]
        if bad:
            raise ValueError(f"angles: {bad} are quaternion components (declared in "
                             f"quaternions=); a quaternion's error is its rotation vector")
        self.output_angles = [list(output_names).index(n) for n in
                              _names(output_angles, list(output_names), "output_angles",
                                     "outputs")]
        self.nx = len(names)
        # the tangent layout: per stored state, its tangent index (None for the 2nd-4th
        # quaternion components); a quaternion's three at the place of its first
        first = {min(g): g for g in self.quaternions}
        self._segments: list[tuple[str, Any, Any]] = []
        self.tangent_names: list[str] = []
        j = 0
        for i, name in enumerate(names):
            if i in first:
                suffix = f"_{len([s for s in self._segments if s[0] == 'q']) + 1}" \
                    if len(self.quaternions) > 1 else ""
                self._segments.append(("q", first[i], (j, j + 1, j + 2)))
                self.tangent_names += [f"theta_{a}{suffix}" for a in "xyz"]
                j += 3
            elif i not in in_quaternion:
                self._segments.append(("a" if i in self.angles else "e", i, j))
                self.tangent_names.append(name)
                j += 1
        self.ndx = j

    @property
    def trivial(self) -> bool:
        """Nothing declared: every state and output is an ordinary vector entry."""
        return not (self.quaternions or self.angles or self.output_angles)

    @property
    def euclidean_states(self) -> bool:
        """No quaternion and no angle among the states (``x ⊕ δ = x + δ``)."""
        return not (self.quaternions or self.angles)

    # ------------------------------------------------------ the padded tangent
    # The windowed solvers keep one block of size nx per slot: their tangent vector is
    # *padded* to nx, each tangent coordinate at the stored position of its state (a
    # quaternion's three at its first three components) and a pad, always 0, at each
    # quaternion's fourth. Euclidean states keep their positions, so bounds apply as
    # they are.
    @cached_property
    def slots(self) -> list[int]:
        """The stored position of each tangent coordinate in a padded tangent vector."""
        out = [0] * self.ndx
        for kind, i, j in self._segments:
            for a, b in (zip(j, i[:3], strict=True) if kind == "q" else [(j, i)]):
                out[a] = b
        return out

    @cached_property
    def pads(self) -> list[int]:
        """The positions of the pads: the fourth component of each quaternion."""
        return [g[3] for g in self.quaternions]

    def padded(self, v: Any) -> Any:
        """A tangent vector ``(..., ndx)`` padded to ``(..., nx)`` (CasADi column or
        numpy array)."""
        if isinstance(v, np.ndarray):
            out = np.zeros(v.shape[:-1] + (self.nx,))
            out[..., self.slots] = v
            return out
        parts: list[Any] = [0.0] * self.nx
        for j, i in enumerate(self.slots):
            parts[i] = v[j]
        return ca.vertcat(*parts)

    def padded_matrix(self, M: np.ndarray) -> np.ndarray:
        """An ``ndx x ndx`` matrix embedded at the tangent positions of an ``nx x nx``
        one, 1 on the pads' diagonal."""
        out = np.zeros((self.nx, self.nx))
        out[np.ix_(self.slots, self.slots)] = M
        out[self.pads, self.pads] = 1.0
        return out

    def window_moves(self, N: int) -> tuple[ca.Function, ca.Function]:
        """The moves of a window of ``N`` slots, as Functions built once (the windowed
        solvers' line searches and the exported C call them): ``retract_window(X, D) ->
        X (+) D`` (each slot by its padded tangent step, ``(nx, N)``) and
        ``local_window(X, X_to) -> X_to (-) X`` (``(ndx, N)``)."""
        X, D, X2 = (ca.SX.sym(n, self.nx, N) for n in ("X", "D", "X_to"))
        moved = ca.horzcat(*[self.retract(X[:, k], D[self.slots, k]) for k in range(N)])
        local = ca.horzcat(*[self.local(X[:, k], X2[:, k]) for k in range(N)])
        return (ca.Function("retract_window", [X, D], [moved], ["X", "D"], ["X_moved"]),
                ca.Function("local_window", [X, X2], [local], ["X", "X_to"], ["D"]))

    def unpadded_matrix(self, M: np.ndarray) -> np.ndarray:
        """The tangent block ``(..., ndx, ndx)`` of a padded ``(..., nx, nx)`` one."""
        s = self.slots
        return M[..., s, :][..., :, s]

    # ------------------------------------------------------------ the operations
    def retract(self, x: Any, d: Any, ops: _Ops = CA) -> Any:
        r""":math:`x \oplus \delta`: ``x`` (nx,) moved by the tangent vector ``d`` (ndx,);
        CasADi columns (or, with ``ops=NP``, numpy arrays with the coordinates on the
        last axis)."""
        out = [x[..., i] if ops is NP else x[i] for i in range(self.nx)]
        dd = [d[..., j] if ops is NP else d[j] for j in range(self.ndx)]
        for kind, i, j in self._segments:
            if kind == "q":
                q = _product([out[k] for k in i], _exp([dd[k] for k in j], ops))
                norm = ops.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
                for k, c in zip(i, q, strict=True):
                    out[k] = c / norm
            else:
                out[i] = out[i] + dd[j] if kind == "e" else wrap(out[i] + dd[j], ops)
        return np.stack(out, axis=-1) if ops is NP else ca.vertcat(*out)

    def local(self, x: Any, x2: Any, ops: _Ops = CA) -> Any:
        r""":math:`x_2 \ominus x`: the tangent vector (ndx,) from ``x`` to ``x2``."""
        a = [x[..., i] if ops is NP else x[i] for i in range(self.nx)]
        b = [x2[..., i] if ops is NP else x2[i] for i in range(self.nx)]
        out: list[Any] = [None] * self.ndx
        for kind, i, j in self._segments:
            if kind == "q":
                qa = [a[i[0]], -a[i[1]], -a[i[2]], -a[i[3]]]  # the inverse of a unit q
                for k, c in zip(j, _log(_product(qa, [b[k] for k in i]), ops), strict=True):
                    out[k] = c
            else:
                out[j] = b[i] - a[i] if kind == "e" else wrap(b[i] - a[i], ops)
        return np.stack(out, axis=-1) if ops is NP else ca.vertcat(*out)

    def output_difference(self, y: Any, yhat: Any, ops: _Ops = CA,
                          rows: Sequence[int] | None = None) -> Any:
        r""":math:`y \ominus \hat y`: ``y - yhat`` with the output angles wrapped; on numpy
        arrays the last axis may hold some outputs only, ``rows`` (default all)."""
        e = y - yhat
        if not self.output_angles:
            return e
        if ops is NP:
            e = np.array(e, dtype=float)
            at = self.output_angles if rows is None else \
                [i for i, r in enumerate(rows) if r in self.output_angles]
            e[..., at] = wrap(e[..., at])
            return e
        return ca.vertcat(*[wrap(e[i], ops) if i in self.output_angles else e[i]
                            for i in range(e.numel())])

    def normalise(self, x: Any, ops: _Ops = CA) -> Any:
        """``x`` with each quaternion scaled to unit norm (and the angles wrapped)."""
        zero = np.zeros(x.shape[:-1] + (self.ndx,)) if ops is NP else ca.DM.zeros(self.ndx)
        return self.retract(x, zero, ops)

    def mean(self, X: np.ndarray, weights: np.ndarray | None = None,
             iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
        r"""The weighted mean of points ``X`` ``(N, nx)`` on the manifold and their
        deviations from it in its tangent space ``(N, ndx)``: the fixed point of
        :math:`\bar x \leftarrow \bar x \oplus \sum_i w_i (x_i \ominus \bar x)`
        from the heaviest point (one iteration on vector states; the Karcher mean of
        the quaternions), ``weights`` default uniform."""
        X = np.asarray(X, dtype=float)
        w = np.full(len(X), 1.0 / len(X)) if weights is None else np.asarray(weights)
        ref = X[int(np.argmax(w))]
        for _ in range(1 if self.euclidean_states else iterations):
            step = w @ self.local(ref, X, NP)
            ref = self.retract(ref, step, NP)
            if np.all(np.abs(step) < 1e-13):
                break
        return ref, self.local(ref, X, NP)

    def errors(self, x_hat: np.ndarray, x: np.ndarray) -> np.ndarray:
        r"""The estimation errors :math:`\hat x \ominus x` of two stacks ``(..., nx)``:
        ``(..., ndx)`` (a quaternion's as the rotation vector from the truth to the
        estimate, whose norm is the attitude error angle)."""
        return self.local(np.asarray(x, dtype=float), np.asarray(x_hat, dtype=float), NP)


def _names(value: Any, choices: list[str], argname: str, what: str) -> list[str]:
    """A list of distinct names out of ``choices``."""
    if value is None:
        return []
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise TypeError(f"{argname} must be a list of {what[:-1]} names, got {value!r}")
    names = list(value)
    for n in names:
        if not isinstance(n, str):
            raise TypeError(f"{argname} must be a list of {what[:-1]} names, got {n!r}")
        if n not in choices:
            raise ValueError(f"{argname}: {n!r} is not one of the {what} {choices}")
    if len(set(names)) != len(names):
        raise ValueError(f"{argname} names a {what[:-1]} twice: {names}")
    return names


def _groups(value: Any, names: list[str]) -> list[tuple[str, ...]]:
    """The quaternion groups: tuples of four distinct state names, not overlapping."""
    if value is None:
        return []
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise TypeError(f"quaternions must be a list of 4-tuples of state names, e.g. "
                        f"[('q0', 'q1', 'q2', 'q3')], got {value!r}")
    groups: list[tuple[str, ...]] = []
    seen: set[str] = set()
    for g in value:
        if isinstance(g, str) or not isinstance(g, Sequence) or len(g) != 4:
            raise ValueError(f"quaternions: each quaternion is four state names (scalar "
                             f"first), got {g!r}")
        g = tuple(_names(list(g), names, "quaternions", "states"))
        overlap = seen.intersection(g)
        if overlap:
            raise ValueError(f"quaternions: {sorted(overlap)} belong to two quaternions")
        seen.update(g)
        groups.append(g)
    return groups


def on_manifold(manifold: Manifold, F: ca.Function) -> tuple[ca.Function, ca.Function]:
    """``(F, F_x)`` with the state after the transition ``F(x, w, p)`` normalised onto
    the manifold (:meth:`Manifold.normalise`: each quaternion scaled to unit norm, the
    angles wrapped), its Jacobian with respect to the stored ``x``."""
    sym: Any = ca.SX if F.is_a("SXFunction") else ca.MX
    x, w, p = (sym.sym(n, F.size1_in(i)) for i, n in enumerate(("x", "w", "p")))
    xn = manifold.normalise(F(x, w, p))
    names = ["x", "u", "p"]
    return (ca.Function("F", [x, w, p], [xn], names, ["x_next"]),
            ca.Function("F_x", [x, w, p], [ca.jacobian(xn, x)], names, ["A"]))


def unit_quaternions(manifold: Manifold, x: np.ndarray, argname: str) -> np.ndarray:
    """``x`` with each quaternion of unit norm: one of another norm is normalised with a
    warning, a zero one refused (``ValueError`` naming ``argname``)."""
    x = np.array(x, dtype=float)
    for g in manifold.quaternions:
        norm = float(np.linalg.norm(x[list(g)]))
        if norm == 0.0:
            raise ValueError(f"{argname}: the quaternion at states {list(g)} is zero; a "
                             f"unit quaternion is needed (e.g. (1, 0, 0, 0))")
        if abs(norm - 1.0) > 1e-12:
            warnings.warn(f"{argname}: the quaternion at states {list(g)} has norm "
                          f"{norm:.6g}; normalised to 1", EstimationWarning, stacklevel=3)
            x[list(g)] /= norm
    return x
