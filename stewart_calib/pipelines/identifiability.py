"""``stewart-calib identifiability``: is a pose set (a log's or a planned list) good enough?

Prints :meth:`~stewart_calib.identifiability.IdentifiabilityReport.format_text`; ``--json``
writes :meth:`~stewart_calib.identifiability.IdentifiabilityReport.to_dict`.
"""

from __future__ import annotations

import argparse
import json

from . import run_command
from .. import io
from ..errors import CalibError
from ..config import load_estimator_config
from ..identifiability import identifiability_report, measured_poses, warning_line
from ..platform import Platform, load_platform
from ..io import read_pose_list
from .plan import add_platform_and_noise_arguments


def log_poses(platform: Platform, path: str, source: str, skip_bad_rows: bool = False):
    """Poses ``(N, 6)`` [mm, rad] of a log: tracker FK of the readings, or the desired pose columns."""
    log = io.read_log(path, platform, skip_bad_rows)
    if source == "desired":
        if log.desired_poses is None:
            raise CalibError(f"{path}: no pose columns; expected {', '.join(io.POSE_COLUMNS)} for --pose-source desired")
        return log.desired_poses
    return measured_poses(platform, log)


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "identifiability",
        help="singular values, predicted parameter std devs and weak directions of a pose set",
        description="Report how well the poses of a log or pose list identify the 42 drive parameters.",
    )
    add_platform_and_noise_arguments(parser)
    given = parser.add_mutually_exclusive_group(required=True)
    given.add_argument("--log", metavar="L.csv", help="a measurement log")
    given.add_argument("--poses", metavar="poses.csv", help="a pose list (columns x_mm … yaw_deg)")
    parser.add_argument(
        "--pose-source",
        choices=("tracker", "desired"),
        default="tracker",
        help="with --log: tracker FK of the readings (default) or the desired pose columns",
    )
    parser.add_argument("--skip-bad-rows", action="store_true", help="with --log: skip bad rows instead of refusing")
    parser.add_argument("--json", metavar="OUT.json", help="also write the report as JSON")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    platform = load_platform(args.platform)
    noise = load_estimator_config(args.config, args.set).noise
    if args.log is not None:
        poses = log_poses(platform, args.log, args.pose_source, args.skip_bad_rows)
    else:
        poses = read_pose_list(args.poses)
    report = identifiability_report(platform, poses, noise)
    print(report.format_text())
    warning = warning_line(report)
    if warning:
        print(warning)
    if args.json:
        io.atomic_write_text(args.json, json.dumps(report.to_dict(), indent=2) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("identifiability", argv)
