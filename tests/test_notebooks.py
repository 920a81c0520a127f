"""The tutorial notebooks (examples/notebooks) run as in Jupyter, and render as doc pages.

Each notebook is executed by ``nbclient`` on a ``python3`` kernel of this
interpreter, in a temporary directory, with matplotlib's inline backend: what a
user gets with "Run all". The execution and the conversion to a page are those
of the documentation build (``docs/hooks/notebooks.py``).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

pytest.importorskip("nbclient", reason="the notebook tests need nbclient (pip install nbclient)")
pytest.importorskip("ipykernel", reason="the notebook tests need ipykernel (pip install ipykernel)")
nbformat = pytest.importorskip("nbformat")

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "examples" / "notebooks").glob("*.ipynb"))


def _hook():
    spec = importlib.util.spec_from_file_location("notebooks_hook",
                                                  ROOT / "docs" / "hooks" / "notebooks.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


hook = _hook()
_executed: dict[Path, object] = {}


def executed(path: Path, tmp_path_factory):
    """The notebook run once per test session (each test that needs it shares the run)."""
    if path not in _executed:
        _executed[path] = hook.execute(path, cwd=tmp_path_factory.mktemp(path.stem))
    return _executed[path]


def _code(nb):
    return [(i, cell) for i, cell in enumerate(nb.cells) if cell.cell_type == "code"]


def test_the_tutorials_are_there():
    assert [p.name for p in NOTEBOOKS] == ["01_getting_started.ipynb", "02_your_own_model.ipynb",
                                           "03_comparing_estimators.ipynb"]
    assert hook.notebooks() == NOTEBOOKS


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_without_outputs(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    dirty = [i for i, cell in _code(nb) if cell.outputs or cell.execution_count is not None]
    assert not dirty, f"{path.name}: cells {dirty} have outputs; clear them before committing"
    assert nb.metadata.kernelspec.name == "python3"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_runs(path, tmp_path_factory):
    nb = executed(path, tmp_path_factory)  # a failing cell raises CellExecutionError
    errors = [(i, out.ename) for i, cell in _code(nb) for out in cell.outputs
              if out.output_type == "error"]
    assert not errors
    # no cell left unexecuted, and every cell's warnings are deliberate: none expected here
    assert all(cell.execution_count is not None for _, cell in _code(nb))
    stderr = ["".join(out.text) for _, cell in _code(nb) for out in cell.outputs
              if out.output_type == "stream" and out.name == "stderr"]
    assert not stderr, stderr


_RETURNS_A_PLOT = re.compile(r"^[\w.\[\]\"']+\.plot\([^;]*\)\s*$")


def test_a_returned_figure_is_drawn_once(tmp_path_factory):
    """A cell ending in ``log.plot()`` (a Figure as the cell's value) shows one image.

    Jupyter's inline backend draws every figure a cell made, and a returned
    Figure is drawn again as the cell's value unless the library prevents it.
    """
    cells = []
    for path in NOTEBOOKS:
        nb = executed(path, tmp_path_factory)
        for i, cell in _code(nb):
            last = cell.source.strip().splitlines()[-1]
            if _RETURNS_A_PLOT.match(last):
                images = sum("image/png" in out.get("data", {}) for out in cell.outputs)
                cells.append((f"{path.stem}, cell {i}: {last}", images))
    assert any("log.plot()" in label for label, _ in cells)
    twice = [f"{label} ({n} images)" for label, n in cells if n != 1]
    assert not twice, "cells whose figure is not drawn exactly once: " + "; ".join(twice)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_page(path, tmp_path_factory):
    """The page of the documentation: code, outputs and images, nothing fetched elsewhere."""
    nb = executed(path, tmp_path_factory)
    page, images = hook.to_markdown(nb, path.stem)
    assert page.startswith("# ")
    assert page.count("```python\n") == sum(bool(c.source.strip()) for _, c in _code(nb))
    linked = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", page)
    assert linked and sorted(linked) == sorted(images)
    assert all(data.startswith(b"\x89PNG") for data in images.values())
    assert ".ipynb)" not in page  # links between notebooks point to their pages
    assert not re.search(r"<(script|link|iframe)\b", page, re.I)
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:)?//""", page, re.I)
