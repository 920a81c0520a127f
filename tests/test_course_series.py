"""The course series (examples/course/exercises): every exercise's student notebook and
autograder are generated from its solution by Otter Assign; the solution is graded to
full marks, the unfilled student version to zero on every graded part, each failed test
with a message; the paired notebooks match their .py sources."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("otter")
jupytext = pytest.importorskip("jupytext")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "course"))
import course  # noqa: E402
import mistakes  # noqa: E402

EXERCISES = course.exercises()
# otter 7.0 (pinned) calls DataFrame.drop(inplace=True), which pandas 3 deprecates
pytestmark = pytest.mark.filterwarnings("ignore:The inplace keyword:Warning")


def test_the_series_has_its_exercises():
    assert len(EXERCISES) >= 9, EXERCISES
    assert EXERCISES[0] == "01_kalman_filter"


@pytest.mark.parametrize("name", EXERCISES)
def test_the_notebook_is_paired_with_its_source(name):
    """The committed .ipynb holds the .py's cells (``python course.py sync`` writes it)."""
    source = jupytext.read(course.EXERCISES / f"{name}.py")
    paired = jupytext.read(course.EXERCISES / f"{name}.ipynb")
    assert [(c.cell_type, c.source) for c in paired.cells] == \
        [(c.cell_type, c.source) for c in source.cells]


@pytest.mark.parametrize("name", EXERCISES)
def test_round_trip(name, tmp_path):
    dist = course.build(name, tmp_path)
    student = dist / "student" / f"{name}.ipynb"
    text = student.read_text()
    assert "BEGIN SOLUTION" not in text and "hidden: true" not in text
    assert "check_filter" not in text or "check_filter" in (
        course.EXERCISES / f"{name}.py").read_text().split("# BEGIN QUESTION")[0]
    solution = course.grade(dist, dist / "autograder" / f"{name}.ipynb")
    assert solution, "no graded part"
    for part in solution.values():
        assert part.score == part.possible > 0, (part.name, part.failures)
    blank = course.grade(dist, student)
    assert blank.keys() == solution.keys()
    for part in blank.values():
        assert part.score == 0, (part.name, part.score)
        assert part.failures and all(m.strip() for m in part.failures.values()), part


@pytest.mark.slow
@pytest.mark.parametrize("mistake", mistakes.MISTAKES, ids=lambda m: m.name)
def test_a_mistake_gets_partial_credit_and_is_told_what(mistake, tmp_path):
    """The submission wrong on purpose (examples/course/mistakes.py) loses some points,
    not all, and its messages say what ``expect`` says. (Slow: a third grading of every
    exercise; the round trip above covers generation and grading in the default run.)"""
    parts = mistakes.grade_mistake(mistake, tmp_path)
    score = sum(p.score for p in parts.values())
    assert 0 < score < sum(p.possible for p in parts.values()), parts
    text = " ".join(m for p in parts.values() for m in p.failures.values())
    for words in mistake.expect:
        assert words in text, (words, text)


def test_every_exercise_has_a_mistake():
    assert {m.name for m in mistakes.MISTAKES} == set(EXERCISES)


def test_the_course_tuning_is_the_batch_reactor_scenarios():
    """Exercise 09 (KU Leuven session 5) grades against estim's filters with the course's
    constants; the scenario holds the same: the guess (1, 0, 4), sigma_w = 0.002,
    sigma_v = 0.25 and the guess's spread 0.5."""
    import numpy as np

    import estim

    tuning = estim.scenarios.batch_reactor().tuning
    assert np.allclose(tuning["x0"], [1.0, 0.0, 4.0])
    assert (tuning["Q"], tuning["R"], tuning["P0"]) == pytest.approx(
        (0.002**2, 0.25**2, 0.5**2))


def test_the_course_extra_installs_what_grading_runs():
    """``pip install "estim[course]"`` alone grades: otter, jupytext, and ipykernel (a
    graded notebook runs on a ``python3`` kernel; without it otter stops on
    ``NoSuchKernel``), and what the exercises import."""
    import re

    tomllib = pytest.importorskip("tomllib")  # Python 3.11
    root = Path(__file__).resolve().parents[1]
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    names = {re.split(r"[<>=\[ ]", r)[0] for r in extras["course"]}
    assert {"otter-grader", "jupytext", "ipykernel", "matplotlib", "sympy"} <= names
