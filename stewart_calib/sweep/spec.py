"""The sweep specification (spec §9): a TOML grid of simulated studies, validated at load.

Layout (``configs/sweeps/smoke.toml`` documents every key)::

    name = "smoke"
    methods = ["ls", "ekf", "isam2"]     # estimators run on every task's data
    seeds = 4                            # seeds first_seed … first_seed + seeds − 1
    first_seed = 0
    checkpoints = [20, 40]               # optional: rms_over_crb_at_N after N samples
    refit_at_checkpoints = ["ls"]        # batch methods refitted on each checkpoint's prefix

    [grid]                               # every setting: one value, or a list of values (an axis)
    platform = ["nim-stewart", "compact"]
    drive = "prismatic"                  # the legs: prismatic, or rotary (servo horns, spec §15)
    reading_sigma_mm = [0.002, 0.02]
    "ekf.gate_probability" = [0.0, 0.9999]   # estimator setting (section.key) as an axis

    [families.compact]                   # a random family of drive geometry (see Family)
    base_radius_mm = [550.0, 650.0]

A **cell** is one combination of grid values; a **task** is one cell × one seed. The cell's
id is a hash of everything that decides a task's rows except the seed (settings, resolved
platform or family, methods, checkpoints, package version), so finished tasks are found again
by content: extending ``seeds``, adding a noise level or rerunning after an interruption
recomputes only what is missing, and a changed platform file never reuses stale rows.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..config import EstimatorConfig, NoiseConfig, config_from_dict
from ..errors import CalibError
from ..estimators import METHODS
from ..instruments import MODELS
from ..io.platform_file import load_platform, platform_to_toml
from ..model import kinematics as kin
from ..model.platform import LegGeometry, Platform
from ..model.rotary import RotaryLegs
from ..resources import CONFIGS, read_toml

#: Samples (and validation poses) of one task at most: a task holds its log in memory, and a
#: study wants many short runs, not one endless one (``stewart-calib calibrate`` streams those).
MAX_SAMPLES = 1_000_000

#: Seeds are stored as Parquet int64.
MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class Setting:
    """One simulated setting of the grid: name, type, default, and what values it accepts."""

    name: str
    kind: type
    default: object
    minimum: float | None = None
    maximum: float | None = None
    positive: bool = False
    doc: str = ""


#: How the payload changes over a log (``payload_schedule``), and what each means.
SCHEDULES_DOC = (
    "constant (payload_kg on every sample)",
    "step (0 kg, then payload_kg from the middle sample on)",
    "stages (0, ½ and 1 × payload_kg, a third of the log each)",
)
SCHEDULES = tuple(doc.split()[0] for doc in SCHEDULES_DOC)

#: The simulated settings, in column order. Estimator settings (``section.key``) follow them.
SETTINGS = (
    Setting(
        "platform",
        str,
        "nim-stewart",
        doc="shipped platform name, platform file (relative to the spec) or a [families] name, of the cell's "
        'drive (default: nim-stewart, or servo-hexapod where drive = "rotary")',
    ),
    Setting(
        "drive",
        str,
        "prismatic",
        doc="the legs: prismatic (6-6 legs whose length is the stroke) or rotary (servo horns and rods, 6-RSS, "
        "spec §15: 66 unknowns, angles logged, measured by an outside instrument; scored in the motion from home)",
    ),
    Setting("instrument", str, "tracker", doc="what measures the platform (spec §7): tracker, pose or points"),
    Setting("instrument_sigma_mm", float, 0.05, positive=True, doc="pose / points: σ of one measured coordinate [mm]"),
    Setting("instrument_sigma_deg", float, 0.05, positive=True, doc="pose: σ of one measured angle [deg]"),
    Setting("targets", int, 3, minimum=1, maximum=3, doc="points: targets on the platform (1 to 3)"),
    Setting("dropout_rate", float, 0.0, minimum=0.0, maximum=0.9, doc="points: chance a target is not seen"),
    Setting("frame_offset_mm", float, 50.0, minimum=0.0, doc="pose / points: true frame's offset from nominal [mm]"),
    Setting("frame_offset_deg", float, 10.0, minimum=0.0, maximum=90.0, doc="pose / points: its rotation [deg]"),
    Setting(
        "stroke_scale_error",
        float,
        0.0,
        minimum=0.0,
        maximum=0.2,
        doc="σ of the true stroke scales k_i (rotary: the servos' angle scales, φ = (1 + k) θ + o)",
    ),
    Setting("samples", int, 200, minimum=1, maximum=MAX_SAMPLES, doc="samples per run, one per random workspace pose"),
    Setting("rate_hz", float, 10.0, positive=True, doc="sample rate [Hz] (sets Δt of the random walk)"),
    Setting(
        "workspace_fraction",
        float,
        0.8,
        positive=True,
        maximum=1.0,
        doc="poses uniform in this fraction of the workspace box",
    ),
    Setting(
        "error_sigma_mm",
        float,
        1.0,
        minimum=0.0,
        doc="σ of the true δM's i.i.d. normal draw [mm] (rotary: of each coordinate of the crank centres and "
        "platform joints)",
    ),
    Setting("reading_sigma_mm", float, 0.002, positive=True, doc="σ of the tracker readings' white noise [mm]"),
    Setting("stroke_sigma_mm", float, 0.001, positive=True, doc="prismatic: σ of the logged strokes' white noise [mm]"),
    Setting(
        "noise_scale",
        float,
        1.0,
        positive=True,
        doc="the simulated reading noise (tracker or outside instrument) is this multiple of what the "
        "estimators are told",
    ),
    Setting("drift_mm_per_sqrt_s", float, 0.0, minimum=0.0, doc="prismatic: random walk of the true δM [mm/√s]"),
    Setting("glitch_rate", float, 0.0, minimum=0.0, maximum=1.0, doc="fraction of samples with one glitched reading"),
    Setting("glitch_size_mm", float, 1.0, minimum=0.0, doc="size of a glitch [mm] (added with a random sign)"),
    Setting("validation_poses", int, 50, minimum=1, maximum=MAX_SAMPLES, doc="fresh poses of the closed-loop check"),
    Setting(
        "platform_mass_kg",
        float,
        0.0,
        minimum=0.0,
        doc="prismatic: the moving platform's mass [kg], its centre at {D}'s origin (spec §10); 0: a rigid "
        "robot, the other elastic settings ignored",
    ),
    Setting("compliance_mm_per_kN", float, 1.0, minimum=0.0, doc="the legs' true axial compliance, their mean [mm/kN]"),
    Setting("compliance_spread", float, 0.0, minimum=0.0, maximum=1.0, doc="relative σ of each leg's true compliance"),
    Setting("payload_kg", float, 0.0, minimum=0.0, doc="the payload at its heaviest [kg], its centre at {D}'s origin"),
    Setting("payload_schedule", str, "constant", doc="the payload over the log: " + ", ".join(SCHEDULES_DOC)),
    Setting("payload_known", bool, True, doc="the log carries each sample's load_kg (else the estimators take 0 kg)"),
    Setting(
        "elastic_model",
        bool,
        True,
        doc="the estimators model the compliance (the platform's [elastic]: nominal 0, default prior σ), "
        "else they calibrate the elastic robot as a rigid one",
    ),
    Setting(
        "angle_sigma_deg",
        float,
        0.05,
        positive=True,
        doc="rotary: σ of the angle a servo holds about its logged command [deg] (white; the estimators are told it)",
    ),
    Setting(
        "angle_offset_limit_deg",
        float,
        2.0,
        minimum=0.0,
        maximum=7.2,
        doc="rotary: the true zero offsets o_i are uniform in ± this [deg] (a horn a fraction of a spline tooth "
        "off, 14.4° a tooth on a 25-tooth spline, after trimming by eye)",
    ),
    Setting("horn_spread_mm", float, 0.2, minimum=0.0, doc="rotary: σ of the true horn lengths' errors [mm]"),
    Setting("rod_spread_mm", float, 0.3, minimum=0.0, doc="rotary: σ of the true rod lengths' errors [mm]"),
    Setting(
        "axis_tilt_spread_deg",
        float,
        0.75,
        minimum=0.0,
        maximum=10.0,
        doc="rotary: σ of each servo shaft's true tilts tu_i, tw_i [deg] (a servo in a printed pocket)",
    ),
)
SETTINGS_BY_NAME = {s.name: s for s in SETTINGS}

#: The leg kinds a cell simulates (spec §15), and the platform a cell of each takes when the grid names none.
DRIVES = ("prismatic", "rotary")
DEFAULT_PLATFORMS = {"prismatic": "nim-stewart", "rotary": "servo-hexapod"}

#: Settings only a rotary cell reads: a cell's id leaves them out at their defaults (:func:`_identity_settings`).
ROTARY_SETTINGS = (
    "drive",
    "angle_sigma_deg",
    "angle_offset_limit_deg",
    "horn_spread_mm",
    "rod_spread_mm",
    "axis_tilt_spread_deg",
)

#: Settings of prismatic legs alone: the elastic robot (its legs' axial compliance, spec §10) and the drift
#: of δM in mm; a rotary cell refuses any value but the default.
PRISMATIC_SETTINGS = (
    "drift_mm_per_sqrt_s",
    "platform_mass_kg",
    "compliance_mm_per_kN",
    "compliance_spread",
    "payload_kg",
    "payload_schedule",
    "payload_known",
    "elastic_model",
)

#: Instruments the sweep simulates (spec §7): every kind.
INSTRUMENTS = tuple(MODELS)

#: Keys of a [families.NAME] table besides the four ring dimensions.
FAMILY_DIMENSIONS = ("base_radius_mm", "platform_radius_mm", "base_half_angle_deg", "platform_half_angle_deg")


@dataclass(frozen=True)
class Family:
    """A random family of drive geometry: three pairs of legs on two rings (the 6-6 layout of
    nim-stewart and of most hexapods), each dimension fixed or drawn uniformly per run.

    Leg ``2k + m`` (k = 0, 1, 2; m = 0, 1) runs from base angle ``120k ∓ a`` on a circle of
    ``base_radius_mm`` to platform angle ``120k ∓ b`` on ``platform_radius_mm`` (``a``, ``b``:
    the half angles [deg]). Joint heights, tracker, ranges and workspace are those of ``like``;
    initial lengths are the leg lengths at home, so every stroke is 0 at home.

    A family is of its ``like``'s drive (:attr:`kind`): a rotary ``like`` (a servo build, spec §15)
    puts the servo shafts on the base ring instead (:func:`servo_ring_platform`).

    Attributes:
        name: the family's name (the ``platform`` value that selects it).
        like: the platform everything but the drive rings comes from.
        ranges: ``(4, 2)`` ``[low, high]`` of :data:`FAMILY_DIMENSIONS` (low = high: fixed).
    """

    name: str
    like: Platform
    ranges: np.ndarray

    @property
    def kind(self) -> str:
        """The drive's kind (``prismatic`` | ``rotary``): its ``like``'s."""
        return self.like.drive.kind

    def draw(self, rng: np.random.Generator) -> Platform:
        """One platform of the family (draws only the dimensions that have a range)."""
        low, high = self.ranges[:, 0], self.ranges[:, 1]
        values = np.where(high > low, low + (high - low) * rng.random(len(low)), low)
        base_radius, platform_radius, base_half_angle, platform_half_angle = values
        build = servo_ring_platform if self.kind == "rotary" else ring_platform
        return build(self.like, base_radius, platform_radius, base_half_angle, platform_half_angle, self.name)


def servo_ring_platform(
    like: Platform,
    base_radius_mm: float,
    platform_radius_mm: float,
    base_half_angle_deg: float,
    platform_half_angle_deg: float,
    name: str,
) -> Platform:
    """``like``'s servo build (spec §15) with its servo shafts and platform joints on two rings (see
    :class:`Family` and :meth:`~stewart_calib.model.rotary.RotaryLegs.on_rings`): horns, heights, angle
    range, instrument and workspace are ``like``'s, the rods span the horns' tips to the platform joints
    at home, so every angle is 0 there (the horns level)."""
    legs = like.drive
    if not isinstance(legs, RotaryLegs):
        raise ValueError(f"a servo ring platform is built on a rotary platform, got a {legs.kind} drive")
    home = kin.pose_to_rt(like.required_workspace("a servo ring platform").home)
    drive = legs.on_rings(base_radius_mm, platform_radius_mm, base_half_angle_deg, platform_half_angle_deg, home)
    return dataclasses.replace(
        like, name=name, drive=drive, description=f"servo ring family '{name}' drawn from {like.name}"
    )


def ring_platform(
    like: Platform,
    base_radius_mm: float,
    platform_radius_mm: float,
    base_half_angle_deg: float,
    platform_half_angle_deg: float,
    name: str,
) -> Platform:
    """``like`` with the drive rebuilt on two rings (see :class:`Family`)."""
    centres = np.repeat([0.0, 120.0, 240.0], 2)
    signs = np.tile([-1.0, 1.0], 3)
    base_angles = np.radians(centres + signs * base_half_angle_deg)
    platform_angles = np.radians(centres + signs * platform_half_angle_deg)
    base = np.column_stack(
        [
            base_radius_mm * np.cos(base_angles),
            base_radius_mm * np.sin(base_angles),
            like.prismatic_drive("a sweep").base_joints[:, 2],
        ]
    )
    plat = np.column_stack(
        [
            platform_radius_mm * np.cos(platform_angles),
            platform_radius_mm * np.sin(platform_angles),
            like.drive.platform_joints[:, 2],
        ]
    )
    home_t = like.required_workspace("a ring platform").home[:3]
    lengths = np.linalg.norm(home_t + plat - base, axis=1)  # home at level orientation: R = I
    drive = LegGeometry(base, plat, lengths)
    return Platform(
        name=name,
        drive=drive,
        tracker=like.tracker,
        stroke_range=like.stroke_range,
        reading_range=like.reading_range,
        workspace=like.workspace,
        description=f"ring family '{name}' drawn from {like.name}",
    )


@dataclass(frozen=True)
class Cell:
    """One combination of grid values.

    Attributes:
        id: 12 hex digits, the content hash (see the module docstring).
        index: position in the spec's grid order (rows are sorted by it).
        settings: setting name → value, simulated settings first (column order).
        platform: the resolved platform, or the family each run draws from.
        estimator_config: the estimators' settings: their noise model matched to the simulated
            one (reading and stroke σ, random walk = drift), then the cell's ``section.key`` values.
    """

    id: str
    index: int
    settings: dict
    platform: Platform | Family
    estimator_config: EstimatorConfig


@dataclass(frozen=True)
class SweepSpec:
    """A parsed sweep spec: the run-wide settings and the grid (its cells in grid order).

    The grid is held as its axes: :attr:`n_tasks` counts it without building a cell, so a spec
    of a billion tasks is refused at once (:func:`stewart_calib.sweep.runner.plan_sweep`); the
    cells are built on first use of :attr:`cells`.
    """

    name: str
    source: str
    methods: tuple[str, ...]
    seeds: range
    checkpoints: tuple[int, ...]
    refit_at_checkpoints: tuple[str, ...]
    axes: dict
    platforms: dict
    run_wide: dict
    platform_named: bool = True

    @property
    def n_cells(self) -> int:
        return math.prod(len(values) for values in self.axes.values())

    @property
    def n_tasks(self) -> int:
        return self.n_cells * len(self.seeds)

    @functools.cached_property
    def cells(self) -> tuple[Cell, ...]:
        """Every combination of the grid's values, in grid order (see :class:`Cell`)."""
        names = list(self.axes)
        cells = []
        for index, values in enumerate(itertools.product(*self.axes.values())):
            settings = dict(zip(names, values, strict=True))
            if not self.platform_named:
                settings["platform"] = DEFAULT_PLATFORMS[settings["drive"]]
            platform = self.platforms[settings["platform"]]
            config = _estimator_config(settings, self.source)
            identity = {"settings": _identity_settings(settings), "platform": _fingerprint(platform), **self.run_wide}
            digest = hashlib.blake2b(json.dumps(identity, sort_keys=True).encode(), digest_size=6).hexdigest()
            cells.append(Cell(digest, index, settings, platform, config))
        return tuple(cells)

    @property
    def swept(self) -> list[str]:
        """Settings with more than one value (the study's axes), in column order."""
        return [name for name, values in self.axes.items() if len(values) > 1]

    def pilot(self, seeds: int) -> SweepSpec:
        """The same study on its first ``seeds`` seeds (its tasks are the full study's: a pilot
        run's rows are kept when the full study runs into the same directory)."""
        if seeds < 1:
            raise CalibError(f"--seeds: expected at least 1 seed, got {seeds}")
        return dataclasses.replace(self, seeds=self.seeds[:seeds])

    def tasks(self) -> list[tuple[Cell, int]]:
        """Every (cell, seed), cell-major."""
        return [(cell, seed) for cell in self.cells for seed in self.seeds]


TOP_KEYS = (
    "name",
    "description",
    "methods",
    "seeds",
    "first_seed",
    "checkpoints",
    "refit_at_checkpoints",
    "grid",
    "families",
)


def load_spec(path: str | Path) -> SweepSpec:
    """Read and validate a sweep spec: a path, or the name of a shipped one (``smoke``, ``study``).

    Raises:
        CalibError: one line naming the file and the key (an unknown key, an unknown method or
            instrument, a wrong type or a value out of range).
    """
    path, doc = read_toml(path, "sweeps", "sweep spec")
    return parse_spec(doc, path)


def parse_spec(doc: dict, path: str | Path) -> SweepSpec:
    """Validate a spec already read from TOML; ``path`` names it and anchors relative platform files."""
    path = Path(path)
    source = str(path)

    def refuse(key: str, expected: str) -> CalibError:
        return CalibError(f"{source}: key '{key}': {expected}")

    for key in doc:
        if key not in TOP_KEYS:
            raise refuse(key, f"unknown key: expected one of {', '.join(TOP_KEYS)}")
    name = doc.get("name", path.stem)
    if not isinstance(name, str) or not name:
        raise refuse("name", "expected a non-empty string")

    methods = _string_list(doc.get("methods", list(METHODS)), "methods", refuse)
    for method in methods:
        if method not in METHODS:
            raise refuse("methods", f"unknown method '{method}': expected one of {', '.join(METHODS)}")
    seeds = (
        _integer(doc.get("seeds"), "seeds", 1, refuse)
        if "seeds" in doc
        else _raise(refuse("seeds", "expected a number of seeds (missing)"))
    )
    first_seed = _integer(doc.get("first_seed", 0), "first_seed", 0, refuse)
    if first_seed + seeds - 1 > MAX_SEED:
        raise refuse("first_seed", f"expected first_seed + seeds − 1 ≤ 2⁶³ − 1, got {first_seed + seeds - 1}")
    checkpoints = doc.get("checkpoints", [])
    if not isinstance(checkpoints, list):
        raise refuse("checkpoints", "expected a list of sample counts")
    checkpoints = tuple(sorted({_integer(n, "checkpoints", 1, refuse) for n in checkpoints}))
    refit = _string_list(doc.get("refit_at_checkpoints", []), "refit_at_checkpoints", refuse)
    for method in refit:
        if method not in methods:
            raise refuse("refit_at_checkpoints", f"method '{method}' is not in 'methods'")

    families = _families(doc.get("families", {}), path, refuse)
    axes = _axes(doc.get("grid", {}), source, refuse)
    for value in axes["instrument"]:
        if value not in INSTRUMENTS:
            raise refuse(
                "grid.instrument",
                f"unknown instrument '{value}': expected one of {', '.join(INSTRUMENTS)} (what the simulator supports)",
            )
        unable = [m for m in methods if value not in METHODS[m].instruments]
        if unable:
            raise refuse(
                "methods", f"method '{unable[0]}' cannot calibrate with instrument '{value}' (grid.instrument)"
            )
    for value in axes["drive"]:
        if value not in DRIVES:
            raise refuse("grid.drive", f"unknown drive '{value}': expected one of {', '.join(DRIVES)}")
    if "rotary" in axes["drive"]:
        _check_rotary(axes, methods, refuse)
    for value in axes["payload_schedule"]:
        if value not in SCHEDULES:
            raise refuse("grid.payload_schedule", f"unknown schedule '{value}': expected one of {', '.join(SCHEDULES)}")
    if checkpoints and max(checkpoints) > min(axes["samples"]):
        raise refuse(
            "checkpoints",
            f"expected sample counts ≤ the smallest 'samples' ({min(axes['samples'])}), got {max(checkpoints)}",
        )
    platform_named = "platform" in doc.get("grid", {})
    platforms: dict[str, Platform | Family] = {}
    for drive in axes["drive"]:
        for value in axes["platform"] if platform_named else [DEFAULT_PLATFORMS[drive]]:
            platform = platforms.get(value) or _platform(value, families, path, refuse)
            kind = platform.kind if isinstance(platform, Family) else platform.drive.kind
            if kind != drive:
                raise refuse(
                    "grid.platform",
                    f"{_shown(value)} is a {kind} platform; the cells of drive = {drive!r} take a {drive} one "
                    f"(shipped: {DEFAULT_PLATFORMS[drive]}, or a [families] table like one)",
                )
            platforms[value] = platform

    run_wide = {
        "methods": list(methods),
        "checkpoints": list(checkpoints),
        "refit_at_checkpoints": list(refit),
        "version": __version__,
    }
    return SweepSpec(
        name,
        source,
        tuple(methods),
        range(first_seed, first_seed + seeds),
        checkpoints,
        tuple(refit),
        axes,
        platforms,
        run_wide,
        platform_named,
    )


def _check_rotary(axes: dict, methods: list[str], refuse) -> None:
    """Refuse what a rotary cell cannot simulate or calibrate: the in-situ tracker (the sweep's is a
    prismatic leg set), the paper's EKF (its error Jacobian is the prismatic legs'), an elastic robot (the
    axial compliance of prismatic legs, spec §10) and a drift of δM in mm/√s (which a servo's angles have no
    rate of)."""
    if "tracker" in axes["instrument"]:
        raise refuse(
            "grid.instrument",
            'drive = "rotary" is measured from outside the robot (spec §15): expected pose or points, got '
            "'tracker' (the sweep's in-situ tracker is a prismatic leg set)",
        )
    if "paper-ekf" in methods:
        raise refuse(
            "methods", "method 'paper-ekf' takes prismatic legs (the paper's error Jacobian), not drive = \"rotary\""
        )
    for name in PRISMATIC_SETTINGS:
        default = SETTINGS_BY_NAME[name].default
        other = [value for value in axes[name] if value != default]
        if other:
            why = (
                "a rotary drive's parameters do not walk here"
                if name == "drift_mm_per_sqrt_s"
                else "the elastic robot is one of prismatic legs (spec §10)"
            )
            raise refuse(
                f"grid.{name}",
                f'drive = "rotary" takes {_toml(default)} ({why}), got {_shown(other[0])}; sweep it in a spec of '
                "prismatic cells",
            )


def cost_kind(settings: dict) -> str:
    """What sets a task's cost per sample most, as the plan line names it: its instrument, and ``rotary``
    before it for a rotary drive (its legs run numpy paths, the prismatic legs compiled kernels)."""
    return settings["instrument"] if settings["drive"] == "prismatic" else f"rotary {settings['instrument']}"


def _toml(value) -> str:
    """A setting's value as the spec writes it (``true``, ``"constant"``, ``0.0``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return f'"{value}"' if isinstance(value, str) else repr(value)


def _identity_settings(settings: dict) -> dict:
    """The settings a cell's id hashes: all but the rotary drive's at their defaults, so that a prismatic
    cell keeps its id whatever settings only a rotary one reads (and its finished rows are found again),
    while two cells that differ in any setting never share one."""
    return {
        name: value
        for name, value in settings.items()
        if not (name in ROTARY_SETTINGS and value == SETTINGS_BY_NAME[name].default)
    }


def _raise(err: CalibError):
    raise err


def _integer(value, key: str, minimum: int, refuse, maximum: int = MAX_SEED) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
        raise refuse(key, f"expected an integer from {minimum} to {maximum}, got {_shown(value)}")
    return value


def _shown(value, limit: int = 40) -> str:
    """``repr`` of a value from the spec, cut short (a 5000-digit integer stays one line)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 1]}…"


def _string_list(value, key: str, refuse) -> list[str]:
    """A list of method names; ``methods`` may not be empty."""
    if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
        raise refuse(key, "expected a list of method names")
    if not value and key == "methods":
        raise refuse(key, "expected at least one method")
    if len(set(value)) != len(value):
        raise refuse(key, "a method is listed twice")
    return list(value)


def _axes(grid, source: str, refuse) -> dict[str, list]:
    """Grid values per setting (defaults for the absent ones), estimator settings last, sorted."""
    if not isinstance(grid, dict):
        raise refuse("grid", "expected a table")
    flat = {}
    for key, value in grid.items():
        if isinstance(value, dict):  # [grid.ekf] gate_probability = … is "ekf.gate_probability"
            for sub, sub_value in value.items():
                flat[f"{key}.{sub}"] = sub_value
        else:
            flat[key] = value
    axes = {}
    for setting in SETTINGS:
        values = flat.pop(setting.name, setting.default)
        axes[setting.name] = [_value(setting, v, refuse) for v in _as_list(values, f"grid.{setting.name}", refuse)]
    for key in sorted(flat):
        if "." not in key:
            raise refuse(
                f"grid.{key}",
                f"unknown key: expected one of {', '.join(SETTINGS_BY_NAME)} or an estimator setting 'section.key'",
            )
        section, _, name = key.partition(".")
        values = _as_list(flat[key], f"grid.{key}", refuse)
        for v in values:  # the estimators' own validation, naming the spec's key
            config_from_dict({section: {name: v}}, f"{source}: grid")
        kinds = {type(v) for v in values}
        if kinds == {int, float}:
            values = [float(v) for v in values]
        elif len(kinds) > 1:
            raise refuse(f"grid.{key}", "expected values of one type")
        axes[key] = values
    return axes


def _as_list(values, key: str, refuse) -> list:
    values = values if isinstance(values, list) else [values]
    if not values:
        raise refuse(key, "expected a value or a non-empty list of values")
    if len(set(map(repr, values))) != len(values):
        raise refuse(key, "a value is listed twice")
    return values


def _value(setting: Setting, value, refuse):
    key = f"grid.{setting.name}"
    if setting.kind is str:
        if not isinstance(value, str) or not value:
            raise refuse(key, f"expected a non-empty string, got {_shown(value)}")
        return value
    if setting.kind is bool:
        if not isinstance(value, bool):
            raise refuse(key, f"expected true or false, got {_shown(value)}")
        return value
    numeric = (int,) if setting.kind is int else (int, float)
    # An integer is finite, but may be too large for a float (math.isfinite would overflow).
    finite = (isinstance(value, int) and (setting.kind is int or abs(value) <= 1e300)) or (
        isinstance(value, float) and math.isfinite(value)
    )
    if isinstance(value, bool) or not isinstance(value, numeric) or not finite:
        raise refuse(key, f"expected {'an integer' if setting.kind is int else 'a finite number'}, got {_shown(value)}")
    if setting.positive and value <= 0:
        raise refuse(key, f"expected a number > 0, got {_shown(value)}")
    if setting.minimum is not None and value < setting.minimum:
        raise refuse(key, f"expected a number ≥ {setting.minimum:g}, got {_shown(value)}")
    if setting.maximum is not None and value > setting.maximum:
        raise refuse(key, f"expected a number ≤ {setting.maximum:g}, got {_shown(value)}")
    return setting.kind(value)


def _families(doc, path: Path, refuse) -> dict[str, Family]:
    if not isinstance(doc, dict):
        raise refuse("families", "expected tables [families.NAME]")
    families = {}
    for name, table in doc.items():
        prefix = f"families.{name}"
        if not isinstance(table, dict):
            raise refuse(prefix, "expected a table")
        for key in table:
            if key not in ("like", *FAMILY_DIMENSIONS):
                raise refuse(f"{prefix}.{key}", f"unknown key: expected one of like, {', '.join(FAMILY_DIMENSIONS)}")
        like_name = table.get("like", "nim-stewart")
        like = _platform_file(like_name, path, lambda expected, prefix=prefix: refuse(f"{prefix}.like", expected))
        if like.workspace is None:
            raise refuse(
                f"{prefix}.like",
                f"expected a platform with a [workspace] (its home places the rings), got {like_name!r}",
            )
        ranges = []
        for key in FAMILY_DIMENSIONS:
            if key not in table:
                raise refuse(f"{prefix}.{key}", "expected a number or [low, high] (missing)")
            value = table[key]
            pair = value if isinstance(value, list) else [value, value]
            if (
                len(pair) != 2
                or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in pair)
                or pair[0] > pair[1]
            ):
                raise refuse(
                    f"{prefix}.{key}", f"expected a number or [low, high] with low ≤ high, got {_shown(value)}"
                )
            if key.endswith("radius_mm") and pair[0] <= 0:
                raise refuse(f"{prefix}.{key}", f"expected radii > 0, got {_shown(value)}")
            ranges.append([float(pair[0]), float(pair[1])])
        families[name] = Family(name, like, np.array(ranges))
    return families


def _platform(value: str, families: dict, path: Path, refuse) -> Platform | Family:
    if value in families:
        return families[value]
    return _platform_file(value, path, lambda expected: refuse("grid.platform", expected))


def _platform_file(value: str, path: Path, refuse) -> Platform:
    """A platform file relative to the spec, or a shipped platform's name, of either drive (each cell
    checks it is of its own, :func:`parse_spec`)."""
    for candidate in (path.parent / value, CONFIGS / "platforms" / f"{value}.toml"):
        if candidate.is_file():
            return load_platform(candidate)
    raise refuse(
        "expected a shipped platform name, a platform file relative to the spec or a [families] name, "
        f"got {_shown(value)}"
    )


def _noise_table(settings: dict, reading_scale: float = 1.0) -> dict:
    """The ``[noise]`` table of what the cell simulates, its readings' σ × ``reading_scale``: where the
    true stroke scales spread, that spread is their prior σ (the scales are then unknowns)."""
    table = {
        "reading_sigma_mm": settings["reading_sigma_mm"] * reading_scale,
        "stroke_sigma_mm": settings["stroke_sigma_mm"],
        "random_walk_mm_per_sqrt_s": settings["drift_mm_per_sqrt_s"],
    }
    if settings["stroke_scale_error"] > 0:
        table["stroke_scale_sigma"] = settings["stroke_scale_error"]
    if settings["drive"] == "rotary":  # a servo's held angle, and its angles' walk (none: they do not drift here)
        table |= {"angle_sigma_deg": settings["angle_sigma_deg"], "angle_random_walk_deg_per_sqrt_s": 0.0}
    return table


def simulated_noise(settings: dict) -> NoiseConfig:
    """The noise the cell simulates (what the bound is for, whatever the estimators are told): the
    readings' σ × ``noise_scale``, and the drive's terms whose true values spread with that spread as
    their prior σ — so :func:`~stewart_calib.model.drive.drive_model` with it draws and bounds them."""
    return NoiseConfig(**_noise_table(settings, settings["noise_scale"]))


def _estimator_config(settings: dict, source: str) -> EstimatorConfig:
    """The estimators' noise model matched to the simulation, then the cell's estimator settings."""
    matched = {
        "noise": _noise_table(settings),
        "robust": {"adapt_noise": False},  # matched already: measuring it again only adds its scatter
    }
    config = config_from_dict(matched, source)
    overrides: dict[str, dict] = {}
    for key, value in settings.items():
        if "." in key:
            section, _, name = key.partition(".")
            overrides.setdefault(section, {})[name] = value
    return config_from_dict(overrides, f"{source}: grid", config)


def _fingerprint(platform: Platform | Family) -> str:
    """What a cell's rows depend on of its platform: the file's values, or the family's definition, each
    number to the bit (a platform's identity: the ids of the cells, which seed their tasks, stay as they were)."""
    if isinstance(platform, Family):
        like = platform_to_toml(platform.like, exact=True)
        return json.dumps({"family": platform.name, "like": like, "ranges": platform.ranges.tolist()})
    return platform_to_toml(platform, exact=True)
