"""mkdocs hook: the pictures of the plotting page, drawn by its own code when the site is built.

The ```` ```python ```` blocks of each page in ``PAGES`` run in order in one
namespace (``numpy as np``, ``casadi as ca`` and ``estim`` imported, as the
pages say; blocks marked ``<!-- no-run: reason -->`` or ``<!-- signature -->``
are skipped), in a temporary directory that holds a link to the repository's
``examples/`` (the pages load data from there), with matplotlib's Agg backend. Every
PNG they write is added to the site as ``figures/<name>.png``, so the page links
``figures/<name>.png`` and shows exactly what its code draws with the real
plotting helpers. An exception in a block stops the build.

Loaded by ``mkdocs.yml`` (``hooks:``).
"""

from __future__ import annotations

import os
import re
import tempfile
import traceback
from pathlib import Path

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

PAGES = ("plotting.md", "particle.md", "attitude.md", "gaussian_filters.md",
         "continuous_noise.md", "bayesian.md", "observability.md")
FOLDER = "figures"

_FENCE = re.compile(
    r"^(?P<marker><!--\s*(?:no-run|signature)\b[^\n]*-->\n)?"
    r"(?P<indent>[ \t]*)```python[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$", re.S | re.M)


def _blocks(text: str) -> list[tuple[int, str]]:
    out = []
    for m in _FENCE.finditer(text):
        if m["marker"]:
            continue
        indent = len(m["indent"])
        code = "".join(line[indent:] for line in m["body"].splitlines(keepends=True))
        out.append((text.count("\n", 0, m.start("body")), code))
    return out


def figures(page: Path) -> dict[str, bytes]:
    """Run the page's Python blocks; the PNGs they write, by file name."""
    import casadi as ca
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    import estim

    namespace = {"__name__": "__doc_page__", "np": np, "ca": ca, "estim": estim}
    cwd = os.getcwd()
    with tempfile.TemporaryDirectory() as tmp:
        examples = page.resolve().parents[1] / "examples"
        if examples.is_dir():
            os.symlink(examples, Path(tmp) / "examples")
        os.chdir(tmp)
        try:
            for line, code in _blocks(page.read_text(encoding="utf-8")):
                exec(compile("\n" * line + code, str(page), "exec"), namespace)
        except Exception as exc:
            raise PluginError(f"{page.name}: a code block failed while drawing its figures:\n"
                              + "".join(traceback.format_exception(exc))) from None
        finally:
            os.chdir(cwd)
            plt.close("all")
        return {p.name: p.read_bytes() for p in sorted(Path(tmp).glob("*.png"))}


def on_files(files, config):
    for name in PAGES:
        page = Path(config.docs_dir) / name
        for png, content in figures(page).items():
            files.append(File.generated(config, f"{FOLDER}/{png}", content=content))
    return files
