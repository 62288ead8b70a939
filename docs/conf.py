"""Sphinx configuration: the guide's pages in MyST Markdown, the API reference from the docstrings of `cosim` and
`agents` (autodoc, autosummary), and the config key reference generated from the config's JSON schema
(`config_reference.py`). Build: `python -m sphinx -W --keep-going -b html docs docs/_build/html`."""

from __future__ import annotations

import re
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
sys.path[:0] = [str(DOCS.parent), str(DOCS)]

import config_reference  # noqa: E402  (docs/config_reference.py)

project = "cosim"
author = "the cosim authors"
copyright = "the cosim authors"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.viewcode",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}  # .rst: autosummary's stubs
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
templates_path = ["_templates"]
myst_heading_anchors = 3

autosummary_generate = True
autodoc_member_order = "bysource"
autodoc_typehints = "signature"

html_theme = "furo"
html_title = "cosim"


# The docstrings are written in Markdown's manner: `code` spans, and bullet lists right under a line ("Contract:").
# reStructuredText reads a single backtick as interpreted text and wants blank lines around a list, and `|x|` is a
# substitution there; so turn the spans into inline literals, set the lists apart and escape the bars, and the
# docstrings render as written. Roles (:class:`x`) and ``literals`` are left alone.
_CODE_SPAN = re.compile(r"(?<![`:])`(?!`)([^`\n]+?)`(?!`)")
_BULLET = re.compile(r"\s*(?:[-*+]|\d+[.)])\s")


def _literal(match: re.Match[str]) -> str:
    text, s, e = match.string, match.start(), match.end()
    before = "\\ " if s and (text[s - 1].isalnum() or text[s - 1] in "_") else ""
    after = "\\ " if e < len(text) and (text[e].isalnum() or text[e] in "_") else ""
    return f"{before}``{match.group(1)}``{after}"


def _rst_line(line: str) -> str:
    parts = _CODE_SPAN.sub(_literal, line).split("``")
    return "``".join(p if i % 2 else p.replace("|", "\\|") for i, p in enumerate(parts))


def _markdown_docstring(app, what, name, obj, options, lines) -> None:  # noqa: ANN001
    out: list[str] = []
    in_list = False
    for line in lines:
        bullet = bool(_BULLET.match(line)) and not line.startswith((" ", "\t"))
        if bullet and out and out[-1].strip() and not in_list:
            out.append("")  # a list right under a line of text
        elif in_list and line.strip() and not bullet and not line.startswith((" ", "\t")):
            out.append("")  # the text after a list
            in_list = False
        in_list = in_list or bullet
        if not line.strip():
            in_list = False
        out.append(_rst_line(line))
    lines[:] = out


def _config_reference(app, docname, source) -> None:  # noqa: ANN001
    if config_reference.MARKER in source[0]:
        source[0] = source[0].replace(config_reference.MARKER, config_reference.markdown())


def setup(app):  # noqa: ANN001, ANN201
    app.connect("autodoc-process-docstring", _markdown_docstring)
    app.connect("source-read", _config_reference)
