"""The documentation: a strict mkdocs build, and a docstring for every public name.

The docstring checks follow python-control's ``docstrings_test``: every name
in ``estim.__all__`` has a docstring of its own, and every parameter of every
public callable (a function, or a class's constructor) is listed in the
numpydoc ``Parameters`` section of its docstring. For a dataclass the
constructor's parameters are its fields, so an ``Attributes`` section counts
too. ``**kwargs``-style catch-alls would be exempt; the public callables have
none: unknown keywords are refused against the real signature
(:func:`estim._validate.check_keywords`), which ``inspect.signature`` still shows.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import inspect
import re
import subprocess
import sys
import types
from pathlib import Path

import pytest

import estim

ROOT = Path(__file__).resolve().parents[1]
DOCS_PACKAGES = {"mkdocs": "mkdocs", "mkdocstrings": "mkdocstrings[python]",
                 "mkdocstrings_handlers": "mkdocstrings[python]",
                 "pymdownx": "pymdown-extensions", "latex2mathml": "latex2mathml",
                 "pygments": "pygments", "matplotlib": "matplotlib",
                 # the tutorials (examples/notebooks) are executed when the site is built
                 "nbclient": "nbclient", "nbformat": "nbformat", "ipykernel": "ipykernel",
                 "pandas": "pandas"}


def _missing_docs_packages() -> list[str]:
    return sorted({pip for module, pip in DOCS_PACKAGES.items()
                   if importlib.util.find_spec(module) is None})


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """The site of one strict mkdocs build, shared by the tests of this module."""
    missing = _missing_docs_packages()
    if missing:
        pytest.skip(f"the documentation build needs {', '.join(missing)} "
                    f"(pip install '.[docs]')")
    site = tmp_path_factory.mktemp("docs") / "site"
    res = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict",
                          "--site-dir", str(site)],
                         cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "WARNING" not in res.stderr, res.stderr
    return site


def test_mkdocs_build_strict(site):
    for page in ("index", "ekf", "mhe", "fie", "shooting", "models", "observability",
                 "comparisons", "performance", "plotting", "api"):
        assert (site / f"{page}.html").exists(), f"{page}.md was not built"
    for notebook in sorted((ROOT / "examples" / "notebooks").glob("*.ipynb")):
        page = site / "tutorials" / f"{notebook.stem}.html"
        assert page.exists(), f"{notebook.name} was not built"
        assert '<img alt="output of cell' in page.read_text(encoding="utf-8"), page
    # the API page documents every public name as what it is (estim.simulate and
    # estim.compare are functions that share their names with modules)
    api = (site / "api.html").read_text(encoding="utf-8")
    absent = []
    for name in estim.__all__:
        obj = getattr(estim, name)
        kind = "module" if isinstance(obj, types.ModuleType) else \
            "class" if inspect.isclass(obj) else "function"
        path = rf"estim\.{name}" if kind == "module" else rf"estim(?:\.\w+)*\.{name}"
        if not re.search(rf'<div class="doc doc-object doc-{kind}">\s*<h\d id="{path}"', api):
            absent.append(f"estim.{name} ({kind})")
    assert not absent, "not on the API page: " + ", ".join(absent)


_EXTERNAL = r"(?:[a-z][a-z0-9+.-]*:)?//"  # http://, https://, //host: anything not in the site
_TAG = re.compile(r"<(script|link|img|source|iframe|embed|object|video|audio|input)\b[^>]*>",
                  re.I | re.S)
_ATTR = re.compile(r"""\b(src|href|srcset|data|poster)\s*=\s*(["']?)([^"'\s>]*)""", re.I)
_CSS_URL = re.compile(r"""url\(\s*(["']?)([^"')]*)|@import\s+(["'])([^"']*)""", re.I)


def _external_references(site: Path) -> list[str]:
    found = []
    for path in sorted(site.rglob("*")):
        if path.suffix not in (".html", ".css"):
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        where = path.relative_to(site)
        css = [text] if path.suffix == ".css" else \
            re.findall(r"<style[^>]*>(.*?)</style>", text, re.S | re.I) + \
            re.findall(r"""\bstyle\s*=\s*"([^"]*)\"""", text, re.I)
        if path.suffix == ".html":
            for tag in _TAG.finditer(text):
                for attr in _ATTR.finditer(tag.group(0)):
                    if re.match(_EXTERNAL, attr.group(3), re.I):
                        found.append(f"{where}: <{tag.group(1)} {attr.group(1)}="
                                     f"{attr.group(3)}>")
        for block in css:
            for m in _CSS_URL.finditer(block):
                url = m.group(2) if m.group(2) is not None else m.group(4)
                if re.match(_EXTERNAL, url or "", re.I):
                    found.append(f"{where}: CSS {url}")
    return found


def test_site_needs_no_network(site):
    """No page loads a script, stylesheet, font or image from another host: the site
    works offline and opened from disk."""
    external = _external_references(site)
    assert not external, "external resources:\n" + "\n".join(external)
    # the check itself sees what it must see
    probe = site.parent / "probe"
    probe.mkdir()
    (probe / "a.html").write_text('<script src="https://cdn.example/x.js"></script>'
                                  '<link rel="stylesheet" href="//cdn.example/s.css">'
                                  '<img src="http://example.org/i.png">'
                                  '<style>@import "https://fonts.example/f.css";</style>'
                                  '<a href="https://example.org">a link is fine</a>')
    (probe / "b.css").write_text("@font-face { src: url(https://fonts.example/f.woff2); }")
    assert len(_external_references(probe)) == 5


def _has_math(markdown: str) -> bool:
    text = re.sub(r"```.*?```", "", markdown, flags=re.S)
    text = re.sub(r"`[^`]*`", "", text)
    return bool(re.search(r"\$[^$\s][^$]*\$", text))


def test_formulas_are_rendered_as_mathml(site):
    """Every formula became MathML when the site was built: no TeX is left for a script."""
    pages = {md.stem: md for md in (ROOT / "docs").glob("*.md")}
    with_math = [name for name, md in pages.items() if _has_math(md.read_text())] + ["api"]
    with_math += [f"tutorials/{nb.stem}"  # every tutorial has formulas in its text
                  for nb in (ROOT / "examples" / "notebooks").glob("*.ipynb")]
    assert len(with_math) > 5
    problems = []
    for name in sorted(set(with_math)):
        html = (site / f"{name}.html").read_text(encoding="utf-8")
        prose = re.sub(r"<(pre|code)\b.*?</\1>", "", html, flags=re.S)
        if "<math" not in html:
            problems.append(f"{name}: no MathML")
        for tex in ("\\(", "\\[", "$$"):
            if tex in prose:
                problems.append(f"{name}: raw {tex} left")
        # browsers draw no mathvariant but "normal" (MathML Core)
        for variant in set(re.findall(r'mathvariant="(?!normal")([^"]*)"', html)):
            problems.append(f"{name}: mathvariant={variant}")
    assert not problems, "; ".join(problems)
    # a formula that does not convert stops the build, naming it
    spec = importlib.util.spec_from_file_location("offline", ROOT / "docs/hooks/offline.py")
    offline = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(offline)
    for bad in (r"\frac{a}{", r"\unknowncommand x"):
        with pytest.raises(ValueError, match=re.escape(bad)):
            offline.tex_to_mathml(bad)
    assert 'mathvariant' not in offline.tex_to_mathml(r"\mathbb R^3 \ni \mathbf x")
    # code is coloured when the site is built (Pygments), with the stylesheet in the site
    ekf = (site / "ekf.html").read_text(encoding="utf-8")
    assert '<div class="highlight"><pre>' in ekf and '<span class="n">' in ekf
    assert (site / "css" / "pygments.css").exists() and "css/pygments.css" in ekf


# ------------------------------------------------------------------ docstrings
_UNDERLINE = re.compile(r"^\s*-{3,}\s*$")


def _sections(doc: str) -> dict[str, list[str]]:
    """numpydoc sections: ``{"Parameters": [lines], ...}`` (header underlined by dashes)."""
    lines = doc.splitlines()
    out: dict[str, list[str]] = {}
    current = None
    for i, line in enumerate(lines):
        if line.strip() and i + 1 < len(lines) and _UNDERLINE.match(lines[i + 1]):
            current = line.strip()
            out.setdefault(current, [])
        elif current is not None and not _UNDERLINE.match(line):
            out[current].append(line)
    return out


def _entry_names(lines: list[str]) -> set[str]:
    """Names in a section: ``name : type``, ``a, b : type``, ``*args``, bare ``name``."""
    indents = [len(line) - len(line.lstrip()) for line in lines if line.strip()]
    if not indents:
        return set()
    base = min(indents)
    names = set()
    for line in lines:
        if line.strip() and len(line) - len(line.lstrip()) == base:
            head = line.strip()
            head = head.split(" :")[0] if " :" in head else head.split(":")[0]
            names.update(n.strip().lstrip("*") for n in head.split(",") if n.strip())
    return names


def _own_doc(obj) -> str:
    """The object's own docstring (not inherited, not a dataclass's generated signature)."""
    doc = obj.__doc__ or ""
    if inspect.isclass(obj) and dataclasses.is_dataclass(obj) \
            and doc.startswith(obj.__name__ + "("):
        doc = ""
    return inspect.cleandoc(doc) if doc.strip() else ""


def _public():
    return [(name, getattr(estim, name)) for name in estim.__all__]


def test_every_public_name_has_a_docstring():
    missing = [f"estim.{name}" for name, obj in _public() if not _own_doc(obj)]
    assert not missing, "public names without a docstring: " + ", ".join(missing)


def _parameters():
    """``(label, parameters to document, all parameters, documented names, names listed
    under Parameters)`` for every public callable."""
    out = []
    for name, obj in _public():
        if isinstance(obj, types.ModuleType) or not callable(obj):
            continue
        try:
            sig = inspect.signature(obj)
        except (TypeError, ValueError):  # pragma: no cover - builtins without a signature
            continue
        docs = [_own_doc(obj)]
        if inspect.isclass(obj) and "__init__" in vars(obj):
            docs.append(_own_doc(obj.__init__))
        documented: set[str] = set()
        listed: set[str] = set()
        for doc in docs:
            sections = _sections(doc)
            listed |= _entry_names(sections.get("Parameters", []))
            if inspect.isclass(obj) and dataclasses.is_dataclass(obj):
                documented |= _entry_names(sections.get("Attributes", []))
        params = [p.name for p in sig.parameters.values()
                  if p.name not in ("self", "cls") and p.kind is not p.VAR_KEYWORD]
        out.append((f"estim.{name}", params, set(sig.parameters), documented | listed, listed))
    return out


def test_every_public_parameter_is_documented():
    undocumented = [f"{label}({p})" for label, params, _, documented, _ in _parameters()
                    for p in params if p not in documented]
    assert not undocumented, (
        f"{len(undocumented)} parameter(s) missing from the docstrings' Parameters sections: "
        + ", ".join(undocumented))


def test_documented_parameters_exist():
    stale = [f"{label}({n})" for label, _, every, _, listed in _parameters()
             for n in sorted(listed - every)]
    assert not stale, "Parameters entries that the signature does not have: " + ", ".join(stale)


def test_identification_recipe_runs(monkeypatch):
    """The recipe of docs/identification.md, run as written (from the repository root),
    gives what its last line says."""
    import re

    import numpy as np

    text = (ROOT / "docs" / "identification.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    monkeypatch.chdir(ROOT)
    ns: dict = {}
    exec(compile(code, "identification.md", "exec"), ns)
    res = ns["res"]
    assert (res.status, res.iterations) == ("ok", 5)
    np.testing.assert_allclose(res.x[0, 2:], [0.5225, 0.06721, 0.4965, 2.012, 5.387], rtol=5e-4)
