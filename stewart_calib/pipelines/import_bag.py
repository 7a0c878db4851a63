"""``stewart-calib import-bag``: a ROS bag → a measurement log (spec §3, §7).

    stewart-calib import-bag BAG --strokes TOPIC (--readings TOPIC | --pose TOPIC) --out L.csv
                             [--stroke-joints N1,…,N6] [--reading-joints N1,…,N6]
                             [--stroke-unit m|mm|um|rad|deg] [--reading-unit m|mm|um] [--pose-unit m|mm|um]
                             [--clock header|bag] [--max-gap-s S] [--load-kg KG]

Reads ROS 2 bags (sqlite3 or MCAP directory) and ROS 1 ``.bag`` files with the ``rosbags``
library — no ROS installation needed. Drive strokes come from a ``sensor_msgs/JointState``
topic; the measurement either from a second ``JointState`` (the in-situ tracker's six readings,
log columns ``s1_mm … s6_mm``) or from a ``geometry_msgs/PoseStamped`` (a motion-capture pose,
columns ``mx_mm … myaw_deg`` of spec §7).

Time alignment: one log row per measurement message. The strokes are interpolated linearly to
the measurement's stamp between the two stroke messages around it; a measurement with no
stroke message on one side, or whose two neighbours are more than ``--max-gap-s`` apart, gets
no row (the count is reported). The legs are matched by joint name in every message; a message
without one of them is refused alone and counted (a reading gets no row; the strokes are
interpolated across a refused stroke message, within ``--max-gap-s``). ``t_s`` is seconds since
the first written row. ROS messages carry SI units (REP 103: metres), hence the default ``m``;
the unit flags say otherwise. ``--load-kg`` writes the payload the platform carries through the
recording as ``load_kg`` in every row (spec §10).
"""

from __future__ import annotations

import argparse
import csv
import io as text_io
import math
import sys
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from .. import io
from ..errors import CalibError, shown
from ..model.platform import INSTRUMENT_SECTIONS, check_payload_option
from ..model.rotations import quaternion_to_rotation, rotation_to_rpy
from . import run_command

JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
#: millimetres per unit of each ``--*-unit`` choice.
MM_PER_UNIT = {"m": 1000.0, "mm": 1.0, "um": 1e-3}
#: degrees per unit of a servo drive's joint positions (spec §15: the log's ``q1_deg … q6_deg``; ROS: rad)
DEG_PER_UNIT = {"rad": 180.0 / math.pi, "deg": 1.0}
#: default largest time between the two stroke messages a row is interpolated from [s].
DEFAULT_MAX_GAP_S = 0.1
#: the log's columns of the tracker's readings and of a measured pose (spec §3, §7)
READING_COLUMNS = INSTRUMENT_SECTIONS["tracker"].log_columns(0)
MEASURED_POSE_COLUMNS = INSTRUMENT_SECTIONS["pose"].log_columns(0)


@dataclass(frozen=True)
class TopicSeries:
    """The messages of one topic in time order.

    Attributes:
        t_s: ``(N,)`` stamps [s] (ROS time, seconds since the epoch).
        values: ``(N, 6)`` six joint positions (in the bag's unit) or a pose
            ``[x, y, z (bag unit), roll, pitch, yaw [rad]]``.
        refused: messages left out, each ``(message number from 1, cause)``: a JointState without
            one of the legs' joints, or whose names and positions do not pair up.
    """

    t_s: np.ndarray
    values: np.ndarray
    refused: tuple[tuple[int, str], ...] = ()

    def refused_words(self, option: str, topic: str) -> str:
        """``"; 2 --strokes /t message(s) refused (first: message 7: …)"`` or ``""``."""
        if not self.refused:
            return ""
        number, cause = self.refused[0]
        return f"; {len(self.refused)} {option} {topic} message(s) refused (first: message {number}: {cause})"


def interpolate_to_stamps(source: TopicSeries, t_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``source`` to the stamps ``t_s``.

    Returns:
        ``(values (M, 6) at the kept stamps, kept (len(t_s),) bool)``: a stamp is kept when
        stroke messages lie at or before and at or after it, at most ``max_gap_s`` apart.
    """
    t_src = source.t_s
    after = np.searchsorted(t_src, t_s, side="left")  # first source stamp >= t
    exact = (after < len(t_src)) & (t_src[np.minimum(after, len(t_src) - 1)] == t_s)
    before = np.where(exact, after, after - 1)
    inside = (before >= 0) & (after < len(t_src))
    lo, hi = np.clip(before, 0, len(t_src) - 1), np.clip(after, 0, len(t_src) - 1)
    gap = t_src[hi] - t_src[lo]
    kept = inside & (gap <= max_gap_s)
    lo, hi, t = lo[kept], hi[kept], t_s[kept]
    span = t_src[hi] - t_src[lo]
    weight = np.divide(t - t_src[lo], span, out=np.zeros_like(t), where=span > 0)[:, None]
    return source.values[lo] * (1.0 - weight) + source.values[hi] * weight, kept


# ----------------------------------------------------------------------------- reading a bag


@contextmanager
def open_bag(bag: Path):
    """An open ``rosbags`` ``AnyReader`` on ``bag`` (closed on leaving the block).

    Raises:
        CalibError: the path is missing or is not a ROS 1 / ROS 2 bag.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError  # only this command needs rosbags
    from rosbags.typesys import Stores, get_typestore

    if not bag.exists():
        raise CalibError(f"{bag}: bag not found")
    # A ROS 2 bag may carry no message definitions; the standard ones are then Humble's.
    try:
        reader = AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except (AnyReaderError, OSError) as err:
        detail = " ".join(str(err).split()) or err.__class__.__name__
        raise CalibError(
            f"{bag}: cannot read as a ROS bag ({detail}); expected a ROS 1 .bag file or a ROS 2 bag directory"
        ) from None
    try:
        yield reader
    finally:
        reader.close()


def _connections(reader, bag: Path, topic: str, option: str, expected: str):
    topics = reader.topics
    if topic not in topics:
        listing = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(topics.items())) or "none"
        raise CalibError(f"{bag}: {option} {topic}: no such topic; the bag has: {listing}")
    found = topics[topic].msgtype
    if found != expected:
        raise CalibError(f"{bag}: {option} {topic}: the topic carries {found}; expected {expected}")
    return topics[topic].connections


def _stamp_s(msg, bag_time_ns: int, clock: str) -> float:
    if clock == "bag":
        return bag_time_ns * 1e-9
    stamp = msg.header.stamp
    return stamp.sec + stamp.nanosec * 1e-9


def _joint_positions(msg, joints: list[str] | None, legs: int) -> list[float] | str:
    """The ``legs`` legs' positions of a JointState, or why this message has none (its row is refused)."""
    positions = list(msg.position)
    if joints is None:
        if len(positions) != legs:
            return (
                f"expected {legs} joint positions, got {len(positions)} (names {shown(', '.join(msg.name))}); "
                "name the six joints with --stroke-joints / --reading-joints"
            )
        return positions
    names = list(msg.name)
    if len(names) != len(positions):
        return f"{len(names)} joint names but {len(positions)} positions"
    missing = [name for name in joints if name not in names]
    if missing:
        return f"joint(s) {shown(', '.join(missing))} not in the message; it has {shown(', '.join(names))}"
    return [positions[names.index(name)] for name in joints]


def read_topic(
    reader,
    bag: Path,
    topic: str,
    option: str,
    kind: str,
    clock: str,
    joints: list[str] | None = None,
    columns: tuple[str, ...] = (),
) -> TopicSeries:
    """All messages of ``topic`` as a :class:`TopicSeries` in stamp order.

    Args:
        kind: ``JOINT_STATE`` (one position a leg: as many as the log ``columns`` they fill, six) or
            ``POSE_STAMPED`` (position + roll, pitch, yaw).
        clock: ``"header"`` (the message's ``header.stamp``) or ``"bag"`` (the recording time).
    Raises:
        CalibError: a missing topic (listing the bag's topics), another message type (naming
            it), a zero header stamp, non-finite values, no message with the six legs' positions
            (a message without one of them is refused alone and counted in ``refused``).
    """
    from rosbags.highlevel import AnyReaderError

    connections = _connections(reader, bag, topic, option, kind)
    stamps, values, refused = [], [], []
    for k, (connection, bag_time_ns, raw) in enumerate(reader.messages(connections=connections)):
        where = f"{bag}: {option} {topic}: message {k + 1}"
        try:
            msg = reader.deserialize(raw, connection.msgtype)
        except AnyReaderError as err:
            raise CalibError(f"{where}: cannot decode the message ({' '.join(str(err).split())})") from None
        t_s = _stamp_s(msg, bag_time_ns, clock)
        if t_s == 0.0:
            raise CalibError(f"{where}: header.stamp is zero; use --clock bag to take the recording time")
        if kind == JOINT_STATE:
            if joints is None and len(set(msg.name)) == len(msg.position) == len(columns) and all(msg.name):
                # the first message's names fix the legs' order: a later message listing them in
                # another order is matched by name, never taken in its own order
                joints = list(msg.name)
            positions = _joint_positions(msg, joints, len(columns))
            if isinstance(positions, str):
                refused.append((k + 1, positions))
                continue
            row = positions
        else:
            p, q = msg.pose.position, msg.pose.orientation
            row = [p.x, p.y, p.z, q.x, q.y, q.z, q.w]
        if not all(math.isfinite(v) for v in row):
            raise CalibError(f"{where}: expected finite values, got {row}")
        stamps.append(t_s)
        values.append(row)
    if not stamps:
        if refused:
            number, cause = refused[0]
            raise CalibError(
                f"{bag}: {option} {topic}: message {number}: {cause} (every one of its {len(refused)} messages refused)"
            )
        raise CalibError(f"{bag}: {option} {topic}: the topic has no messages")
    order = np.argsort(stamps, kind="stable")
    times, rows = np.array(stamps)[order], np.array(values, dtype=float)[order]
    if kind == POSE_STAMPED:
        if np.any(np.linalg.norm(rows[:, 3:], axis=1) < 1e-9):
            raise CalibError(f"{bag}: {option} {topic}: a pose has a zero quaternion; expected unit quaternions")
        rows = np.hstack([rows[:, :3], rotation_to_rpy(quaternion_to_rotation(rows[:, 3:], "xyzw"))])
    return TopicSeries(times, rows, tuple(refused))


# ----------------------------------------------------------------------------- the log


def log_text(
    t_s: np.ndarray,
    strokes_mm: np.ndarray,
    header: tuple[str, ...],
    measured: np.ndarray,
    drive_columns: tuple[str, ...] = io.STROKE_COLUMNS,
) -> str:
    """The CSV text of a log: ``t_s``, the drive's ``drive_columns`` (``q1_mm … q6_mm``, a servo
    drive's ``q1_deg … q6_deg``), then the measurement columns ``header``."""
    buffer = text_io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["t_s", *drive_columns, *header])
    writer.writerows(np.column_stack([t_s, strokes_mm, measured]).tolist())
    return buffer.getvalue()


def _joint_names(value: str | None, option: str, legs: int) -> list[str] | None:
    if value is None:
        return None
    names = [name.strip() for name in value.split(",")]
    if len(names) != legs or not all(names) or len(set(names)) != legs:
        raise CalibError(f"{option}: expected six distinct joint names separated by commas, got {value!r}")
    return names


def run(args: argparse.Namespace) -> int:
    bag, out = Path(args.bag), Path(args.out)
    if not out.parent.is_dir():
        raise CalibError(f"--out {out}: directory {out.parent} does not exist")
    if not (math.isfinite(args.max_gap_s) and args.max_gap_s > 0):
        raise CalibError(f"--max-gap-s: expected a finite positive number of seconds, got {args.max_gap_s!r}")
    if args.load_kg is not None:
        check_payload_option("--load-kg", args.load_kg)
    if args.readings is not None and args.readings == args.strokes:
        raise CalibError(f"--readings {shown(args.readings)}: the same topic as --strokes; expected the tracker's own")
    stroke_joints = _joint_names(args.stroke_joints, "--stroke-joints", len(io.STROKE_COLUMNS))
    reading_joints = _joint_names(args.reading_joints, "--reading-joints", len(READING_COLUMNS))
    with open_bag(bag) as reader:
        strokes = read_topic(
            reader, bag, args.strokes, "--strokes", JOINT_STATE, args.clock, stroke_joints, io.STROKE_COLUMNS
        )
        if args.readings is not None:
            measured = read_topic(
                reader, bag, args.readings, "--readings", JOINT_STATE, args.clock, reading_joints, READING_COLUMNS
            )
            header = READING_COLUMNS
            values = measured.values * MM_PER_UNIT[args.reading_unit]
        else:
            measured = read_topic(reader, bag, args.pose, "--pose", POSE_STAMPED, args.clock)
            header = MEASURED_POSE_COLUMNS
            values = np.hstack(
                [measured.values[:, :3] * MM_PER_UNIT[args.pose_unit], np.degrees(measured.values[:, 3:])]
            )
    q, kept = interpolate_to_stamps(strokes, measured.t_s, args.max_gap_s)
    if not kept.any():
        raise CalibError(
            f"{bag}: no measurement of {args.readings or args.pose} lies between two {args.strokes} messages at most "
            f"{args.max_gap_s!r} s apart (strokes {strokes.t_s[0]:.3f}–{strokes.t_s[-1]:.3f} s, measurements "
            f"{measured.t_s[0]:.3f}–{measured.t_s[-1]:.3f} s); check --clock or raise --max-gap-s"
        )
    t_s = measured.t_s[kept]
    angles = args.stroke_unit in DEG_PER_UNIT  # a servo drive's joint positions
    strokes_mm = q * (DEG_PER_UNIT if angles else MM_PER_UNIT)[args.stroke_unit]
    measured_values = values[kept]
    for option, array in (("--strokes", strokes_mm), ((args.readings and "--readings") or "--pose", measured_values)):
        if not np.all(np.isfinite(array)):  # finite in the bag, overflowed by the unit's scale
            raise CalibError(f"{bag}: {option}: values that are not finite in mm (overflow of the unit conversion)")
    drive_columns = io.ANGLE_COLUMNS if angles else io.STROKE_COLUMNS
    if args.load_kg is not None:  # one payload through the whole recording
        header = (*header, "load_kg")
        measured_values = np.column_stack([measured_values, np.full(len(t_s), args.load_kg)])
    io.atomic_write_text(out, log_text(t_s - t_s[0], strokes_mm, header, measured_values, drive_columns))
    start = datetime.fromtimestamp(t_s[0], tz=UTC).isoformat(timespec="milliseconds")
    dropped = int((~kept).sum())
    option, topic = ("--readings", args.readings) if args.readings is not None else ("--pose", args.pose)
    messages = len(measured.t_s) + len(measured.refused)
    print(
        f"stewart-calib import-bag: wrote {out} ({int(kept.sum())} rows from t = {start}, of {messages} {option} "
        f"message(s); {dropped} without stroke messages within {args.max_gap_s!r} s dropped"
        f"{measured.refused_words(option, shown(topic))}{strokes.refused_words('--strokes', shown(args.strokes))}"
        f"{'' if args.load_kg is None else f'; payload {args.load_kg:g} kg in every row'})",
        file=sys.stderr,
    )
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "import-bag",
        description="Read drive strokes (JointState) and tracker readings (JointState) or a measured pose "
        "(PoseStamped) from a ROS bag, align them in time and write a measurement log (spec §3, §7).",
    )
    parser.add_argument("bag", metavar="BAG", help="ROS 1 .bag file or ROS 2 bag directory (sqlite3 or MCAP)")
    parser.add_argument(
        "--strokes", required=True, metavar="TOPIC", help="sensor_msgs/JointState topic of the six drive strokes"
    )
    measurement = parser.add_mutually_exclusive_group(required=True)
    measurement.add_argument(
        "--readings", metavar="TOPIC", help="sensor_msgs/JointState topic of the six tracker readings"
    )
    measurement.add_argument(
        "--pose", metavar="TOPIC", help="geometry_msgs/PoseStamped topic of the measured pose (spec §7)"
    )
    parser.add_argument("--out", required=True, metavar="L.csv", help="measurement log to write")
    parser.add_argument(
        "--stroke-joints", metavar="N1,…,N6", help="joint names of legs 1..6 (default: the message's six, in order)"
    )
    parser.add_argument(
        "--reading-joints", metavar="N1,…,N6", help="joint names of tracker legs 1..6 (default: in order)"
    )
    for what in ("stroke", "reading", "pose"):
        angles = ", or rad | deg: a servo drive's angles, written as q1_deg … q6_deg" if what == "stroke" else ""
        parser.add_argument(
            f"--{what}-unit",
            choices=(*MM_PER_UNIT, *DEG_PER_UNIT) if what == "stroke" else tuple(MM_PER_UNIT),
            default="m",
            help=f"unit of the {what} positions in the bag (default m, as ROS{angles})",
        )
    parser.add_argument(
        "--clock",
        choices=("header", "bag"),
        default="header",
        help="stamp of a message: its header.stamp (default) or the bag's recording time",
    )
    parser.add_argument(
        "--max-gap-s",
        type=float,
        default=DEFAULT_MAX_GAP_S,
        metavar="S",
        help=f"largest gap between the stroke messages a row is interpolated across (default {DEFAULT_MAX_GAP_S} s)",
    )
    parser.add_argument(
        "--load-kg",
        type=float,
        metavar="KG",
        help="the payload [kg] the platform carries through the recording, written as load_kg in every row (an "
        "input where the platform has [elastic], spec §10)",
    )
    parser.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    return run_command("import-bag", argv)
