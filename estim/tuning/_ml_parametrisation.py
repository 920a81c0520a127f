r"""The parameters of maximum likelihood: ``Q`` and ``R`` positive definite by construction.

The vector :math:`\theta` the optimiser moves holds, for each covariance, by structure

* ``"diagonal"``: the log-variances, :math:`Q = \operatorname{diag}(e^{\theta_1}, \dots)`;
* ``"scalar"``: one log-variance, :math:`Q = e^{\theta} I`;
* ``"full"``: the log-Cholesky factor, :math:`Q = LL^\top` with
  :math:`L_{ii} = e^{\theta_{ii}}` and :math:`L_{ij} = \theta_{ij}` below the diagonal
  (Pinheiro & Bates 1996);
* ``"fixed"``: nothing, the matrix held at its start,

then the estimated model parameters, by name. Every :math:`\theta` gives positive
definite matrices, so the likelihood is maximised without constraints; the delta method
takes the covariance of :math:`\hat\theta` to the entries through the Jacobian of
:math:`\theta \mapsto (\operatorname{vec} Q, \operatorname{vec} R, p)`.

J. C. Pinheiro, D. M. Bates, "Unconstrained parametrizations for variance-covariance
matrices", Statistics and Computing 6, 289-296, 1996.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import casadi as ca
import numpy as np

from estim._validate import as_choice, as_float
from estim.model import Model

STRUCTURES = ("diagonal", "full", "scalar", "fixed")


def _structures(structure: object) -> dict[str, str]:
    """The structure of ``Q`` and of ``R`` (one for both, or a dict of them)."""
    if isinstance(structure, str):
        s = as_choice(structure, STRUCTURES, "structure")
        return {"Q": s, "R": s}
    if isinstance(structure, Mapping):
        unknown = sorted(set(structure) - {"Q", "R"})
        if unknown:
            raise ValueError(f"structure as a dict takes the keys 'Q' and 'R', got {unknown}")
        return {k: as_choice(structure.get(k, "diagonal"), STRUCTURES, f"structure[{k!r}]")
                for k in ("Q", "R")}
    raise TypeError(f"structure must be one of {STRUCTURES} or a dict {{'Q': ..., 'R': ...}}, "
                    f"got {type(structure).__name__}")


def _covariance_of(theta: ca.SX, kind: str, n: int, fixed: ca.SX) -> tuple[ca.SX, int]:
    """The covariance of its parameters: ``(matrix expression, number used)``; ``fixed``
    is the (symbolic) matrix a ``"fixed"`` structure holds."""
    if kind == "fixed":
        return fixed, 0
    if kind == "scalar":
        return ca.exp(theta[0]) * ca.SX.eye(n), 1
    if kind == "diagonal":
        return ca.diag(ca.exp(theta[:n])), n
    L = ca.SX(n, n)  # log-Cholesky: L_ii = exp(theta), L_ij = theta below the diagonal
    i = 0
    for col in range(n):
        for row in range(col, n):
            L[row, col] = ca.exp(theta[i]) if row == col else theta[i]
            i += 1
    return L @ L.T, i


def _initial(kind: str, C: np.ndarray, name: str) -> np.ndarray:
    """The parameters of a starting covariance."""
    if kind == "fixed":
        return np.zeros(0)
    d = np.diag(C)
    if kind in ("scalar", "diagonal") and not (d > 0).all():
        raise ValueError(f"{name} must have a positive diagonal for structure {kind!r} "
                         f"(use 'fixed' to hold it), got diagonal {d}")
    if kind == "scalar":
        return np.array([np.log(d.mean())])
    if kind == "diagonal":
        return np.log(d)
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        raise ValueError(f"{name} must be positive definite for structure 'full'") from None
    n = C.shape[0]
    return np.array([np.log(L[r, c]) if r == c else L[r, c]
                     for c in range(n) for r in range(c, n)])


def _params_spec(model: Model, params: object) -> dict[str, float]:
    """``params`` (None, names, or ``{name: start}``) as ``{name: start}``."""
    if params is None:
        return {}
    if isinstance(params, str):
        params = [params]
    if isinstance(params, Mapping):
        spec = {k: as_float(v, f"params[{k!r}]") for k, v in params.items()}
    elif isinstance(params, Sequence):
        spec = {k: float(model.params[k]) if k in model.params else np.nan for k in params}
    else:
        raise TypeError(f"params must be a list of parameter names or a dict {{name: start}}, "
                        f"got {type(params).__name__}")
    unknown = [k for k in spec if not isinstance(k, str) or k not in model.param_names]
    if unknown:
        raise ValueError(f"params names unknown parameters {unknown}; the model's parameters "
                         f"are {model.param_names}")
    return spec


class _Parametrisation:
    r"""``(theta, fixed) -> (vec Q, vec R, p)``: log-variances (diagonal, scalar) or the
    log-Cholesky factor (full), then the estimated model parameters; ``fixed = [vec Q0;
    vec R0; p]`` holds what is not estimated (data, so that the compiled objective serves
    any start and record of the same length)."""

    def __init__(self, model: Model, structures: dict, Q0: np.ndarray, R0: np.ndarray,
                 spec: dict[str, float]):
        nx, ny = Q0.shape[0], model.ny  # nx: the size of Q (of Qc, nq, with a noise input)
        self.structures = structures
        self.names = list(spec)
        index = [model.param_names.index(k) for k in spec]
        t0 = [_initial(structures["Q"], Q0, "Q0"), _initial(structures["R"], R0, "R0")]
        self.n_noise = sum(len(t) for t in t0)
        # the parameters that are logs: (theta index, matrix, diagonal entry or None for
        # a scalar, 1 for a log-variance or 2 for a log-Cholesky diagonal)
        self.logs: list[tuple[int, str, int | None, int]] = []
        offset = 0
        for name, n in (("Q", nx), ("R", ny)):
            kind = structures[name]
            if kind == "scalar":
                self.logs.append((offset, name, None, 1))
            elif kind == "diagonal":
                self.logs += [(offset + i, name, i, 1) for i in range(n)]
            elif kind == "full":
                k = 0
                for col in range(n):
                    for row in range(col, n):
                        if row == col:
                            self.logs.append((offset + k, name, col, 2))
                        k += 1
            offset += len(t0[0]) if name == "Q" else 0
        self.theta0 = np.concatenate(t0 + [np.array(list(spec.values()), dtype=float)])
        self.fixed = np.concatenate([Q0.ravel(order="F"), R0.ravel(order="F"), model.p])
        self.key = (structures["Q"], structures["R"], tuple(index))
        theta = ca.SX.sym("theta", self.theta0.size)
        fixed = ca.SX.sym("fixed", self.fixed.size)
        Q, nq = _covariance_of(theta, structures["Q"], nx, ca.reshape(fixed[:nx * nx], nx, nx))
        R, nr = _covariance_of(theta[nq:], structures["R"], ny,
                               ca.reshape(fixed[nx * nx:nx * nx + ny * ny], ny, ny))
        p = fixed[nx * nx + ny * ny:]
        for j, i in enumerate(index):
            p[i] = theta[nq + nr + j]
        out = ca.vertcat(ca.vec(Q), ca.vec(R), p[index] if index else ca.SX(0, 1))
        self.unpack = ca.Function("unpack", [theta, fixed], [ca.vec(Q), ca.vec(R), p])
        self._entries = ca.Function("entries", [theta, fixed], [out, ca.jacobian(out, theta)])

    def entries(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The estimated entries ``[vec Q; vec R; params]`` and their Jacobian."""
        out, J = self._entries(theta, self.fixed)
        return np.asarray(out, dtype=float).ravel(), np.asarray(J, dtype=float)

    def matrices(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``vec Q``, ``vec R`` and the model's parameter vector at ``theta``."""
        q, r, p = (np.asarray(v, dtype=float).ravel() for v in self.unpack(theta, self.fixed))
        return q, r, p

