"""``stewart-calib import``: an instrument's export and a controller's log → a measurement log.

    stewart-calib import (--motive F.csv --rigid-body NAME | --vicon F.csv (--segment NAME | --markers A,B,C)
                          | --csv F.csv | --point-list F.csv) [--mapping M.toml] [--strokes C.csv]
                         [--clock-offset-s S | --estimate-clock-offset] [--max-gap-s S] [--up y|z]
                         [--load-kg KG] [--platform P.toml] --out L.csv

The instrument's export gives the measurement columns of spec §7 (``mx_mm … myaw_deg`` for a
pose, ``p1x_mm …`` for points) on its own clock; the strokes come from the same file (a generic
CSV whose mapping file's ``[strokes]`` names its columns) or from the controller's log
(``--strokes``, described by ``[strokes]``), on another clock: ``t_controller = t_instrument +
offset``, the offset given or estimated (the lag at which the measured motion best explains the
strokes, :func:`estimate_clock_offset`). Strokes are interpolated linearly to each measurement's
time between the two controller rows around it, at most ``--max-gap-s`` apart; a measurement with
no such pair, or where the instrument lost the body, gets no row — and is counted. The payload
(``load_kg``, spec §10) is ``--load-kg`` in every row, or the mapping's ``[strokes] load_kg`` column
held from the controller row at or before each measurement (a payload changes in steps). Both files
are read a block at a time and the log written as it goes (atomically: nothing partial is left).

One line on stderr says what was done: rows read, rows written, rows dropped and why, the units
and conventions assumed. With ``--platform`` the log is also checked for the mistakes of
:mod:`stewart_calib.workflows.diagnosis` before it is written. The formats and the mapping file:
docs/formats.md §12.
"""

from __future__ import annotations

import argparse
import math
import os
import stat
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .. import io
from ..errors import CalibError, number
from ..instruments import MODELS
from ..io import exports
from ..io.exports import Block
from ..io.platform_file import load_platform
from ..model.platform import INSTRUMENT_SECTIONS, check_payload_option, payload_expected, payloads_refused
from ..model.rotations import rpy_to_rotation
from . import run_command

#: default largest time between the two controller rows a measurement is interpolated across [s]
DEFAULT_MAX_GAP_S = 0.1
#: rows of each file the clock offset is estimated from
ESTIMATE_ROWS = 200_000
#: the strokes must follow the measured motion at least this well (R = √R²) at the estimated offset
MIN_CORRELATION = 0.5
#: most points of the common grid the coarse search of the clock offset correlates on
GRID_POINTS = 1 << 21
#: peaks of the coarse search whose offsets are scored by the regression itself
CANDIDATE_PEAKS = 16
#: grid steps either side of a candidate the fit itself is scanned over
REFINE_STEPS = 12
#: candidates whose unexplained part is within this factor of the best's fit as well
AS_GOOD = 1.5
#: instrument rows the fits of the clock offset are evaluated on
FIT_ROWS = 20_000
#: a fit within this fraction of its best is as good (the offsets a held pose cannot tell apart)
FLAT_TOP = 1e-9
#: the least overlap of the two files (a fraction of the shorter) an estimated offset leaves, the
#: first tried first
OVERLAP_FRACTIONS = (0.9, 0.5)
#: a row's position more than this factor from the log's typical size looks like another unit
MIXED_UNITS_FACTOR = 100.0
#: the rows whose median size is the log's typical one
TYPICAL_ROWS = 20


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "import",
        description="Turn an instrument's export (OptiTrack Motive CSV, Vicon Nexus CSV, a laser tracker's point "
        "list, or any CSV described by a mapping file) and the controller's stroke log into a measurement log "
        "(spec §3, §7); formats in docs/formats.md §12.",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--motive", metavar="F.csv", help="OptiTrack Motive CSV export (quaternions)")
    source.add_argument("--vicon", metavar="F.csv", help="Vicon Nexus CSV export (Segments or Trajectories)")
    source.add_argument("--csv", metavar="F.csv", help="a CSV described by the mapping file's [instrument]")
    source.add_argument("--point-list", metavar="F.csv", help="a laser tracker's point list (one row per target)")
    parser.add_argument("--rigid-body", metavar="NAME", help="--motive: the rigid body on the platform")
    parser.add_argument("--segment", metavar="NAME", help="--vicon: the segment on the platform (a pose)")
    parser.add_argument("--markers", metavar="A,B,C", help="--vicon: 1-3 markers on the platform (points)")
    parser.add_argument("--mapping", metavar="M.toml", help="mapping file: [instrument] and/or [strokes]")
    parser.add_argument("--strokes", metavar="C.csv", help="the controller's log of the strokes ([strokes])")
    offset = parser.add_mutually_exclusive_group()
    offset.add_argument("--clock-offset-s", type=float, metavar="S", help="controller clock minus instrument clock [s]")
    offset.add_argument(
        "--estimate-clock-offset", action="store_true", help="estimate the offset from the two files' motion"
    )
    parser.add_argument(
        "--max-gap-s",
        type=float,
        metavar="S",
        help=f"largest gap between controller rows interpolated across (default {DEFAULT_MAX_GAP_S} s)",
    )
    parser.add_argument(
        "--up", choices=("y", "z"), help="the instrument's up axis (default: y for Motive, z otherwise)"
    )
    parser.add_argument(
        "--load-kg",
        type=float,
        metavar="KG",
        help="the payload [kg] the platform carries through the whole import, written as load_kg in every row "
        "(an input where the platform has [elastic], spec §10); or map the controller's column as [strokes] load_kg",
    )
    parser.add_argument("--platform", metavar="P.toml", help="check the log against this platform (spec §2, §7)")
    parser.add_argument("--out", required=True, metavar="L.csv", help="measurement log to write (spec §3, §7)")
    parser.set_defaults(func=run)


def _check_payloads(path, lines: np.ndarray, values: np.ndarray, columns: exports.StrokeColumns, platform) -> None:
    """Refuse a row whose mapped payload (``values``: :meth:`~.exports.StrokeColumns.convert_row`'s, in
    kg) is not one the log reader takes (:func:`~stewart_calib.model.platform.payload_expected`)."""
    if not columns.load:
        return
    load = values[:, len(columns.columns)]
    bad = payloads_refused(platform, load)
    if bad.any():
        k = int(np.argmax(bad))
        raise CalibError(
            f"{path}: row {lines[k]}: column {columns.load!r}: expected {payload_expected(platform, float(load[k]))}"
        )


def _check_seekable(option: str, path: str | None) -> None:
    """Refuse an input that is not a regular file: the header and the rows of an export (and of
    the controller's log) are read in passes, which a pipe, a process substitution
    (``<(cat F.csv)``) or standard input cannot give twice."""
    if path is None:
        return
    if path == "-" and not os.path.exists(path):
        raise CalibError(
            f"{option} -: standard input cannot be read twice; import reads its files in passes: save it to a file"
        )
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return  # not found, unreadable: the reader says which
    if not stat.S_ISREG(mode) and not stat.S_ISDIR(mode):
        raise CalibError(
            f"{path}: not a regular file (a pipe, a process substitution or a device: cannot seek); import reads "
            f"{option}'s file in passes: save it to a file"
        )


def _instrument(args, mapping: dict, mapping_path) -> tuple:
    """``(blocks factory, what, kind, path, tally)`` of the instrument's export; ``tally`` (a point
    list's: how its rows became the log's) or None."""
    if args.motive:
        if not args.rigid_body:
            raise CalibError("--motive: expected --rigid-body NAME (the rigid body on the platform)")
        path, up = Path(args.motive), args.up or "y"
        _, what = exports.motive_blocks(path, args.rigid_body, up)  # reads (and checks) the header now
        return (lambda: exports.motive_blocks(path, args.rigid_body, up)[0]), what, "pose", path, None
    if args.vicon:
        if bool(args.segment) == bool(args.markers):
            raise CalibError("--vicon: expected --segment NAME (a pose) or --markers A,B,C (points)")
        names = [args.segment] if args.segment else [name.strip() for name in args.markers.split(",")]
        path, up = Path(args.vicon), args.up or "z"
        option = "--segment" if args.segment else "--markers"
        _, what, kind = exports.vicon_blocks(path, names, up, option)
        return (lambda: exports.vicon_blocks(path, names, up, option)[0]), what, kind, path, None
    if "instrument" not in mapping:
        option = "--csv" if args.csv else "--point-list"
        raise CalibError(f"{option}: expected --mapping M.toml with an [instrument] table describing its columns")
    table = mapping["instrument"]
    path = Path(args.csv or args.point_list)
    if args.csv:
        checked = args.platform is None  # with a platform, the diagnosis checks the order against the strokes
        _, what, kind = exports.generic_instrument_blocks(path, mapping_path, table, args.up or "z")
        return (
            (
                lambda extra=(): exports.generic_instrument_blocks(
                    path, mapping_path, table, args.up or "z", list(extra), checked
                )[0]
            ),
            what,
            kind,
            path,
            None,
        )
    _, what, kind = exports.point_list_blocks(path, mapping_path, table, args.up or "z")

    def read_again():
        tally.targets, tally.times, tally.others = 0, 0, {}  # the reading the log is written from counts
        return exports.point_list_blocks(path, mapping_path, table, args.up or "z", tally)[0]

    tally = exports.PointListTally()
    return read_again, what, kind, path, tally


#: a --max-gap-s below this many of the controller's row periods is hinted at when rows are dropped
GAP_PERIODS = 1.5


class ControllerLog:
    """The controller's strokes [mm] on its clock, and its payload [kg] and its legs' temperatures [°C]
    where the mapping names them (``[strokes] load_kg``, spec §10, and ``temperatures``, §17), read a
    block at a time and kept only as far back as the next measurement needs (the measurements come in
    time order)."""

    def __init__(self, path: Path, columns: exports.StrokeColumns, platform=None):
        if columns.time is None:
            raise CalibError(f"{path}: the mapping's [strokes] names no 'time' column of the controller's log")
        header = exports.header_of(path)
        indices = exports.column_indices(path, header, [columns.time, *columns.read_columns], "strokes")
        self.path, self.columns, self.platform = path, columns, platform
        self._blocks = exports.numeric_blocks(path, 2, header, indices)
        # the strokes, then the payload and each leg's temperature where the mapping names them
        self.t_s, self.q_mm = np.zeros(0), np.zeros((0, len(columns.columns) + len(columns.log_columns)))
        self.rows, self.first_s, self._latest, self._done = 0, math.nan, -math.inf, False
        self.period_s = math.nan  # the median step of its first block: a --max-gap-s below it joins few rows

    def gap_hint(self, max_gap_s: float) -> str:
        """``"; --max-gap-s 0.1 s is within 1.5× the controller's row period …"`` where it is, else ``""``."""
        enough = round(GAP_PERIODS * self.period_s, 6)  # to the µs: 1.5 × 0.1 in binary floats is one ulp above 0.15
        if not (math.isfinite(self.period_s) and max_gap_s < enough):
            return ""
        return (
            f"; --max-gap-s {max_gap_s:g} s is within {GAP_PERIODS:g}× the controller's row period "
            f"({number(self.period_s)} s), so the two rows around a measurement are often further apart: give "
            f"--max-gap-s {number(enough)} or more"
        )

    def _read(self) -> bool:
        block = next(self._blocks, None)
        if block is None:
            self._done = True
            if not self.rows:
                raise CalibError(f"{self.path}: no data rows after the header; expected the controller's strokes")
            return False
        block.t_s = block.t_s * self.columns.time_scale
        self._latest = exports.check_time_order(self.path, block, self._latest, f"column {self.columns.time!r}")
        if not np.all(np.isfinite(block.values)):
            k, j = np.argwhere(~np.isfinite(block.values))[0]
            raise CalibError(
                f"{self.path}: row {block.lines[k]}: column {self.columns.read_columns[j]!r}: expected a number, "
                "got none"
            )
        if not self.rows:
            self.first_s = float(block.t_s[0])
            if len(block.t_s) > 1:
                self.period_s = float(np.median(np.diff(block.t_s)))
        self.rows += len(block.t_s)
        self.t_s = np.concatenate([self.t_s, block.t_s])
        converted = self.columns.convert_row(block.values)
        _check_payloads(self.path, block.lines, converted, self.columns, self.platform)
        self.q_mm = np.concatenate([self.q_mm, converted])
        return True

    def strokes_at(self, t_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(strokes (M, 6) [mm] then the payload [kg] and the legs' temperatures (M, 6) [°C] where mapped,
        kept (len(t_s),))`` at the controller times ``t_s`` (increasing): the strokes and temperatures
        interpolated, the payload that of the row at or before (it changes in steps: a load put on between
        two rows is not half there)."""
        from .import_bag import TopicSeries, interpolate_to_stamps

        while not self._done and (not len(self.t_s) or self.t_s[-1] < t_s[-1]):
            self._read()
        q, kept = interpolate_to_stamps(TopicSeries(self.t_s, self.q_mm), t_s, max_gap_s)
        if self.columns.load:  # a kept time has a row at or before it
            load = len(self.columns.columns)
            q[:, load] = self.q_mm[np.searchsorted(self.t_s, t_s[kept], side="right") - 1, load]
        keep_from = max(int(np.searchsorted(self.t_s, t_s[-1], side="right")) - 1, 0)
        self.t_s, self.q_mm = self.t_s[keep_from:], self.q_mm[keep_from:]
        return q, kept

    def drain(self) -> float:
        """Read the rest (every row is checked and counted); returns the last time."""
        while self._read():
            self.t_s, self.q_mm = self.t_s[-1:], self.q_mm[-1:]
        return float(self.t_s[-1]) if len(self.t_s) else math.nan


#: the time units a clock may be logged in, by how many of them make a second
TIME_UNITS = {"ms": 1e3, "us": 1e6, "ns": 1e9}


def time_unit_hint(instrument_span_s: float, controller_span_s: float) -> str:
    """``"; the controller's times span 1e+03× the instrument's: …"`` where the two logs of one
    session span times a unit's factor apart (within 2×: a clock read in the wrong unit), else ``""``."""
    if not (instrument_span_s > 0 and controller_span_s > 0):
        return ""
    ratio = controller_span_s / instrument_span_s
    for unit, factor in TIME_UNITS.items():
        if factor / 2 < ratio < 2 * factor:
            return (
                f"; the controller's times span {ratio:.3g}× the instrument's: in {unit}? set "
                f'time_unit = "{unit}" in the mapping\'s [strokes]'
            )
        if factor / 2 < 1 / ratio < 2 * factor:
            return f"; the instrument's times span {1 / ratio:.3g}× the controller's: in {unit}? set its time_unit"
    return ""


def estimate_clock_offset(
    instrument: Iterator[Block], controller: Iterator[Block], stroke_columns, where: str, kind: str, source=None
) -> tuple[float, float]:
    """The offset ``t_controller − t_instrument`` [s] at which the strokes are best explained by
    the measured motion, from the first :data:`ESTIMATE_ROWS` rows of each file; of two fits, the
    one that explains them better:

    * **the pose** — near a pose the strokes are a nearly linear function of the platform's pose,
      so the strokes at ``t + offset`` are regressed on the instrument's coordinates at ``t``
      (positions, and a pose's rotation as the vector part of ``R₀ᵀ R``): the offset maximises the
      variance explained, R². A hexapod's strokes are such a function; their speed is not one of
      the measured position's speed (a rotation moves the strokes and not the position);
    * **the speeds** — the distance the strokes travel over each interval of the instrument's rows
      against the distance the measured position travels (a drive whose strokes follow its path).

    Each is searched coarsely on a common grid (normalised cross-correlations by FFT; the
    controller's motion averaged over each cell of the grid, never point-sampled — a 10 Hz
    controller that holds each pose between 2 Hz camera frames, sampled at the frames, stands
    still) and refined on the instrument's own rows against the controller's strokes interpolated
    at ``t + offset``, continuous in the offset: no grid step remains in the estimate.

    Returns ``(offset_s, R)``. Raises CalibError when neither fit reaches :data:`MIN_CORRELATION`."""
    t_i, x = _gather(instrument, source or where)
    t_c, q = _gather(controller, where)
    t_c, q = t_c * stroke_columns.time_scale, stroke_columns.convert(q)
    seen = np.all(np.isfinite(x), axis=1)
    t_i, x = t_i[seen], _motion_coordinates(x[seen], kind)
    if len(t_i) < 10 or len(t_c) < 10:
        raise CalibError(f"{where}: too few rows to estimate the clock offset; give --clock-offset-s")
    moving = np.std(q, axis=0) > 0
    q = q[:, moving]
    if not moving.any() or not np.any(np.std(x[:, :3], axis=0) > 0):
        raise CalibError(f"{where}: the strokes or the measured positions do not move; give --clock-offset-s")
    step = min(np.median(np.diff(t_i)), np.median(np.diff(t_c)))
    step = max(step, max(t_i[-1] - t_i[0], t_c[-1] - t_c[0]) / GRID_POINTS)
    grid_i, grid_c = np.arange(t_i[0], t_i[-1], step), np.arange(t_c[0], t_c[-1], step)
    if len(grid_i) < 10 or len(grid_c) < 10:
        raise CalibError(f"{where}: too few rows to estimate the clock offset; give --clock-offset-s")
    overlap = _correlate(np.ones(len(grid_c)), np.ones(len(grid_i)))
    # two recordings of one session overlap nearly whole: an offset that leaves most of either
    # unmatched is looked at only if none does (a fit to part of a smooth log can look good)
    for fraction in OVERLAP_FRACTIONS:
        enough = overlap >= fraction * min(len(grid_i), len(grid_c))
        if enough.any():
            offset, correlation = _best_offset(t_i, x, t_c, q, grid_i, grid_c, step, overlap, enough)
            if correlation >= MIN_CORRELATION:
                return offset, correlation
    raise CalibError(
        f"{where}: cannot estimate the clock offset: the strokes follow the measured motion at best with "
        f"R = {correlation:.2f} (expected ≥ {MIN_CORRELATION})"
        + (time_unit_hint(t_i[-1] - t_i[0], t_c[-1] - t_c[0]) or "; give --clock-offset-s")
    )


def _best_offset(t_i, x, t_c, q, grid_i, grid_c, step: float, overlap, enough) -> tuple[float, float]:
    """The better of the pose's and the speeds' fits over the offsets ``enough`` allows (see
    :func:`estimate_clock_offset`): ``(offset_s, R)``."""

    def candidates(explained: np.ndarray) -> np.ndarray:
        # the grid's score only approximates the fit over a partial overlap: its highest peaks are
        # candidates, each scored by the fit itself
        score = np.where(enough, explained / np.maximum(overlap, 1.0) ** 2, -np.inf)
        inner = score[1:-1]
        peaks = np.flatnonzero(np.isfinite(inner) & (inner >= score[:-2]) & (inner >= score[2:])) + 1
        best = peaks[np.argsort(score[peaks])[::-1][:CANDIDATE_PEAKS]] if len(peaks) else np.array([np.argmax(score)])
        return grid_c[0] - grid_i[0] + (best - (len(grid_i) - 1)) * step

    # the pose: whitened coordinates against each leg; a linear fit tells the candidates apart (few
    # coefficients: a wrong offset is not fitted away by them), one with the curvature refines
    z = _whitened(np.column_stack([np.interp(grid_i, t_i, column) for column in x.T]))
    legs = [_standardised(np.interp(grid_c, t_c, column)) for column in q.T]
    explained = np.sum([_correlate(leg, column) ** 2 for leg in legs for column in z.T], axis=0) / len(legs)
    lags = candidates(explained)
    # the fits themselves on at most FIT_ROWS of the instrument's rows, evenly spread (each is
    # evaluated some 200 times)
    every = max(1, math.ceil(len(t_i) / FIT_ROWS))
    t_i, x = t_i[::every], x[::every]

    def r2(offset: float, curved: bool = False) -> float:
        return _explained(t_i, x, t_c, q, offset, curved)

    coarse = _refined_maximum(r2, _most_overlapping(lags, r2, t_i, t_c), step)
    pose_offset = _refined_maximum(lambda lag: r2(lag, True), coarse, step)
    pose_r = math.sqrt(max(r2(pose_offset), 0.0))

    # the speeds: each file's travelled distance, averaged over the grid's cells
    speed_i = _standardised(np.diff(np.interp(np.append(grid_i, grid_i[-1] + step), t_i, _travelled(x[:, :3]))))
    speed_c = _standardised(np.diff(np.interp(np.append(grid_c, grid_c[-1] + step), t_c, _travelled(q))))
    lags = candidates(_correlate(speed_c, speed_i) * np.maximum(overlap, 1.0))

    def speed_r(offset: float) -> float:
        return _speed_correlation(t_i, x[:, :3], t_c, q, offset)

    speed_offset = _refined_maximum(speed_r, _most_overlapping(lags, speed_r, t_i, t_c), step)
    correlation, offset = max((pose_r, pose_offset), (speed_r(speed_offset), speed_offset))
    return float(offset), correlation


def _most_overlapping(lags: np.ndarray, fit, t_i: np.ndarray, t_c: np.ndarray) -> float:
    """Of the candidate offsets, the one leaving the files overlapping longest among those that
    fit about as well as the best (their unexplained part within :data:`AS_GOOD` of the best's): a
    motion that repeats itself (a Lissajous figure, a pose sequence run twice) fits as well one
    period off, over a shorter overlap."""
    unexplained = np.array([1.0 - fit(lag) for lag in lags])
    good = unexplained <= AS_GOOD * np.min(unexplained)
    overlap = np.minimum(t_i[-1] + lags, t_c[-1]) - np.maximum(t_i[0] + lags, t_c[0])
    return float(lags[good][np.argmax(overlap[good])])


def _standardised(x: np.ndarray) -> np.ndarray:
    spread = x.std()
    return (x - x.mean()) / (spread if spread > 0 else 1.0)


def _travelled(x: np.ndarray) -> np.ndarray:
    """The distance travelled up to each row (0 at the first)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(x, axis=0), axis=1))])


def _speed_correlation(t_i: np.ndarray, p: np.ndarray, t_c: np.ndarray, q: np.ndarray, offset: float) -> float:
    """Correlation of the distance the position travels between successive instrument rows with
    the strokes' travel over the same intervals at ``t + offset`` (the strokes' distance travelled,
    interpolated); −inf where fewer than 10 intervals lie inside the controller's span."""
    inside = (t_i + offset >= t_c[0]) & (t_i + offset <= t_c[-1])
    pairs = inside[1:] & inside[:-1]
    if pairs.sum() < 10:
        return -math.inf
    a = np.linalg.norm(np.diff(p, axis=0), axis=1)[pairs]
    b = np.diff(np.interp(t_i + offset, t_c, _travelled(q)))[pairs]
    if not (a.std() > 0 and b.std() > 0):
        return -math.inf
    return float(np.corrcoef(a, b)[0, 1])


def _gather(blocks: Iterator[Block], what) -> tuple[np.ndarray, np.ndarray]:
    t, v, n = [], [], 0
    for block in blocks:
        t.append(block.t_s)
        v.append(block.values)
        n += len(block.t_s)
        if n >= ESTIMATE_ROWS:
            break
    if not n:
        raise CalibError(f"{what}: no data rows after the header; expected rows to estimate the clock offset from")
    return np.concatenate(t), np.concatenate(v)


def _motion_coordinates(values: np.ndarray, kind: str) -> np.ndarray:
    """The instrument's coordinates the strokes are regressed on: a pose's position [mm] and the
    vector part of its rotation relative to the first row's, ``R₀ᵀ R`` (``sin θ`` times the axis:
    linear in small rotations, with no wrap at ±180° as roll-pitch-yaw angles have); points:
    their coordinates [mm]."""
    if kind != "pose":
        return values
    R = rpy_to_rotation(np.radians(values[:, 3:6]))
    M = np.einsum("ji,njk->nik", R[0], R)
    vector = 0.5 * np.column_stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1]])
    return np.column_stack([values[:, :3], vector])


def _whitened(x: np.ndarray) -> np.ndarray:
    """Centred ``x`` in orthonormal coordinates (its principal directions, each of unit variance;
    directions without spread dropped)."""
    centred = x - x.mean(axis=0)
    u, s, _ = np.linalg.svd(centred, full_matrices=False)
    keep = s > 1e-9 * s[0]
    return u[:, keep] * math.sqrt(len(x))


def _explained(
    t_i: np.ndarray, x: np.ndarray, t_c: np.ndarray, q: np.ndarray, offset: float, curved: bool = False
) -> float:
    """R² of the strokes at ``t_i + offset`` (linear interpolation, rows inside the controller's
    span) regressed on ``[1, x]`` (``curved``: and the products of ``x``), averaged over the legs;
    −inf where fewer than 10 rows overlap."""
    inside = (t_i + offset >= t_c[0]) & (t_i + offset <= t_c[-1])
    if inside.sum() < 10:
        return -math.inf
    design = _design(x[inside], curved)
    target = np.column_stack([np.interp(t_i[inside] + offset, t_c, leg) for leg in q.T])
    basis = np.linalg.qr(design)[0]  # an orthonormal basis of the fit's columns (lstsq's SVD: 50× slower)
    residual = target - basis @ (basis.T @ target)
    total = np.sum((target - target.mean(axis=0)) ** 2, axis=0)
    if not np.all(total > 0):
        return -math.inf
    return float(np.mean(1.0 - np.sum(residual**2, axis=0) / total))


def _design(x: np.ndarray, curved: bool) -> np.ndarray:
    """``[1, x]`` or (``curved``) ``[1, x, x_j x_k (j ≤ k)]`` of coordinates ``x`` scaled to unit
    spread: the strokes are a smooth function of the pose, and a linear fit alone leaves its
    curvature (a leg's length over ±10° and ±20 mm of motion), which moves the best offset by
    milliseconds."""
    z = (x - x.mean(axis=0)) / np.where(x.std(axis=0) > 0, x.std(axis=0), 1.0)
    if not curved:
        return np.column_stack([np.ones(len(z)), z])
    j, k = np.triu_indices(z.shape[1])
    return np.column_stack([np.ones(len(z)), z, z[:, j] * z[:, k]])


def _refined_maximum(f, start: float, step: float) -> float:
    """The offset near ``start`` where ``f`` is largest: ``f`` scanned over ±:data:`REFINE_STEPS`
    grid steps at half a step (the grid's score is only near the fit's own peak), the best refined
    by golden section."""
    scan = start + step * np.arange(-REFINE_STEPS, REFINE_STEPS + 0.5, 0.5)
    values = np.array([f(lag) for lag in scan])
    k = int(np.argmax(values))
    flat = values >= values[k] - FLAT_TOP * abs(values[k])
    low, high = k, k
    while low > 0 and flat[low - 1]:
        low -= 1
    while high < len(scan) - 1 and flat[high + 1]:
        high += 1
    if high > low:  # a flat top (a controller holding each pose between the frames): its middle
        return float(scan[low] + scan[high]) / 2.0
    return _golden_maximum(f, float(scan[k]) - step / 2, float(scan[k]) + step / 2)


def _golden_maximum(f, low: float, high: float, iterations: int = 40) -> float:
    """The argument in ``[low, high]`` where ``f`` (one peak) is largest: golden-section search."""
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = low, high
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iterations):
        if fc >= fd:
            b, d, fd = d, c, fc
            c = b - ratio * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + ratio * (b - a)
            fd = f(d)
    return (a + b) / 2.0


def _correlate(b: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``Σ_n b[n + k] a[n]`` for ``k = −(len(a) − 1) … len(b) − 1`` by FFT (scipy.signal's
    ``correlate(b, a, "full")``, whose import alone takes ~2 s)."""
    size = 1 << int(np.ceil(np.log2(len(a) + len(b) - 1)))
    circular = np.fft.irfft(np.fft.rfft(b, size) * np.conj(np.fft.rfft(a, size)), size)
    return np.concatenate([circular[size - (len(a) - 1) :], circular[: len(b)]])


def _check_mixed_units(path, block: Block, typical: list) -> None:
    """Refuse a row whose position is orders of magnitude off the log's typical size (a file
    pasted together from exports in metres and in millimetres)."""
    size = np.linalg.norm(block.values[:, :3], axis=1)
    finite = np.isfinite(size) & (size > 0)
    if not finite.any():
        return
    if not typical:  # the file's first rows set the scale: a later row in another unit stands out
        typical.append(float(np.median(size[finite][:TYPICAL_ROWS])))
    ratio = size[finite] / typical[0]
    odd = (ratio > MIXED_UNITS_FACTOR) | (ratio < 1.0 / MIXED_UNITS_FACTOR)
    if odd.any():
        k = int(np.flatnonzero(finite)[np.argmax(odd)])
        raise CalibError(
            f"{path}: row {block.lines[k]}: a position {size[k]:.4g} mm from the origin where the rows before are "
            f"about {typical[0]:.4g} mm: mixed units? expected one length unit in the whole file"
        )


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if not out.parent.is_dir():
        raise CalibError(f"--out {out}: directory {out.parent} does not exist")
    for option in ("motive", "vicon", "csv", "point_list", "strokes"):
        _check_seekable(f"--{option.replace('_', '-')}", getattr(args, option))
    mapping_path = Path(args.mapping) if args.mapping else None
    mapping = exports.load_mapping(mapping_path) if mapping_path else {}
    make_blocks, what, kind, source, tally = _instrument(args, mapping, mapping_path)
    stroke_table = mapping.get("strokes")
    if stroke_table is None or mapping_path is None:
        raise CalibError("expected --mapping M.toml with a [strokes] table: the stroke columns, their unit and clock")
    strokes = exports.stroke_columns(mapping_path, stroke_table)
    max_gap_s = args.max_gap_s if args.max_gap_s is not None else stroke_table.get("max_gap_s", DEFAULT_MAX_GAP_S)
    if not (exports.is_finite_number(max_gap_s) and max_gap_s > 0):
        raise CalibError(f"--max-gap-s: expected a finite positive number of seconds, got {max_gap_s!r}")
    platform = None
    if args.platform:
        platform = load_platform(args.platform)
        if platform.instrument.kind != kind:
            raise CalibError(
                f"--platform {args.platform}: its [instrument] is '{platform.instrument.kind}'; the import gives "
                f"a {kind} log"
            )
        if platform.drive.coordinate_unit != strokes.log_unit:
            raise CalibError(
                f"{mapping_path}: [strokes] unit gives {strokes.what} where --platform {args.platform}'s [drive] "
                f'(kind = "{platform.drive.kind}") takes {io.drive_columns(platform)[0]} … '
                f"{io.drive_columns(platform)[-1]}; expected a unit in {platform.drive.coordinate_unit}"
            )
    if args.load_kg is not None:
        if strokes.load:
            raise CalibError(
                f"--load-kg: the mapping's [strokes] load_kg = {strokes.load!r} gives the payload already; expected "
                "one of the two"
            )
        check_payload_option("--load-kg", args.load_kg, platform)
    constant_load = ("load_kg",) if args.load_kg is not None else ()
    drive_columns = tuple(f"q{i}_{strokes.log_unit}" for i in range(1, 7))  # spec §3, §15
    notes: list = [what, *([tally] if tally is not None else []), strokes.what]
    if constant_load:
        notes.append(f"payload {args.load_kg:g} kg in every row")
    controller = None
    if args.strokes is None:
        blocks = _same_file_rows(make_blocks, source, strokes, args.csv, notes, platform)
    else:
        offset = _clock_offset(args, stroke_table, make_blocks, strokes, mapping_path, notes, kind, source)
        estimated = args.clock_offset_s is None and (
            args.estimate_clock_offset or stroke_table.get("clock_offset_s") == "estimate"
        )
        controller = ControllerLog(Path(args.strokes), strokes, platform)
        blocks = _joined_rows(make_blocks(), controller, offset, max_gap_s, notes, source, estimated)
    counts = {"read": 0, "lost": 0, "unjoined": 0, "written": 0}
    checked: list = []
    columns: list[str] = []

    def rows():
        typical: list = []
        latest = -math.inf
        for block, q, kept, lost in blocks:
            counts["read"] += len(block.t_s)
            latest = exports.check_time_order(source, block, latest)
            _check_mixed_units(source, block, typical)
            counts["lost"] += int(lost.sum())
            counts["unjoined"] += int((~kept & ~lost).sum())
            use = kept & ~lost
            strokes_mm = np.full((len(block.t_s), len(drive_columns)), np.nan)  # a servo's: degrees
            strokes_mm[kept] = q[:, : len(drive_columns)]
            channels = np.full((len(block.t_s), len(strokes.log_columns)), np.nan)  # the payload, the temperatures
            channels[kept] = q[:, len(drive_columns) :]
            if constant_load:
                channels = np.column_stack([np.full(len(block.t_s), args.load_kg), channels])
            if not columns:
                columns.extend(INSTRUMENT_SECTIONS[kind].log_columns(block.values.shape[1] // 3))
                if platform is not None and kind == "points":
                    _check_target_count(args.platform, block.values.shape[1] // 3, len(platform.instrument.targets))
            if platform is not None and not checked and use.any():
                from ..workflows.diagnosis import diagnose_log

                readings = io.readings_in_code_units(block.values[use], platform)
                inputs = str(source) if args.strokes is None else f"{source} with the strokes of {args.strokes}"
                coordinates = io.strokes_in_code_units(strokes_mm[use], platform)
                diagnose_log(platform, coordinates, readings, inputs, count=False)
                checked.append(True)
            counts["written"] += int(use.sum())
            yield [block.t_s[use], *strokes_mm[use].T, *block.values[use].T, *channels[use].T]
        if not counts["read"]:
            raise CalibError(f"{source}: no data rows after the header; expected the instrument's measurements")
        if not counts["written"]:  # raised inside the write: its temporary file is removed
            hint = controller.gap_hint(max_gap_s) if controller is not None and counts["unjoined"] else ""
            raise CalibError(
                f"{source}: no row could be written ({counts['read']} read, {counts['lost']} without the body, "
                f"{counts['unjoined']} without strokes within {max_gap_s:g} s); nothing written{hint}"
            )

    _write(out, rows, drive_columns, columns, MODELS[kind].unseen_channels, (*constant_load, *strokes.log_columns))
    gap_hint = controller.gap_hint(max_gap_s) if controller is not None and counts["unjoined"] else ""
    print(
        f"stewart-calib import: wrote {out}: {counts['written']} of {counts['read']} rows ({counts['lost']} where the "
        f"instrument lost the body, {counts['unjoined']} without strokes within {max_gap_s:g} s dropped); "
        + "; ".join(map(str, notes))
        + gap_hint,
        file=sys.stderr,
    )
    return 0


def _check_target_count(platform_path, imported: int, targets: int) -> None:
    if imported != targets:
        raise CalibError(
            f"--platform {platform_path}: the import gives {imported} targets (p1 … p{imported}) where its "
            f"[instrument] has {targets} targets_mm; expected one target of the export for each"
        )


def _write(
    out: Path, rows, drive_columns: tuple[str, ...], columns: list[str], unseen: bool, after: tuple[str, ...] = ()
) -> int:
    """Write the rows (blocks of float columns) as a log, the drive's in ``drive_columns`` (``q1_mm …``,
    a servo's ``q1_deg …``), the measured ``columns``, then ``after`` (the payload ``load_kg``, spec §10,
    and the legs' temperatures ``temp1_C … temp6_C``, spec §17, each or none); the header is known once
    the first block is, so the first block is looked at before the file is opened. ``unseen``: the
    instrument may leave a reading's channels unmeasured (NaN, written as empty fields)."""
    blocks = iter(rows())
    first = next(blocks)
    header = ["t_s", *drive_columns, *columns, *after]
    blank = tuple(1 + len(drive_columns) + j for j in range(len(columns))) if unseen else ()

    def all_blocks():
        yield first
        yield from blocks

    return io.write_csv_blocks(out, header, all_blocks(), blank)


def _same_file_rows(make_blocks, source, strokes, is_csv, notes, platform=None):
    """The strokes (and the payload and the legs' temperatures, where mapped) from the instrument's own
    file (a generic CSV, its stroke columns read with the measurement's, after them): every row joins itself."""
    if not is_csv:
        raise CalibError("expected --strokes C.csv: the controller's log of the strokes (this export has none)")
    notes.append("strokes from the same rows")
    read = strokes.read_columns
    for block in make_blocks(read):
        raw = block.values[:, -len(read) :]
        finite = np.isfinite(raw)
        if not finite.all():
            k, j = np.argwhere(~finite)[0]
            raise CalibError(f"{source}: row {block.lines[k]}: column {read[j]!r}: expected a number")
        measured = Block(block.t_s * 1.0, block.values[:, : -len(read)], block.lines)
        lost = ~np.any(np.isfinite(measured.values), axis=1)
        converted = strokes.convert_row(raw)
        _check_payloads(source, block.lines, converted, strokes, platform)
        yield measured, converted, np.ones(len(raw), dtype=bool), lost


def _clock_offset(args, table: dict, make_blocks, strokes, mapping_path, notes, kind: str, source) -> float:
    offset = args.clock_offset_s
    from_file = table.get("clock_offset_s", 0.0)
    if offset is None and not args.estimate_clock_offset and from_file != "estimate":
        if not exports.is_finite_number(from_file):
            raise CalibError(
                f"{mapping_path}: 'strokes.clock_offset_s': expected seconds or \"estimate\", got {from_file!r}"
            )
        offset = float(from_file)
    if offset is None:
        path = Path(args.strokes)
        header = exports.header_of(path)
        indices = exports.column_indices(path, header, [strokes.time, *strokes.columns], "strokes")
        offset, correlation = estimate_clock_offset(
            make_blocks(), exports.numeric_blocks(path, 2, header, indices), strokes, str(path), kind, source
        )
        notes.append(
            f"clock offset estimated {offset:.9g} s (the strokes follow the measured motion: R = {correlation:.4f})"
        )
    elif not math.isfinite(offset):
        raise CalibError(f"--clock-offset-s: expected a finite number of seconds, got {offset!r}")
    else:
        notes.append(f"clock offset {offset:g} s")
    return offset


def _joined_rows(
    instrument: Iterator[Block],
    controller: ControllerLog,
    offset_s: float,
    max_gap_s: float,
    notes,
    source,
    estimated: bool = False,
):
    """``(block, strokes of the kept rows, kept, lost)`` per instrument block, the strokes from the
    controller's log at ``t + offset``; refuses a join with no overlap at all."""
    any_kept = False
    first_t = last_t = math.nan
    for block in instrument:
        lost = ~np.any(np.isfinite(block.values), axis=1)
        if not len(block.t_s):
            continue
        first_t = block.t_s[0] if math.isnan(first_t) else first_t
        last_t = block.t_s[-1]
        if np.any(np.diff(block.t_s) <= 0):
            yield block, np.zeros((0, 6)), np.zeros(len(block.t_s), dtype=bool), lost  # refused by check_time_order
            return
        q, kept = controller.strokes_at(block.t_s + offset_s, max_gap_s)
        any_kept = any_kept or bool((kept & ~lost).any())
        yield block, q, kept, lost
    if math.isnan(first_t):
        raise CalibError(f"{source}: no data rows after the header; expected the instrument's measurements")
    controller_last = controller.drain()
    if not any_kept:
        hint = time_unit_hint(last_t - first_t, controller_last - controller.first_s)
        if not hint:
            hint = (
                "; the estimated offset lines up no rows: give --clock-offset-s"
                if estimated
                else "; give the clock offset (--clock-offset-s or --estimate-clock-offset)"
            )
        raise CalibError(
            f"{controller.path}: no measurement falls between two controller rows at most {max_gap_s:g} s apart: "
            f"instrument {first_t:.6g}–{last_t:.6g} s + offset {offset_s:g} s against controller "
            f"{controller.first_s:.6g}–{controller_last:.6g} s{hint}"
        )
    notes.append(f"{controller.rows} controller rows")


def main(argv: list[str] | None = None) -> int:
    return run_command("import", argv)
