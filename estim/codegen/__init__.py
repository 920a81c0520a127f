r"""C code of a fused Kalman filter (:class:`~estim.EKF`, :class:`~estim.UKF`) for
deployment without Python or CasADi.

:func:`export` writes CasADi's generated C code of the filter's two step functions
(update only for the first sample, prediction and update for every later one), a
small hand-written driver that does what :meth:`~estim.Estimator.step` does with
their results (the gate, the suspect flag, the recovery of a failed update with its
last trusted estimate), a ``Makefile`` and a ``README.md``. The code is plain C99
with ``<math.h>`` and ``<string.h>`` only: no allocation, no CasADi runtime.

The real-time iteration of the moving horizon estimator (:class:`~estim.MHE` with
``rti=True``) is exported the same way: CasADi's generated code of the window's
preparation, feedback and cost (:func:`estim.solvers.rti.build`), of the arrival
covariance's step and of the model's transition, and a driver that does the window's
bookkeeping as the Python estimator does, in the same order (see
``docs/deployment.md``).
"""

from __future__ import annotations

import re
from pathlib import Path

import casadi as ca
import numpy as np

__all__ = ["export"]

#: Status codes of ``<name>_step`` (the C enum), with the Python status they stand for.
STATUS = {0: "ok", 1: "suspect", 2: "rejected", 3: "failed: kept the prediction",
          4: "failed: re-anchored", -1: "invalid argument (inf in y, non-finite u)"}

#: Flags of the Makefile: optimised, position-independent, and no contraction of
#: products and sums into fused multiply-adds, so that the code computes what CasADi's
#: interpreter computes in Python, operation for operation.
CFLAGS = "-O2 -fPIC -fno-fast-math -ffp-contract=off"

_FILTER_IN = ["s", "w", "y", "tuning"]


def export(estimator, directory: str | Path, *, name: str | None = None,
           overwrite: bool = False) -> dict[str, Path]:
    r"""Write C code of an EKF, a UKF or a real-time iteration MHE that steps as
    :meth:`~estim.Estimator.step` does.

    Files written into ``directory`` (created if needed):

    ``<name>_functions.c``, ``<name>_functions.h``
        CasADi's generated code of the filter's two step functions,
        ``<name>_update`` (the first sample) and ``<name>_predict_update``, each
        ``(s, w, y, tuning) -> (s_new, innovation, flags, s_prior)`` with the filter
        state :math:`s = [x; \operatorname{vec}(P)]` (column-major,
        :math:`n_x + n_x^2`), the transition's input :math:`w` and the tuning
        :math:`[\operatorname{vec}(Q); \operatorname{vec}(R)]`. The model, its
        parameters, the sigma-point weights, the bounds of ``clip`` and the
        :math:`\chi^2` limits of the suspect flag and of ``gate`` are constants in it.
    ``<name>.h``, ``<name>.c``
        The driver: a struct ``<name>_t`` holding the filter state, the tuning
        (``Q``, ``R``, ``x0``, ``P0``: the estimator's at export time, settable) and
        all work memory (its size is fixed at export time and given in the README);
        ``<name>_init``, ``<name>_reset``, ``<name>_step`` (returns 0 ok, 1 suspect,
        2 rejected by the gate, 3 failed and kept the prediction, 4 failed and
        re-anchored on the last trusted estimate with :math:`P + P_0`, -1 for an
        ``inf`` in ``y`` or a non-finite ``u``), ``<name>_nis`` and
        ``<name>_set_tuning``.
    ``Makefile``
        Builds ``lib<name>.a`` and ``lib<name>.so`` (``cc -O2 -fPIC`` without
        contraction into fused multiply-adds).
    ``README.md``
        The API, the memory and the build.

    NaN in ``y`` marks a missing output, as in Python. For a model with sampled
    inputs (``hold="foh"``) the driver keeps the previous input, as ``step`` does.

    For an :class:`~estim.MHE` with ``rti=True`` the same six files hold the
    generated ``<name>_prepare_window``, ``<name>_feedback_window``,
    ``<name>_window_cost``, ``<name>_cov_step`` and ``<name>_transition``, and a
    driver with ``<name>_init``, ``<name>_reset``, ``<name>_prepare(e, u)`` (the
    preparation phase, :meth:`~estim.MHE.prepare`), ``<name>_step(e, y, u, x_hat,
    P)`` (0 ok, 1 inexact start-up, 2 suspect, -1 invalid argument, -2 a non-finite step, where
    Python falls back to its converged solver: reset needed, -3 ``u`` is not the
    input given to prepare), ``<name>_iterations`` and ``<name>_size``. The window,
    the arrival cost (every ``arrival_cost``), the start-up's projected Gauss-Newton
    iterations and the bounds are those of the estimator.

    Parameters
    ----------
    estimator : EKF, UKF or MHE
        The estimator (its tuning, options and bounds are what the code does); an
        MHE with ``rti=True``.
    directory : str or Path
        Where the files go.
    name : str, optional
        The C identifier that prefixes every file and symbol, default
        ``"<filter>_<model name>"`` made an identifier (e.g. ``ekf_batch_reactor``).
    overwrite : bool
        Replace files of the same names in ``directory`` (refused by default).

    Returns
    -------
    dict
        The paths written, by kind: ``"functions_c"``, ``"functions_h"``, ``"h"``,
        ``"c"``, ``"makefile"``, ``"readme"``.

    Raises
    ------
    TypeError
        ``estimator`` is not an :class:`~estim.EKF`, :class:`~estim.UKF` or
        :class:`~estim.MHE`.
    ValueError
        An invalid ``name``; a model with ``variable_dt=True`` (the interval of each
        step would be an argument of the C step: not supported) or integrated by
        CVODES (``integrator="cvodes"``, which needs the CasADi runtime); an MHE
        without ``rti=True`` or with ``horizon=1``.
    FileExistsError
        A file to write exists and ``overwrite`` is False.
    """
    from estim.estimators.fused import FusedKalman
    from estim.estimators.mhe import MHE

    if not isinstance(estimator, (FusedKalman, MHE)):
        raise TypeError(f"estimator must be an estim.EKF, estim.UKF or estim.MHE with "
                        f"rti=True, got {type(estimator).__name__}")
    m = estimator.model
    if isinstance(estimator, MHE):
        _check_mhe(estimator)
    if m.variable_dt:
        raise ValueError(f"{m.name} has variable_dt=True: the C step takes the model's "
                         f"fixed dt only; build the model without variable_dt to export")
    if getattr(m, "integrator", None) == "cvodes":
        raise ValueError(f"{m.name} is integrated by CVODES, which needs the CasADi "
                         f"runtime: build the model with integrator='rk4' to export")
    if name is None:
        name = re.sub(r"\W+", "_", f"{estimator.name}_{m.name}".lower()).strip("_")
        if name[:1].isdigit():
            name = f"f_{name}"
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
        raise ValueError(f"name must be a C identifier, got {name!r}")
    directory = Path(directory)
    paths = {"functions_c": directory / f"{name}_functions.c",
             "functions_h": directory / f"{name}_functions.h",
             "h": directory / f"{name}.h", "c": directory / f"{name}.c",
             "makefile": directory / "Makefile", "readme": directory / "README.md"}
    existing = [p.name for p in paths.values() if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"{directory} already holds {', '.join(existing)}: pass "
                              f"overwrite=True to replace them")
    directory.mkdir(parents=True, exist_ok=True)
    if isinstance(estimator, MHE):
        _write_mhe(estimator, directory, name, paths)
        return paths

    funs = [_renamed(estimator._update.fun, f"{name}_update", _FILTER_IN),
            _renamed(estimator._predict_update.fun, f"{name}_predict_update",
                     _FILTER_IN)]
    gen = ca.CodeGenerator(f"{name}_functions.c", {"with_header": True})
    for fun in funs:
        gen.add(fun)
    gen.generate(str(directory) + "/")
    sizes = {k: max(1, *(int(getattr(f, f"sz_{k}")()) for f in funs))
             for k in ("arg", "res", "iw", "w")}
    dims = _dimensions(estimator, sizes)
    values = _values(estimator)
    paths["h"].write_text(_fill(_HEADER, name, dims, values, estimator))
    paths["c"].write_text(_fill(_SOURCE, name, dims, values, estimator))
    paths["makefile"].write_text(_fill(_MAKEFILE, name, dims, values, estimator))
    paths["readme"].write_text(_fill(_README, name, dims, values, estimator))
    return paths


def memory(estimator) -> int:
    """Bytes of the struct ``<name>_t`` that :func:`export` writes for ``estimator``
    (8-byte doubles, pointers and ``casadi_int``; the filter state, the tuning, the
    step's results and CasADi's work arrays; for the MHE also the window, the
    arrival cost and the real-time iteration's intermediate results)."""
    from estim.estimators.mhe import MHE

    if isinstance(estimator, MHE):
        _check_mhe(estimator)
        return _mhe_layout(estimator, _mhe_sizes(_mhe_functions(estimator, "m")))[1]
    funs = [_renamed(estimator._update.fun, "update", _FILTER_IN),
            _renamed(estimator._predict_update.fun, "predict_update", _FILTER_IN)]
    sizes = {k: max(1, *(int(getattr(f, f"sz_{k}")()) for f in funs))
             for k in ("arg", "res", "iw", "w")}
    return _dimensions(estimator, sizes)["BYTES"]


def _renamed(fun: ca.Function, name: str,
             names_in: list[str] | None = None) -> ca.Function:
    """``fun`` (an SX Function) under another name, every output dense."""
    args = fun.sx_in()
    return ca.Function(name, args, [ca.densify(o) for o in fun.call(args)],
                       names_in or fun.name_in(), fun.name_out())


def _dimensions(estimator, sizes: dict) -> dict:
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


def _c(v: float) -> str:
    """A double as C reads it back exactly (shortest round trip)."""
    v = float(v)
    if np.isinf(v):
        return "INFINITY" if v > 0 else "-INFINITY"
    return repr(v)


def _array(a) -> str:
    a = np.asarray(a, dtype=float).ravel(order="F")
    return "{" + ", ".join(_c(v) for v in a) + "}" if a.size else "{0.0}"


def _values(estimator) -> dict:
    m = estimator.model
    return {"Q": _array(estimator.Q), "R": _array(estimator.R), "X0": _array(estimator.x0),
            "P0": _array(estimator.P0),
            "LOWER": _array(getattr(estimator, "lower", m.lower)),
            "UPPER": _array(getattr(estimator, "upper", m.upper))}


def _describe(estimator) -> str:
    parts = [type(estimator).__name__]
    if hasattr(estimator, "horizon"):
        return (f"MHE(horizon={estimator.horizon}, arrival_cost="
                f"{estimator.arrival_cost!r}, rti=True)")
    if getattr(estimator, "points", None):
        parts.append(f"points={estimator.points!r}")
    if estimator.clip:
        parts.append("clip=True")
    if estimator.gate is not None:
        parts.append(f"gate={estimator.gate:g}")
    return ", ".join(parts)


def _fill(template: str, name: str, dims: dict, values: dict, estimator) -> str:
    from estim._version import __version__
    from estim.consistency import SUSPECT_TAIL

    m = estimator.model
    text = (template.replace("@name@", name).replace("@NAME@", name.upper())
            .replace("@filter@", _describe(estimator)).replace("@model@", m.name)
            .replace("@version@", __version__).replace("@CFLAGS@", CFLAGS)
            .replace("@TAIL@", f"{SUSPECT_TAIL:g}")
            .replace("@states@", ", ".join(m.state_names))
            .replace("@outputs@", ", ".join(m.output_names))
            .replace("@inputs@", ", ".join(m.input_names) or "none"))
    for key, value in values.items():
        text = text.replace(f"@{key}@", value)
    for key, value in dims.items():
        text = text.replace(f"@{key}@", str(value))
    return text


_HEADER = r"""/* @name@.h -- @filter@ of the model "@model@" (estim @version@).
 *
 * States (x): @states@
 * Outputs (y): @outputs@
 * Inputs (u): @inputs@
 *
 * Matrices are stored column-major: P[i + j*NX] is P(i, j).
 *
 * Use:
 *     @name@_t f;                       // all memory: @BYTES@ bytes, no malloc
 *     @name@_init(&f);                  // tuning of the export, x = x0, P = P0
 *     int status = @name@_step(&f, y, u, x_hat, P);
 *
 * y (@NAME@_NY doubles): the measurement, NaN for an output not measured.
 * u (@NAME@_NU doubles, or NULL for zeros): the input that acted since the
 *   previous sample (for sampled inputs, hold="foh": the input at this sample);
 *   ignored by the prediction on the first step, seen by the output function.
 * x_hat (@NAME@_NX), P (@NAME@_NX * @NAME@_NX): the estimate and its
 *   covariance after the step (either may be NULL).
 *
 * Status of a step (what estim's step reports in info.status):
 *    0  ok
 *    1  suspect: NIS beyond the @TAIL@ tail of chi2(outputs measured); update kept
 *    2  rejected by the gate: the prediction, with P0 added to its covariance
 *    3  failed: non-finite update (or, UKF, a covariance that is not positive
 *       definite); the prediction of a trusted estimate is kept
 *    4  failed: re-anchored on the last trusted estimate (projected on the
 *       bounds) with P + P0 and updated with this measurement
 *   -1  invalid argument: inf in y, a non-finite u, a NULL f or y (the filter is
 *       unchanged), or (from init) work sizes that do not match the functions
 */
#ifndef @NAME@_H
#define @NAME@_H

#ifdef __cplusplus
extern "C" {
#endif

#include <stddef.h>

#define @NAME@_NX @NX@  /* states */
#define @NAME@_NY @NY@  /* outputs */
#define @NAME@_NU @NU@  /* inputs given to step */
#define @NAME@_NW @NW@  /* the transition's input (u, or [u_prev; u] if sampled) */
#define @NAME@_NS @NS@  /* filter state [x; vec(P)] */
#define @NAME@_NT @NT@  /* tuning [vec(Q); vec(R)] */
/* CasADi's work memory of the two step functions (the larger of each) */
#define @NAME@_SZ_ARG @SZ_ARG@
#define @NAME@_SZ_RES @SZ_RES@
#define @NAME@_SZ_IW @SZ_IW@
#define @NAME@_SZ_W @SZ_W@

enum {
    @NAME@_OK = 0,
    @NAME@_SUSPECT = 1,
    @NAME@_REJECTED = 2,
    @NAME@_KEPT_PREDICTION = 3,
    @NAME@_REANCHORED = 4,
    @NAME@_INVALID = -1
};

/* The filter and all its memory. Read x = s, P = s + NX (column-major). Q, R, x0
 * and P0 are set by init to the tuning of the export; change them (or call
 * set_tuning) between steps: Q, R and P0 act from the next step on, x0 and P0 at
 * the next reset. A filter exported with a diagonal Q (R) reads only the
 * diagonal. */
typedef struct {
    double Q[@NX@ * @NX@];    /* process-noise covariance */
    double R[@NY1@ * @NY1@];    /* measurement-noise covariance */
    double x0[@NX@];        /* initial guess */
    double P0[@NX@ * @NX@];   /* its covariance (also added by the gate and recovery) */
    double s[@NS@];         /* filter state [x; vec(P)] */
    double s_trusted[@NS@]; /* the last trusted filter state (anchor of recovery) */
    double u_last[@NU1@];     /* the previous input (sampled inputs) */
    double nis;            /* NIS of the last step (NaN: none) */
    double innovation[@NY1@]; /* innovation of the last step (0 missing, NaN failed) */
    int first;             /* 1 until the first step: update only */
    int trusted;           /* 1 when s is the anchor (the last step was ok) */
    /* work memory of a step */
    double w_in[@NW1@];
    double tuning[@NT@];
    double s_new[@NS@], e[@NY1@], flags[8], s_prior[@NS@];
    const double *arg[@SZ_ARG@];
    double *res[@SZ_RES@];
    long long iw[@SZ_IW@];
    double w[@SZ_W@];
} @name@_t;

/* Set the tuning of the export and reset. Returns 0, or -1 if the work sizes of
 * the generated functions exceed the struct's (code of another export). */
int @name@_init(@name@_t *f);

/* Reset to x = x0, P = P0 (the struct's current values); the next step is the
 * first (update only). Returns 0 (-1 for NULL). */
int @name@_reset(@name@_t *f);

/* One step: the measurement y after the input u. Returns the status (above) and
 * writes the estimate x_hat and its covariance P (column-major). */
int @name@_step(@name@_t *f, const double *y, const double *u, double *x_hat, double *P);

/* NIS of the last step: e' S^-1 e over the outputs measured (NaN when no output
 * was measured, before the first step, and after a failed step). */
double @name@_nis(const @name@_t *f);

/* Replace any of Q, R, x0, P0 (column-major; NULL keeps one). Returns 0. */
int @name@_set_tuning(@name@_t *f, const double *Q, const double *R, const double *x0,
                      const double *P0);

/* sizeof(@name@_t), for callers that allocate it from another language. */
size_t @name@_size(void);

#ifdef __cplusplus
}
#endif

#endif
"""

_SOURCE = r"""/* @name@.c -- the step of @filter@ on "@model@" (estim @version@).
 * See @name@.h. No allocation; every array lives in @name@_t. */
#include <math.h>
#include <string.h>

#include "@name@.h"
#include "@name@_functions.h"

#define NX @NAME@_NX
#define NY @NAME@_NY
#define NU @NAME@_NU
#define NW @NAME@_NW
#define NS @NAME@_NS

static const int sampled = @SAMPLED@;
static const double default_Q[] = @Q@;
static const double default_R[] = @R@;
static const double default_x0[] = @X0@;
static const double default_P0[] = @P0@;
/* the bounds a failed step projects its anchor on */
static const double lower[] = @LOWER@;
static const double upper[] = @UPPER@;

static void copy(double *to, const double *from, int n) {
    if (n > 0) memcpy(to, from, (size_t) n * sizeof(double));
}

size_t @name@_size(void) { return sizeof(@name@_t); }

int @name@_reset(@name@_t *f) {
    int k;
    if (!f) return @NAME@_INVALID;
    copy(f->s, f->x0, NX);
    copy(f->s + NX, f->P0, NX * NX);
    copy(f->s_trusted, f->s, NS);
    for (k = 0; k < NU; ++k) f->u_last[k] = 0.0;
    for (k = 0; k < NY; ++k) f->innovation[k] = NAN;
    f->nis = NAN;
    f->first = 1;
    f->trusted = 1;
    return @NAME@_OK;
}

static int fits(int (*work)(casadi_int *, casadi_int *, casadi_int *, casadi_int *)) {
    casadi_int a, r, i, w;
    return work(&a, &r, &i, &w) == 0 && a <= @NAME@_SZ_ARG && r <= @NAME@_SZ_RES &&
           i <= @NAME@_SZ_IW && w <= @NAME@_SZ_W;
}

int @name@_init(@name@_t *f) {
    if (!f || !fits(@name@_update_work) || !fits(@name@_predict_update_work))
        return @NAME@_INVALID;
    @name@_set_tuning(f, default_Q, default_R, default_x0, default_P0);
    return @name@_reset(f);
}

int @name@_set_tuning(@name@_t *f, const double *Q, const double *R, const double *x0,
                      const double *P0) {
    if (!f) return @NAME@_INVALID;
    if (Q) copy(f->Q, Q, NX * NX);
    if (R) copy(f->R, R, NY * NY);
    if (x0) copy(f->x0, x0, NX);
    if (P0) copy(f->P0, P0, NX * NX);
    return @NAME@_OK;
}

double @name@_nis(const @name@_t *f) { return f ? f->nis : NAN; }

/* (s, w_in, y, tuning) -> (s_new, e, flags, s_prior): update only, or predict and update */
static void evaluate(@name@_t *f, const double *y, int predict) {
    copy(f->tuning, f->Q, NX * NX);
    copy(f->tuning + NX * NX, f->R, NY * NY);
    f->arg[0] = f->s;
    f->arg[1] = f->w_in;
    f->arg[2] = y;
    f->arg[3] = f->tuning;
    f->res[0] = f->s_new;
    f->res[1] = f->e;
    f->res[2] = f->flags;
    f->res[3] = f->s_prior;
    if (predict)
        @name@_predict_update(f->arg, f->res, (casadi_int *) f->iw, f->w, 0);
    else
        @name@_update(f->arg, f->res, (casadi_int *) f->iw, f->w, 0);
}

/* A failed update: keep the prediction of a trusted estimate, or re-anchor on the
 * last trusted estimate (projected on the bounds) with P + P0 (P0 if P is not
 * finite) and update with this measurement. */
static int recover(@name@_t *f, const double *y) {
    int k, status, finite = 1;
    if (f->trusted) copy(f->s_trusted, f->s, NS);
    if (f->flags[2] != 0.0 && f->trusted) {
        copy(f->s, f->s_prior, NS);
        status = @NAME@_KEPT_PREDICTION;
    } else {
        for (k = 0; k < NX; ++k) f->s[k] = fmin(fmax(f->s_trusted[k], lower[k]), upper[k]);
        for (k = 0; k < NX * NX; ++k) finite = finite && isfinite(f->s_trusted[NX + k]);
        for (k = 0; k < NX * NX; ++k)
            f->s[NX + k] = finite ? f->s_trusted[NX + k] + f->P0[k] : f->P0[k];
        evaluate(f, y, 0);
        if (f->flags[1] != 0.0) copy(f->s, f->s_new, NS);
        status = @NAME@_REANCHORED;
    }
    f->trusted = 0;
    f->nis = NAN;
    for (k = 0; k < NY; ++k) f->innovation[k] = NAN;
    return status;
}

int @name@_step(@name@_t *f, const double *y, const double *u, double *x_hat, double *P) {
    int k, status, suspect;
    if (!f || !y) return @NAME@_INVALID;
    for (k = 0; k < NY; ++k)
        if (isinf(y[k])) return @NAME@_INVALID;
    for (k = 0; k < NU; ++k)
        if (u && !isfinite(u[k])) return @NAME@_INVALID;
    /* the transition's input: u, or [u_prev; u] for sampled inputs */
    for (k = 0; k < NU; ++k) {
        double uk = u ? u[k] : 0.0;
        if (sampled) {
            f->w_in[k] = f->u_last[k];
            f->w_in[NU + k] = uk;
        } else {
            f->w_in[k] = uk;
        }
    }
    evaluate(f, y, !f->first);
    if (f->flags[1] == 0.0) {
        status = recover(f, y);
    } else {
        suspect = f->flags[6] != 0.0 || f->flags[7] != 0.0;
        if (suspect && f->trusted) copy(f->s_trusted, f->s, NS);
        f->trusted = !suspect;
        if (f->flags[7] != 0.0) { /* gated: the prediction, with P0 added */
            copy(f->s, f->s_prior, NS);
            for (k = 0; k < NX * NX; ++k) f->s[NX + k] += f->P0[k];
            status = @NAME@_REJECTED;
        } else {
            copy(f->s, f->s_new, NS);
            status = suspect ? @NAME@_SUSPECT : @NAME@_OK;
        }
        f->nis = f->flags[4] > 0.0 ? f->flags[0] : NAN;
        copy(f->innovation, f->e, NY);
    }
    f->first = 0;
    if (sampled)
        for (k = 0; k < NU; ++k) f->u_last[k] = u ? u[k] : 0.0;
    if (x_hat) copy(x_hat, f->s, NX);
    if (P) copy(P, f->s + NX, NX * NX);
    return status;
}
"""

_MAKEFILE = """# Builds lib@name@.a and lib@name@.so from the exported estimator (estim @version@).
# No contraction into fused multiply-adds: the library then computes what estim
# computes in Python, operation for operation.
CC ?= cc
AR ?= ar
CFLAGS ?= @CFLAGS@
OBJECTS = @name@.o @name@_functions.o

all: lib@name@.a lib@name@.so

%.o: %.c @name@.h @name@_functions.h
\t$(CC) $(CFLAGS) -c $< -o $@

lib@name@.a: $(OBJECTS)
\t$(AR) rcs $@ $(OBJECTS)

lib@name@.so: $(OBJECTS)
\t$(CC) -shared $(OBJECTS) -o $@ -lm

clean:
\trm -f $(OBJECTS) lib@name@.a lib@name@.so

.PHONY: all clean
"""

_README = """# @name@: @filter@ of "@model@" in C

Exported by `estim.codegen.export` (estim @version@). The code steps as
`estim`'s `step` does: prediction and update in CasADi's generated code
(`@name@_functions.c`), and in `@name@.c` what a step does with their flags: a
measurement beyond the gate keeps the prediction with `P0` added, a suspect one
(NIS beyond the @TAIL@ tail of its chi-square distribution) keeps its update, and a
failed update keeps the prediction of a trusted estimate or re-anchors on the last
trusted estimate with `P + P0`. NaN in `y` marks an output not measured.

- states `x` (@NX@): @states@
- outputs `y` (@NY@): @outputs@
- inputs `u` (@NU@): @inputs@

## API (`@name@.h`)

```c
@name@_t f;                                     /* the filter and all its memory */
int @name@_init(@name@_t *f);                   /* exported tuning, x = x0, P = P0 */
int @name@_reset(@name@_t *f);                  /* x = f->x0, P = f->P0 */
int @name@_step(@name@_t *f, const double *y, const double *u,
                double *x_hat, double *P);      /* status: 0 ok, 1 suspect,
                    2 rejected, 3 failed (kept the prediction), 4 failed
                    (re-anchored), -1 invalid argument */
double @name@_nis(const @name@_t *f);           /* NIS of the last step */
int @name@_set_tuning(@name@_t *f, const double *Q, const double *R,
                      const double *x0, const double *P0);
size_t @name@_size(void);                       /* sizeof(@name@_t) */
```

Matrices are column-major (`P[i + j*@NX@]` is `P(i, j)`). `u` is what Python's
`step(y, u)` gets (NULL for zeros).

## Memory

One `@name@_t` holds everything: @BYTES@ bytes on a 64-bit target (filter state,
tuning, the step's results and CasADi's work arrays: @SZ_W@ doubles, @SZ_IW@
integers, @SZ_ARG@ + @SZ_RES@ pointers). `@name@_step` allocates nothing and uses a
few hundred bytes of stack at most.

## Build

```sh
make            # lib@name@.a and lib@name@.so with $(CC) @CFLAGS@
```

or compile `@name@.c` and `@name@_functions.c` into your project (C99, `-lm`).
Keep `-ffp-contract=off` (and no `-ffast-math`) to compute what Python computes
operation for operation; without it the results agree to rounding only.

## Agreement with Python

estim's tests export filters like this one, build the library with the Makefile
and run recorded experiments through `@name@_step` and through `step`: estimates
and covariances agree to 1e-12 (in practice to the last bit) and the statuses are
the same, with missing outputs, gated and suspect measurements and failed updates.
"""


# ------------------------------------------------------------ the real-time MHE
#: Status codes of the MHE's ``<name>_step`` and ``<name>_prepare``.
MHE_STATUS = {0: "ok", 1: "inexact: the start-up's Gauss-Newton steps did not converge",
              2: "suspect: the window's cost beyond the 1e-9 chi-square tail",
              -1: "invalid argument (inf in y, non-finite u)",
              -2: "non-finite step: Python solves the window to convergence instead; "
                  "reset needed",
              -3: "u is not the input given to prepare"}

_ARRIVAL = {"none": 0, "fixed": 1, "filtering": 2, "smoothing": 3}


def _check_mhe(estimator) -> None:
    """Refuse the MHE configurations that have no C counterpart."""
    m = estimator.model
    if not estimator.rti:
        raise ValueError("estimator: an MHE is exported as its real-time iteration only "
                           "(the converged solve has no C counterpart): build it with "
                           "rti=True")
    if m.variable_dt:
        raise ValueError(f"{m.name} has variable_dt=True: the C step takes the model's "
                         f"fixed dt only; build the model without variable_dt to export")
    if getattr(m, "integrator", None) == "cvodes":
        raise ValueError(f"{m.name} is integrated by CVODES, which needs the CasADi "
                         f"runtime: build the model with integrator='rk4' to export")
    if estimator.horizon < 2:
        raise ValueError(f"horizon must be at least 2 to export the MHE, got "
                         f"{estimator.horizon}")


def _mhe_functions(estimator, name: str) -> list[ca.Function]:
    """The Functions of the real-time MHE under C names: ``prepare``, ``feedback`` and
    ``cost`` of :func:`estim.solvers.rti.build`, the arrival covariance's step and the
    model's transition ``F(x, u, p)``."""
    from estim.solvers import rti

    m = estimator.model
    prepare, feedback, cost = rti.build(m, estimator.horizon)
    return [_renamed(prepare, f"{name}_prepare_window"),
            _renamed(feedback, f"{name}_feedback_window"),
            _renamed(cost, f"{name}_window_cost"),
            _renamed(estimator._build_cov_step(), f"{name}_cov_step"),
            _renamed(m.F, f"{name}_transition")]


def _mhe_sizes(funs: list[ca.Function]) -> dict:
    return {k: max(1, *(int(getattr(f, f"sz_{k}")()) for f in funs))
            for k in ("arg", "res", "iw", "w")}


def _mhe_layout(estimator, sizes: dict) -> tuple[str, int, dict]:
    """The struct's fields (C text), its size in bytes and the dimensions."""
    m, N = estimator.model, estimator.horizon
    nx = m.nx
    ny, nu, nw = max(m.ny, 1), max(m.nu, 1), max(m.nw, 1)
    window = N * nx
    fields = [
        ("the tuning (the export's after init): the estimator reads Qinv, not Q, in "
         "the window's weights", None),
        ("Q", nx * nx, "process-noise covariance (the arrival covariance's step)"),
        ("Qinv", nx * nx, "its inverse (numpy's, at export): set it with Q"),
        ("R", ny * ny, "measurement-noise covariance"),
        ("x0", nx, "initial guess"),
        ("P0", nx * nx, "its covariance (the arrival cost's at reset; 'fixed': always)"),
        ("the window, oldest slot first (slot k: X + k*NX, ...)", None),
        ("X", window, "the window's estimates"),
        ("Y", N * ny, "its measurements (NaN: not measured)"),
        ("U", N * nw, "U[k]: the transition's input from slot k to k + 1"),
        ("Uprev", N * nu, "the input the output function sees at slot k"),
        ("xbar", nx, "the arrival cost's mean"),
        ("Pbar", nx * nx, "and covariance (filtering, smoothing)"),
        ("history", window, "the estimates of the window's times, oldest first"),
        ("u_last", nu, "the previous input (sampled inputs)"),
        ("u_prepared", nu, "the input given to prepare"),
        ("cost_last", 1, "the window's cost at the last estimate (its chi-square statistic)"),
        ("work memory of prepare and step", None),
        ("u_in", nu, ""), ("Xs", window, ""), ("trial", window, ""), ("dX", window, ""),
        ("P", nx * nx, ""), ("P_held", nx * nx, ""), ("grad_y", nx, ""), ("G", window, ""),
        ("ones", window, ""), ("free", window, ""), ("free_new", nx, ""), ("yv", ny, ""),
        ("ymask", ny, ""), ("a_Y", (N - 1) * ny, ""), ("a_mask", (N - 1) * ny, ""),
        ("a_U", (N - 1) * nw, ""), ("a_Up", N * nu, ""), ("a_a", N, ""), ("a_om", N - 1, ""),
        ("a_Pbar", nx * nx, ""), ("a_arrival", 1, ""), ("S0", nx * nx, ""), ("g0", nx, ""),
        ("C", ny * nx, ""), ("h", ny, ""), ("v", nx * (N - 1), ""),
        ("M", nx * nx * (N - 1), ""), ("grad", window, ""), ("cost", 1, ""),
        ("mask_old", ny, ""), ("Pn", nx * nx, ""), ("Pu", nx * nx, ""), ("pred", nx, ""),
        ("xbar_new", nx, ""), ("w", sizes["w"], "CasADi's work array"),
    ]
    lines, doubles = [], 0
    for field in fields:
        if field[1] is None:
            lines.append(f"    /* {field[0]} */")
            continue
        fname, size, comment = field
        doubles += size
        lines.append(f"    double {fname}[{size}];" + (f"  /* {comment} */" if comment else ""))
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
    dims = {"N": N, "NX": nx, "NY": m.ny, "NU": m.nu, "NW": m.nw, "NY1": ny, "NU1": nu,
            "NW1": nw, "SAMPLED": int(m.sampled), "SZ_ARG": sizes["arg"],
            "SZ_RES": sizes["res"], "SZ_IW": sizes["iw"], "SZ_W": sizes["w"], "BYTES": size}
    return "\n".join(lines), size, dims


def _write_mhe(estimator, directory: Path, name: str, paths: dict) -> None:
    from estim.consistency import chi2_limit
    from estim.estimators.mhe import RTI_STARTUP_ITERATIONS, RTI_STARTUP_XTOL

    m = estimator.model
    funs = _mhe_functions(estimator, name)
    gen = ca.CodeGenerator(f"{name}_functions.c", {"with_header": True})
    for fun in funs:
        gen.add(fun)
    gen.generate(str(directory) + "/")
    fields, _, dims = _mhe_layout(estimator, _mhe_sizes(funs))
    nx = m.nx
    P0 = estimator.P0 if estimator.P0 is not None else np.zeros((nx, nx))
    values = {"Q": _array(estimator.Q), "QINV": _array(np.linalg.inv(estimator.Q)),
              "R": _array(estimator.R), "X0": _array(estimator.x0), "P0": _array(P0),
              "LOWER": _array(estimator.lower), "UPPER": _array(estimator.upper),
              "PARAMS": _array(m.p), "EYE": _array(np.eye(nx)),
              "ARRIVAL": str(_ARRIVAL[estimator.arrival_cost]),
              "ARRIVAL_NAME": estimator.arrival_cost,
              "BOUNDED": str(int(bool(np.isfinite(estimator.lower).any()
                                      or np.isfinite(estimator.upper).any()))),
              "XTOL": _c(RTI_STARTUP_XTOL), "ITERATIONS": str(RTI_STARTUP_ITERATIONS),
              "CHI2": _array([chi2_limit(d) for d in range(estimator.horizon * m.ny + nx + 1)]),
              "FIELDS": fields}
    paths["h"].write_text(_fill(_MHE_HEADER, name, dims, values, estimator))
    paths["c"].write_text(_fill(_MHE_SOURCE, name, dims, values, estimator))
    paths["makefile"].write_text(_fill(_MAKEFILE, name, dims, values, estimator))
    paths["readme"].write_text(_fill(_MHE_README, name, dims, values, estimator))


_MHE_HEADER = r"""/* @name@.h -- @filter@ of the model "@model@" (estim @version@):
 * the moving horizon estimator's real-time iteration.
 *
 * States (x): @states@
 * Outputs (y): @outputs@
 * Inputs (u): @inputs@
 *
 * Matrices are stored column-major: P[i + j*NX] is P(i, j).
 *
 * Use:
 *     @name@_t e;                       // all memory: @BYTES@ bytes, no malloc
 *     @name@_init(&e);                  // tuning of the export, empty window
 *     for each sample:
 *         @name@_prepare(&e, u);        // optional, before y arrives
 *         int status = @name@_step(&e, y, u, x_hat, P);
 *
 * y (@NAME@_NY doubles): the measurement, NaN for an output not measured.
 * u (@NAME@_NU doubles, or NULL for zeros): the input that acted since the
 *   previous sample (for sampled inputs, hold="foh": the input at this sample),
 *   the same in prepare and in the step that follows it.
 * x_hat (@NAME@_NX), P (@NAME@_NX * @NAME@_NX): the estimate of the newest state
 *   and its covariance after the step (either may be NULL).
 *
 * The first @NAME@_N samples fill the window: each is solved to convergence by
 * projected Gauss-Newton steps (prepare does nothing then). Once the window is
 * full, prepare shifts it, moves the arrival cost on and linearises; the step
 * adds the measurement (one Gauss-Newton step). A step without prepare does both.
 *
 * Status of prepare and step:
 *    0  ok
 *    1  inexact: the start-up's Gauss-Newton steps did not converge in
 *       @ITERATIONS@ iterations (the estimate is the last iterate)
 *    2  suspect: the window's cost at the estimate (e.cost_last) is beyond the
 *       1e-9 tail of its chi-square distribution (outliers, or a model the data
 *       contradict); the estimate is kept
 *   -1  invalid argument: inf in y, a non-finite u, a NULL e or y (nothing
 *       changes), or (from init) work sizes that do not match the functions
 *   -2  a step that is not finite: estim's Python estimator then solves the
 *       window with its converged solver, which has no C counterpart; the
 *       estimator returns -2 until it is reset
 *   -3  u differs from the input given to prepare (nothing changes)
 */
#ifndef @NAME@_H
#define @NAME@_H

#ifdef __cplusplus
extern "C" {
#endif

#include <stddef.h>

#define @NAME@_N @N@    /* horizon: measurements in a full window */
#define @NAME@_NX @NX@  /* states */
#define @NAME@_NY @NY@  /* outputs */
#define @NAME@_NU @NU@  /* inputs given to step */
#define @NAME@_NW @NW@  /* the transition's input (u, or [u_prev; u] if sampled) */
/* CasADi's work memory of the generated functions (the largest of each) */
#define @NAME@_SZ_ARG @SZ_ARG@
#define @NAME@_SZ_RES @SZ_RES@
#define @NAME@_SZ_IW @SZ_IW@
#define @NAME@_SZ_W @SZ_W@

enum {
    @NAME@_OK = 0,
    @NAME@_INEXACT = 1,
    @NAME@_SUSPECT = 2,
    @NAME@_INVALID = -1,
    @NAME@_NONFINITE = -2,
    @NAME@_INPUT_MISMATCH = -3
};

/* The estimator and all its memory. The tuning is set by init to the export's;
 * change it between steps (Q, Qinv = Q^-1 and R act from the next step on, x0 and
 * P0 at the next reset; P0 at once with the fixed arrival cost). */
typedef struct {
@FIELDS@
} @name@_t;

/* Set the tuning of the export and reset. Returns 0, or -1 if the work sizes of
 * the generated functions exceed the struct's (code of another export). */
int @name@_init(@name@_t *e);

/* Empty the window: x = x0 everywhere, the arrival cost x0, P0; the next step
 * is the first. Returns 0 (-1 for NULL). */
int @name@_reset(@name@_t *e);

/* The preparation phase before the measurement of the next sample arrives, with
 * the input u the step will get: nothing while the window fills. Returns 0, -1
 * (non-finite u) or -2. */
int @name@_prepare(@name@_t *e, const double *u);

/* One sample: the measurement y after the input u. Returns the status (above)
 * and writes the estimate x_hat of the newest state and its covariance P. */
int @name@_step(@name@_t *e, const double *y, const double *u, double *x_hat,
                double *P);

/* Gauss-Newton iterations of the last step (1 once the window is full). */
int @name@_iterations(const @name@_t *e);

/* sizeof(@name@_t), for callers that allocate it from another language. */
size_t @name@_size(void);

#ifdef __cplusplus
}
#endif

#endif
"""

_MHE_SOURCE = r"""/* @name@.c -- @filter@ on "@model@" (estim @version@).
 * See @name@.h. No allocation; every array lives in @name@_t. Each function below
 * does what the method of estim's MHE named in its comment does, in the same order:
 * the numbers are the same doubles. */
#include <math.h>
#include <string.h>

#include "@name@.h"
#include "@name@_functions.h"

#define N @NAME@_N
#define NX @NAME@_NX
#define NY @NAME@_NY
#define NU @NAME@_NU
#define NW @NAME@_NW
#define NY1 @NY1@
#define NU1 @NU1@
#define NW1 @NW1@

enum { NONE = 0, FIXED = 1, FILTERING = 2, SMOOTHING = 3 };
static const int arrival_cost = @ARRIVAL@; /* @ARRIVAL_NAME@ */
static const int sampled = @SAMPLED@;
static const int bounded = @BOUNDED@;
static const double xtol = @XTOL@;
/* chi2_limits[d]: the value a chi-square variable with d degrees of freedom exceeds with
 * probability 1e-9 (the suspect test of the window's cost) */
static const double chi2_limits[] = @CHI2@;
static const int max_iterations = @ITERATIONS@;
static const double default_Q[] = @Q@;
static const double default_Qinv[] = @QINV@;
static const double default_R[] = @R@;
static const double default_x0[] = @X0@;
static const double default_P0[] = @P0@;
static const double lower[] = @LOWER@;
static const double upper[] = @UPPER@;
static const double params[] = @PARAMS@;
static const double eye[] = @EYE@;

typedef @name@_t est_t;

static void copy(double *to, const double *from, int n) {
    if (n > 0) memmove(to, from, (size_t) n * sizeof(double));
}

static int all_finite(const double *a, int n) {
    int k;
    for (k = 0; k < n; ++k)
        if (!isfinite(a[k])) return 0;
    return 1;
}

/* numpy's clip: NaN stays NaN, else max with lo, then min with hi */
static double clip(double x, double lo, double hi) {
    double v = isnan(x) ? x : (x > lo ? x : lo);
    return isnan(v) ? v : (v < hi ? v : hi);
}

/* arr[:-1] = arr[1:] of an (N, width) array */
static void shift_left(double *a, int width) {
    copy(a, a + width, (N - 1) * width);
}

size_t @name@_size(void) { return sizeof(est_t); }

int @name@_iterations(const est_t *e) { return e ? e->iterations : 0; }

/* MHE._reset */
int @name@_reset(est_t *e) {
    int k;
    if (!e) return @NAME@_INVALID;
    for (k = 0; k < N * NY1; ++k) e->Y[k] = NAN;
    for (k = 0; k < N * NW1; ++k) e->U[k] = 0.0;
    for (k = 0; k < N * NU1; ++k) e->Uprev[k] = 0.0;
    for (k = 0; k < N; ++k) copy(e->X + k * NX, e->x0, NX);
    for (k = 0; k < N * NX; ++k) e->ones[k] = 1.0;
    copy(e->xbar, e->x0, NX);
    copy(e->Pbar, e->P0, NX * NX);
    for (k = 0; k < NU1; ++k) e->u_last[k] = 0.0;
    e->n = 0;
    e->n_history = 0;
    e->first = 1;
    e->prepared = 0;
    e->failed = 0;
    e->iterations = 0;
    return @NAME@_OK;
}

static int fits(int (*work)(casadi_int *, casadi_int *, casadi_int *, casadi_int *)) {
    casadi_int a, r, i, w;
    return work(&a, &r, &i, &w) == 0 && a <= @NAME@_SZ_ARG && r <= @NAME@_SZ_RES &&
           i <= @NAME@_SZ_IW && w <= @NAME@_SZ_W;
}

int @name@_init(est_t *e) {
    if (!e || !fits(@name@_prepare_window_work) || !fits(@name@_feedback_window_work) ||
        !fits(@name@_window_cost_work) || !fits(@name@_cov_step_work) ||
        !fits(@name@_transition_work))
        return @NAME@_INVALID;
    copy(e->Q, default_Q, NX * NX);
    copy(e->Qinv, default_Qinv, NX * NX);
    copy(e->R, default_R, NY * NY);
    copy(e->x0, default_x0, NX);
    copy(e->P0, default_P0, NX * NX);
    return @name@_reset(e);
}

/* model.F(x, w, p) */
static void transition(est_t *e, const double *x, const double *w, double *x_next) {
    e->arg[0] = x;
    e->arg[1] = w;
    e->arg[2] = params;
    e->res[0] = x_next;
    @name@_transition(e->arg, e->res, (casadi_int *) e->iw, e->w, 0);
}

/* MHE._slide: drop the oldest measurement, move the arrival cost to the next time */
static void slide(est_t *e) {
    const double *x_est = e->history; /* the estimate of the time that leaves */
    int k;
    if (arrival_cost == FILTERING || arrival_cost == SMOOTHING) {
        for (k = 0; k < NY; ++k) e->mask_old[k] = isfinite(e->Y[k]) ? 1.0 : 0.0;
        e->arg[0] = x_est;
        e->arg[1] = e->U;
        e->arg[2] = e->Uprev;
        e->arg[3] = e->mask_old;
        e->arg[4] = e->Pbar;
        e->arg[5] = e->Q;
        e->arg[6] = e->R;
        e->res[0] = e->Pn;
        e->res[1] = e->Pu;
        @name@_cov_step(e->arg, e->res, (casadi_int *) e->iw, e->w, 0);
        if (all_finite(e->Pn, NX * NX))
            copy(e->Pbar, e->Pn, NX * NX);
        else /* the covariance grows as for a random walk */
            for (k = 0; k < NX * NX; ++k) e->Pbar[k] = e->Pbar[k] + e->Q[k];
    }
    copy(e->xbar_new, e->X + NX, NX);
    if (arrival_cost == FILTERING) {
        transition(e, x_est, e->U, e->pred);
        if (all_finite(e->pred, NX)) copy(e->xbar_new, e->pred, NX);
    }
    if (arrival_cost != NONE) copy(e->xbar, e->xbar_new, NX);
    shift_left(e->Y, NY1);
    shift_left(e->U, NW1);
    shift_left(e->Uprev, NU1);
    shift_left(e->X, NX);
    copy(e->history, e->history + NX, (e->n_history - 1) * NX);
    e->n_history -= 1;
    e->n -= 1;
}

/* MHE._shift: room for the arriving sample (input e->u_in) */
static void shift(est_t *e) {
    double *w = e->U + (N - 1) * NW1;
    int k;
    for (k = 0; k < NU; ++k) { /* Estimator._transition */
        if (sampled) {
            w[k] = e->u_last[k];
            w[NU + k] = e->u_in[k];
        } else {
            w[k] = e->u_in[k];
        }
    }
    if (e->n == N) {
        slide(e);
    } else {
        shift_left(e->Y, NY1);
        shift_left(e->U, NW1);
        shift_left(e->Uprev, NU1);
        shift_left(e->X, NX);
    }
    transition(e, e->X + (N - 2) * NX, e->U + (N - 2) * NW1, e->pred);
    copy(e->X + (N - 1) * NX, all_finite(e->pred, NX) ? e->pred : e->X + (N - 2) * NX, NX);
}

/* the arguments the preparation and cost Functions share: the window at X and its data */
static void window_args(est_t *e, const double *X) {
    e->arg[0] = X;
    e->arg[1] = e->a_Y;
    e->arg[2] = e->a_mask;
    e->arg[3] = e->a_U;
    e->arg[4] = e->a_Up;
    e->arg[5] = e->a_a;
    e->arg[6] = e->a_om;
    e->arg[7] = e->xbar;
    e->arg[8] = e->a_Pbar;
    e->arg[9] = e->a_arrival;
    e->arg[10] = e->Qinv;
    e->arg[11] = e->R;
}

/* MHE._linearise: the preparation Function at X for the window with the arriving
 * sample; free_vars (N*NX) the variables that may move (NULL: all) */
static void linearise(est_t *e, const double *free_vars) {
    int s0 = N - (e->n + 1), k, j;
    for (k = 0; k < N - 1; ++k)
        for (j = 0; j < NY; ++j) {
            int measured = k >= s0 && isfinite(e->Y[k * NY1 + j]);
            e->a_mask[k * NY1 + j] = measured ? 1.0 : 0.0;
            e->a_Y[k * NY1 + j] = measured ? e->Y[k * NY1 + j] : 0.0;
        }
    copy(e->a_U, e->U, (N - 1) * NW1);
    copy(e->a_Up, e->Uprev, (N - 1) * NU1);
    copy(e->a_Up + (N - 1) * NU1, e->u_in, NU1);
    for (k = 0; k < s0; ++k) { /* unused slots: the first used one's inputs */
        for (j = 0; j < NW; ++j) e->a_U[k * NW1 + j] = s0 < N - 1 ? e->a_U[s0 * NW1 + j] : 0.0;
        for (j = 0; j < NU; ++j) e->a_Up[k * NU1 + j] = e->a_Up[s0 * NU1 + j];
    }
    for (k = 0; k < N; ++k) e->a_a[k] = k == s0 ? 1.0 : 0.0;
    for (k = 0; k < N - 1; ++k) e->a_om[k] = k >= s0 ? 1.0 : 0.0;
    copy(e->a_Pbar, arrival_cost == NONE ? eye : arrival_cost == FIXED ? e->P0 : e->Pbar,
         NX * NX);
    e->a_arrival[0] = arrival_cost != NONE ? 1.0 : 0.0;
    if (!free_vars) free_vars = e->ones;
    copy(e->free_new, free_vars + (N - 1) * NX, NX);
    window_args(e, e->X);
    e->arg[12] = free_vars;
    e->res[0] = e->S0;
    e->res[1] = e->g0;
    e->res[2] = e->C;
    e->res[3] = e->h;
    e->res[4] = e->v;
    e->res[5] = e->M;
    e->res[6] = e->grad;
    @name@_prepare_window(e->arg, e->res, (casadi_int *) e->iw, e->w, 0);
}

/* the feedback Function on the prepared window and e->yv, e->ymask */
static void feedback(est_t *e, double *dX, double *P) {
    e->arg[0] = e->S0;
    e->arg[1] = e->g0;
    e->arg[2] = e->C;
    e->arg[3] = e->h;
    e->arg[4] = e->yv;
    e->arg[5] = e->ymask;
    e->arg[6] = e->R;
    e->arg[7] = e->v;
    e->arg[8] = e->M;
    e->arg[9] = e->free_new;
    e->res[0] = dX;
    e->res[1] = P;
    e->res[2] = e->grad_y;
    @name@_feedback_window(e->arg, e->res, (casadi_int *) e->iw, e->w, 0);
}

/* the window's cost at X with the newest measurement */
static double window_cost(est_t *e, const double *X) {
    window_args(e, X);
    e->arg[12] = e->yv;
    e->arg[13] = e->ymask;
    e->res[0] = e->cost;
    @name@_window_cost(e->arg, e->res, (casadi_int *) e->iw, e->w, 0);
    return e->cost[0];
}

static void measurement(est_t *e, const double *y) {
    int k;
    for (k = 0; k < NY; ++k) {
        int measured = isfinite(y[k]);
        e->yv[k] = measured ? y[k] : 0.0;
        e->ymask[k] = measured ? 1.0 : 0.0;
    }
}

/* the sample is in: the window's newest slot, its estimate in history */
static void accept(est_t *e, const double *y) {
    copy(e->Y + (N - 1) * NY1, y, NY);
    copy(e->Uprev + (N - 1) * NU1, e->u_in, NU);
    copy(e->history + e->n_history * NX, e->X + (N - 1) * NX, NX);
    e->n_history += 1;
}

/* MHE._rti_check: the window's cost at X (the newest measurement included) and whether
 * it is beyond the chi-square tail of its degrees of freedom */
static int suspect(est_t *e, const double *X) {
    int k, dof = arrival_cost != NONE ? NX : 0;
    e->cost_last[0] = 2.0 * window_cost(e, X);
    for (k = 0; k < (N - 1) * NY; ++k) dof += e->a_mask[k] != 0.0;
    for (k = 0; k < NY; ++k) dof += e->ymask[k] != 0.0;
    return e->cost_last[0] > chi2_limits[dof];
}

/* MHE._startup: a step while the window fills, solved by projected Gauss-Newton */
static int startup(est_t *e, const double *y) {
    int s0, k, i, iteration = 0, trials, held_any;
    double before, t, largest_step, largest;
    if (!e->first) shift(e);
    s0 = N - (e->n + 1);
    for (k = 0; k < s0; ++k) copy(e->X + k * NX, e->X + s0 * NX, NX);
    measurement(e, y);
    copy(e->Xs, e->X, N * NX);
    while (iteration < max_iterations) {
        iteration += 1;
        copy(e->X, e->Xs, N * NX);
        linearise(e, NULL);
        feedback(e, e->dX, e->P);
        copy(e->G, e->grad, N * NX);
        for (i = 0; i < NX; ++i) e->G[(N - 1) * NX + i] += e->grad_y[i];
        held_any = 0;
        for (k = 0; k < N; ++k)
            for (i = 0; i < NX; ++i) {
                double x = e->Xs[k * NX + i], g = e->G[k * NX + i];
                int held = ((x <= lower[i]) && (g > 0)) || ((x >= upper[i]) && (g < 0));
                if (k < s0) held = 0;
                e->free[k * NX + i] = held ? 0.0 : 1.0;
                held_any |= held;
            }
        if (held_any) {
            linearise(e, e->free);
            feedback(e, e->dX, e->P_held);
        }
        before = window_cost(e, e->Xs);
        t = 1.0;
        for (trials = 0; trials < 31; ++trials) {
            for (k = 0; k < N; ++k)
                for (i = 0; i < NX; ++i) {
                    double d = t * e->dX[k * NX + i];
                    e->trial[k * NX + i] = clip(e->Xs[k * NX + i] + d, lower[i], upper[i]);
                }
            if (window_cost(e, e->trial) <= before) break;
            t *= 0.5;
        }
        largest_step = 0.0;
        largest = 0.0;
        for (k = 0; k < N * NX; ++k) {
            double s = fabs(e->trial[k] - e->Xs[k]);
            if (s > largest_step) largest_step = s;
        }
        copy(e->Xs, e->trial, N * NX);
        if (!(all_finite(e->Xs, N * NX) && all_finite(e->P, NX * NX)))
            return @NAME@_NONFINITE;
        for (k = 0; k < N * NX; ++k)
            if (fabs(e->Xs[k]) > largest) largest = fabs(e->Xs[k]);
        if (largest_step <= xtol * (1 + largest)) break;
    }
    e->iterations = iteration;
    copy(e->X, e->Xs, N * NX);
    linearise(e, NULL); /* the covariance at the window found */
    feedback(e, e->dX, e->P);
    if (!all_finite(e->P, NX * NX)) return @NAME@_NONFINITE;
    k = suspect(e, e->X);
    accept(e, y);
    e->n += 1;
    return iteration < max_iterations ? (k ? @NAME@_SUSPECT : @NAME@_OK) : @NAME@_INEXACT;
}

/* MHE.prepare's work once the window is full: shift, then linearise */
static void prepare(est_t *e) {
    shift(e);
    linearise(e, NULL);
    copy(e->u_prepared, e->u_in, NU);
    e->prepared = 1;
}

/* MHE._feedback: the prepared window with the measurement */
static int feedback_step(est_t *e, const double *y) {
    int k, i;
    measurement(e, y);
    feedback(e, e->dX, e->P);
    for (k = 0; k < N; ++k)
        for (i = 0; i < NX; ++i) {
            double x = e->X[k * NX + i] + e->dX[k * NX + i];
            e->trial[k * NX + i] = bounded ? clip(x, lower[i], upper[i]) : x;
        }
    if (!(all_finite(e->trial, N * NX) && all_finite(e->P, NX * NX)))
        return @NAME@_NONFINITE;
    e->prepared = 0;
    k = suspect(e, e->trial);
    copy(e->X, e->trial, N * NX);
    accept(e, y);
    e->n = N;
    e->iterations = 1;
    return k ? @NAME@_SUSPECT : @NAME@_OK;
}

static int valid_input(const double *u) {
    int k;
    for (k = 0; k < NU; ++k)
        if (u && !isfinite(u[k])) return 0;
    return 1;
}

static void take_input(est_t *e, const double *u) {
    int k;
    for (k = 0; k < NU1; ++k) e->u_in[k] = u && k < NU ? u[k] : 0.0;
}

int @name@_prepare(est_t *e, const double *u) {
    int k;
    if (!e || !valid_input(u)) return @NAME@_INVALID;
    if (e->failed) return @NAME@_NONFINITE;
    if (e->prepared) { /* prepared already: the same input is a no-op */
        for (k = 0; k < NU; ++k)
            if (e->u_prepared[k] != (u ? u[k] : 0.0)) return @NAME@_INPUT_MISMATCH;
        return @NAME@_OK;
    }
    take_input(e, u);
    e->prepared = 0;
    if (e->first || e->n < N) return @NAME@_OK; /* filling: the step solves the window */
    prepare(e);
    return @NAME@_OK;
}

int @name@_step(est_t *e, const double *y, const double *u, double *x_hat, double *P) {
    int k, status;
    if (!e || !y || !valid_input(u)) return @NAME@_INVALID;
    for (k = 0; k < NY; ++k)
        if (isinf(y[k])) return @NAME@_INVALID;
    if (e->failed) return @NAME@_NONFINITE;
    if (e->prepared)
        for (k = 0; k < NU; ++k)
            if (e->u_prepared[k] != (u ? u[k] : 0.0)) return @NAME@_INPUT_MISMATCH;
    take_input(e, u);
    if (!e->prepared && (e->first || e->n < N)) {
        status = startup(e, y);
    } else if (!e->first && (e->prepared || e->n == N)) {
        if (!e->prepared) prepare(e);
        status = feedback_step(e, y);
    } else {
        return @NAME@_INVALID; /* not reached */
    }
    if (status == @NAME@_NONFINITE) {
        e->failed = 1;
        return status;
    }
    e->first = 0;
    if (sampled) copy(e->u_last, e->u_in, NU);
    if (x_hat) copy(x_hat, e->X + (N - 1) * NX, NX);
    if (P) copy(P, e->P, NX * NX);
    return status;
}
"""

_MHE_README = """# @name@: @filter@ of "@model@" in C

Exported by `estim.codegen.export` (estim @version@). The code is the moving horizon
estimator's real-time iteration over a window of @N@ samples with the "@ARRIVAL_NAME@"
arrival cost, as `estim.MHE(..., rti=True)` runs it in Python: CasADi's generated code
(`@name@_functions.c`) of the window's preparation, feedback and cost, of the arrival
covariance's step and of the model's transition, and in `@name@.c` the window's
bookkeeping (shift, arrival cost, start-up iterations with the bounds' held set and
halved steps, projection on the bounds). NaN in `y` marks an output not measured.

- states `x` (@NX@): @states@
- outputs `y` (@NY@): @outputs@
- inputs `u` (@NU@): @inputs@

## API (`@name@.h`)

```c
@name@_t e;                                     /* the estimator and all its memory */
int @name@_init(@name@_t *e);                   /* exported tuning, empty window */
int @name@_reset(@name@_t *e);                  /* empty window, arrival cost x0, P0 */
int @name@_prepare(@name@_t *e, const double *u);  /* before y arrives (optional) */
int @name@_step(@name@_t *e, const double *y, const double *u,
                double *x_hat, double *P);      /* status: 0 ok, 1 inexact start-up, 2 suspect,
                    -1 invalid argument, -2 non-finite step (reset needed),
                    -3 u is not the input given to prepare */
int @name@_iterations(const @name@_t *e);       /* Gauss-Newton iterations of the step */
size_t @name@_size(void);                       /* sizeof(@name@_t) */
```

Matrices are column-major (`P[i + j*@NX@]` is `P(i, j)`). `u` is what Python's
`step(y, u)` gets (NULL for zeros); `prepare` takes the same `u` before the measurement
arrives, and the step then only adds the measurement. While the window fills (the first
@N@ samples) each step solves the window to convergence and `prepare` does nothing.

A step that is not finite (status -2) is where Python solves the window with its
converged solver instead, which the C code does not have: the estimator then returns -2
until `@name@_reset`.

The tuning is in the struct (`Q`, `Qinv` = `Q`^-1, `R`, `x0`, `P0`): write `Q` and `Qinv`
together; `x0` and `P0` act at the next reset (`P0` at once with the fixed arrival cost).

## Memory

One `@name@_t` holds everything: @BYTES@ bytes on a 64-bit target (the window, the
arrival cost, the intermediate results of the preparation and CasADi's work arrays:
@SZ_W@ doubles, @SZ_IW@ integers, @SZ_ARG@ + @SZ_RES@ pointers). `@name@_prepare` and
`@name@_step` allocate nothing and use a few hundred bytes of stack at most.

## Build

```sh
make            # lib@name@.a and lib@name@.so with $(CC) @CFLAGS@
```

or compile `@name@.c` and `@name@_functions.c` into your project (C99, `-lm`).
Keep `-ffp-contract=off` (and no `-ffast-math`) to compute what Python computes
operation for operation; without it the results agree to rounding only.

## Agreement with Python

estim's tests export MHEs like this one, build the library and run recorded experiments
through `@name@_step` (with and without `@name@_prepare`) and through `step`: estimates
and covariances agree to 1e-12 (in practice to the last bit) and the statuses are the
same, with missing outputs, active bounds and every arrival cost.
"""
