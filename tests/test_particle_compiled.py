"""The compiled particle filter's pieces against references written here from their
published definitions: the per-particle C loops against CasADi's own evaluation, the
random numbers against xoshiro256** and the ziggurat written in Python, and the normal
law (Kolmogorov-Smirnov, moments, tails). The filter itself runs through every test of
``test_particle.py`` (the ``PF`` fixture: interpreted and compiled)."""

from __future__ import annotations

import ctypes
import math
import pickle
import warnings

import casadi as ca
import numpy as np
import pytest
from linear_gaussian import P0, X0, Q, R, linear_model, record
from scipy import stats

import estim
from estim._compile import compiler, shared_library
from estim._vectorised import c_kernel
from estim.exceptions import EstimationWarning
from estim.solvers.sampling import particle_kernel as pk

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

MASK = (1 << 64) - 1


def _rotl(x: int, k: int) -> int:
    return ((x << k) | (x >> (64 - k))) & MASK


def _xoshiro(s: list[int]) -> int:
    """xoshiro256** (Blackman, Vigna 2021), one output; ``s`` updated in place."""
    result = (_rotl((s[1] * 5) & MASK, 7) * 9) & MASK
    t = (s[1] << 17) & MASK
    s[2] ^= s[0]
    s[3] ^= s[1]
    s[1] ^= s[2]
    s[0] ^= s[3]
    s[2] ^= t
    s[3] = _rotl(s[3], 45)
    return result


def _normals_reference(state: np.ndarray, m: int) -> np.ndarray:
    """The kernel's normal numbers written out in Python: lane l of eight xoshiro256**
    streams gives the candidate of entry 8 j + l, ``u = 2 d - 3`` with ``d`` in [1, 2)
    from its bits 12..63 and layer ``i`` from bits 0..7; inside the box
    (``|u| < x[i+1]/x[i]``) it is ``u x[i]``, else the ziggurat goes on with the ninth
    stream (Marsaglia, Tsang 2000)."""
    x, q, f = pk.ziggurat_tables()
    lanes = [[int(state[8 * j + lane]) for j in range(4)] for lane in range(8)]
    scalar = [int(v) for v in state[32:36]]

    def unit(b: int) -> float:
        return float(np.array([(b >> 12) | 0x3FF0000000000000], np.uint64).view(np.float64)[0]) \
            * 2.0 - 3.0

    def uniform() -> float:
        return (_xoshiro(scalar) >> 11) * 2.0 ** -53

    def rest(u: float, i: int) -> float:
        while True:
            if abs(u) < q[i]:
                return u * x[i]
            if i == 0:
                while True:
                    a = math.log(1.0 - uniform()) / pk.ZIGGURAT_R
                    b = math.log(1.0 - uniform())
                    if not -2.0 * b < a * a:
                        return a - pk.ZIGGURAT_R if u < 0 else pk.ZIGGURAT_R - a
            xx = u * x[i]
            if f[i + 1] + uniform() * (f[i] - f[i + 1]) < math.exp(-0.5 * xx * xx):
                return xx
            b = _xoshiro(scalar)
            u, i = unit(b), b & 0xFF

    m8 = -(-m // 8) * 8
    bits = [_xoshiro(lanes[j % 8]) for j in range(m8)]
    out = [unit(b) * x[b & 0xFF] for b in bits]
    for j, b in enumerate(bits):
        if not abs(unit(b)) < q[b & 0xFF]:
            out[j] = rest(unit(b), b & 0xFF)
    return np.array(out[:m])


def _normals(seed: int, m: int, isa: int = -1) -> np.ndarray | None:
    lib = pk._driver()
    lib.pf_normals.restype = ctypes.c_int64
    lib.pf_normals.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]
    state = np.random.SeedSequence(seed).generate_state(36, np.uint64)
    out = np.empty(m)
    if lib.pf_normals(state.ctypes.data, out.ctypes.data, m, isa) != 0:
        return None
    return out


def test_the_normal_numbers_are_the_published_algorithms():
    """The first 3001 numbers (a length not a multiple of the eight lanes) equal the
    Python transcription bit for bit, including the draws beyond the boxes; and
    xoshiro256** itself gives the reference's first outputs from the state (1, 2, 3, 4):
    11520, 0, 1509978240, 1215971899390074240."""
    s = [1, 2, 3, 4]
    assert [_xoshiro(s) for _ in range(4)] == [11520, 0, 1509978240, 1215971899390074240]
    state = np.random.SeedSequence(5).generate_state(36, np.uint64)
    ours = _normals(5, 3001)
    assert np.array_equal(ours, _normals_reference(state, 3001))
    x, q, _ = pk.ziggurat_tables()
    # (the check above covered wedge draws: about one in a hundred leaves its box)
    assert 0.002 < np.mean(np.abs(ours / x[0]) > 0) <= 1.0


def test_every_instruction_set_gives_the_same_numbers():
    """Plain C, AVX2 and AVX-512 (where the processor has them) give identical numbers:
    a seed means the same run on every machine."""
    plain = _normals(11, 4099, isa=0)
    for isa in (1, 2):
        other = _normals(11, 4099, isa=isa)
        if other is not None:
            assert np.array_equal(other, plain), isa
    assert np.array_equal(_normals(11, 4099), plain)


def test_the_numbers_are_standard_normal():
    """10^6 numbers: Kolmogorov-Smirnov against N(0, 1), the first four moments within
    5 standard errors, and the tails beyond 3 and 3.65 (the ziggurat's base) as often as
    the normal law says (binomial, 5 standard errors)."""
    z = _normals(2024, 1_000_000)
    assert stats.kstest(z, "norm").pvalue > 1e-3
    n = len(z)
    assert abs(z.mean()) < 5 / math.sqrt(n)
    assert abs(z.var() - 1.0) < 5 * math.sqrt(2.0 / n)
    assert abs(stats.skew(z)) < 5 * math.sqrt(6.0 / n)
    assert abs(stats.kurtosis(z)) < 5 * math.sqrt(24.0 / n)
    for edge in (3.0, pk.ZIGGURAT_R, 4.0):
        p = 2 * stats.norm.sf(edge)
        count = np.sum(np.abs(z) > edge)
        assert abs(count - n * p) < 5 * math.sqrt(n * p * (1 - p)) + 1, (edge, count, n * p)


def test_c_loops_compute_what_casadi_computes():
    """``c_kernel`` over 1000 points equals CasADi's own evaluation of every point bit for
    bit: arithmetic, the elementary functions, comparisons and conditionals, a constant
    output and a structural zero, with some inputs shared by every point."""
    x, v, c = ca.SX.sym("x", 3), ca.SX.sym("v", 2), ca.SX.sym("c", 2)
    e1 = ca.sin(x[0]) * ca.exp(-x[1] ** 2) + ca.atan2(x[2], v[0]) - ca.sqrt(ca.fabs(x[1]))
    e2 = ca.if_else(x[0] > c[0], ca.log1p(x[0] ** 2), ca.fmin(x[1], c[1]) / (1 + v[1] ** 2))
    e3 = ca.sign(v[0]) * ca.power(ca.fabs(x[2]) + 1, 1.5) + ca.tanh(c[0] * x[1]) \
        + ca.floor(x[0]) - ca.cos(c[1])
    f = ca.Function("f", [x, v, c], [ca.vertcat(e1, e2, e3, c[0] * 2 + 1), ca.SX(1, 1)])
    code = c_kernel(f, "f_all", {0, 1})
    assert code is not None
    wrapper = code.replace("static void f_all", "void f_all")
    lib = shared_library("#include <math.h>\n#include <stddef.h>\n" + wrapper, "test_kernel",
                         pk.FLAGS)
    n = 1000
    rng = np.random.default_rng(0)
    X, V, C = rng.normal(size=(3, n)) * 3, rng.normal(size=(2, n)), np.array([0.3, -1.2])
    out0, out1 = np.empty((4, n)), np.full((1, n), 7.0)
    lib.f_all.restype = None
    lib.f_all(ctypes.c_size_t(n), *(ctypes.c_void_p(a.ctypes.data) for a in (X, V, C)),
              ctypes.c_void_p(out0.ctypes.data), ctypes.c_void_p(out1.ctypes.data))
    ref = np.hstack([np.asarray(f(X[:, i], V[:, i], C)[0]) for i in range(n)])
    assert np.array_equal(out0, ref)
    assert np.array_equal(out1, np.zeros((1, n)))  # the structural zero is written
    assert c_kernel(f.map(2), "m", {0}) is None  # not an SX graph: no C loop


def test_filter_is_fast_path_of_step_and_falls_back_with_a_warning():
    """``filter`` (one compiled call) equals ``replay`` (one call per step) bit for bit;
    a model whose states live on a manifold stays interpreted with one warning, as does
    a machine without a C compiler."""
    m, Y = linear_model(), record(30)
    pf = estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=257, jit=True, seed=4)
    res = pf.filter(Y)
    log = estim.replay(pf, Y)
    assert np.array_equal(np.asarray(log.x_hat), res.x)
    assert pf.particles[0].shape == (257, 2)
    att = estim.Model(states=["q0", "q1", "q2", "q3"], outputs=["y"],
                      dynamics=lambda x, u, p: x, output=lambda x, u, p: x[:1],
                      quaternions=[("q0", "q1", "q2", "q3")])
    with pytest.warns(EstimationWarning, match="stays interpreted.*quaternion"):
        estim.ParticleFilter(att, Q=np.eye(3) * 1e-4, R=0.1, x0=[1.0, 0, 0, 0],
                             P0=np.eye(3) * 1e-2, jit=True)


def test_without_a_compiler_the_filter_stays_interpreted(monkeypatch, tmp_path):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(tmp_path))
    m, Y = linear_model(), record(10)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        pf = estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=100, jit=True)
    assert any("stays interpreted" in str(w.message) for w in caught)
    ref = estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=100)
    assert np.array_equal(pf.filter(Y).x, ref.filter(Y).x)


def test_a_pickled_filter_goes_on_where_it_was():
    """The compiled state (particles, weights, random streams) travels with the filter:
    a copy made mid-record continues exactly as the original."""
    m, Y = linear_model(), record(12)
    pf = estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=300, jit=True, seed=2)
    for y in Y[:6]:
        pf.step(y)
    copy = pickle.loads(pickle.dumps(pf))
    a = [pf.step(y) for y in Y[6:]]
    b = [copy.step(y) for y in Y[6:]]
    assert np.array_equal(np.array(a), np.array(b))


def test_innovations_by_pattern_of_measured_outputs():
    """The batched NIS over patterns of missing outputs equals the one-by-one formula,
    with NaN where nothing is measured or the prediction is not finite."""
    from estim.estimators.sampling.particle_compiled import innovations

    rng = np.random.default_rng(3)
    T, ny = 40, 3
    Y = rng.normal(size=(T, ny))
    Y[rng.random((T, ny)) < 0.3] = np.nan
    Y[5] = np.nan
    yb = rng.normal(size=(T, ny))
    yb[7, :] = np.inf
    G = rng.normal(size=(T, ny, ny))
    Syy = G @ G.transpose(0, 2, 1)
    Rm = np.diag([0.1, 0.2, 0.3])
    E, nis = innovations(Y, ~np.isnan(Y), yb, Syy, Rm)
    for t in range(T):
        obs = ~np.isnan(Y[t])
        if not obs.any() or not np.isfinite(yb[t, obs]).all():
            assert np.isnan(nis[t]) and not E[t].any()
            continue
        e = Y[t, obs] - yb[t, obs]
        ref = e @ np.linalg.solve(Syy[t][np.ix_(obs, obs)] + Rm[np.ix_(obs, obs)], e)
        assert nis[t] == pytest.approx(ref, rel=1e-12)
        assert np.array_equal(E[t, obs], e) and not E[t, ~obs].any()


def test_the_normals_drawn_ahead_in_a_thread_are_the_same():
    """With the second thread drawing the next step's normal numbers, and without it,
    a record gives the same run bit for bit, also across a step that re-anchors (the
    streams left for the next call are those of the last step run)."""
    m, Y = linear_model(), record(40)
    Y[17] = 1e3  # no particle can explain it under the capped density below

    def capped(y, yhat, p):
        return ca.if_else(ca.fabs(y[0] - yhat[0]) < 5, -0.5 * (y[0] - yhat[0]) ** 2, -ca.inf)

    for loglik in (None, capped):
        runs = []
        for ahead in (False, True):
            pf = estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=500, jit=True,
                                      loglik=loglik, seed=9)
            pf._kernel.ahead = ahead
            runs.append(pf.filter(Y))
        assert np.array_equal(runs[0].x, runs[1].x) and np.array_equal(runs[0].P, runs[1].P)
        assert np.array_equal(runs[0].log_likelihood_increments,
                              runs[1].log_likelihood_increments, equal_nan=True)
    assert runs[1].status[17].startswith("failed: every particle weight is zero")
    assert all(s.startswith(("ok", "suspect")) for s in runs[1].status[18:])
