"""The paper's figures (Ren et al. Figs. 5–9) as PNG files beside tables.md.

* ``fig5_<run>.png`` — δM of one online run through the no-load stage, one panel per parameter (a
  row per kind, a column per leg), each with its ±σ band and the truth in force (dashed): the
  convergence of Fig. 5;
* ``fig6_<run>.png`` — the same through every load stage, the stages' starts marked (Fig. 6);
* ``fig7_pose_errors.png`` — the true pose error at each validation pose, before calibration and
  with every run, per stage (Fig. 7);
* ``fig8_circle.png`` — the circle as run, its deviation from the desired circle magnified (Fig. 8);
* ``fig9_polar.png`` — the deviation around the circle in polar form, per stage (Fig. 9).

Figs. 5–6 are drawn for ``paper-ekf`` (the paper's method) and, with every part of its model, for
each method held to the paper's headline improvements (:data:`~.report.TARGET_METHODS`). Pose errors
are of the truth view (the verdict's); one value per held
pose as in the tables (:mod:`.metrics`).
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..io import atomic_write_bytes
from ..model.platform import PARAMETER_FIELDS, LegGeometry
from ..viz.html_report import new_figure, png_bytes
from .metrics import held_pose_ends, view_errors
from .report import TARGET_METHODS, VERDICT_VIEW
from .runs import NOMINAL, MethodRun, Part, Reproduction, WorkerPool, fullest_run

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: one colour per estimator; the runs of one estimator differ by line style (and marker, Fig. 7).
METHOD_COLORS = {NOMINAL: "0.45", "ls": "#d62728", "paper-ekf": "#ff7f0e", "ekf": "#1f77b4", "isam2": "#2ca02c"}
#: a run with every part of its model solid, one part fewer dashed, two fewer dotted, …
LINESTYLES = ("-", "--", ":", "-.")
#: Fig. 7's markers in the same order, so that a run reads apart where its lines overlap
MARKERS = ("o", "^", "s", "D")
#: one colour per parameter of a leg (δj_x … δl), as the recording's parameter tabs.
PARAMETER_COLORS = ("#e41a1c", "#377eb8", "#4daf4a", "#984ea3", "#ff7f00", "#a65628", "#1e1e1e")
#: the method of the paper, drawn in Figs. 5–6 beside the methods held to its headline improvements.
PAPER_METHOD = "paper-ekf"
#: Fig. 8 magnifies the calibrated runs' deviation so that the largest is this fraction of the radius.
CIRCLE_DEVIATION_SHARE = 0.25


def parameter_runs(parts: tuple[Part, ...]) -> list[str]:
    """The runs of Figs. 5–6 of a reproduction with ``parts``."""
    return [PAPER_METHOD, *(fullest_run(method, parts) for method in TARGET_METHODS)]


def _style(reproduction: Reproduction, run: str) -> dict:
    """Colour by the run's estimator, line style and marker by how many parts of the model it lacks
    against that estimator's fullest run (the runs of one estimator come rigid first, then a part
    more each: :func:`.runs.online_runs`), so that every run of a figure has a style of its own."""
    method = reproduction.runs[run].method
    siblings = [name for name, method_run in reproduction.runs.items() if method_run.method == method]
    fewer = len(siblings) - 1 - siblings.index(run)
    return {
        "color": METHOD_COLORS.get(method, "0.3"),
        "linestyle": LINESTYLES[fewer % len(LINESTYLES)],
        "marker": MARKERS[fewer % len(MARKERS)],
        "label": run,
    }


def _line_style(reproduction: Reproduction, run: str) -> dict:
    """:func:`_style` without the marker: the circles of Figs. 8–9 are lines of many points."""
    style = _style(reproduction, run)
    del style["marker"]
    return style


def _parameter_figure(drive: LegGeometry, method_run: MethodRun, rows: np.ndarray, title: str):
    """One panel per parameter — a row per kind (δj_x … δl), a column per leg — with δM of
    ``method_run`` at ``rows``, its ±σ band and its truth (dashed): in force, or unloaded for a run
    whose model carries the sag. One band a panel: seven overlapping bands in one leg's panel hide
    each other, and the kinds differ in scale (δl moves by millimetres where δd_z moves by tenths)."""
    result = method_run.result
    nominal = drive.as_vector()
    t = result.log.t_s[rows]
    # an elastic model's δM is the unloaded drive: its truth is the robot's, not the one in force
    truth = (
        np.broadcast_to(result.robot.base_params, (len(rows), nominal.size)) - nominal
        if method_run.unloaded
        else result.truth.params[rows] - nominal
    )
    kinds = len(PARAMETER_FIELDS)
    fig = new_figure(2.1 * drive.n_legs + 0.8, 1.25 * kinds + 0.9)
    axes = fig.subplots(kinds, drive.n_legs, sharex=True, sharey="row", squeeze=False)
    for leg in range(drive.n_legs):
        for k in range(kinds):
            ax, col, color = axes[k, leg], kinds * leg + k, PARAMETER_COLORS[k]
            estimate = method_run.trace[rows, col]
            if method_run.stddev is not None:  # σ is kept at every parameter_stride-th sample
                kept = np.isfinite(method_run.stddev[rows, col])
                sigma = method_run.stddev[rows, col][kept]
                ax.fill_between(
                    t[kept], estimate[kept] - sigma, estimate[kept] + sigma, color=color, alpha=0.25, lw=0, label="± σ"
                )
            ax.plot(t, estimate, color=color, lw=1.0, label="estimate")
            ax.plot(t, truth[:, col], color="0.2", lw=0.8, ls="--", label="truth")
            ax.grid(alpha=0.3)
            ax.tick_params(labelsize=6)
        axes[0, leg].set_title(f"leg {leg + 1}", fontsize=9)
        axes[-1, leg].set_xlabel("t [s]", fontsize=8)
    for k, field in enumerate(PARAMETER_FIELDS):
        axes[k, 0].set_ylabel(f"δ{field} [mm]", fontsize=8)
    # the legend in grey: each row has its own colour, the legend says what the three marks are
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Patch(color="0.5", alpha=0.35),
        Line2D([], [], color="0.35", lw=1.0),
        Line2D([], [], color="0.2", lw=0.8, ls="--"),
    ]
    labels = ["± σ" if method_run.stddev is not None else "", "estimate", "truth"]
    keep = [k for k, label in enumerate(labels) if label]
    fig.legend([handles[k] for k in keep], [labels[k] for k in keep], loc="outside right center", fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig


def _stage_starts(result) -> list[tuple[float, str]]:
    names = list(dict.fromkeys(result.stages))
    return [(float(result.log.t_s[np.flatnonzero(result.stages == name)[0]]), name) for name in names]


def fig5(drive: LegGeometry, run: str, method_run: MethodRun):
    result = method_run.result
    rows = np.flatnonzero(result.stages == result.stages[0])
    return _parameter_figure(
        drive,
        method_run,
        rows,
        f"Fig. 5 — {run}: parameter errors through the {result.stages[0]} stage (calibration, validation, circle)",
    )


def fig6(drive: LegGeometry, run: str, method_run: MethodRun):
    result = method_run.result
    fig = _parameter_figure(
        drive, method_run, np.arange(len(result.log)), f"Fig. 6 — {run}: parameter errors through the load stages"
    )
    top_row = [ax for ax in fig.axes if ax.get_subplotspec().is_first_row()]
    for ax in fig.axes:
        for start, name in _stage_starts(result)[1:]:
            ax.axvline(start, color="0.3", lw=0.8, ls=":")
            if ax in top_row:  # the stage's name once a column, not in each of its panels
                ax.text(start, 1.0, f" {name}", transform=ax.get_xaxis_transform(), fontsize=7, va="top", color="0.3")
    return fig


def fig7(reproduction: Reproduction):
    """True pose error at each validation pose, per stage: before calibration and every run."""
    stages = reproduction.stage_names
    fig = new_figure(4.2 * len(stages) + 1.6, 6.0)
    axes = fig.subplots(2, len(stages), sharey="row", squeeze=False)
    for run in (NOMINAL, *reproduction.calibrated):
        result = reproduction.runs[run].result
        position, orientation = view_errors(result, reproduction.platform)[VERDICT_VIEW]
        ends = held_pose_ends(result) & (result.kinds == "validation")
        style = _style(reproduction, run)
        if run == NOMINAL:
            style["label"] = "before calibration"
        for column, stage in enumerate(stages):
            mask = ends & (result.stages == stage)
            for row, values in enumerate((position, orientation)):
                axes[row, column].plot(values[mask], ms=3.0, lw=0.9, **style)
    for column, stage in enumerate(stages):
        axes[0, column].set_title(stage, fontsize=9)
        axes[1, column].set_xlabel("validation pose", fontsize=8)
    axes[0, 0].set_ylabel("position error [mm]", fontsize=8)
    axes[1, 0].set_ylabel("orientation error [°]", fontsize=8)
    for ax in axes.ravel():
        ax.set_yscale("log")
        ax.grid(alpha=0.3, which="both")
        ax.tick_params(labelsize=7)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle("Fig. 7 — pose error at the validation poses before and after calibration (truth view)", fontsize=10)
    return fig


def _circle_points(reproduction: Reproduction, run: str, stage: str) -> tuple[np.ndarray, np.ndarray]:
    """``(desired, actual)`` circle positions ``(n, 3)`` [mm] of ``run`` in ``stage``."""
    result = reproduction.runs[run].result
    circle = (result.stages == stage) & (result.kinds == "circle")
    return result.desired_poses[circle, :3], result.actual_poses[circle, :3]


def _magnified(desired: np.ndarray, actual: np.ndarray, centre: np.ndarray, gain: float) -> np.ndarray:
    return desired[:, :2] - centre[:2] + gain * (actual[:, :2] - desired[:, :2])


def fig8(reproduction: Reproduction):
    """The circle in its plane (x, y about its centre) as run, deviations magnified: first
    before calibration at the first stage, then every calibrated run per stage."""
    stages, first = reproduction.stage_names, reproduction.stage_names[0]
    runs = reproduction.calibrated
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
    fig = new_figure(4.0 * (len(stages) + 1) + 1.6, 4.4)
    axes = fig.subplots(1, len(stages) + 1, sharey=True)
    panels = [(axes[0], first, [NOMINAL], nominal_gain, f"before calibration, {first}")]
    panels += [(ax, stage, runs, gain, stage) for ax, stage in zip(axes[1:], stages, strict=True)]
    for ax, stage, panel_runs, panel_gain, title in panels:
        desired, _ = _circle_points(reproduction, NOMINAL, stage)
        ring = desired[:, :2] - centre[:2]
        ax.plot(*np.vstack([ring, ring[:1]]).T, color="0.75", lw=3.0, label="desired")
        for run in panel_runs:
            d, a = _circle_points(reproduction, run, stage)
            xy = _magnified(d, a, centre, panel_gain)
            style = _line_style(reproduction, run)
            if run == NOMINAL:
                style["label"] = "before calibration"
            ax.plot(*np.vstack([xy, xy[:1]]).T, lw=1.0, **style)
        ax.set_title(f"{title} (deviation ×{panel_gain:.0f})", fontsize=9)
        ax.set_aspect("equal")
        ax.set_xlabel("x − centre [mm]", fontsize=8)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("y − centre [mm]", fontsize=8)
    handles, labels = [], []
    for ax in axes[:2]:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle(
        "Fig. 8 — the circle trajectory as run (truth view), deviation from the desired circle magnified", fontsize=10
    )
    return fig


def fig9(reproduction: Reproduction):
    """Position deviation around the circle, polar (angle: where on the circle), log radius."""
    stages = reproduction.stage_names
    fig = new_figure(4.2 * len(stages) + 1.6, 4.6)
    axes = fig.subplots(1, len(stages), subplot_kw={"projection": "polar"})
    axes = np.atleast_1d(axes)
    lowest, highest = np.inf, 0.0
    for ax, stage in zip(axes, stages, strict=True):
        for run in (NOMINAL, *reproduction.calibrated) if stage == stages[0] else reproduction.calibrated:
            desired, actual = _circle_points(reproduction, run, stage)
            centre = desired.mean(axis=0)
            angle = np.unwrap(np.arctan2(desired[:, 1] - centre[1], desired[:, 0] - centre[0]))
            deviation = np.linalg.norm(actual - desired, axis=1)
            lowest, highest = min(lowest, deviation.min()), max(highest, deviation.max())
            style = _line_style(reproduction, run)
            if run == NOMINAL:
                style["label"] = "before calibration"
            ax.plot(np.append(angle, angle[0]), np.append(deviation, deviation[0]), lw=1.0, **style)
        ax.set_title(stage, fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in axes:
        ax.set_rscale("log")
        ax.set_rlim(10 ** np.floor(np.log10(lowest)), 10 ** np.ceil(np.log10(highest)))
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", fontsize=8)
    fig.suptitle("Fig. 9 — position deviation around the circle [mm, log radius] (truth view)", fontsize=10)
    return fig


def _fig5(drive: LegGeometry, run: str, method_run: MethodRun) -> tuple[str, str, Callable[[], Figure]]:
    return f"fig5_{run}.png", f"Fig. 5 — {run}: parameter convergence at no load", partial(fig5, drive, run, method_run)


def _fig6(drive: LegGeometry, run: str, method_run: MethodRun) -> tuple[str, str, Callable[[], Figure]]:
    return (
        f"fig6_{run}.png",
        f"Fig. 6 — {run}: parameters through the load stages",
        partial(fig6, drive, run, method_run),
    )


def figures(reproduction: Reproduction) -> list[tuple[str, str, Callable[[], Figure]]]:
    """``(file name, caption, how to draw it)`` of every figure, in the order of the page."""
    drive, runs = reproduction.platform.prismatic_drive("the paper's figures"), reproduction.runs
    named = parameter_runs(reproduction.parts)
    return [
        *(_fig5(drive, run, runs[run]) for run in named),
        *(_fig6(drive, run, runs[run]) for run in named),
        ("fig7_pose_errors.png", "Fig. 7 — pose errors before and after calibration", lambda: fig7(reproduction)),
        ("fig8_circle.png", "Fig. 8 — the circle trajectory", lambda: fig8(reproduction)),
        ("fig9_polar.png", "Fig. 9 — the circle's deviation, polar", lambda: fig9(reproduction)),
    ]


def _png(figure: Figure) -> bytes:
    return png_bytes(figure, dpi=100)


@dataclass(frozen=True)
class RunFigures:
    """Figs. 5–6 of a run, drawn as soon as it is done where it ran (:func:`~.runs.reproduce`'s
    ``draw``: in its worker process, while the other runs go on). They need that run alone; drawn
    one by one in the parent after every run, the nine figures would take ~10 s of a ~40 s
    reproduction with a core idle. Figs. 7–9 compare every run: :func:`draw_in` draws them in the
    same processes after."""

    drive: LegGeometry
    runs: tuple[str, ...]

    @classmethod
    def of(cls, drive: LegGeometry, parts: tuple[Part, ...]) -> RunFigures:
        return cls(drive, tuple(parameter_runs(parts)))

    def __call__(self, run: str, method_run: MethodRun) -> dict[str, bytes]:
        if run not in self.runs:
            return {}
        return {
            name: _png(draw())
            for name, _, draw in (_fig5(self.drive, run, method_run), _fig6(self.drive, run, method_run))
        }


def draw_figure(reproduction: Reproduction, name: str) -> bytes:
    """The PNG of the figure file ``name`` of :func:`figures`."""
    return _png(next(draw for file, _, draw in figures(reproduction) if file == name)())


def draw_in(pool: WorkerPool, reproduction: Reproduction) -> dict[str, concurrent.futures.Future]:
    """The figures the runs did not draw (Figs. 7–9: they compare every run) drawn in ``pool``'s
    processes, a figure a process, while the caller goes on: PNG futures by file name (in the
    parent they would be ~5 s of CPU after every run, with the other core idle)."""
    undrawn = [name for name, _, _ in figures(reproduction) if name not in reproduction.drawn]
    return {name: pool.executor.submit(draw_figure, reproduction, name) for name in undrawn}


def write_figures(directory: str | Path, reproduction: Reproduction, bar=None) -> list[tuple[str, str]]:
    """Every figure into ``directory`` (each file atomically; those the runs drew,
    :attr:`~.runs.Reproduction.drawn`, as they were drawn); ``(file name, caption)`` in order.
    ``bar``, if given, is ticked once per figure."""
    directory = Path(directory)
    written = []
    for name, caption, draw in figures(reproduction):
        drawn = reproduction.drawn.get(name)
        atomic_write_bytes(directory / name, _png(draw()) if drawn is None else drawn)
        written.append((name, caption))
        if bar is not None:
            bar.update()
    return written
