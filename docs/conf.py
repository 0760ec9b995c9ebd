"""Sphinx configuration of the usdeform documentation (``bash docs/build``)."""

from __future__ import annotations

import re
from importlib.metadata import version as _version
from typing import Any

project = "usdeform"
author = "the usdeform maintainers"
copyright = "the usdeform maintainers, BSD-3-Clause"
release = _version("usdeform")
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
root_doc = "index"

# The pages come from the README (Markdown); `#section` links resolve to headings down to ###.
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]

# The docstrings mix Google style (``Args:``) and NumPy style (``Parameters``); napoleon reads both.
napoleon_google_docstring = True
napoleon_numpy_docstring = True
napoleon_use_rtype = False
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_typehints_format = "short"
autodoc_preserve_defaults = True

html_theme = "furo"
html_title = f"usdeform {release}"
html_static_path = ["_static"]
html_css_files = ["tables.css"]


_LITERAL = re.compile(r"(``.+?``)")
_UNPACKING = re.compile(r"(?<=\()\*(?=\w)|(?<=, )\*(?=\w)")
_AFTER_LITERAL = set(" \t-.,:;!?\\/'\")]}>")


def _plain_text_notation(app: Any, what: str, name: str, obj: Any, options: Any, lines: list[str]) -> None:
    """Escape the docstrings' plain-text notation that reST reads as markup, outside ``literals``: ``|x|``
    (an absolute value, not a substitution), ``(n, *shape)`` (unpacking, not emphasis) and a literal
    followed by a letter or ``^`` (``size``^3), which would leave the literal open."""
    for number, line in enumerate(lines):
        if line.lstrip().startswith(("|", "+-", "+=")):  # a table
            continue
        parts = _LITERAL.split(line)
        for index in range(0, len(parts), 2):
            text = _UNPACKING.sub(r"\\*", parts[index].replace("|", r"\|"))
            if index and text and text[0] not in _AFTER_LITERAL:
                text = "\\ " + text
            parts[index] = text
        lines[number] = "".join(parts)


def _hanging_indents(app: Any, what: str, name: str, obj: Any, options: Any, lines: list[str]) -> None:
    """Join a line indented deeper than the line before it onto that line (a hanging indent, as in
    ``name: text`` lists written for the terminal), except in literal blocks and directives; reST
    would read it as an unexpected block quote."""
    joined: list[str] = []
    block: int | None = None  # indent of the line that opened a literal block or a directive
    for line in lines:
        text, indent = line.strip(), len(line) - len(line.lstrip())
        if block is not None and (not text or indent > block):
            joined.append(line)
            continue
        block = None
        before = joined[-1] if joined else ""
        opens = before.rstrip().endswith("::") or before.lstrip().startswith(".. ")
        if text and before.strip() and indent > len(before) - len(before.lstrip()) and not opens:
            joined[-1] = f"{before.rstrip()} {text}"
            continue
        if text.endswith("::") or text.startswith(".. "):
            block = indent
        joined.append(line)
    lines[:] = joined


def setup(app: Any) -> None:
    app.connect("autodoc-process-docstring", _plain_text_notation)
    app.connect("autodoc-process-docstring", _hanging_indents)
