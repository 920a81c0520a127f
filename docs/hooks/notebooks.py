"""mkdocs hook: the tutorial notebooks of ``examples/notebooks`` as pages of the site.

Each notebook is executed when the site is built (``nbclient``, a kernel on the
interpreter that runs mkdocs, in a temporary directory, matplotlib's inline
backend as in Jupyter) and written as a Markdown page ``tutorials/<name>.md``:

* Markdown cells as they are (links to another notebook, ``NAME.ipynb``, point
  to its page);
* code cells as ``python`` code blocks;
* outputs: images (``image/png``) as PNG files next to the page, HTML
  (``text/html``: tables) as it is, text and streams as plain code blocks.

Nothing refers to a script or stylesheet elsewhere: the pages are Markdown,
rendered like every other page. A cell that raises stops the build with the
notebook, the cell and the error. The nav lists the pages (``mkdocs.yml``,
"Tutorials"). :func:`execute` is also what ``tests/test_notebooks.py`` runs.

Loaded by ``mkdocs.yml`` (``hooks:``).
"""

from __future__ import annotations

import base64
import os
import re
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "examples" / "notebooks"
SECTION = "tutorials"
TIMEOUT = 300  # seconds per cell

_LINK = re.compile(r"\]\(([\w.-]+)\.ipynb(#[\w-]*)?\)")
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def notebooks() -> list[Path]:
    """The tutorial notebooks, in name order."""
    return sorted(NOTEBOOKS.glob("*.ipynb"))


def _kernel_manager(directory: str):
    """A kernel manager for a ``python3`` kernel on this interpreter.

    The kernel spec is written to ``directory`` and is the only one the manager
    sees, so a ``python3`` spec of the user or the system that points to another
    Python is never picked.
    """
    import zmq
    from ipykernel.kernelspec import write_kernel_spec
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import KernelManager

    kernels = Path(directory) / "kernels"
    write_kernel_spec(str(kernels / "python3"))  # argv: this interpreter, sys.executable
    # the kernel talks to nbclient over encrypted TCP (CurveZMQ) or a local socket,
    # and so logs no warning about plain-text TCP
    if "transport_encryption" in KernelManager.class_trait_names() and zmq.has("curve"):
        transport = {"transport_encryption": "auto"}
    elif os.name != "nt":
        transport = {"transport": "ipc", "ip": str(Path(directory) / "kernel")}
    else:  # pragma: no cover - Windows without CurveZMQ: plain TCP on localhost
        transport = {}
    return KernelManager(kernel_name="python3",
                         kernel_spec_manager=KernelSpecManager(kernel_dirs=[str(kernels)]),
                         **transport)


def execute(path: str | os.PathLike, cwd: str | os.PathLike | None = None,
            timeout: int = TIMEOUT):
    """Execute a notebook as Jupyter would and return it with its outputs.

    The kernel runs this interpreter, in ``cwd`` (a temporary directory by
    default, removed afterwards), with matplotlib's inline backend.
    ``nbclient.exceptions.CellExecutionError`` is raised by the first cell
    that fails.
    """
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(str(path), as_version=4)
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}  # the inline backend
    env["PYDEVD_DISABLE_FILE_VALIDATION"] = "1"  # no debugger warning on frozen modules
    env["ESTIM_PROGRESS"] = "0"  # a page or a test records outputs: no progress bars there
    with tempfile.TemporaryDirectory(prefix="estim-kernel-") as spec_dir, \
            tempfile.TemporaryDirectory(prefix="estim-notebook-") as tmp:
        client = NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                km=_kernel_manager(spec_dir),
                                resources={"metadata": {"path": str(cwd or tmp)}})
        client.execute(env=env, cleanup_kc=True)  # stop the kernel it was given too
    return nb


def _fence(text: str, lang: str = "") -> str:
    text = text.rstrip("\n")
    ticks = "```"
    while ticks in text:
        ticks += "`"
    return f"{ticks}{lang}\n{text}\n{ticks}"


def _text(value) -> str:
    return "".join(value) if isinstance(value, list) else str(value)


def to_markdown(nb, name: str) -> tuple[str, dict[str, bytes]]:
    """An executed notebook as a Markdown page and its images.

    Returns the page's text and ``{path relative to the page's directory: PNG
    bytes}``; the images are ``<name>/cell<i>_<j>.png``.
    """
    parts: list[str] = []
    images: dict[str, bytes] = {}
    for i, cell in enumerate(nb.cells):
        source = _text(cell.source)
        if cell.cell_type == "markdown":
            parts.append(_LINK.sub(lambda m: f"]({m.group(1)}.md{m.group(2) or ''})", source))
            continue
        if cell.cell_type != "code" or not source.strip():
            continue
        parts.append(_fence(source, "python"))
        for j, out in enumerate(cell.get("outputs", [])):
            kind = out.get("output_type")
            if kind == "stream":
                parts.append(_fence(_ANSI.sub("", _text(out["text"]))))
            elif kind == "error":
                parts.append(_fence(_ANSI.sub("", "\n".join(out.get("traceback", [])))))
            elif kind in ("execute_result", "display_data"):
                data = out.get("data", {})
                if "image/png" in data:
                    image = f"{name}/cell{i}_{j}.png"
                    images[image] = base64.b64decode(_text(data["image/png"]))
                    parts.append(f"![output of cell {i}]({image})")
                elif "text/html" in data:
                    # one block of raw HTML: no blank line may end it early
                    html = "\n".join(line for line in _text(data["text/html"]).splitlines()
                                     if line.strip())
                    parts.append(f'<div class="notebook-output">\n{html}\n</div>')
                elif "text/plain" in data:
                    parts.append(_fence(_ANSI.sub("", _text(data["text/plain"]))))
    source = f"`examples/notebooks/{name}.ipynb`"
    parts.insert(1 if parts and parts[0].lstrip().startswith("# ") else 0,
                 f"*This page is the notebook {source}, executed when the site was built.*")
    return "\n\n".join(parts) + "\n", images


def on_files(files, config):
    """Execute every notebook and add its page and images to the site."""
    from mkdocs.exceptions import PluginError
    from mkdocs.structure.files import File

    for path in notebooks():
        try:
            nb = execute(path)
        except ImportError as exc:
            raise PluginError(f"the tutorial notebooks need nbclient and ipykernel "
                              f"(pip install 'estim[docs]'): {exc}") from exc
        except Exception as exc:  # a failing cell: name the notebook, keep nbclient's text
            raise PluginError(f"{path.relative_to(ROOT)} failed:\n{exc}") from exc
        page, images = to_markdown(nb, path.stem)
        files.append(File.generated(config, f"{SECTION}/{path.stem}.md", content=page))
        for image, data in images.items():
            files.append(File.generated(config, f"{SECTION}/{image}", content=data))
    return files


def on_serve(server, config, builder):
    """``mkdocs serve`` rebuilds when a notebook changes."""
    server.watch(str(NOTEBOOKS))
    return server
