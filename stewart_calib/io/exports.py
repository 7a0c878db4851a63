"""What instruments and controllers export, read a block at a time (``stewart-calib import``).

Each reader yields :class:`Block`\\ s — times [s] on the file's own clock and values in the
log's units (mm, degrees) — from files of any length, holding one block of rows:

* :func:`motive_blocks` — an OptiTrack Motive CSV export (format 1.2x): a first line of
  ``key,value`` pairs (``Length Units``, ``Rotation Type``, …), a blank line, then five header rows
  (type, name, ID, property, axis; the first two columns ``Frame`` and ``Time (Seconds)``) and one
  row per frame; a rigid body is chosen by name, its ``Rotation`` ``X Y Z W`` (quaternion) and
  ``Position`` ``X Y Z`` columns read; a frame where it was not tracked has empty cells;
* :func:`vicon_blocks` — a Vicon Nexus CSV export: a section title (``Segments`` or
  ``Trajectories``), the capture rate, a row of ``Subject:Name`` labels, the axis row (``Frame,Sub
  Frame,RX,RY,RZ,TX,TY,TZ`` for a segment, ``X,Y,Z`` per marker) and a units row, then frames; a
  segment's ``RX RY RZ`` is its orientation as a rotation vector (helical angle) in degrees;
* :func:`table_blocks` — a plain CSV with one header row, any columns (a generic instrument export
  described by a mapping file, or a controller's log of strokes);
* :func:`point_list_blocks` — a laser tracker's point list in long form (one row per measured
  target: time, target name, X, Y, Z; SpatialAnalyzer and the vendors' software export this),
  grouped by time into one row of up to K targets, a target not measured left empty.

The conversions: positions to mm by the file's unit; orientation to roll-pitch-yaw [deg] with
``R = Rz(yaw) Ry(pitch) Rx(roll)`` (spec §1) from a quaternion (either order) or Euler angles
(scipy's convention strings: upper case intrinsic, lower case extrinsic); a Y-up system turned
to Z-up (``x' = x, y' = −z, z' = y``, a proper rotation); encoder counts to mm per leg; a
controller's temperatures (one per leg, or one for all) to °C per leg (spec §17); its payload to kg
(spec §10).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import CalibError, did_you_mean
from ..errors import number as shown_number
from ..model.rotations import quaternion_to_rotation, rotation_to_rpy
from .logs import TEMPERATURE_COLUMNS

#: millimetres per length unit, by the names a mapping file or an export uses
MM_PER = {
    "m": 1000.0,
    "meters": 1000.0,
    "metres": 1000.0,
    "cm": 10.0,
    "centimeters": 10.0,
    "mm": 1.0,
    "millimeters": 1.0,
    "um": 1e-3,
    "in": 25.4,
    "inches": 25.4,
}
#: degrees per angle unit: a servo drive's commanded angles (spec §15), which a log holds in degrees
DEG_PER = {"deg": 1.0, "degrees": 1.0, "rad": 180.0 / np.pi, "radians": 180.0 / np.pi}
#: seconds per time unit
S_PER = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
#: °C at 0 of a temperature unit: a controller's temperatures, which a log holds in °C (spec §17)
CELSIUS_AT_ZERO = {"C": 0.0, "K": -273.15}
#: kilograms per mass unit: a controller's payload, which a log holds in kg (``load_kg``, spec §10)
KG_PER = {"kg": 1.0, "g": 1e-3, "lb": 0.45359237}
#: how a note names a temperature unit
_TEMPERATURE_WORDS = {"C": "°C", "K": "K"}
#: a platform's orientation in an instrument set up near it stays this close to the identity [deg]
NEAR_IDENTITY_DEG = 30.0
#: groups of a point list held before they are handed on as a block
POINT_LIST_ROWS = 65536
#: Z-up from Y-up: x' = x, y' = −z, z' = y
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: bytes of text a block holds (pyarrow's reader peaks near 40× a block: 4 MiB blocks held ~270 MB, 1 MiB ~150 MB)
BLOCK_BYTES = 1 << 20


@dataclass
class Block:
    """Rows of an export: ``t_s (n,)`` on its clock [s], ``values (n, k)``, and the 1-based file
    line of each row (``lines (n,)``) for messages."""

    t_s: np.ndarray
    values: np.ndarray
    lines: np.ndarray


def _refuse(path, message: str):
    raise CalibError(f"{path}: {message}")


class _TextFile:
    """An export's text, read a line at a time (``readline``, iteration, a context manager); a line
    that is not UTF-8 is refused naming the file and row, not raised as a decoding traceback."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.file = open(path, encoding="utf-8-sig", newline="")
        except FileNotFoundError:
            _refuse(path, "file not found")
        except OSError as err:
            _refuse(path, f"cannot read ({err.strerror})")

    def readline(self) -> str:
        try:
            line = self.file.readline()
        except UnicodeDecodeError as err:  # decoded a chunk ahead: the row from the bytes (the slow path)
            _refuse(self.path, f"row {self._undecodable_row()}: not UTF-8 text ({err.reason}); expected UTF-8 CSV")
        return line

    def _undecodable_row(self) -> int:
        with open(self.path, "rb") as raw:
            for row, line in enumerate(raw, start=1):
                try:
                    line.decode("utf-8-sig" if row == 1 else "utf-8")
                except UnicodeDecodeError:
                    return row
        return 1

    def __iter__(self) -> Iterator[str]:
        while line := self.readline():
            yield line

    def __enter__(self) -> _TextFile:
        return self

    def __exit__(self, *exc) -> None:
        self.file.close()


def _open_text(path: Path) -> _TextFile:
    return _TextFile(path)


def _split(line: str) -> list[str]:
    return [field.strip().strip('"') for field in line.rstrip("\r\n").split(",")]


def numeric_blocks(path: Path, first_line: int, names: list[str], wanted: list[int]) -> Iterator[Block]:
    """The columns ``wanted`` (indices into the file's columns ``names``) of the data rows from
    line ``first_line`` (1-based) on, as float arrays (an empty cell: NaN), a block of about
    :data:`BLOCK_BYTES` at a time. ``Block.t_s`` is the first wanted column, ``values`` the rest.

    Raises:
        CalibError: a cell that is not a number, named by line and column.
    """
    import pyarrow as pa
    from pyarrow import csv as pacsv

    read = pacsv.ReadOptions(
        skip_rows=first_line - 1,
        column_names=[f"c{j}" for j in range(len(names))],
        block_size=BLOCK_BYTES,
        use_threads=False,
    )
    include = [f"c{j}" for j in wanted]
    convert = pacsv.ConvertOptions(
        include_columns=include, column_types={c: pa.float64() for c in include}, strings_can_be_null=True
    )
    parse = pacsv.ParseOptions(invalid_row_handler=None)
    line = first_line
    try:
        reader = pacsv.open_csv(path, read_options=read, parse_options=parse, convert_options=convert)
        for batch in reader:
            columns = [batch.column(c).to_numpy(zero_copy_only=False).astype(float) for c in include]
            n = batch.num_rows
            yield Block(
                columns[0], np.column_stack(columns[1:]) if len(columns) > 1 else np.zeros((n, 0)), line + np.arange(n)
            )
            line += n
    except pa.ArrowInvalid as err:
        _refuse(path, _first_bad_cell(path, first_line, names, wanted) or " ".join(str(err).split()))


def _first_bad_cell(path: Path, first_line: int, names: list[str], wanted: list[int]) -> str | None:
    """Where pyarrow stopped, in our words: the first row with too few fields or a wanted cell that
    is no number (the slow path, read only after a refusal)."""
    with _open_text(path) as file:
        for number, text in enumerate(file, start=1):
            if number < first_line or not text.strip():
                continue
            fields = _split(text)
            if len(fields) < len(names):
                return f"row {number}: expected {len(names)} fields, got {len(fields)}"
            for j in wanted:
                try:
                    float(fields[j]) if fields[j] else None
                except ValueError:
                    return f"row {number}: column '{names[j]}': expected a number, got {fields[j]!r}"
    return None


# ----------------------------------------------------------------------------- orientations


def euler_rotations(angles_rad: np.ndarray, convention: str) -> np.ndarray:
    """``(n, 3)`` Euler angles [rad] in scipy's ``convention`` (e.g. ``ZYX`` intrinsic, ``xyz``
    extrinsic) → ``(n, 3, 3)`` rotations."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler(convention, angles_rad).as_matrix()


def rotation_vector_rotations(rotvec_rad: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rotvec_rad).as_matrix()


def pose_columns(positions_mm: np.ndarray, R: np.ndarray, up: str) -> np.ndarray:
    """``(n, 6)`` ``mx_mm … myaw_deg`` of positions [mm] and rotations, turned to Z-up if ``up == "y"``."""
    if up == "y":
        positions_mm = positions_mm @ Y_UP_TO_Z_UP.T
        R = Y_UP_TO_Z_UP @ R
    return np.column_stack([positions_mm, np.degrees(rotation_to_rpy(R))])


def points_columns(points_mm: np.ndarray, up: str) -> np.ndarray:
    """``(n, 3K)`` ``p1x_mm …`` turned to Z-up if ``up == "y"``."""
    if up != "y":
        return points_mm
    n = len(points_mm)
    return (points_mm.reshape(n, -1, 3) @ Y_UP_TO_Z_UP.T).reshape(n, -1)


# ----------------------------------------------------------------------------- Motive


@dataclass(frozen=True)
class Layout:
    """Where a reader finds its columns: the file's column names, the first data line, the
    indices of time and the value columns, and what the header says (units, rotation type)."""

    names: list[str]
    first_line: int
    columns: list[int]
    mm_per_unit: float
    note: str


def motive_layout(path: Path, body: str) -> Layout:
    """The columns of rigid body ``body`` in a Motive CSV export (time, qx, qy, qz, qw, x, y, z).

    Raises:
        CalibError: not a Motive export, a rotation type other than quaternion, an unknown length
            unit, or no rigid body of that name (the ones present are listed).
    """
    with _open_text(path) as file:
        header = [file.readline() for _ in range(7)]
    info_fields = _split(header[0])
    if not info_fields or info_fields[0] != "Format Version":
        _refuse(path, "row 1: expected a Motive CSV export starting with 'Format Version'")
    info = dict(zip(info_fields[0::2], info_fields[1::2], strict=False))
    rotation = info.get("Rotation Type", "Quaternion")
    if rotation != "Quaternion":
        _refuse(path, f"row 1: 'Rotation Type' is {rotation!r}; export again with Rotation Type = Quaternion")
    unit = info.get("Length Units", "Meters").lower()
    if unit not in MM_PER:
        _refuse(
            path, f"row 1: 'Length Units' {info.get('Length Units')!r}; expected Meters, Centimeters or Millimeters"
        )
    types, labels, ids, properties, axes = (_split(line) for line in header[2:7])
    if axes[:2] != ["Frame", "Time (Seconds)"]:
        _refuse(path, "row 7: expected the columns 'Frame' and 'Time (Seconds)' first (Motive's header of 7 rows)")
    found = {}
    bodies = []
    body_ids: list[str] = []  # the IDs (row 5) of the rigid bodies named ``body``
    ids += [""] * (len(types) - len(ids))
    for j, (kind, label, prop, axis) in enumerate(zip(types, labels, properties, axes, strict=False)):
        if kind != "Rigid Body":
            continue
        if label not in bodies:
            bodies.append(label)
        if label == body and ids[j] not in body_ids:
            body_ids.append(ids[j])
        if label == body and prop in ("Rotation", "Position"):
            if (prop, axis) in found:  # a second body of this name: which is the platform cannot be told
                shown = f" (IDs {', '.join(body_ids)})" if len(body_ids) > 1 else ""
                _refuse(
                    path,
                    f"row 4: two rigid bodies are named {body!r}{shown}; rename one in Motive and export again",
                )
            found[(prop, axis)] = j
    keys = [("Rotation", "X"), ("Rotation", "Y"), ("Rotation", "Z"), ("Rotation", "W")]
    keys += [("Position", "X"), ("Position", "Y"), ("Position", "Z")]
    if body not in bodies:
        _refuse(path, f"row 4: no rigid body named {body!r}; the file has {', '.join(map(repr, bodies)) or 'none'}")
    missing = [f"{p} {a}" for p, a in keys if (p, a) not in found]
    if missing:
        _refuse(path, f"rigid body {body!r}: no column {', '.join(missing)}")
    return Layout(axes, 8, [1, *(found[k] for k in keys)], MM_PER[unit], f"lengths in {info.get('Length Units')}")


def motive_blocks(path: Path, body: str, up: str = "y") -> tuple[Iterator[Block], str]:
    """Rigid body ``body``'s poses (``mx_mm … myaw_deg``) from a Motive CSV export; frames where
    it was not tracked (empty cells) come as NaN rows."""
    layout = motive_layout(path, body)

    def blocks():
        for block in numeric_blocks(path, layout.first_line, layout.names, layout.columns):
            q, p = block.values[:, :4], block.values[:, 4:] * layout.mm_per_unit
            yield Block(block.t_s, _poses_or_nan(p, q, "xyzw", up), block.lines)

    return blocks(), f"Motive rigid body {body!r}, quaternion x y z w, {layout.note}, {up.upper()}-up"


def _poses_or_nan(positions_mm: np.ndarray, q: np.ndarray, order: str, up: str) -> np.ndarray:
    out = np.full((len(q), 6), np.nan)
    seen = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(positions_mm), axis=1)
    seen &= np.linalg.norm(np.where(np.isfinite(q), q, 0.0), axis=1) > 1e-9
    if seen.any():
        out[seen] = pose_columns(positions_mm[seen], quaternion_to_rotation(q[seen], order), up)
    return out


# ----------------------------------------------------------------------------- Vicon


def vicon_blocks(
    path: Path, names: list[str], up: str = "z", option: str | None = None
) -> tuple[Iterator[Block], str, str]:
    """A segment's poses (``Segments`` section, one name) or markers' positions (``Trajectories``,
    names in the order of ``p1 …``) from a Vicon Nexus CSV export; returns ``(blocks, what was
    read, kind)`` with kind ``pose`` or ``points``. The time is ``(Frame − 1) / rate``. A name is a
    ``Subject:Name`` label or its ``Name`` alone where one subject has it; ``option`` (``--segment``
    or ``--markers``) is the command-line option that named them, checked against the section."""
    with _open_text(path) as file:
        header = [file.readline() for _ in range(5)]
    section = _split(header[0])[0]
    if section not in ("Segments", "Trajectories"):
        _refuse(path, f"row 1: expected a Vicon Nexus export section 'Segments' or 'Trajectories', got {section!r}")
    wanted = {"Segments": "--segment", "Trajectories": "--markers"}[section]
    if option is not None and option != wanted:
        _refuse(path, f"row 1: a {section} export, read with {wanted} (not {option})")
    try:
        rate = float(_split(header[1])[0])
    except ValueError:
        _refuse(path, f"row 2: expected the capture rate [Hz], got {_split(header[1])[0]!r}")
    if not (math.isfinite(rate) and rate > 0):
        _refuse(path, f"row 2: expected the capture rate [Hz], a positive number, got {_split(header[1])[0]!r}")
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        _refuse(path, f"{option or 'names'}: {twice[0]!r} is named twice; expected each marker once")
    labels, axes, units = _split(header[2]), _split(header[3]), _split(header[4])
    if axes[:2] != ["Frame", "Sub Frame"]:
        _refuse(path, "row 4: expected the columns 'Frame' and 'Sub Frame' first (Vicon Nexus's header)")
    present = [label for label in labels if label]
    width = 6 if section == "Segments" else 3
    expected = ["RX", "RY", "RZ", "TX", "TY", "TZ"] if section == "Segments" else ["X", "Y", "Z"]
    if section == "Segments" and len(names) != 1:
        _refuse(path, f"a Segments export gives one pose: expected one segment name, got {len(names)}")
    columns, length_units = [0], set()
    for name in names:
        matches = [j for j, label in enumerate(labels) if label and name in (label, label.split(":")[-1])]
        what = section[:-1].lower().replace("trajectorie", "marker")
        if not matches:
            _refuse(path, f"row 3: no {what} named {name!r}; the file has {', '.join(map(repr, present))}")
        if len(matches) > 1:  # two subjects with a segment (marker) of this name: which one is the platform's?
            held = ", ".join(f"{labels[j]!r} (field {j + 1})" for j in matches)
            fix = (
                "rename one in Nexus and export again"
                if len({labels[j] for j in matches}) < len(matches)
                else "name one as Subject:Name"
            )
            _refuse(path, f"row 3: {len(matches)} {what}s are named {name!r}: {held}; {fix}")
        j = matches[0]
        if axes[j : j + width] != expected:
            _refuse(
                path, f"row 4: {labels[j]!r}: expected the columns {', '.join(expected)}, got {axes[j : j + width]}"
            )
        columns += list(range(j, j + width))
        length_units.add(units[j + width - 1].lower() if j + width - 1 < len(units) else "")
    if len(length_units) != 1 or next(iter(length_units)) not in MM_PER:
        _refuse(path, f"row 5: expected one length unit (mm or m) for {', '.join(names)}, got {sorted(length_units)}")
    mm = MM_PER[length_units.pop()]
    in_radians = section == "Segments" and units[columns[1]].lower() == "rad"

    def blocks():
        for block in numeric_blocks(path, 6, axes, columns):
            t_s, v = (block.t_s - 1.0) / rate, block.values
            if section == "Trajectories":
                yield Block(t_s, points_columns(v * mm, up), block.lines)
                continue
            out = np.full((len(v), 6), np.nan)
            seen = np.all(np.isfinite(v), axis=1)
            if seen.any():
                angles = v[seen, :3] if in_radians else np.radians(v[seen, :3])
                out[seen] = pose_columns(v[seen, 3:] * mm, rotation_vector_rotations(angles), up)
            yield Block(t_s, out, block.lines)

    what = f"Vicon {section.lower()} {', '.join(map(repr, names))} at {rate:g} Hz, {up.upper()}-up"
    return blocks(), what, "pose" if section == "Segments" else "points"


# ----------------------------------------------------------------------------- mapping files


MAPPING_KEYS = {
    "instrument": {
        "time",
        "time_unit",
        "time_format",
        "position",
        "position_unit",
        "quaternion",
        "quaternion_order",
        "euler",
        "euler_convention",
        "angle_unit",
        "points",
        "up",
        "target",
        "targets",
    },
    "strokes": {
        "time",
        "time_unit",
        "columns",
        "unit",
        "counts_per_mm",
        "mm_per_rev",
        "counts_per_rev",
        "sign",
        "zero",
        "clock_offset_s",
        "max_gap_s",
        "temperatures",
        "temperature_unit",
        "load_kg",
        "load_unit",
    },
}


def load_mapping(path: Path) -> dict:
    """A mapping file (TOML, docs/formats.md §12): ``[instrument]`` and/or ``[strokes]``.

    Raises:
        CalibError: not TOML, or an unknown table or key (with the nearest known one).
    """
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        _refuse(path, "mapping file not found")
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        _refuse(path, f"not a TOML mapping file ({err})")
    for table, value in data.items():
        if table not in MAPPING_KEYS:
            _refuse(
                path, f"unknown table [{table}]{did_you_mean(table, MAPPING_KEYS)}; expected [instrument] or [strokes]"
            )
        if not isinstance(value, dict):
            _refuse(path, f"{table}: expected a table [{table}]")
        for key in value:
            if key not in MAPPING_KEYS[table]:
                _refuse(path, f"unknown key '{table}.{key}'{did_you_mean(key, MAPPING_KEYS[table])}")
    return data


def mapping_value(path, table: dict, section: str, key: str, default=None, kind=None, choices=None):
    """``table[key]`` checked against ``kind`` (a type or tuple) and ``choices``; refusals name the key."""
    value = table.get(key, default)
    if value is None:
        return None
    if (kind is not None and not isinstance(value, kind)) or (isinstance(value, bool) and kind is not bool):
        _refuse(path, f"'{section}.{key}': expected {_kind_words(kind)}, got {value!r}")
    if choices is not None and value not in choices:
        _refuse(path, f"'{section}.{key}': expected one of {', '.join(map(str, choices))}, got {value!r}")
    return value


def _kind_words(kind) -> str:
    if kind is list:
        return "a list"
    if kind is str:
        return "a string"
    return "a number"


def header_of(path: Path) -> list[str]:
    with _open_text(path) as file:
        line = file.readline()
    if not line.strip():
        _refuse(path, "row 1: expected a header row of column names")
    return _split(line)


def column_indices(path: Path, header: list[str], names: list, key: str) -> list[int]:
    """The indices of ``names`` in ``header``; an unknown name is refused with the nearest present,
    a name the header holds twice (which of them is meant cannot be told) naming both places."""
    out = []
    for name in names:
        if not isinstance(name, str):
            _refuse(path, f"'{key}': expected column names, got {name!r}")
        if name not in header:
            _refuse(path, f"'{key}': no column {name!r} in the file{did_you_mean(name, header)}")
        places = [j + 1 for j, label in enumerate(header) if label == name]
        if len(places) > 1:
            _refuse(
                path,
                f"row 1: column {name!r} ('{key}') appears {len(places)} times in the header (fields "
                f"{', '.join(map(str, places))}); expected one column of each name",
            )
        out.append(header.index(name))
    return out


def check_distinct(mapping_path, uses: list[tuple[str, list]]) -> None:
    """Refuse a mapping that reads one column for two quantities (``uses``: ``(key, column names)``
    in the order the mapping gives them, e.g. the time column also named as a position)."""
    seen: dict[str, str] = {}
    for key, names in uses:
        for name in names:
            if name in seen:
                same = "twice" if seen[name] == key else f"as '{seen[name]}' and as '{key}'"
                _refuse(mapping_path, f"column {name!r} is named {same}; expected a different column for each")
            seen[name] = key


def check_quaternion_order(path, mapping_path, columns: list[str], order: str, q: np.ndarray) -> None:
    """Refuse quaternions whose declared order puts the scalar in the wrong place, told without
    any model by where the identity is: a platform's orientation in an instrument set up near it
    stays within tens of degrees of the identity, whose scalar part is ±1 — read in the other
    order, that scalar becomes a vector part, and every rotation lies near 180°. A unit-norm check
    cannot tell (every order has norm 1), nor can the spread of the rotations (the other order
    turns between two rows by the same angles). Refused only where the declared order puts every
    row near 180° and the other near the identity (an instrument really turned 180° from the
    platform reads so too: its platform file's frame, through ``--platform``, decides then)."""
    finite = np.all(np.isfinite(q), axis=1)
    norm = np.linalg.norm(q[finite], axis=1)
    if not finite.any() or not np.all(norm > 0):
        return
    other = "xyzw" if order == "wxyz" else "wxyz"
    scalar = np.abs(q[finite] / norm[:, None])

    def angles_deg(order_: str) -> np.ndarray:
        return np.degrees(2.0 * np.arccos(np.clip(scalar[:, order_.index("w")], 0.0, 1.0)))

    declared, fits = angles_deg(order), angles_deg(other)
    if np.min(declared) > 180.0 - NEAR_IDENTITY_DEG and np.max(fits) < NEAR_IDENTITY_DEG:
        _refuse(
            mapping_path,
            f"'instrument.quaternion_order' = {order!r}: read so, the quaternions {', '.join(columns)} of {path} are "
            f"all {np.min(declared):.0f}–{np.max(declared):.0f}° from the identity; read as {other!r}, within "
            f"{np.max(fits):.0f}° of it: expected quaternion_order = {other!r} (an instrument turned 180° from the "
            "platform: give --platform with its frame to check the order against the strokes)",
        )


def generic_instrument_blocks(
    path: Path,
    mapping_path: Path,
    table: dict,
    up_default: str = "z",
    extra: list[str] | None = None,
    check_order: bool = True,
):
    """A plain CSV described by ``[instrument]``: ``(blocks, what, kind)``; the columns ``extra``
    (e.g. the strokes logged in the same rows) follow the measurement's in each block, as read.
    ``check_order``: refuse quaternions whose declared order looks wrong
    (:func:`check_quaternion_order`; without it the platform's check against the strokes decides)."""
    extra = extra or []
    header = header_of(path)
    section = "instrument"
    time = mapping_value(mapping_path, table, section, "time", None, str)
    if time is None:
        _refuse(mapping_path, "'instrument.time': expected the name of the time column")
    time_scale = S_PER[mapping_value(mapping_path, table, section, "time_unit", "s", str, tuple(S_PER))]
    unit = mapping_value(mapping_path, table, section, "position_unit", "mm", str, tuple(MM_PER))
    up = mapping_value(mapping_path, table, section, "up", up_default, str, ("y", "z"))
    points = mapping_value(mapping_path, table, section, "points", None, list)
    if points is not None:
        if not points or not all(isinstance(p, list) and len(p) == 3 for p in points):
            _refuse(mapping_path, "'instrument.points': expected a list of [x, y, z] column names per target")
        flat = [c for p in points for c in p]
        columns = column_indices(path, header, [time, *flat], "instrument.points")
        columns += column_indices(path, header, extra, "strokes.columns")
        check_distinct(
            mapping_path, [("instrument.time", [time]), ("instrument.points", flat), ("strokes.columns", extra)]
        )
        width = 3 * len(points)

        def point_blocks():
            for block in numeric_blocks(path, 2, header, columns):
                measured = points_columns(block.values[:, :width] * MM_PER[unit], up)
                yield Block(block.t_s * time_scale, np.hstack([measured, block.values[:, width:]]), block.lines)

        return point_blocks(), f"{len(points)} target(s) in {unit}, {up.upper()}-up", "points"
    position = mapping_value(mapping_path, table, section, "position", None, list)
    if position is None or len(position) != 3:
        _refuse(mapping_path, "'instrument.position': expected the three position columns [x, y, z]")
    quaternion = mapping_value(mapping_path, table, section, "quaternion", None, list)
    euler = mapping_value(mapping_path, table, section, "euler", None, list)
    if (quaternion is None) == (euler is None):
        _refuse(mapping_path, "[instrument]: expected either 'quaternion' (4 columns) or 'euler' (3 columns)")
    if quaternion is not None:
        order = mapping_value(mapping_path, table, section, "quaternion_order", None, str, ("wxyz", "xyzw"))
        if order is None or len(quaternion) != 4:
            _refuse(mapping_path, "'instrument.quaternion': expected 4 columns and quaternion_order = wxyz or xyzw")
        angles, what = quaternion, f"quaternion {' '.join(order)}"
    else:
        convention = mapping_value(mapping_path, table, section, "euler_convention", "ZYX", str)
        try:
            euler_rotations(np.zeros((1, 3)), convention)
        except ValueError:
            _refuse(
                mapping_path, f"'instrument.euler_convention': expected e.g. ZYX (intrinsic) or xyz, got {convention!r}"
            )
        if len(euler) != 3:
            _refuse(mapping_path, "'instrument.euler': expected the three angle columns")
        angle_unit = mapping_value(mapping_path, table, section, "angle_unit", "deg", str, ("deg", "rad"))
        angles, what = euler, f"Euler {convention} in {angle_unit}"
    columns = column_indices(path, header, [time, *position, *angles], "instrument")
    columns += column_indices(path, header, extra, "strokes.columns")
    angle_key = "instrument.quaternion" if quaternion is not None else "instrument.euler"
    check_distinct(
        mapping_path,
        [
            ("instrument.time", [time]),
            ("instrument.position", position),
            (angle_key, angles),
            ("strokes.columns", extra),
        ],
    )

    def pose_blocks():
        first = True
        for block in numeric_blocks(path, 2, header, columns):
            p, a = block.values[:, :3] * MM_PER[unit], block.values[:, 3 : 3 + len(angles)]
            if quaternion is not None:
                if first and check_order:
                    check_quaternion_order(path, mapping_path, quaternion, order, a)
                first = False
                out = _poses_or_nan(p, a, order, up)
            else:
                out = np.full((len(a), 6), np.nan)
                seen = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(p), axis=1)
                if seen.any():
                    rad = a[seen] if angle_unit == "rad" else np.radians(a[seen])
                    out[seen] = pose_columns(p[seen], euler_rotations(rad, convention), up)
            yield Block(block.t_s * time_scale, np.hstack([out, block.values[:, 3 + len(angles) :]]), block.lines)

    return pose_blocks(), f"pose in {unit}, {what}, {up.upper()}-up", "pose"


@dataclass
class PointListTally:
    """What became of a point list's rows as they were read: grouped into a time's row (one of
    the ``targets``) or passed over as another target of the job (a reference nest), by name."""

    targets: int = 0
    times: int = 0
    others: dict[str, int] = field(default_factory=dict)

    def __str__(self) -> str:
        others = self.others
        rows = self.targets + sum(others.values())
        text = f"{rows} point-list rows: {self.targets} of the targets, grouped into {self.times} times"
        if others:
            named = ", ".join(f"{count} of {name!r}" for name, count in others.items())
            text += f"; {sum(others.values())} of other targets, not on the platform, passed over ({named})"
        return text


#: how a point list's time column is written: seconds (× time_unit) or ISO 8601 date-times
TIME_FORMATS = ("number", "iso")


def iso_seconds(text: str) -> float:
    """An ISO 8601 date-time (``2026-03-14T09:26:53.589`` or with a space, ``Z`` or an offset) as
    seconds since the Unix epoch; one without a zone is taken as UTC, so that a log's times keep
    their differences whatever the machine's zone.

    Raises:
        ValueError: not an ISO date-time.
    """
    import datetime

    stamp = datetime.datetime.fromisoformat(text.strip())
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=datetime.UTC)
    return stamp.timestamp()


def _is_iso(text: str) -> bool:
    try:
        iso_seconds(text)
    except ValueError:
        return False
    return True


def point_list_blocks(
    path: Path, mapping_path: Path, table: dict, up_default: str = "z", tally: PointListTally | None = None
):
    """A laser tracker's point list (one row per measured target) grouped by time into rows of
    the ``targets`` named in order (``p1 …``), a target not measured at that time left empty;
    ``tally`` counts every row read (:class:`PointListTally`)."""
    tally = tally if tally is not None else PointListTally()
    header = header_of(path)
    section = "instrument"
    time = mapping_value(mapping_path, table, section, "time", None, str)
    target = mapping_value(mapping_path, table, section, "target", None, str)
    targets = mapping_value(mapping_path, table, section, "targets", None, list)
    position = mapping_value(mapping_path, table, section, "position", None, list)
    if None in (time, target, targets, position) or len(position) != 3 or not 1 <= len(targets) <= 3:
        _refuse(
            mapping_path,
            "[instrument] of a point list: expected 'time', 'target' (the column naming the target), "
            "'targets' (1 to 3 names, in the order of p1, p2, p3) and 'position' (3 columns)",
        )
    time_scale = S_PER[mapping_value(mapping_path, table, section, "time_unit", "s", str, tuple(S_PER))]
    iso = mapping_value(mapping_path, table, section, "time_format", "number", str, TIME_FORMATS) == "iso"
    unit = mapping_value(mapping_path, table, section, "position_unit", "mm", str, tuple(MM_PER))
    up = mapping_value(mapping_path, table, section, "up", up_default, str, ("y", "z"))
    time_j, target_j, *xyz = column_indices(path, header, [time, target, *position], "instrument")
    check_distinct(
        mapping_path, [("instrument.time", [time]), ("instrument.target", [target]), ("instrument.position", position)]
    )
    if not all(isinstance(name, str) for name in targets):
        _refuse(mapping_path, f"'instrument.targets': expected target names, got {targets!r}")
    twice = sorted({name for name in targets if targets.count(name) > 1})
    if twice:
        _refuse(mapping_path, f"'instrument.targets': {twice[0]!r} is named twice; expected each target once")
    K = len(targets)

    def block_of(rows: list[tuple[float, np.ndarray, int]]) -> Block:
        t, values, lines = zip(*rows, strict=True)
        return Block(np.array(t), points_columns(np.array(values), up), np.array(lines))

    def blocks():
        import csv

        with _open_text(path) as file:
            reader = csv.reader(file)
            next(reader)
            rows: list[tuple[float, np.ndarray, int]] = []  # (time, p1x … pKz, first line) of each group
            for number, fields in enumerate(reader, start=2):
                if not fields:
                    continue
                try:
                    t = iso_seconds(fields[time_j]) if iso else float(fields[time_j]) * time_scale
                    p = [float(fields[j]) * MM_PER[unit] for j in xyz]
                except (ValueError, IndexError):
                    stamp = fields[time_j] if time_j < len(fields) else ""
                    hint = (
                        f' ({stamp!r} is an ISO date-time: set time_format = "iso" in [instrument])'
                        if not iso and _is_iso(stamp)
                        else ""
                    )
                    what = "an ISO date-time" if iso else "a number"
                    _refuse(
                        path,
                        f"row {number}: expected {what} in column {time!r} and numbers in {', '.join(position)}{hint}",
                    )
                name = fields[target_j].strip()
                if name not in targets:  # another target of the job (a reference nest): not on the platform
                    tally.others[name] = tally.others.get(name, 0) + 1
                    continue
                tally.targets += 1
                if not rows or t != rows[-1][0]:
                    tally.times += 1
                    if rows and t < rows[-1][0]:
                        _refuse(
                            path,
                            f"row {number}: column {time!r}: time goes back ({shown_number(t)} after "
                            f"{shown_number(rows[-1][0])})",
                        )
                    if len(rows) >= POINT_LIST_ROWS:
                        yield block_of(rows)
                        rows = []
                    rows.append((t, np.full(3 * K, np.nan), number))
                k, current = targets.index(name), rows[-1][1]
                if np.isfinite(current[3 * k]):
                    _refuse(path, f"row {number}: target {name!r} measured twice at {time} = {fields[time_j]}")
                current[3 * k : 3 * k + 3] = p
            if rows:
                yield block_of(rows)

    return blocks(), f"point list of {K} target(s) ({', '.join(targets)}) in {unit}, {up.upper()}-up", "points"


# ----------------------------------------------------------------------------- strokes


@dataclass(frozen=True)
class StrokeColumns:
    """How a file's stroke columns become ``q1_mm … q6_mm``: ``q = sign (raw − zero) mm_per_raw``; a
    servo drive's angles (``unit`` deg or rad) ``q1_deg … q6_deg``, ``mm_per_raw`` then degrees per raw
    unit and ``log_unit`` ``"deg"``."""

    time: str | None
    time_scale: float
    columns: list[str]
    mm_per_raw: np.ndarray
    sign: np.ndarray
    zero: np.ndarray
    what: str
    log_unit: str = "mm"
    temperatures: tuple[str, ...] = ()
    celsius_at_zero: float = 0.0
    load: str | None = None
    kg_per_load_unit: float = 1.0

    def convert(self, raw: np.ndarray) -> np.ndarray:
        return self.sign * (raw - self.zero) * self.mm_per_raw

    @property
    def read_columns(self) -> list[str]:
        """The controller's columns a row of it is read from: the six strokes, the payload, then the temperatures."""
        return [*self.columns, *([self.load] if self.load else []), *self.temperatures]

    @property
    def log_columns(self) -> tuple[str, ...]:
        """The log columns of its payload (``load_kg``, spec §10) and its temperatures (``temp1_C …
        temp6_C``, spec §17), each where mapped, in the order of :meth:`convert_row`'s columns after the strokes."""
        return (*(("load_kg",) if self.load else ()), *(TEMPERATURE_COLUMNS if self.temperatures else ()))

    def convert_row(self, raw: np.ndarray) -> np.ndarray:
        """``(n, 6 + l + t)`` raw values of :attr:`read_columns` → ``(n, 6 + len(log_columns))`` the strokes
        in the log's unit, the payload [kg], then each leg's temperature [°C] (one column for all legs
        repeated): the values the import joins to each measurement's time."""
        raw = np.asarray(raw, dtype=float)
        six, loads = len(self.columns), int(bool(self.load))
        celsius = raw[:, six + loads :] + self.celsius_at_zero
        return np.hstack(
            [
                self.convert(raw[:, :six]),
                raw[:, six : six + loads] * self.kg_per_load_unit,
                np.repeat(celsius, 6 // celsius.shape[1], axis=1) if self.temperatures else celsius,
            ]
        )


def stroke_columns(mapping_path: Path, table: dict) -> StrokeColumns:
    """The ``[strokes]`` table of a mapping file."""
    section = "strokes"
    columns = mapping_value(mapping_path, table, section, "columns", None, list)
    if columns is None or len(columns) != 6 or not all(isinstance(c, str) for c in columns):
        _refuse(mapping_path, "'strokes.columns': expected the six stroke column names of legs 1..6")
    unit = mapping_value(mapping_path, table, section, "unit", "mm", str, ("counts", *MM_PER, *DEG_PER))
    if unit == "counts":
        per_mm = table.get("counts_per_mm")
        if per_mm is None:
            lead, per_rev = table.get("mm_per_rev"), table.get("counts_per_rev")
            if lead is None or per_rev is None:
                _refuse(
                    mapping_path,
                    "[strokes] unit = counts: expected 'counts_per_mm', or 'mm_per_rev' with 'counts_per_rev'",
                )
            lead, per_rev = (
                _six(mapping_path, "strokes.mm_per_rev", lead),
                _six(mapping_path, "strokes.counts_per_rev", per_rev),
            )
            mm_per_raw, what = lead / per_rev, "encoder counts × mm_per_rev / counts_per_rev"
        else:
            mm_per_raw, what = (
                1.0 / _six(mapping_path, "strokes.counts_per_mm", per_mm),
                "encoder counts / counts_per_mm",
            )
    elif unit in DEG_PER:
        mm_per_raw, what = np.full(6, DEG_PER[unit]), f"servo angles in {unit}"
    else:
        mm_per_raw, what = np.full(6, MM_PER[unit]), f"strokes in {unit}"
    sign = _six(mapping_path, "strokes.sign", table.get("sign", 1.0))
    if not np.all(np.isin(sign, (-1.0, 1.0))):
        _refuse(mapping_path, "'strokes.sign': expected 1 or -1 per leg")
    zero = _six(mapping_path, "strokes.zero", table.get("zero", 0.0))
    time = mapping_value(mapping_path, table, section, "time", None, str)
    temperatures = mapping_value(mapping_path, table, section, "temperatures", [], list)
    if len(temperatures) not in (0, 1, 6) or not all(isinstance(c, str) for c in temperatures):
        _refuse(
            mapping_path,
            f"'strokes.temperatures': expected the temperature column names of legs 1..6, or one for all legs "
            f"(spec §17), got {temperatures!r}",
        )
    load = mapping_value(mapping_path, table, section, "load_kg", None, str)
    check_distinct(
        mapping_path,
        [
            ("strokes.time", [time] if time else []),
            ("strokes.columns", columns),
            ("strokes.temperatures", temperatures),
            ("strokes.load_kg", [load] if load else []),
        ],
    )
    load_unit = mapping_value(mapping_path, table, section, "load_unit", "kg", str, tuple(KG_PER))
    temperature_unit = mapping_value(mapping_path, table, section, "temperature_unit", "C", str, tuple(CELSIUS_AT_ZERO))
    time_scale = S_PER[mapping_value(mapping_path, table, section, "time_unit", "s", str, tuple(S_PER))]
    log_unit = "deg" if unit in DEG_PER else "mm"
    if temperatures:
        shown = "one for all legs" if len(temperatures) == 1 else "one per leg"
        what += f", temperatures in {_TEMPERATURE_WORDS[temperature_unit]} ({shown})"
    if load:
        what += f", payload {load!r} in {load_unit} (held from the row at or before each measurement)"
    return StrokeColumns(
        time,
        time_scale,
        columns,
        mm_per_raw,
        sign,
        zero,
        what,
        log_unit,
        tuple(temperatures),
        CELSIUS_AT_ZERO[temperature_unit],
        load,
        KG_PER[load_unit],
    )


def _six(path, key: str, value) -> np.ndarray:
    array = np.broadcast_to(np.asarray(value, dtype=float) if _numbers(value) else np.array(np.nan), (6,))
    if (
        array.shape != (6,)
        or not np.all(np.isfinite(array))
        or (key.endswith(("per_mm", "per_rev")) and np.any(array <= 0))
    ):
        _refuse(path, f"'{key}': expected a positive number or six, got {value!r}")
    return np.array(array, dtype=float)


def _numbers(value) -> bool:
    if isinstance(value, bool):
        return False
    if isinstance(value, (int, float)):
        return True
    return (
        isinstance(value, list)
        and len(value) == 6
        and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    )


def check_time_order(path, block: Block, latest: float, what: str = "time") -> float:
    """Refuse a block whose times go back or repeat (a duplicate frame) after ``latest``."""
    t = np.concatenate([[latest], block.t_s])
    finite = np.isfinite(block.t_s)
    if not finite.all():
        k = int(np.flatnonzero(~finite)[0])
        _refuse(path, f"row {block.lines[k]}: {what}: expected a number, got an empty or non-finite value")
    step = np.diff(t)
    if np.any(step <= 0):
        k = int(np.flatnonzero(step <= 0)[0])
        problem = "repeats the row before (a duplicate frame)" if step[k] == 0 else "goes back"
        _refuse(path, f"row {block.lines[k]}: {what} {float(block.t_s[k])!r} {problem}; expected increasing times")
    return float(block.t_s[-1]) if len(block.t_s) else latest


def is_finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
