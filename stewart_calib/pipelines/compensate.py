"""``stewart-calib compensate``: strokes for desired poses from IK with the calibrated model.

Reads a result JSON (spec §5) on its nominal platform — or the calibrated platform file alone
(``calibrate --platform-out``, spec §8) — and a pose list with the log's pose columns (spec §3);
writes the pose columns and ``q1_mm … q6_mm``: the strokes to command so that the calibrated
drive ``nominal + error`` lands at each pose (paper Fig. 3 step 4). A platform with ``[elastic]``
carries its weight and ``--payload-kg M`` (default 0) there: the strokes are those that reach the
poses under that load (spec §10).
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator

import numpy as np

from .. import io
from ..compensation import PoseOutOfRange, compensate
from ..errors import CalibError
from ..io import read_pose_list_blocks
from ..platform import load_platform, payload_refusal
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
    parser.add_argument("--poses", required=True, metavar="poses.csv", help="x_mm y_mm z_mm roll_deg pitch_deg yaw_deg")
    parser.add_argument("--out", required=True, metavar="strokes.csv")
    parser.add_argument(
        "--payload-kg",
        type=float,
        default=0.0,
        metavar="M",
        help="payload [kg] carried at the poses (a platform with [elastic], spec §10; default 0)",
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not (np.isfinite(args.payload_kg) and args.payload_kg >= 0.0):
        raise CalibError(f"--payload-kg: expected a finite payload ≥ 0 kg, got {args.payload_kg!r}")
    platform = load_platform(args.platform)
    if args.payload_kg and platform.elastic is None:
        raise CalibError(
            f"--payload-kg: {args.platform} has no [elastic] (spec §10): a rigid model has no payload to compensate"
        )
    too_heavy = payload_refusal(platform, args.payload_kg)
    if too_heavy:
        raise CalibError(f"--payload-kg: expected {too_heavy}")
    drive = calibrated_model(platform, args.result)  # with its blocks, where the calibration identified them
    strokes = _compensated_blocks(args.poses, drive, platform, args.payload_kg)
    rows = io.write_pose_list_blocks(args.out, strokes, io.STROKE_COLUMNS)
    print(f"wrote {rows} stroke rows to {args.out}")
    return 0


def _compensated_blocks(
    poses_path: str, drive, platform, payload_kg: float = 0.0
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(poses [mm, rad], strokes [mm])`` a block of the pose list at a time. A pose out of range
    is refused once the rest of the list is read, so that a bad row anywhere in it is refused
    first, as when the list was read whole."""
    blocks = read_pose_list_blocks(poses_path)
    done = 0
    for poses in blocks:
        try:
            strokes = compensate(drive, poses, limits=platform, payload_kg=payload_kg)
        except PoseOutOfRange as err:
            for _ in blocks:
                pass
            raise CalibError(f"{poses_path}: row {done + err.pose_index + 2}: {err.reason}") from None
        yield poses, strokes
        done += len(poses)


def main(argv: list[str] | None = None) -> int:
    return run_command("compensate", argv)
