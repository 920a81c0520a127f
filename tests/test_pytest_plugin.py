"""estim's pytest plugin (``estim.pytest_plugin``, entry point ``pytest11``): the fixtures,
the options, baselines, the summary and the report, under pytest-xdist too; run in
pytest's own ``pytester``."""

from __future__ import annotations

import json

import matplotlib
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot  # noqa: E402,F401  (imported before pytester's in-process runs)

pytest_plugins = ["pytester"]

TESTS = '''
import estim
from estim import testing

SC = estim.scenarios.get("van_der_pol", n_steps=40)


def test_filters(estim_compare):
    res = estim_compare(SC, {"ekf": estim.EKF, "ukf": estim.UKF,
                             "bad": lambda m, t: estim.EKF(m, **{**t, "R": FACTOR * t["R"]})},
                        seeds=range(4), name="vdp")
    testing.assert_better(res, "ekf", "bad")


def test_other(estim_compare):
    estim_compare(SC, {"ekf": estim.EKF}, seeds=range(3))
'''


def _write(pytester, factor: float = 30.0):
    pytester.makepyfile(test_user=TESTS.replace("FACTOR", repr(factor)))


def test_fixtures_options_summary_and_report(pytester):
    _write(pytester)
    result = pytester.runpytest("--estim-seeds", "6", "--estim-report", "out/report.md", "-q",
                                "-p", "no:cacheprovider")
    result.assert_outcomes(passed=2)
    result.stdout.fnmatch_lines(["*estim comparisons*", "vdp (6 seeds; test_user.py::test_filters)",
                                 "*ekf *", "test_other: van_der_pol (6 seeds;*",
                                 "estim report: out/report.md, out/report_1.png, *"])
    text = (pytester.path / "out" / "report.md").read_text()
    assert "## vdp" in text and "![RMSE per seed](report_1.png)" in text
    assert (pytester.path / "out" / "report_2.png").stat().st_size > 5000
    html = pytester.runpytest("--estim-report", "r.html", "-q", "-p", "no:cacheprovider")
    html.assert_outcomes(passed=2)
    assert "<pre>" in (pytester.path / "r.html").read_text()
    bad = pytester.runpytest("--estim-report", "r.txt")
    assert bad.ret == pytest.ExitCode.USAGE_ERROR
    bad.stderr.fnmatch_lines(["*--estim-report must end in .md or .html*"])
    off = pytester.runpytest("-p", "no:estim", "-q")
    off.assert_outcomes(errors=2)
    off.stdout.fnmatch_lines(["*fixture 'estim_compare' not found*"])


def test_baselines_catch_a_regression(pytester):
    """The first run stores the per-seed metrics; the same code passes exactly; a worse
    estimator under the same label fails with the paired test's message; updating
    accepts it."""
    _write(pytester)
    args = ["--estim-baseline", "base", "-q", "-p", "no:cacheprovider"]
    pytester.runpytest(*args).assert_outcomes(passed=2)
    stored = json.loads((pytester.path / "base" / "vdp.json").read_text())
    assert stored["scenario"] == "van_der_pol" and stored["seeds"] == [0, 1, 2, 3]
    assert set(stored["metrics"]) == {"ekf", "ukf", "bad"}
    pytester.runpytest(*args).assert_outcomes(passed=2)
    _write(pytester, factor=100.0)  # 'bad' got worse
    worse = pytester.runpytest(*args)
    worse.assert_outcomes(passed=1, failed=1)
    worse.stdout.fnmatch_lines(["*regression against *vdp.json* 'bad': rmse*"])
    pytester.runpytest(*args, "--estim-baseline-update").assert_outcomes(passed=2)
    pytester.runpytest(*args).assert_outcomes(passed=2)
    seeds = pytester.runpytest(*args, "--estim-seeds", "5")
    seeds.assert_outcomes(passed=1, failed=1)
    seeds.stdout.fnmatch_lines(["*baseline: *vdp.json* has seeds 0..3 (4), the comparison "
                                "0..4 (5)*"])


def test_xdist_gives_the_serial_results(pytester):
    pytest.importorskip("xdist")
    _write(pytester)
    serial = pytester.runpytest("--estim-baseline", "serial", "-q", "-p", "no:cacheprovider")
    serial.assert_outcomes(passed=2)
    parallel = pytester.runpytest_subprocess("-n", "2", "--estim-baseline", "parallel", "-q",
                                             "-p", "no:cacheprovider")
    parallel.assert_outcomes(passed=2)
    parallel.stdout.fnmatch_lines(["*estim comparisons*", "vdp (4 seeds;*"])
    a = json.loads((pytester.path / "serial" / "vdp.json").read_text())
    b = json.loads((pytester.path / "parallel" / "vdp.json").read_text())
    assert a["metrics"] == b["metrics"]


def test_scenario_fixture_runs_every_scenario(pytester):
    pytester.makepyfile(test_each="""
        def test_short(estim_scenario):
            assert estim_scenario.n_steps > 0
    """)
    result = pytester.runpytest("--collect-only", "-q")
    result.stdout.fnmatch_lines(["*test_short?batch_reactor?*", "*test_short?van_der_pol?*"])
    import estim
    assert f"{len(estim.scenarios.SCENARIOS)} tests collected" in result.stdout.str()


def test_the_example_test_modules_pass(pytester):
    """examples/test_estimators.py (the assertions, the fixtures, a filterpy filter) and
    the course's grading file pass as users run them."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for path, n in ((root / "examples" / "test_estimators.py", 6),
                    (root / "examples" / "course" / "test_grade.py", 3)):
        result = pytester.runpytest(str(path), "-q", "-p", "no:cacheprovider")
        result.assert_outcomes(passed=n)
