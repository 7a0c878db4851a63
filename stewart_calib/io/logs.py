"""Measurement logs, pose lists and truth files (spec §3–§4), with the logs' input channels: the
payload ``load_kg`` (spec §10), each leg's temperature ``temp1_C … temp6_C`` or ``temp_C`` and the
direction of gravity ``gravity_x gravity_y gravity_z`` (spec §17), read into ``Log.inputs`` by the
names of :mod:`stewart_calib.samples` (:class:`InputColumns`).

Files hold mm and degrees; the arrays returned hold mm and rad. Every refusal is a
:class:`~stewart_calib.errors.CalibError` with one line naming the file, the row (its
1-based line number in the file; the header is line 1) and the column, and what was
expected. Every writer goes through :func:`~.atomic.atomic_write_text`.
"""

from __future__ import annotations

import hashlib
import math
import operator
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from itertools import chain
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import CalibError, shown
from ..inputs import MAX_LINE_BYTES, MAX_TIME_S, open_input
from ..model.drive import STROKE_SCALE
from ..model.platform import (
    PARAMETER_NAMES,
    TEMPERATURE_RANGE_C,
    Instrument,
    Platform,
    payload_expected,
    payload_limit,
    payloads_refused,
)
from ..samples import GRAVITY, LOAD_KG, TEMPERATURE_C, Log, Sample, Truth
from .atomic import atomic_write_text
from .platform_file import unit_direction
from .results import parameters_from_file, parameters_to_file
from .tables import (
    Table,
    csv_text,
    flag_non_finite,
    header_fields,
    numbers_by_arrow,
    optional_group,
    parse_careful,
    parse_rows,
    parse_table,
    pose_columns_deg,
    read_header,
    read_text,
    refuse_first,
    require_columns,
    write_csv_blocks,
)

if TYPE_CHECKING:
    from ..instruments.registry import InstrumentKind

STROKE_COLUMNS = tuple(f"q{i}_mm" for i in range(1, 7))
#: a rotary drive's commanded angles (spec §15)
ANGLE_COLUMNS = tuple(f"q{i}_deg" for i in range(1, 7))
READING_COLUMNS = tuple(f"s{i}_mm" for i in range(1, 7))
LOG_REQUIRED = ("t_s", *STROKE_COLUMNS, *READING_COLUMNS)
POSE_COLUMNS = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
TRUE_POSE_COLUMNS = tuple(f"true_{name}" for name in POSE_COLUMNS)
STROKE_SCALE_NAMES = tuple(f"k{i}" for i in range(1, 7))
#: the prefix of a truth file's unloaded drive parameters (an elastic robot's, spec §10): ``unloaded_j1x …``
UNLOADED_PREFIX = "unloaded_"
#: each drive leg's temperature [°C] (spec §17)
TEMPERATURE_COLUMNS = tuple(f"temp{i}_C" for i in range(1, 7))
#: one temperature [°C] for all legs (spec §17), read where the per-leg columns are absent
TEMPERATURE_COLUMN = "temp_C"
#: the direction gravity acts along, a vector in {J} normalised per row (spec §17)
GRAVITY_COLUMNS = ("gravity_x", "gravity_y", "gravity_z")


def drive_columns(platform: Platform | None) -> tuple[str, ...]:
    """The log columns of the drive's coordinates (spec §3, §15): ``q1_mm … q6_mm`` for a prismatic
    drive (also when ``platform`` is None), ``q1_deg … q6_deg`` for a rotary drive's commanded angles,
    in the unit its leg model declares (``coordinate_unit``)."""
    if platform is None:
        return STROKE_COLUMNS
    return tuple(f"q{i}_{platform.drive.coordinate_unit}" for i in range(1, platform.drive.n_legs + 1))


def _drive_in_degrees(platform: Platform | None) -> bool:
    """Whether the drive's log columns hold degrees (radians in code: a rotary drive's angles)."""
    return platform is not None and platform.drive.coordinate_unit == "deg"


def strokes_in_code_units(values: np.ndarray, platform: Platform | None) -> np.ndarray:
    """File drive coordinates ``(..., legs)`` → code units (a rotary drive's degrees → radians)."""
    values = np.asarray(values, dtype=float)
    return np.radians(values) if _drive_in_degrees(platform) else values


def strokes_in_file_units(values: np.ndarray, platform: Platform | None) -> np.ndarray:
    """Code-unit drive coordinates ``(..., legs)`` → the log's units (:func:`drive_columns`)."""
    values = np.asarray(values, dtype=float)
    return np.degrees(values) if _drive_in_degrees(platform) else values


def drive_range(platform: Platform | None) -> tuple[tuple[float, float] | None, str, str]:
    """``(bounds in the log's units or None, the platform key that gives them, their unit)`` of the
    drive's coordinates: ``drive.stroke_range_mm``, or a rotary drive's ``drive.angle_range_deg``."""
    if _drive_in_degrees(platform):
        low, high = np.degrees(platform.drive.angle_range)  # type: ignore[union-attr]  # a rotary drive's
        return (float(low), float(high)), "drive.angle_range_deg", "deg"
    return (None if platform is None else platform.stroke_range), "drive.stroke_range_mm", "mm"


def reading_columns(platform: Platform | None) -> tuple[str, ...]:
    """The log columns of the instrument that measured ``platform``'s logs (spec §7): the tracker's
    ``s1_mm … s6_mm`` (also when ``platform`` is None), a pose's ``mx_mm … myaw_deg`` or the
    targets' ``p1x_mm … pKz_mm``."""
    return _kind(platform).columns_of(_instrument(platform))


def angle_columns(platform: Platform | None) -> tuple[str, ...]:
    """Those of :func:`reading_columns` that hold angles, degrees in the file and radians in code, as
    the instrument's model declares them (:attr:`~stewart_calib.instruments.base.InstrumentModel.angle_columns`:
    a pose's ``mroll_deg mpitch_deg myaw_deg``); the others hold millimetres in both."""
    angles = _kind(platform).angle_columns
    return tuple(name for name in reading_columns(platform) if name in angles)


def _angle_indices(platform: Platform | None) -> list[int]:
    """The indices of :func:`angle_columns` among :func:`reading_columns`."""
    angles = angle_columns(platform)
    return [j for j, name in enumerate(reading_columns(platform)) if name in angles]


def _instrument(platform: Platform | None) -> Instrument:
    """``platform``'s ``[instrument]``; without a platform, the default one (spec §7)."""
    return Instrument() if platform is None else platform.instrument


def _kind(platform: Platform | None) -> InstrumentKind:
    from ..instruments.registry import kind_of  # instruments import platform, not io

    return kind_of(_instrument(platform))


def readings_to_file(readings: np.ndarray, platform: Platform | None) -> list:
    """Code-unit readings ``(N, m)`` of ``platform``'s instrument → file columns: radians → degrees
    for its angles, NaN (a channel not measured, e.g. a point target not seen) → an empty field."""
    blank = blank_reading_columns(platform)
    return [
        ["" if not np.isfinite(v) else v for v in values.tolist()] if j in blank else values
        for j, values in enumerate(readings_in_file_units(readings, platform))
    ]


def readings_in_file_units(readings: np.ndarray, platform: Platform | None) -> list[np.ndarray]:
    """Code-unit readings ``(N, m)`` of ``platform``'s instrument → file-unit float columns (radians →
    degrees for its angles); :func:`readings_to_file` with NaN kept, for
    :func:`~.tables.write_csv_blocks`, whose ``blank`` columns are those of :func:`blank_reading_columns`."""
    readings = np.asarray(readings, dtype=float)
    angles = _angle_indices(platform)
    return [np.degrees(readings[:, j]) if j in angles else readings[:, j] for j in range(readings.shape[1])]


def blank_reading_columns(platform: Platform | None) -> tuple[int, ...]:
    """The indices of the reading columns whose NaN is an empty field: every one where the
    instrument's readings may leave channels unmeasured (a point target not seen), else none."""
    return tuple(range(len(reading_columns(platform)))) if _kind(platform).unseen_channels else ()


def readings_in_code_units(values: np.ndarray, platform: Platform | None) -> np.ndarray:
    """File readings ``(N, m)`` of ``platform``'s instrument → code units (its angles in radians)."""
    values = np.array(values, dtype=float)
    angles = _angle_indices(platform)
    values[:, angles] = np.radians(values[:, angles])
    return values


def write_log(path: str | Path, log: Log, platform: Platform | None = None) -> None:
    """Write a measurement log (spec §3, §7) atomically; see :func:`log_text`."""
    atomic_write_text(path, log_text(log, platform))


def log_text(log: Log, platform: Platform | None = None, header: bool = True) -> str:
    """A measurement log's CSV (spec §3, §7, §17): ``t_s``, q, the readings of ``platform``'s instrument
    (the tracker's s when None), then pose [mm, deg], ``stage`` and the input channels the log has:
    ``load_kg``, ``temp1_C … temp6_C``, ``gravity_x gravity_y gravity_z`` (a temperature or direction
    not known, NaN, as an empty field).

    ``header=False``: the rows only, to append to a log written block by block.
    """
    readings = reading_columns(platform)
    names = ["t_s", *drive_columns(platform), *readings]
    columns = [
        log.t_s,
        *strokes_in_file_units(log.strokes, platform).T,
        *readings_to_file(np.asarray(log.readings, dtype=float), platform),
    ]
    if log.desired_poses is not None:
        names += POSE_COLUMNS
        columns += pose_columns_deg(log.desired_poses)
    if log.stages is not None:
        names.append("stage")
        columns.append(list(log.stages))
    load = log.inputs.get(LOAD_KG)
    if load is not None:  # a payload not known as "nan", as it always was
        names.append("load_kg")
        columns.append(np.asarray(load, dtype=float))
    for name, channel_columns in ((TEMPERATURE_C, TEMPERATURE_COLUMNS), (GRAVITY, GRAVITY_COLUMNS)):
        channel = log.inputs.get(name)
        if channel is not None:
            names += channel_columns
            values = np.asarray(channel, dtype=float).reshape(len(log), len(channel_columns))
            columns += [_blank_unknown(column) for column in values.T]
    return csv_text(names, columns, header)


def _blank_unknown(values: np.ndarray) -> np.ndarray | list:
    """A float column with its NaN (a value not known) as empty fields, for :func:`~.tables.csv_text`."""
    values = np.asarray(values, dtype=float)
    if np.isfinite(values).all():
        return values
    return ["" if not math.isfinite(v) else v for v in values.tolist()]


def _flag_out_of_range(table: Table, columns, bounds, what: str, key: str, unit: str = "mm") -> None:
    if bounds is None:
        return
    lo, hi = bounds
    for name in columns:
        values = table.numbers[name]
        table.flag(
            (values < lo) | (values > hi),
            lambda k, name=name, values=values: (
                f"column '{name}': expected a {what} within [{lo!r}, {hi!r}] {unit} ({key}), got {float(values[k])!r}"
            ),
        )


def _flag_time_backwards(table: Table, latest_s: float = -math.inf) -> float:
    """Flag rows whose t_s is below an earlier good row's (running max, so one glitch row is one skip).

    ``latest_s``: the latest good time before this table (a log read in blocks). Returns the
    latest good time after it.
    """
    t = table.numbers["t_s"]
    good = np.ones(len(t), dtype=bool)
    good[list(table.issues)] = False
    latest = np.maximum.accumulate(np.r_[latest_s, np.where(good, t, -np.inf)])
    table.flag(good & (t < latest[:-1]), lambda k: _time_backwards(float(t[k]), float(latest[k])))
    good[list(table.issues)] = False
    return float(max(latest_s, np.max(t[good], initial=-math.inf)))


def _time_backwards(t_s: float, latest_s: float) -> str:
    return f"column 't_s': expected time non-decreasing, got {t_s!r} after {latest_s!r}"


@dataclass(frozen=True)
class InputColumns:
    """The columns of a log's input channels as its header holds them (spec §3, §10, §17), and what
    the platform needs of them.

    Attributes:
        load: the header has ``load_kg``.
        temperatures: :data:`TEMPERATURE_COLUMNS`, ``(TEMPERATURE_COLUMN,)`` (one for all legs) or ``()``.
        gravity: the header has :data:`GRAVITY_COLUMNS`.
        load_limit_kg: the largest payload the platform carries where ``load_kg`` is an input (its
            ``[elastic]``), else None.
        thermal: the platform declares ``[thermal]``: every row needs its temperatures.
        elastic: the platform declares ``[elastic]``: a row with gravity columns needs its direction.
    """

    load: bool = False
    temperatures: tuple[str, ...] = ()
    gravity: bool = False
    load_limit_kg: float | None = None
    thermal: bool = False
    elastic: bool = False

    @classmethod
    def of(cls, path: Path, header: list[str], platform: Platform | None) -> InputColumns:
        """The input columns of a log ``header``; the per-leg temperatures win over ``temp_C`` where
        both are given (``temp_C`` is then an unknown column, ignored).

        Raises:
            CalibError: some but not all of the per-leg temperatures or of the gravity columns; no
                temperature where ``platform`` declares ``[thermal]``.
        """
        per_leg = optional_group(path, header, TEMPERATURE_COLUMNS)
        temperatures = TEMPERATURE_COLUMNS if per_leg else (TEMPERATURE_COLUMN,) if TEMPERATURE_COLUMN in header else ()
        thermal = platform is not None and platform.thermal is not None
        if thermal and not temperatures:
            raise CalibError(
                f"{path}: row 1: missing column(s) {_span(list(TEMPERATURE_COLUMNS))} or {TEMPERATURE_COLUMN}: "
                "each leg's temperature [°C], an input where the platform has [thermal] (spec §17)"
            )
        elastic = platform is not None and platform.elastic is not None
        load = "load_kg" in header
        return cls(
            load,
            temperatures,
            optional_group(path, header, GRAVITY_COLUMNS),
            payload_limit(platform) if load and elastic else None,  # type: ignore[arg-type]  # elastic: a platform
            thermal,
            elastic,
        )

    @property
    def names(self) -> tuple[str, ...]:
        """The columns, in the order of :meth:`channels`' channels."""
        return (*(("load_kg",) if self.load else ()), *self.temperatures, *(GRAVITY_COLUMNS if self.gravity else ()))

    def channels(self, numbers: Mapping[str, np.ndarray | float]) -> dict[str, np.ndarray]:
        """``Log.inputs`` (or ``Sample.inputs``) of the checked values of :attr:`names` (each ``(n,)``,
        or a float for one row): :data:`~stewart_calib.samples.LOAD_KG` as read,
        :data:`~stewart_calib.samples.TEMPERATURE_C` ``(n, 6)`` [°C] (``temp_C`` for every leg) and
        :data:`~stewart_calib.samples.GRAVITY` ``(n, 3)`` normalised
        (:func:`~.platform_file.unit_direction`); NaN where a value is not known."""
        out: dict[str, np.ndarray] = {}
        if self.load:
            out[LOAD_KG] = numbers["load_kg"]  # type: ignore[assignment]  # a row's float or a column
        if self.temperatures:
            temperature = _rows_of(numbers, self.temperatures)
            if len(self.temperatures) == 1:
                temperature = np.repeat(temperature, len(TEMPERATURE_COLUMNS), axis=-1)
            out[TEMPERATURE_C] = temperature
        if self.gravity:
            out[GRAVITY] = unit_direction(_rows_of(numbers, GRAVITY_COLUMNS))
        return out

    def plain(self, numbers: Mapping[str, np.ndarray]) -> np.ndarray:
        """Which rows' values of :attr:`names` (columns ``(n,)``) every check passes as they are — a
        payload within what the platform carries where it is an input, temperatures within
        :data:`~stewart_calib.model.platform.TEMPERATURE_RANGE_C`, a direction of finite nonzero length
        — for the row parser's block path; the others go the careful way, which takes an empty field
        where the platform needs no value and words every refusal. :meth:`plain_row` for one row."""
        good = np.ones(len(next(iter(numbers.values()))), dtype=bool) if numbers else np.array(True)
        if self.load_limit_kg is not None:
            load = numbers["load_kg"]
            good &= (load >= 0.0) & (load <= self.load_limit_kg)
        low, high = TEMPERATURE_RANGE_C
        for name in self.temperatures:
            good &= (numbers[name] >= low) & (numbers[name] <= high)
        if self.gravity:
            direction = [numbers[name] for name in GRAVITY_COLUMNS]
            good &= np.logical_and.reduce([np.isfinite(g) for g in direction])
            good &= np.logical_or.reduce([g != 0.0 for g in direction])
        return good

    def plain_row(self, values: Mapping[str, float]) -> bool:
        """:meth:`plain` of one row's floats, in Python's own arithmetic: the row parser's per-row path,
        where numpy's call on a few scalars would cost several times the row's parsing."""
        if self.load_limit_kg is not None and not 0.0 <= values["load_kg"] <= self.load_limit_kg:
            return False
        low, high = TEMPERATURE_RANGE_C
        if not all(low <= values[name] <= high for name in self.temperatures):
            return False
        if self.gravity:
            direction = [values[name] for name in GRAVITY_COLUMNS]
            return all(map(math.isfinite, direction)) and any(g != 0.0 for g in direction)
        return True

    def flag(self, table: Table) -> None:
        """Flag the rows whose temperatures or gravity directions are bad (the payload's checks need
        the platform: :func:`_flag_log_values`): a temperature outside the range, or none where the
        platform has ``[thermal]``; a direction with one or two of its three components, not finite or
        of zero length, or none where the platform has ``[elastic]``."""
        low, high = TEMPERATURE_RANGE_C
        for name in self.temperatures:
            values = table.numbers[name]
            if self.thermal:
                table.flag(
                    np.isnan(values),
                    lambda k, name=name: (
                        f"column '{name}': expected each leg's temperature [°C] in every row where the platform "
                        "has [thermal] (spec §17), got none"
                    ),
                )
            table.flag(
                ~np.isnan(values) & ~((values >= low) & (values <= high)),
                lambda k, name=name, values=values: (
                    f"column '{name}': expected a temperature within [{low:g}, {high:g}] °C (spec §17), "
                    f"got {float(values[k])!r}"
                ),
            )
        if not self.gravity:
            return
        direction = np.column_stack([table.numbers[name] for name in GRAVITY_COLUMNS]).reshape(-1, 3)
        known = ~np.isnan(direction)
        count = known.sum(axis=1)
        both = ", ".join(GRAVITY_COLUMNS)
        table.flag(
            (count > 0) & (count < 3),
            lambda k: (
                f"column '{GRAVITY_COLUMNS[int(np.argmin(known[k]))]}': expected all three of {both} or none (spec §17)"
            ),
        )
        if self.elastic:
            table.flag(
                count == 0,
                lambda k: (
                    f"column '{GRAVITY_COLUMNS[0]}': expected the direction of gravity in {{J}} in every row "
                    "where the platform has [elastic] and the log its columns (spec §17), got none"
                ),
            )
        table.flag(
            (count == 3) & ~np.isfinite(direction).all(axis=1),
            lambda k: (
                f"column '{GRAVITY_COLUMNS[int(np.argmin(np.isfinite(direction[k])))]}': expected a finite "
                f"number, got {float(direction[k][np.argmin(np.isfinite(direction[k]))])!r}"
            ),
        )
        table.flag(
            (count == 3) & ~np.any(direction != 0.0, axis=1),
            lambda k: (
                f"columns {both}: expected the direction of gravity in {{J}}, of nonzero length (spec §17), "
                f"got {direction[k].tolist()}"
            ),
        )


def _rows_of(numbers: Mapping[str, np.ndarray | float], names: tuple[str, ...]) -> np.ndarray:
    """``(n, len(names))`` (or ``(len(names),)`` for one row's floats) of the columns ``names``."""
    return np.ascontiguousarray(np.array([numbers[name] for name in names], dtype=float).T)


def _log_columns(
    path: Path, header: list[str], platform: Platform | None = None
) -> tuple[bool, list[str], list[str], InputColumns]:
    """``(has_pose, numeric columns, text columns, input columns)`` of a log header (spec §3, §7, §17)."""
    drive = drive_columns(platform)
    required = ("t_s", *drive, *reading_columns(platform))
    # missing columns of one kind are named for what they hold: the drive's strokes are no instrument's
    missing = [name for name in required if name not in header]
    other = ANGLE_COLUMNS if drive == STROKE_COLUMNS else STROKE_COLUMNS
    if set(missing) & set(drive) and set(other) & set(header):  # before the instrument's: the drive's kind
        kind = "prismatic" if drive == STROKE_COLUMNS else "rotary"
        raise CalibError(
            f"{path}: row 1: columns {_span([name for name in other if name in header])} are another drive's; "
            "the platform's [drive] "
            f'(kind = "{kind}") expects {drive[0]} … {drive[-1]} ({_DRIVE_WORDS[kind]}, spec §15)'
        )
    if missing and set(missing) <= set(drive):
        kind = "prismatic" if drive == STROKE_COLUMNS else "rotary"
        raise CalibError(
            f"{path}: row 1: missing column(s) {', '.join(missing)} of the drive's {_DRIVE_WORDS[kind]} (spec §3, §15)"
        )
    if missing and _kind(platform).outside and set(missing) <= set(reading_columns(platform)):
        raise CalibError(
            f"{path}: row 1: missing column(s) {', '.join(missing)} of the {_instrument(platform).kind} instrument "
            "that the platform's [instrument] names (spec §7)"
        )
    require_columns(path, header, required)
    has_pose = optional_group(path, header, POSE_COLUMNS)
    inputs = InputColumns.of(path, header, platform)
    numeric = [*required, *(POSE_COLUMNS if has_pose else ()), *inputs.names]
    return has_pose, numeric, ["stage"] if "stage" in header else [], inputs


def _span(names: list[str]) -> str:
    """``q1_deg … q6_deg`` for a run of columns, the one name for one."""
    return names[0] if len(names) == 1 else f"{names[0]} … {names[-1]}"


#: what a drive's log columns hold, by its kind
_DRIVE_WORDS = {"prismatic": "strokes [mm]", "rotary": "commanded angles [deg]"}


def _blank_columns(platform: Platform | None) -> tuple[str, ...]:
    """Columns whose empty fields read as NaN: the input channels' (a payload, a temperature or a
    direction may be unknown; :meth:`InputColumns.flag` refuses it where the platform needs it) and the
    target coordinates of a points instrument (a target not seen)."""
    return (
        "load_kg",
        *TEMPERATURE_COLUMNS,
        TEMPERATURE_COLUMN,
        *GRAVITY_COLUMNS,
        *(reading_columns(platform) if _kind(platform).unseen_channels else ()),
    )


def _flag_partial_targets(table: Table, platform: Platform) -> None:
    """A target with one or two of its three coordinates: refused naming the first empty one."""
    names = reading_columns(platform)
    for k in range(0, len(names), 3):
        triple = names[k : k + 3]
        finite = np.column_stack([np.isfinite(table.numbers[name]) for name in triple])
        count = finite.sum(axis=1)
        table.flag(
            (count > 0) & (count < 3),
            lambda row, triple=triple, finite=finite, k=k: (
                f"column '{triple[int(np.argmin(finite[row]))]}': expected all three coordinates of target "
                f"{k // 3 + 1} or none (a target not seen leaves all three empty)"
            ),
        )
        values = np.column_stack([table.numbers[name] for name in triple])
        table.flag(
            np.any(np.isinf(values), axis=1),
            lambda row, triple=triple: f"column '{triple[0]}': expected finite coordinates",
        )


def _flag_log_values(table: Table, platform: Platform | None, has_pose: bool, inputs: InputColumns) -> None:
    """Non-finite required values, readings or strokes outside the platform's ranges and bad input
    channels (a payload the platform cannot carry, :meth:`InputColumns.flag`)."""
    readings = reading_columns(platform)
    finite_required = ["t_s", *drive_columns(platform), *(() if _kind(platform).unseen_channels else readings)]
    flag_non_finite(table, [*finite_required, *(POSE_COLUMNS if has_pose else ())])
    t_s = table.numbers["t_s"]
    table.flag(
        np.abs(t_s) > MAX_TIME_S, lambda k: f"column 't_s': expected a time within ±1e12 s, got {float(t_s[k])!r}"
    )
    if _kind(platform).unseen_channels and platform is not None:
        _flag_partial_targets(table, platform)
    if platform is not None:
        bounds, key, unit = drive_range(platform)
        what = "commanded angle" if unit == "deg" else "stroke"
        _flag_out_of_range(table, drive_columns(platform), bounds, what, key, unit)
        if not _kind(platform).outside:
            _flag_out_of_range(table, READING_COLUMNS, platform.reading_range, "reading", "tracker.reading_range_mm")
        if platform.elastic is not None and "load_kg" in table.numbers:
            load = table.numbers["load_kg"]
            # a payload the platform could not carry is an impossible reading, like a stroke out of range
            table.flag(
                payloads_refused(platform, load),
                lambda k: f"column 'load_kg': expected {payload_expected(platform, float(load[k]))}",
            )
    inputs.flag(table)


class LogDigest:
    """The SHA-256 of a log's bytes as a reader hands them on (the ``digest`` hook of :func:`read_log` and
    :func:`read_log_blocks`, ``track``'s lines): a result's ``"log_sha256"``, by which ``validate`` knows
    the log a calibration was fitted to (docs/formats.md)."""

    #: the result's field
    FIELD = "log_sha256"

    def __init__(self):
        self._sha256 = hashlib.sha256()

    def update(self, data: bytes) -> None:
        """The next bytes of the log, in order (a reader's ``digest`` hook)."""
        self._sha256.update(data)

    def field(self) -> dict[str, str]:
        """The result's field: the digest of the bytes so far, in lower-case hex."""
        return {self.FIELD: self._sha256.hexdigest()}

    def is_of(self, result: dict) -> bool:
        """Whether ``result`` was fitted to these bytes (its ``"log_sha256"``); False for one written without it."""
        return result.get(self.FIELD) == self._sha256.hexdigest()


#: bytes of a log read and parsed at a time (a few ten thousand rows): what reading a log holds
#: in memory besides the samples kept, whatever the log's length.
BLOCK_BYTES = 1 << 22


def read_log(
    path: str | Path,
    platform: Platform | None = None,
    skip_bad_rows: bool = False,
    digest: Callable[[bytes], None] | None = None,
) -> Log:
    """Read a measurement log (spec §3) into a :class:`Log` [mm, rad].

    A bad sample row — wrong number of fields, a missing, non-numeric or non-finite value,
    a stroke outside ``platform.stroke_range`` or a reading outside ``platform.reading_range``
    (inclusive, when the platform gives them), or ``t_s`` going backwards — refuses the file,
    or with ``skip_bad_rows`` is dropped and recorded in ``Log.skipped`` as ``(row, reason)``.
    :func:`read_log_blocks` gives the same samples a block at a time.

    The readings are those of ``platform``'s instrument (spec §7; the tracker when ``platform``
    is None): ``Log.readings`` holds the tracker's s [mm], a pose's ``[x, y, z mm, roll, pitch,
    yaw rad]`` or the targets' ``p1x … pKz`` [mm] with NaN for a target not seen.

    ``digest`` is handed every byte of the log, in order, before a row is parsed: the bytes read (a
    pipe's or standard input's as they came), e.g. :meth:`LogDigest.update` for the result's ``log_sha256``.

    Raises:
        CalibError: the file is missing, unreadable or not UTF-8; a required column is
            missing or the pose columns are partial; there are no sample rows; a bad row
            (unless skipped); every row is bad.
    """
    return Log.concatenate(list(read_log_blocks(path, platform, skip_bad_rows, digest=digest)))


def _open_log(path: Path, what: str = "log file"):
    """``path`` open for reading, seekable (a pipe or FIFO read once into a temporary file:
    :func:`~stewart_calib.inputs.open_input`)."""
    return open_input(path, what)


class _NotUtf8(CalibError):
    """A file's bytes that are not UTF-8 (the refusal a pose list puts before any other)."""


def _decoded(data: bytes, path: Path, offset: int, encoding: str = "utf-8", what: str = "log file") -> str:
    """``data`` (read at byte ``offset`` of the file) as text with ``\\r\\n`` line breaks made ``\\n``."""
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as err:
        raise _NotUtf8(
            f"{path}: {what} is not UTF-8 text (byte 0x{data[err.start]:02x} at offset {offset + err.start}); "
            "expected a UTF-8 CSV file"
        ) from None
    return text.replace("\r\n", "\n")


def read_log_blocks(
    path: str | Path,
    platform: Platform | None = None,
    skip_bad_rows: bool = False,
    block_bytes: int | None = None,
    digest: Callable[[bytes], None] | None = None,
) -> Iterator[Log]:
    """:func:`read_log`'s samples, checks and messages, one :class:`Log` per block of rows.

    Memory stays that of one block (about ``block_bytes`` of text, default :data:`BLOCK_BYTES`)
    however long the log: what online methods and streaming commands read. Each block's
    ``skipped`` lists its bad rows (when skipped); a block may hold no sample. A refusal is
    raised when its block is reached, so a consumer must not act on earlier blocks before the
    last one is read. ``digest``: as :func:`read_log`'s, when the first block is asked for.

    Raises:
        CalibError: as :func:`read_log`.
    """
    path, block_bytes = Path(path), block_bytes or BLOCK_BYTES
    with _open_log(path) as file:
        if digest is not None:  # the file is seekable (a pipe spooled): its bytes once, then parsed from the start
            for chunk in iter(lambda: file.read(BLOCK_BYTES), b""):
                digest(chunk)
            file.seek(0)
        header_bytes = _line(file, path)
        header_line = _decoded(header_bytes, path, 0, "utf-8-sig").rstrip(
            "\n"
        )  # a byte-order mark: spreadsheet exports
        if not header_line.strip() and not any(chunk.strip() for chunk in iter(lambda: file.read(1 << 16), b"")):
            read_header(path, "")  # refuses the empty file
        header = header_fields(path, header_line)
        file.seek(len(header_bytes))
        has_pose, numeric, textual, inputs = _log_columns(path, header, platform)
        latest_s, rows, good = -math.inf, 0, 0
        first_skipped: tuple[int, str] | None = None
        by_arrow = set(numeric) == set(header)
        for table in _row_tables(
            file, path, header_line, header, numeric, textual, _blank_columns(platform), by_arrow, block_bytes
        ):
            _flag_log_values(table, platform, has_pose, inputs)
            latest_s = _flag_time_backwards(table, latest_s)
            if not skip_bad_rows:
                refuse_first(path, table)
            block = _log_of(table, has_pose, textual, platform, inputs)
            rows, good = rows + len(table), good + len(block)
            first_skipped = first_skipped or (block.skipped[0] if block.skipped else None)
            yield block
        if rows == 0:
            raise CalibError(f"{path}: no sample rows; expected a header row and at least one sample row")
        if good == 0:
            first = "" if first_skipped is None else f" (first: row {first_skipped[0]}: {first_skipped[1]})"
            raise CalibError(f"{path}: all {rows} sample rows are bad{first}")


def _row_tables(
    file,
    path: Path,
    header_line: str,
    header: list[str],
    numeric,
    textual,
    blank_is_nan,
    by_arrow: bool,
    block_bytes: int,
    what: str = "log file",
) -> Iterator[Table]:
    """The rows from ``file``'s position (just after the header line) to its end, parsed a block of
    about ``block_bytes`` at a time, each row numbered by its line in the file.

    ``by_arrow``: every column of the header is meant to hold numbers; pyarrow then reads a long
    file's blocks straight from the bytes (its import, ~0.1 s, pays off there), and anything it
    doubts goes the text path, which words the problems.
    """
    offset, line = file.tell(), 1
    by_arrow = by_arrow and os.fstat(file.fileno()).st_size > block_bytes
    while data := _next_block(file, block_bytes, path):
        table = numbers_by_arrow(header, data) if by_arrow else None
        if table is not None:
            lines = len(table)  # every line a row, or pyarrow would have refused the block
        else:
            text = _decoded(data, path, offset, what=what)
            table = parse_rows(header, f"{header_line}\n{text}", numeric, textual, blank_is_nan)
            lines = data.count(b"\n") + (not data.endswith(b"\n"))
        table.lines += line - 1
        offset, line = offset + len(data), line + lines
        yield table


def _line(file, path) -> bytes:
    """The rest of ``file``'s line (with its line break), refused past :data:`~stewart_calib.inputs.MAX_LINE_BYTES`."""
    line = file.readline(MAX_LINE_BYTES + 1)
    if len(line) > MAX_LINE_BYTES:
        raise CalibError(f"{shown(path)}: a line longer than {MAX_LINE_BYTES} bytes (no line break); expected CSV rows")
    return line


def _next_block(file, block_bytes: int, path: Path) -> bytes:
    """The next whole lines of ``file``, about ``block_bytes`` of them (empty at the end); a quoted
    field may hold a line break, so a block ends where the quotes pair up."""
    parts = [file.read(block_bytes)]
    if parts[0] and not parts[0].endswith(b"\n"):
        parts.append(_line(file, path))
    if b'"' in parts[0] or b'"' in parts[-1]:
        quotes = sum(part.count(b'"') for part in parts)
        while quotes % 2 and (more := _line(file, path)):
            parts.append(more)
            quotes += more.count(b'"')
    return b"".join(parts)


def _log_of(table: Table, has_pose: bool, textual: list[str], platform: Platform | None, inputs: InputColumns) -> Log:
    """The good rows of a checked table as a :class:`Log` [mm, rad]; its bad rows as ``skipped``."""
    skipped = [(int(table.lines[k]), table.issues[k]) for k in sorted(table.issues)]
    keep = np.ones(len(table), dtype=bool)
    keep[list(table.issues)] = False
    col = lambda names: np.column_stack([table.numbers[name][keep] for name in names]).reshape(-1, len(names))  # noqa: E731
    poses = None
    if has_pose:
        poses = col(POSE_COLUMNS)
        poses[:, 3:] = np.radians(poses[:, 3:])
    return Log(
        t_s=table.numbers["t_s"][keep],
        strokes=strokes_in_code_units(col(drive_columns(platform)), platform),
        readings=readings_in_code_units(col(reading_columns(platform)), platform),
        desired_poses=poses,
        stages=[s for s, k in zip(table.texts["stage"], keep, strict=True) if k] if textual else None,
        inputs=inputs.channels({name: table.numbers[name][keep] for name in inputs.names}),
        skipped=skipped,
    )


#: rows a block must hold before :meth:`LogRowParser.parse_block` hands it to pyarrow: a log read
#: faster than it is written (a replay, a reader catching up), where pyarrow's import (~0.07 s) pays off.
ARROW_MIN_ROWS = 64


class LogRowParser:
    """Spec §3 rows one at a time, for a log that is still being written (``track``).

    Each row gets exactly :func:`read_log`'s checks and messages (a row that is not plainly
    good is parsed as a one-row table by the same code); time must not go back from the last
    good row. A quoted field
    holding a line break is not supported (a stream is split at line breaks).

    Args:
        source: names the input in messages (a path or ``<stdin>``).
        header_line: the header row (a leading byte-order mark is dropped).
        platform: gives the stroke and reading ranges, or None.
    Raises:
        CalibError: a bad header (as :func:`read_log`).
    """

    def __init__(self, source: str, header_line: str, platform: Platform | None = None):
        self._path = Path(source)
        self._header_line = header_line.lstrip("\ufeff").rstrip("\r\n")
        self._header = read_header(self._path, self._header_line)
        self._has_pose, self._numeric, self._textual, self._inputs = _log_columns(self._path, self._header, platform)
        self._platform = platform
        self._last_t_s = -math.inf
        index = {name: k for k, name in enumerate(self._header)}
        readings = reading_columns(platform)
        stroke_indices = [index[name] for name in drive_columns(platform)]
        reading_indices = [index[name] for name in readings]
        pose_indices = [index[name] for name in POSE_COLUMNS] if self._has_pose else []
        # the input channels' fields: a row whose values are not plainly good takes the careful path
        self._input_indices = [index[name] for name in self._inputs.names]
        self._stage = index.get("stage")
        self._reading_angles = _angle_indices(platform)
        self._stroke_range = drive_range(platform)[0]
        self._strokes_in_degrees = _drive_in_degrees(platform)
        legs = not _kind(platform).outside
        self._reading_range = platform.reading_range if legs and platform is not None else None
        # a points instrument's empty coordinates (a target not seen) take the careful path
        self._plain_rows = not _kind(platform).unseen_channels
        # _plain's fields in one pick: t_s, the strokes, the readings, the pose (if any)
        self._pick_indices = (index["t_s"], *stroke_indices, *reading_indices, *pose_indices)
        self._pick = operator.itemgetter(*self._pick_indices)
        self._all_numeric = set(self._numeric) == set(self._header)  # what pyarrow's block reader takes
        self._stroke_slice = slice(1, 1 + len(stroke_indices))
        self._reading_slice = slice(self._stroke_slice.stop, self._stroke_slice.stop + len(reading_indices))

    def _plain(self, line: str) -> Sample | None:
        """The common row, fast: no quoting, every field a finite number within range, time
        not going back. Anything else gives None, and the careful path words the problem
        (the same fields, the same ``float`` parsing as numpy's, so the same samples)."""
        fields = line.split(",")
        if '"' in line or "_" in line or len(fields) != len(self._header):  # "_": float("1_0") is 10.0
            return None
        try:
            values = list(map(float, self._pick(fields)))  # t_s, strokes, readings, pose
            named = {name: float(fields[k]) for name, k in zip(self._inputs.names, self._input_indices, strict=True)}
        except ValueError:
            return None
        if not all(map(math.isfinite, values)) or values[0] < self._last_t_s or abs(values[0]) > MAX_TIME_S:
            return None
        if named and not self._inputs.plain_row(named):
            return None
        for bounds, group in ((self._stroke_range, self._stroke_slice), (self._reading_range, self._reading_slice)):
            if bounds is not None and not bounds[0] <= min(values[group]) <= max(values[group]) <= bounds[1]:
                return None
        self._last_t_s = t_s = values[0]
        row = np.array(values)  # one array a row; the sample's fields are views of it
        readings = row[self._reading_slice]
        if self._reading_angles:
            readings[self._reading_angles] = np.radians(readings[self._reading_angles])
        desired = None
        if self._has_pose:
            desired = row[self._reading_slice.stop :]
            desired[3:] = np.radians(desired[3:])
        stage = fields[self._stage].strip() if self._stage is not None else ""
        strokes = row[self._stroke_slice]
        if self._strokes_in_degrees:
            strokes[:] = np.radians(strokes)
        return Sample(t_s, strokes, readings, desired, stage, self._inputs.channels(named))

    def parse_block(self, lines: list[bytes]) -> Log | None:
        """The samples of consecutive rows ``lines`` (bytes, line breaks removed) when :meth:`parse`
        would take every one by its plain path: the same samples (correctly rounded numbers, the
        same checks and conversions) as one :class:`Log`, at a fraction of the cost a row. None,
        the parser unchanged, when any row is not plain (a blank line, quoting, text that is not
        UTF-8, a bad or out-of-range value, time going back): the caller then parses the rows one
        by one, and :meth:`parse` words the problem."""
        if not self._plain_rows or not lines:
            return None
        parsed = self._block_by_arrow(lines) if len(lines) >= ARROW_MIN_ROWS and self._all_numeric else None
        parsed = parsed or self._block_by_float(lines)
        if parsed is None:
            return None
        values, named, stages = parsed  # values: t_s, strokes, readings, pose; named: the input columns
        t_s = values[:, 0]
        if not np.isfinite(values).all() or t_s[0] < self._last_t_s or np.any(t_s[1:] < t_s[:-1]):
            return None
        if t_s[0] < -MAX_TIME_S or t_s[-1] > MAX_TIME_S:
            return None
        if named and not np.all(self._inputs.plain(named)):
            return None
        for bounds, group in ((self._stroke_range, self._stroke_slice), (self._reading_range, self._reading_slice)):
            if bounds is not None and not bounds[0] <= values[:, group].min() <= values[:, group].max() <= bounds[1]:
                return None
        self._last_t_s = float(t_s[-1])
        readings = values[:, self._reading_slice]
        if self._reading_angles:
            readings[:, self._reading_angles] = np.radians(readings[:, self._reading_angles])
        desired = None
        if self._has_pose:
            desired = values[:, self._reading_slice.stop :]
            desired[:, 3:] = np.radians(desired[:, 3:])
        strokes = values[:, self._stroke_slice]
        if self._strokes_in_degrees:
            strokes[:] = np.radians(strokes)
        return Log(t_s, strokes, readings, desired, stages, self._inputs.channels(named))

    def _block_by_arrow(self, lines: list[bytes]) -> tuple | None:
        """``(values, the input columns by name, None)`` of an all-numeric log's rows by pyarrow (several times faster
        a row than ``float`` on each field; BENCHMARKS.md), or None where it has any doubt."""
        table = numbers_by_arrow(self._header, b"\n".join(lines) + b"\n")
        if table is None or len(table) != len(lines):
            return None
        values = np.column_stack([table.numbers[self._header[k]] for k in self._pick_indices])
        return values, {name: table.numbers[name] for name in self._inputs.names}, None

    def _block_by_float(self, lines: list[bytes]) -> tuple | None:
        """``(values, the input columns by name, stages)`` of the rows by :meth:`_plain`'s field split and ``float``, or
        None where :meth:`_plain` would give None."""
        try:
            text = b"\n".join(lines).decode("utf-8")
        except UnicodeDecodeError:
            return None
        if '"' in text or "_" in text:  # "_": float("1_0") is 10.0; the careful path refuses it
            return None
        rows = [line.rstrip("\r").split(",") for line in text.split("\n")]  # parse strips a row's line-break characters
        if any(len(fields) != len(self._header) for fields in rows):  # a blank line too
            return None
        try:
            values = np.fromiter(map(float, chain.from_iterable(map(self._pick, rows))), dtype=float)
            named = {
                name: np.array([float(fields[k]) for fields in rows])
                for name, k in zip(self._inputs.names, self._input_indices, strict=True)
            }
        except ValueError:
            return None
        stages = [fields[self._stage].strip() for fields in rows] if self._stage is not None else None
        return values.reshape(len(rows), -1), named, stages

    def parse(self, line: str, row: int) -> Sample | None:
        """The sample of one row (``row``: its 1-based line number), or None for a blank line.

        Raises:
            CalibError: ``"<source>: row <row>: column '<name>': expected ..."`` for a bad row;
                the parser's state is unchanged, so the caller may skip the row and go on.
        """
        line = line.rstrip("\r\n")
        if not line.strip():
            return None
        if self._plain_rows:
            sample = self._plain(line)
            if sample is not None:
                return sample
        table = parse_careful(
            self._header,
            f"{self._header_line}\n{line}",
            self._numeric,
            self._textual,
            set(_blank_columns(self._platform)),
        )
        table.lines = np.array([row])
        _flag_log_values(table, self._platform, self._has_pose, self._inputs)
        t_s = float(table.numbers["t_s"][0])
        if not table.issues and t_s < self._last_t_s:
            table.issues[0] = _time_backwards(t_s, self._last_t_s)
        refuse_first(self._path, table)
        self._last_t_s = t_s
        number = lambda name: float(table.numbers[name][0])  # noqa: E731
        pose = None
        if self._has_pose:
            pose = np.array([number(name) for name in POSE_COLUMNS])
            pose[3:] = np.radians(pose[3:])
        return Sample(
            t_s,
            strokes_in_code_units(np.array([number(name) for name in drive_columns(self._platform)]), self._platform),
            readings_in_code_units(
                np.array([[number(name) for name in reading_columns(self._platform)]]), self._platform
            )[0],
            pose,
            table.texts["stage"][0] if self._textual else "",
            self._inputs.channels({name: number(name) for name in self._inputs.names}),
        )


# ----------------------------------------------------------------------------- truth


def write_pose_list(
    path: str | Path, poses: np.ndarray, dwell_s: float | None = 1.0, columns: dict[str, np.ndarray] | None = None
) -> None:
    """Write the six pose columns [mm, deg] (atomically), after ``t_s`` (one pose per ``dwell_s``
    seconds) unless ``dwell_s`` is None, and before any extra float ``columns`` (e.g. strokes).

    Raises:
        CalibError: a ``dwell_s`` that is not a finite positive number (times must increase).
    """
    poses, columns = np.asarray(poses, dtype=float).reshape(-1, 6), columns or {}
    extra = (
        np.column_stack([np.asarray(c, dtype=float) for c in columns.values()])
        if columns
        else np.empty((len(poses), 0))
    )
    write_pose_list_blocks(path, [(poses, extra)], tuple(columns), dwell_s)


def write_pose_list_blocks(
    path: str | Path,
    blocks: Iterable[tuple[np.ndarray, np.ndarray]],
    column_names: tuple[str, ...] = (),
    dwell_s: float | None = 1.0,
) -> int:
    """:func:`write_pose_list`'s file, byte for byte, from blocks ``(poses (n, 6) [mm, rad], columns
    (n, k))`` of consecutive rows, ``column_names`` naming the k extra columns, written as they
    come and atomically (:func:`~.tables.write_csv_blocks`). Returns the number of rows.

    Raises:
        CalibError: as :func:`write_pose_list`; the file cannot be written.
    """
    if dwell_s is not None and not (math.isfinite(dwell_s) and dwell_s > 0):
        raise CalibError(f"dwell time: expected a finite positive number of seconds, got {dwell_s!r}")

    def columns() -> Iterator[list[np.ndarray]]:
        rows = 0
        for poses, extra in blocks:
            lead = [] if dwell_s is None else [(rows + np.arange(len(poses))) * dwell_s]
            yield [*lead, *pose_columns_deg(poses), *np.asarray(extra).T]
            rows += len(poses)

    header = [*([] if dwell_s is None else ["t_s"]), *POSE_COLUMNS, *column_names]
    return write_csv_blocks(path, header, columns())


def read_pose_list(path: str | Path) -> np.ndarray:
    """The six pose columns of a pose list or a measurement log, ``(N, 6)`` [mm, rad];
    :func:`read_pose_list_blocks` gives them a block at a time.

    Raises:
        CalibError: missing file or columns, no rows, or a non-finite pose value (naming the row).
    """
    return np.concatenate(list(read_pose_list_blocks(path)))


#: bytes of a pose list read at a time (~8000 poses): a quarter of a log's, as a pose's work (its
#: IK, its written row) holds several times its text (compensate at 10⁶ poses peaks at 225 MB,
#: 251 MB with 4 MB blocks, in the same time).
POSE_BLOCK_BYTES = 1 << 20

#: columns a pose list holds as numbers when written by this package (its own, a log's, strokes):
#: a header of these only is read by pyarrow.
_POSE_LIST_NUMBERS = frozenset(
    ("t_s", *POSE_COLUMNS, *STROKE_COLUMNS, *ANGLE_COLUMNS, *READING_COLUMNS, *TEMPERATURE_COLUMNS, *GRAVITY_COLUMNS)
)


def read_pose_list_blocks(path: str | Path, block_bytes: int | None = None) -> Iterator[np.ndarray]:
    """:func:`read_pose_list`'s poses, checks and messages, ``(n, 6)`` [mm, rad] a block of rows at
    a time (about ``block_bytes`` of text, default :data:`POSE_BLOCK_BYTES`): memory stays that of one
    block however long the list. A block may hold no pose (blank lines).

    A refusal is raised when its block is reached (no rows: after the last), so a consumer must
    not act on earlier blocks before the last one is read. Bytes that are not UTF-8 anywhere in
    the file are refused before any other problem, as when the file was read whole.

    Raises:
        CalibError: as :func:`read_pose_list`.
    """
    path, block_bytes = Path(path), block_bytes or POSE_BLOCK_BYTES
    with _open_log(path, "pose list") as file:
        first = _line(file, path)
        header_line = _decoded(first, path, 0, "utf-8-sig", "pose list").rstrip("\n")  # a spreadsheet's byte-order mark
        try:
            yield from _pose_list_blocks(file, path, header_line, block_bytes)
        except _NotUtf8:
            raise
        except CalibError:
            _refuse_non_utf8(file, path, len(first), "pose list")
            raise


def _pose_list_blocks(file, path: Path, header_line: str, block_bytes: int) -> Iterator[np.ndarray]:
    """:func:`read_pose_list_blocks` after the header line, ``file`` positioned just after it."""
    start = file.tell()
    if not header_line.strip() and not any(chunk.strip() for chunk in iter(lambda: file.read(1 << 16), b"")):
        read_header(path, "")  # refuses the empty file
    header = header_fields(path, header_line)
    require_columns(path, header, POSE_COLUMNS)
    file.seek(start)
    rows = 0
    for table in _row_tables(
        file,
        path,
        header_line,
        header,
        POSE_COLUMNS,
        (),
        (),
        set(header) <= _POSE_LIST_NUMBERS,
        block_bytes,
        "pose list",
    ):
        flag_non_finite(table, POSE_COLUMNS)
        refuse_first(path, table)
        rows += len(table)
        poses = np.column_stack([table.numbers[name] for name in POSE_COLUMNS]).reshape(-1, 6)
        poses[:, 3:] = np.radians(poses[:, 3:])
        yield poses
    if rows == 0:
        raise CalibError(f"{path}: no sample rows; expected a header row and at least one sample row")


def _refuse_non_utf8(file, path: Path, offset: int, what: str) -> None:
    """Refuse the first bytes from ``offset`` on that are not UTF-8 text, if any."""
    file.seek(offset)
    while data := _next_block(file, BLOCK_BYTES, path):
        if not data.isascii():
            _decoded(data, path, offset, what=what)
        offset += len(data)


def write_truth(path: str | Path, truth: Truth, platform: Platform | None = None) -> None:
    """Write a truth file (spec §4) atomically; see :func:`truth_text`."""
    atomic_write_text(path, truth_text(truth, platform=platform))


def _parameter_names(platform: Platform | None) -> tuple[str, ...]:
    """The drive parameters' names of ``platform`` (spec §5, §15); the 42 without a platform."""
    return PARAMETER_NAMES if platform is None else platform.drive.parameter_names


def truth_text(truth: Truth, header: bool = True, platform: Platform | None = None) -> str:
    """A truth file's CSV (spec §4): ``t_s``, the drive's parameters (``platform``'s: the 42 [mm]
    without one, a rotary drive's 66 with its angles in degrees, spec §15), the true pose [mm, deg]
    if present, then the constant spec §7 truth columns (a rotary drive's angle scale ``k1 … k6``) and an
    elastic robot's unloaded drive (spec §10, ``unloaded_j1x …``).

    ``header=False``: the rows only, to append to a truth file written block by block.
    """
    names = ["t_s", *_parameter_names(platform)]
    params = np.asarray(truth.params, dtype=float)
    params = params if platform is None else parameters_to_file(params, platform.drive)
    columns = [truth.t_s, *params.T]
    if truth.true_poses is not None:
        names += TRUE_POSE_COLUMNS
        columns += pose_columns_deg(truth.true_poses)
    # spec §7 truth, constant over the log: one column per value, added beside §4's
    constants: list[tuple[str, float]] = []
    if STROKE_SCALE in truth.drive_terms:
        constants += zip(STROKE_SCALE_NAMES, truth.drive_terms[STROKE_SCALE], strict=True)
    if truth.instrument is not None:
        constants += zip(*truth.instrument, strict=True)
    if truth.unloaded is not None:
        unloaded = truth.unloaded if platform is None else parameters_to_file(truth.unloaded, platform.drive)
        constants += zip((UNLOADED_PREFIX + name for name in _parameter_names(platform)), unloaded, strict=True)
    for name, value in constants:
        names.append(name)
        columns.append(np.full(len(truth.t_s), float(value)))
    return csv_text(names, columns, header)


def read_truth(path: str | Path, platform: Platform | None = None) -> Truth:
    """Read a truth file (spec §4) of ``platform``'s drive (the 42 parameters without one; a rotary
    drive's 66, its angles read in degrees into radians, spec §15).

    Raises:
        CalibError: as for logs — missing file or column, no rows, a bad value (never skipped).
    """
    path = Path(path)
    text = read_text(path, "truth file")
    header = read_header(path, text)
    required = ("t_s", *_parameter_names(platform))
    require_columns(path, header, required)
    has_pose = optional_group(path, header, TRUE_POSE_COLUMNS)
    numeric = [*required, *(TRUE_POSE_COLUMNS if has_pose else ())]
    table = parse_table(path, header, text, numeric)
    flag_non_finite(table, numeric)
    refuse_first(path, table)
    poses = None
    if has_pose:
        poses = np.column_stack([table.numbers[name] for name in TRUE_POSE_COLUMNS])
        poses[:, 3:] = np.radians(poses[:, 3:])
    params = np.column_stack([table.numbers[name] for name in _parameter_names(platform)])
    params = params if platform is None else parameters_from_file(params, platform.drive)
    scale = None
    if all(name in header for name in STROKE_SCALE_NAMES):
        scale = _first_numbers(path, header, text, STROKE_SCALE_NAMES)
    unloaded_names = [UNLOADED_PREFIX + name for name in _parameter_names(platform)]
    unloaded = None
    if all(name in header for name in unloaded_names):
        unloaded = _first_numbers(path, header, text, unloaded_names)
        unloaded = unloaded if platform is None else parameters_from_file(unloaded, platform.drive)
    others = [name for name in header if name and name not in {*numeric, *STROKE_SCALE_NAMES, *unloaded_names}]
    instrument = (tuple(others), _first_numbers(path, header, text, others)) if others else None
    terms = {} if scale is None else {STROKE_SCALE: scale}
    return Truth(table.numbers["t_s"], params, poses, terms, instrument, unloaded)


def _first_numbers(path: Path, header: list[str], text: str, names: list[str] | tuple[str, ...]) -> np.ndarray:
    """The values of constant truth columns (spec §7 blocks, §10's unloaded drive) in the first row."""
    table = parse_table(path, header, text, list(names))
    flag_non_finite(table, list(names))
    refuse_first(path, table)
    return np.array([table.numbers[name][0] for name in names], dtype=float)
