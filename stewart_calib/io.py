"""Files at the edge: measurement logs, truth files, calibration results, traces (spec §3–§6).

Files hold mm and degrees; the arrays returned hold mm and rad. Every refusal is a
:class:`~stewart_calib.errors.CalibError` with one line naming the file, the row (its
1-based line number in the file; the header is line 1) and the column or key, and what
was expected. Every writer goes through :func:`atomic_write_text`, so a failed write
never leaves a partial file behind.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import CalibError
from .estimators.base import Estimate
from .platform import N_PARAMS, PARAMETER_NAMES, LegGeometry, Platform
from .samples import Log, Sample

STROKE_COLUMNS = tuple(f"q{i}_mm" for i in range(1, 7))
READING_COLUMNS = tuple(f"s{i}_mm" for i in range(1, 7))
LOG_REQUIRED = ("t_s", *STROKE_COLUMNS, *READING_COLUMNS)
POSE_COLUMNS = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
TRUE_POSE_COLUMNS = tuple(f"true_{name}" for name in POSE_COLUMNS)
RESULT_FORMAT = "stewart-calib/result@1"

#: |estimate − (nominal + error)| a result file may show before it is refused [mm]: JSON
#: writers that round to the nanometre still pass.
RESULT_SUM_TOLERANCE_MM = 1e-6

# ----------------------------------------------------------------------------- writing


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path in ``path``'s directory for the block to write; renamed onto ``path``
    (``os.replace``) when the block succeeds and removed when it fails, so readers see the old
    file or the whole new one, never a partial one.

    Raises:
        CalibError: the file cannot be written (nothing is left behind).
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise CalibError(f"{path}: cannot write ({err.strerror or err.__class__.__name__})") from None
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; an output file should not be
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise CalibError(f"{path}: cannot write ({err.strerror or err.__class__.__name__})") from None
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8", newline="")


def _csv_text(header: list[str], columns: list) -> str:
    """CSV text of equal-length columns; floats are written with ``repr`` (round-trip exact)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    writer.writerows(zip(*(c.tolist() if isinstance(c, np.ndarray) else c for c in columns)))
    return buffer.getvalue()


def _pose_columns_deg(poses: np.ndarray) -> list[np.ndarray]:
    """``(N, 6)`` poses [mm, rad] → six file columns [mm, deg]."""
    poses = np.asarray(poses, dtype=float)
    return [poses[:, 0], poses[:, 1], poses[:, 2], *np.degrees(poses[:, 3:]).T]


def write_log(path: str | Path, log: Log) -> None:
    """Write a measurement log (spec §3): ``t_s``, q, s, then pose [mm, deg], ``stage``, ``load_kg`` if present."""
    header = list(LOG_REQUIRED)
    columns = [log.t_s, *np.asarray(log.strokes).T, *np.asarray(log.readings).T]
    if log.desired_poses is not None:
        header += POSE_COLUMNS
        columns += _pose_columns_deg(log.desired_poses)
    if log.stages is not None:
        header.append("stage")
        columns.append(list(log.stages))
    if log.load_kg is not None:
        header.append("load_kg")
        columns.append(np.asarray(log.load_kg, dtype=float))
    atomic_write_text(path, _csv_text(header, columns))


# ----------------------------------------------------------------------------- reading CSV


def _read_text(path: Path, what: str) -> str:
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CalibError(f"{path}: {what} not found") from None
    except OSError as err:
        raise CalibError(f"{path}: cannot read {what} ({err.strerror or err.__class__.__name__})") from None
    try:
        text = data.decode("utf-8-sig")  # a byte-order mark is what spreadsheet exports add
    except UnicodeDecodeError as err:
        raise CalibError(
            f"{path}: {what} is not UTF-8 text (byte 0x{data[err.start]:02x} at offset {err.start}); expected a UTF-8 CSV file"
        ) from None
    return text.replace("\r\n", "\n")


@dataclass
class _Table:
    """Parsed CSV body: numeric columns as float arrays (NaN where unparsable), text columns
    as lists, the file line of each row, and the first problem found in each bad row."""

    numbers: dict[str, np.ndarray]
    texts: dict[str, list[str]]
    lines: np.ndarray
    issues: dict[int, str]

    def __len__(self) -> int:
        return len(self.lines)

    def flag(self, bad: np.ndarray, describe) -> None:
        """Record ``describe(k)`` for every row ``k`` in the mask that has no problem yet."""
        for k in np.flatnonzero(bad):
            self.issues.setdefault(int(k), describe(int(k)))


def _header(path: Path, text: str) -> list[str]:
    if not text.strip():
        raise CalibError(f"{path}: empty file, no sample rows; expected a header row and at least one sample row")
    first = text.split("\n", 1)[0]
    try:
        header = [name.strip() for name in next(csv.reader([first]), [])]
    except csv.Error as err:  # e.g. a lone carriage return
        raise CalibError(f"{path}: row 1: expected a CSV header row ({err})") from None
    seen = set()
    for name in header:
        if name and name in seen:
            raise CalibError(f"{path}: row 1: column '{name}' appears twice; expected unique column names")
        seen.add(name)
    return header


def _require_columns(path: Path, header: list[str], required) -> None:
    missing = [name for name in required if name not in header]
    if missing:
        raise CalibError(f"{path}: row 1: missing required column(s) {', '.join(missing)}")


def _optional_group(path: Path, header: list[str], group) -> bool:
    """True when all of ``group`` is present, False when none; a partial set is refused."""
    present = [name for name in group if name in header]
    if present and len(present) < len(group):
        missing = [name for name in group if name not in header]
        raise CalibError(
            f"{path}: row 1: columns {', '.join(group)} come all six or none; missing {', '.join(missing)}"
        )
    return bool(present)


def _parse_fast(header: list[str], text: str, numeric: list[str], textual: list[str]) -> _Table | None:
    """The common case in C speed: no quoting, no blank lines, every field a number.

    Returns None when the file needs the careful path (which also finds the bad row).
    """
    if '"' in text:
        return None
    rows = text.split("\n")[1:]
    while rows and rows[-1] == "":
        rows.pop()
    commas = len(header) - 1
    if not rows or any(row.count(",") != commas for row in rows):
        return None
    index = {name: i for i, name in enumerate(header)}
    try:
        values = np.loadtxt(
            rows, delimiter=",", usecols=[index[name] for name in numeric], comments=None, ndmin=2, dtype=float
        )
    except ValueError:
        return None
    numbers = {name: values[:, j] for j, name in enumerate(numeric)}
    texts = {
        name: [v.strip() for v in np.loadtxt(rows, delimiter=",", usecols=[index[name]], comments=None, ndmin=1, dtype=str)]
        for name in textual
    }
    return _Table(numbers, texts, np.arange(2, len(rows) + 2), {})


def _floats(texts: tuple[str, ...], column: str, issues: dict[int, str], blank_is_nan: bool) -> np.ndarray:
    try:
        return np.array(texts, dtype=float)
    except ValueError:
        pass  # find the offending rows one by one below
    out = np.full(len(texts), np.nan)
    for k, text in enumerate(texts):
        try:
            out[k] = float(text)
        except ValueError:
            if not text.strip():
                if not blank_is_nan:
                    issues.setdefault(k, f"column '{column}': expected a number, got an empty field")
            else:
                issues.setdefault(k, f"column '{column}': expected a number, got {text!r}")
    return out


def _parse_careful(header: list[str], text: str, numeric: list[str], textual: list[str], blank_is_nan) -> _Table:
    """Row by row with the csv module: quoting, blank lines, wrong field counts, bad numbers."""
    reader = csv.reader(io.StringIO(text))
    next(reader, None)
    rows, lines, issues = [], [], {}
    width = len(header)
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as err:  # e.g. a lone carriage return inside a row; the reader goes on with the next line
            issues[len(rows)] = f"expected a CSV row ({err})"
            row = [""] * width
        if len(row) <= 1 and not (row and row[0].strip()):
            continue  # a blank line holds no sample
        if len(row) != width:
            issues[len(rows)] = f"expected {width} fields as in the header, got {len(row)}"
            row = [""] * width
        rows.append(row)
        lines.append(reader.line_num)
    columns = list(zip(*rows)) if rows else [()] * width
    index = {name: i for i, name in enumerate(header)}
    numbers = {name: _floats(columns[index[name]], name, issues, name in blank_is_nan) for name in numeric}
    texts = {name: [field.strip() for field in columns[index[name]]] for name in textual}
    return _Table(numbers, texts, np.array(lines, dtype=int), issues)


def _parse(path: Path, header: list[str], text: str, numeric, textual=(), blank_is_nan=()) -> _Table:
    numeric, textual = list(numeric), list(textual)
    table = _parse_fast(header, text, numeric, textual) or _parse_careful(header, text, numeric, textual, set(blank_is_nan))
    if len(table) == 0:
        raise CalibError(f"{path}: no sample rows; expected a header row and at least one sample row")
    return table


def _flag_non_finite(table: _Table, columns) -> None:
    for name in columns:
        values = table.numbers[name]
        table.flag(~np.isfinite(values), lambda k: f"column '{name}': expected a finite number, got {float(values[k])!r}")


def _flag_out_of_range(table: _Table, columns, bounds, what: str, key: str) -> None:
    if bounds is None:
        return
    lo, hi = bounds
    for name in columns:
        values = table.numbers[name]
        table.flag(
            (values < lo) | (values > hi),
            lambda k: f"column '{name}': expected a {what} within [{lo!r}, {hi!r}] mm ({key}), got {float(values[k])!r}",
        )


def _flag_time_backwards(table: _Table) -> None:
    """Flag rows whose t_s is below an earlier good row's (running max, so one glitch row is one skip)."""
    t = table.numbers["t_s"]
    good = np.ones(len(t), dtype=bool)
    good[list(table.issues)] = False
    latest = np.maximum.accumulate(np.r_[-np.inf, np.where(good, t, -np.inf)[:-1]])
    table.flag(good & (t < latest), lambda k: _time_backwards(float(t[k]), float(latest[k])))


def _time_backwards(t_s: float, latest_s: float) -> str:
    return f"column 't_s': expected time non-decreasing, got {t_s!r} after {latest_s!r}"


def _refuse_first(path: Path, table: _Table) -> None:
    if table.issues:
        k = min(table.issues)
        raise CalibError(f"{path}: row {table.lines[k]}: {table.issues[k]}")


def _log_columns(path: Path, header: list[str]) -> tuple[bool, list[str], list[str]]:
    """``(has_pose, numeric columns, text columns)`` of a log header (spec §3)."""
    _require_columns(path, header, LOG_REQUIRED)
    has_pose = _optional_group(path, header, POSE_COLUMNS)
    numeric = [*LOG_REQUIRED, *(POSE_COLUMNS if has_pose else ()), *(["load_kg"] if "load_kg" in header else [])]
    return has_pose, numeric, ["stage"] if "stage" in header else []


def _flag_log_values(table: _Table, platform: Platform | None, has_pose: bool) -> None:
    """Non-finite required values and readings or strokes outside the platform's ranges."""
    _flag_non_finite(table, [*LOG_REQUIRED, *(POSE_COLUMNS if has_pose else ())])
    if platform is not None:
        _flag_out_of_range(table, STROKE_COLUMNS, platform.stroke_range, "stroke", "drive.stroke_range_mm")
        _flag_out_of_range(table, READING_COLUMNS, platform.reading_range, "reading", "tracker.reading_range_mm")


def read_log(path: str | Path, platform: Platform | None = None, skip_bad_rows: bool = False) -> Log:
    """Read a measurement log (spec §3) into a :class:`Log` [mm, rad].

    A bad sample row — wrong number of fields, a missing, non-numeric or non-finite value,
    a stroke outside ``platform.stroke_range`` or a reading outside ``platform.reading_range``
    (inclusive, when the platform gives them), or ``t_s`` going backwards — refuses the file,
    or with ``skip_bad_rows`` is dropped and recorded in ``Log.skipped`` as ``(row, reason)``.

    Raises:
        CalibError: the file is missing, unreadable or not UTF-8; a required column is
            missing or the pose columns are partial; there are no sample rows; a bad row
            (unless skipped); every row is bad.
    """
    path = Path(path)
    text = _read_text(path, "log file")
    header = _header(path, text)
    has_pose, numeric, textual = _log_columns(path, header)
    table = _parse(path, header, text, numeric, textual, blank_is_nan=("load_kg",))  # payload may be unknown
    _flag_log_values(table, platform, has_pose)
    _flag_time_backwards(table)
    if not skip_bad_rows:
        _refuse_first(path, table)
    skipped = [(int(table.lines[k]), table.issues[k]) for k in sorted(table.issues)]
    if len(skipped) == len(table):
        raise CalibError(f"{path}: all {len(table)} sample rows are bad (first: row {skipped[0][0]}: {skipped[0][1]})")
    keep = np.ones(len(table), dtype=bool)
    keep[list(table.issues)] = False
    col = lambda names: np.column_stack([table.numbers[name][keep] for name in names])  # noqa: E731
    poses = None
    if has_pose:
        poses = col(POSE_COLUMNS)
        poses[:, 3:] = np.radians(poses[:, 3:])
    return Log(
        t_s=table.numbers["t_s"][keep],
        strokes=col(STROKE_COLUMNS),
        readings=col(READING_COLUMNS),
        desired_poses=poses,
        stages=[s for s, k in zip(table.texts["stage"], keep) if k] if textual else None,
        load_kg=table.numbers["load_kg"][keep] if "load_kg" in header else None,
        skipped=skipped,
    )


class LogRowParser:
    """Spec §3 rows one at a time, for a log that is still being written (``track``).

    Each row gets exactly :func:`read_log`'s checks and messages (it is parsed as a one-row
    table by the same code); time must not go back from the last good row. A quoted field
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
        self._header = _header(self._path, self._header_line)
        self._has_pose, self._numeric, self._textual = _log_columns(self._path, self._header)
        self._platform = platform
        self._last_t_s = -math.inf

    def parse(self, line: str, row: int) -> Sample | None:
        """The sample of one row (``row``: its 1-based line number), or None for a blank line.

        Raises:
            CalibError: ``"<source>: row <row>: column '<name>': expected ..."`` for a bad row;
                the parser's state is unchanged, so the caller may skip the row and go on.
        """
        line = line.rstrip("\r\n")
        if not line.strip():
            return None
        table = _parse_careful(self._header, f"{self._header_line}\n{line}", self._numeric, self._textual, {"load_kg"})
        table.lines = np.array([row])
        _flag_log_values(table, self._platform, self._has_pose)
        t_s = float(table.numbers["t_s"][0])
        if not table.issues and t_s < self._last_t_s:
            table.issues[0] = _time_backwards(t_s, self._last_t_s)
        _refuse_first(self._path, table)
        self._last_t_s = t_s
        number = lambda name: float(table.numbers[name][0])  # noqa: E731
        pose = None
        if self._has_pose:
            pose = np.array([number(name) for name in POSE_COLUMNS])
            pose[3:] = np.radians(pose[3:])
        return Sample(
            t_s,
            np.array([number(name) for name in STROKE_COLUMNS]),
            np.array([number(name) for name in READING_COLUMNS]),
            pose,
            table.texts["stage"][0] if self._textual else "",
            number("load_kg") if "load_kg" in self._numeric else None,
        )


# ----------------------------------------------------------------------------- truth


def write_pose_list(
    path: str | Path, poses: np.ndarray, dwell_s: float | None = 1.0, columns: dict[str, np.ndarray] | None = None
) -> None:
    """Write the six pose columns [mm, deg] (atomically), after ``t_s`` (one pose per ``dwell_s``
    seconds) unless ``dwell_s`` is None, and before any extra ``columns`` (e.g. strokes).

    Raises:
        CalibError: a ``dwell_s`` that is not a finite positive number (times must increase).
    """
    if dwell_s is not None and not (math.isfinite(dwell_s) and dwell_s > 0):
        raise CalibError(f"dwell time: expected a finite positive number of seconds, got {dwell_s!r}")
    columns = columns or {}
    head = [] if dwell_s is None else ["t_s"]
    lead = [] if dwell_s is None else [np.arange(len(poses)) * dwell_s]
    atomic_write_text(
        path, _csv_text([*head, *POSE_COLUMNS, *columns], [*lead, *_pose_columns_deg(poses), *columns.values()])
    )


def read_pose_list(path: str | Path) -> np.ndarray:
    """The six pose columns of a pose list or a measurement log, ``(N, 6)`` [mm, rad].

    Raises:
        CalibError: missing file or columns, no rows, or a non-finite pose value (naming the row).
    """
    path = Path(path)
    text = _read_text(path, "pose list")
    header = _header(path, text)
    _require_columns(path, header, POSE_COLUMNS)
    table = _parse(path, header, text, POSE_COLUMNS)
    _flag_non_finite(table, POSE_COLUMNS)
    _refuse_first(path, table)
    poses = np.column_stack([table.numbers[name] for name in POSE_COLUMNS])
    poses[:, 3:] = np.radians(poses[:, 3:])
    return poses


@dataclass(frozen=True)
class Truth:
    """The simulator's truth for a log, row for row (spec §4).

    Attributes:
        t_s: ``(N,)`` [s].
        params: ``(N, 42)`` true absolute drive parameters [mm], paper order.
        true_poses: ``(N, 6)`` true pose ``[mm, rad]``, or None.
    """

    t_s: np.ndarray
    params: np.ndarray
    true_poses: np.ndarray | None = None


def write_truth(path: str | Path, truth: Truth) -> None:
    """Write a truth file (spec §4): ``t_s``, the 42 parameters [mm], the true pose [mm, deg] if present."""
    header = ["t_s", *PARAMETER_NAMES]
    columns = [truth.t_s, *np.asarray(truth.params, dtype=float).T]
    if truth.true_poses is not None:
        header += TRUE_POSE_COLUMNS
        columns += _pose_columns_deg(truth.true_poses)
    atomic_write_text(path, _csv_text(header, columns))


def read_truth(path: str | Path) -> Truth:
    """Read a truth file (spec §4).

    Raises:
        CalibError: as for logs — missing file or column, no rows, a bad value (never skipped).
    """
    path = Path(path)
    text = _read_text(path, "truth file")
    header = _header(path, text)
    required = ("t_s", *PARAMETER_NAMES)
    _require_columns(path, header, required)
    has_pose = _optional_group(path, header, TRUE_POSE_COLUMNS)
    numeric = [*required, *(TRUE_POSE_COLUMNS if has_pose else ())]
    table = _parse(path, header, text, numeric)
    _flag_non_finite(table, numeric)
    _refuse_first(path, table)
    poses = None
    if has_pose:
        poses = np.column_stack([table.numbers[name] for name in TRUE_POSE_COLUMNS])
        poses[:, 3:] = np.radians(poses[:, 3:])
    params = np.column_stack([table.numbers[name] for name in PARAMETER_NAMES])
    return Truth(table.numbers["t_s"], params, poses)


# ----------------------------------------------------------------------------- traces


def trace_text(t_s: np.ndarray, params: np.ndarray) -> str:
    """Trace CSV (spec §6): ``t_s`` plus the 42 estimated absolute parameters [mm] per sample."""
    t_s = np.asarray(t_s, dtype=float)
    params = np.asarray(params, dtype=float)
    if t_s.ndim != 1 or params.shape != (len(t_s), N_PARAMS):
        raise ValueError(f"trace needs t_s (N,) and params (N, {N_PARAMS}), got {t_s.shape} and {params.shape}")
    return _csv_text(["t_s", *PARAMETER_NAMES], [t_s, *params.T])


def write_trace(path: str | Path, t_s: np.ndarray, params: np.ndarray) -> None:
    """Write a trace CSV (spec §6); see :func:`trace_text`."""
    atomic_write_text(path, trace_text(t_s, params))


# ----------------------------------------------------------------------------- results


def result_dict(estimate: Estimate, platform: Platform, samples_skipped: int = 0, extra: dict | None = None) -> dict:
    """The spec §5 result of ``estimate`` on ``platform`` (``estimate = nominal + error`` [mm]).

    ``extra`` adds optional fields; it may not replace the spec's.
    """
    nominal = platform.drive.as_vector()
    error = np.asarray(estimate.error, dtype=float)
    stddev = estimate.stddev
    result = {
        "format": RESULT_FORMAT,
        "method": estimate.method,
        "platform": platform.name,
        "parameter_names": list(PARAMETER_NAMES),
        "nominal": nominal.tolist(),
        "estimate": (nominal + error).tolist(),
        "error": error.tolist(),
        "stddev": None if stddev is None else stddev.tolist(),
        "samples_used": int(estimate.samples_used),
        "samples_skipped": int(samples_skipped),
    }
    clash = set(extra or {}) & set(result)
    if clash:
        raise ValueError(f"extra result fields may not replace spec fields: {', '.join(sorted(clash))}")
    return {**result, **(extra or {})}


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def validate_result(result, source: str) -> None:
    """Check a result against spec §5.

    Raises:
        CalibError: ``source`` and the offending key, with what was expected.
    """
    refuse = lambda key, expected: CalibError(f"{source}: key '{key}': expected {expected}")  # noqa: E731
    if not isinstance(result, dict):
        raise CalibError(f"{source}: expected a JSON object (spec §5 result)")
    missing = [key for key in ("format", "method", "platform", "parameter_names", "nominal", "estimate", "error",
                               "stddev", "samples_used", "samples_skipped") if key not in result]
    if missing:
        raise refuse(missing[0], "a value (missing)")
    if result["format"] != RESULT_FORMAT:
        raise refuse("format", f"{RESULT_FORMAT!r}, got {result['format']!r}")
    for key in ("method", "platform"):
        if not isinstance(result[key], str) or not result[key]:
            raise refuse(key, "a non-empty string")
    if result["parameter_names"] != list(PARAMETER_NAMES):
        raise refuse("parameter_names", f"the {N_PARAMS} names j1x ... l6 in the paper's order")
    for key in ("nominal", "estimate", "error", "stddev"):
        value = result[key]
        if key == "stddev" and value is None:
            continue
        if not isinstance(value, list) or len(value) != N_PARAMS or not all(_is_number(v) for v in value):
            raise refuse(key, f"a list of {N_PARAMS} finite numbers" + (" or null" if key == "stddev" else ""))
    if result["stddev"] is not None and min(result["stddev"]) < 0:
        raise refuse("stddev", "non-negative numbers")
    for key in ("samples_used", "samples_skipped"):
        value = result[key]
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise refuse(key, f"a non-negative whole number, got {value!r}")
    gap = np.abs(np.array(result["estimate"]) - np.array(result["nominal"]) - np.array(result["error"]))
    if gap.max() > RESULT_SUM_TOLERANCE_MM:
        i = int(gap.argmax())
        raise refuse("estimate", f"nominal + error; {PARAMETER_NAMES[i]} differs by {gap[i]:.3g} mm")


def result_text(result: dict, source: str) -> str:
    """The JSON text of a validated result (see :func:`validate_result`)."""
    validate_result(result, source)
    return json.dumps(result, indent=2) + "\n"


def write_result(path: str | Path, result: dict) -> None:
    """Validate and write a result JSON (spec §5) atomically; a bad result writes nothing."""
    atomic_write_text(path, result_text(result, str(path)))


def read_result(path: str | Path) -> dict:
    """Read and validate a result JSON (spec §5); returns the parsed object.

    Raises:
        CalibError: unreadable or not JSON; a wrong format, length or non-finite number, naming the key.
    """
    path = Path(path)
    text = _read_text(path, "result file")
    try:
        result = json.loads(text)
    except json.JSONDecodeError as err:
        raise CalibError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    validate_result(result, str(path))
    return result


#: |result nominal − platform nominal| above which a result belongs to another platform [mm].
NOMINAL_TOLERANCE_MM = 1e-6


def read_calibrated_drive(path: str | Path, platform: Platform) -> LegGeometry:
    """The drive ``nominal + error`` of a result JSON (spec §5) made for ``platform``.

    Raises:
        CalibError: an invalid result, or one whose ``nominal`` is not ``platform``'s drive.
    """
    result = read_result(path)
    gap = float(np.max(np.abs(np.array(result["nominal"]) - platform.drive.as_vector())))
    if gap > NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{path}: key 'nominal': expected the nominal drive of platform '{platform.name}'; "
            f"it differs by {gap:.3g} mm (a result for another platform?)"
        )
    return platform.drive.perturbed(np.array(result["error"]))
