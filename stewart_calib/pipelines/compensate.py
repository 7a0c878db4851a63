"""``stewart-calib compensate``: strokes for desired poses from IK with the calibrated model.

Reads a result JSON (spec §5) on its nominal platform — or the calibrated platform file alone
(``calibrate --platform-out``, spec §8) — and a pose list with the log's pose columns (spec §3);
writes the pose columns and ``q1_mm … q6_mm`` (a rotary drive: ``q1_deg … q6_deg``, spec §15): the
strokes (commanded angles) to command so that the calibrated
drive ``nominal + error`` lands at each pose (paper Fig. 3 step 4). A platform with ``[elastic]``
carries its weight and ``--payload-kg M`` (default 0) there: the strokes are those that reach the
poses under that load (spec §10). A platform with ``[thermal]`` has its legs at ``--temperature-C T``
(all legs; default the reference temperature): the strokes are those that reach the poses with each
leg grown by ``α_i (T − T_ref) L_i`` (spec §17).

``--poses -`` streams (spec §16): poses from standard input, each pose's row (the pose columns and
the strokes) written and flushed as soon as its line has come, to ``--out`` (``-``: standard
output); an unreachable pose gets its row with the stroke fields empty and one line on stderr.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .. import io
from ..analysis.compensation import PoseOutOfRange, compensate
from ..errors import CalibError, shown, without_noise
from ..io import read_pose_list_blocks
from ..io.logs import POSE_COLUMNS
from ..io.platform_file import load_platform
from ..io.tables import header_fields, require_columns
from ..model.platform import TEMPERATURE_RANGE_C, check_payload_option, payload_refusal
from ..samples import LOAD_KG, TEMPERATURE_C, Inputs
from . import run_command
from .handover import calibrated_model


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "compensate",
        description="Compute drive strokes that put the calibrated robot at the desired poses.",
    )
    parser.add_argument(
        "--platform", required=True, metavar="P.toml", help="nominal platform, or the calibrated one alone (spec §8)"
    )
    parser.add_argument(
        "--result", metavar="R.json", help="calibration result (spec §5); omit it with a calibrated platform"
    )
    parser.add_argument(
        "--poses",
        required=True,
        metavar="poses.csv",
        help="x_mm y_mm z_mm roll_deg pitch_deg yaw_deg; '-': read them from standard input and write each pose's"
        " row as soon as it is read",
    )
    parser.add_argument("--out", required=True, metavar="strokes.csv", help="'-': standard output")
    parser.add_argument(
        "--payload-kg",
        type=float,
        default=0.0,
        metavar="M",
        help="payload [kg] carried at the poses (a platform with [elastic], spec §10; default 0)",
    )
    parser.add_argument(
        "--temperature-C",
        dest="temperature_C",
        type=float,
        metavar="T",
        help="every leg's temperature [°C] at the poses (a platform with [thermal], spec §17; default its "
        "reference temperature)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_payload_option("--payload-kg", args.payload_kg)
    platform = load_platform(args.platform)
    if args.payload_kg and platform.elastic is None:
        raise CalibError(
            f"--payload-kg: {args.platform} has no [elastic] (spec §10): a rigid model has no payload to compensate"
        )
    too_heavy = payload_refusal(platform, args.payload_kg)
    if too_heavy:
        raise CalibError(f"--payload-kg: expected {too_heavy}")
    temperature_C = _temperature_C(args, platform)
    drive = calibrated_model(platform, args.result)  # with its blocks, where the calibration identified them
    inputs: dict = {LOAD_KG: args.payload_kg}  # the input channels every pose is commanded at
    if temperature_C is not None:  # one temperature for every leg: the channel's shape, a value per leg
        inputs[TEMPERATURE_C] = np.full(drive.rows, temperature_C)
    if args.poses == "-":
        return _stream(sys.stdin.buffer, "<stdin>", args.out, drive, platform, inputs)
    if args.out == "-":
        try:
            with open(args.poses, "rb") as poses:
                return _stream(poses, args.poses, args.out, drive, platform, inputs)
        except OSError as err:
            raise CalibError(f"{shown(args.poses)}: cannot read the pose list ({err.strerror})") from None
    strokes = _compensated_blocks(args.poses, drive, platform, inputs)
    rows = io.write_pose_list_blocks(args.out, strokes, io.drive_columns(platform))
    print(f"stewart-calib compensate: wrote {rows} stroke rows to {shown(args.out)}")
    return 0


def _temperature_C(args: argparse.Namespace, platform) -> float | None:
    """``--temperature-C`` checked (a platform with ``[thermal]``, a temperature within
    :data:`~stewart_calib.model.platform.TEMPERATURE_RANGE_C`), its reference temperature where the
    option is not given; None for a platform without ``[thermal]``."""
    value = args.temperature_C
    if value is not None:
        low, high = TEMPERATURE_RANGE_C
        if not (np.isfinite(value) and low <= value <= high):
            raise CalibError(f"--temperature-C: expected a temperature within [{low:g}, {high:g}] °C, got {value!r}")
        if platform.thermal is None:
            raise CalibError(
                f"--temperature-C: {args.platform} has no [thermal] (spec §17): a model without the legs' "
                "expansion has no temperature to compensate"
            )
    if platform.thermal is None:
        return None
    return float(platform.thermal.reference_temperature_C if value is None else value)


def _compensated_blocks(poses_path: str, drive, platform, inputs: Inputs) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(poses [mm, rad], strokes in the log's units)`` a block of the pose list at a time (a rotary
    drive's commanded angles in degrees, spec §15). A pose out of range
    is refused once the rest of the list is read, so that a bad row anywhere in it is refused
    first, as when the list was read whole."""
    blocks = read_pose_list_blocks(poses_path)
    done = 0
    for poses in blocks:
        try:
            strokes = compensate(drive, poses, limits=platform, inputs=inputs)
        except PoseOutOfRange as err:
            for _ in blocks:
                pass
            raise CalibError(f"{poses_path}: row {done + err.pose_index + 2}: {err.reason}") from None
        yield poses, io.strokes_in_file_units(strokes, platform)
        done += len(poses)


def _stream(source: BinaryIO, name_text: str, out: str, drive, platform, inputs: Inputs) -> int:
    """``--poses -`` (or ``--out -``): the header, then each pose's row as soon as its line has come,
    flushed (spec §16).

    A row whose pose is unreachable gets its stroke fields empty, a row that is no pose (a field
    that is no finite number) no row; each says why in one line on stderr, and the stream goes on.
    The pose fields are written as read (the shortest text of their double).
    """
    name = Path(name_text)
    header = header_fields(name, _text(source.readline(), name, 1).rstrip("\r\n").lstrip("\ufeff"))
    require_columns(name, header, POSE_COLUMNS)
    index = [header.index(column) for column in POSE_COLUMNS]
    sink = sys.stdout if out == "-" else open(out, "w", encoding="utf-8")  # closed below
    try:
        columns = io.drive_columns(platform)
        print(",".join([*POSE_COLUMNS, *columns]), file=sink, flush=True)
        for row, line in enumerate(iter(source.readline, b""), start=2):
            text = _text(line, name, row).rstrip("\r\n")
            if not text.strip():
                continue
            fields = text.split(",")
            try:
                pose = np.array([_number(fields, k, POSE_COLUMNS[j]) for j, k in enumerate(index)])
            except ValueError as err:
                print(f"stewart-calib compensate: {shown(name)}: row {row}: {err}; no row written", file=sys.stderr)
                continue
            radians = np.r_[pose[:3], np.radians(pose[3:])]
            try:
                commanded = compensate(drive, radians, limits=platform, inputs=inputs)
                strokes = [repr(q) for q in without_noise(io.strokes_in_file_units(commanded, platform)).tolist()]
            except PoseOutOfRange as err:
                print(f"stewart-calib compensate: {shown(name)}: row {row}: {err.reason}", file=sys.stderr)
                strokes = [""] * len(columns)
            print(",".join([*map(repr, without_noise(pose).tolist()), *strokes]), file=sink, flush=True)
    except BrokenPipeError:  # the reader went away: nothing more to say to it
        return 0
    finally:
        if sink is not sys.stdout:
            sink.close()
    return 0


def _text(line: bytes, name: Path, row: int) -> str:
    try:
        return line.decode("utf-8")
    except UnicodeDecodeError:
        raise CalibError(f"{name}: row {row}: not UTF-8 text; expected a CSV row of poses") from None


def _number(fields: list[str], k: int, column: str) -> float:
    try:
        value = float(fields[k]) if k < len(fields) and "_" not in fields[k] else math.nan
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise ValueError(f"column {column}: expected a finite number, got {fields[k] if k < len(fields) else ''!r}")
    return value


def main(argv: list[str] | None = None) -> int:
    return run_command("compensate", argv)
