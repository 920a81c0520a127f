"""Griffe extension for the API page: the reST bits of estim's docstrings as Markdown.

estim's docstrings are numpydoc with Sphinx markup. mkdocstrings parses the
numpydoc sections itself; this extension rewrites, before parsing,

* ``.. math::`` blocks (indented or on the same line) to ``$$ ... $$``
  (wrapped in ``gathered`` where they break lines with ``\\``),
* ``:math:`...``` to ``$...$`` (rendered by ``pymdownx.arithmatex`` + MathJax),
* ``:class:`~estim.Model``` and the other cross-reference roles to code,
* ``term`` lines followed by an indented description (reST definition
  lists) to Markdown definition lists, and ``text::`` literal blocks to
  fenced code,
* the backticks in the types of ``name : type`` lines to plain text.

The docstrings themselves are not changed. Loaded by ``mkdocs.yml``
(``plugins: mkdocstrings: handlers: python: options: extensions``).
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:class|func|meth|mod|attr|obj|data|exc):`~?([^`]+)`")
_MATH = re.compile(r":math:`([^`]+)`", re.S)
_HEADER = re.compile(r"^\s*-{3,}\s*$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def _math_block(body: list[str], indent: str) -> list[str]:
    text = "\n".join(body).strip("\n")
    if "\\\\" in text:
        text = "\\begin{gathered}\n" + text + "\n\\end{gathered}"
    return [indent + "$$", *[indent + t.strip() for t in text.splitlines()], indent + "$$"]


def _block(lines: list[str], start: int) -> tuple[list[str], int]:
    """The indented block after ``lines[start - 1]``; returns it and the next index."""
    base = _indent(lines[start - 1])
    i, body = start, []
    while i < len(lines) and (not lines[i].strip() or _indent(lines[i]) > base):
        body.append(lines[i])
        i += 1
    while body and not body[-1].strip():
        body.pop()
        i -= 1
    if body:
        cut = min(_indent(b) for b in body if b.strip())
        body = [b[cut:] for b in body]
    return body, i


def convert(text: str) -> str:
    """reST markup of one docstring to Markdown (see the module docstring)."""
    lines = text.splitlines()
    out: list[str] = []
    i = 0
    in_sections = False
    in_deflist = False
    while i < len(lines):
        line = lines[i]
        stripped = line.strip()
        if i + 1 < len(lines) and stripped and _HEADER.match(lines[i + 1]):
            in_sections = True
        if stripped.startswith(".. math::"):
            indent = line[: _indent(line)]
            rest = stripped[len(".. math::"):].strip()
            body, i = _block(lines, i + 1)
            out.extend(_math_block(([rest] if rest else []) + body, indent))
            continue
        if stripped.endswith("::") and not stripped.startswith(".."):
            indent = line[: _indent(line)]
            body, j = _block(lines, i + 1)
            if body:
                head = line.rstrip()[:-1]  # "text::" -> "text:"
                out.extend([head, "", indent + "```python",
                            *[indent + b for b in body], indent + "```"])
                i = j
                continue
        # reST definition list in the free text: a term, then an indented description
        if (not in_sections and stripped and _indent(line) == 0 and i + 1 < len(lines)
                and lines[i + 1].strip() and _indent(lines[i + 1]) > 0
                and (i == 0 or not lines[i - 1].strip() or in_deflist)
                and not lines[i + 1].strip().startswith((">>>", "..."))):
            body, i = _block(lines, i + 1)
            if in_deflist:
                out.append("")
            out.extend([stripped, ":   " + " ".join(b.strip() for b in body)])
            in_deflist = True
            continue
        in_deflist = False
        if in_sections and _indent(line) == 0 and " : " in line:
            # numpydoc "name : type" line: the type is shown as plain text, without markup
            name, _, kind = line.partition(" : ")
            line = name + " : " + kind.replace("`", "")
        out.append(line)
        i += 1
    text = "\n".join(out)
    text = _MATH.sub(lambda m: "$" + " ".join(m.group(1).split()) + "$", text)
    return _ROLE.sub(lambda m: "`" + m.group(1).split(".")[-1]
                     .removesuffix("()") + ("()" if ":func:" in m.group(0)
                                            or ":meth:" in m.group(0) else "") + "`", text)


class RstToMarkdown(griffe.Extension):
    """Rewrite every docstring once the object tree is complete."""

    def on_object(self, *, obj, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value)
