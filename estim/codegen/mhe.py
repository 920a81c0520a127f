"""The C export of the moving horizon estimator's real-time iteration (:class:`~estim.MHE`
with ``rti=True``).

CasADi's generated code of the window's preparation, feedback and cost
(:func:`estim.solvers.least_squares.rti.build`), of the arrival covariance's step and of the model's
transition, and the driver of ``templates/mhe.c.in``, which does the window's
bookkeeping as the Python estimator does, in the same order (see
``docs/deployment.md``). The struct ``<name>_t`` holds the window, the arrival cost and
every intermediate result: its fields are written here (:func:`layout`), with their
sizes for this horizon and model.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import casadi as ca
import numpy as np

from estim.codegen.files import (
    CFLAGS,
    c_array,
    c_double,
    check_model,
    generate,
    renamed,
    work_sizes,
    write_driver,
)
from estim.consistency import chi2_limit

if TYPE_CHECKING:
    from estim.estimators.window.mhe import MHE

#: Status codes of the MHE's ``<name>_step`` and ``<name>_prepare``.
STATUS = {0: "ok", 1: "inexact: the start-up's Gauss-Newton steps did not converge",
          2: "suspect: the window's cost beyond the 1e-9 chi-square tail",
          -1: "invalid argument (inf in y, non-finite u)",
          -2: "non-finite step: Python solves the window to convergence instead; "
              "reset needed",
          -3: "u is not the input given to prepare"}

#: The C constants of the arrival costs (the driver's enum).
_ARRIVAL = {"none": 0, "fixed": 1, "filtering": 2, "smoothing": 3}


def check(estimator: MHE) -> None:
    """Refuse the MHE configurations that have no C counterpart.

    Raises
    ------
    ValueError
        An MHE without ``rti=True``, a model :func:`~estim.codegen.files.check_model`
        refuses, or ``horizon=1``.
    """
    if not estimator.rti:
        raise ValueError("estimator: an MHE is exported as its real-time iteration only "
                         "(the converged solve has no C counterpart): build it with "
                         "rti=True")
    check_model(estimator.model)
    if estimator.horizon < 2:
        raise ValueError(f"horizon must be at least 2 to export the MHE, got "
                         f"{estimator.horizon}")


def functions(estimator: MHE, name: str) -> list[ca.Function]:
    """The Functions of the real-time MHE under C names: ``prepare``, ``feedback`` and
    ``cost`` of :func:`estim.solvers.least_squares.rti.build`, the arrival covariance's step and the
    model's transition ``F(x, u, p)``."""
    from estim.solvers.least_squares import rti

    m = estimator.model
    from estim.solvers.kalman.continuous import interval_weight

    prepare, feedback, cost = rti.build(
        m, estimator.horizon, process_weight=interval_weight if estimator.Qc is not None
        else None)
    funs = [renamed(prepare, f"{name}_prepare_window"),
            renamed(feedback, f"{name}_feedback_window"),
            renamed(cost, f"{name}_window_cost"),
            renamed(estimator._build_cov_step(), f"{name}_cov_step"),
            renamed(m.F, f"{name}_transition")]
    if not m.manifold.euclidean_states:  # the window's moves (retraction, tangent steps)
        retract, local = m.manifold.window_moves(estimator.horizon)
        funs += [renamed(retract, f"{name}_retract_window"),
                 renamed(local, f"{name}_local_window")]
    return funs


def layout(estimator: MHE, sizes: Mapping[str, int]) -> tuple[str, int, dict[str, int]]:
    """The struct's fields (C text), its size in bytes (8-byte doubles, pointers and
    ``casadi_int``, 4-byte ints, padded to 8 bytes) and the header's dimensions."""
    m, N = estimator.model, estimator.horizon
    nx, nd = m.nx, m.ndx  # stored states; the covariances' (tangent) size
    ny, nu, nw = max(m.ny, 1), max(m.nu, 1), max(m.nw, 1)
    window = N * nx
    # (name, doubles, comment) of each array; a comment alone (None doubles) heads a group
    fields: list[tuple[str, int | None, str]] = [
        ("the tuning (the export's after init): the estimator reads Qinv, not Q, in "
         "the window's weights", None, ""),
        ("Q", nd * nd, "process-noise covariance (the arrival covariance's step)"),
        ("Qinv", nx * nx, "its inverse (numpy's, at export; on a manifold padded to NX "
         "x NX, 1 on the pads): set it with Q"),
        ("R", ny * ny, "measurement-noise covariance"),
        ("x0", nx, "initial guess"),
        ("P0", nd * nd, "its covariance (the arrival cost's at reset; 'fixed': always)"),
        ("the window, oldest slot first (slot k: X + k*NX, ...)", None, ""),
        ("X", window, "the window's estimates"),
        ("Y", N * ny, "its measurements (NaN: not measured)"),
        ("U", N * nw, "U[k]: the transition's input from slot k to k + 1"),
        ("Uprev", N * nu, "the input the output function sees at slot k"),
        ("xbar", nx, "the arrival cost's mean"),
        ("Pbar", nd * nd, "and covariance (filtering, smoothing)"),
        ("history", window, "the estimates of the window's times, oldest first"),
        ("u_last", nu, "the previous input (sampled inputs)"),
        ("u_prepared", nu, "the input given to prepare"),
        ("cost_last", 1, "the window's cost at the last estimate (its chi-square statistic)"),
        ("trusted_x", nx, "the last estimate returned with status 0 (x0 at reset)"),
        ("trusted_P", nd * nd, "and its covariance (P0 at reset)"),
        ("work memory of prepare and step", None, ""),
        ("u_in", nu, ""), ("Xs", window, ""), ("trial", window, ""), ("dX", window, ""),
        ("P", nx * nx, ""), ("P_held", nx * nx, ""), ("grad_y", nx, ""), ("G", window, ""),
        ("ones", window, ""), ("free", window, ""), ("free_new", nx, ""), ("yv", ny, ""),
        ("ymask", ny, ""), ("a_Y", (N - 1) * ny, ""), ("a_mask", (N - 1) * ny, ""),
        ("a_U", (N - 1) * nw, ""), ("a_Up", N * nu, ""), ("a_a", N, ""), ("a_om", N - 1, ""),
        ("a_Pbar", nx * nx, ""), ("a_arrival", 1, ""), ("S0", nx * nx, ""), ("g0", nx, ""),
        ("C", ny * nx, ""), ("h", ny, ""), ("v", nx * (N - 1), ""),
        ("M", nx * nx * (N - 1), ""), ("grad", window, ""), ("cost", 1, ""),
        ("mask_old", ny, ""), ("Pn", nd * nd, ""), ("Pu", nd * nd, ""), ("pred", nx, ""),
        ("xbar_new", nx, ""), ("w", sizes["w"], "CasADi's work array"),
    ]
    if m.variable_dt:  # the interval, an argument of prepare and step
        at = fields.index(("u_prepared", nu, "the input given to prepare")) + 1
        fields[at:at] = [("dt_in", 1, "the interval of the arriving sample"),
                         ("dt_prepared", 1, "the interval given to prepare")]
    if not m.manifold.euclidean_states:  # the moves' work: the steps, the tangent ones
        fields[-1:-1] = [("step", window, ""), ("tangent", N * nd, "")]
    lines, doubles = [], 0
    for fname, count, comment in fields:
        if count is None:
            lines.append(f"    /* {fname} */")
            continue
        doubles += count
        lines.append(f"    double {fname}[{count}];" + (f"  /* {comment} */" if comment else ""))
    lines += [f"    const double *arg[{sizes['arg']}];", f"    double *res[{sizes['res']}];",
              f"    long long iw[{sizes['iw']}];",
              "    int n;          /* measurements in the window */",
              "    int n_history;  /* estimates in history (n) */",
              "    int first;      /* 1 until the first step */",
              "    int prepared;   /* 1 after prepare, until the step */",
              "    int failed;     /* 1 after a non-finite step: reset needed */",
              "    int iterations; /* Gauss-Newton iterations of the last step */"]
    ints = 6
    size = 8 * (doubles + sizes["arg"] + sizes["res"] + sizes["iw"]) + 4 * ints
    size = -(-size // 8) * 8
    dims = {"N": N, "NX": nx, "NDX": nd, "NY": m.ny, "NU": m.nu, "NW": m.nw, "NY1": ny,
            "NU1": nu,
            "NW1": nw, "SAMPLED": int(m.sampled), "SZ_ARG": sizes["arg"],
            "SZ_RES": sizes["res"], "SZ_IW": sizes["iw"], "SZ_W": sizes["w"], "BYTES": size}
    return "\n".join(lines), size, dims


def values(estimator: MHE, fields: str) -> dict[str, str]:
    r"""The driver's constants as C text: the tuning (``Q``, ``QINV``, ``R``, ``X0``,
    ``P0``: zeros without one), the bounds, the model's parameters, the arrival cost,
    the start-up's tolerance and iterations, the :math:`\chi^2` limits of the suspect
    test by degrees of freedom, and the struct's ``fields``."""
    from estim.estimators.window.mhe import RTI_STARTUP_ITERATIONS, RTI_STARTUP_XTOL

    m = estimator.model
    nx, M = m.nx, m.manifold
    P0 = estimator.P0 if estimator.P0 is not None else np.zeros((m.ndx, m.ndx))
    # Q^-1, or a continuous noise's density L Qc L^T (the window's weights made from it)
    Qinv = np.linalg.inv(estimator.Q) if estimator.Qc is None else estimator.Q
    return {"Q": c_array(estimator.Q),
            "QINV": c_array(Qinv if M.euclidean_states else M.padded_matrix(Qinv)),
            "SLOTS": "{" + ", ".join(map(str, M.slots)) + "}",
            "PADS": "{" + ", ".join(map(str, M.pads or [-1])) + "}",
            "NPADS": str(len(M.pads)),
            "R": c_array(estimator.R), "X0": c_array(estimator.x0), "P0": c_array(P0),
            "LOWER": c_array(estimator.lower), "UPPER": c_array(estimator.upper),
            "PARAMS": c_array(m.p), "EYE": c_array(np.eye(nx)),
            "ARRIVAL": str(_ARRIVAL[estimator.arrival_cost]),
            "ARRIVAL_NAME": estimator.arrival_cost,
            "BOUNDED": str(int(bool(np.isfinite(estimator.lower).any()
                                    or np.isfinite(estimator.upper).any()))),
            "XTOL": c_double(RTI_STARTUP_XTOL), "ITERATIONS": str(RTI_STARTUP_ITERATIONS),
            "CHI2": c_array([chi2_limit(d)
                             for d in range(estimator.horizon * m.ny + m.ndx + 1)]),
            "FIELDS": fields}


def describe(estimator: MHE) -> str:
    """What the estimator is, as the files' comments say it."""
    return (f"MHE(horizon={estimator.horizon}, arrival_cost="
            f"{estimator.arrival_cost!r}, rti=True)")


def write(estimator: MHE, directory: Path, name: str, paths: Mapping[str, Path],
          flags: str = CFLAGS) -> None:
    """Write the estimator's files to ``paths`` (see :func:`estim.codegen.export`), the
    Makefile with the compiler ``flags``."""
    funs = functions(estimator, name)
    generate(funs, directory, name)
    fields, _, dims = layout(estimator, work_sizes(funs))
    write_driver(paths, "mhe", name, estimator.model, describe(estimator),
                 values(estimator, fields), dims,
                 {"manifold": not estimator.model.manifold.euclidean_states}, flags)


def memory(estimator: MHE) -> int:
    """Bytes of the struct ``<name>_t`` of the estimator's export (refused
    configurations raise as in :func:`check`)."""
    check(estimator)
    return layout(estimator, work_sizes(functions(estimator, "m")))[1]
