"""mkdocs hook: formulas and code rendered at build time, so the site needs no network.

* Math. ``pymdownx.arithmatex`` (generic mode) leaves ``\\(...\\)`` in
  ``<span class="arithmatex">`` and ``\\[...\\]`` in ``<div class="arithmatex">``.
  This hook converts each to MathML with ``latex2mathml``, which browsers render
  natively: no script, no font download. The sidebar's table of contents gets the
  same MathML. Before converting, ``\\operatorname{f}`` becomes ``\\mathrm{f}``
  and the ``gathered``/``aligned`` environments become ``array`` (centred; right,
  left, ...), which latex2mathml lays out as tables. After it, a few slips are
  mended (``\\sim`` and ``\\pm`` as operators, accents as overscripts) and
  bold, double-struck, script and fraktur letters become their Unicode letters,
  since browsers draw no ``mathvariant`` but ``normal``. A formula that does not
  convert, or that leaves a command latex2mathml does not know as text, stops the
  build with its page and TeX.
* Code. ``pymdownx.highlight`` colours code blocks with Pygments when the page is
  built; this hook writes the Pygments stylesheet (``css/pygments.css``) and the
  math rules (``css/math.css``) into the site.

Loaded by ``mkdocs.yml`` (``hooks:``).
"""

from __future__ import annotations

import html
import re
import unicodedata

from latex2mathml.converter import convert
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File
from pygments.formatters import HtmlFormatter

PYGMENTS_STYLE = "default"
STYLESHEETS = ("css/pygments.css", "css/math.css")

_INLINE = re.compile(r'<span class="arithmatex">\\\((.*?)\\\)</span>', re.S)
_BLOCK = re.compile(r'<div class="arithmatex">\\\[(.*?)\\\]</div>', re.S)
_TOC_MATH = re.compile(r"\\\((.*?)\\\)", re.S)
_OPERATORNAME = re.compile(r"\\operatorname\s*\{")
_ENV = re.compile(r"\\begin\{(gathered|aligned)\}(.*?)\\end\{\1\}", re.S)
# what latex2mathml leaves of a command it does not know, or of an alignment mark
_LEFTOVER = re.compile(r"<m(?:i|o|n|text)[^>]*>\s*(\\[A-Za-z]+|&amp;|&)\s*</m(?:i|o|n|text)>")

# latex2mathml's slips, mended: \sim and \pm as operators; accents (\hat, \dot, ...)
# as plain overscripts, the hat as the modifier circumflex: a browser whose math font
# lacks accent metrics (Chromium with DejaVu Math, for one) draws an accent="true"
# glyph into its letter, while an overscript sits above it with every font
_FIXES = (
    (re.compile(r"<mi>&#x0007E;</mi>"), "<mo>&#x0223C;</mo>"),
    (re.compile(r"<mi>&#x000B1;</mi>"), "<mo>&#x000B1;</mo>"),
    (re.compile(r'<mover accent="true">'), "<mover>"),
    (re.compile(r"<mo>&#x0005E;</mo></mover>"), "<mo>&#x002C6;</mo></mover>"),
    (re.compile(r'<mtext mathvariant="monospace">'), '<mtext style="font-family: monospace">'),
)

MATH_CSS = """\
/* MathML written by docs/hooks/offline.py; "block math" keeps MathML layout for display
   formulas (plain "block" would lay their children out as text) */
math { font-family: "STIX Two Math", "Latin Modern Math", "Cambria Math", math; }
math[display="block"] {
  display: block math; math-style: normal; margin: 1em 0; padding: 0.3em 0;
  overflow-x: auto; overflow-y: hidden;
}
.arithmatex { overflow-x: auto; }
"""


def _environment(match: re.Match) -> str:
    name, body = match.group(1), match.group(2)
    if name == "gathered":
        columns = "c"
    else:
        ampersands = max(row.count("&") for row in body.split(r"\\"))
        columns = "".join("rl"[i % 2] for i in range(ampersands + 1))
    return rf"\begin{{array}}{{{columns}}}{body}\end{{array}}"


_VARIANT = re.compile(r'<(mi|mn) mathvariant="(bold|bold-italic|double-struck|script|fraktur|'
                      r'sans-serif)">([A-Za-z0-9])</\1>')
_VARIANT_NAMES = {"bold": "BOLD", "bold-italic": "BOLD ITALIC", "double-struck": "DOUBLE-STRUCK",
                  "script": "SCRIPT", "fraktur": "FRAKTUR", "sans-serif": "SANS-SERIF"}
_DIGITS = "ZERO ONE TWO THREE FOUR FIVE SIX SEVEN EIGHT NINE".split()
_SINGLE_MATHRM = re.compile(r"\\mathrm\s*\{\s*([A-Za-z])\s*\}")


def _unicode_variant(match: re.Match) -> str:
    """``<mi mathvariant="double-struck">R</mi>`` as ``<mi>ℝ</mi>``: browsers (MathML Core)
    draw only the mathvariant ``normal``, the others are letters of their own in Unicode."""
    tag, variant, char = match.groups()
    kind = f"DIGIT {_DIGITS[int(char)]}" if char.isdigit() else \
        f"{'CAPITAL' if char.isupper() else 'SMALL'} {char.upper()}"
    style = _VARIANT_NAMES[variant]
    holes = {"DOUBLE-STRUCK": "DOUBLE-STRUCK", "SCRIPT": "SCRIPT", "FRAKTUR": "BLACK-LETTER"}
    for name in (f"MATHEMATICAL {style} {kind}", f"{holes.get(style, style)} {kind}"):
        try:
            return f"<{tag}>&#x{ord(unicodedata.lookup(name)):05X};</{tag}>"
        except KeyError:
            continue
    return match.group(0)


def tex_to_mathml(tex: str, display: bool = False) -> str:
    """MathML of a TeX formula; a ``ValueError`` names what does not convert."""
    source = _OPERATORNAME.sub(r"\\mathrm{", tex.strip())
    # latex2mathml draws \mathrm{d} as an italic d; \text is upright
    source = _ENV.sub(_environment, _SINGLE_MATHRM.sub(r"\\text{\1}", source))
    try:
        out = convert(source, display="block" if display else "inline")
    except Exception as exc:  # latex2mathml raises its own exception types
        raise ValueError(f"latex2mathml cannot convert {tex!r}: "
                         f"{type(exc).__name__}: {exc}") from exc
    left = _LEFTOVER.search(out)
    if left:
        raise ValueError(f"latex2mathml does not know {html.unescape(left.group(1))!r} "
                         f"in {tex!r}")
    for pattern, replacement in _FIXES:
        out = pattern.sub(replacement, out)
    return _VARIANT.sub(_unicode_variant, out)


def _converter(page, display: bool):
    def replace(match: re.Match) -> str:
        try:
            return tex_to_mathml(html.unescape(match.group(1)), display)
        except ValueError as exc:
            raise PluginError(f"{page.file.src_uri}: {exc}") from None

    return replace


def _toc(items, page) -> None:
    for item in items:
        if "\\(" in item.title:
            item.title = _TOC_MATH.sub(_converter(page, False), item.title)
        _toc(item.children, page)


def on_page_content(html_text: str, page, config, files) -> str:
    html_text = _BLOCK.sub(_converter(page, True), html_text)
    html_text = _INLINE.sub(_converter(page, False), html_text)
    _toc(page.toc.items, page)
    return html_text


def on_config(config):
    for sheet in STYLESHEETS:
        if sheet not in config.extra_css:
            config.extra_css.append(sheet)
    return config


def on_files(files, config):
    css = HtmlFormatter(style=PYGMENTS_STYLE).get_style_defs(".highlight")
    for uri, content in zip(STYLESHEETS, (css + "\n", MATH_CSS), strict=True):
        files.append(File.generated(config, uri, content=content))
    return files
