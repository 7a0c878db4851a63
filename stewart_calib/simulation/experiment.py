"""Experiment description (TOML in ``configs/experiments/``) and the desired-pose schedule.

An experiment file holds everything that defines a simulated run; the same file and seed give
identical output. Layout (every key optional except ``seed`` and ``platform``; defaults below)::

    name = "paper"
    seed = 20240517
    platform = "../platforms/nim-stewart.toml"   # relative to this file, or a packaged name
    sample_period_s = 0.1                        # t_s step between samples [s]

    [robot]     errors = "table4" | "random", scale_base_joints, scale_platform_joints,
                scale_lengths, random_spread_mm, encoder_noise_mm, stroke_scale_spread,
                encoder_zero_spread_mm
                — a rotary drive's (spec §15) instead: angle_offset_limit_deg, horn_spread_mm,
                rod_spread_mm, joint_spread_mm, axis_tilt_spread_deg, angle_scale_spread,
                angle_noise_deg (:class:`RotaryRobotConfig`; no [load]: it is simulated rigid)
    [instrument] the nominal instrument of spec §7 (kind, frame, target, targets_mm,
                position_sigma_mm, orientation_sigma_deg: written into the simulated platform and
                used as the true noise) and its truth: frame_offset, target_offset,
                target_spread_mm, dropout_probability (see simulation/instrument.py)
    [load]      platform_mass_kg, platform_com_mm, payload_com_mm, leg_N_per_mm,
                base_joint_N_per_mm, platform_joint_N_per_mm, bending_N_per_mm, iterations,
                gravity = [gx, gy, gz] (the direction gravity acts along in {J} on a mount tilted once:
                normalised, a zero vector refused; default [0, 0, -1]; simulate writes it as the
                platform's [elastic] gravity, spec §17), tilt_axis = [ax, ay, az] (the axis in {J} a
                tilting mount turns about, like a telescope's elevation axis; normalised; default
                [1, 0, 0])
    [tracker]   noise_mm, quantum_mm, geometry_residual_mm
    [thermal]   a warm-up (spec §17; prismatic drives only): ambient_start_C, ambient_end_C (the
                hall's temperature at the first and the last sample, a linear ramp between),
                leg_spread_K (each leg's own offset from the ambient, uniform in ± this),
                time_constant_s (the legs follow the ambient through a first-order lag; 0: at once),
                expansion_ppm_per_K, expansion_spread_ppm_per_K (the true robot's α_i: this nominal
                plus a normal draw of this σ per leg) — see :class:`WarmUp`
    [poses]     calibration, validation (counts), samples_per_pose, workspace_fraction, margin_mm,
                calibration_file (a pose list, spec §3's pose columns — ``plan``'s output — relative to
                this file: the calibration poses, in its order, instead of ``calibration`` random ones;
                every pose within the nominal stroke and reading ranges, or the row is refused)
    [circle]    radius_mm, plane, points, samples_per_point, centre_offset_mm
    [[stages]]  name, load_kg, ramp_s, segments = ["calibration", "validation", "circle"],
                tilt_deg (the mount turned by this angle [deg] about tilt_axis, right-handed, within
                ±180; reached over ramp_s from the stage before's, as the payload is; default 0)

A mount that tilts: where any stage's ``tilt_deg`` is not 0, gravity at a sample with the mount at
``θ`` acts along ``Rot(tilt_axis, θ)ᵀ gravity`` in {J} (the base turned by ``θ``, the world's
gravity fixed), the robot settles under it and the log carries it per row (``Log.inputs`` ``gravity``,
spec §17 ``gravity_x gravity_y gravity_z``).

:func:`load_experiment` validates every key (a wrong type or an unknown key raises
:class:`~stewart_calib.errors.CalibError` naming the file and the key). :func:`schedule` turns an
experiment into per-sample arrays (desired pose, time, payload, stage, segment kind, the legs'
temperatures); the calibration and validation pose sets are drawn once per experiment (in that
order, from the experiment's generator) and shared by all stages, so stages are comparable.

A ``[thermal]`` warm-up's draws (the legs' offsets from the ambient, then their true expansion) come
from the seed's seventh stream (:data:`THERMAL_STREAM`, beside the closed loop's six), at load: the
experiment's platform then carries the truth as ``[thermal] true_expansion_ppm_per_K`` (the platform
file's own ``[thermal]``, or its defaults where it has none), as ``simulate`` writes it, and the true
robot's legs grow by it (:mod:`.closed_loop`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CalibError
from ..instruments.registry import instrument_kind, kind_of
from ..io.platform_file import load_platform, parse_instrument
from ..model.platform import (
    EXPANSION_LIMIT_PPM_PER_K,
    TEMPERATURE_RANGE_C,
    LegGeometry,
    Platform,
    Thermal,
    centre_too_far,
)
from ..resources import CONFIGS, read_toml
from .instrument import InstrumentTruth
from .load import LoadModel
from .trajectories import CIRCLE_PLANES, circle_poses, in_range, random_static_poses

SEGMENT_KINDS = ("calibration", "validation", "circle")


@dataclass(frozen=True)
class RobotConfig:
    """True robot: δM_base = scales · (paper Table 4 EKF errors | random draws); encoder noise.

    The default ``scale_platform_joints = 0.3`` is the tuned nim-stewart value that brings the
    uncalibrated error to the paper's Table 5/6 (``configs/experiments/paper.toml`` says why).

    Attributes:
        errors: ``"table4"`` or ``"random"``.
        scale_base_joints, scale_platform_joints, scale_lengths: factors on the δj, δd, δl blocks.
        random_spread_mm: σ of random draws [mm].
        encoder_noise_mm: σ of the logged strokes' white noise [mm].
        stroke_scale_spread: σ of the true stroke scale errors k_i (dimensionless): the encoders
            log ``q / (1 + k_i)`` for a true stroke q (spec §7).
        encoder_zero_spread_mm: σ of the encoders' zero errors z_i [mm]: they log ``q − z_i``, which
            the model sees as initial lengths ``l_i + z_i``.
    """

    errors: str = "table4"
    scale_base_joints: float = 1.0
    scale_platform_joints: float = 0.3
    scale_lengths: float = 1.0
    random_spread_mm: float = 1.0
    encoder_noise_mm: float = 0.0
    stroke_scale_spread: float = 0.0
    encoder_zero_spread_mm: float = 0.0


@dataclass(frozen=True)
class RotaryRobotConfig:
    """True servo-horn robot (spec §15): per leg i.i.d. errors of its 11 parameters.

    Attributes:
        angle_offset_limit_deg: the zero offsets o_i are uniform in ± this [deg]: a horn sits on its
            spline a fraction of a tooth off (25 teeth: 14.4° a tooth), what is left after trimming.
        horn_spread_mm, rod_spread_mm: σ of the horn and rod lengths' errors [mm].
        joint_spread_mm: σ of every coordinate of the crank centres and platform joints [mm].
        axis_tilt_spread_deg: σ of each crank axis's tilts tu_i, tw_i [deg].
        angle_scale_spread: σ of the servos' angle scale k_i: a commanded θ turns the horn by (1 + k_i) θ.
        angle_noise_deg: σ of the white error of the angle a servo holds about its command [deg].
    """

    angle_offset_limit_deg: float = 2.0
    horn_spread_mm: float = 0.2
    rod_spread_mm: float = 0.3
    joint_spread_mm: float = 0.5
    axis_tilt_spread_deg: float = 0.75
    angle_scale_spread: float = 0.02
    angle_noise_deg: float = 0.0


@dataclass(frozen=True)
class TrackerConfig:
    """Ruler noise σ [mm], quantum [mm] (50 nm), σ of the tracker's own geometry residual [mm]."""

    noise_mm: float = 0.0005
    quantum_mm: float = 5e-5
    geometry_residual_mm: float = 0.015


@dataclass(frozen=True)
class PoseSetConfig:
    """Static pose sets: counts, samples held per pose, workspace fraction, range margin [mm], and
    the calibration poses given (``(N, 6)`` [mm, rad] from ``calibration_file``; None: drawn)."""

    calibration: int = 60
    validation: int = 50
    samples_per_pose: int = 1
    workspace_fraction: float = 0.8
    margin_mm: float = 10.0
    calibration_poses: np.ndarray | None = field(default=None, compare=False)


@dataclass(frozen=True)
class CircleConfig:
    """Circle trajectory (paper §4.3): radius [mm], plane, points, samples per point, centre offset [mm]."""

    radius_mm: float = 150.0
    plane: str = "xy"
    points: int = 180
    samples_per_point: int = 1
    centre_offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)


#: the seed's stream (``SeedSequence(seed).spawn``'s index) a warm-up draws from: after the closed loop's six
THERMAL_STREAM = 6


@dataclass(frozen=True, eq=False)
class WarmUp:
    """The legs' temperatures over a simulated log and the true robot's expansion (``[thermal]``).

    Leg i at time ``t`` [s] since the first sample is at ``T_i(t) = A_lag(t) + o_i``: the ambient ramps
    linearly, ``A(t) = A_0 + ρ t`` with ``ρ = (A_1 − A_0) / t_end`` over the log's ``t_end``, and each leg
    follows it through a first-order lag of time constant ``τ`` from equilibrium at the start,
    ``A_lag(t) = A_0 + ρ (t − τ (1 − e^{−t/τ}))`` (exact for a ramp; ``τ = 0``: ``A(t)``); ``o_i`` is the
    leg's own offset (a motor's heat, a draught). The true leg's length joint to joint is scaled by
    ``1 + α_i (T_i − T_ref) · 1e-6`` (spec §17).

    Attributes:
        ambient_start_C, ambient_end_C: ``A_0``, ``A_1`` [°C].
        time_constant_s: ``τ`` [s].
        leg_offsets_K: ``(6,)`` ``o_i`` [K] (drawn uniform in ± ``leg_spread_K``).
        true_expansion_ppm_per_K: ``(6,)`` the true ``α_i`` [ppm/K] (drawn).
        reference_temperature_C: ``T_ref`` [°C], the platform's ``[thermal]``.
    """

    ambient_start_C: float
    ambient_end_C: float
    time_constant_s: float
    leg_offsets_K: np.ndarray
    true_expansion_ppm_per_K: np.ndarray
    reference_temperature_C: float = 20.0

    def leg_temperatures(self, t_s: np.ndarray) -> np.ndarray:
        """``(N, 6)`` ``T_i`` [°C] of the samples at times ``t_s (N,)`` [s] (the first is the ramp's start)."""
        t = np.asarray(t_s, dtype=float)
        elapsed = t - (t[0] if t.size else 0.0)
        duration = float(elapsed[-1]) if t.size else 0.0
        rate = (self.ambient_end_C - self.ambient_start_C) / duration if duration > 0 else 0.0
        tau = self.time_constant_s
        lagged = elapsed if tau == 0 else elapsed - tau * -np.expm1(-elapsed / tau)
        return self.ambient_start_C + rate * lagged[:, None] + self.leg_offsets_K


@dataclass(frozen=True)
class Stage:
    """One load stage: payload [kg] reached linearly over ``ramp_s`` [s] from the previous
    stage's payload, while the listed segments run in order."""

    name: str
    load_kg: float
    ramp_s: float
    segments: tuple[str, ...]
    tilt_deg: float = 0.0


@dataclass(frozen=True)
class Experiment:
    """A complete simulated experiment (see the module docstring for the TOML)."""

    name: str
    seed: int
    platform: Platform
    sample_period_s: float
    robot: RobotConfig | RotaryRobotConfig
    load: LoadModel
    tracker: TrackerConfig
    poses: PoseSetConfig
    circle: CircleConfig
    stages: tuple[Stage, ...]
    source: str = field(default="<memory>", compare=False)
    instrument: InstrumentTruth | None = None
    warm_up: WarmUp | None = None


#: [load] defaults — the tuned nim-stewart values; configs/experiments/paper.toml explains them.
LOAD_DEFAULTS = dict(
    platform_mass_kg=15.0,
    platform_com_mm=(0.0, 0.0, -40.0),
    payload_com_mm=(60.0, 40.0, 100.0),
    leg_N_per_mm=3000.0,
    base_joint_N_per_mm=1000.0,
    platform_joint_N_per_mm=1000.0,
    bending_N_per_mm=math.inf,
    iterations=2,
)


class _Table:
    """Reads one TOML table, refusing wrong types and unknown keys with file and key named."""

    def __init__(self, doc, prefix: str, source: str):
        self.source, self.prefix = source, prefix
        if not isinstance(doc, dict):
            raise self.refuse("", "a table")
        self.doc, self.used = doc, set[str]()

    def refuse(self, key: str, expected: str) -> CalibError:
        full = ".".join(k for k in (self.prefix, key) if k)
        return CalibError(f"{self.source}: key '{full}': expected {expected}")

    def number(self, key: str, default, minimum: float | None = None, integer: bool = False, allow_inf: bool = False):
        self.used.add(key)
        value = self.doc.get(key, default)
        kinds = (int,) if integer else (int, float)
        if (
            isinstance(value, bool)
            or not isinstance(value, kinds)
            or math.isnan(value)
            or (math.isinf(value) and not allow_inf)
        ):
            raise self.refuse(key, "an integer" if integer else "a finite number")
        if minimum is not None and value < minimum:
            raise self.refuse(key, f"a number ≥ {minimum}, got {value}")
        return int(value) if integer else float(value)

    def choice(self, key: str, default: str, options) -> str:
        self.used.add(key)
        value = self.doc.get(key, default)
        if value not in options:
            raise self.refuse(key, f"one of {', '.join(map(repr, options))}, got {value!r}")
        return value

    def string(self, key: str, default: str | None) -> str:
        self.used.add(key)
        value = self.doc.get(key, default)
        if not isinstance(value, str) or not value:
            raise self.refuse(key, "a non-empty string")
        return value

    def direction(self, key: str, default) -> np.ndarray:
        """A direction ``[x, y, z]``, normalised; a zero, non-finite or short vector refused."""
        self.used.add(key)
        value = self.doc.get(key, default)
        try:
            arr = np.array(value, dtype=float)
        except (TypeError, ValueError):
            arr = np.array([])
        norm = float(np.linalg.norm(arr)) if arr.shape == (3,) else math.nan
        if not (np.all(np.isfinite(arr)) and norm > 0.0):
            raise self.refuse(key, f"a direction [x, y, z] in {{J}} (a non-zero vector, normalised), got {value!r}")
        return arr / norm

    def vector3(self, key: str, default) -> tuple[float, float, float]:
        x, y, z = self.vector(key, default, 3)
        return x, y, z

    def vector(self, key: str, default, n: int) -> tuple[float, ...]:
        self.used.add(key)
        value = self.doc.get(key, default)
        try:
            arr = np.array(value, dtype=float)
        except (TypeError, ValueError):
            arr = np.array([])
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise self.refuse(key, "[x, y, z] in mm" if n == 3 else "[x, y, z mm, roll, pitch, yaw deg]")
        return tuple(float(v) for v in arr)

    def done(self, subtables: tuple[str, ...] = ()) -> None:
        unknown = sorted(set(self.doc) - self.used - set(subtables))
        if unknown:
            full = ".".join(k for k in (self.prefix, unknown[0]) if k)
            raise CalibError(f"{self.source}: key '{full}': unknown key")


def load_experiment(path: str | Path) -> Experiment:
    """Read and validate an experiment TOML file, given by path or by the name of a shipped
    experiment (``"quick"``, ``"paper"``; spec §8).

    ``platform`` is a path relative to the experiment file, or the name of a packaged platform
    (``configs/platforms/<name>.toml``, e.g. ``"nim-stewart"``).

    Raises:
        CalibError: one line naming the file and the key.
    """
    path, doc = read_toml(path, "experiments", "experiment file")
    source = str(path)
    top = _Table(doc, "", source)
    name = top.string("name", path.stem)
    seed = (
        top.number("seed", None, minimum=0, integer=True) if "seed" in doc else _missing(top, "seed", "an integer seed")
    )
    platform = _platform(
        top.string("platform", None) if "platform" in doc else _missing(top, "platform", "a path or name"), path, top
    )
    period = top.number("sample_period_s", 0.1, minimum=1e-9)

    sections = {key: _Table(doc.get(key, {}), key, source) for key in ("robot", "load", "tracker", "poses", "circle")}
    r = sections["robot"]
    rotary = platform.drive.kind == "rotary"
    robot = _rotary_robot(r) if rotary else _robot(r)
    if rotary and "load" in doc:
        raise sections["load"].refuse("", 'no [load] table: a rotary drive (kind = "rotary") is simulated rigid')
    ld, dflt = sections["load"], LOAD_DEFAULTS
    load = LoadModel(
        platform_mass_kg=ld.number("platform_mass_kg", dflt["platform_mass_kg"], minimum=0.0),
        platform_com_mm=np.array(ld.vector3("platform_com_mm", dflt["platform_com_mm"])),
        payload_com_mm=np.array(ld.vector3("payload_com_mm", dflt["payload_com_mm"])),
        **{
            key: ld.number(key, dflt[key], minimum=1e-9, allow_inf=True)
            for key in ("leg_N_per_mm", "base_joint_N_per_mm", "platform_joint_N_per_mm", "bending_N_per_mm")
        },
        iterations=ld.number("iterations", dflt["iterations"], minimum=1, integer=True),
        gravity=ld.direction("gravity", [0.0, 0.0, -1.0]),
        tilt_axis=ld.direction("tilt_axis", [1.0, 0.0, 0.0]),
    )
    # the platform file simulate writes carries these centres as [elastic]'s: refused here by [elastic]'s rule,
    # not written into a platform every other command refuses
    for key in ("platform_com_mm", "payload_com_mm"):
        if not isinstance(platform.drive, LegGeometry):  # a rotary drive takes no [load] (refused above)
            break
        too_far = centre_too_far(platform.drive, getattr(load, key))
        if too_far:
            raise ld.refuse(key, too_far)
    tr = sections["tracker"]
    tracker = TrackerConfig(
        noise_mm=tr.number("noise_mm", TrackerConfig.noise_mm, minimum=0.0),
        quantum_mm=tr.number("quantum_mm", TrackerConfig.quantum_mm, minimum=0.0),
        geometry_residual_mm=tr.number("geometry_residual_mm", TrackerConfig.geometry_residual_mm, minimum=0.0),
    )
    ps = sections["poses"]
    given = _calibration_file(ps, path, platform) if "calibration_file" in ps.doc else None
    poses = PoseSetConfig(
        calibration=len(given)
        if given is not None
        else ps.number("calibration", PoseSetConfig.calibration, minimum=0, integer=True),
        validation=ps.number("validation", PoseSetConfig.validation, minimum=0, integer=True),
        samples_per_pose=ps.number("samples_per_pose", PoseSetConfig.samples_per_pose, minimum=1, integer=True),
        workspace_fraction=ps.number("workspace_fraction", PoseSetConfig.workspace_fraction, minimum=0.0),
        margin_mm=ps.number("margin_mm", PoseSetConfig.margin_mm, minimum=0.0),
        calibration_poses=given,
    )
    if poses.workspace_fraction > 1.0:
        raise ps.refuse("workspace_fraction", "a fraction in [0, 1]")
    c = sections["circle"]
    circle = CircleConfig(
        radius_mm=c.number("radius_mm", CircleConfig.radius_mm, minimum=0.0),
        plane=c.choice("plane", CircleConfig.plane, tuple(CIRCLE_PLANES)),
        points=c.number("points", CircleConfig.points, minimum=1, integer=True),
        samples_per_point=c.number("samples_per_point", CircleConfig.samples_per_point, minimum=1, integer=True),
        centre_offset_mm=c.vector3("centre_offset_mm", CircleConfig.centre_offset_mm),
    )
    for table in sections.values():
        table.done()
    platform, instrument = _instrument(doc, platform, source)
    platform, warm_up = _warm_up(doc, platform, seed, source)

    top.used.add("stages")
    raw_stages = doc.get("stages")
    if not isinstance(raw_stages, list) or not raw_stages:
        raise top.refuse("stages", "one or more [[stages]] tables")
    stages = tuple(_stage(raw, f"stages[{k}]", source) for k, raw in enumerate(raw_stages))
    top.done(subtables=(*sections, "instrument", "thermal"))
    return Experiment(
        name, seed, platform, period, robot, load, tracker, poses, circle, stages, source, instrument, warm_up
    )


def _robot(r: _Table) -> RobotConfig:
    """A prismatic drive's ``[robot]`` (:class:`RobotConfig`)."""
    return RobotConfig(
        errors=r.choice("errors", "table4", ("table4", "random")),
        scale_base_joints=r.number("scale_base_joints", 1.0),
        scale_platform_joints=r.number("scale_platform_joints", RobotConfig.scale_platform_joints),
        scale_lengths=r.number("scale_lengths", 1.0),
        random_spread_mm=r.number("random_spread_mm", 1.0, minimum=0.0),
        encoder_noise_mm=r.number("encoder_noise_mm", 0.0, minimum=0.0),
        stroke_scale_spread=r.number("stroke_scale_spread", 0.0, minimum=0.0),
        encoder_zero_spread_mm=r.number("encoder_zero_spread_mm", 0.0, minimum=0.0),
    )


def _rotary_robot(r: _Table) -> RotaryRobotConfig:
    """A rotary drive's ``[robot]`` (:class:`RotaryRobotConfig`; spec §15)."""
    defaults = RotaryRobotConfig()
    config = RotaryRobotConfig(
        **{
            key: r.number(key, getattr(defaults, key), minimum=0.0)
            for key in RotaryRobotConfig.__dataclass_fields__  # every one a spread or limit ≥ 0
        }
    )
    if config.angle_offset_limit_deg > 180.0:
        raise r.refuse("angle_offset_limit_deg", f"a zero offset within 180 deg, got {config.angle_offset_limit_deg}")
    if config.angle_scale_spread > 0.1:
        raise r.refuse("angle_scale_spread", f"a σ of the angle scale within 0.1, got {config.angle_scale_spread}")
    return config


#: the experiment's [instrument] keys that describe the truth, not the nominal instrument
_TRUTH_KEYS = ("frame_offset", "target_offset", "target_spread_mm", "dropout_probability")


def _instrument(doc: dict, platform: Platform, source: str) -> tuple[Platform, InstrumentTruth | None]:
    """The experiment's ``[instrument]``: the nominal instrument (replacing the platform file's)
    and the truth offsets; none: the platform's own instrument, simulated without offsets."""
    from dataclasses import replace

    if "instrument" not in doc:
        outside = instrument_kind(platform).outside
        return platform, (InstrumentTruth(np.zeros(6), np.zeros(6)) if outside else None)
    raw = doc["instrument"]
    t = _Table(raw, "instrument", source)
    nominal = {key: value for key, value in raw.items() if key not in _TRUTH_KEYS}
    instrument = parse_instrument(nominal, source)
    if not kind_of(instrument).outside:  # part of the robot: no truth of its own to offset
        if set(raw) - {"kind"}:
            raise t.refuse(sorted(set(raw) - {"kind"})[0], f'no other key with kind = "{instrument.kind}"')
        return platform, None
    t.used.update(nominal)
    truth = InstrumentTruth(
        frame_offset=np.array(t.vector("frame_offset", [0.0] * 6, 6)),
        target_offset=np.array(t.vector("target_offset", [0.0] * 6, 6)),
        target_spread_mm=t.number("target_spread_mm", 0.0, minimum=0.0),
        dropout_probability=t.number("dropout_probability", 0.0, minimum=0.0),
    )
    if truth.dropout_probability >= 1.0:
        raise t.refuse("dropout_probability", "a probability in [0, 1)")
    t.done()
    return replace(platform, instrument=instrument), truth


def _warm_up(doc: dict, platform: Platform, seed: int, source: str) -> tuple[Platform, WarmUp | None]:
    """The experiment's ``[thermal]`` warm-up (:class:`WarmUp`; its draws from :data:`THERMAL_STREAM`)
    and the platform with the truth in its ``[thermal]``; none: the platform as it is, no warm-up."""
    from dataclasses import replace

    if "thermal" not in doc:
        return platform, None
    t = _Table(doc["thermal"], "thermal", source)
    if platform.drive.kind != "prismatic":
        raise t.refuse("", f"no [thermal] table: a {platform.drive.kind} drive is simulated without a warm-up (yet)")
    low, high = TEMPERATURE_RANGE_C
    start = t.number("ambient_start_C", 20.0)
    end = t.number("ambient_end_C", start)
    spread = t.number("leg_spread_K", 0.0, minimum=0.0)
    tau = t.number("time_constant_s", 0.0, minimum=0.0)
    nominal = t.number("expansion_ppm_per_K", 11.5)
    sigma = t.number("expansion_spread_ppm_per_K", 0.0, minimum=0.0)
    t.done()
    for key, value in (("ambient_start_C", start), ("ambient_end_C", end)):
        if not (low <= value - spread and value + spread <= high):
            expected = f"legs within {low:g}…{high:g} °C (spec §17) with leg_spread_K = {spread:g}, got {value:g}"
            raise t.refuse(key, expected)
    thermal_rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(THERMAL_STREAM + 1)[THERMAL_STREAM])
    offsets = thermal_rng.uniform(-spread, spread, platform.drive.n_legs)
    alpha = nominal + sigma * thermal_rng.standard_normal(platform.drive.n_legs)
    if np.any(np.abs(alpha) > EXPANSION_LIMIT_PPM_PER_K):
        key = "expansion_ppm_per_K" if abs(nominal) > EXPANSION_LIMIT_PPM_PER_K else "expansion_spread_ppm_per_K"
        drew = alpha.round(1).tolist()
        raise t.refuse(key, f"true expansions within ±{EXPANSION_LIMIT_PPM_PER_K:g} ppm/K, drew {drew}")
    table = platform.thermal or Thermal()
    platform = replace(platform, thermal=replace(table, true_expansion_ppm_per_K=alpha))
    return platform, WarmUp(start, end, tau, offsets, alpha, float(table.reference_temperature_C))


def _missing(table: _Table, key: str, expected: str):
    raise table.refuse(key, f"{expected} (missing)")


def _platform(value: str, experiment_path: Path, table: _Table) -> Platform:
    for candidate in (experiment_path.parent / value, CONFIGS / "platforms" / f"{value}.toml"):
        if candidate.is_file():
            platform = load_platform(candidate)
            platform.required_workspace("the simulation")  # refused here, before any output
            return platform
    raise table.refuse("platform", f"a platform file relative to the experiment or a packaged name, got {value!r}")


def _calibration_file(table: _Table, experiment_path: Path, platform: Platform) -> np.ndarray:
    """``[poses] calibration_file``'s poses ``(N, 6)`` [mm, rad]: a pose list relative to the experiment
    file, each pose within the nominal ranges (the true robot reaches the others only by chance)."""
    from ..io import read_pose_list

    if "calibration" in table.doc:
        raise table.refuse("calibration", "no count where calibration_file gives the poses")
    poses = read_pose_list(experiment_path.parent / table.string("calibration_file", None))
    outside = np.flatnonzero(~in_range(platform, poses, 0.0))
    if outside.size:
        raise table.refuse(
            "calibration_file",
            f"poses within the nominal stroke and reading ranges; pose {outside[0] + 1} (row {outside[0] + 2}) "
            f"is not, nor are {outside.size - 1} other(s)",
        )
    return poses


def _stage(raw, prefix: str, source: str) -> Stage:
    t = _Table(raw, prefix, source)
    t.used.add("segments")
    segments = raw.get("segments", list(SEGMENT_KINDS))
    if not isinstance(segments, list) or not segments or any(s not in SEGMENT_KINDS for s in segments):
        raise t.refuse("segments", f"a non-empty list drawn from {list(SEGMENT_KINDS)}")
    stage = Stage(
        name=t.string("name", None) if "name" in raw else _missing(t, "name", "a stage name"),
        load_kg=t.number("load_kg", 0.0, minimum=0.0),
        ramp_s=t.number("ramp_s", 0.0, minimum=0.0),
        segments=tuple(segments),
        tilt_deg=t.number("tilt_deg", 0.0),
    )
    if abs(stage.tilt_deg) > 180.0:
        raise t.refuse("tilt_deg", f"an angle within ±180 deg, got {stage.tilt_deg}")
    t.done()
    return stage


@dataclass(frozen=True)
class Schedule:
    """Per-sample plan of an experiment, N samples.

    Attributes:
        t_s: ``(N,)`` [s]. desired_poses: ``(N, 6)`` [mm, rad]. payload_kg: ``(N,)`` payload in
        force (ramped) [kg]. stages: ``(N,)`` stage names. kinds: ``(N,)`` segment kinds.
        pose_index: ``(N,)`` index of the pose within its segment (static pose or circle point).
        gravity: ``(N, 3)`` the unit vector in {J} gravity acts along at each sample where the mount
        tilts (a stage's ``tilt_deg``), else None (``[load] gravity`` throughout).
        temperature_C: ``(N, 6)`` each leg's temperature [°C] of a warm-up (:class:`WarmUp`), else None.
    """

    t_s: np.ndarray
    desired_poses: np.ndarray
    payload_kg: np.ndarray
    stages: np.ndarray
    kinds: np.ndarray
    pose_index: np.ndarray
    gravity: np.ndarray | None = None
    temperature_C: np.ndarray | None = None


def tilted_gravity(gravity: np.ndarray, axis: np.ndarray, tilt_deg: np.ndarray) -> np.ndarray:
    """``(N, 3)`` gravity's unit vector in {J} with the mount turned by ``tilt_deg (N,)`` [deg] about the
    unit ``axis`` (in {J}, right-handed): ``Rot(axis, θ)ᵀ gravity``, Rodrigues' formula with ``−θ``."""
    theta = -np.radians(np.asarray(tilt_deg, dtype=float))[:, None]
    g, a = np.asarray(gravity, dtype=float), np.asarray(axis, dtype=float)
    return g * np.cos(theta) + np.cross(a, g) * np.sin(theta) + a * (a @ g) * (1.0 - np.cos(theta))


def schedule(experiment: Experiment, rng: np.random.Generator) -> Schedule:
    """Lay the stages' segments out in time (draws the calibration, then validation poses)."""
    e = experiment
    sets = {
        kind: given
        if given is not None
        else random_static_poses(e.platform, count, rng, e.poses.workspace_fraction, e.poses.margin_mm)
        for kind, count, given in (
            ("calibration", e.poses.calibration, e.poses.calibration_poses),
            ("validation", e.poses.validation, None),
        )
    }
    sets["circle"] = circle_poses(
        e.platform.required_workspace("the circle").home,
        e.circle.radius_mm,
        e.circle.plane,
        e.circle.points,
        e.circle.centre_offset_mm,
    )
    hold = {
        "calibration": e.poses.samples_per_pose,
        "validation": e.poses.samples_per_pose,
        "circle": e.circle.samples_per_point,
    }

    # filled in place, segment by segment: a long schedule is held once, not also as its pieces
    n = sum(len(sets[kind]) * hold[kind] for stage in e.stages for kind in stage.segments)
    desired, index = np.empty((n, 6)), np.empty(n, dtype=int)
    stages, kinds = np.empty(n, dtype=object), np.empty(n, dtype=object)
    stage_start, lo = [], 0
    for stage in e.stages:
        stage_start.append(lo)
        for kind in stage.segments:
            rows = slice(lo, lo + len(sets[kind]) * hold[kind])
            index[rows] = np.repeat(np.arange(len(sets[kind])), hold[kind])
            np.take(sets[kind], index[rows], axis=0, out=desired[rows])
            stages[rows], kinds[rows] = stage.name, kind
            lo = rows.stop
    t_s = np.arange(n) * e.sample_period_s

    # Payload and tilt: linear ramps from the previous stage's over ramp_s from the stage's start.
    payload, tilt = np.empty(n), np.empty(n)
    bounds = stage_start + [n]
    previous, previous_tilt = 0.0, 0.0
    for stage, lo, hi in zip(e.stages, bounds[:-1], bounds[1:], strict=True):
        elapsed = t_s[lo:hi] - (t_s[lo] if hi > lo else 0.0)
        ramp = np.ones_like(elapsed) if stage.ramp_s == 0 else np.clip(elapsed / stage.ramp_s, 0.0, 1.0)
        payload[lo:hi] = previous + (stage.load_kg - previous) * ramp
        tilt[lo:hi] = previous_tilt + (stage.tilt_deg - previous_tilt) * ramp
        previous, previous_tilt = stage.load_kg, stage.tilt_deg
    tilting = any(stage.tilt_deg != 0.0 for stage in e.stages)
    gravity = tilted_gravity(e.load.gravity, e.load.tilt_axis, tilt) if tilting else None
    temperature = None if e.warm_up is None else e.warm_up.leg_temperatures(t_s)
    return Schedule(t_s, desired, payload, stages, kinds, index, gravity, temperature)
