"""Build and grade the exercise series with otter-grader (no Docker, no database).

The source of every exercise is its solution, ``exercises/NN_name.py``: a jupytext
"percent" script paired with ``exercises/NN_name.ipynb`` and marked up for Otter Assign
(solution regions and hidden tests). This script makes everything else from it::

    python course.py build [NAME ...] [--out dist]   # student notebooks + autograders
    python course.py grade dist/NAME SUBMISSION.ipynb [...]  # points and messages
    python course.py sync [NAME ...]                 # the .ipynb pairs from the .py

``build`` writes, per exercise, ``dist/NAME/student/NAME.ipynb`` (solutions replaced by
``...``, hidden tests removed: what students get, with the data files it reads) and
``dist/NAME/autograder/NAME-autograder_*.zip`` (what grades a submission).
``grade`` runs the autograder on submitted notebooks in this Python environment
(``otter.api.grade_submission``) and prints each part's points and, for every failed
test, the message the grader wrote.

Needs ``pip install "estim[course]"`` (otter-grader and jupytext).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
EXERCISES = HERE / "exercises"
DATA = HERE.parent / "data"


def exercises() -> list[str]:
    """The names of the exercises, in order (``01_kalman_filter``, ...)."""
    return sorted(p.stem for p in EXERCISES.glob("[0-9][0-9]_*.py"))


def _data_files(source: Path) -> list[str]:
    """The data files an exercise declares in its assignment config (``files: [...]``)."""
    for line in source.read_text().splitlines():
        line = line.lstrip("# ").strip()
        if line.startswith("files:"):
            inside = line.split(":", 1)[1].strip().strip("[]")
            return [f.strip().strip("'\"") for f in inside.split(",") if f.strip()]
    return []


def master_notebook(name: str, folder: Path) -> Path:
    """The exercise's master notebook in ``folder`` (from its .py), with its data files."""
    import jupytext

    source = EXERCISES / f"{name}.py"
    folder.mkdir(parents=True, exist_ok=True)
    for f in _data_files(source):
        shutil.copy(DATA / f, folder / f)
    path = folder / f"{name}.ipynb"
    jupytext.write(jupytext.read(source), path)
    return path


def build(name: str, out: Path | str = "dist", *, run_tests: bool = False) -> Path:
    """Otter Assign on exercise ``name``: ``out/NAME/student`` and ``out/NAME/autograder``.
    ``run_tests``: also run the tests on the solution while assigning (``grade`` does it
    on any notebook). Returns ``out/NAME``."""
    from otter.assign import main as assign

    if name not in exercises():
        raise ValueError(f"name must be one of {exercises()}, got {name!r}")
    target = Path(out).resolve() / name
    shutil.rmtree(target, ignore_errors=True)
    master = master_notebook(name, target / "master")
    assign(str(master), str(target), no_pdfs=True, no_run_tests=not run_tests)
    return target


@dataclass
class Part:
    """One graded part (an Otter question): points and the failed tests' messages."""
    name: str
    score: float
    possible: float
    failures: dict[str, str] = field(default_factory=dict)


def autograder(dist: Path | str) -> Path:
    """The autograder zip that ``build`` wrote in ``dist`` (its name has a time stamp)."""
    zips = sorted((Path(dist) / "autograder").glob("*-autograder_*.zip"))
    if not zips:
        raise ValueError(f"dist holds no autograder (run `python course.py build`): {dist}")
    return zips[-1]


def _message(case) -> str:
    """What a failed test tells the student: its failure message, then the first
    exception the test raised (the grading check's explanation), or the output the test
    did not expect."""
    text = case.message
    why = ""
    if "Exception raised:" in text:
        block = text.split("Exception raised:", 1)[1]
        block = block.split("\nTrying:", 1)[0].split("*" * 20, 1)[0]
        lines = [ln.strip() for ln in block.splitlines() if ln.strip()]
        why = lines[-1] if lines else ""
    elif "Got:" in text:
        got = text.split("Got:", 1)[1].split("\nTrying:", 1)[0].split("*" * 20, 1)[0]
        why = "unexpected output: " + " ".join(got.split())
    else:
        lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
        why = lines[-1] if lines else ""
    head = case.test_case.failure_message or ""
    return f"{head} | {why}" if head else why


def grade(dist: Path | str, submission: Path | str) -> dict[str, Part]:
    """Grade the notebook ``submission`` with the autograder in ``dist``: per part, the
    points and, for each failed test case, its message."""
    from otter.api import grade_submission

    res = grade_submission(str(submission), str(autograder(dist)), quiet=True)
    parts = {}
    for qname, tfr in res.results.items():
        fails = {c.test_case.name: _message(c) for c in tfr.test_case_results
                 if not c.passed}
        parts[qname] = Part(qname, float(tfr.score), float(tfr.possible), fails)
    return parts


def sync(names: list[str] | None = None) -> list[Path]:
    """Write the paired notebooks of ``names`` (default: every exercise) from their .py
    (outputs are not kept)."""
    import jupytext

    paths = []
    for name in names or exercises():
        if name not in exercises():
            raise ValueError(f"name must be one of {exercises()}, got {name!r}")
        nb = jupytext.read(EXERCISES / f"{name}.py")
        nb.metadata.setdefault("jupytext", {})["formats"] = "ipynb,py:percent"
        path = EXERCISES / f"{name}.ipynb"
        jupytext.write(nb, path)
        paths.append(path)
    return paths


def _report(parts: dict[str, Part]) -> str:
    lines = []
    total = sum(p.score for p in parts.values())
    possible = sum(p.possible for p in parts.values())
    for p in parts.values():
        lines.append(f"  {p.name}: {p.score:g}/{p.possible:g}")
        for case, msg in p.failures.items():
            lines.append(f"    {case}: {msg}")
    return f"{total:g}/{possible:g}\n" + "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    b = sub.add_parser("build", help="student notebooks and autograders")
    b.add_argument("names", nargs="*", help="exercises (default: all)")
    b.add_argument("--out", default="dist")
    b.add_argument("--run-tests", action="store_true",
                   help="also run the tests on the solution")
    g = sub.add_parser("grade", help="grade submitted notebooks")
    g.add_argument("dist", help="an exercise's folder written by build (dist/NAME)")
    g.add_argument("submissions", nargs="+")
    y = sub.add_parser("sync", help="write the .ipynb pairs from the .py sources")
    y.add_argument("names", nargs="*", help="exercises (default: all)")
    args = parser.parse_args(argv)
    if args.command == "build":
        for name in args.names or exercises():
            print(build(name, args.out, run_tests=args.run_tests))
    elif args.command == "grade":
        for path in args.submissions:
            print(f"{path}: {_report(grade(args.dist, path))}")
    else:
        for path in sync(args.names):
            print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
