"""The per-machine compile cache (estim._compile): where it lives, its permissions, reuse
across processes, corrupt and foreign entries, and no compiler."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

from estim import _compile
from estim._compile import CompilerUnavailable, cache_directory, compiled, compiler

needs_cc = pytest.mark.skipif(compiler() is None, reason="no C compiler on this machine")


def _function(name="cache_test"):
    x = ca.SX.sym("x", 3)
    p = ca.SX.sym("p")
    return ca.Function(name, [x, p], [ca.vertcat(ca.sin(x[0]) * p, x[1] ** 2 / (1 + x[2] ** 2),
                                                 ca.sqrt(ca.fabs(x[2])) + 1e-17)],
                       ["x", "p"], ["y"])


@pytest.fixture
def cache(monkeypatch, tmp_path):
    """A fresh cache directory and nothing loaded in this process."""
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(tmp_path / "estim-cache"))
    monkeypatch.setattr(_compile, "_LOADED", {})
    return tmp_path / "estim-cache"


def _entries(root):
    return sorted(p.name for p in root.iterdir() if not p.name.startswith("build-"))


@needs_cc
def test_compiled_equals_the_interpreter_and_is_cached_privately(cache, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    f = _function()
    g = compiled(f)
    for x in ([0.3, -1.2, 2.0], [1e3, 1e-8, -0.5]):
        np.testing.assert_array_equal(np.asarray(g(x, 1.7)), np.asarray(f(x, 1.7)))
    assert stat.S_IMODE(cache.stat().st_mode) == 0o700
    names = _entries(cache)
    assert len(names) == 2 and names[0].endswith(".json") and names[1].endswith(".so")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["estim-cache"]  # not in the cwd
    record = json.loads((cache / names[0]).read_text())
    assert record["flags"] == list(_compile.FLAGS) and len(record["sha256"]) == 64


_IN_A_PROCESS = (
    "import sys, time, casadi as ca\n"
    "from estim import _compile\n"
    "built = []\n"
    "build = _compile._build\n"
    "_compile._build = lambda *a: (built.append(1), build(*a))\n"
    "x = ca.SX.sym('x', 3); p = ca.SX.sym('p')\n"
    "f = ca.Function('cache_test', [x, p], [ca.vertcat(ca.sin(x[0]) * p, x[1] ** 2 / "
    "(1 + x[2] ** 2), ca.sqrt(ca.fabs(x[2])) + 1e-17)], ['x', 'p'], ['y'])\n"
    "t0 = time.perf_counter(); g = _compile.compiled(f); t = time.perf_counter() - t0\n"
    "same = bool((g([0.3, -1.2, 2.0], 1.7) == f([0.3, -1.2, 2.0], 1.7)).is_one())\n"
    "print(len(built), same, t)\n")


def _run():
    """Compile (or load) the test Function in a new process: (compiled?, same numbers)."""
    out = subprocess.run([sys.executable, "-c", _IN_A_PROCESS], capture_output=True,
                         text=True, env={**os.environ}, check=True).stdout.split()
    return out[0] == "1", out[1] == "True"


@needs_cc
def test_a_later_process_loads_without_compiling(cache):
    assert _run() == (True, True)
    lib = next(cache.glob("*.so"))
    mtime = lib.stat().st_mtime_ns
    assert _run() == (False, True)
    assert lib.stat().st_mtime_ns == mtime


@needs_cc
@pytest.mark.parametrize("damage", ["truncated library", "foreign record", "no record"])
def test_damaged_entries_are_rebuilt(cache, damage):
    assert _run() == (True, True)
    lib, record = next(cache.glob("*.so")), next(cache.glob("*.json"))
    if damage == "truncated library":
        lib.write_bytes(lib.read_bytes()[:100])
    elif damage == "foreign record":
        meta = json.loads(record.read_text())
        record.write_text(json.dumps({**meta, "key": "0" * 64}))
    else:
        record.unlink()
    assert _run() == (True, True)  # detected, compiled again, right numbers
    meta = json.loads(record.read_text())
    assert meta["sha256"] == _compile._sha256(lib) and meta["key"] != "0" * 64
    assert _run() == (False, True)


def test_the_default_directory_is_the_users_cache(monkeypatch, tmp_path):
    monkeypatch.delenv("ESTIM_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    if sys.platform != "win32":
        assert cache_directory() == tmp_path / "xdg" / "estim"
        assert stat.S_IMODE((tmp_path / "xdg" / "estim").stat().st_mode) == 0o700


def test_without_a_compiler_a_clear_error(cache, monkeypatch):
    monkeypatch.setenv("CC", "/nonexistent/cc")
    assert compiler() is None
    with pytest.raises(CompilerUnavailable, match=r"no C compiler found \(\$CC = "
                                                  r"'/nonexistent/cc'\).*interpreted"):
        compiled(_function())


@needs_cc
def test_a_failing_compiler_is_reported(cache, monkeypatch, tmp_path):
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\nif [ \"$1\" = --version ]; then echo fake 1.0; exit 0; fi\n"
                    "echo 'fake: cannot compile' >&2; exit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    with pytest.raises(CompilerUnavailable, match="fake: cannot compile"):
        compiled(_function("another_test"))


@needs_cc
def test_an_unwritable_cache_is_reported(monkeypatch, tmp_path):
    blocker = tmp_path / "a file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(blocker / "cache"))
    monkeypatch.setattr(_compile, "_LOADED", {})
    with pytest.raises(CompilerUnavailable, match="ESTIM_CACHE_DIR to a writable"):
        compiled(_function("unwritable_test"))
    if getattr(os, "geteuid", lambda: 0)() != 0:  # root writes anywhere
        readonly = tmp_path / "readonly"
        readonly.mkdir(mode=0o500)
        monkeypatch.setenv("ESTIM_CACHE_DIR", str(readonly))
        with pytest.raises(CompilerUnavailable, match="not writable"):
            compiled(_function("readonly_test"))
