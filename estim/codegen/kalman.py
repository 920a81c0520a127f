r"""The C export of a fused Kalman filter (:class:`~estim.EKF`, :class:`~estim.UKF`).

CasADi's generated code of the filter's two step functions, ``<name>_update`` (the
first sample) and ``<name>_predict_update``, each ``(s, w, y, tuning) -> (s_new,
innovation, flags, s_prior)`` with the filter state :math:`s = [x;
\operatorname{vec}(P)]`, and the driver of ``templates/kalman.c.in``, which does with
their flags what :meth:`~estim.Estimator.step` does (the gate, the suspect flag, the
recovery of a failed update).

In the square-root form (``form="sqrt"``) the filter state is :math:`s = [x;
\operatorname{vec}(S)]`, :math:`P = S S^\top`, and the tuning
:math:`[\operatorname{vec}(L_Q); \operatorname{vec}(L_R)]`; four more generated
Functions serve the driver (:func:`factor_functions`): the factors of ``Q`` and ``R``
that a step reads, the Cholesky factor of ``P0``, the factor
:math:`\operatorname{tria}([S, \operatorname{chol}(P_0)])` of :math:`P + P_0` that the
gate and the recovery keep, and :math:`S S^\top`, the covariance a step reports.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import casadi as ca

from estim.codegen.files import (
    CFLAGS,
    c_array,
    c_double,
    generate,
    renamed,
    work_sizes,
    write_driver,
)
from estim.solvers.kalman.kalman import NFLAGS
from estim.solvers.kalman.triangular import tria

if TYPE_CHECKING:
    from estim.estimators.kalman.ekf import EKF
    from estim.estimators.kalman.ukf import UKF

#: Status codes of ``<name>_step`` (the C enum), with the Python status they stand for.
STATUS = {0: "ok", 1: "suspect", 2: "rejected", 3: "failed: kept the prediction",
          4: "failed: re-anchored", -1: "invalid argument (inf in y, non-finite u)"}

#: The names of the step functions' inputs in the generated code.
_FILTER_IN = ["s", "w", "y", "tuning"]


def functions(estimator: EKF | UKF, name: str) -> list[ca.Function]:
    """The filter's two step functions under the C names ``<name>_update`` and
    ``<name>_predict_update``, every output dense; in the square-root form followed by
    :func:`factor_functions`."""
    funs = [renamed(estimator._update.fun, f"{name}_update", _FILTER_IN),
            renamed(estimator._predict_update.fun, f"{name}_predict_update", _FILTER_IN)]
    return funs + (factor_functions(estimator, name) if estimator.form == "sqrt" else [])


def cholesky(A: ca.SX) -> ca.SX:
    r"""The lower Cholesky factor :math:`L` of a symmetric ``A`` (``(n, n)``),
    :math:`L L^\top = A`, column by column; a pivot that is not positive gives a zero
    column (a semi-definite ``A`` whose null space is spanned by unit vectors, such as a
    ``Q`` without noise on some states, is factored exactly)."""
    n = A.shape[0]
    L = ca.SX.zeros(n, n)
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d = d - L[j, k] * L[j, k]
        root = ca.sqrt(ca.fmax(d, 0))
        L[j, j] = root
        for i in range(j + 1, n):
            a = A[i, j]
            for k in range(j):
                a = a - L[i, k] * L[j, k]
            L[i, j] = ca.if_else(root > 0, a / root, 0)
    return L


def factor_functions(estimator: EKF | UKF, name: str) -> list[ca.Function]:
    r"""The square-root form's Functions for the driver, under their C names:

    ``<name>_noise_factors``
        ``(Q, R) -> [vec(L_Q); vec(L_R)]``, the tuning a step reads: the square roots
        of the diagonal where the filter reads the diagonal only, else
        :func:`cholesky`.
    ``<name>_cholesky``
        ``P0 -> vec(chol(P0))``, the factor after a reset.
    ``<name>_add_P0``
        ``(vec(S), vec(L0)) -> vec(tria([S, L0]))``, the factor of
        :math:`S S^\top + L_0 L_0^\top` (:func:`~estim.solvers.kalman.triangular.tria`, as
        the Python gate and recovery form it).
    ``<name>_covariance``
        ``vec(S) -> vec(S S^T)``, the covariance a step reports.
    """
    m = estimator.model
    nx, ny = m.ndx, m.ny  # (the covariances' size: on a manifold the tangent space's)
    Q, R = ca.SX.sym("Q", nx, nx), ca.SX.sym("R", ny, ny)
    diagonal = estimator._diagonal

    def factor(M: ca.SX, key: str) -> ca.SX:
        if diagonal[key]:
            return ca.diag(ca.sqrt(ca.diag(M)))
        return cholesky(M)

    tuning = ca.vertcat(ca.vec(factor(Q, "Q")), ca.vec(factor(R, "R")))
    P0, S, L0 = (ca.SX.sym(k, nx * nx) for k in ("P0", "S", "L0"))
    Sm = ca.reshape(S, nx, nx)
    added = tria(ca.horzcat(Sm, ca.reshape(L0, nx, nx)))
    dense = ca.densify
    return [ca.Function(f"{name}_noise_factors", [ca.vec(Q), ca.vec(R)], [dense(tuning)],
                        ["Q", "R"], ["tuning"]),
            ca.Function(f"{name}_cholesky", [P0], [dense(ca.vec(cholesky(
                ca.reshape(P0, nx, nx))))], ["P0"], ["L0"]),
            ca.Function(f"{name}_add_P0", [S, L0], [dense(ca.vec(added))], ["S", "L0"],
                        ["S_added"]),
            ca.Function(f"{name}_covariance", [S], [dense(ca.vec(Sm @ Sm.T))], ["S"], ["P"])]


def dimensions(estimator: EKF | UKF, sizes: Mapping[str, int]) -> dict[str, int]:
    """The header's dimensions (``NX``, ``NY``, ..., CasADi's work sizes ``SZ_*``) and
    ``BYTES``, the size of the struct ``<name>_t`` (8-byte doubles, pointers and
    ``casadi_int``, 4-byte ints)."""
    m = estimator.model
    nx, ny, nu, nw, nd = m.nx, m.ny, m.nu, m.nw, m.ndx  # P is nd x nd (tangent space)
    ns, nt = nx + nd * nd + estimator._n_adapt, nd * nd + ny * ny
    d = {"NX": nx, "NDX": nd, "NY": ny, "NU": nu, "NW": nw, "NS": ns, "NT": nt,
         "NY1": max(ny, 1), "NU1": max(nu, 1), "NW1": max(nw, 1),
         "SAMPLED": int(m.sampled),
         "SZ_ARG": sizes["arg"], "SZ_RES": sizes["res"], "SZ_IW": sizes["iw"],
         "SZ_W": sizes["w"]}
    doubles = (nd * nd + ny * ny + nx + nd * nd  # Q, R, x0, P0
               + 2 * ns + d["NU1"] + 1 + d["NY1"]  # s, s_trusted, u_last, nis, innovation
               + d["NW1"] + nt + ns + d["NY1"] + NFLAGS + ns  # w_in, tuning, results
               + (nd * nd if estimator.form == "sqrt" else 0)  # L0, the factor of P0
               + sizes["w"])
    ints = 2  # first, trusted (int, 4 bytes each)
    d["BYTES"] = 8 * (doubles + sizes["arg"] + sizes["res"] + sizes["iw"]) + 4 * ints
    return d


def values(estimator: EKF | UKF) -> dict[str, str]:
    """The C initializers of the tuning (``Q``, ``R``, ``X0``, ``P0``) and of the bounds a
    failed step projects its anchor on (``LOWER``, ``UPPER``)."""
    m = estimator.model
    assert estimator.P0 is not None  # a Kalman filter always has its prior covariance
    from estim.estimators.kalman.adaptive import start_parts

    # an adaptive filter's statistics at a reset: [first; scale * vec R]
    first, scale = start_parts(estimator) if estimator._n_adapt else (0.0, 1.0)
    return {"ADAPT_FIRST": c_double(first), "ADAPT_SCALE": c_double(scale),
            "Q": c_array(estimator.Q), "R": c_array(estimator.R),
            "X0": c_array(estimator.x0), "P0": c_array(estimator.P0),
            "LOWER": c_array(getattr(estimator, "lower", m.lower)),
            "UPPER": c_array(getattr(estimator, "upper", m.upper)), "DT": c_double(m.dt)}


def describe(estimator: EKF | UKF) -> str:
    """What the filter is, as the files' comments say it: ``UKF, points='cubature',
    clip=True, gate=1e-06`` (``EKF, form='sqrt'`` in the square-root form)."""
    parts = [type(estimator).__name__]
    if estimator.form != "covariance":
        parts.append(f"form={estimator.form!r}")
    points = getattr(estimator, "points", None)  # the UKF's sigma points
    if points:
        parts.append(f"points={points!r}")
    order = getattr(estimator, "order", 3)
    if order != 3 and points == "gauss-hermite":
        parts.append(f"order={order}")
    if getattr(estimator, "iterations", 1) > 1:
        parts.append(f"iterations={estimator.iterations}")
    if getattr(estimator, "damping", None) is not None:
        parts.append(f"damping={estimator.damping!r}")
    if estimator.clip:
        parts.append("clip=True")
    if estimator.gate is not None:
        parts.append(f"gate={estimator.gate:g}")
    return ", ".join(parts)


def write(estimator: EKF | UKF, directory: Path, name: str,
          paths: Mapping[str, Path], flags: str = CFLAGS) -> None:
    """Write the filter's files to ``paths`` (see :func:`estim.codegen.export`), the
    Makefile with the compiler ``flags``."""
    funs = functions(estimator, name)
    generate(funs, directory, name)
    write_driver(paths, "kalman", name, estimator.model, describe(estimator),
                 values(estimator), dimensions(estimator, work_sizes(funs)),
                 {"sqrt": estimator.form == "sqrt",
                  "damped": getattr(estimator, "damping", None) is not None,
                  "variable_dt": estimator.model.variable_dt,
                  "adaptive": bool(estimator._n_adapt),
                  "sage_husa": getattr(estimator, "adapt", None) == "sage-husa",
                  "adapt_qr": getattr(estimator, "adapt", None) == "QR"}, flags)


def memory(estimator: EKF | UKF) -> int:
    """Bytes of the struct ``<name>_t`` of the filter's export."""
    return dimensions(estimator, work_sizes(functions(estimator, "m")))["BYTES"]
