"""The paper's figures (Ren et al. Figs. 5–9) as PNG files beside tables.md.

* ``fig5_<run>.png`` — δM of one calibrated run through the no-load stage, one panel per parameter
  (a row per kind, a column per leg), each with its ±σ band and the truth in force (dashed): the
  convergence of Fig. 5;
* ``fig6_<run>.png`` — the same through every load stage, the stages' starts marked (Fig. 6);
* ``fig7_pose_errors.png`` — the true pose error at each validation pose, before calibration and
  with every run, per stage (Fig. 7);
* ``fig8_circle.png`` — the circle as run, its deviation from the desired circle magnified (Fig. 8);
* ``fig9_polar.png`` — the deviation around the circle in polar form, per stage (Fig. 9).

Figs. 5–6 are drawn for every calibrated run (the page lets the reader choose the run shown). Every
run is drawn in the style :func:`run_styles` gives it, the one table every figure and the page's
run selector read. Pose errors are of the truth view (the verdict's); one value per held pose as in
the tables (:mod:`.metrics`).
"""

from __future__ import annotations

import concurrent.futures
import io
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from ..io import atomic_write_bytes
from ..model.platform import PARAMETER_FIELDS, LegGeometry
from ..viz.html_report import new_figure
from .metrics import held_pose_ends, view_errors
from .report import VERDICT_VIEW
from .runs import BATCH_METHOD, NOMINAL, MethodRun, Part, Reproduction, WorkerPool, online_runs

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: each estimator's runs in shades of one hue, from its rigid run (light) to its run with every
#: part of the model (dark): the hue says the estimator, the shade how much of the model it has.
METHOD_SHADES = {
    NOMINAL: ("#737373", "#737373"),
    BATCH_METHOD: ("#d62728", "#d62728"),
    "paper-ekf": ("#ff7f0e", "#ff7f0e"),
    "ekf": ("#6baed6", "#08519c"),
    "isam2": ("#74c476", "#006d2c"),
}
#: the shades of an online method the table does not name (a plugin's), in the order they come
SPARE_SHADES = (("#bca6dc", "#6a3d9a"), ("#d9a77e", "#8c510a"), ("#f2a5cf", "#ae017e"), ("#7fd3d9", "#00797b"))
#: a run with every part of its model solid, one part fewer dashed, two fewer dotted, …
LINESTYLES = ("-", "--", ":", "-.")
#: one marker per run, in the order of the runs: a run reads apart where lines overlap or colour fails
MARKERS = ("o", "s", "^", "D", "v", "p", "h", "<", ">")
#: the method of the paper, the run the page shows first in Figs. 5–6.
PAPER_METHOD = "paper-ekf"
#: Fig. 8 magnifies the calibrated runs' deviation so that the largest is this fraction of the radius.
CIRCLE_DEVIATION_SHARE = 0.25
#: Fig. 7's shift between neighbouring runs' points at one validation pose [pose]
POSE_DODGE = 0.04
#: markers a closed curve of Figs. 8–9 carries, spread round it (every point would hide the line)
MARKERS_PER_CIRCLE = 6
#: the y range of a row of Figs. 5–6 spans the estimate and the truth with this margin on each side
#: (a fraction of the span): the first samples' σ of several mm would squeeze the converged part flat
Y_MARGIN = 0.12


#: a panel of Figs. 5–6 [in] (width, height), and the margins round them [in] (left, bottom, right,
#: top) that hold the kinds' labels, the time axis, and the title over the legend over the legs
PANEL_IN = (2.1, 1.2)
MARGINS_IN = (0.75, 0.5, 0.15, 0.95)
#: the PNGs' resolution [dots per inch]
PNG_DPI = 100


@dataclass(frozen=True)
class RunStyle:
    """How one run is drawn in every figure (and in the page's run selector).

    Attributes:
        label: the legend's name of the run (``before calibration`` for ``nominal``).
        color: ``#rrggbb``.
        linestyle: a matplotlib line style of :data:`LINESTYLES`.
        marker: a matplotlib marker of :data:`MARKERS`.
    """

    label: str
    color: str
    linestyle: str
    marker: str

    def line(self) -> dict:
        """Keyword arguments of ``Axes.plot`` for a line of this run, its markers included."""
        return {
            "color": self.color,
            "linestyle": self.linestyle,
            "marker": self.marker,
            "mfc": "none",  # hollow: a marker over another run's line or marker leaves it visible
            "mew": 1.0,
            "label": self.label,
        }


def _blend(light: str, dark: str, share: float) -> str:
    """``#rrggbb`` ``share`` of the way from ``light`` to ``dark``."""
    a, b = (np.array([int(c[k : k + 2], 16) for k in (1, 3, 5)], float) for c in (light, dark))
    return "#" + "".join(f"{round(v):02x}" for v in a + share * (b - a))


def run_styles(parts: tuple[Part, ...]) -> dict[str, RunStyle]:
    """The style of every run of a reproduction with ``parts`` (``nominal``, ``ls``, then
    :func:`.runs.online_runs`, in that order), keyed by run: colour by estimator and shade by the
    parts of the model it has (:data:`METHOD_SHADES`), line style by the parts it lacks against
    that estimator's fullest run, a marker of its own. No two runs share a colour (while no more
    than four estimators lack a row of :data:`METHOD_SHADES`)."""
    runs = [(NOMINAL, NOMINAL), (BATCH_METHOD, BATCH_METHOD), *((run, method) for run, method, _ in online_runs(parts))]
    siblings: dict[str, list[str]] = {}
    for run, method in runs:
        siblings.setdefault(method, []).append(run)
    spare = iter(SPARE_SHADES * len(siblings))
    shades = {method: METHOD_SHADES.get(method) or next(spare) for method in siblings}
    styles = {}
    for index, (run, method) in enumerate(runs):
        family = siblings[method]
        more = family.index(run)  # parts of the model this run has beyond the estimator's first run
        share = 1.0 if len(family) == 1 else more / (len(family) - 1)
        styles[run] = RunStyle(
            label="before calibration" if run == NOMINAL else run,
            color=_blend(*shades[method], share),
            linestyle=LINESTYLES[(len(family) - 1 - more) % len(LINESTYLES)],
            marker=MARKERS[index % len(MARKERS)],
        )
    return styles


def _markevery(run_index: int, n_runs: int, n_points: int) -> tuple[int, int]:
    """Every how many points a closed curve of Figs. 8–9 carries its run's marker, each run's
    markers shifted round the circle so that overlapping runs show their markers side by side."""
    step = max(1, n_points // MARKERS_PER_CIRCLE)
    return (run_index * step // max(1, n_runs)) % step, step


def _parameter_figure(drive: LegGeometry, method_run: MethodRun, style: RunStyle, rows: np.ndarray, title: str):
    """One panel per parameter — a row per kind (δj_x … δl), a column per leg — with δM of
    ``method_run`` at ``rows`` in its run's colour, its ±σ band and its truth (dashed): in force,
    or unloaded for a run whose model carries the sag. One band a panel: seven overlapping bands in
    one leg's panel hide each other, and the kinds differ in scale (δl moves by millimetres where
    δd_z moves by tenths). A row's y range is that of its estimates and truths: the band may leave
    it while σ is larger than the error it bounds."""
    result = method_run.result
    nominal = drive.as_vector()
    t = result.log.t_s[rows]
    # an elastic model's δM is the unloaded drive: its truth is the robot's, not the one in force
    truth = (
        np.broadcast_to(result.robot.base_params, (len(rows), nominal.size)) - nominal
        if method_run.unloaded
        else result.truth.params[rows] - nominal
    )
    estimate = method_run.trace[rows]
    kinds = len(PARAMETER_FIELDS)
    width_in, height_in = PANEL_IN[0] * drive.n_legs + sum(MARGINS_IN[::2]), PANEL_IN[1] * kinds + sum(MARGINS_IN[1::2])
    fig = _hand_laid_figure(width_in, height_in)
    left, bottom, right, top = MARGINS_IN
    axes = fig.subplots(
        kinds,
        drive.n_legs,
        sharex=True,
        sharey="row",
        squeeze=False,
        gridspec_kw={
            "left": left / width_in,
            "right": 1.0 - right / width_in,
            "bottom": bottom / height_in,
            "top": 1.0 - top / height_in,
            "wspace": 0.08,
            "hspace": 0.14,
        },
    )
    for leg in range(drive.n_legs):
        for k in range(kinds):
            ax, col = axes[k, leg], kinds * leg + k
            if method_run.stddev is not None:  # σ is kept at every parameter_stride-th sample
                kept = np.isfinite(method_run.stddev[rows, col])
                sigma = method_run.stddev[rows, col][kept]
                mean = estimate[kept, col]
                ax.fill_between(t[kept], mean - sigma, mean + sigma, color=style.color, alpha=0.18, lw=0)
            ax.plot(t, estimate[:, col], color=style.color, lw=1.4)
            ax.plot(t, truth[:, col], color="0.15", lw=0.8, ls="--")
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=6)
        axes[0, leg].set_title(f"leg {leg + 1}", fontsize=9)
        axes[-1, leg].set_xlabel("t [s]", fontsize=8)
    for k, field in enumerate(PARAMETER_FIELDS):
        axes[k, 0].set_ylabel(f"δ{field} [mm]", fontsize=8)
        of_kind = np.concatenate([estimate[:, k::kinds].ravel(), truth[:, k::kinds].ravel()])
        low, high = float(of_kind.min()), float(of_kind.max())
        pad = Y_MARGIN * max(high - low, 1e-3)
        axes[k, 0].set_ylim(low - pad, high + pad)
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    marks = [
        (Patch(color=style.color, alpha=0.3), "± σ" if method_run.stddev is not None else ""),
        (Line2D([], [], color=style.color, lw=1.4), "estimate"),
        (Line2D([], [], color="0.15", lw=0.8, ls="--"), "truth"),
        (Line2D([], [], lw=1.0, ms=4.0, **style.line()), f"{style.label} in Figs. 7–9"),
    ]
    # the legend in a row under the title: a run's name may be long, the panels keep the width
    shown = [mark for mark in marks if mark[1]]
    fig.legend(
        *zip(*shown, strict=True),
        loc="upper center",
        bbox_to_anchor=(0.5, 1.0 - 0.36 / height_in),
        ncol=len(shown),
        fontsize=8,
        frameon=False,
    )
    fig.suptitle(title, fontsize=10, y=1.0 - 0.1 / height_in, va="top")
    return fig


def _stage_starts(result) -> list[tuple[float, str]]:
    names = list(dict.fromkeys(result.stages))
    return [(float(result.log.t_s[np.flatnonzero(result.stages == name)[0]]), name) for name in names]


def fig5(drive: LegGeometry, style: RunStyle, method_run: MethodRun):
    result = method_run.result
    rows = np.flatnonzero(result.stages == result.stages[0])
    return _parameter_figure(
        drive,
        method_run,
        style,
        rows,
        f"Fig. 5 — {style.label}: parameter errors through the {result.stages[0]} stage "
        "(calibration, validation, circle)",
    )


def fig6(drive: LegGeometry, style: RunStyle, method_run: MethodRun):
    result = method_run.result
    fig = _parameter_figure(
        drive,
        method_run,
        style,
        np.arange(len(result.log)),
        f"Fig. 6 — {style.label}: parameter errors through the load stages",
    )
    top_row = [ax for ax in fig.axes if ax.get_subplotspec().is_first_row()]
    for ax in fig.axes:
        for start, name in _stage_starts(result)[1:]:
            ax.axvline(start, color="0.3", lw=0.8, ls=":")
            if ax in top_row:  # the stage's name once a column, not in each of its panels
                ax.text(start, 1.0, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="top", color="0.3")
    return fig


def _legend(fig, axes) -> None:
    """One legend for the figure, right of its panels: every run of ``axes`` once, in order."""
    handles, labels = [], []
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    fig.legend(handles, labels, loc="outside right center", fontsize=8, handlelength=3.0)


def fig7(reproduction: Reproduction):
    """True pose error at each validation pose, per stage: before calibration and every run."""
    stages, styles = reproduction.stage_names, run_styles(reproduction.parts)
    fig = new_figure(4.2 * len(stages) + 2.0, 6.0)
    axes = fig.subplots(2, len(stages), sharey="row", squeeze=False)
    runs = [NOMINAL, *reproduction.calibrated]
    for index, run in enumerate(runs):
        result = reproduction.runs[run].result
        position, orientation = view_errors(result, reproduction.platform)[VERDICT_VIEW]
        ends = held_pose_ends(result) & (result.kinds == "validation")
        # the poses are categories: each run's points shifted a little, so that equal errors sit side by side
        shift = POSE_DODGE * (index - (len(runs) - 1) / 2)
        for column, stage in enumerate(stages):
            mask = ends & (result.stages == stage)
            for row, values in enumerate((position, orientation)):
                axes[row, column].plot(
                    np.arange(mask.sum()) + shift, values[mask], ms=4.0, lw=1.0, **styles[run].line()
                )
    for column, stage in enumerate(stages):
        axes[0, column].set_title(stage, fontsize=9)
        axes[1, column].set_xlabel("validation pose", fontsize=8)
    axes[0, 0].set_ylabel("position error [mm]", fontsize=8)
    axes[1, 0].set_ylabel("orientation error [°]", fontsize=8)
    for ax in axes.ravel():
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        ax.tick_params(labelsize=7)
    _legend(fig, axes[0, :1])
    fig.suptitle("Fig. 7 — pose error at the validation poses before and after calibration (truth view)", fontsize=10)
    return fig


def _circle_points(reproduction: Reproduction, run: str, stage: str) -> tuple[np.ndarray, np.ndarray]:
    """``(desired, actual)`` circle positions ``(n, 3)`` [mm] of ``run`` in ``stage``."""
    result = reproduction.runs[run].result
    circle = (result.stages == stage) & (result.kinds == "circle")
    return result.desired_poses[circle, :3], result.actual_poses[circle, :3]


def _magnified(desired: np.ndarray, actual: np.ndarray, centre: np.ndarray, gain: float) -> np.ndarray:
    return desired[:, :2] - centre[:2] + gain * (actual[:, :2] - desired[:, :2])


def _closed_curve(ax, x: np.ndarray, y: np.ndarray, style: RunStyle, index: int, n_runs: int) -> None:
    """A run's closed curve through ``(x, y)``, its markers a few and spread (:func:`_markevery`)."""
    ax.plot(
        np.append(x, x[0]),
        np.append(y, y[0]),
        lw=1.1,
        ms=4.0,
        markevery=_markevery(index, n_runs, len(x)),
        **style.line(),
    )


def fig8(reproduction: Reproduction):
    """The circle in its plane (x, y about its centre) as run, deviations magnified: first
    before calibration at the first stage, then every calibrated run per stage."""
    stages, first = reproduction.stage_names, reproduction.stage_names[0]
    styles, runs = run_styles(reproduction.parts), reproduction.calibrated
    deviations = [
        np.linalg.norm(np.subtract(*_circle_points(reproduction, run, stage)), axis=1).max()
        for run in runs
        for stage in stages
    ]
    desired0, actual0 = _circle_points(reproduction, NOMINAL, first)
    centre = desired0.mean(axis=0)
    radius = float(np.linalg.norm(desired0[:, :2] - centre[:2], axis=1).mean())
    gain = CIRCLE_DEVIATION_SHARE * radius / max(deviations)
    nominal_gain = CIRCLE_DEVIATION_SHARE * radius / np.linalg.norm(actual0 - desired0, axis=1).max()
    fig = new_figure(4.0 * (len(stages) + 1) + 2.0, 4.4)
    axes = fig.subplots(1, len(stages) + 1, sharey=True)
    panels = [(axes[0], first, [NOMINAL], nominal_gain, f"before calibration, {first}")]
    panels += [(ax, stage, runs, gain, stage) for ax, stage in zip(axes[1:], stages, strict=True)]
    for ax, stage, panel_runs, panel_gain, title in panels:
        desired, _ = _circle_points(reproduction, NOMINAL, stage)
        ring = desired[:, :2] - centre[:2]
        ax.plot(*np.vstack([ring, ring[:1]]).T, color="0.8", lw=3.0, label="desired")
        for index, run in enumerate(panel_runs):
            xy = _magnified(*_circle_points(reproduction, run, stage), centre, panel_gain)
            _closed_curve(ax, xy[:, 0], xy[:, 1], styles[run], index, len(panel_runs))
        ax.set_title(f"{title} (deviation ×{panel_gain:.0f})", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x − centre [mm]", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("y − centre [mm]", fontsize=8)
    _legend(fig, axes[:2])
    fig.suptitle(
        "Fig. 8 — the circle trajectory as run (truth view), deviation from the desired circle magnified", fontsize=10
    )
    return fig


def fig9(reproduction: Reproduction):
    """Position deviation around the circle, polar (angle: where on the circle), log radius."""
    stages, styles = reproduction.stage_names, run_styles(reproduction.parts)
    fig = new_figure(4.2 * len(stages) + 2.0, 4.6)
    axes = fig.subplots(1, len(stages), subplot_kw={"projection": "polar"})
    axes = np.atleast_1d(axes)
    lowest, highest = np.inf, 0.0
    for ax, stage in zip(axes, stages, strict=True):
        runs = [NOMINAL, *reproduction.calibrated] if stage == stages[0] else reproduction.calibrated
        for index, run in enumerate(runs):
            desired, actual = _circle_points(reproduction, run, stage)
            centre = desired.mean(axis=0)
            angle = np.unwrap(np.arctan2(desired[:, 1] - centre[1], desired[:, 0] - centre[0]))
            deviation = np.linalg.norm(actual - desired, axis=1)
            lowest, highest = min(lowest, deviation.min()), max(highest, deviation.max())
            _closed_curve(ax, angle, deviation, styles[run], index, len(runs))
        ax.set_title(stage, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes:
        ax.set_rscale("log")
        ax.set_rlim(10 ** np.floor(np.log10(lowest)), 10 ** np.ceil(np.log10(highest)))
    _legend(fig, axes[:1])
    fig.suptitle("Fig. 9 — position deviation around the circle [mm, log radius] (truth view)", fontsize=10)
    return fig


class FigureFile(NamedTuple):
    """A figure file written: its name, its caption and, for Figs. 5–6, the run it shows."""

    name: str
    caption: str
    run: str | None = None
    style: RunStyle | None = None


def _run_figures(
    drive: LegGeometry, style: RunStyle, run: str, method_run: MethodRun
) -> list[tuple[str, str, Callable[[], Figure]]]:
    """Figs. 5–6 of ``run``: ``(file name, caption, how to draw it)``."""
    return [
        (
            f"fig5_{run}.png",
            f"Fig. 5 — {style.label}: parameter convergence at no load",
            partial(fig5, drive, style, method_run),
        ),
        (
            f"fig6_{run}.png",
            f"Fig. 6 — {style.label}: parameters through the load stages",
            partial(fig6, drive, style, method_run),
        ),
    ]


def figures(reproduction: Reproduction) -> list[tuple[str, str, Callable[[], Figure]]]:
    """``(file name, caption, how to draw it)`` of every figure, in the order of the page: Figs.
    5–6 of each calibrated run, then Figs. 7–9."""
    drive, styles = reproduction.platform.prismatic_drive("the paper's figures"), run_styles(reproduction.parts)
    return [
        *(
            figure
            for run in reproduction.calibrated
            for figure in _run_figures(drive, styles[run], run, reproduction.runs[run])
        ),
        ("fig7_pose_errors.png", "Fig. 7 — pose errors before and after calibration", lambda: fig7(reproduction)),
        ("fig8_circle.png", "Fig. 8 — the circle trajectory", lambda: fig8(reproduction)),
        ("fig9_polar.png", "Fig. 9 — the circle's deviation, polar", lambda: fig9(reproduction)),
    ]


def _hand_laid_figure(width_in: float, height_in: float) -> Figure:
    """A figure whose panels sit at margins given in inches: a constrained layout of Figs. 5–6's
    42 panels costs more than drawing them, and finds the same margins every time."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in))


def _png(figure: Figure) -> bytes:
    """The figure as PNG at :data:`PNG_DPI`, its layout as it is (constrained, or by hand: a tight
    box on top would draw it twice)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(figure)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=PNG_DPI)
    return buffer.getvalue()


@dataclass(frozen=True)
class RunFigures:
    """Figs. 5–6 of a run, drawn as soon as it is done where it ran (:func:`~.runs.reproduce`'s
    ``draw``: in its worker process, while the other runs go on). They need that run alone; drawn
    one by one in the parent after every run, the sixteen figures would leave a core idle for
    most of the reproduction's figure time. Figs. 7–9 compare every run: :func:`draw_in` draws
    them in the same processes after."""

    drive: LegGeometry
    styles: dict[str, RunStyle]

    @classmethod
    def of(cls, drive: LegGeometry, parts: tuple[Part, ...]) -> RunFigures:
        return cls(drive, run_styles(parts))

    def __call__(self, run: str, method_run: MethodRun) -> dict[str, bytes]:
        return {name: _png(draw()) for name, _, draw in _run_figures(self.drive, self.styles[run], run, method_run)}


def draw_figure(reproduction: Reproduction, name: str) -> bytes:
    """The PNG of the figure file ``name`` of :func:`figures`."""
    return _png(next(draw for file, _, draw in figures(reproduction) if file == name)())


def draw_in(pool: WorkerPool, reproduction: Reproduction) -> dict[str, concurrent.futures.Future]:
    """The figures the runs did not draw (Figs. 7–9: they compare every run) drawn in ``pool``'s
    processes, a figure a process, while the caller goes on: PNG futures by file name (in the
    parent they would be ~5 s of CPU after every run, with the other core idle)."""
    undrawn = [name for name, _, _ in figures(reproduction) if name not in reproduction.drawn]
    return {name: pool.executor.submit(draw_figure, reproduction, name) for name in undrawn}


def write_figures(directory: str | Path, reproduction: Reproduction, bar=None) -> list[FigureFile]:
    """Every figure into ``directory`` (each file atomically; those the runs drew,
    :attr:`~.runs.Reproduction.drawn`, as they were drawn), in the order of :func:`figures`.
    ``bar``, if given, is ticked once per figure."""
    directory, styles = Path(directory), run_styles(reproduction.parts)
    runs = {name: run for run in reproduction.calibrated for name in (f"fig5_{run}.png", f"fig6_{run}.png")}
    written = []
    for name, caption, draw in figures(reproduction):
        drawn = reproduction.drawn.get(name)
        atomic_write_bytes(directory / name, _png(draw()) if drawn is None else drawn)
        run = runs.get(name)
        written.append(FigureFile(name, caption, run, None if run is None else styles[run]))
        if bar is not None:
            bar.update()
    return written
