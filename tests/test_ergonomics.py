"""Notebook ergonomics: pandas records read by name, plain Python values in reports,
numpy functions on symbols without CasADi's warning, figures drawn once in Jupyter."""

from __future__ import annotations

import importlib.util
import subprocess
import sys

import casadi as ca
import numpy as np
import pytest

import estim

pd = pytest.importorskip("pandas")


def _model():
    return estim.Model(states=["a", "b"], outputs=["ya", "yb"], inputs=["u1"],
                       ode=lambda x, u, p: ca.vertcat(x[1], -x[0] + u[0]),
                       output=lambda x, u, p: ca.vertcat(x[0], 2 * x[1]), dt=0.1)


@pytest.fixture(scope="module")
def record():
    m = _model()
    u = np.sin(0.1 * np.arange(80))[:, None]
    log = estim.simulate(m, estim.EKF(m, Q=1e-4, R=0.01, x0=[0, 0], P0=1.0), x0=[1, 0],
                         n_steps=80, Q=1e-4, R=0.01, inputs=u, seed=0)
    return m, log


def test_dataframes_are_read_by_the_models_names(record):
    m, log = record
    ekf = estim.EKF(m, Q=1e-4, R=0.01, x0=[0, 0], P0=1.0)
    ref = estim.replay(ekf, log.y, log.u, x=log.x)
    # columns in another order, with an extra time column: read by name
    Y = pd.DataFrame({"t": log.t, "yb": log.y[:, 1], "ya": log.y[:, 0]})
    U = pd.DataFrame({"u1": log.u[:, 0]})
    X = pd.DataFrame(log.x[:, ::-1], columns=["b", "a"])
    got = estim.replay(ekf, Y, U, x=X)
    np.testing.assert_array_equal(got.x_hat, ref.x_hat)
    np.testing.assert_array_equal(got.x, ref.x)
    fie = estim.FullInformation(m, Q=1e-4, R=0.01)
    np.testing.assert_array_equal(fie.fit(Y, U.iloc[:-1]).x, fie.fit(log.y, log.u[:-1]).x)
    sim = estim.simulate(m, estim.EKF(m, Q=1e-4, R=0.01, x0=[0, 0], P0=1.0), x0=[1, 0],
                         n_steps=80, Q=1e-4, R=0.01, inputs=U, seed=0)
    np.testing.assert_array_equal(sim.x_hat, log.x_hat)
    # unnamed columns (0, 1, ...) are read by position, as arrays are
    np.testing.assert_array_equal(estim.replay(ekf, pd.DataFrame(log.y), log.u).x_hat,
                                  ref.x_hat)


def test_a_missing_column_is_named(record):
    m, log = record
    ekf = estim.EKF(m, Q=1e-4, R=0.01, x0=[0, 0], P0=1.0)
    Y = pd.DataFrame({"ya": log.y[:, 0], "y_b": log.y[:, 1]})
    with pytest.raises(ValueError, match=r"y is a DataFrame without the column\(s\) \['yb'\]"
                                         r".*outputs are \['ya', 'yb'\]"):
        estim.replay(ekf, Y)
    with pytest.raises(ValueError, match=r"Y is a DataFrame without.*\['yb'\]"):
        estim.FullInformation(m, Q=1e-4, R=0.01).fit(Y)
    with pytest.raises(ValueError, match=r"inputs is a DataFrame without.*\['u1'\]"):
        estim.simulate(m, ekf, x0=[1, 0], n_steps=80, Q=1e-4, R=0.01,
                       inputs=pd.DataFrame({"u": log.u[:, 0]}))


def test_reports_hold_plain_python_values():
    sc = estim.scenarios.van_der_pol().replace(n_steps=20)
    for est in (estim.EKF(sc.model, **sc.tuning), estim.UKF(sc.model, **sc.tuning),
                estim.MHE(sc.model, horizon=5, **sc.tuning),
                estim.ShootingObserver(sc.model, window=5, every=1, **sc.tuning)):
        log = estim.simulate(sc, est, seed=0)
        info = est.info
        assert type(info.success) is bool and type(info.status) is str
        assert type(info.iterations) is int and type(info.solve_time) is float
        assert "np." not in repr(info).split("P=")[0]
        assert type(log.status[0]) is str
        assert (log.status == "ok").all()
    html = log._repr_html_()
    assert "RMSE RMSE" not in html and "RMSE(" in html


def test_numpy_functions_on_symbols_do_not_warn():
    """np.sin on a CasADi symbol inside a model is CasADi's sin, with no FutureWarning (a
    fresh process: CasADi warns once per process)."""
    code = ("import numpy as np, estim\n"
            "m = estim.Model(states=['th', 'om'], outputs=['y'], dt=0.05,\n"
            "                ode=lambda x, u, p: [x[1], -9.81 * np.sin(x[0])],\n"
            "                output=lambda x, u, p: np.cos(x[0]))\n"
            "print(m.f([0.5, 0.0])[1], m.h([0.5, 0.0])[0])\n")
    res = subprocess.run([sys.executable, "-W", "error::FutureWarning", "-c", code],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "FutureWarning" not in res.stderr and "numpy function" not in res.stderr
    f1, h0 = map(float, res.stdout.split())
    assert h0 == pytest.approx(np.cos(0.5), rel=1e-14)
    assert f1 < 0


def test_comparison_plot_kinds(record):
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sc = estim.scenarios.van_der_pol().replace(n_steps=30)
    res = estim.compare(sc, {"ekf": estim.EKF, "ukf": estim.UKF}, seeds=range(2),
                        keep_logs=True)
    for kind, n_axes in (("overview", 3), ("errors", 2), ("times", 1)):
        fig = res.plot(kind=kind, seed_index=1)
        assert len(fig.axes) == n_axes
        plt.close(fig)
    with pytest.raises(ValueError, match="kind must be one of"):
        res.plot(kind="nees")
    with pytest.raises(ValueError, match="seed_index 2 is out of range"):
        res.plot(seed_index=2)
    bare = estim.compare(sc, {"ekf": estim.EKF}, seeds=range(1))
    with pytest.raises(ValueError, match="keep_logs=True"):
        bare.plot()


@pytest.mark.skipif(any(importlib.util.find_spec(m) is None
                        for m in ("nbclient", "nbformat", "ipykernel", "matplotlib")),
                    reason="needs nbclient, nbformat, ipykernel and matplotlib")
def test_figures_are_drawn_once_in_jupyter(tmp_path, monkeypatch):
    import nbclient
    import nbformat

    # the kernel's own (inline) backend: a headless MPLBACKEND=Agg in the environment
    # would be inherited by the kernel and draw nothing
    monkeypatch.delenv("MPLBACKEND", raising=False)

    cells = ["import estim\nsc = estim.scenarios.van_der_pol().replace(n_steps=30)\n"
             "log = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning), seed=0)",
             "log.plot()",                                   # the cell's value
             "fig = log.plot()",                             # not the value
             "import matplotlib.pyplot as plt\nfig = log.plot(); plt.close(fig)\nfig",
             "r = estim.compare(sc, {'ekf': estim.EKF}, seeds=range(2), keep_logs=True)\n"
             "r.plot(kind='errors')",
             "r.plot(); r.plot(kind='times')"]                # two figures, one each
    nb = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(c) for c in cells])
    nbclient.NotebookClient(nb, kernel_name="python3", timeout=300,
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    images = [sum("image/png" in o.get("data", {}) for o in c.outputs) for c in nb.cells]
    assert images == [0, 1, 1, 1, 1, 2]


def test_a_step_without_measurements_has_no_nis():
    """NIS is NaN when no output was measured (not 0, which would read as perfect
    agreement and lower averages of log.nis)."""
    sc = estim.scenarios.van_der_pol()
    for est in (estim.EKF(sc.model, **sc.tuning), estim.UKF(sc.model, **sc.tuning)):
        est.step([np.nan, np.nan])
        assert np.isnan(est.info.nis) and est.info.status == "ok"
        est.step([1.0, np.nan])
        assert np.isfinite(est.info.nis) and est.info.nis > 0
