"""Progress of long work: a bar on a terminal or in Jupyter once the work is slow, never
in a log or under pytest's capture unless asked, silenced by ESTIM_PROGRESS=0."""

from __future__ import annotations

import numpy as np
import pytest
from linear_gaussian import P0, X0, Q, R, linear_model, record

import estim
from estim import _progress


@pytest.fixture
def shown(monkeypatch):
    """Bars on (as on a terminal), with no delay."""
    monkeypatch.setenv(_progress.ENV, "1")
    monkeypatch.setattr(_progress, "DELAY", 0.0)


def test_who_sees_a_bar(monkeypatch):
    monkeypatch.delenv(_progress.ENV, raising=False)
    assert not _progress.enabled()  # pytest's capture: stderr is not a terminal
    assert isinstance(_progress.bar(10), _progress._NoBar)
    monkeypatch.setenv(_progress.ENV, "1")
    assert _progress.enabled() and not isinstance(_progress.bar(10), _progress._NoBar)
    for off in ("0", "false", "Off"):
        monkeypatch.setenv(_progress.ENV, off)
        assert not _progress.enabled() and _progress.enabled(True)
    monkeypatch.delenv(_progress.ENV)
    # a Jupyter kernel: an IPython shell of a kernel application
    import sys
    import types

    shell = types.SimpleNamespace(config={"IPKernelApp": {}})
    monkeypatch.setitem(sys.modules, "IPython",
                        types.SimpleNamespace(get_ipython=lambda: shell))
    assert _progress.enabled()
    shell.config = {}  # a terminal IPython, whose stderr pytest captures
    assert not _progress.enabled()
    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    assert _progress.enabled()  # a terminal


def test_long_work_reports_and_quiet_work_does_not(shown, capsys, monkeypatch):
    m = linear_model()
    Y = record(60, seed=1)
    estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y)
    err = capsys.readouterr().err
    assert "FullInformation.fit, 60 samples" in err and "cost" in err
    estim.ParticleFilter(m, Q=Q, R=R, x0=X0, P0=P0, n_particles=50, seed=0).smooth(
        Y, n_paths=5)
    err = capsys.readouterr().err
    assert "ParticleFilter.filter" in err and "particle smoother, 5 paths" in err
    sc = estim.scenarios.van_der_pol(n_steps=20)
    estim.compare(sc, {"ekf": estim.EKF}, seeds=range(2))
    assert "compare on van_der_pol" in capsys.readouterr().err
    estim.compare(sc, {"ekf": estim.EKF}, seeds=range(2), progress=False)
    assert capsys.readouterr().err == ""
    # the bars leave nothing behind them, and nothing at all when silenced
    monkeypatch.setenv(_progress.ENV, "0")
    estim.FullInformation(m, Q=Q, R=R, x0=X0, P0=P0).fit(Y)
    assert capsys.readouterr().err == ""


def test_a_first_compilation_says_so(shown, capsys, monkeypatch, tmp_path):
    from estim._compile import compiler

    if compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setenv("ESTIM_CACHE_DIR", str(tmp_path))
    ekf = estim.EKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, jit=True)
    ekf.step(np.array([0.1]))
    err = capsys.readouterr().err
    assert "compiling ekf" in err and "once per machine" in err
    # the second build of the same code is loaded from the cache, without a word
    estim.EKF(linear_model(), Q=Q, R=R, x0=X0, P0=P0, jit=True).step(np.array([0.1]))
    assert "compiling" not in capsys.readouterr().err
