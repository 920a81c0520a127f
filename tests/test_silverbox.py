"""The Silverbox example (measured data): the shipped subset, and FOH against ZOH on the arrow."""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
CSV = Path(os.environ.get("SILVERBOX_CSV", "/work/shared/data/silverbox/SNLS80mV.csv"))


def _load(name: str, path: Path):
    if name not in sys.modules:  # registered: the benchmark's dataclasses need it
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


example = _load("silverbox_identification_example",
                ROOT / "examples" / "silverbox_identification.py")


def test_subset_layout():
    data = example.load()
    assert data.u_test.shape == data.y_test.shape == (40475,)
    assert data.u_train.shape == data.y_train.shape == (40000,)
    assert data.fs == 1e7 / 2**14
    assert (data.test_start, data.train_start) == (100, 40650)
    with np.load(example.DATA) as raw:
        assert all(raw[k].dtype == np.float32 for k in ("u_test", "y_test", "u_train",
                                                        "y_train"))
    # a few values as SNLS80mV.csv prints them (rows 100, 40574, 40650, 80649 after the
    # header): load() returns the printed decimals, not float32's binary values
    assert [data.u_test[0], data.y_test[0], data.y_test[-1], data.u_train[0],
            data.y_train[-1]] == [0.0059927, 0.00085876, 0.0021432, -0.014504, -0.030045]
    assert example.DATA.stat().st_size < 700_000


@pytest.mark.skipif(not CSV.exists(), reason=f"{CSV} not available (set SILVERBOX_CSV)")
def test_subset_matches_csv(tmp_path):
    # make_subset refuses to write unless float32 reproduces every printed value
    rebuilt = example.make_subset(CSV, tmp_path / "silverbox.npz")
    u, y = example.read_csv(CSV)
    with np.load(example.DATA) as shipped, np.load(rebuilt) as new:
        for name in ("u_test", "y_test", "u_train", "y_train", "fs", "train_start",
                     "test_start"):
            assert np.array_equal(shipped[name], new[name]), name
    # load() gives back the CSV's values exactly (float64, bit for bit)
    data = example.load()
    for v, ref in ((data.u_test, u[100:40575]), (data.y_test, y[100:40575]),
                   (data.u_train, u[40650:80650]), (data.y_train, y[40650:80650])):
        assert v.dtype == np.float64 and np.array_equal(v, ref)


def test_silverbox_identification(tmp_path, capsys):
    """The example as run: estim's full information (the default method) under both holds,
    least_squares on the simulation error as the reference."""
    out = tmp_path / "silverbox.png"
    res = example.main(["--out", str(out), "--samples", "2000"])
    assert out.stat().st_size > 20_000
    assert res["method"] == "estim" and res["reference"] == "least_squares"
    assert res["status"] == {"zoh": "ok", "foh": "ok"}
    rmse = res["rmse_mv"]
    # measured with 500 to 40 000 training samples: FOH 1.00-1.06 mV on the arrow (the
    # dataset's README: 0.96), ZOH 13.35-13.48 mV, a factor 13; the ZOH error is the held
    # input lagging the real one by half a sample at 9 samples per resonance period, which
    # no parameter value removes. A FOH falling back to ZOH's stage inputs would give 13 mV,
    # a fit stuck at its start (the linear ARX guess, a3 = 0) 14 mV.
    assert rmse["foh"] < 1.5
    assert rmse["zoh"] > 10.0
    assert rmse["zoh"] > 8 * rmse["foh"]
    # and on the training record itself (0.96 and 13.8 mV here)
    train = res["train_rmse_mv"]
    assert train["foh"] < 1.5 and train["zoh"] > 8 * train["foh"]
    # full information with Q -> 0 is the simulation-error fit: the parameters agree with
    # least_squares' to 1.6e-5 (FOH) and 1.4e-5 (ZOH) here; the issue's goal is 1e-4
    assert res["agreement"]["foh"] < 1e-4 and res["agreement"]["zoh"] < 1e-4
    # both fits describe the same circuit: resonance sqrt(a0) fs / 2 pi about 68-70 Hz
    for theta in res["theta"].values():
        assert 60 < np.sqrt(theta[2]) * example.FS / (2 * np.pi) < 80
    assert "ZOH / FOH" in capsys.readouterr().out


def test_least_squares_method(tmp_path):
    res = example.main(["--out", str(tmp_path / "s.png"), "--samples", "1000",
                        "--method", "least_squares", "--reference", "none"])
    assert all(s.startswith("`ftol`") for s in res["status"].values())
    assert res["rmse_mv"]["zoh"] > 8 * res["rmse_mv"]["foh"] and res["agreement"] == {}


def test_example_has_docstring_and_main():
    assert example.__doc__ and len(example.__doc__) > 200
    assert callable(example.main)
    assert set(example.METHODS) == {"least_squares", "estim"}


def test_ftol_stops_the_linear_tail_of_a_large_residual_fit():
    """Zero-order hold, 1000 samples: Gauss-Newton converges linearly (rate about 0.06
    in the predicted decrease) to a large-residual optimum. ``ftol = 1e-10`` stops when
    the next step promises less than that fraction of the cost: two iterations fewer
    than the default (the step tolerance), a cost within ``ftol`` of it, and the same
    parameters as ``least_squares`` (which stops on its own ``ftol = 1e-8``)."""
    sb = _load("silverbox_model", ROOT / "examples" / "silverbox_model.py")
    data = example.load()
    u, y = data.u_train[:1000], data.y_train[:1000]
    ls = sb.fit_least_squares(u, y, "zoh", method="trf")
    fits = [sb.fit_estim(u, y, "zoh", "gauss-newton", 1e-8, 1e-14, options, "measured",
                         refit=False) for options in (None, {"ftol": 1e-10})]
    tight, loose = fits
    assert tight.success and loose.success
    assert loose.iterations <= tight.iterations - 2
    assert 0.0 <= loose.cost - tight.cost <= 1e-10 * tight.cost
    np.testing.assert_allclose(loose.theta, tight.theta, rtol=1e-6)
    np.testing.assert_allclose(loose.theta, ls.theta, rtol=1e-4)
