"""A tiny document model rendered both as Markdown and as self-contained HTML.

A report is a list of blocks (:class:`Heading`, :class:`Paragraph`,
:class:`Warning`, :class:`Table`, :class:`Figure`).  :func:`to_markdown`
links the PNG figures by file name; :func:`to_html` embeds them as base64
``data:`` URIs so that ``report.html`` is one file with no external resources.
"""

from __future__ import annotations

import base64
import html
import math
import numbers
from pathlib import Path
from typing import NamedTuple, Sequence, Union

__all__ = ["Heading", "Paragraph", "Alert", "Table", "Figure", "Block", "to_markdown", "to_html",
           "format_number", "format_rhat", "format_ess"]

MISSING = "–"


def format_number(x, digits: int = 3) -> str:
    """``x`` to ``digits`` significant digits for a report or a printed line.

    Integers print whole, booleans as yes/no, ``None`` and NaN as a dash.
    Magnitudes of ``10**digits`` or more print as whole numbers (``12346``,
    not ``1.23e+04``) up to 1e9.
    """
    if x is None:
        return MISSING
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, numbers.Integral):
        return str(int(x))
    x = float(x)
    if math.isnan(x):
        return MISSING
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    if 10**digits <= abs(x) < 1e9:
        return f"{x:.0f}"
    return f"{x:.{digits}g}"


def format_rhat(x) -> str:
    """R-hat to 3 decimals (``1.004``); ``None`` and NaN as a dash."""
    return MISSING if x is None or math.isnan(float(x)) else f"{float(x):.3f}"


def format_ess(x) -> str:
    """An effective sample size as a whole number; ``None`` and NaN as a dash."""
    return MISSING if x is None or math.isnan(float(x)) else str(int(round(float(x))))


class Heading(NamedTuple):
    text: str
    level: int = 2


class Paragraph(NamedTuple):
    text: str


class Alert(NamedTuple):
    """A loud warning box."""

    text: str


class Table(NamedTuple):
    header: Sequence[str]
    rows: Sequence[Sequence[str]]
    caption: str = ""


class Figure(NamedTuple):
    path: Path
    caption: str


Block = Union[Heading, Paragraph, Alert, Table, Figure]


def to_markdown(blocks: Sequence[Block]) -> str:
    """Markdown with figures referenced by their file name (relative to the report)."""
    out = []
    for block in blocks:
        if isinstance(block, Heading):
            out.append("#" * block.level + " " + block.text)
        elif isinstance(block, Paragraph):
            out.append(block.text)
        elif isinstance(block, Alert):
            out.append("> **WARNING.** " + block.text)
        elif isinstance(block, Table):
            lines = ["| " + " | ".join(block.header) + " |", "|" + "---|" * len(block.header)]
            lines += ["| " + " | ".join(row) + " |" for row in block.rows]
            if block.caption:
                lines = [block.caption, ""] + lines
            out.append("\n".join(lines))
        elif isinstance(block, Figure):
            out.append(f"![{block.caption}]({Path(block.path).name})\n\n*{block.caption}*")
        else:  # pragma: no cover - programming error
            raise TypeError(f"unknown block {block!r}")
    return "\n\n".join(out) + "\n"


_STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; padding: 0 1em; line-height: 1.45; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
.alert { border: 3px solid #c00; background: #fee; padding: 0.8em 1em; font-weight: bold; }
figure { margin: 1em 0 2em; } figure img { max-width: 100%; } figcaption { font-style: italic; }
code { background: #f4f4f4; padding: 0 0.2em; }
"""


def _inline(text: str) -> str:
    """Escape text and turn Markdown inline code and bold into HTML."""
    import re

    text = html.escape(text)
    text = re.sub(r"`([^`]+)`", r"<code>\1</code>", text)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", text)


def to_html(blocks: Sequence[Block], title: str) -> str:
    """A self-contained HTML page: inline CSS, figures embedded as base64 PNG."""
    out = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>",
           f"<style>{_STYLE}</style></head><body>"]
    for block in blocks:
        if isinstance(block, Heading):
            out.append(f"<h{block.level}>{_inline(block.text)}</h{block.level}>")
        elif isinstance(block, Paragraph):
            out.append(f"<p>{_inline(block.text)}</p>")
        elif isinstance(block, Alert):
            out.append(f"<div class='alert'>WARNING. {_inline(block.text)}</div>")
        elif isinstance(block, Table):
            cap = f"<caption>{_inline(block.caption)}</caption>" if block.caption else ""
            head = "".join(f"<th>{_inline(h)}</th>" for h in block.header)
            rows = "".join("<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in row) + "</tr>" for row in block.rows)
            out.append(f"<table>{cap}<thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
        elif isinstance(block, Figure):
            data = base64.b64encode(Path(block.path).read_bytes()).decode("ascii")
            out.append(f"<figure><img alt='{html.escape(block.caption)}' src='data:image/png;base64,{data}'>"
                       f"<figcaption>{_inline(block.caption)}</figcaption></figure>")
        else:  # pragma: no cover - programming error
            raise TypeError(f"unknown block {block!r}")
    out.append("</body></html>")
    return "\n".join(out) + "\n"
