"""The reproduction's figures as a reader holds them beside the paper's (stewart_calib.reproduction.figures)."""

from __future__ import annotations

import itertools
import re
from types import SimpleNamespace

import numpy as np
import pytest

from stewart_calib.pipelines.reproduce import PARTS
from stewart_calib.reproduction.figures import (
    LINESTYLES,
    MARKERS,
    PAPER_METHOD,
    FigureFile,
    figures,
    run_styles,
)
from stewart_calib.reproduction.page import DASHES, MARKER_POLYGONS, index_html, swatch_svg
from stewart_calib.reproduction.runs import BATCH_METHOD, NOMINAL, Part, Reproduction, online_runs

#: the parts of the model the reproduce command adds, and made-up ones for more or fewer parts
PART_NAMES = [tuple(name for name, *_ in PARTS), *(tuple(f"part{k}" for k in range(n)) for n in range(4))]


def _reproduction(names: tuple[str, ...]) -> Reproduction:
    """A reproduction's runs in the order reproduce() makes them (nominal, ls, then online_runs),
    each standing for a MethodRun by its method alone: all the styles and the figure list read."""
    parts = tuple(Part(name, "", None, "") for name in names)
    runs = {NOMINAL: NOMINAL, BATCH_METHOD: BATCH_METHOD, **{run: method for run, method, _ in online_runs(parts)}}
    platform = SimpleNamespace(prismatic_drive=lambda what: None)
    return Reproduction(
        experiment=SimpleNamespace(platform=platform),
        config=None,
        runs={run: SimpleNamespace(method=method) for run, method in runs.items()},
        parts=parts,
    )


def _rgb(color: str) -> np.ndarray:
    return np.array([int(color[k : k + 2], 16) for k in (1, 3, 5)], float)


@pytest.mark.parametrize("names", PART_NAMES, ids="-".join)
def test_every_run_has_a_style_of_its_own(names):
    """One table keyed by run, for every run the reproduction makes: no two runs share a colour,
    and none a (colour, line style, marker); the colours stay apart on screen; each estimator's
    fullest run is solid, its runs with fewer parts dashed, dotted, …"""
    reproduction = _reproduction(names)
    styles = run_styles(reproduction.parts)
    assert list(styles) == list(reproduction.runs)
    colours = [style.color for style in styles.values()]
    assert len(set(colours)) == len(colours), colours
    assert len({(s.color, s.linestyle, s.marker) for s in styles.values()}) == len(styles)
    # the nearest two of the command's nine (two shades of ekf's blue) are 73 apart of the 441 of RGB; shades
    # closer than 60 read as one colour in a thin line. With three parts or more an estimator has four shades
    # or more between the same two ends, 49 apart: there the line style and the marker set its runs apart.
    nearest = min(np.linalg.norm(_rgb(a) - _rgb(b)) for a, b in itertools.combinations(colours, 2))
    assert nearest > (60 if len(names) <= 2 else 40), nearest
    if len(styles) <= len(MARKERS):  # the reproduce command's nine runs: a marker each
        assert len({style.marker for style in styles.values()}) == len(styles)
    assert [style.label for style in styles.values()] == ["before calibration", *reproduction.calibrated]
    for run, style in styles.items():
        method = reproduction.runs[run].method
        family = [name for name in reproduction.runs if reproduction.runs[name].method == method]
        assert style.linestyle == LINESTYLES[(len(family) - 1 - family.index(run)) % len(LINESTYLES)], run
        assert style.line()["label"] == style.label


@pytest.mark.parametrize("names", PART_NAMES, ids="-".join)
def test_every_calibrated_run_has_figs_5_and_6(names):
    reproduction = _reproduction(names)
    files = [name for name, _, _ in figures(reproduction)]
    expected = [f"fig{k}_{run}.png" for run in reproduction.calibrated for k in (5, 6)]
    assert files == [*expected, "fig7_pose_errors.png", "fig8_circle.png", "fig9_polar.png"]


def test_every_style_has_its_swatch_on_the_page():
    """The page's tabs draw a run's line and marker as the figures do: each line style a dash
    pattern, each marker its shape (a polygon of as many corners, or a circle)."""
    assert set(DASHES) == set(LINESTYLES)
    assert set(MARKERS) <= {*MARKER_POLYGONS, "o"}
    for style in run_styles(_reproduction(PART_NAMES[0]).parts).values():
        svg = swatch_svg(style)
        assert svg.count(style.color) == 2  # the line and the marker's edge
        assert ('stroke-dasharray="' + DASHES[style.linestyle] + '"' in svg) == (style.linestyle != "-")
        if style.marker == "o":
            assert "<circle" in svg
        else:
            points = re.search(r'<polygon points="([^"]+)"', svg).group(1).split()
            assert len(points) == MARKER_POLYGONS[style.marker][0]


def test_the_page_shows_one_runs_figures_at_a_time_with_no_script():
    """A radio button, a tab (with the run's swatch) and a panel of its Figs. 5–6 per run, the
    paper's method checked; Figs. 7–9 after them; nothing fetched, nothing run."""
    styles = run_styles(_reproduction(PART_NAMES[0]).parts)
    runs = [run for run in styles if run != NOMINAL]
    files = [FigureFile(f"fig{k}_{run}.png", f"Fig. {k} — {run}", run, styles[run]) for run in runs for k in (5, 6)]
    files += [FigureFile("fig7_pose_errors.png", "Fig. 7"), FigureFile("fig9_polar.png", "Fig. 9")]
    page = index_html("# Title\n\nText.\n", files, "reproduce.rrd")
    assert "<script" not in page and "http" not in page
    radios = re.findall(r'<input type="radio" name="run" id="(run-\d+)"( checked)?>', page)
    assert [name for name, _ in radios] == [f"run-{k}" for k in range(len(runs))]
    assert [k for k, (_, checked) in enumerate(radios) if checked] == [runs.index(PAPER_METHOD)]
    tabs = re.findall(r'<label for="(run-\d+)">(<svg.*?</svg>)([^<]+)</label>', page)
    assert [(name, label) for name, _, label in tabs] == [(f"run-{k}", run) for k, run in enumerate(runs)]
    assert [svg for _, svg, _ in tabs] == [swatch_svg(styles[run]) for run in runs]
    for k, run in enumerate(runs):
        panel = re.search(rf'<div class="panel" id="panel-{k}">(.*?)</div>', page).group(1)
        assert re.findall(r'src="([^"]+)"', panel) == [f"fig5_{run}.png", f"fig6_{run}.png"]
        assert f"#run-{k}:checked ~ #panel-{k} {{ display: block; }}" in page
    rest = page.rsplit("</div>", 1)[1]  # after the last panel
    assert re.findall(r'src="([^"]+)"', rest) == ["fig7_pose_errors.png", "fig9_polar.png"]
