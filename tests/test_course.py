"""The course exercise (examples/course): the template stops at each gap, the solution works."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import estim

COURSE = Path(__file__).resolve().parents[1] / "examples" / "course"


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"course_{name}", COURSE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def solution():
    return load("solution")


def test_template_stops_at_each_gap_in_order(tmp_path, monkeypatch, solution):
    template = load("template")
    argv = ["--out", str(tmp_path / "template.png")]
    # filling the gaps one by one with the solution's code moves the error to the next one
    fills = [(template, "plot", solution.plot),
             (template.EKF, "__call__", solution.EKF.__call__),
             (template.EKF, "clip", solution.EKF.clip),
             (template, "mhe", lambda n, solver: estim.EKF(template.MODEL, **template.SC.tuning)),
             (template, "compare", solution.compare)]
    for exercise, (obj, name, code) in zip(["exercise 1", "exercise 3", "exercise 4",
                                            "exercise 6", "final exercise"], fills, strict=True):
        with pytest.raises(NotImplementedError, match=exercise):
            template.main(argv)
        monkeypatch.setattr(obj, name, code)
    res = template.main(argv)
    assert set(res["rmse"]) == {"EKF", "clipped EKF", "MHE N=10", "MHE N=25"}
    text = (COURSE / "template.py").read_text()
    for n in (1, 2, 3, 4, 5, 6):
        assert f"TODO (exercise {n})" in text
    assert "TODO (final)" in text


def test_solution_reproduces_the_course(tmp_path, capsys, solution):
    out = tmp_path / "course.png"
    res = solution.main(["--out", str(out), "--solver", "fatrop"])
    assert out.stat().st_size > 20_000
    rmse, low = res["rmse"], res["min_estimate"]
    assert set(rmse) == {"EKF", "clipped EKF", "MHE N=10", "MHE N=25"}
    # the EKF from the bad guess settles on a wrong, partly negative state (0.42 on seed 0)
    assert rmse["EKF"] > 0.1 and low["EKF"] < 0
    # clipping keeps it non-negative and, after its large start-up transient, near the truth
    assert low["clipped EKF"] >= 0
    assert res["rmse_after_burn_in"]["clipped EKF"] < 0.2 * res["rmse_after_burn_in"]["EKF"]
    # exercise 6: the zero-prior MHE with 0 <= x <= 10 is far better (0.13 and 0.046), and
    # the longer window better still
    assert rmse["MHE N=10"] < 0.5 * rmse["EKF"] and rmse["MHE N=25"] < 0.5 * rmse["EKF"]
    assert rmse["MHE N=25"] < rmse["MHE N=10"]
    assert min(low["MHE N=10"], low["MHE N=25"]) >= -1e-8
    printed = capsys.readouterr().out
    assert "MHE N=25" in printed and "clipped EKF" in printed


def test_course_tuning_is_the_scenarios(solution):
    tuning = solution.SC.tuning
    assert np.allclose(tuning["x0"], solution.GUESS)
    assert (tuning["Q"], tuning["R"], tuning["P0"]) == pytest.approx(
        (solution.SIG_W**2, solution.SIG_V**2, solution.SIG_P**2))


@pytest.mark.parametrize("clipping", [False, True])
def test_solution_ekf_equals_estim_ekf(solution, clipping):
    sc = solution.SC
    ekf = solution.EKF(sc.model, x0=sc.tuning["x0"], P0=sc.tuning["P0"] * np.eye(3),
                       Q=sc.tuning["Q"] * np.eye(3), R=sc.tuning["R"] * np.eye(1),
                       clipping=clipping)
    ours = solution.run(ekf, seed=0)
    ref = estim.simulate(sc, estim.EKF(sc.model, **sc.tuning, clip=clipping), seed=0)
    assert np.array_equal(ours.y, ref.y) and np.array_equal(ours.x, ref.x)
    # the first step is a pure update from the prior (1, 0, 4), then update and predict
    np.testing.assert_allclose(ours.x_hat, ref.x_hat, rtol=0, atol=1e-8)
    if clipping:  # the projection is active: without it the estimate goes negative
        assert ours.x_hat.min() == 0.0 and ours.x_hat.max() > 100
    else:
        assert ours.x_hat.min() < -1
