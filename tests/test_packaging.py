"""The package as users get it: a light ``import estim``, lazy names that behave like
eager ones, and type information a type checker reads."""

from __future__ import annotations

import importlib
import importlib.util
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import estim

ROOT = Path(__file__).resolve().parents[1]
#: Imported on first use only: each takes a tenth of a second or more to import.
HEAVY = ("filterpy", "matplotlib", "pandas", "scipy.stats", "scipy.optimize", "dask", "sympy")


def _imported_by(code: str) -> set[str]:
    """The modules that ``code`` imports in a fresh interpreter: those that
    ``-X importtime`` reports, and those in ``sys.modules`` at the end (importtime
    leaves out what ``importlib.import_module`` loads)."""
    marker = "--- sys.modules ---"
    code += f"\nimport sys\nprint({marker!r}, *sys.modules, sep='\\n')"
    proc = subprocess.run([sys.executable, "-X", "importtime", "-c", code],
                          capture_output=True, text=True, timeout=120, check=True)
    timed = {line.rsplit("|", 1)[1].strip() for line in proc.stderr.splitlines()
             if line.startswith("import time:") and "|" in line}
    assert timed, proc.stderr
    return timed | set(proc.stdout.split(marker, 1)[1].split())


def test_import_estim_leaves_heavy_modules_alone():
    modules = _imported_by("import estim")
    assert "estim" in modules and "casadi" in modules
    assert not {m for m in modules if m in HEAVY or m.startswith(tuple(f"{h}." for h in HEAVY))}
    # the estimator modules wait for their first use too
    assert not {m for m in modules if m.startswith(("estim.estimators.kalman.ekf",
                                                      "estim.estimators.window.shooting",
                                                      "estim.estimators.kalman.ukf"))}


def test_estimators_without_their_optional_dependencies():
    # building every estimator needs neither filterpy (estim never imports it: it is the
    # reference of the tests and benchmarks) nor matplotlib, pandas or scipy.stats
    modules = _imported_by("import estim; from estim import EKF, MHE, FullInformation, "
                           "ShootingObserver, UKF; from estim.estimators import ESTIMATORS")
    assert not {"filterpy", "matplotlib", "pandas", "scipy.stats", "scipy.optimize"} & modules


def test_cli_list_leaves_heavy_modules_alone():
    modules = _imported_by("import sys; from estim.cli import main; "
                           "sys.argv = ['estim', 'list']; main()")
    assert "estim.estimators.window.shooting" in modules  # it lists every estimator
    assert not {"filterpy", "matplotlib", "pandas", "scipy.stats", "scipy.optimize",
                "scipy.special"} & modules


def test_lazy_names_are_public_names():
    assert estim.__all__ == [
        "EKF", "MHE", "UKF", "Comparison", "EnKF", "EstimationWarning", "Estimator",
        "FitResult",
        "FullInformation", "IMM", "Log", "Model", "ParameterEstimates", "ParticleFilter", "RMSE",
        "Record", "Scenario", "ShootingObserver", "StepInfo", "chi2_bounds",
        "compare", "convergence_time", "errors", "models", "nees", "nis", "observability",
        "parameter_uncertainty", "records", "replay", "rmse", "scenarios", "simulate", "smooth",
        "soft", "tuning"]
    assert set(estim.__all__) <= set(dir(estim))
    from estim import EKF, UKF, FitResult, FullInformation, observability, smooth, soft
    from estim.estimators import ESTIMATORS
    from estim.estimators.kalman.ekf import EKF as EKF_
    from estim.estimators.window.fie import FitResult as FitResult_

    assert EKF is EKF_ is estim.EKF is ESTIMATORS["ekf"] and FitResult is FitResult_
    assert UKF is ESTIMATORS["ukf"] and FullInformation is ESTIMATORS["fie"]
    assert observability.__name__ == "estim.observability" and soft.__name__ == "estim.soft"
    # the switches' helpers' former name still works, the very functions
    assert smooth.__name__ == "estim.smooth" and smooth.relu is soft.relu
    assert all(getattr(smooth, name) is getattr(soft, name) for name in soft.__all__)
    from estim import ParameterEstimates, parameter_uncertainty
    from estim.uncertainty import ParameterEstimates as ParameterEstimates_

    assert ParameterEstimates is ParameterEstimates_ and callable(parameter_uncertainty)
    from estim import records

    assert records.__name__ == "estim.records" and callable(records.merge)
    # the submodule estim.compare does not hide the function estim.compare
    importlib.import_module("estim.compare")
    assert callable(estim.compare) and estim.compare.__module__ == "estim.compare"
    with pytest.raises(AttributeError, match="no attribute 'EFK'"):
        _ = estim.EFK
    with pytest.raises(ImportError):
        from estim import EFK  # noqa: F401
    code = ("import estim, estim.estimators as e; "
            "assert all(hasattr(estim, n) for n in estim.__all__); "
            "assert all(hasattr(e, n) for n in e.__all__)")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_estimators_and_logs_pickle():
    """What joblib workers send back and forth: estimators (with cloudpickle, as the
    models hold the user's functions) and logs (plain pickle)."""
    try:
        from joblib.externals import cloudpickle  # joblib < 1.5 vendors it
    except ImportError:
        cloudpickle = pytest.importorskip("cloudpickle")
    sc = estim.scenarios.van_der_pol().replace(n_steps=20)
    for cls in (estim.EKF, estim.UKF, estim.MHE):
        kwargs = {"horizon": 5} if cls is estim.MHE else {}
        est = cls(sc.model, **sc.tuning, **kwargs)
        log = estim.simulate(sc, est, seed=1)
        est2 = cloudpickle.loads(cloudpickle.dumps(est))
        log2 = pickle.loads(pickle.dumps(log))
        assert type(est2) is cls and type(log2) is estim.Log
        np.testing.assert_array_equal(log2.x_hat, log.x_hat)
        y = log.y[-1]
        np.testing.assert_array_equal(est2.step(y), est.step(y))
    runs = [estim.compare(sc, {"ekf": estim.EKF, "ukf": estim.UKF}, seeds=range(2),
                          n_jobs=n_jobs) for n_jobs in (1, 2)]
    assert [r.rmse_mean for r in runs[0].rows] == [r.rmse_mean for r in runs[1].rows]


def test_dask_backend_names_its_extra(monkeypatch):
    """Without dask, backend="dask" says which extra to install."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name.startswith("dask") else real(name, *a))
    sc = estim.scenarios.van_der_pol().replace(n_steps=5)
    with pytest.raises(ImportError, match=r'pip install "estim\[dask\]"'):
        estim.compare(sc, {"ekf": estim.EKF}, seeds=range(2), n_jobs=2, backend="dask")


def test_package_data():
    package = Path(estim.__file__).parent
    assert (package / "py.typed").is_file()
    license_text = (ROOT / "LICENSE").read_text()
    assert "BSD 3-Clause License" in license_text and "The estim developers" in license_text


def _mypy_environment(tmp_path: Path) -> tuple[dict, list[str]]:
    """Environment and extra options so that mypy reads estim as a user's mypy would.

    An installed estim is found in site-packages, where mypy reports no error of
    the library's own. A source tree (an editable install, whose import hook mypy
    does not follow) goes on MYPYPATH, with the library's own errors left out
    the same way."""
    env = {k: v for k, v in os.environ.items() if k != "MYPYPATH"}
    package_parent = Path(estim.__file__).resolve().parents[1]
    options = ["--cache-dir", str(tmp_path / "cache"), "--no-incremental"]
    if package_parent.name not in ("site-packages", "dist-packages"):
        env["MYPYPATH"] = str(package_parent)
        config = tmp_path / "mypy.ini"
        config.write_text("[mypy]\n\n[mypy-estim.*]\nignore_errors = True\n\n"
                          "[mypy-filterpy.*,scipy.*,sympy.*]\nignore_missing_imports = True\n")
        options += ["--config-file", str(config)]
    return env, options


def test_user_script_type_checks(tmp_path):
    """mypy on a user's script finds estim's annotations (py.typed) and no error."""
    pytest.importorskip("mypy")
    user = ROOT / "tests" / "data" / "typed_user.py"
    reveal = tmp_path / "reveal.py"
    reveal.write_text(
        "import numpy as np\nimport estim\n"
        "sc = estim.scenarios.van_der_pol()\n"
        "ekf = estim.EKF(sc.model, **sc.tuning)\n"
        "log = estim.simulate(sc, ekf, seed=0)\n"
        "reveal_type(log)\nreveal_type(log.x_hat)\nreveal_type(estim.rmse(log))\n"
        "reveal_type(ekf.step(np.zeros(2)))\nreveal_type(estim.FullInformation)\n"
        "reveal_type(estim.compare(sc, {'ekf': estim.EKF}, seeds=range(2)))\n"
        "estim.simulate(sc, ekf, seed='zero')  # type: ignore[arg-type]\n")
    env, options = _mypy_environment(tmp_path)
    proc = subprocess.run([sys.executable, "-m", "mypy", *options, "--warn-unused-ignores",
                           "--strict-optional", str(user), str(reveal)],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Success: no issues found in 2 source files" in proc.stdout
    revealed = [line.split("Revealed type is ", 1)[1] for line in proc.stdout.splitlines()
                if "Revealed type is" in line]
    assert revealed[0] == '"estim.log.Log"'
    assert revealed[1].startswith('"numpy.ndarray')
    assert revealed[2] == '"estim.metrics.RMSE"'
    assert revealed[3].startswith('"numpy.ndarray')
    assert "estim.estimators.window.fie.FullInformation" in revealed[4]
    assert revealed[5] == '"estim.compare.Comparison"'


def test_user_script_runs(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "tests" / "data" / "typed_user.py")],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
