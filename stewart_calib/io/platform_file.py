"""The platform file (spec §2, §6, §10, §15, §17): its TOML reader (:func:`load_platform`,
:func:`parse_platform`, :func:`parse_instrument`) and writer (:func:`platform_to_toml`).

The geometry it builds lives in :mod:`stewart_calib.model.platform` (the prismatic leg set, the
workspace, the instrument, the elastic drive of ``[elastic]``, the legs' thermal expansion of
``[thermal]``) and :mod:`stewart_calib.model.rotary` (the rotary leg set); what each instrument kind
reads of the file is that module's ``INSTRUMENT_SECTIONS``.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .. import resources
from ..errors import CalibError, did_you_mean, without_noise
from ..inputs import implausible_sigma_mm
from ..model.platform import (
    DEFAULT_ORIENTATION_SIGMA_DEG,
    DEFAULT_POSITION_SIGMA_MM,
    DOWN,
    EXPANSION_LIMIT_PPM_PER_K,
    G_N_PER_KG,
    INSTRUMENT_KINDS,
    INSTRUMENT_SECTIONS,
    MIN_PLATFORM_MASS_KG,
    N_LEGS,
    TEMPERATURE_RANGE_C,
    Elastic,
    Instrument,
    LegGeometry,
    Platform,
    Thermal,
    Workspace,
    centre_too_far,
    default_compliance_sigma,
    give_reference_mm,
    least_give_mm_per_kg,
    payload_limit_kg,
)
from ..model.rotary import RotaryLegs, orthonormal_zero_directions
from ..model.rotations import pose_to_rt, transform_points

#: the keys a platform file may hold, per table ("" = top level). A misspelt optional key
#: would otherwise be ignored without a word (a stroke range silently not enforced).
#: ``[instrument]``'s keys depend on its kind; :func:`parse_instrument` checks them.
PLATFORM_KEYS: dict[str, set[str]] = {
    "": {"name", "description", "drive", "tracker", "workspace", "instrument", "elastic", "thermal"},
    "tracker": {"base_joints_mm", "platform_joints_mm", "initial_lengths_mm", "reading_range_mm", "geometry_sigma_mm"},
    "workspace": {"home", "translation_limit_mm", "rotation_limit_deg"},
    "elastic": {
        "platform_mass_kg",
        "platform_com_mm",
        "payload_com_mm",
        "compliance_mm_per_kN",
        "compliance_sigma_mm_per_kN",
        "true_compliance_mm_per_kN",
        "payload_sigma_kg",
        "gravity",
    },
    "thermal": {
        "reference_temperature_C",
        "expansion_ppm_per_K",
        "expansion_sigma_ppm_per_K",
        "true_expansion_ppm_per_K",
    },
}

#: the keys of ``[drive]`` per ``kind`` (spec §2, §15); a ``[drive]`` without ``kind`` is the first.
DRIVE_KEYS: dict[str, frozenset[str]] = {
    "prismatic": frozenset(
        {"kind", "base_joints_mm", "platform_joints_mm", "initial_lengths_mm", "stroke_range_mm", "stroke_scale"}
    ),
    "rotary": frozenset(
        {
            "kind",
            "crank_centres_mm",
            "crank_axes",
            "crank_zero_directions",
            "horn_lengths_mm",
            "rod_lengths_mm",
            "platform_joints_mm",
            "angle_offsets_deg",
            "angle_range_deg",
            "stroke_scale",
        }
    ),
}
DRIVE_KINDS = tuple(DRIVE_KEYS)

#: a crank's zero direction farther than this from orthogonal to its axis is refused [deg] (spec §15)
ZERO_DIRECTION_TOLERANCE_DEG = 1.0

#: a leg set whose every coordinate and length is below this [mm] was written in metres: no
#: hexapod a tracker of grating rulers measures is under a centimetre.
METRES_SUSPECT_MM = 10.0

#: joints whose second principal extent is below this fraction of the first lie on one line
#: (or one point): the platform can then turn about that line with no leg changing length.
COLLINEAR_RATIO = 1e-3


def _refuse(source: str, key: str, expected: str) -> CalibError:
    return CalibError(f"{source}: key '{key}': expected {expected}")


def drive_kind(doc: dict, source: str) -> str:
    """``[drive] kind`` of a platform document (spec §15): ``"prismatic"`` where absent.

    Raises:
        CalibError: a kind that is not one of :data:`DRIVE_KINDS`, naming ``source`` and the key.
    """
    table = doc.get("drive")
    kind = table.get("kind", DRIVE_KINDS[0]) if isinstance(table, dict) else DRIVE_KINDS[0]
    if kind not in DRIVE_KINDS:
        raise _refuse(source, "drive.kind", f"one of {', '.join(map(repr, DRIVE_KINDS))}, got {kind!r}")
    return kind


def _check_keys(doc: dict, source: str) -> None:
    """Refuse a key :data:`PLATFORM_KEYS` (``[drive]``: :data:`DRIVE_KEYS` of its kind) does not know,
    suggesting the nearest known one — of another drive kind too, saying which kind uses it."""
    kind = drive_kind(doc, source)
    for table, known in {**PLATFORM_KEYS, "drive": DRIVE_KEYS[kind]}.items():
        values = doc if not table else doc.get(table)
        if not isinstance(values, dict):
            continue
        for key in values:
            if key not in known:
                # a key with a newline or other control character would break the one-line message
                shown = key if key.isprintable() else key.encode("unicode_escape").decode("ascii")
                full = f"{table}.{shown}" if table else shown
                hint = did_you_mean(key, known)
                if table == "drive":
                    hint = _drive_key_hint(key, kind) or hint
                raise CalibError(f"{source}: unknown key '{full}'{hint}; expected one of {', '.join(sorted(known))}")


def _drive_key_hint(key: str, kind: str) -> str:
    """Where ``key``, or the ``[drive]`` key nearest it, belongs to another drive kind than ``kind``:
    a hint naming that kind (and the key meant); else ``""``."""
    other = next((name for name, keys in DRIVE_KEYS.items() if key in keys), None)
    if other is not None:
        return f' (a key of [drive] kind = "{other}", spec §15; this [drive] is kind = "{kind}")'
    nearest = did_you_mean(key, set().union(*DRIVE_KEYS.values()))
    if not nearest or nearest == did_you_mean(key, DRIVE_KEYS[kind]):
        return ""
    other = next(name for name, keys in DRIVE_KEYS.items() if nearest == did_you_mean(key, keys))
    return f'{nearest[:-1]} it is a key of [drive] kind = "{other}" (spec §15); this [drive] is kind = "{kind}")'


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers_only(value) -> bool:
    """True when ``value`` is a number or nested lists of numbers (never text such as ``"1048.5"``)."""
    if isinstance(value, list):
        return all(_numbers_only(v) for v in value)
    return _is_number(value)


def _array(table: dict, key: str, shape: tuple[int, ...], source: str, prefix: str) -> np.ndarray:
    full = f"{prefix}.{key}"
    if key not in table:
        raise _refuse(source, full, f"{_shape_words(shape)} (missing)")
    if not _numbers_only(table[key]):  # numpy would read the text "1048.5" as a number
        raise _refuse(source, full, f"{_shape_words(shape)} of numbers (not quoted text)")
    try:
        value = np.array(table[key], dtype=float)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond float range
        raise _refuse(source, full, f"{_shape_words(shape)} of numbers") from None
    if value.shape != shape:
        raise _refuse(source, full, f"{_shape_words(shape)}, got shape {value.shape}")
    if not np.all(np.isfinite(value)):
        raise _refuse(source, full, f"{_shape_words(shape)} of finite numbers")
    return value


def _shape_words(shape: tuple[int, ...]) -> str:
    if shape == (6, 3):
        return "6 rows of [x, y, z] in mm"
    if len(shape) == 1:
        return f"a list of {shape[0]} numbers"
    return f"an array of shape {shape}"


def _range(table: dict, key: str, source: str, prefix: str) -> tuple[float, float] | None:
    if key not in table:
        return None
    lo, hi = _array(table, key, (2,), source, prefix)
    if not lo < hi:
        raise _refuse(source, f"{prefix}.{key}", f"[min, max] with min < max, got [{lo}, {hi}]")
    return float(lo), float(hi)


def _legs(doc: dict, section: str, source: str) -> tuple[LegGeometry, dict]:
    table = doc.get(section)
    if not isinstance(table, dict):
        raise _refuse(source, section, f"a [{section}] table")
    legs = LegGeometry(
        _array(table, "base_joints_mm", (6, 3), source, section),
        _array(table, "platform_joints_mm", (6, 3), source, section),
        _array(table, "initial_lengths_mm", (6,), source, section),
    )
    if np.any(legs.initial_lengths <= 0):
        raise _refuse(source, f"{section}.initial_lengths_mm", "6 positive lengths in mm")
    largest = max(np.abs(legs.base_joints).max(), np.abs(legs.platform_joints).max(), legs.initial_lengths.max())
    if largest < METRES_SUSPECT_MM:
        raise CalibError(
            f"{source}: [{section}]: the geometry looks like metres (largest coordinate or length {largest:.4g}); "
            "expected millimetres (spec §2)"
        )
    for key, joints in (("base_joints_mm", legs.base_joints), ("platform_joints_mm", legs.platform_joints)):
        _check_spread(joints, source, f"{section}.{key}")
    return legs, table


def _rotary(doc: dict, source: str) -> tuple[RotaryLegs, dict]:
    """The ``[drive]`` table of ``kind = "rotary"`` (spec §15) as :class:`~stewart_calib.model.rotary.RotaryLegs`
    [mm, rad]: axes normalised, zero directions made orthogonal to their axes and normalised."""

    table = doc.get("drive")
    if not isinstance(table, dict):
        raise _refuse(source, "drive", "a [drive] table")
    centres = _array(table, "crank_centres_mm", (N_LEGS, 3), source, "drive")
    given = {key: _array(table, key, (N_LEGS, 3), source, "drive") for key in ("crank_axes", "crank_zero_directions")}
    for key, rows in given.items():
        bad = np.flatnonzero(~(np.linalg.norm(rows, axis=1) > 0.0))
        if bad.size:
            raise _refuse(source, f"drive.{key}[{int(bad[0]) + 1}]", "a direction [x, y, z] of nonzero length")
    axes, zeros, off_deg = orthonormal_zero_directions(given["crank_axes"], given["crank_zero_directions"])
    bad = np.flatnonzero(~(off_deg <= ZERO_DIRECTION_TOLERANCE_DEG))  # NaN: along the axis
    if bad.size:
        i = int(bad[0])
        raise _refuse(
            source,
            f"drive.crank_zero_directions[{i + 1}]",
            f"a direction within {ZERO_DIRECTION_TOLERANCE_DEG:g}° of orthogonal to its axis (crank_axes row "
            f"{i + 1}), got one {90.0 if np.isnan(off_deg[i]) else off_deg[i]:.4g}° from orthogonal",
        )
    lengths = {}
    for key in ("horn_lengths_mm", "rod_lengths_mm"):
        lengths[key] = _array(table, key, (N_LEGS,), source, "drive")
        if np.any(lengths[key] <= 0):
            raise _refuse(source, f"drive.{key}", "6 positive lengths in mm")
    joints = _array(table, "platform_joints_mm", (N_LEGS, 3), source, "drive")
    offsets_deg = (
        _array(table, "angle_offsets_deg", (N_LEGS,), source, "drive")
        if "angle_offsets_deg" in table
        else np.zeros(N_LEGS)
    )
    if np.any(np.abs(offsets_deg) > 180.0):
        raise _refuse(source, "drive.angle_offsets_deg", f"6 zero trims within ±180 deg, got {offsets_deg.tolist()}")
    if "angle_range_deg" not in table:
        raise _refuse(
            source,
            "drive.angle_range_deg",
            '[min, max] in degrees: the commanded angles the servos accept (missing; required with kind = "rotary")',
        )
    low, high = _range(table, "angle_range_deg", source, "drive")  # type: ignore[misc]  # present: not None
    if high - low > 360.0:
        raise _refuse(source, "drive.angle_range_deg", f"[min, max] at most 360 deg apart, got [{low}, {high}]")
    largest = max(np.abs(centres).max(), np.abs(joints).max(), *(values.max() for values in lengths.values()))
    if largest < METRES_SUSPECT_MM:
        raise CalibError(
            f"{source}: [drive]: the geometry looks like metres (largest coordinate or length {largest:.4g}); "
            "expected millimetres (spec §15)"
        )
    for key, points in (("crank_centres_mm", centres), ("platform_joints_mm", joints)):
        _check_spread(points, source, f"drive.{key}")
    legs = RotaryLegs(
        crank_centres=centres,
        crank_axes=axes,
        zero_directions=zeros,
        horn_lengths=lengths["horn_lengths_mm"],
        rod_lengths=lengths["rod_lengths_mm"],
        platform_joints=joints,
        angle_offsets=np.radians(offsets_deg),
        angle_range=(math.radians(low), math.radians(high)),
    )
    return legs, table


def _check_spread(joints: np.ndarray, source: str, key: str) -> None:
    """Refuse six joints that coincide or lie on one line: a rotation about that line (or any,
    about a point) changes no leg length, so no pose could be solved or calibrated."""
    centred = joints - joints.mean(axis=0)
    extents = np.linalg.svd(centred, compute_uv=False)
    if extents[0] <= 1e-9 * max(1.0, float(np.abs(joints).max())):
        raise _refuse(source, key, f"6 joints spread in a plane; joints 1–6 all coincide at {joints[0].tolist()}")
    if extents[1] < COLLINEAR_RATIO * extents[0]:
        raise _refuse(source, key, "6 joints spread in a plane; joints 1–6 lie on one line")


def parse_platform(doc: dict, source: str = "<memory>") -> Platform:
    """Validate a parsed platform TOML document (spec §2) and build a :class:`Platform`.

    Raises:
        CalibError: naming ``source``, the key and what was expected.
    """
    _check_keys(doc, source)
    name = doc.get("name")
    if not isinstance(name, str) or not name.strip():
        raise _refuse(source, "name", "a non-empty string")
    description = doc.get("description", "")
    if not isinstance(description, str):
        raise _refuse(source, "description", "a string")
    rotary = drive_kind(doc, source) == "rotary"
    drive, drive_table = _rotary(doc, source) if rotary else _legs(doc, "drive", source)
    if rotary and "elastic" in doc:
        raise _refuse(
            source,
            "elastic",
            'no [elastic] table with [drive] kind = "rotary" (a servo\'s torsional give is not modelled)',
        )
    instrument = _instrument(doc, source)
    tracker, reading_range, geometry_sigma = None, None, 0.0
    if INSTRUMENT_SECTIONS[instrument.kind].reads_tracker or "tracker" in doc:
        tracker, tracker_table = _legs(doc, "tracker", source)
        reading_range = _range(tracker_table, "reading_range_mm", source, "tracker")
        geometry_sigma = _non_negative(tracker_table, "geometry_sigma_mm", 0.0, source, "tracker")
    stroke_range = None if rotary else _range(drive_table, "stroke_range_mm", source, "drive")
    stroke_scale = (
        _array(drive_table, "stroke_scale", (N_LEGS,), source, "drive")
        if "stroke_scale" in drive_table
        else np.zeros(N_LEGS)
    )
    if np.any(np.abs(stroke_scale) > 0.5):
        raise _refuse(
            source,
            "drive.stroke_scale",
            f"6 scale errors k_i within ±0.5 (a leg moves (1 + k_i) mm per logged mm), got {stroke_scale.tolist()}",
        )

    workspace = None
    if "workspace" in doc:
        ws = doc["workspace"]
        if not isinstance(ws, dict):
            raise _refuse(source, "workspace", "a [workspace] table")
        home = _array(ws, "home", (6,), source, "workspace")
        limits = {}
        for key, default in (("translation_limit_mm", 200.0), ("rotation_limit_deg", 20.0)):
            value = ws.get(key, default)
            finite = (
                isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= sys.float_info.max
            )
            if not finite or math.isnan(value) or value < 0:
                raise _refuse(source, f"workspace.{key}", "a finite non-negative number")
            limits[key] = float(value)
        workspace = Workspace(
            home=np.concatenate([home[:3], np.radians(home[3:])]),
            translation_limit=limits["translation_limit_mm"],
            rotation_limit=math.radians(limits["rotation_limit_deg"]),
        )

    elastic = (
        _elastic(doc, drive, source, give_reference_mm(drive, stroke_range)) if isinstance(drive, LegGeometry) else None
    )
    platform = Platform(
        name,
        drive,
        tracker,
        stroke_range,
        reading_range,
        workspace,
        description,
        source,
        instrument,
        stroke_scale,
        geometry_sigma,
        elastic,
        _thermal(doc, source),
    )
    if workspace is not None:
        _check_home_reachable(platform, workspace, source)
    return platform


def _number(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = table.get(key, default)
    finite = isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= sys.float_info.max
    if not finite or math.isnan(value):
        raise _refuse(source, f"{prefix}.{key}", "a finite number")
    return float(value)


def _non_negative(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = _number(table, key, default, source, prefix)
    if value < 0:
        raise _refuse(source, f"{prefix}.{key}", f"a σ ≥ 0 (0: known exactly), got {value!r}")
    return value


def _positive(table: dict, key: str, default: float, source: str, prefix: str) -> float:
    value = _number(table, key, default, source, prefix)
    if not value > 0:
        raise _refuse(source, f"{prefix}.{key}", f"a positive σ, got {value!r}")
    implausible = implausible_sigma_mm(value) if key.endswith("_mm") else None
    if implausible:
        raise _refuse(source, f"{prefix}.{key}", implausible)
    if key.endswith("_deg") and not 1e-9 <= value <= 180.0:
        raise _refuse(source, f"{prefix}.{key}", f"a σ within [1e-9, 180] deg, got {value!r}")
    return value


def _elastic(doc: dict, drive: LegGeometry, source: str, reference: tuple[float, str]) -> Elastic | None:
    """The optional ``[elastic]`` table (spec §10); None without it. ``reference``: what no leg can
    give (:func:`give_reference_mm`), which bounds the compliances, their σ and the payload's σ."""
    if "elastic" not in doc:
        return None
    table = doc["elastic"]
    if not isinstance(table, dict):
        raise _refuse(source, "elastic", "an [elastic] table")
    if "platform_mass_kg" not in table:
        raise _refuse(source, "elastic.platform_mass_kg", "the platform's mass in kg (missing)")
    mass = _number(table, "platform_mass_kg", 0.0, source, "elastic")
    if not mass >= MIN_PLATFORM_MASS_KG:
        raise _refuse(
            source,
            "elastic.platform_mass_kg",
            f"a mass in kg of at least {MIN_PLATFORM_MASS_KG:g} (a gram), got {mass!r}",
        )
    centres = {}
    for key in ("platform_com_mm", "payload_com_mm"):
        centre = (
            _array(table, key, (3,), source, "elastic") if key in table or key == "platform_com_mm" else np.zeros(3)
        )
        too_far = centre_too_far(drive, centre)
        if too_far:
            raise _refuse(source, f"elastic.{key}", too_far)
        centres[key] = centre
    compliance = (
        _array(table, "compliance_mm_per_kN", (N_LEGS,), source, "elastic")
        if "compliance_mm_per_kN" in table
        else np.zeros(N_LEGS)
    )
    truth = (
        _array(table, "true_compliance_mm_per_kN", (N_LEGS,), source, "elastic")
        if "true_compliance_mm_per_kN" in table
        else None
    )
    sigma = _non_negative(table, "compliance_sigma_mm_per_kN", default_compliance_sigma(mass), source, "elastic")
    reference_mm, what = reference
    weight_n = mass * G_N_PER_KG / N_LEGS
    at_most = reference_mm / (least_give_mm_per_kg(1.0) * mass)  # [mm/kN]: a leg gives its reference length
    for key, values in (("compliance_mm_per_kN", compliance), ("compliance_sigma_mm_per_kN", np.array([sigma]))):
        largest = float(np.max(np.abs(values)))
        if not largest <= at_most:
            raise _refuse(
                source,
                f"elastic.{key}",
                f"legs that can hold the platform: {largest:.4g} mm/kN gives a leg at least "
                f"{least_give_mm_per_kg(largest) * mass:.4g} mm under a sixth of the platform's weight "
                f"({weight_n:.4g} N), beyond {reference_mm:.4g} mm of {what} (expected at most {at_most:.4g} mm/kN)",
            )
    elastic = Elastic(
        mass,
        centres["platform_com_mm"],
        centres["payload_com_mm"],
        compliance,
        sigma,
        truth,
        _non_negative(table, "payload_sigma_kg", 0.0, source, "elastic"),
        _gravity(table, source),
    )
    limit = payload_limit_kg(elastic, reference_mm)
    if not elastic.payload_sigma_kg <= limit:
        raise _refuse(
            source,
            "elastic.payload_sigma_kg",
            f"a payload σ the platform could carry: at most {limit:.4g} kg, beyond which its legs (compliance "
            f"{float(np.max(np.abs(compliance))):.4g} + σ {sigma:.4g} mm/kN) would give more than "
            f"{reference_mm:.4g} mm of {what}; got {elastic.payload_sigma_kg!r}",
        )
    return elastic


def _gravity(table: dict, source: str) -> np.ndarray:
    """``[elastic] gravity`` (spec §17): the direction gravity acts along in {J}, normalised; −z where absent."""
    if "gravity" not in table:
        return DOWN.copy()
    direction = _array(table, "gravity", (3,), source, "elastic")
    if not np.any(direction != 0.0):
        raise _refuse(
            source, "elastic.gravity", "a direction [gx, gy, gz] in {J} of nonzero length (default [0, 0, -1])"
        )
    return unit_direction(direction)


def unit_direction(direction: np.ndarray) -> np.ndarray:
    """``(..., 3)`` directions of finite, nonzero components scaled to unit length (NaN where a component
    is), by the largest component first so that no square overflows or underflows. One already of unit
    length (to the last bit or two) is kept as it is: a written unit vector then reads back bit for bit,
    where dividing by its norm again moves the last bit of about a third of them (a platform file
    written by :func:`platform_to_toml`, a log by :func:`~.logs.log_text`). Written out component by
    component, not as numpy reductions, so that every row, alone or in a block, gets the same correctly
    rounded operations in the same order, so the same bits; one row's (the row parser's per-row path)
    in Python's floats, at a tenth of numpy's cost on three numbers."""
    direction = np.asarray(direction, dtype=float)
    if direction.shape == (3,):
        return _unit_row(*direction.tolist())
    x, y, z = direction[..., 0], direction[..., 1], direction[..., 2]
    with np.errstate(invalid="ignore", over="ignore"):
        largest = np.maximum(np.maximum(np.abs(x), np.abs(y)), np.abs(z))
        sx, sy, sz = x / largest, y / largest, z / largest
        scaled_norm = np.sqrt(sx * sx + sy * sy + sz * sz)
        norm = np.sqrt(x * x + y * y + z * z)
    unit = np.stack([sx / scaled_norm, sy / scaled_norm, sz / scaled_norm], axis=-1)
    return np.where((np.abs(norm - 1.0) <= UNIT_TOLERANCE)[..., None], direction, unit)


#: a direction whose norm is this close to 1 is taken as of unit length (:func:`unit_direction`): 4 ulp
UNIT_TOLERANCE = 4.0 * np.finfo(float).eps


def _unit_row(x: float, y: float, z: float) -> np.ndarray:
    """:func:`unit_direction` of one direction, the same operations on Python's floats."""
    if math.isnan(x) or math.isnan(y) or math.isnan(z):
        return np.full(3, math.nan)
    norm = math.sqrt(x * x + y * y + z * z)  # a float product overflows to inf, as numpy's does
    if abs(norm - 1.0) <= UNIT_TOLERANCE:
        return np.array([x, y, z])
    largest = max(abs(x), abs(y), abs(z))
    sx, sy, sz = x / largest, y / largest, z / largest
    scaled_norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    return np.array([sx / scaled_norm, sy / scaled_norm, sz / scaled_norm])


def _thermal(doc: dict, source: str) -> Thermal | None:
    """The optional ``[thermal]`` table (spec §17); None without it. A rotary drive's is read too (its
    rods grow alike); whether the drive model takes it is :func:`~stewart_calib.model.drive.drive_model`'s
    to say."""
    if "thermal" not in doc:
        return None
    table = doc["thermal"]
    if not isinstance(table, dict):
        raise _refuse(source, "thermal", "a [thermal] table")
    low, high = TEMPERATURE_RANGE_C
    reference = _number(table, "reference_temperature_C", Thermal.reference_temperature_C, source, "thermal")
    if not low <= reference <= high:
        raise _refuse(
            source,
            "thermal.reference_temperature_C",
            f"a temperature within [{low:g}, {high:g}] °C (where the geometry of [drive] holds), got {reference!r}",
        )
    coefficients: dict[str, np.ndarray | None] = {}
    for key in ("expansion_ppm_per_K", "true_expansion_ppm_per_K"):
        values = _array(table, key, (N_LEGS,), source, "thermal") if key in table else None
        if values is not None and np.any(np.abs(values) > EXPANSION_LIMIT_PPM_PER_K):
            raise _refuse(
                source,
                f"thermal.{key}",
                f"6 expansion coefficients α_i within ±{EXPANSION_LIMIT_PPM_PER_K:g} ppm/K (steel's is about 11.5, "
                f"aluminium's 23), got {values.tolist()}",
            )
        coefficients[key] = values
    nominal = coefficients["expansion_ppm_per_K"]
    return Thermal(
        reference,
        np.zeros(N_LEGS) if nominal is None else nominal,
        _non_negative(table, "expansion_sigma_ppm_per_K", Thermal.expansion_sigma_ppm_per_K, source, "thermal"),
        coefficients["true_expansion_ppm_per_K"],
    )


def _pose6(table: dict, key: str, source: str) -> np.ndarray:
    """A ``[x, y, z mm, roll, pitch, yaw deg]`` key (default all zero) as pose6 ``[mm, rad]``."""
    if key not in table:
        return np.zeros(6)
    value = _array(table, key, (6,), source, "instrument")
    return np.concatenate([value[:3], np.radians(value[3:])])


def _instrument(doc: dict, source: str) -> Instrument:
    """The optional ``[instrument]`` table (spec §7); without it, the tracker."""
    if "instrument" not in doc:
        return Instrument()
    return parse_instrument(doc["instrument"], source)


def parse_instrument(table, source: str) -> Instrument:
    """Validate an ``[instrument]`` table (spec §7).

    Raises:
        CalibError: an unknown kind, a key the kind does not use, a wrong shape or a σ ≤ 0,
            naming ``source`` and the key.
    """
    if not isinstance(table, dict):
        raise _refuse(source, "instrument", "an [instrument] table")
    kind = table.get("kind", INSTRUMENT_KINDS[0])
    if kind not in INSTRUMENT_KINDS:
        raise _refuse(source, "instrument.kind", f"one of {', '.join(map(repr, INSTRUMENT_KINDS))}, got {kind!r}")
    section = INSTRUMENT_SECTIONS[kind]
    unused = sorted(set(table) - {"kind", *section.keys})
    if unused:
        known = {key for other in INSTRUMENT_SECTIONS.values() for key in other.keys}
        why = (
            f"a key that kind = {kind!r} uses"
            if unused[0] in known
            else f"a known key (spec §7){did_you_mean(unused[0], section.keys)}"
        )
        raise _refuse(source, f"instrument.{unused[0]}", why)
    # a key the kind does not read was refused above: every other key takes its default when absent
    targets = np.zeros((0, 3))
    if "targets_mm" in section.required and "targets_mm" not in table:
        raise _refuse(source, "instrument.targets_mm", "1..K rows of [x, y, z] in mm (missing)")
    if "targets_mm" in table:
        try:
            targets = np.array(table["targets_mm"], dtype=float)
        except (TypeError, ValueError, OverflowError):
            targets = np.zeros((0,))
        if targets.ndim != 2 or targets.shape[1:] != (3,) or len(targets) == 0 or not np.all(np.isfinite(targets)):
            raise _refuse(source, "instrument.targets_mm", "1..K rows of [x, y, z] in mm (finite numbers)")
    cone, axes = _visibility(table, len(targets), source)
    return Instrument(
        kind=kind,
        frame=_pose6(table, "frame", source),
        target=_pose6(table, "target", source),
        targets=targets,
        position_sigma_mm=_positive(table, "position_sigma_mm", DEFAULT_POSITION_SIGMA_MM, source, "instrument"),
        orientation_sigma_rad=math.radians(
            _positive(table, "orientation_sigma_deg", DEFAULT_ORIENTATION_SIGMA_DEG, source, "instrument")
        ),
        visibility_cone_deg=cone,
        target_axes=axes,
    )


def _visibility(table: dict, n_targets: int, source: str) -> tuple[float | None, np.ndarray]:
    """``[instrument] visibility_cone_deg`` (in (0, 180]) and ``target_axes`` (K nonzero rows,
    default {D}'s z for every target; only with the cone)."""
    axes = np.tile([0.0, 0.0, 1.0], (n_targets, 1))
    if "visibility_cone_deg" not in table:
        if "target_axes" in table:
            raise _refuse(source, "instrument.target_axes", "visibility_cone_deg beside it (the axes are of the cone)")
        return None, axes
    cone = _number(table, "visibility_cone_deg", 0.0, source, "instrument")
    if not 0.0 < cone <= 180.0:
        raise _refuse(source, "instrument.visibility_cone_deg", f"a half-angle in (0, 180] degrees, got {cone!r}")
    if "target_axes" in table:
        axes = _array(table, "target_axes", (n_targets, 3), source, "instrument")
        if np.any(np.linalg.norm(axes, axis=1) == 0.0):
            raise _refuse(source, "instrument.target_axes", f"{n_targets} nonzero [x, y, z] directions in {{D}}")
    return float(cone), axes


def _check_home_reachable(platform: Platform, workspace: Workspace, source: str) -> None:
    R, t = pose_to_rt(workspace.home)
    drive = platform.drive
    if not isinstance(drive, LegGeometry):  # a rotary drive (spec §15)
        angles = drive.coordinates(R, t)
        bad = np.flatnonzero(~np.isfinite(angles))
        if bad.size:
            low, high = np.degrees(drive.angle_range)
            raise _refuse(
                source,
                "workspace.home",
                f"a home pose every crank reaches with a commanded angle within [{low:g}, {high:g}] deg "
                f"(drive.angle_range_deg); leg {int(bad[0]) + 1} cannot",
            )
    for legs, bounds, what in (
        (drive if isinstance(drive, LegGeometry) else None, platform.stroke_range, "drive strokes"),
        (platform.tracker, platform.reading_range, "tracker readings"),
    ):
        if bounds is None or legs is None:
            continue
        strokes = np.linalg.norm(transform_points(R, t, legs.platform_joints) - legs.base_joints, axis=-1)
        strokes -= legs.initial_lengths
        bad = np.flatnonzero((strokes < bounds[0]) | (strokes > bounds[1]))
        if bad.size:
            i = int(bad[0])
            raise _refuse(
                source,
                "workspace.home",
                f"a home pose whose {what} lie within [{bounds[0]}, {bounds[1]}] mm; "
                f"leg {i + 1} needs {strokes[i]:.3f} mm",
            )


def load_platform(path: str | Path) -> Platform:
    """Read and validate a platform TOML file (spec §2), given by path or by the name of a shipped
    platform (``"nim-stewart"``, spec §8).

    Raises:
        CalibError: one line naming the file, the key and what was expected.
    """
    path, doc = resources.read_toml(path, "platforms", "platform file")
    return parse_platform(doc, str(path))


#: a float as TOML text (``12.0``)
FloatText = Callable[[float], str]


def _toml_float(value: float) -> str:
    """A float as the platform file writes it: TOML's float (``12.0``) of its 15 significant digits."""
    return repr(without_noise(float(value)))


def _exact_float(value: float) -> str:
    """A float as its double's ``repr``, to the bit: :func:`platform_to_toml`'s ``exact`` text."""
    return repr(float(value))


def _toml_rows(rows: np.ndarray, text: FloatText) -> str:
    return "[\n" + "".join(f"    [{', '.join(text(v) for v in row)}],\n" for row in rows) + "]"


def _toml_list(values, text: FloatText) -> str:
    return "[" + ", ".join(text(v) for v in values) + "]"


def platform_to_toml(platform: Platform, exact: bool = False) -> str:
    """Serialise to the spec §2 TOML (a rotary drive's ``[drive]``: spec §15), every number to 15
    significant digits (:func:`~stewart_calib.errors.without_noise`: ``12.0``, not the
    ``12.000000000000002`` of 12° through radians); ``parse_platform(tomllib.loads(...))`` gives the
    platform to those digits, and writing it again gives the same text. ``exact``: every number as its
    double's ``repr`` instead, to the bit (what identifies a platform's values: a sweep's cell ids)."""
    text = _exact_float if exact else _toml_float
    lines = [f"name = {_toml_str(platform.name)}"]
    if platform.description:
        lines.append(f"description = {_toml_str(platform.description)}")
    drive, prismatic = platform.drive, None
    if isinstance(drive, LegGeometry):
        prismatic = drive
    else:  # a rotary drive (spec §15)
        lines += _rotary_toml(drive, text)
        if np.any(platform.stroke_scale != 0):
            lines.append(f"stroke_scale = {_toml_list(platform.stroke_scale, text)}")
    for section, legs, key, bounds in (
        ("drive", prismatic, "stroke_range_mm", platform.stroke_range),
        ("tracker", platform.tracker, "reading_range_mm", platform.reading_range),
    ):
        if legs is None:
            continue
        lines += [
            "",
            f"[{section}]",
            f"base_joints_mm = {_toml_rows(legs.base_joints, text)}",
            f"platform_joints_mm = {_toml_rows(legs.platform_joints, text)}",
            f"initial_lengths_mm = {_toml_list(legs.initial_lengths, text)}",
        ]
        if bounds is not None:
            lines.append(f"{key} = {_toml_list(bounds, text)}")
        if section == "drive" and np.any(platform.stroke_scale != 0):
            lines.append(f"stroke_scale = {_toml_list(platform.stroke_scale, text)}")
        if section == "tracker" and platform.tracker_geometry_sigma_mm > 0:
            lines.append(f"geometry_sigma_mm = {text(platform.tracker_geometry_sigma_mm)}")
    lines += _instrument_toml(platform.instrument, text)
    lines += _elastic_toml(platform.elastic, text)
    lines += _thermal_toml(platform.thermal, text)
    if platform.workspace is not None:
        ws = platform.workspace
        home = np.concatenate([ws.home[:3], np.degrees(ws.home[3:])])
        lines += [
            "",
            "[workspace]",
            f"home = {_toml_list(home, text)}",
            f"translation_limit_mm = {text(ws.translation_limit)}",
            f"rotation_limit_deg = {text(math.degrees(ws.rotation_limit))}",
        ]
    return "\n".join(lines) + "\n"


def _rotary_toml(legs: RotaryLegs, text: FloatText) -> list[str]:
    """The ``[drive]`` lines of a rotary drive (spec §15): its axes and zero directions as they are
    (turned, in a calibrated platform), the zero trims in degrees."""
    return [
        "",
        "[drive]",
        'kind = "rotary"',
        f"crank_centres_mm = {_toml_rows(legs.crank_centres, text)}",
        f"crank_axes = {_toml_rows(legs.crank_axes, text)}",
        f"crank_zero_directions = {_toml_rows(legs.zero_directions, text)}",
        f"horn_lengths_mm = {_toml_list(legs.horn_lengths, text)}",
        f"rod_lengths_mm = {_toml_list(legs.rod_lengths, text)}",
        f"platform_joints_mm = {_toml_rows(legs.platform_joints, text)}",
        f"angle_offsets_deg = {_toml_list(np.degrees(legs.angle_offsets), text)}",
        f"angle_range_deg = {_toml_list(np.degrees(legs.angle_range), text)}",
    ]


def _pose6_toml(pose6: np.ndarray, text: FloatText) -> str:
    return _toml_list(np.concatenate([pose6[:3], np.degrees(pose6[3:])]), text)


#: ``[instrument]`` key → its value in TOML, or None where it is left out (the cone's keys without a cone).
_INSTRUMENT_TOML = {
    "frame": lambda instrument, text: _pose6_toml(instrument.frame, text),
    "target": lambda instrument, text: _pose6_toml(instrument.target, text),
    "targets_mm": lambda instrument, text: _toml_rows(instrument.targets, text),
    "position_sigma_mm": lambda instrument, text: text(instrument.position_sigma_mm),
    "orientation_sigma_deg": lambda instrument, text: text(math.degrees(instrument.orientation_sigma_rad)),
    "visibility_cone_deg": lambda instrument, text: (
        None if instrument.visibility_cone_deg is None else text(instrument.visibility_cone_deg)
    ),
    "target_axes": lambda instrument, text: (
        None if instrument.visibility_cone_deg is None else _toml_rows(instrument.target_axes, text)
    ),
}


def _instrument_toml(instrument: Instrument, text: FloatText) -> list[str]:
    """The ``[instrument]`` lines: the keys its kind reads (none for the default, the tracker)."""
    keys = INSTRUMENT_SECTIONS[instrument.kind].keys
    if not keys:
        return []
    values = {key: _INSTRUMENT_TOML[key](instrument, text) for key in keys}
    lines = ["", "[instrument]", f"kind = {_toml_str(instrument.kind)}"]
    return lines + [f"{key} = {value}" for key, value in values.items() if value is not None]


def _elastic_toml(elastic: Elastic | None, text: FloatText) -> list[str]:
    """The ``[elastic]`` lines (none for a rigid robot)."""
    if elastic is None:
        return []
    lines = [
        "",
        "[elastic]",
        f"platform_mass_kg = {text(elastic.platform_mass_kg)}",
        f"platform_com_mm = {_toml_list(elastic.platform_com_mm, text)}",
        f"payload_com_mm = {_toml_list(elastic.payload_com_mm, text)}",
        f"compliance_mm_per_kN = {_toml_list(elastic.compliance_mm_per_kN, text)}",
        f"compliance_sigma_mm_per_kN = {text(elastic.compliance_sigma_mm_per_kN)}",
    ]
    if elastic.true_compliance_mm_per_kN is not None:
        lines.append(f"true_compliance_mm_per_kN = {_toml_list(elastic.true_compliance_mm_per_kN, text)}")
    if elastic.payload_sigma_kg > 0.0:
        lines.append(f"payload_sigma_kg = {text(elastic.payload_sigma_kg)}")
    if not np.array_equal(elastic.gravity, DOWN):
        lines.append(f"gravity = {_toml_list(elastic.gravity, text)}")
    return lines


def _thermal_toml(thermal: Thermal | None, text: FloatText) -> list[str]:
    """The ``[thermal]`` lines (none where temperature is ignored): a calibrated platform's expansion as
    ``expansion_ppm_per_K`` (spec §17, ``--platform-out``)."""
    if thermal is None:
        return []
    lines = [
        "",
        "[thermal]",
        f"reference_temperature_C = {text(thermal.reference_temperature_C)}",
        f"expansion_ppm_per_K = {_toml_list(thermal.expansion_ppm_per_K, text)}",
        f"expansion_sigma_ppm_per_K = {text(thermal.expansion_sigma_ppm_per_K)}",
    ]
    if thermal.true_expansion_ppm_per_K is not None:
        lines.append(f"true_expansion_ppm_per_K = {_toml_list(thermal.true_expansion_ppm_per_K, text)}")
    return lines


def _toml_str(text: str) -> str:
    """``text`` as a TOML basic string that reads back as ``text`` whatever it holds: a backslash,
    a quote and every control character (which TOML forbids raw in a string) escaped."""
    escaped = "".join(
        "\\\\" if ch == "\\" else '\\"' if ch == '"' else f"\\u{ord(ch):04x}" if ch < " " or ch == "\x7f" else ch
        for ch in text
    )
    return f'"{escaped}"'
