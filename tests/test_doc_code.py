"""The Python code of README.md and docs/*.md runs, so the examples cannot drift.

Each page is one test: its ```` ```python ```` blocks run in order in one
namespace (``numpy as np``, ``casadi as ca`` and ``estim`` imported, as the
pages say), in a temporary directory that holds a link to ``examples/`` (the
pages load data from there), with matplotlib's Agg backend.

An HTML comment on the line before a fence, invisible in the rendered page,
changes what happens to a block:

* ``<!-- signature -->``: a call signature with placeholders (``Q=...``), not
  run; every call of an ``estim`` name in it (and of a method of an object it
  builds) is checked against the real signature: each parameter exists, and
  each default written as a literal is the real default.
* ``<!-- no-run: reason -->``: not run, for the reason given (a fragment that
  needs the reader's own data, a cluster, ...).

Console blocks (```` ```sh ````) are not run; the ``estim`` subcommands and
options they use must exist.
"""

from __future__ import annotations

import ast
import inspect
import re
import shlex
import types
from pathlib import Path

import pytest

import estim

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_FENCE = re.compile(
    r"^(?P<marker><!--\s*(?P<kind>no-run|signature)(?::\s*(?P<why>.*?))?\s*-->\n)?"
    r"(?P<indent>[ \t]*)```(?P<lang>[\w-]*)[^\n]*\n(?P<body>.*?)^(?P=indent)```[ \t]*$",
    re.S | re.M)


def _blocks(path: Path) -> list[dict]:
    """The fenced blocks of a page: ``lang``, ``kind`` (run, no-run, signature), ``why``,
    ``code`` (dedented) and ``line``."""
    text = path.read_text(encoding="utf-8")
    out = []
    for m in _FENCE.finditer(text):
        indent = len(m["indent"])
        code = "".join(line[indent:] if line[:indent].isspace() else line
                       for line in m["body"].splitlines(keepends=True))
        out.append({"lang": m["lang"], "kind": m["kind"] or "run", "why": m["why"],
                    "code": code, "line": text.count("\n", 0, m.start("body"))})
    return out


def _label(path: Path) -> str:
    return str(path.relative_to(ROOT))


def _figure_pages() -> set[str]:
    """The pages whose code the site build runs too (``PAGES`` of docs/hooks/figures.py,
    read without importing mkdocs)."""
    tree = ast.parse((ROOT / "docs" / "hooks" / "figures.py").read_text(encoding="utf-8"))
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "PAGES"
                                                for t in node.targets):
            return set(ast.literal_eval(node.value))
    raise AssertionError("docs/hooks/figures.py has no PAGES")


def _python_pages():
    # the figure pages' blocks run in the strict site build of tests/test_docs.py (the
    # same namespace, directory and backend; a failing block stops the build): in the
    # default run they run there, and here with -m slow
    figures = _figure_pages()
    return [pytest.param(p, id=_label(p),
                         marks=[pytest.mark.slow] if p.name in figures and
                         p.parent.name == "docs" else [])
            for p in PAGES if any(b["lang"] == "python" for b in _blocks(p))]


@pytest.mark.parametrize("page", _python_pages())
def test_code_blocks_run(page, tmp_path, monkeypatch):
    pytest.importorskip("matplotlib")
    import casadi as ca
    import matplotlib
    import matplotlib.pyplot as plt
    import numpy as np

    matplotlib.use("Agg")
    (tmp_path / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__doc_page__", "np": np, "ca": ca, "estim": estim}
    try:
        for block in _blocks(page):
            if block["lang"] != "python" or block["kind"] != "run":
                continue
            # line numbers of the page in tracebacks
            code = "\n" * block["line"] + block["code"]
            exec(compile(code, str(page), "exec"), namespace)
    finally:
        plt.close("all")


def test_exclusions_give_a_reason():
    """``no-run`` says why; ``signature`` marks only Python blocks."""
    bad = [f"{_label(p)}:{b['line']}" for p in PAGES for b in _blocks(p)
           if (b["kind"] == "no-run" and not (b["why"] or "").strip())
           or (b["kind"] != "run" and b["lang"] != "python")]
    assert not bad, "no-run without a reason, or a marker on a non-Python block: " + ", ".join(bad)


# --------------------------------------------------------------- signatures
def _calls(code: str):
    """``(assigned name or None, dotted target, argument text)`` of every top-level call
    statement of a signature block."""
    out = []
    for m in re.finditer(r"^(?:(\w+)\s*=\s*)?([A-Za-z_][\w.]*)\(", code, re.M):
        depth, i = 1, m.end()
        while depth and i < len(code):
            depth += {"(": 1, ")": -1}.get(code[i], 0)
            i += 1
        out.append((m[1], m[2], code[m.end():i - 1]))
    return out


def _resolve(target: str, built: dict):
    head, *rest = target.split(".")
    if head == "estim":
        obj = estim
    elif head in built:
        obj = built[head]
    else:
        return None
    for part in rest:
        obj = getattr(obj, part, None)
        if obj is None:
            raise AssertionError(f"{target}: {part!r} does not exist")
    return obj


def _signature_blocks():
    return [pytest.param(b, id=f"{_label(p)}:{b['line']}") for p in PAGES for b in _blocks(p)
            if b["kind"] == "signature"]


@pytest.mark.parametrize("block", _signature_blocks())
def test_signature_blocks_match_the_code(block):
    built: dict = {}
    problems = []
    for name, target, args in _calls(block["code"]):
        obj = _resolve(target, built)
        if obj is None or isinstance(obj, types.ModuleType):
            continue
        if name and inspect.isclass(obj):
            built[name] = obj
        real = inspect.signature(obj)
        written = ast.parse(f"def f({args}): pass").body[0].args
        params = [*written.posonlyargs, *written.args, *written.kwonlyargs]
        positional = [p.arg for p in [*written.posonlyargs, *written.args]]
        defaults = dict(zip(positional[len(positional) - len(written.defaults):],
                            written.defaults, strict=True))
        defaults.update({p.arg: d for p, d in zip(written.kwonlyargs, written.kw_defaults,
                                                   strict=True) if d is not None})
        for p in params:
            if p.arg not in real.parameters:
                problems.append(f"{target}: no parameter {p.arg!r} (it has "
                                f"{', '.join(real.parameters)})")
                continue
            default = defaults.get(p.arg)
            try:
                value = ast.literal_eval(default) if default is not None else Ellipsis
            except ValueError:
                continue  # a placeholder (N, range(5), ...)
            if value is not Ellipsis and real.parameters[p.arg].default != value:
                problems.append(f"{target}: {p.arg}={value!r} written, the default is "
                                f"{real.parameters[p.arg].default!r}")
    assert not problems, "\n".join(problems)


# ------------------------------------------------------------ console blocks
def _estim_commands():
    for page in PAGES:
        for block in _blocks(page):
            if block["lang"] not in ("sh", "bash", "console", "shell"):
                continue
            for line in block["code"].splitlines():
                line = line.split("#", 1)[0].strip()
                m = re.search(r"(?:^|&&\s*|\s)(?:\S*/)?estim\s+(\w+)(.*)$", line)
                if m and not line.startswith("pip"):
                    yield _label(page), m[1], shlex.split(m[2])


def test_console_blocks_use_existing_commands_and_options(monkeypatch, capsys):
    """Every ``estim ...`` line of a console block parses (subcommand, options, choices),
    and its ``-e`` estimator specs name existing estimators and options."""
    from estim import cli

    seen = []
    for command in ("list", "run", "observe", "tune"):
        monkeypatch.setattr(cli, f"_cmd_{command}", lambda args: seen.append(args) or 0)
    problems = []
    commands = list(_estim_commands())
    assert commands, "no estim command found in the console blocks"
    for page, command, args in commands:
        seen.clear()
        try:
            status = cli.main([command, *args])
        except SystemExit as exc:
            status = exc.code
        if status != 0 or not seen:
            err = capsys.readouterr().err.strip().splitlines()
            problems.append(f"{page}: estim {command} {shlex.join(args)}: "
                            f"{err[-1] if err else status}")
            continue
        for spec in getattr(seen[0], "estimator", None) or []:
            try:
                cli.parse_estimator(spec)
            except (ValueError, TypeError) as exc:
                problems.append(f"{page}: estim {command} -e {spec}: {exc}")
    assert not problems, "\n".join(problems)
