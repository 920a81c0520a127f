"""The pytest plugin of estim: seeded comparisons as fixtures, baselines, a summary and a
report (registered through the ``pytest11`` entry point: active wherever estim is
installed; ``-p no:estim`` turns it off).

Options
-------
``--estim-seeds N``
    Run every ``estim_compare`` with seeds ``0..N-1`` instead of the test's own (a
    nightly run with more seeds, a quick one with fewer).
``--estim-jobs N``
    Parallel jobs of each comparison (``estim.compare(n_jobs=)``).
``--estim-baseline DIR``
    Each named comparison's per-seed metrics are stored as ``DIR/<name>.json`` the first
    time (or with ``--estim-baseline-update``) and checked against later with
    :func:`estim.testing.assert_no_regression`; the summary says what was stored and what
    was checked (file, estimators, seeds, verdict).
``--estim-report PATH``
    Write, test by test, the tables of every comparison of the session, a box plot of
    each one's per-seed RMSE, and every assertion of :mod:`estim.testing` with its
    statistics and whether it passed, to ``PATH`` (``.md`` or ``.html``; the figures
    beside it).

Fixtures
--------
``estim_compare``
    ``estim_compare(scenario, estimators, seeds=range(20), name=None, **kw)`` runs
    :func:`estim.compare` with the options above and records the result for the
    terminal summary and the report; with a ``name`` and ``--estim-baseline`` it also
    checks the baseline.
``estim_scenario``
    The scenarios of :mod:`estim.scenarios`, one test per name (narrow it with
    ``@pytest.mark.parametrize("estim_scenario", ["van_der_pol"], indirect=True)``).

The comparisons and the assertions' outcomes (:func:`estim.testing.recording`) travel
with each test's report (``user_properties``), so the summary and the report are the same
under ``pytest -n`` (pytest-xdist) as in a serial run.
"""

from __future__ import annotations

import html
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estim import scenarios as _scenarios
from estim import testing
from estim.compare import Comparison, compare
from estim.testing import assert_no_regression, save_baseline
from estim.verdicts import seed_range_text

#: The ``user_properties`` key of a recorded comparison.
KEY = "estim_comparison"
#: The ``user_properties`` key of a test's assertions (and baselines stored).
ASSERTIONS = "estim_assertions"
#: The assertions of one test the terminal summary shows (the report has all).
SHOWN = 5


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("estim", "estim: comparisons of estimators")
    group.addoption("--estim-seeds", type=int, default=None, metavar="N",
                    help="run every estim_compare with seeds 0..N-1 (default: the test's)")
    group.addoption("--estim-jobs", type=int, default=1, metavar="N",
                    help="parallel jobs of each comparison (default 1)")
    group.addoption("--estim-baseline", default=None, metavar="DIR",
                    help="store named comparisons' per-seed metrics in DIR, and check "
                         "later runs against them")
    group.addoption("--estim-baseline-update", action="store_true",
                    help="rewrite the baselines instead of checking them")
    group.addoption("--estim-report", default=None, metavar="PATH",
                    help="write the session's comparison tables and plots (.md or .html)")


def pytest_configure(config: pytest.Config) -> None:
    config.pluginmanager.register(_Collector(config), "estim-collector")
    seeds = config.getoption("--estim-seeds")
    if seeds is not None and seeds < 2:
        raise pytest.UsageError(f"--estim-seeds must be at least 2, got {seeds}")
    baseline = config.getoption("--estim-baseline")
    if baseline is not None and Path(baseline).exists() and not Path(baseline).is_dir():
        raise pytest.UsageError(f"--estim-baseline must be a folder (the baselines are "
                                f"<folder>/<name>.json), got the file {baseline!r}")
    report = config.getoption("--estim-report")
    if report is not None and Path(report).suffix not in (".md", ".html"):
        raise pytest.UsageError(f"--estim-report must end in .md or .html, got {report!r}")


class _Runner:
    """What the ``estim_compare`` fixture returns: :func:`estim.compare` with the
    session's options; it keeps what it ran for the test's report."""

    def __init__(self, config: pytest.Config, node: pytest.Item):
        self.config, self.node = config, node

    def __call__(self, scenario, estimators: Mapping[str, Any],
                 seeds: Iterable[int] = range(20), *, name: str | None = None,
                 **kwargs: Any) -> Comparison:
        override = self.config.getoption("--estim-seeds")
        seed_list = list(range(override)) if override is not None else list(seeds)
        kwargs.setdefault("n_jobs", self.config.getoption("--estim-jobs"))
        result = compare(scenario, estimators, seed_list, **kwargs)
        label = name or f"{self.node.name}: {result.scenario}"
        self.node.user_properties.append((KEY, {
            "name": label, "test": self.node.nodeid, "table": result.table(),
            "seeds": [int(s) for s in result.seeds],
            "rmse": {k: [float(v) for v in a] for k, a in result.rmse.items()}}))
        folder = self.config.getoption("--estim-baseline")
        if name is not None and folder is not None:
            path = Path(folder) / f"{name}.json"
            if self.config.getoption("--estim-baseline-update") or not path.exists():
                save_baseline(result, path)
                testing.record("baseline", True, f"stored {str(path)!r} (estimators "
                               f"{', '.join(result.rmse)}; seeds "
                               f"{seed_range_text(result.seeds)}): later runs are checked "
                               f"against it")
            else:
                assert_no_regression(result, path)
        return result


@pytest.fixture
def estim_compare(request: pytest.FixtureRequest) -> _Runner:
    """``estim.compare`` with the ``--estim-*`` options, recorded for the summary and the
    report (see :mod:`estim.pytest_plugin`)."""
    return _Runner(request.config, request.node)


@pytest.fixture(params=sorted(_scenarios.SCENARIOS))
def estim_scenario(request: pytest.FixtureRequest):
    """Each scenario of :mod:`estim.scenarios` in turn (by name)."""
    return _scenarios.get(request.param)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Record the outcome of every :mod:`estim.testing` assertion the test makes."""
    records: list[dict] = []
    previous = testing.recording(records)
    try:
        yield
    finally:
        testing.recording(previous)
        if records:
            item.user_properties.append((ASSERTIONS, {"test": item.nodeid,
                                                      "records": records}))


class _Collector:
    """Gathers the comparisons and the assertions from every test's report (also from
    pytest-xdist's workers) and writes the summary and the report at the end of the
    session."""

    def __init__(self, config: pytest.Config):
        self.config = config
        self.results: list[dict] = []
        self.assertions: dict[str, list[dict]] = {}

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if report.when == "call":
            for key, value in report.user_properties:
                if key == KEY and isinstance(value, dict):
                    self.results.append(value)
                elif key == ASSERTIONS and isinstance(value, dict):
                    self.assertions.setdefault(value["test"], []).extend(value["records"])

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if not self.results and not self.assertions:
            return
        terminalreporter.section("estim comparisons")
        for test in _tests(self.results, self.assertions):
            for r in (r for r in self.results if r["test"] == test):
                terminalreporter.write_line(f"{r['name']} ({len(r['seeds'])} seeds; {test})")
                for line in r["table"].splitlines():
                    terminalreporter.write_line("  " + line)
            done = self.assertions.get(test, [])
            for a in done[:SHOWN]:
                terminalreporter.write_line(_outcome(a, test))
            if len(done) > SHOWN:
                failed = sum(not a["passed"] for a in done[SHOWN:])
                terminalreporter.write_line(f"... and {len(done) - SHOWN} more assertions of "
                                            f"{test} ({failed} of them failed; all are in "
                                            f"--estim-report)")
        report = self.config.getoption("--estim-report")
        if report is not None:
            written = write_report(self.results, Path(report), self.assertions)
            terminalreporter.write_line(f"estim report: {', '.join(map(str, written))}")


def _tests(results: list[dict], assertions: Mapping[str, list[dict]]) -> list[str]:
    """The tests that compared or asserted, in order of their node ids."""
    return sorted({r["test"] for r in results} | set(assertions))


def _outcome(a: dict, test: str) -> str:
    """``"[passed] assert_better (test_x.py::test_y): 'mhe' is shown better ..."``."""
    head = "[stored]" if a["assertion"] == "baseline" else \
        ("[passed]" if a["passed"] else "[failed]")
    return f"{head} {a['assertion']} ({test}): {a['text']}"


def write_report(results: list[dict], path: Path,
                 assertions: Mapping[str, list[dict]] | None = None) -> list[Path]:
    """Write, test by test, the tables and a box plot of each comparison's per-seed RMSE
    (if matplotlib is there) and the outcome of every assertion (``assertions``: by test,
    as recorded) to ``path`` (.md or .html); the files written."""
    assertions = assertions or {}
    path.parent.mkdir(parents=True, exist_ok=True)
    figures: list[Path | None] = []
    plt: Any = None
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        pass
    tests = _tests(results, assertions)
    results = sorted(results, key=lambda r: tests.index(r["test"]))
    for i, r in enumerate(results):
        if plt is None:
            figures.append(None)
            continue
        drawing, ax = plt.subplots(figsize=(6, 3))
        names = list(r["rmse"])
        ax.boxplot([np.asarray(r["rmse"][n], float)[np.isfinite(r["rmse"][n])]
                    for n in names])
        ax.set_xticks(range(1, len(names) + 1), names)
        ax.set_ylabel("RMSE per seed")
        ax.set_title(r["name"])
        drawing.tight_layout()
        figure = path.with_name(f"{path.stem}_{i + 1}.png")
        drawing.savefig(figure, dpi=90)
        plt.close(drawing)
        figures.append(figure)
    drawn = dict(zip(map(id, results), figures, strict=True))
    passed = sum(a["passed"] for t in tests for a in assertions.get(t, [])
                 if a["assertion"] != "baseline")
    total = sum(a["assertion"] != "baseline" for t in tests for a in assertions.get(t, []))
    tally = f"{passed} of {total} assertions passed"
    if path.suffix == ".html":
        parts = ["<html><head><meta charset='utf-8'><title>estim comparisons</title></head>"
                 f"<body><h1>estim comparisons</h1><p>{tally}</p>"]
        for test in tests:
            parts.append(f"<h2>{html.escape(test)}</h2>")
            for r in (r for r in results if r["test"] == test):
                parts.append(f"<h3>{html.escape(r['name'])}</h3><p>{len(r['seeds'])} seeds</p>"
                             f"<pre>{html.escape(r['table'])}</pre>")
                fig = drawn[id(r)]
                if fig is not None:
                    parts.append(f"<img src='{fig.name}' alt='RMSE per seed'>")
            items = "".join(f"<li><b>{html.escape(_outcome(a, test).split(' (')[0])}</b>: "
                            f"{html.escape(a['text'])}</li>" for a in assertions.get(test, []))
            if items:
                parts.append(f"<ul>{items}</ul>")
        parts.append("</body></html>")
        path.write_text("\n".join(parts))
    else:
        parts = ["# estim comparisons", "", tally, ""]
        for test in tests:
            parts += [f"## {test}", ""]
            for r in (r for r in results if r["test"] == test):
                parts += [f"### {r['name']}", "", f"{len(r['seeds'])} seeds", "",
                          "```", r["table"], "```", ""]
                fig = drawn[id(r)]
                if fig is not None:
                    parts += [f"![RMSE per seed]({fig.name})", ""]
            parts += [f"- **{_outcome(a, test).split(' (')[0]}**: {a['text']}"
                      for a in assertions.get(test, [])]
            parts.append("")
        path.write_text("\n".join(parts))
    return [path, *[f for f in figures if f is not None]]
