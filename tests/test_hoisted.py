"""The slot step split into its weights-only part and the rest (solvers.stages.hoisted):
the same numbers bit for bit, and fewer instructions per iteration on a full record."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import estim
from estim.solvers.least_squares import stages
from estim.solvers.least_squares.stages import StageFunctions, hoisted

# the slot step's inputs after the carries: x, x_next, y, wy, up, a, u, omega, wq, link,
# xbar, w0, A0 (and lam when damped); the weights, bookkeeping and damping are hoisted
_AFTER_CARRY = ["x", "xn", "y", "wy", "up", "a", "u", "om", "wq", "link", "xbar", "w0",
                "a0", "lam"]
_HOISTED = {"wy", "a", "om", "wq", "link", "xbar", "w0", "a0", "lam"}


def _models():
    return [estim.models.lorenz(), estim.models.van_der_pol()]


@pytest.mark.parametrize("model", _models(), ids=lambda m: m.name)
@pytest.mark.parametrize("newton, damped, bounded", [(False, False, False), (True, False, False),
                                                     (False, True, False), (True, True, True)])
def test_split_step_is_bit_identical(model, newton, damped, bounded):
    nx = model.nx
    bounds = (np.full(nx, -2.0), np.full(nx, 2.0)) if bounded else None
    for diagonal in (False, True):
        step = StageFunctions(model, diagonal, diagonal).fused(newton, damped, bounds)
        n_carry = step.n_in() - len(_AFTER_CARRY) + (0 if damped else 1)
        names = _AFTER_CARRY if damped else _AFTER_CARRY[:-1]
        inputs = [n_carry + k for k, n in enumerate(names) if n in _HOISTED]
        split = hoisted(step, inputs)
        assert split is not None
        pre, core = split
        rng = np.random.default_rng(1)
        for bookkeeping in ((1.0, 1.0, 1.0), (0.0, 1.0, 1.0), (0.0, 0.0, 0.0)):
            args = [rng.uniform(-1.5, 1.5, step.sparsity_in(i).nnz())
                    for i in range(step.n_in())]
            for name, value in zip(("a", "om", "link"), bookkeeping, strict=True):
                args[n_carry + names.index(name)] = np.array([value])
            dm = [ca.DM(step.sparsity_in(i), a) for i, a in enumerate(args)]
            want = step(*dm)
            got = core(*dm, pre(*[dm[i] for i in inputs]))
            for w, g in zip(want, got, strict=True):
                assert np.array_equal(np.asarray(w), np.asarray(g))


def _iteration_instructions():
    y = np.random.default_rng(0).normal(size=(100, 3))
    fie = estim.FullInformation(estim.models.lorenz(), Q=np.eye(3) / 20, R=np.eye(3))
    res = fie.fit(y)
    gn = next(iter(fie._nlps.values())).gn
    return gn._function("gn", True)[0].fun.n_instructions(), res


def test_full_record_iteration_runs_fewer_instructions(monkeypatch):
    """The Lorenz fit's iteration computes the products of the weights once, not in
    every slot: about a tenth fewer instructions, the same fit."""
    hoisted_count, res = _iteration_instructions()
    monkeypatch.setattr(stages, "_hoisted_scan", lambda *args: None)
    plain_count, plain = _iteration_instructions()
    assert hoisted_count < 0.95 * plain_count
    assert np.array_equal(res.x, plain.x) and res.iterations == plain.iterations
