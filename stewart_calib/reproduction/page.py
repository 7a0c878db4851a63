"""index.html: tables.md and the figures on one static page — no script, no server, no network.

The page is tables.md itself turned into HTML (the markdown :func:`.report.tables_markdown` writes:
headings, paragraphs, bullet lists, pipe tables, ``**bold**`` and ```code```), so the page and the
file cannot disagree, followed by the figures, which it links as the PNG files beside it: Figs. 5–6
of one run at a time under a row of tabs, one a run, each with the run's line and marker of Figs.
7–9 (radio buttons and CSS: a tab shows its run's figures in place, with no script), then Figs.
7–9. Layout and table style are the calibration report's (:mod:`stewart_calib.viz.html_report`).
"""

from __future__ import annotations

import html
import math
import re

from ..viz.html_report import html_page, html_table
from .figures import PAPER_METHOD, FigureFile, RunStyle

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


#: SVG dash patterns of the line styles of :data:`.figures.LINESTYLES` [px at a stroke of 2 px]
DASHES = {"-": "", "--": "6 3", ":": "1.5 2.5", "-.": "6 2.5 1.5 2.5"}
#: SVG shapes of the markers of :data:`.figures.MARKERS`: a circle, or a regular polygon's
#: (corners, angle of its first corner [°]), as matplotlib draws them
MARKER_POLYGONS = {"^": (3, 90), "v": (3, 270), "<": (3, 180), ">": (3, 0), "s": (4, 45), "D": (4, 90)}
MARKER_POLYGONS |= {"p": (5, 90), "h": (6, 90)}
#: the swatch of a run in its tab [px]: width, height, marker radius
SWATCH_PX = (34, 12, 4.0)

_TABS_STYLE = """
.runs > input { position: absolute; opacity: 0; pointer-events: none; }
.runs .tabs { display: flex; flex-wrap: wrap; gap: .25em; border-bottom: 1px solid #ccc; margin: .6em 0 0; }
.runs .tabs label { display: inline-flex; align-items: center; gap: .4em; padding: .3em .7em; cursor: pointer;
  border: 1px solid #ccc; border-bottom: none; border-radius: 4px 4px 0 0; background: #f4f4f4; font-size: .9em; }
.runs .panel { display: none; }
"""


def swatch_svg(style: RunStyle) -> str:
    """An inline SVG of ``style``'s line and hollow marker, as a legend of Figs. 7–9 draws the run."""
    width, height, radius = SWATCH_PX
    x, y = width / 2, height / 2
    dash = DASHES[style.linestyle]
    line = (
        f'<line x1="1" y1="{y}" x2="{width - 1}" y2="{y}" stroke="{style.color}" stroke-width="2"'
        + (f' stroke-dasharray="{dash}"' if dash else "")
        + "/>"
    )
    paint = f'fill="#fff" stroke="{style.color}" stroke-width="1.3"'
    if style.marker in MARKER_POLYGONS:
        corners, first_deg = MARKER_POLYGONS[style.marker]
        angles = [math.radians(first_deg + 360.0 * k / corners) for k in range(corners)]
        points = " ".join(f"{x + radius * math.cos(a):.2f},{y - radius * math.sin(a):.2f}" for a in angles)
        marker = f'<polygon points="{points}" {paint}/>'
    else:
        marker = f'<circle cx="{x}" cy="{y}" r="{radius * 0.85:.2f}" {paint}/>'
    box = f'width="{width}" height="{height}" viewBox="0 0 {width} {height}"'
    return f'<svg {box} aria-hidden="true">{line}{marker}</svg>'


def _figure_html(figure: FigureFile) -> str:
    name, caption = html.escape(figure.name), html.escape(figure.caption)
    return (
        f'<figure><img alt="{caption}" src="{name}"><figcaption>{caption} '
        f'(<a href="{name}">{name}</a>)</figcaption></figure>'
    )


def run_tabs_html(figures: list[FigureFile]) -> str:
    """The figures of each run under a row of tabs, one a run in the order they come, the paper's
    method shown first: radio buttons before the tabs and the panels, whose ``:checked`` state CSS
    reads to show one panel and mark its tab."""
    runs: dict[str, list[FigureFile]] = {}
    for figure in figures:
        if figure.run is not None:
            runs.setdefault(figure.run, []).append(figure)
    if not runs:
        return ""
    shown = PAPER_METHOD if PAPER_METHOD in runs else next(iter(runs))
    inputs, tabs, panels, rules = [], [], [], []
    for k, (run, run_figures) in enumerate(runs.items()):
        style = run_figures[0].style
        checked = " checked" if run == shown else ""
        inputs.append(f'<input type="radio" name="run" id="run-{k}"{checked}>')
        swatch = "" if style is None else swatch_svg(style)
        tabs.append(f'<label for="run-{k}">{swatch}{html.escape(run)}</label>')
        panels.append(f'<div class="panel" id="panel-{k}">{"".join(_figure_html(f) for f in run_figures)}</div>')
        rules.append(
            f"#run-{k}:checked ~ #panel-{k} {{ display: block; }}\n"
            f"#run-{k}:checked ~ .tabs label[for=run-{k}] {{ background: #fff; font-weight: 600; "
            "margin-bottom: -1px; border-bottom: 1px solid #fff; }\n"
            f"#run-{k}:focus-visible ~ .tabs label[for=run-{k}] {{ outline: 2px solid #4a90d9; }}\n"
        )
    return (
        f"<style>{_TABS_STYLE}{''.join(rules)}</style>"
        "<p>Figs. 5–6 of one run: choose it by its tab (its line and marker are those of Figs. 7–9).</p>"
        f'<div class="runs">{"".join(inputs)}<div class="tabs">{"".join(tabs)}</div>{"".join(panels)}</div>'
    )


def index_html(tables_md: str, figures: list[FigureFile], recording: str) -> str:
    """The whole page: tables.md, then the figures (Figs. 5–6 of each run under its tab, then the
    others), then where the rerun recording ``recording`` is."""
    title, body = markdown_html(tables_md)
    figure_html = run_tabs_html(figures) + "".join(_figure_html(f) for f in figures if f.run is None)
    recording_html = (
        f"<p>Every sample of every run, the 3D scene and the diagnostics: <code>rerun {html.escape(recording)}</code> "
        "in this directory.</p>"
    )
    return html_page(title, f"{body}<h2>Figures</h2>{figure_html}<h2>Recording</h2>{recording_html}")
