"""estim's pytest plugin (``estim.pytest_plugin``, entry point ``pytest11``): the fixtures,
the options, baselines, the summary and the report, under pytest-xdist too; run in
pytest's own ``pytester``."""

from __future__ import annotations

import json

import matplotlib
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot  # noqa: E402,F401  (imported before pytester's in-process runs)
import scipy.stats  # noqa: E402,F401  (likewise: estim.verdicts imports it when first used)

pytest_plugins = ["pytester"]

TESTS = '''
import estim
from estim import testing

SC = estim.scenarios.get("van_der_pol", n_steps=40)


def test_filters(estim_compare):
    res = estim_compare(SC, {"ekf": estim.EKF, "ukf": estim.UKF,
                             "bad": lambda m, t: estim.EKF(m, **{**t, "R": FACTOR * t["R"]})},
                        seeds=range(6), name="vdp")
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
                                 "*ekf *", "[[]passed] assert_better (test_user.py::test_filters): "
                                 "'ekf' is shown better than 'bad' in rmse at confidence 0.95 "
                                 "(6 paired seeds): Wilcoxon signed-rank p = 0.0156, 6 of 6 *",
                                 "test_other: van_der_pol (6 seeds;*",
                                 "estim report: out/report.md, out/report_1.png, *"])
    text = (pytester.path / "out" / "report.md").read_text()
    assert "### vdp" in text and "![RMSE per seed](report_1.png)" in text
    assert "1 of 1 assertions passed" in text
    assert "- **[passed] assert_better**: 'ekf' is shown better than 'bad'" in text
    assert (pytester.path / "out" / "report_2.png").stat().st_size > 5000
    html = pytester.runpytest("--estim-report", "r.html", "-q", "-p", "no:cacheprovider")
    html.assert_outcomes(passed=2)
    page = (pytester.path / "r.html").read_text()
    assert "<pre>" in page
    assert "<li><b>[passed] assert_better</b>: &#x27;ekf&#x27; is shown better" in page
    (pytester.path / "afile").write_text("")
    bad = pytester.runpytest("--estim-baseline", "afile")
    assert bad.ret == pytest.ExitCode.USAGE_ERROR
    bad.stderr.fnmatch_lines(["*--estim-baseline must be a folder*got the file 'afile'*"])
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
    first = pytester.runpytest(*args)
    first.assert_outcomes(passed=2)
    first.stdout.fnmatch_lines(["[[]stored] baseline (test_user.py::test_filters): stored "
                                "'base/vdp.json' (estimators ekf, ukf, bad; seeds 0..5 (6)): "
                                "later runs are checked against it"])
    stored = json.loads((pytester.path / "base" / "vdp.json").read_text())
    assert stored["scenario"] == "van_der_pol" and stored["seeds"] == list(range(6))
    assert set(stored["metrics"]) == {"ekf", "ukf", "bad"}
    same = pytester.runpytest(*args)
    same.assert_outcomes(passed=2)
    same.stdout.fnmatch_lines(["[[]passed] assert_no_regression (test_user.py::test_filters): no "
                               "regression against 'base/vdp.json' (estimators ekf, ukf, bad; "
                               "seeds 0..5 (6)) at confidence 0.95; 'ekf': unchanged on all 6 "
                               "seeds; 'ukf': unchanged on all 6 seeds; 'bad': unchanged*"])
    _write(pytester, factor=100.0)  # 'bad' got worse
    worse = pytester.runpytest(*args)
    worse.assert_outcomes(passed=1, failed=1)
    worse.stdout.fnmatch_lines(["*regression against *vdp.json* 'bad': rmse median * -> *, "
                                "mean * -> *; 6 of 6 seeds worse, 0 better; Wilcoxon "
                                "signed-rank p = 0.0156, Hodges-Lehmann *; the largest rises: "
                                "seed *",
                                "[[]failed] assert_no_regression (test_user.py::test_filters): "
                                "regression against*"])
    pytester.runpytest(*args, "--estim-baseline-update").assert_outcomes(passed=2)
    pytester.runpytest(*args).assert_outcomes(passed=2)
    seeds = pytester.runpytest(*args, "--estim-seeds", "5")
    seeds.assert_outcomes(passed=1, failed=1)
    seeds.stdout.fnmatch_lines(["*baseline: *vdp.json* has seeds 0..5 (6), the comparison "
                                "0..4 (5)*"])


def test_xdist_gives_the_serial_results(pytester):
    pytest.importorskip("xdist")
    _write(pytester)
    serial = pytester.runpytest("--estim-baseline", "serial", "-q", "-p", "no:cacheprovider")
    serial.assert_outcomes(passed=2)
    parallel = pytester.runpytest_subprocess("-n", "2", "--estim-baseline", "parallel", "-q",
                                             "-p", "no:cacheprovider")
    parallel.assert_outcomes(passed=2)
    parallel.stdout.fnmatch_lines(["*estim comparisons*", "vdp (6 seeds;*",
                                   "[[]passed] assert_better (test_user.py::test_filters)*"])
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
    """examples/test_estimators.py (the assertions, the fixtures, a filterpy filter)
    passes as users run it."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for path, n in ((root / "examples" / "test_estimators.py", 6),):
        result = pytester.runpytest(str(path), "-q", "-p", "no:cacheprovider")
        result.assert_outcomes(passed=n)
