"""A calibration as one self-contained static HTML page (spec §8: ``calibrate --report DIR``,
``validate --report DIR``): matplotlib figures inlined as PNG data, no script, no server, no network.

The page shows what a user acts on: the residuals per measured channel before and after the
calibration (RMS and over time), the parameter errors δM with ±σ, their correlation matrix, the
conditioning with the weakest directions in named parameters, the held-out errors where the
calibration was validated, and the config and versions that produced it. The input is the result
dict (spec §5 with the optional fields of §8) plus the series to plot; the caller writes the text.
"""

from __future__ import annotations

import base64
import html
import io as bytes_io
import json
from dataclasses import dataclass
from importlib import metadata

import numpy as np

from ..errors import number
from ..model.drive import COMPLIANCE, STROKE_SCALE, THERMAL

#: libraries whose versions the page lists (the calibration's own comes from the result).
LIBRARIES = ("numpy", "scipy", "gtsam", "matplotlib")
#: |correlation| above which a pair of parameters is listed as strongly correlated.
STRONG_CORRELATION = 0.9
#: at most this many samples per residual curve (evenly strided; the RMS uses every sample).
MAX_PLOTTED_SAMPLES = 5000


@dataclass(frozen=True)
class Residuals:
    """Measured minus predicted, per measured channel (file units: mm, deg).

    Attributes:
        channels: column names of the log, e.g. ``s1_mm`` … ``s6_mm`` or ``mx_mm`` … ``myaw_deg``.
        t_s: ``(N,)`` sample times [s].
        before: ``(N, m)`` with the nominal model.
        after: ``(N, m)`` with the calibrated model.
        log: which log they are of, for the page's text.
        before_model: what "before" predicted with, for the page's text.
    """

    channels: tuple[str, ...]
    t_s: np.ndarray
    before: np.ndarray
    after: np.ndarray
    log: str = "the calibration log"
    before_model: str = "the nominal platform"


@dataclass(frozen=True)
class HeldOut:
    """Prediction errors of a held-out log (``validate``).

    Attributes:
        log: the held-out log's name.
        t_s: ``(N,)`` [s].
        position_error_mm: ``(N,)``.
        orientation_error_deg: ``(N,)`` or None (points instruments).
        registered: the instrument frame was fitted again on this log.
    """

    log: str
    t_s: np.ndarray
    position_error_mm: np.ndarray
    orientation_error_deg: np.ndarray | None
    registered: bool = False


@dataclass(frozen=True)
class LegForces:
    """An elastic drive's axial leg forces over a log (spec §10), at the calibrated model's settled poses.

    Attributes:
        t_s: ``(N,)`` [s].
        forces_N: ``(N, legs)`` [N], compression > 0.
        compliance_mm_per_kN: ``(legs,)`` the model's c_i: identified, or ``[elastic]``'s held value.
    """

    t_s: np.ndarray
    forces_N: np.ndarray
    compliance_mm_per_kN: np.ndarray


@dataclass(frozen=True)
class LegTemperatures:
    """A thermal drive's legs over a log (spec §17).

    Attributes:
        t_s: ``(N,)`` [s].
        temperatures_C: ``(N, legs)`` each leg's temperature [°C].
        growth_um: ``(N, legs)`` what each leg grew by at it, ``α_i (T_i − T_ref) L_i`` [µm], with the
            model's α (identified, or ``[thermal]``'s held value).
    """

    t_s: np.ndarray
    temperatures_C: np.ndarray
    growth_um: np.ndarray


@dataclass(frozen=True)
class Robot:
    """The drive drawn at one pose, nominal and calibrated (:func:`~stewart_calib.viz.geometry.robot_at`).

    Attributes:
        kind: the drive's leg kind (``prismatic``, ``rotary``: its legs drawn crank → horn → rod).
        pose: what the pose is, for the page's text (e.g. ``the workspace's home``).
        nominal: ``(L, k, 3)`` each nominal leg's polyline in {J} [mm]
            (:func:`~stewart_calib.viz.geometry.leg_polylines`).
        calibrated: ``(L, k, 3)`` the calibrated legs' at the same pose.
        parameter_degrees: ``(n_params,)`` True where the result gives the parameter in degrees
            (a servo's zero offset and axis tilts, spec §15).
    """

    kind: str
    pose: str
    nominal: np.ndarray
    calibrated: np.ndarray
    parameter_degrees: np.ndarray


def rms(values: np.ndarray, axis=0) -> np.ndarray:
    """Root mean square ignoring NaN (a target not seen in a row)."""
    return np.sqrt(np.nanmean(np.square(values), axis=axis))


def channel_unit(channel: str) -> str:
    return "deg" if channel.endswith("_deg") else "mm"


# ----------------------------------------------------------------------------- figures


def png_bytes(figure, dpi: int = 110) -> bytes:
    """The figure as PNG, rendered by the Agg canvas (no display, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(figure)
    buffer = bytes_io.BytesIO()
    # a constrained layout already fits everything inside the figure; a tight box on top would draw it twice
    tight = None if figure.get_layout_engine() is not None else "tight"
    figure.savefig(buffer, format="png", dpi=dpi, bbox_inches=tight)
    return buffer.getvalue()


def _png(figure) -> str:
    """The figure as an inline ``<img>``."""
    data = base64.b64encode(png_bytes(figure)).decode("ascii")
    return f'<img alt="" src="data:image/png;base64,{data}">'


def new_figure(width_in: float, height_in: float):
    """A matplotlib figure with constrained layout, outside pyplot (nothing global, no display)."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def residual_rms_figure(residuals: Residuals) -> str:
    fig = new_figure(8.0, 2.8)
    units = sorted({channel_unit(c) for c in residuals.channels})
    axes = fig.subplots(1, len(units), squeeze=False)[0]
    for ax, unit in zip(axes, units, strict=True):
        idx = [k for k, c in enumerate(residuals.channels) if channel_unit(c) == unit]
        x = np.arange(len(idx))
        ax.bar(x - 0.2, rms(residuals.before[:, idx]), 0.4, label="before (nominal)", color="#c44e52")
        ax.bar(x + 0.2, rms(residuals.after[:, idx]), 0.4, label="after (calibrated)", color="#4c72b0")
        ax.set_xticks(x, [residuals.channels[k] for k in idx], rotation=45, ha="right", fontsize=8)
        ax.set_yscale("log")
        ax.set_ylabel(f"RMS residual [{unit}]")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    return _png(fig)


#: times beyond this many seconds (a clock's epoch) are drawn from the log's first, named in the label
TIME_ORIGIN_S = 1e4


def time_axis(t_s: np.ndarray) -> tuple[np.ndarray, str]:
    """A plot's times and their label: from the log's first where they are a clock's epoch
    (:data:`TIME_ORIGIN_S`), which a plot would otherwise print as an offset of some 1.7e9 s (a Unix time)."""
    t = np.asarray(t_s, dtype=float)
    if len(t) and abs(t[0]) > TIME_ORIGIN_S:
        return t - t[0], f"t − {number(t[0])} s [s]"
    return t, "t [s]"


def residual_series(residuals: Residuals) -> tuple[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """What :func:`residual_time_figure` draws: the time axis' label and, per channel, ``(t, before,
    after)`` at the rows that read it (a points log's row holds one target: a line through every
    row would be broken at each other target's row and draw nothing), at most
    :data:`MAX_PLOTTED_SAMPLES` of them; times from the log's first where they are a clock's epoch."""
    t, label = time_axis(residuals.t_s)
    series = []
    for k in range(len(residuals.channels)):
        rows = np.flatnonzero(np.isfinite(residuals.before[:, k]) | np.isfinite(residuals.after[:, k]))
        rows = rows[:: max(1, len(rows) // MAX_PLOTTED_SAMPLES)]
        series.append((t[rows], residuals.before[rows, k], residuals.after[rows, k]))
    return label, series


def residual_time_figure(residuals: Residuals) -> str:
    m = len(residuals.channels)
    cols = 3 if m > 4 else m
    rows = -(-m // cols)
    fig = new_figure(9.0, 1.9 * rows + 0.4)
    axes = np.atleast_1d(fig.subplots(rows, cols, sharex=True, squeeze=False)).ravel()
    label, series = residual_series(residuals)
    for k, (channel, (t, before, after)) in enumerate(zip(residuals.channels, series, strict=True)):
        ax = axes[k]
        ax.plot(t, before, lw=0.7, color="#c44e52", alpha=0.6, label="before")
        ax.plot(t, after, lw=0.7, color="#4c72b0", label="after")
        ax.set_title(channel, fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes[m:]:
        ax.set_visible(False)
    for ax in axes[-cols:]:
        ax.set_xlabel(label, fontsize=8)
    axes[0].legend(fontsize=7)
    return _png(fig)


def parameter_figure(
    names: list[str], error: np.ndarray, stddev: np.ndarray | None, degrees: np.ndarray | None = None
) -> str:
    """δM ± σ per parameter; with ``degrees`` (True: the entry is an angle [deg]) one panel per unit."""
    degrees = np.zeros(len(names), dtype=bool) if degrees is None else np.asarray(degrees, dtype=bool)
    panels = [(unit, np.flatnonzero(degrees == (unit == "deg"))) for unit in ("mm", "deg")]
    panels = [(unit, idx) for unit, idx in panels if len(idx)]
    fig = new_figure(10.0, 3.0 * len(panels))
    for ax, (unit, idx) in zip(fig.subplots(len(panels), 1, squeeze=False)[:, 0], panels, strict=True):
        x = np.arange(len(idx))
        ax.axhline(0.0, color="0.6", lw=0.8)
        if stddev is not None:
            ax.errorbar(
                x,
                error[idx],
                yerr=stddev[idx],
                fmt="o",
                ms=3,
                capsize=2,
                color="#4c72b0",
                ecolor="#8fa8d8",
                label="δM ± σ",
            )
        else:
            ax.plot(x, error[idx], "o", ms=3, color="#4c72b0", label="δM (no covariance)")
        ax.set_xticks(x, [names[k] for k in idx], rotation=90, fontsize=7)
        ax.set_xlim(-0.7, len(idx) - 0.3)
        ax.set_ylabel(f"parameter error δM [{unit}]")
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=8)
    return _png(fig)


#: the report's drawing: (the leg's segment, its colour) — a rotary leg's horn, then its rod
_SEGMENT_COLORS = {"prismatic": (("leg", "#dd8452"),), "rotary": (("horn", "#c44e52"), ("rod", "#dd8452"))}


def robot_figure(robot: Robot) -> str:
    """The robot from above (x–y) and from the side (x–z): the calibrated legs in colour (a rotary
    leg's horn and rod apart), the nominal ones thin and grey, each platform's outline through its joints."""
    fig = new_figure(9.0, 4.2)
    axes = fig.subplots(1, 2)
    segments = _SEGMENT_COLORS.get(robot.kind, _SEGMENT_COLORS["prismatic"])
    for ax, (i, j, view) in zip(axes, ((0, 1, "from above"), (0, 2, "from the side")), strict=True):
        for polylines, calibrated in ((robot.nominal, False), (robot.calibrated, True)):
            for k, (segment, color) in enumerate(segments):
                ends = polylines[:, k : k + 2]
                for leg, (a, b) in enumerate(ends):
                    label = f"{segment}s {'calibrated' if calibrated else 'nominal'}" if leg == 0 else None
                    style = {"color": color, "lw": 2.2} if calibrated else {"color": "0.6", "lw": 0.8, "ls": "--"}
                    ax.plot([a[i], b[i]], [a[j], b[j]], label=label, **style)
            joints = polylines[:, -1]
            order = np.argsort(np.arctan2(joints[:, 1], joints[:, 0]))
            outline = joints[np.r_[order, order[:1]]]
            ax.plot(
                outline[:, i], outline[:, j], color="#4c72b0" if calibrated else "0.7", lw=1.2 if calibrated else 0.6
            )
            ax.plot(polylines[:, 0, i], polylines[:, 0, j], "o", ms=3, color="k" if calibrated else "0.6")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(f"{'xyz'[i]} [mm]")
        ax.set_ylabel(f"{'xyz'[j]} [mm]")
        ax.set_title(view, fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper right")
    return _png(fig)


def correlation_matrix(covariance: np.ndarray) -> np.ndarray:
    """``C_ij / (σ_i σ_j)``; a parameter with zero variance correlates with nothing (0)."""
    sigma = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    scale = np.outer(sigma, sigma)
    return np.divide(covariance, scale, out=np.zeros_like(covariance), where=scale > 0)


def correlation_figure(names: list[str], correlation: np.ndarray) -> str:
    fig = new_figure(7.0, 6.2)
    ax = fig.subplots()
    image = ax.imshow(correlation, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    ticks = np.arange(len(names))
    ax.set_xticks(ticks, names, rotation=90, fontsize=6)
    ax.set_yticks(ticks, names, fontsize=6)
    fig.colorbar(image, ax=ax, shrink=0.8, label="correlation")
    return _png(fig)


def held_out_figure(held: HeldOut) -> str:
    fig = new_figure(9.0, 2.6)
    panels = [("position error [mm]", held.position_error_mm)]
    if held.orientation_error_deg is not None:
        panels.append(("orientation error [deg]", held.orientation_error_deg))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, (label, values) in zip(axes, panels, strict=True):
        t, t_label = time_axis(held.t_s)
        ax.plot(t, values, lw=0.7, color="#55a868")
        ax.set_xlabel(t_label)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    return _png(fig)


# ----------------------------------------------------------------------------- page


def html_table(header: list[str] | None, rows: list[list], cls: str = "") -> str:
    """A ``<table>`` of escaped cells; ``header`` None for none, ``cls`` its class (``num``: numbers right-aligned)."""
    head = (
        ""
        if header is None
        else "<thead><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in header) + "</tr></thead>"
    )
    body = "".join("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}">{head}<tbody>{body}</tbody></table>'


def _fmt(value: float | None, digits: int = 4) -> str:
    return "—" if value is None or not np.isfinite(value) else f"{value:.{digits}g}"


def library_versions() -> dict[str, str]:
    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _residual_section(residuals: Residuals) -> str:
    before, after = rms(residuals.before), rms(residuals.after)
    rows = [
        [c, channel_unit(c), _fmt(b), _fmt(a), _fmt(a / b if b > 0 else np.nan, 3)]
        for c, b, a in zip(residuals.channels, before, after, strict=True)
    ]
    return (
        "<h2>Residuals per measured channel</h2>"
        f"<p>Measured minus predicted by the model, over {html.escape(residuals.log)} "
        f"({len(residuals.t_s)} samples): before = {html.escape(residuals.before_model)}, after = calibrated.</p>"
        + html_table(["channel", "unit", "RMS before", "RMS after", "after / before"], rows, "num")
        + residual_rms_figure(residuals)
        + residual_time_figure(residuals)
    )


def _parameter_section(result: dict, degrees: np.ndarray | None = None) -> str:
    """δM ± σ of every parameter; ``degrees`` (True: given in degrees) adds each one's unit."""
    names = list(result["parameter_names"])
    error = np.array(result["error"], dtype=float)
    stddev = None if result.get("stddev") is None else np.array(result["stddev"], dtype=float)
    mixed = degrees is not None and bool(np.any(degrees))
    rows = []
    for k, name in enumerate(names):
        sigma = None if stddev is None else stddev[k]
        ratio = None if sigma is None or sigma <= 0 else abs(error[k]) / sigma
        unit = ["deg" if degrees[k] else "mm"] if mixed else []  # type: ignore[index]  # mixed: not None
        rows.append(
            [
                name,
                *unit,
                _fmt(result["nominal"][k], 8),
                _fmt(result["estimate"][k], 8),
                _fmt(error[k]),
                _fmt(sigma),
                _fmt(ratio, 3),
            ]
        )
    if mixed:
        text = "estimate = nominal + δM, in mm and degrees as each parameter's unit says (spec §15)"
        header = ["parameter", "unit", "nominal", "estimate", "δM", "σ", "|δM| / σ"]
    else:
        text = "estimate = nominal + δM [mm] (paper eq. 9, Table 4)"
        header = ["parameter", "nominal [mm]", "estimate [mm]", "δM [mm]", "σ [mm]", "|δM| / σ"]
    return (
        "<h2>Parameter errors δM ± σ</h2>"
        f"<p>{text}; σ from the estimate's covariance.</p>"
        + parameter_figure(names, error, stddev, degrees if mixed else None)
        + f"<details><summary>all {len(names)} parameters</summary>"
        + html_table(header, rows, "num")
        + "</details>"
    )


def _robot_section(robot: Robot) -> str:
    legs = "crank → horn → rod → platform joint" if robot.kind == "rotary" else "base joint → platform joint"
    return (
        "<h2>The robot</h2>"
        f"<p>The calibrated drive at {html.escape(robot.pose)}, each leg drawn {legs} (the nominal one dashed "
        "grey; the differences are the calibration's, at the drawing's scale often a fraction of a line's "
        "width).</p>" + robot_figure(robot)
    )


def _block_rows(block: dict) -> list[list[str]]:
    """``[name, estimate, σ]`` of each value of a result's block (σ blank where the result gives none)."""
    stddev = block.get("stddev") or [None] * len(block["names"])
    return [
        [name, _fmt(value), _fmt(sigma)]
        for name, value, sigma in zip(block["names"], block["estimate"], stddev, strict=True)
    ]


def _compliance_section(result: dict) -> str:
    """The legs' compliance c_i ± σ (spec §10), where the result identified it."""
    block = result.get(COMPLIANCE)
    if not isinstance(block, dict):
        return ""
    rows = _block_rows(block)
    return (
        "<h2>Leg compliance c ± σ</h2><p>Each drive leg is c_i f_i / 1000 mm shorter under an axial force "
        "f_i [N] (compression), the forces from the statics of the platform's weight and the payload "
        "(spec §10).</p>" + html_table(["leg", "c [mm/kN]", "σ [mm/kN]"], rows, "num")
    )


def leg_force_figure(forces: LegForces) -> str:
    fig = new_figure(9.0, 2.6)
    ax = fig.subplots()
    stride = max(1, len(forces.t_s) // MAX_PLOTTED_SAMPLES)
    t, label = time_axis(forces.t_s)
    for leg in range(forces.forces_N.shape[1]):
        ax.plot(t[::stride], forces.forces_N[::stride, leg], lw=0.7, label=f"leg {leg + 1}")
    ax.set_xlabel(label, fontsize=8)
    ax.set_ylabel("axial force [N]")
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=min(6, forces.forces_N.shape[1]))
    return _png(fig)


def _leg_force_section(forces: LegForces) -> str:
    """Each leg's force over the log and what it gives under it, c_i f_i (spec §10)."""
    f, c = np.asarray(forces.forces_N, dtype=float), np.asarray(forces.compliance_mm_per_kN, dtype=float)
    give_um = f * c  # c [mm/kN] × f [N] = [µm]
    rows = [
        [f"leg {i + 1}", _fmt(np.nanmin(f[:, i])), _fmt(np.nanmean(f[:, i])), _fmt(np.nanmax(f[:, i]))]
        + [_fmt(np.nanmin(give_um[:, i])), _fmt(np.nanmax(give_um[:, i]))]
        for i in range(f.shape[1])
    ]
    return (
        "<h2>Leg forces</h2><p>Each drive leg's axial force over the log (compression positive), from the statics "
        "of the platform's weight and each row's payload at the calibrated model's poses, and the give "
        "c_i f_i it takes under it (spec §10).</p>"
        + html_table(["leg", "min [N]", "mean [N]", "max [N]", "c·f min [µm]", "c·f max [µm]"], rows, "num")
        + leg_force_figure(forces)
    )


def _thermal_section(result: dict) -> str:
    """The legs' expansion α_i ± σ (spec §17), where the platform declares ``[thermal]``."""
    block = result.get(THERMAL)
    if not isinstance(block, dict):
        return ""
    rows = _block_rows(block)
    return (
        "<h2>Leg expansion α ± σ</h2><p>Each drive leg's length from joint to joint is scaled by "
        "1 + α_i (T_i − T_ref) · 1e-6 at its temperature T_i (spec §17); σ 0: held at the platform's value.</p>"
        + html_table(["leg", "α [ppm/K]", "σ [ppm/K]"], rows, "num")
    )


def leg_temperature_figure(legs: LegTemperatures) -> str:
    """Two panels over the log, one line per leg: its temperature, and what it grew by."""
    fig = new_figure(9.0, 4.4)
    top, bottom = fig.subplots(2, 1, sharex=True)
    stride = max(1, len(legs.t_s) // MAX_PLOTTED_SAMPLES)
    t, label = time_axis(legs.t_s)
    for leg in range(legs.temperatures_C.shape[1]):
        top.plot(t[::stride], legs.temperatures_C[::stride, leg], lw=0.7, label=f"leg {leg + 1}")
        bottom.plot(t[::stride], legs.growth_um[::stride, leg], lw=0.7, label=f"leg {leg + 1}")
    top.set_ylabel("temperature [°C]")
    bottom.set_ylabel("growth α ΔT L [µm]")
    bottom.set_xlabel(label, fontsize=8)
    for ax in (top, bottom):
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    top.legend(fontsize=7, ncol=min(6, legs.temperatures_C.shape[1]))
    return _png(fig)


def _leg_temperature_section(legs: LegTemperatures) -> str:
    """Each leg's temperature over the log and what it grew by, α_i ΔT_i L_i (spec §17)."""
    T, growth = np.asarray(legs.temperatures_C, dtype=float), np.asarray(legs.growth_um, dtype=float)
    rows = [
        [f"leg {i + 1}", _fmt(np.nanmin(T[:, i])), _fmt(np.nanmean(T[:, i])), _fmt(np.nanmax(T[:, i]))]
        + [_fmt(np.nanmin(growth[:, i])), _fmt(np.nanmax(growth[:, i]))]
        for i in range(T.shape[1])
    ]
    header = ["leg", "min [°C]", "mean [°C]", "max [°C]", "growth min [µm]", "growth max [µm]"]
    return (
        "<h2>Leg temperatures</h2><p>Each drive leg's temperature over the log and what it grew by there, "
        "α_i (T_i − T_ref) L_i with the model's expansion α_i and L_i its length from joint to joint (spec §17): "
        "what a controller without thermal compensation leaves out.</p>"
        + html_table(header, rows, "num")
        + leg_temperature_figure(legs)
    )


def _correlation_section(result: dict) -> str:
    covariance = result.get("covariance")
    if covariance is None:
        return "<h2>Correlations</h2><p>The method gave no covariance.</p>"
    covariance = np.array(covariance, dtype=float)
    names = list(result["parameter_names"])
    for block in (STROKE_SCALE, "instrument", COMPLIANCE, THERMAL):  # the covariance's order (spec §8, §10, §17)
        if isinstance(result.get(block), dict):
            names += list(result[block]["names"])
    names = names[: len(covariance)]
    correlation = correlation_matrix(covariance)
    i, j = np.triu_indices(len(names), k=1)
    strong = np.abs(correlation[i, j]) >= STRONG_CORRELATION
    pairs = sorted(zip(np.abs(correlation[i, j])[strong], i[strong], j[strong], strict=True), reverse=True)[:20]
    listing = (
        html_table(
            ["parameter", "parameter", "correlation"],
            [[names[a], names[b], f"{correlation[a, b]:+.3f}"] for _, a, b in pairs],
            "num",
        )
        if pairs
        else f"<p>No pair correlates beyond ±{STRONG_CORRELATION}.</p>"
    )
    return (
        "<h2>Correlation matrix</h2>"
        + correlation_figure(names, correlation)
        + f"<p>Pairs with |correlation| ≥ {STRONG_CORRELATION} (at most 20):</p>"
        + listing
    )


def _conditioning_section(result: dict) -> str:
    cond = result.get("conditioning")
    if not isinstance(cond, dict):
        return ""
    weakest = "".join(f"<li><code>{html.escape(d)}</code></li>" for d in cond.get("weakest_directions", []))
    null = "".join(f"<li><code>{html.escape(d)}</code></li>" for d in cond.get("null_space", []))
    outside = "condition_number_equilibrated" in cond  # a pose or points instrument's: drive and instrument
    return (
        "<h2>Conditioning</h2>"
        + html_table(
            ["verdict", "rank", "condition number" + (" (unit columns)" if outside else ""), "unidentified directions"],
            [
                [
                    cond.get("verdict"),
                    cond.get("rank"),
                    _fmt(cond.get("condition_number_equilibrated" if outside else "condition_number"), 4),
                    cond.get("null_space_dimension"),
                ]
            ],
        )
        + (
            "<p>Weakest directions of the drive's and the instrument's unknowns (each unknown's share in σ "
            "of the readings; the poses constrain these least):</p><ol>"
            if outside
            else f"<p>Weakest directions of the {len(result['parameter_names'])} parameters (unit vectors in "
            "named parameters; the poses constrain these least):</p><ol>"
        )
        + weakest
        + "</ol>"
        + (f"<p>Unidentified directions:</p><ol>{null}</ol>" if null else "")
    )


def _prediction_section(result: dict) -> str:
    """The predicted closed-loop (absolute) pose error of the result's covariance, with its warning."""
    predicted = result.get("predicted_closed_loop")
    if not isinstance(predicted, dict):
        return ""
    if predicted.get("available") is False:
        return f"<h2>Predicted closed-loop error</h2><p>{html.escape(str(predicted.get('warning')))}</p>"
    warning = predicted.get("warning")
    return (
        "<h2>Predicted closed-loop error</h2>"
        "<p>Where the robot goes when the controller commands the calibrated model: the expected mean "
        f"error over {predicted.get('poses')} {html.escape(str(predicted.get('over')))} poses, from the "
        "estimate's covariance. A check through the instrument's calibrated frame cannot see it.</p>"
        + html_table(
            [
                "position [mm]",
                "90 % of such calibrations [mm]",
                "orientation [deg]",
                "the calibration's correction [mm]",
            ],
            [
                [
                    _fmt(predicted.get("position_mm"), 3),
                    "–".join(_fmt(v, 3) for v in predicted.get("position_band_mm") or ()),
                    _fmt(predicted.get("orientation_deg"), 3),
                    _fmt(predicted.get("correction_mm"), 3),
                ]
            ],
            "num",
        )
        + (f"<p><strong>{html.escape(warning)}</strong></p>" if warning else "")
    )


def _held_out_section(held: HeldOut) -> str:
    rows = [["position [mm]", _fmt(float(rms(held.position_error_mm))), _fmt(float(np.nanmax(held.position_error_mm)))]]
    if held.orientation_error_deg is not None:
        rows.append(
            [
                "orientation [deg]",
                _fmt(float(rms(held.orientation_error_deg))),
                _fmt(float(np.nanmax(held.orientation_error_deg))),
            ]
        )
    note = " The instrument frame was fitted again on this log." if held.registered else ""
    return (
        "<h2>Held-out errors</h2>"
        f"<p>The calibrated model predicts what the instrument read on <code>{html.escape(held.log)}</code> "
        f"({len(held.t_s)} samples not used for the calibration).{note}</p>"
        + html_table(["error", "RMS", "max"], rows, "num")
        + held_out_figure(held)
    )


STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; }
h1 { font-size: 1.5em; }
h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; padding-bottom: .2em; margin-top: 1.6em; }
table { border-collapse: collapse; margin: .6em 0; font-size: .9em; }
th, td { border: 1px solid #ddd; padding: .25em .6em; } th { background: #f3f3f3; }
table.num td { text-align: right; font-variant-numeric: tabular-nums; }
img { max-width: 100%; display: block; margin: .6em 0; }
pre { background: #f7f7f7; padding: .8em; overflow-x: auto; font-size: .85em; }
.summary td:first-child { font-weight: 600; }
"""


def report_html(
    title: str,
    result: dict,
    residuals: Residuals | None = None,
    held_out: HeldOut | None = None,
    inputs: dict[str, str] | None = None,
    leg_forces: LegForces | None = None,
    verdict: str | None = None,
    robot: Robot | None = None,
    leg_temperatures: LegTemperatures | None = None,
) -> str:
    """The whole page as text.

    Args:
        title: the page's heading.
        result: a calibration result (spec §5, with the optional fields of §8 where present).
        residuals: the calibration log's residuals, or None.
        held_out: a validation's errors, or None.
        inputs: named input files (``{"platform file": "P.toml", "log": "L.csv"}``).
        leg_forces: an elastic drive's leg forces over the log, or None.
        verdict: the command's verdict line (:func:`~stewart_calib.analysis.accuracy.verdict_line`), shown
            first; with its warning where the calibration rests on noise.
        robot: the drive drawn nominal and calibrated, and which parameters are angles, or None.
        leg_temperatures: a thermal drive's leg temperatures and growth over the log, or None.
    """
    summary = [
        ["method", result["method"]],
        ["platform", result["platform"]],
        *([name, value] for name, value in (inputs or {}).items()),
        ["samples used / skipped", f"{result['samples_used']} / {result['samples_skipped']}"],
        ["created", result.get("created", "—")],
        ["stewart-calib", result.get("version", "—")],
    ]
    sections = [
        f'<h2>Verdict</h2><p class="verdict">{html.escape(verdict.removeprefix("verdict: "))}</p>' if verdict else "",
        "<h2>Summary</h2>" + html_table(None, summary, "summary"),
        _held_out_section(held_out) if held_out is not None else "",
        _residual_section(residuals) if residuals is not None else "",
        _robot_section(robot) if robot is not None else "",
        _parameter_section(result, None if robot is None else robot.parameter_degrees),
        _compliance_section(result),
        _leg_force_section(leg_forces) if leg_forces is not None else "",
        _thermal_section(result),
        _leg_temperature_section(leg_temperatures) if leg_temperatures is not None else "",
        _correlation_section(result),
        _conditioning_section(result),
        _prediction_section(result),
        "<h2>Config</h2><p>The estimator settings used.</p><pre>"
        + html.escape(json.dumps(result.get("config", {}), indent=2))
        + "</pre>",
        "<h2>Versions</h2>"
        + html_table(
            ["library", "version"],
            [[k, v] for k, v in {"stewart-calib": result.get("version", "—"), **library_versions()}.items()],
        ),
    ]
    return html_page(title, "".join(sections))


def html_page(title: str, body: str) -> str:
    """A whole static page: ``title`` as its heading, then ``body`` (HTML), in :data:`STYLE`."""
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>"
        f"<h1>{html.escape(title)}</h1>{body}</body></html>\n"
    )
