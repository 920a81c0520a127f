r"""The C export of a fused Kalman filter (:class:`~estim.EKF`, :class:`~estim.UKF`).

CasADi's generated code of the filter's two step functions, ``<name>_update`` (the
first sample) and ``<name>_predict_update``, each ``(s, w, y, tuning) -> (s_new,
innovation, flags, s_prior)`` with the filter state :math:`s = [x;
\operatorname{vec}(P)]`, and the driver of ``templates/kalman.c.in``, which does with
their flags what :meth:`~estim.Estimator.step` does (the gate, the suspect flag, the
recovery of a failed update).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import casadi as ca

from estim.codegen.files import c_array, generate, renamed, work_sizes, write_driver

if TYPE_CHECKING:
    from estim.estimators.ekf import EKF
    from estim.estimators.ukf import UKF

#: Status codes of ``<name>_step`` (the C enum), with the Python status they stand for.
STATUS = {0: "ok", 1: "suspect", 2: "rejected", 3: "failed: kept the prediction",
          4: "failed: re-anchored", -1: "invalid argument (inf in y, non-finite u)"}

#: The names of the step functions' inputs in the generated code.
_FILTER_IN = ["s", "w", "y", "tuning"]


def functions(estimator: EKF | UKF, name: str) -> list[ca.Function]:
    """The filter's two step functions under the C names ``<name>_update`` and
    ``<name>_predict_update``, every output dense."""
    return [renamed(estimator._update.fun, f"{name}_update", _FILTER_IN),
            renamed(estimator._predict_update.fun, f"{name}_predict_update", _FILTER_IN)]


def dimensions(estimator: EKF | UKF, sizes: Mapping[str, int]) -> dict[str, int]:
    """The header's dimensions (``NX``, ``NY``, ..., CasADi's work sizes ``SZ_*``) and
    ``BYTES``, the size of the struct ``<name>_t`` (8-byte doubles, pointers and
    ``casadi_int``, 4-byte ints)."""
    m = estimator.model
    nx, ny, nu, nw = m.nx, m.ny, m.nu, m.nw
    ns, nt = nx + nx * nx, nx * nx + ny * ny
    d = {"NX": nx, "NY": ny, "NU": nu, "NW": nw, "NS": ns, "NT": nt,
         "NY1": max(ny, 1), "NU1": max(nu, 1), "NW1": max(nw, 1),
         "SAMPLED": int(m.sampled),
         "SZ_ARG": sizes["arg"], "SZ_RES": sizes["res"], "SZ_IW": sizes["iw"],
         "SZ_W": sizes["w"]}
    doubles = (nx * nx + ny * ny + nx + nx * nx  # Q, R, x0, P0
               + 2 * ns + d["NU1"] + 1 + d["NY1"]  # s, s_trusted, u_last, nis, innovation
               + d["NW1"] + nt + ns + d["NY1"] + 8 + ns  # w_in, tuning, results
               + sizes["w"])
    ints = 2  # first, trusted (int, 4 bytes each)
    d["BYTES"] = 8 * (doubles + sizes["arg"] + sizes["res"] + sizes["iw"]) + 4 * ints
    return d


def values(estimator: EKF | UKF) -> dict[str, str]:
    """The C initializers of the tuning (``Q``, ``R``, ``X0``, ``P0``) and of the bounds a
    failed step projects its anchor on (``LOWER``, ``UPPER``)."""
    m = estimator.model
    assert estimator.P0 is not None  # a Kalman filter always has its prior covariance
    return {"Q": c_array(estimator.Q), "R": c_array(estimator.R),
            "X0": c_array(estimator.x0), "P0": c_array(estimator.P0),
            "LOWER": c_array(getattr(estimator, "lower", m.lower)),
            "UPPER": c_array(getattr(estimator, "upper", m.upper))}


def describe(estimator: EKF | UKF) -> str:
    """What the filter is, as the files' comments say it: ``UKF, points='cubature',
    clip=True, gate=1e-06``."""
    parts = [type(estimator).__name__]
    points = getattr(estimator, "points", None)  # the UKF's sigma points
    if points:
        parts.append(f"points={points!r}")
    if estimator.clip:
        parts.append("clip=True")
    if estimator.gate is not None:
        parts.append(f"gate={estimator.gate:g}")
    return ", ".join(parts)


def write(estimator: EKF | UKF, directory: Path, name: str,
          paths: Mapping[str, Path]) -> None:
    """Write the filter's six files to ``paths`` (see :func:`estim.codegen.export`)."""
    funs = functions(estimator, name)
    generate(funs, directory, name)
    write_driver(paths, "kalman", name, estimator.model, describe(estimator),
                 values(estimator), dimensions(estimator, work_sizes(funs)))


def memory(estimator: EKF | UKF) -> int:
    """Bytes of the struct ``<name>_t`` of the filter's export."""
    return dimensions(estimator, work_sizes(functions(estimator, "m")))["BYTES"]
