"""Building blocks of a rerun recording (``.rrd``) of a calibration run.

Every function takes a :class:`Recording` (our own stream, never rerun's global one) and logs
one kind of data. Time series go in columnar batches (``send_columns``), so a pipeline should
hand over whole arrays, or at least batches, not one sample at a time.

Units as logged: lengths in mm, angles in degrees; 3D data in the base frame {J} (z up) unless
the path says otherwise. The 42 parameters keep the paper's order (``j_i, d_i, l_i`` per leg).

Timelines — every time-series row carries both:

* ``sample`` (sequence): the sample index in the log (default ``0 … N−1`` of the call),
* ``time`` (duration): ``t_s`` of the sample [s].

Entity paths (a contract: the tests and the reproduce pipeline rely on it). ``{i}`` is the leg
number 1…6, ``{name}`` one of :data:`PARAMETER_FIELDS`, ``{method}`` an estimator name (``ls``,
``paper_ekf``, ``ekf``, ``isam2``, …) or ``truth``, ``{stage}`` an experiment stage label;
method and stage names must match ``[A-Za-z0-9_.-]+``::

    conventions                            static  TextDocument: units, frames, RPY, orderings
    world                                  static  ViewCoordinates (right-handed, z up) = {J}
    world/base/outline                     static  LineStrips3D through all base joints
    world/base/drive_joints                static  Points3D j_i, labels J1…J6
    world/base/tracker_joints              static  Points3D z_i, labels Z1…Z6
    world/platform                         series  Transform3D T_world_platform (actual pose);
                                           static  TransformAxes3D (the {D} axes)
    world/platform/outline                 static  LineStrips3D in {D}
    world/platform/drive_joints            static  Points3D d_i in {D}
    world/platform/tracker_joints          static  Points3D h_i in {D}
    world/platform_desired                 series  Transform3D of the desired pose
    world/platform_desired/outline         static  ghost outline in {D}
    world/legs/drive                       series  LineStrips3D j_i → t + R d_i, 6 per row
    world/legs/tracker                     series  LineStrips3D z_i → t + R h_i, 6 per row
    params/leg{i}/{name}/{method}          series  Scalars [mm]   (Figs. 5–6)
    params/leg{i}/{name}/{method}/upper    series  Scalars [mm]: the estimate + σ (the ±σ band's edges)
    params/leg{i}/{name}/{method}/lower    series  Scalars [mm]: the estimate − σ
    diagnostics/{method}/residual/leg{i}   series  Scalars [mm]: drive-leg residual after the sample
    diagnostics/{method}/innovation/leg{i} series  Scalars [mm]: drive-leg residual before it
    diagnostics/{method}/nis               series  Scalars: normalised innovation squared (Kalman methods)
    errors/position_mm/{method}            series  Scalars [mm]   (Fig. 7a)
    errors/orientation_deg/{method}        series  Scalars [deg]  (Fig. 7b)
    trajectories/{stage}/{method}/desired  static  LineStrips3D [mm] (Fig. 8)
    trajectories/{stage}/{method}/actual   static  LineStrips3D [mm]
    polar/{stage}/reference                static  LineStrips2D: the zero-deviation circle
    polar/{stage}/{method}                 static  LineStrips2D: r = base + gain·deviation (Fig. 9)
    polar/{stage}/{method}/raw             static  AnyValues angle_deg, deviation_mm (per point)
"""

from __future__ import annotations

import re
import uuid
import zlib
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ..model.legs import LegModel
from ..model.platform import PARAMETER_FIELDS, Platform
from .geometry import leg_joints, leg_polylines

SAMPLE_TIMELINE = "sample"
#: per-method diagnostic series: leg residuals after and before each sample, and the NIS.
DIAGNOSTICS = ("residual", "innovation", "nis")
DIAGNOSTIC_LABELS = {
    "residual": "leg residual after the sample [mm]",
    "innovation": "leg residual before it [mm]",
    "nis": "NIS",
}
TIME_TIMELINE = "time"
TRUTH = "truth"

CONVENTIONS_MARKDOWN = """\
# stewart-calib conventions

* Units as logged: lengths **mm**, angles **degrees**; timelines `sample` (index) and `time` (s).
* Frames: `{J}` base = `world`, origin at the centre of the base's upper surface, z up;
  `{D}` platform = `world/platform`, origin at the centre of the platform's upper surface.
* Pose: `{D}` in `{J}`, position `(x, y, z)` and roll-pitch-yaw with `R = Rz(yaw) Ry(pitch) Rx(roll)`
  (paper eq. 20–21).
* Pose tangent (GTSAM `Pose3`): `ξ = [ω, v]`, rotation first, body frame.
* Legs 1…6: drive leg `l_i + q_i = ‖t + R d_i − j_i‖`, tracker leg `ls_i + s_i = ‖t + R h_i − z_i‖`.
* 42 parameters in the paper's order: `j_i (x, y, z), d_i (x, y, z), l_i` for leg 1, then leg 2, …
  (`params/leg{i}/{j_x … l}/{method}`).
"""

_NAME_PATTERN = re.compile(r"[A-Za-z0-9_.\-]+")

# Colours [RGB]: drive legs warm, tracker legs cool, desired pose as a translucent ghost.
_DRIVE_COLOR = (230, 120, 30)
_TRACKER_COLOR = (40, 160, 220)
_OUTLINE_COLOR = (160, 160, 160)
_GHOST_COLOR = (200, 200, 200, 90)
_DESIRED_TRAJECTORY_COLOR = (120, 120, 120)
# One hue per parameter of a leg so that a leg's seven curves (one view, as in Fig. 5) stay apart.
_PARAMETER_COLORS = (
    (228, 26, 28),
    (55, 126, 184),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (30, 30, 30),
)
_METHOD_COLORS = {
    "ls": (228, 26, 28),
    "paper_ekf": (255, 127, 0),
    "ekf": (55, 126, 184),
    "isam2": (77, 175, 74),
    TRUTH: (30, 30, 30),
}
#: one colour per leg 1…6 for per-leg diagnostic series.
_LEG_COLORS = ((228, 26, 28), (55, 126, 184), (77, 175, 74), (152, 78, 163), (255, 127, 0), (166, 86, 40))
_FALLBACK_COLORS = ((152, 78, 163), (166, 86, 40), (247, 129, 191), (0, 150, 150))

_LEG_RADIUS_MM = 6.0
_OUTLINE_RADIUS_MM = 3.0
_JOINT_RADIUS_MM = 12.0
_AXIS_LENGTH_MM = 150.0


class Recording:
    """A rerun stream written by stewart-calib; a context manager that flushes and disconnects.

    Wrap any stream (``Recording(rr.RecordingStream(...))`` after ``spawn()`` for a live viewer)
    or use :func:`open_recording` for a file. ``stream`` is the underlying ``rr.RecordingStream``.
    """

    def __init__(self, stream: rr.RecordingStream) -> None:
        self.stream = stream
        # Static styling is logged once per entity, however many batches a pipeline sends.
        self._static_done: set[str] = set()

    def static_once(self, entity_path: str, archetype) -> None:
        """Log ``archetype`` as static data at ``entity_path`` unless already done."""
        key = f"{entity_path}#{type(archetype).__name__}"
        if key not in self._static_done:
            self.stream.log(entity_path, archetype, static=True)
            self._static_done.add(key)

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()


def open_recording(
    path: str | Path, application_id: str = "stewart-calib", recording_id: str | None = None
) -> Recording:
    """A new recording saved to ``path`` (parent folders created), with a fresh recording id.

    The stream is not made the global or thread default, so several recordings can be written
    side by side and nothing else in the process logs into this one by accident.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stream = rr.RecordingStream(application_id, recording_id=recording_id or str(uuid.uuid4()))
    stream.save(path)
    return Recording(stream)


# ----------------------------------------------------------------------------- paths


def _checked_name(name: str, what: str) -> str:
    if not _NAME_PATTERN.fullmatch(name):
        raise ValueError(f"{what} {name!r} must match [A-Za-z0-9_.-]+ to be one entity-path part")
    return name


def parameter_fields(names: tuple[str, ...], n_legs: int) -> tuple[str, ...]:
    """The fields of one leg in a leg model's parameter order, from its ``names`` (the first leg's,
    its number written ``_`` or dropped at the end): ``j1x … l1`` → :data:`PARAMETER_FIELDS`
    ``j_x … l``, a rotary leg's ``a1x … tw1`` → ``a_x … tw``."""
    return tuple(name.replace("1", "_", 1).rstrip("_") for name in names[: len(names) // n_legs])


def parameter_path(leg: int, field: str, method: str, fields: tuple[str, ...] = PARAMETER_FIELDS) -> str:
    """``params/leg{leg}/{field}/{method}`` for a leg numbered from 1 and one of its ``fields``."""
    if leg < 1 or field not in fields:
        raise ValueError(f"no parameter leg {leg} / {field!r}")
    return f"params/leg{leg}/{field}/{_checked_name(method, 'method')}"


def band_paths(leg: int, field: str, method: str, fields: tuple[str, ...] = PARAMETER_FIELDS) -> tuple[str, str]:
    """``(upper, lower)`` edges of the ±σ band of one parameter."""
    path = parameter_path(leg, field, method, fields)
    return f"{path}/upper", f"{path}/lower"


def diagnostic_path(method: str, kind: str, leg: int | None = None) -> str:
    """``diagnostics/{method}/{kind}[/leg{leg}]`` for ``kind`` in :data:`DIAGNOSTICS`."""
    if kind not in DIAGNOSTICS:
        raise ValueError(f"diagnostic kind must be one of {DIAGNOSTICS}, got {kind!r}")
    path = f"diagnostics/{_checked_name(method, 'method')}/{kind}"
    return path if leg is None else f"{path}/leg{leg}"


def error_paths(method: str) -> tuple[str, str]:
    """``(errors/position_mm/{method}, errors/orientation_deg/{method})``."""
    method = _checked_name(method, "method")
    return f"errors/position_mm/{method}", f"errors/orientation_deg/{method}"


def trajectory_paths(stage: str, method: str) -> tuple[str, str]:
    """``(trajectories/{stage}/{method}/desired, …/actual)``."""
    base = f"trajectories/{_checked_name(stage, 'stage')}/{_checked_name(method, 'method')}"
    return f"{base}/desired", f"{base}/actual"


def polar_path(stage: str, method: str) -> str:
    """``polar/{stage}/{method}``; its raw values live at ``…/raw``."""
    return f"polar/{_checked_name(stage, 'stage')}/{_checked_name(method, 'method')}"


# ----------------------------------------------------------------------------- helpers


def method_color(method: str) -> tuple[int, int, int]:
    """A fixed colour per known estimator, a stable (hash-based) one for any other name."""
    return _METHOD_COLORS.get(method) or _FALLBACK_COLORS[zlib.crc32(method.encode()) % len(_FALLBACK_COLORS)]


def _time_columns(times_s, samples) -> tuple[int, list[rr.TimeColumn]]:
    times_s = np.atleast_1d(np.asarray(times_s, dtype=float))
    if times_s.ndim != 1:
        raise ValueError(f"times_s must be a scalar or 1-D, got shape {times_s.shape}")
    n = len(times_s)
    samples = np.arange(n) if samples is None else np.atleast_1d(np.asarray(samples, dtype=np.int64))
    if samples.shape != (n,):
        raise ValueError(f"samples must have shape ({n},) like times_s, got {samples.shape}")
    return n, [rr.TimeColumn(SAMPLE_TIMELINE, sequence=samples), rr.TimeColumn(TIME_TIMELINE, duration=times_s)]


def _batch(values, n: int, tail: tuple[int, ...], what: str) -> np.ndarray:
    """``values`` as ``(n, *tail)``; a single ``tail``-shaped value is one row."""
    values = np.asarray(values, dtype=float)
    if values.shape == tail:
        values = values[None]
    if values.shape != (n, *tail):
        raise ValueError(f"{what} must have shape {tail} or ({n}, {', '.join(map(str, tail))}), got {values.shape}")
    return values


def _per_leg(values, n: int, what: str, fields: int) -> np.ndarray:
    """``values`` ``(n, F L)`` leg by leg (a single ``(F L,)`` is one row) as ``(n, L, F)``: a leg
    set's parameters, ``fields`` F a leg, its L legs read off the array's own width."""
    values = np.asarray(values, dtype=float)
    width = values.shape[-1] if values.ndim else 0
    if width == 0 or width % fields:
        raise ValueError(f"{what} must hold {fields} parameters a leg, got shape {values.shape}")
    return _batch(values, n, (width,), what).reshape(n, width // fields, fields)


def _closed_outline(points: np.ndarray) -> np.ndarray:
    """Polygon through ``points`` in order of azimuth about the z axis, closed."""
    order = np.argsort(np.arctan2(points[:, 1], points[:, 0]))
    return np.vstack([points[order], points[order[:1]]])


# ----------------------------------------------------------------------------- scene


def log_platform_geometry(rec: Recording, platform: Platform) -> None:
    """Static scene: conventions text, base and platform outlines, joints, the {D} axes.

    The platform parts live under ``world/platform`` (in {D}), so they follow the pose logged
    by :func:`log_platform_pose`.
    """
    log = rec.stream.log
    log("conventions", rr.TextDocument(CONVENTIONS_MARKDOWN, media_type=rr.MediaType.MARKDOWN), static=True)
    log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
    # Joint letters as in the paper: drive j_i / d_i, tracker z_i / h_i (a platform measured by
    # another instrument may have no tracker).
    legs = {"drive": platform.drive} | ({} if platform.tracker is None else {"tracker": platform.tracker})
    for side, (frame, letters) in enumerate((("base", "JZ"), ("platform", "DH"))):
        joints = {kind: leg_joints(leg_set)[side] for kind, leg_set in legs.items()}
        outline = _closed_outline(np.vstack(list(joints.values())))
        outline_strip = rr.LineStrips3D([outline], colors=_OUTLINE_COLOR, radii=_OUTLINE_RADIUS_MM)
        log(f"world/{frame}/outline", outline_strip, static=True)
        # the tracker's letter and colour go unused without a tracker
        for (kind, points), letter, color in zip(joints.items(), letters, (_DRIVE_COLOR, _TRACKER_COLOR), strict=False):
            labels = [f"{letter}{i}" for i in range(1, len(points) + 1)]
            log(
                f"world/{frame}/{kind}_joints",
                rr.Points3D(points, colors=color, radii=_JOINT_RADIUS_MM, labels=labels),
                static=True,
            )
    log("world/platform", rr.TransformAxes3D(_AXIS_LENGTH_MM), static=True)


def log_platform_pose(
    rec: Recording,
    platform: Platform,
    R: np.ndarray,
    t: np.ndarray,
    times_s,
    samples=None,
    drive_legs: LegModel | None = None,
    desired: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Platform pose(s), drive and tracker legs, and optionally the desired pose as a ghost.

    Args:
        R, t: actual pose(s) of {D} in {J}: ``(3, 3)``/``(3,)`` for one sample or
            ``(N, 3, 3)``/``(N, 3)`` [mm].
        times_s: ``t_s`` per sample, scalar or ``(N,)`` [s].
        samples: sample indices ``(N,)``; default ``0 … N−1``.
        drive_legs: the drive geometry to draw (e.g. the simulator's true legs); default the
            nominal ``platform.drive``. The tracker legs are always ``platform.tracker``.
        desired: ``(R_d, t_d)`` shaped like ``(R, t)``: the commanded pose.
    """
    n, index = _time_columns(times_s, samples)
    R, t = _batch(R, n, (3, 3), "R"), _batch(t, n, (3,), "t")
    send = rec.stream.send_columns
    send("world/platform", indexes=index, columns=rr.Transform3D.columns(translation=t, mat3x3=R))
    drawn = [("drive", drive_legs or platform.drive, _DRIVE_COLOR)]
    if platform.tracker is not None:  # a platform measured by another instrument may have none
        drawn.append(("tracker", platform.tracker, _TRACKER_COLOR))
    for name, legs, color in drawn:
        rec.static_once(f"world/legs/{name}", rr.LineStrips3D.from_fields(colors=color, radii=_LEG_RADIUS_MM))
        strips = rr.LineStrips3D.columns(strips=leg_polylines(legs, R, t)).partition(np.full(n, legs.n_legs))
        send(f"world/legs/{name}", indexes=index, columns=strips)
    if desired is not None:
        R_d, t_d = _batch(desired[0], n, (3, 3), "R_desired"), _batch(desired[1], n, (3,), "t_desired")
        ghost = _closed_outline(
            np.vstack([leg_joints(platform.drive)[1], *(leg_joints(legs)[1] for _, legs, _ in drawn[1:])])
        )
        rec.static_once(
            "world/platform_desired/outline", rr.LineStrips3D([ghost], colors=_GHOST_COLOR, radii=_OUTLINE_RADIUS_MM)
        )
        send("world/platform_desired", indexes=index, columns=rr.Transform3D.columns(translation=t_d, mat3x3=R_d))


# ----------------------------------------------------------------------------- time series


def _send_scalars(rec: Recording, entity_path: str, index, values: np.ndarray, style: rr.SeriesLines) -> None:
    rec.static_once(entity_path, style)
    rec.stream.send_columns(entity_path, indexes=index, columns=rr.Scalars.columns(scalars=values))


def log_parameters(
    rec: Recording, method: str, params_mm, times_s, samples=None, fields: tuple[str, ...] = PARAMETER_FIELDS
) -> None:
    """The 42 parameters of one method over time at ``params/leg{i}/{name}/{method}``.

    Pass the identified errors δM (or the truth's, with ``method=TRUTH``) rather than absolute
    values, so that each leg's curves share a mm-scale axis as in Figs. 5–6; the recording takes
    whatever it is given.

    Args:
        method: estimator name, or :data:`TRUTH`.
        params_mm: ``(42,)`` for one sample or ``(N, 42)`` in the paper's order [mm].
        times_s: scalar or ``(N,)`` [s].
        samples: ``(N,)`` sample indices; default ``0 … N−1``.
        fields: one leg's parameters (:func:`parameter_fields` of another leg model's names).
    """
    n, index = _time_columns(times_s, samples)
    per_leg = _per_leg(params_mm, n, "params_mm", len(fields))
    # Truth: thin and pale, under the estimates drawn in the same hue.
    width, alpha = (1.0, 140) if method == TRUTH else (2.0, 255)
    for leg in range(per_leg.shape[1]):
        for k, field in enumerate(fields):
            color = _PARAMETER_COLORS[k % len(_PARAMETER_COLORS)]
            style = rr.SeriesLines(colors=(*color, alpha), widths=width, names=f"{field} {method}")
            _send_scalars(rec, parameter_path(leg + 1, field, method, fields), index, per_leg[:, leg, k], style)


def log_parameter_band(
    rec: Recording,
    method: str,
    params_mm,
    stddev_mm,
    times_s,
    samples=None,
    fields: tuple[str, ...] = PARAMETER_FIELDS,
) -> None:
    """The ±σ band of each of the 42 parameters: ``params ± stddev`` at ``…/{method}/upper|lower``,
    drawn thin in the parameter's colour around :func:`log_parameters`' curve.

    Args:
        params_mm: ``(N, 42)`` as passed to :func:`log_parameters` [mm], leg by leg of ``fields``.
        stddev_mm: ``(N, 42)`` σ of each parameter after each sample [mm] (NaN: none).
    """
    n, index = _time_columns(times_s, samples)
    centre = _per_leg(params_mm, n, "params_mm", len(fields))
    sigma = _batch(stddev_mm, n, (centre[0].size,), "stddev_mm").reshape(centre.shape)
    for leg in range(centre.shape[1]):
        for k, field in enumerate(fields):
            color = _PARAMETER_COLORS[k % len(_PARAMETER_COLORS)]
            style = rr.SeriesLines(colors=(*color, 110), widths=0.75, names=f"{field} {method} ±σ")
            upper, lower = band_paths(leg + 1, field, method, fields)
            _send_scalars(rec, upper, index, centre[:, leg, k] + sigma[:, leg, k], style)
            _send_scalars(rec, lower, index, centre[:, leg, k] - sigma[:, leg, k], style)


def log_elastic(rec: Recording, method: str, forces_N, compliance, compliance_sigma, times_s) -> None:
    """An elastic drive (spec §10): each leg's axial force [N] at every sample at
    ``forces/leg{i}/{method}`` and the identified compliance ``c_i`` [mm/kN] with its ±σ (constant
    over the run: the result's) at ``compliance/leg{i}/{method}[/upper|/lower]``.

    Args:
        forces_N: ``(N, 6)`` compression > 0; compliance, compliance_sigma: ``(6,)`` (σ None: no band).
    """
    n, index = _time_columns(times_s, None)
    forces = _batch(forces_N, n, np.shape(compliance), "forces_N")
    for leg in range(len(compliance)):
        colour = _PARAMETER_COLORS[leg % len(_PARAMETER_COLORS)]
        style = rr.SeriesLines(colors=(*colour, 255), widths=1.5, names=f"f{leg + 1} {method} [N]")
        _send_scalars(rec, f"forces/leg{leg + 1}/{_checked_name(method, 'method')}", index, forces[:, leg], style)
        base = f"compliance/leg{leg + 1}/{_checked_name(method, 'method')}"
        lines = {"": np.full(n, compliance[leg])}
        if compliance_sigma is not None:
            lines |= {"/upper": lines[""] + compliance_sigma[leg], "/lower": lines[""] - compliance_sigma[leg]}
        for suffix, values in lines.items():
            width = 2.0 if not suffix else 0.75
            style = rr.SeriesLines(
                colors=(*colour, 255 if not suffix else 110), widths=width, names=f"c{leg + 1} {method}"
            )
            _send_scalars(rec, base + suffix, index, values, style)


#: the views of the inputs tab (:func:`send_blueprint`): a thermal drive's legs (:func:`log_thermal`)
THERMAL_VIEWS = (("temperature", "leg temperatures [°C]"), ("growth", "leg growth α_i ΔT_i L_i [µm]"))


def log_thermal(rec: Recording, method: str, temperatures_C, growth_um, times_s) -> None:
    """A thermal drive (spec §17): each leg's temperature [°C] at every sample at
    ``temperature/leg{i}`` and what it grew by there, ``α_i (T_i − T_ref) L_i`` [µm] with the method's
    α, at ``growth/leg{i}/{method}``: one line per leg in each of the inputs tab's views
    (:data:`THERMAL_VIEWS`).

    Args:
        temperatures_C, growth_um: ``(N, legs)``.
    """
    n, index = _time_columns(times_s, None)
    temperatures = _batch(temperatures_C, n, np.shape(temperatures_C)[1:], "temperatures_C")
    growth = _batch(growth_um, n, np.shape(temperatures_C)[1:], "growth_um")
    for leg in range(temperatures.shape[1]):
        colour = (*_LEG_COLORS[leg % len(_LEG_COLORS)], 255)
        style = rr.SeriesLines(colors=colour, widths=1.5, names=f"T{leg + 1} [°C]")
        _send_scalars(rec, f"temperature/leg{leg + 1}", index, temperatures[:, leg], style)
        style = rr.SeriesLines(colors=colour, widths=1.5, names=f"leg {leg + 1} {method} [µm]")
        _send_scalars(rec, f"growth/leg{leg + 1}/{_checked_name(method, 'method')}", index, growth[:, leg], style)


def log_diagnostics(
    rec: Recording, method: str, times_s, residual_mm=None, innovation_mm=None, nis=None, samples=None
) -> None:
    """How one method fits the data over time, at ``diagnostics/{method}/…``.

    Args:
        residual_mm: ``(N, 6)`` drive-leg residuals ``‖t + R d_i − j_i‖ − (l_i + q_i)`` with the
            estimate after each sample, at the tracker's pose of that sample [mm], or None.
        innovation_mm: ``(N, 6)`` the same with the estimate before the sample (for the leg-model
            EKF exactly its innovation, sign aside), or None (a batch fit has no "before").
        nis: ``(N,)`` normalised innovation squared ``νᵀ S⁻¹ ν`` (Kalman methods; NaN where the
            sample was refused), or None.
    """
    n, index = _time_columns(times_s, samples)
    series = [("residual", residual_mm), ("innovation", innovation_mm)]
    for kind, values in series:
        if values is None:
            continue
        values = _batch(values, n, np.shape(values)[-1:], kind)  # one column a leg
        for leg in range(values.shape[1]):
            style = rr.SeriesLines(colors=_LEG_COLORS[leg % len(_LEG_COLORS)], widths=1.0, names=f"leg {leg + 1}")
            _send_scalars(rec, diagnostic_path(method, kind, leg + 1), index, values[:, leg], style)
    if nis is not None:
        style = rr.SeriesLines(colors=method_color(method), widths=1.0, names=f"NIS {method}")
        _send_scalars(rec, diagnostic_path(method, "nis"), index, _batch(nis, n, (), "nis"), style)


def log_pose_errors(
    rec: Recording, method: str, times_s, position_error_mm, orientation_error_deg, samples=None
) -> None:
    """Pose errors of one method over time (Fig. 7) at ``errors/position_mm|orientation_deg/{method}``.

    Args:
        times_s: scalar or ``(N,)`` [s].
        position_error_mm: ``(N,)`` ‖t_actual − t_desired‖ [mm].
        orientation_error_deg: ``(N,)`` rotation angle of ``R_desiredᵀ R_actual`` [deg].
        samples: ``(N,)`` sample indices; default ``0 … N−1``.
    """
    n, index = _time_columns(times_s, samples)
    style = rr.SeriesLines(colors=method_color(method), widths=2.0, names=method)
    for path, values in zip(error_paths(method), (position_error_mm, orientation_error_deg), strict=True):
        _send_scalars(rec, path, index, _batch(values, n, (), path), style)


# ----------------------------------------------------------------------------- trajectories


def circle_angles_rad(points_mm: np.ndarray) -> np.ndarray:
    """Angle of each point about the centre of the best-fit circle, in its best-fit plane [rad].

    The plane's first axis is world x projected onto it (world y if x is near its normal) and
    its normal points to +z where possible, so a horizontal circle gets the usual azimuth. The
    centre is an algebraic least-squares fit, so partial arcs and uneven sampling are fine.
    """
    centred = points_mm - points_mm.mean(axis=0)
    normal = np.linalg.svd(centred, full_matrices=False)[2][2]
    if normal[2] < 0:
        normal = -normal
    for axis in np.eye(3)[:2]:
        u = axis - (axis @ normal) * normal
        if np.linalg.norm(u) > 0.1:
            break
    u /= np.linalg.norm(u)
    in_plane = np.stack([centred @ u, centred @ np.cross(normal, u)], axis=-1)
    # Circle through the points: x² + y² = 2 c·(x, y) + k, linear in the centre c and k.
    design = np.hstack([2.0 * in_plane, np.ones((len(in_plane), 1))])
    centre = np.linalg.lstsq(design, np.sum(in_plane**2, axis=1), rcond=None)[0][:2]
    relative = in_plane - centre
    return np.arctan2(relative[:, 1], relative[:, 0])


def _polar_strip(angles_rad: np.ndarray, radii: np.ndarray) -> np.ndarray:
    return np.stack([radii * np.cos(angles_rad), radii * np.sin(angles_rad)], axis=-1)


def log_trajectory(
    rec: Recording,
    stage: str,
    method: str,
    desired_xyz_mm,
    actual_xyz_mm,
    polar_base_radius_mm: float = 1.0,
    polar_gain: float = 1.0,
) -> None:
    """A circle trajectory, desired vs actual (Fig. 8), and its polar deviation plot (Fig. 9).

    The deviation of point k is ``‖actual_k − desired_k‖`` [mm]; its angle is that of
    ``desired_k`` about the circle's centre (:func:`circle_angles_rad`). The polar strip has
    radius ``polar_base_radius_mm + polar_gain · deviation``, so zero deviation is the reference
    circle at ``polar/{stage}/reference`` and the shape of small deviations stays visible.

    Args:
        desired_xyz_mm, actual_xyz_mm: ``(N, 3)`` positions of {D}'s origin in {J} [mm].
    """
    desired = np.asarray(desired_xyz_mm, dtype=float)
    actual = np.asarray(actual_xyz_mm, dtype=float)
    if desired.ndim != 2 or desired.shape[1] != 3 or actual.shape != desired.shape:
        raise ValueError(f"desired and actual must both be (N, 3), got {desired.shape} and {actual.shape}")
    color = method_color(method)
    desired_path, actual_path = trajectory_paths(stage, method)
    log = rec.stream.log
    log(desired_path, rr.LineStrips3D([desired], colors=_DESIRED_TRAJECTORY_COLOR, radii=1.0), static=True)
    log(actual_path, rr.LineStrips3D([actual], colors=color, radii=1.0, labels=method), static=True)

    deviation_mm = np.linalg.norm(actual - desired, axis=1)
    angles_rad = circle_angles_rad(desired)
    order = np.argsort(angles_rad)
    reference = np.linspace(-np.pi, np.pi, 181)
    reference_strip = _polar_strip(reference, np.full_like(reference, polar_base_radius_mm))
    log(
        f"polar/{_checked_name(stage, 'stage')}/reference",
        rr.LineStrips2D([reference_strip], colors=_OUTLINE_COLOR, labels="0 mm"),
        static=True,
    )
    radii = polar_base_radius_mm + polar_gain * deviation_mm[order]
    polar = _polar_strip(angles_rad[order], radii)
    path = polar_path(stage, method)
    log(path, rr.LineStrips2D([np.vstack([polar, polar[:1]])], colors=color, labels=method), static=True)
    log(f"{path}/raw", rr.AnyValues(angle_deg=np.degrees(angles_rad), deviation_mm=deviation_mm), static=True)


# ----------------------------------------------------------------------------- layout


def send_blueprint(
    rec: Recording,
    n_legs: int,
    methods,
    stages,
    diagnostics=None,
    fields: tuple[str, ...] = PARAMETER_FIELDS,
    inputs: tuple[tuple[str, str], ...] = (),
) -> None:
    """Lay the panels out in tabs: scene, one parameter tab per method, pose errors, trajectories,
    one diagnostics tab per method in ``diagnostics``, and, where ``inputs`` names ``(origin, title)``
    views (:data:`THERMAL_VIEWS`), an inputs tab of those time series.

    Each parameter tab holds one time-series view per drive leg (``n_legs`` of them) with that
    method's seven curves, their ±σ bands where logged, and the truth (Fig. 5); method comparison
    is in the pose-error tab (Fig. 7). ``diagnostics`` maps a method to the kinds of :data:`DIAGNOSTICS` logged for it;
    ``fields``: one leg's parameters, as :func:`log_parameters` took them.
    """
    methods = [_checked_name(method, "method") for method in methods]
    stages = [_checked_name(stage, "stage") for stage in stages]
    scene = rrb.Horizontal(
        rrb.Spatial3DView(origin="world", name="platform"),
        rrb.TextDocumentView(origin="conventions", name="conventions"),
        column_shares=[3, 1],
        name="scene",
    )
    parameter_tabs = [
        rrb.Grid(
            *(
                rrb.TimeSeriesView(
                    origin=f"params/leg{leg}",
                    # Entity queries know no inner wildcard, so list the 7 + 7 series.
                    contents=[
                        f"$origin/{field}/{name}{edge}"
                        for field in fields
                        for name in (method, TRUTH)
                        for edge in ("", "/upper", "/lower")
                    ],
                    name=f"leg {leg} [mm]",
                )
                for leg in range(1, n_legs + 1)
            ),
            grid_columns=3,
            name=f"parameters {method}",
        )
        for method in methods
    ]
    errors = rrb.Vertical(
        rrb.TimeSeriesView(origin="errors/position_mm", name="position error [mm]"),
        rrb.TimeSeriesView(origin="errors/orientation_deg", name="orientation error [deg]"),
        name="pose errors",
    )
    trajectories = rrb.Grid(
        *(
            rrb.Horizontal(
                rrb.Spatial3DView(origin=f"trajectories/{stage}", name=f"{stage} trajectory"),
                rrb.Spatial2DView(origin=f"polar/{stage}", name=f"{stage} deviation (polar)"),
                name=stage,
            )
            for stage in stages
        ),
        grid_columns=1,
        name="trajectories",
    )
    diagnostic_tabs = [
        rrb.Vertical(
            *(
                rrb.TimeSeriesView(origin=diagnostic_path(method, kind), name=f"{method} {DIAGNOSTIC_LABELS[kind]}")
                for kind in DIAGNOSTICS
                if kind in kinds
            ),
            name=f"diagnostics {method}",
        )
        for method, kinds in (diagnostics or {}).items()
    ]
    input_tabs = (
        [rrb.Vertical(*(rrb.TimeSeriesView(origin=origin, name=name) for origin, name in inputs), name="inputs")]
        if inputs
        else []
    )
    rec.stream.send_blueprint(
        rrb.Blueprint(
            rrb.Tabs(scene, *parameter_tabs, errors, trajectories, *diagnostic_tabs, *input_tabs),
            rrb.TimePanel(timeline=TIME_TIMELINE),
        )
    )
