r"""The particle filter compiled to machine code: whole records in one call.

Two libraries, both through the per-machine compile cache
(:func:`estim._compile.shared_library`):

* the **driver** (``templates/particle_driver.c.in``, the same for every model:
  compiled once per machine), which runs :math:`T` steps per call: the normal draws,
  the model's per-particle Functions, the weights and their log-sum, the effective
  sample size, the weighted mean and covariance, the predicted outputs' mean and
  covariance under the previous weights, and the resampling
  (:mod:`estim.solvers.sampling.resampling`'s schemes);
* the **model's kernels**: its two per-particle Functions (the first step from the
  prior, and the step from a particle), each written as one loop over the particles
  (:func:`estim._vectorised.c_kernel`), which the driver calls through pointers (a
  few tenths of a second to compile).

The random numbers are the kernel's own: xoshiro256** (Blackman, Vigna 2021) in
eight interleaved streams for the normal numbers, drawn by a 256-layer ziggurat
(Marsaglia, Tsang 2000, with Doornik's 2005 uniforms), whose rare draws outside the
layers' boxes come from a ninth stream, and the resampling's uniforms from a tenth; all
ten are seeded from the filter's seed by :class:`numpy.random.SeedSequence`. On a
machine with more than one core, a second thread draws the next step's normal numbers
while a step runs (from :data:`AHEAD_MIN` numbers per step; the same numbers). The eight
streams are advanced together (AVX-512 or AVX2 where the processor has them, plain C
otherwise) and give the same numbers on every instruction set, so a seed gives the
same run bit for bit.

References
----------
D. Blackman, S. Vigna, "Scrambled linear pseudorandom number generators", ACM
Trans. Math. Softw. 47(4), 2021; J. A. Doornik, "An improved ziggurat method to
generate normal random samples", University of Oxford, 2005; G. Marsaglia,
W. W. Tsang, "The ziggurat method for generating random variables", J. Stat. Softw.
5(8), 2000; L. Devroye, *Non-Uniform Random Variate Generation*, Springer 1986, ch. 5
(sorted uniforms from exponential spacings).
"""

from __future__ import annotations

import ctypes
import math
import os
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import casadi as ca
import numpy as np

from estim._compile import shared_library
from estim._vectorised import c_kernel
from estim.exceptions import CompilerUnavailable

__all__ = ["KernelRecord", "ParticleKernel", "ziggurat_tables"]

#: the 256-layer ziggurat's right edge and layer area (Marsaglia, Tsang 2000)
ZIGGURAT_R = 3.6541528853610088
ZIGGURAT_V = 4.92867323399e-3
ZIGGURAT_LAYERS = 256
#: the kernel's flags: optimised with vectorisation, no fast-math, no contraction (the
#: per-particle Functions compute what CasADi's virtual machine computes)
FLAGS = ("-O3", "-pthread", "-fPIC", "-shared", "-fno-fast-math", "-ffp-contract=off")
_SCHEMES = {"systematic": 0, "stratified": 1, "multinomial": 2, "residual": 3}
#: the fewest normal numbers per step for which a second thread draws them ahead (below,
#: handing a step's numbers over costs more than drawing them)
AHEAD_MIN = 8192


def ziggurat_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    r"""The ziggurat's layer edges ``x (L+1,)`` (``x[0] = V / f(R)``, the base layer
    with its tail, ``x[1] = R``, ``x[L] = 0``; layers of equal area ``V`` under
    :math:`f(x) = e^{-x^2/2}`), the ratios ``x[i+1] / x[i]`` ``(L,)`` below which a
    candidate ``u x[i]`` lies inside its layer's box, and ``f(x[i])`` ``(L+1,)``."""
    R, V, L = ZIGGURAT_R, ZIGGURAT_V, ZIGGURAT_LAYERS
    x = np.zeros(L + 1)
    f = math.exp(-0.5 * R * R)
    x[0], x[1] = V / f, R
    for i in range(2, L):
        x[i] = math.sqrt(-2.0 * math.log(V / x[i - 1] + f))
        f = math.exp(-0.5 * x[i] * x[i])
    return x, x[1:] / x[:-1], np.exp(-0.5 * x * x)


class _Args(ctypes.Structure):
    """The C driver's ``pf_args``, field for field."""

    _fields_ = [(name, ctypes.c_int64) for name in
                ("n", "T", "first", "scheme", "nx", "ny", "nd", "nw", "ntun", "ahead")] + \
        [("threshold", ctypes.c_double)] + \
        [(name, ctypes.c_void_p) for name in (
            "k_first", "k_advance", "lower", "upper", "x0", "tun0", "w", "tun", "y0", "WR",
            "miss", "measured", "X", "lw", "Wp", "equal", "rng", "work", "iwork", "xh", "P",
            "ess", "inc", "yb", "Syy", "resampled", "distinct", "trace_X", "trace_W")]


#: the kernels' file: the two Functions of a model, compiled for AVX-512, AVX2 and the
#: baseline where the compiler can (the same numbers on each)
_KERNEL_HEAD = """#include <math.h>
#include <stddef.h>
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__linux__)
#define PF_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define PF_CLONES
#endif
"""


def _contiguous(value: np.ndarray, dtype: type) -> np.ndarray:
    """``value`` as a C-contiguous array of ``dtype`` (itself when it is one already)."""
    if isinstance(value, np.ndarray) and value.dtype == dtype and value.flags.c_contiguous:
        return value
    return np.ascontiguousarray(value, dtype=dtype)


@lru_cache(maxsize=1)
def _driver() -> ctypes.CDLL:
    """The driver's library (the same for every model: compiled once per machine)."""
    text = (resources.files("estim.solvers.sampling") / "templates" /
            "particle_driver.c.in").read_text()
    x, q, f = ziggurat_tables()
    for key, value in {"ZR": ZIGGURAT_R.hex(), "ZX": ", ".join(v.hex() for v in x),
                       "ZQ": ", ".join(v.hex() for v in q),
                       "ZF": ", ".join(v.hex() for v in f)}.items():
        text = text.replace(f"@{key}@", value)
    lib = shared_library(text, "estim_particles", FLAGS)
    lib.pf_run.restype = lib.pf_work_size.restype = ctypes.c_int64
    lib.pf_run.argtypes = [ctypes.POINTER(_Args)]
    lib.pf_work_size.argtypes = [ctypes.c_int64] * 4
    return lib


#: the outputs of a call, in this order in one buffer: x, P, ess, inc, yb, Syy, the
#: resampling flags and the distinct particles (int64, the same size as a double)
_OUTPUTS = ("xh", "P", "ess", "inc", "yb", "Syy", "resampled", "distinct")


@dataclass
class KernelRecord:
    """What :meth:`ParticleKernel.run` gives for the steps it ran (``(k, ...)`` arrays)."""

    done: int
    x: np.ndarray
    P: np.ndarray
    ess: np.ndarray
    inc: np.ndarray
    yb: np.ndarray
    Syy: np.ndarray
    resampled: np.ndarray
    distinct: np.ndarray


class ParticleKernel:
    """A particle filter's compiled steps and their state.

    Parameters
    ----------
    first, advance : casadi.Function
        ``first(x0, v, w, tun0, y0, WR, miss) -> (x, yhat, l)`` and
        ``advance(x, v, w, tun, y0, WR, miss) -> (x, yhat, l)``: a particle from the
        prior and from a particle, drawn with the standard normal ``v`` (ndx), its
        predicted output and log-weight factor (see
        :func:`estim.estimators.sampling.particle_graphs.graphs`).
    n : int
        The number of particles.
    lower, upper : (nx,) arrays
        The support (-inf and inf where unbounded).

    Raises
    ------
    CompilerUnavailable
        No C compiler (the caller stays interpreted), or a Function that calls
        another Function.

    Attributes
    ----------
    X : (nx, n) array
        The particles after the last step (after resampling).
    lw : (n,) array
        Their normalised log-weights (meaningful when not :attr:`equal`).
    W : (n,) array
        Their normalised weights (meaningful when not :attr:`equal`).
    equal : bool
        Equal weights (after a resampling).
    """

    def __init__(self, first: ca.Function, advance: ca.Function, *, n: int,
                 lower: np.ndarray, upper: np.ndarray):
        k_first, k_advance = c_kernel(first, "k_first", {1}), c_kernel(advance, "k_advance", {0, 1})
        if k_first is None or k_advance is None:
            raise CompilerUnavailable("the model's graph calls another Function (an "
                                      "integrator): the particle filter stays interpreted")
        self.nx, self.nd = advance.nnz_in(0), advance.nnz_in(1)
        self.nw, self.ny = advance.nnz_in(2), advance.nnz_in(4)
        self.ntun, self.ntun0 = advance.nnz_in(3), first.nnz_in(3)
        self.n = n
        self.bounds = (np.ascontiguousarray(lower, float), np.ascontiguousarray(upper, float))
        self._lib = _driver()
        code = _KERNEL_HEAD + "\n".join(k.replace("static void k_", "PF_CLONES void k_")
                                         for k in (k_first, k_advance))
        self._model_lib = shared_library(code, "estim_particle_model", FLAGS)
        self._kernels = [ctypes.cast(getattr(self._model_lib, name), ctypes.c_void_p).value
                         for name in ("k_first", "k_advance")]
        self.work = np.empty(int(self._lib.pf_work_size(n, self.nx, self.nd, self.ny)))
        self.iwork = np.empty(n, dtype=np.int64)
        self.X = np.zeros((self.nx, n))
        self.lw, self.W = np.zeros(n), np.full(n, 1.0 / n)
        self._equal = np.ones(1, dtype=np.int64)
        self.rng = np.zeros(40, dtype=np.uint64)
        self._zero = np.zeros(1)
        self._empty = self._zero.ctypes.data  # (an input without entries)
        # the call's arguments that do not change (the buffers are the kernel's own)
        self._args = _Args(n=n, nx=self.nx, ny=self.ny, nd=self.nd, nw=self.nw,
                           ntun=self.ntun, k_first=self._kernels[0],
                           k_advance=self._kernels[1])
        for name, array in (("lower", self.bounds[0]), ("upper", self.bounds[1]),
                            ("X", self.X), ("lw", self.lw), ("Wp", self.W),
                            ("equal", self._equal), ("rng", self.rng), ("work", self.work),
                            ("iwork", self.iwork)):
            setattr(self._args, name, array.ctypes.data)
        self._step_io: tuple | None = None  # (step's argument buffers: built on first use)
        #: draw the next step's normal numbers in a second thread while a step runs
        #: (the same numbers either way), from :data:`AHEAD_MIN` numbers per step
        self.ahead = (os.cpu_count() or 1) > 1 and self.nd * n >= AHEAD_MIN

    @property
    def equal(self) -> bool:
        return bool(self._equal[0])

    def step(self, *, first: bool, x0: np.ndarray, tun0: np.ndarray, w: np.ndarray,
             tun: np.ndarray, y0: np.ndarray, WR: np.ndarray, miss: np.ndarray,
             measured: bool, scheme: str, threshold: float) -> KernelRecord:
        """One step (:meth:`run` with ``T = 1``, the data of the step as flat arrays),
        through buffers kept from call to call: no addresses to take."""
        if self._step_io is None:  # built on the first step
            sizes = [self.nx, self.ntun0, self.nw, self.ntun, self.ny,
                     self.ny * self.ny, self.ny, 1]
            names = ["x0", "tun0", "w", "tun", "y0", "WR", "miss", "measured"]
            bounds = np.cumsum([0, *[max(size, 1) for size in sizes]])
            inputs = np.zeros(bounds[-1])
            args = _Args()
            ctypes.pointer(args)[0] = self._args  # (a copy of the unchanging fields)
            base, views = inputs.ctypes.data, {}
            for i, name in enumerate(names):
                setattr(args, name, base + 8 * int(bounds[i]))
                views[name] = inputs[bounds[i]:bounds[i] + sizes[i]]
            views["measured"] = inputs[bounds[7]:bounds[7] + 1].view(np.int64)
            outputs, offsets = self._outputs(1)
            self._point_outputs(args, outputs, offsets)
            args.T, args.trace_X, args.trace_W = 1, None, None
            self._step_io = (args, views, outputs, offsets)
        args, views, outputs, offsets = self._step_io
        for name, value in (("w", w), ("tun", tun), ("y0", y0), ("WR", WR), ("miss", miss)):
            views[name][:] = value
        if first:
            views["x0"][:], views["tun0"][:] = x0, tun0
        views["measured"][0] = int(measured)
        args.first, args.scheme = int(first), _SCHEMES[scheme]
        args.threshold, args.ahead = threshold, 0
        done = int(self._lib.pf_run(ctypes.byref(args)))
        return self._record(outputs.copy(), offsets, 1, done)

    def _outputs(self, T: int) -> tuple[np.ndarray, np.ndarray]:
        """One buffer for the outputs of ``T`` steps (see :data:`_OUTPUTS`) and the
        offsets of its parts."""
        nx, ny = self.nx, self.ny
        offsets = np.cumsum([0, T * nx, T * nx * nx, T, T, T * ny, T * ny * ny, T, T])
        return np.empty(offsets[-1]), offsets

    @staticmethod
    def _point_outputs(args: _Args, buf: np.ndarray, offsets: np.ndarray) -> None:
        """The call's output fields pointed at the parts of ``buf``."""
        base = buf.ctypes.data
        for i, name in enumerate(_OUTPUTS):
            setattr(args, name, base + 8 * int(offsets[i]))

    def _record(self, buf: np.ndarray, offsets: np.ndarray, T: int, done: int
                ) -> KernelRecord:
        """The outputs of ``T`` steps in ``buf`` as a :class:`KernelRecord` (views)."""
        nx, ny = self.nx, self.ny
        part = [buf[offsets[i]:offsets[i + 1]] for i in range(len(_OUTPUTS))]
        return KernelRecord(done, part[0].reshape(T, nx), part[1].reshape(T, nx, nx), part[2],
                            part[3], part[4].reshape(T, ny), part[5].reshape(T, ny, ny),
                            part[6].view(np.int64), part[7].view(np.int64))

    def seed(self, seed: int) -> None:
        """Start the ten streams of ``seed`` again."""
        self.rng[:] = np.random.SeedSequence(seed).generate_state(40, np.uint64)
        for lane in range(10):  # a stream's state must not be all zero
            idx = [8 * j + lane for j in range(4)] if lane < 8 else \
                [32 + 4 * (lane - 8) + j for j in range(4)]
            if not self.rng[idx].any():
                self.rng[idx[0]] = 1

    def set_particles(self, X: np.ndarray, W: np.ndarray | None) -> None:
        """Particles ``(nx, n)`` and their normalised weights (None: equal) set from
        outside (a re-anchoring step run interpreted)."""
        self.X[:] = X
        self._equal[0] = W is None
        if W is not None:
            self.W[:] = W
            with np.errstate(divide="ignore"):
                self.lw[:] = np.log(W)

    def run(self, *, first: bool, x0: np.ndarray, tun0: np.ndarray, w: np.ndarray,
            tun: np.ndarray, y0: np.ndarray, WR: np.ndarray, miss: np.ndarray,
            measured: np.ndarray, scheme: str, threshold: float,
            trace: tuple[np.ndarray, np.ndarray] | None = None) -> KernelRecord:
        """Run the steps of a record (``(T, ...)`` rows of the step data: ``w`` (T, nw),
        ``tun`` (T, ntun), ``y0``, ``miss`` (T, ny), ``WR`` (T, ny * ny), ``measured``
        (T,) 0/1), from the prior if ``first``, resampling by ``scheme`` when the
        effective sample size falls below ``threshold * n``. Stops before a step that leaves no
        weight (:attr:`KernelRecord.done` less than T); its particles are then the
        last step's. ``trace``: ``(T, nx, n)`` and ``(T, n)`` arrays filled with the
        particles and weights of every step before resampling."""
        T = len(measured)
        buf, offsets = self._outputs(T)
        args = self._args
        args.T, args.first, args.scheme = T, int(first), _SCHEMES[scheme]
        args.threshold, args.ahead = threshold, int(self.ahead)
        held = []  # (the arrays whose addresses the call reads, alive until it returns)
        for name, value in (("x0", x0), ("tun0", tun0), ("w", w), ("tun", tun), ("y0", y0),
                            ("WR", WR), ("miss", miss), ("measured", measured)):
            array = _contiguous(value, np.int64 if name == "measured" else np.float64)
            held.append(array)
            setattr(args, name, array.ctypes.data if array.size else self._empty)
        self._point_outputs(args, buf, offsets)
        args.trace_X = None if trace is None else trace[0].ctypes.data
        args.trace_W = None if trace is None else trace[1].ctypes.data
        done = int(self._lib.pf_run(ctypes.byref(args)))
        return self._record(buf, offsets, T, done)
