"""User-provided text made inert in the report's Markdown and CSV files.

Option values, method, dataset, split and setting names, preset titles and sweep labels are
the user's (or a plugin's) strings. The HTML and LaTeX renderers escape them with
``html.escape`` and ``tables.tex_escape``; these are the same for the other two formats:

- :func:`md_text`: Markdown viewers render inline HTML, so ``<``, ``>`` and ``&`` become
  entities (every CommonMark and GitHub viewer shows them as the characters), the characters
  that make emphasis, code, links, table cells or math are backslash-escaped, and line breaks
  (which would end a table row or start a block) become spaces.
- :func:`csv_frame` / :func:`write_csv`: a spreadsheet runs a cell that starts with ``=``,
  ``+``, ``-``, ``@``, a tab or a carriage return as a formula, so such a text cell gets a
  leading ``'`` (OWASP's CSV-injection advice); a number, or text that is exactly a decimal
  number (``-0.5``, an option value), stays as it is.
"""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

_MD_ENTITIES = {"&": "&amp;", "<": "&lt;", ">": "&gt;"}
#: backslash-escaped: code spans, emphasis, links and images, table cells, strikethrough,
#: GitHub's math, a heading's closing sequence, the escape character itself
_MD_BACKSLASHED = set("\\`*_[]|~$#")
_LINE_BREAK = re.compile(r"\r\n|\r|\n")


def md_text(s: object) -> str:
    """``s`` as literal Markdown text (a table cell, a heading, a list item): it renders as the
    characters of ``s`` and never as HTML, a link, emphasis or a new table cell."""
    out = []
    for ch in _LINE_BREAK.sub(" ", str(s)):
        if ch in _MD_ENTITIES:
            out.append(_MD_ENTITIES[ch])
        elif ch in _MD_BACKSLASHED:
            out.append("\\" + ch)
        else:
            out.append(ch)
    return "".join(out)


_FORMULA_START = ("=", "+", "-", "@", "\t", "\r", "\n")
_NUMBER = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?")


def csv_cell(v: object) -> object:
    """``v`` as a CSV cell no spreadsheet reads as a formula: text starting with = + - @ tab
    or CR gets a leading ``'`` unless it is a plain decimal number; anything else is ``v``."""
    if isinstance(v, str) and v.startswith(_FORMULA_START) and not _NUMBER.fullmatch(v):
        return "'" + v
    return v


def csv_frame(df: pd.DataFrame) -> pd.DataFrame:
    """A copy of ``df`` with :func:`csv_cell` applied to every text cell and column name;
    numeric columns are untouched (their values are written as pandas writes them)."""
    out = df.rename(columns=lambda c: csv_cell(c) if isinstance(c, str) else c)
    for i, dt in enumerate(out.dtypes):
        if dt.kind in "OSU" or isinstance(dt, pd.StringDtype):  # text (or mixed) columns only
            out.isetitem(i, out.iloc[:, i].map(csv_cell))
    return out


def csv_text(df: pd.DataFrame) -> str:
    """``df`` as CSV text (no index), through :func:`csv_frame`."""
    return csv_frame(df).to_csv(index=False)


def write_csv(df: pd.DataFrame, path: Path) -> None:
    """Write ``df`` to ``path`` as CSV (no index), through :func:`csv_frame`."""
    csv_frame(df).to_csv(path, index=False)
