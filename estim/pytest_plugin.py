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
    :func:`estim.testing.assert_no_regression`.
``--estim-report PATH``
    Write the tables of every comparison of the session and a box plot of each one's
    per-seed RMSE to ``PATH`` (``.md`` or ``.html``; the figures beside it).

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

The results travel with each test's report (``user_properties``), so the summary and
the report are the same under ``pytest -n`` (pytest-xdist) as in a serial run.
"""

from __future__ import annotations

import html
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from estim import scenarios as _scenarios
from estim.compare import Comparison, compare
from estim.testing import assert_no_regression, save_baseline

#: The ``user_properties`` key of a recorded comparison.
KEY = "estim_comparison"


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


class _Collector:
    """Gathers the comparisons from every test's report (also from pytest-xdist's
    workers) and writes the summary and the report at the end of the session."""

    def __init__(self, config: pytest.Config):
        self.config = config
        self.results: list[dict] = []

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if report.when == "call":
            self.results += [value for key, value in report.user_properties
                             if key == KEY and isinstance(value, dict)]

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if not self.results:
            return
        terminalreporter.section("estim comparisons")
        for r in sorted(self.results, key=lambda r: r["test"]):
            terminalreporter.write_line(f"{r['name']} ({len(r['seeds'])} seeds; {r['test']})")
            for line in r["table"].splitlines():
                terminalreporter.write_line("  " + line)
        report = self.config.getoption("--estim-report")
        if report is not None:
            written = write_report(self.results, Path(report))
            terminalreporter.write_line(f"estim report: {', '.join(map(str, written))}")


def write_report(results: list[dict], path: Path) -> list[Path]:
    """Write the tables and a box plot of each comparison's per-seed RMSE (if matplotlib
    is there) to ``path`` (.md or .html); the files written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    figures: list[Path | None] = []
    plt: Any = None
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        pass
    results = sorted(results, key=lambda r: r["test"])
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
    if path.suffix == ".html":
        parts = ["<html><head><meta charset='utf-8'><title>estim comparisons</title></head>"
                 "<body><h1>estim comparisons</h1>"]
        for r, fig in zip(results, figures, strict=True):
            parts.append(f"<h2>{html.escape(r['name'])}</h2><p>{html.escape(r['test'])}, "
                         f"{len(r['seeds'])} seeds</p><pre>{html.escape(r['table'])}</pre>")
            if fig is not None:
                parts.append(f"<img src='{fig.name}' alt='RMSE per seed'>")
        parts.append("</body></html>")
        path.write_text("\n".join(parts))
    else:
        parts = ["# estim comparisons", ""]
        for r, fig in zip(results, figures, strict=True):
            parts += [f"## {r['name']}", "", f"{r['test']}, {len(r['seeds'])} seeds", "",
                      "```", r["table"], "```", ""]
            if fig is not None:
                parts += [f"![RMSE per seed]({fig.name})", ""]
        path.write_text("\n".join(parts))
    return [path, *[f for f in figures if f is not None]]
