r"""C code of a fused Kalman filter (:class:`~estim.EKF`, :class:`~estim.UKF`) for
deployment without Python or CasADi.

:func:`export` writes CasADi's generated C code of the filter's two step functions
(update only for the first sample, prediction and update for every later one), a
small hand-written driver that does what :meth:`~estim.Estimator.step` does with
their results (the gate, the suspect flag, the recovery of a failed update with its
last trusted estimate), a ``Makefile`` and a ``README.md``. The code is plain C99
with ``<math.h>`` and ``<string.h>`` only: no allocation, no CasADi runtime.
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


def export(estimator, directory: str | Path, *, name: str | None = None,
           overwrite: bool = False) -> dict[str, Path]:
    r"""Write C code of an EKF or UKF that steps as :meth:`~estim.Estimator.step` does.

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

    Parameters
    ----------
    estimator : EKF or UKF
        The filter (its tuning, options and bounds are what the code does).
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
        ``estimator`` is not an :class:`~estim.EKF` or :class:`~estim.UKF`.
    ValueError
        An invalid ``name``; a model with ``variable_dt=True`` (the interval of each
        step would be an argument of the C step: not supported) or integrated by
        CVODES (``integrator="cvodes"``, which needs the CasADi runtime).
    FileExistsError
        A file to write exists and ``overwrite`` is False.
    """
    from estim.estimators.fused import FusedKalman

    if not isinstance(estimator, FusedKalman):
        raise TypeError(f"estimator must be an estim.EKF or estim.UKF, got "
                        f"{type(estimator).__name__}")
    m = estimator.model
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

    funs = [_renamed(estimator._update.fun, f"{name}_update"),
            _renamed(estimator._predict_update.fun, f"{name}_predict_update")]
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
    step's results and CasADi's work arrays)."""
    funs = [_renamed(estimator._update.fun, "update"),
            _renamed(estimator._predict_update.fun, "predict_update")]
    sizes = {k: max(1, *(int(getattr(f, f"sz_{k}")()) for f in funs))
             for k in ("arg", "res", "iw", "w")}
    return _dimensions(estimator, sizes)["BYTES"]


def _renamed(fun: ca.Function, name: str) -> ca.Function:
    """``fun`` (an SX Function) under another name, every output dense."""
    args = fun.sx_in()
    return ca.Function(name, args, [ca.densify(o) for o in fun.call(args)],
                       ["s", "w", "y", "tuning"], fun.name_out())


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
    if getattr(estimator, "points", None):
        parts.append(f"points={estimator.points!r}")
    if estimator.clip:
        parts.append("clip=True")
    if estimator.gate is not None:
        parts.append(f"gate={estimator.gate:g}")
    return ", ".join(parts)


def _fill(template: str, name: str, dims: dict, values: dict, estimator) -> str:
    from estim import __version__
    from estim.estimators.base import SUSPECT_TAIL

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

_MAKEFILE = """# Builds lib@name@.a and lib@name@.so from the exported filter (estim @version@).
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
