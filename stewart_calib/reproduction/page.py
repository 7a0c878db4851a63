"""index.html: tables.md and the figures on one static page — no script, no server, no network.

The page is tables.md itself turned into HTML (the markdown :func:`.report.tables_markdown` writes:
headings, paragraphs, bullet lists, pipe tables, ``**bold**`` and ```code```), so the page and the
file cannot disagree, followed by the figures, which it links as the PNG files beside it. Layout
and table style are the calibration report's (:mod:`stewart_calib.viz.html_report`).
"""

from __future__ import annotations

import html
import re

from ..viz.html_report import html_page, html_table

_INLINE = ((re.compile(r"\*\*(.+?)\*\*"), r"<strong>\1</strong>"), (re.compile(r"`(.+?)`"), r"<code>\1</code>"))


def _inline(text: str) -> str:
    text = html.escape(text, quote=False)
    for pattern, replacement in _INLINE:
        text = pattern.sub(replacement, text)
    return text


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _table_html(lines: list[str]) -> str:
    """A pipe table (header, separator, rows) through :func:`html_table`, cells' inline markup kept."""
    marker = "\x00{}\x00"  # html_table escapes its cells: put each rendered cell back after it
    cells: list[str] = []

    def slot(text: str) -> str:
        cells.append(_inline(text))
        return marker.format(len(cells) - 1)

    header = [slot(cell) for cell in _cells(lines[0])]
    rows = [[slot(cell) for cell in _cells(line)] for line in lines[2:]]
    rendered = html_table(header, rows, "num")
    return re.sub("\x00(\\d+)\x00", lambda m: cells[int(m.group(1))], rendered)


def markdown_html(text: str) -> tuple[str, str]:
    """``(title, body HTML)`` of the markdown subset tables.md uses (see the module docstring)."""
    title, parts = "", []
    block: list[str] = []
    kind = None

    def flush() -> None:
        if not block:
            return
        if kind == "table":
            parts.append(_table_html(block))
        elif kind == "list":
            parts.append("<ul>" + "".join(f"<li>{_inline(item[2:])}</li>" for item in block) + "</ul>")
        else:
            parts.append(f"<p>{_inline(' '.join(block))}</p>")
        block.clear()

    for line in text.splitlines():
        if line.startswith("# "):
            flush()
            title = line[2:]
        elif line.startswith("## "):
            flush()
            parts.append(f"<h2>{_inline(line[3:])}</h2>")
        elif not line.strip():
            flush()
            kind = None
        else:
            line_kind = "table" if line.startswith("|") else "list" if line.startswith("- ") else "text"
            if line_kind != kind:
                flush()
                kind = line_kind
            block.append(line)
    flush()
    return title, "".join(parts)


def index_html(tables_md: str, figures: list[tuple[str, str]], recording: str) -> str:
    """The whole page: tables.md, then each ``(file name, caption)`` figure, then where the rerun
    recording ``recording`` is."""
    title, body = markdown_html(tables_md)
    figure_html = "".join(
        f'<figure><img alt="{html.escape(caption)}" src="{html.escape(name)}"><figcaption>{html.escape(caption)} '
        f'(<a href="{html.escape(name)}">{html.escape(name)}</a>)</figcaption></figure>'
        for name, caption in figures
    )
    recording_html = (
        f"<p>Every sample of every run, the 3D scene and the diagnostics: <code>rerun {html.escape(recording)}</code> "
        "in this directory.</p>"
    )
    return html_page(title, f"{body}<h2>Figures</h2>{figure_html}<h2>Recording</h2>{recording_html}")
