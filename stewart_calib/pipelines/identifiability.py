"""``stewart-calib identifiability``: is a pose set (a log's or a planned list) good enough?

Prints :meth:`~stewart_calib.identifiability.IdentifiabilityReport.format_text`; ``--json``
writes :meth:`~stewart_calib.identifiability.IdentifiabilityReport.to_dict`.
"""

from __future__ import annotations

import argparse
import json

from .. import io
from ..config import load_estimator_config
from ..errors import CalibError
from ..identifiability import NO_POSE, InformationAccumulator, identifiability_report, tracker_poses, warning_line
from ..io import read_pose_list
from ..platform import Platform, load_platform
from . import run_command
from .plan import add_platform_and_noise_arguments


def log_information(platform: Platform, path: str, source: str, noise, skip_bad_rows: bool = False):
    """The :class:`InformationAccumulator` of a log's poses — tracker FK of the readings, or the
    desired pose columns — read a block at a time (memory independent of the log's length)."""
    information = InformationAccumulator(platform, noise)
    for block in io.read_log_blocks(path, platform, skip_bad_rows):
        if source == "desired":
            if block.desired_poses is None:
                raise CalibError(
                    f"{path}: no pose columns; expected {', '.join(io.POSE_COLUMNS)} for --pose-source desired"
                )
            information.add(block.desired_poses)
        else:
            information.add(tracker_poses(platform, block))
    if information.n_poses == 0:
        raise CalibError(NO_POSE)
    return information


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "identifiability",
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
    if platform.instrument.kind != "tracker":
        return _run_outside_instrument(args, platform)
    if args.log is not None:
        report = log_information(platform, args.log, args.pose_source, noise, args.skip_bad_rows).report()
    else:
        report = identifiability_report(platform, read_pose_list(args.poses), noise)
    print(report.format_text())
    warning = warning_line(report)
    if warning:
        print(warning)
    if args.json:
        io.atomic_write_text(args.json, json.dumps(report.to_dict(), indent=2) + "\n")
    return 0


def _run_outside_instrument(args: argparse.Namespace, platform: Platform) -> int:
    """An instrument outside the robot (spec §7): the Cramér–Rao σ of drive, stroke scale and
    instrument unknowns together, at the nominal drive and the instrument registered on the log
    (a pose list: the nominal instrument reading the nominal robot at those poses)."""
    import numpy as np

    from .. import kinematics as kin
    from ..estimators.batch import BatchProblem, identifiability
    from ..instruments.external import model_for, registered_platform

    if args.log is not None:
        log = io.read_log(args.log, platform, args.skip_bad_rows)
        strokes, readings = log.strokes, log.readings
        platform = registered_platform(platform, strokes, readings)
        model = model_for(platform)
    else:
        model = model_for(platform)
        R, t = kin.pose_to_rt(read_pose_list(args.poses))
        strokes = kin.inverse_kinematics(platform.drive, R, t) / (1.0 + platform.stroke_scale)
        predicted = model.module.predict(model.nominal_unknowns(), R, t)
        readings = kin.rt_to_pose(*predicted) if model.kind == "pose" else predicted.reshape(len(R), -1)
    unknowns = model.nominal_unknowns()
    problem = BatchProblem(
        platform.drive,
        platform.stroke_scale,
        strokes,
        readings,
        model.module,
        model.register,
        model.sigmas,
        model.channels,
        model.channel_names,
        np.arange(len(strokes), dtype=float),
    )
    report = identifiability(problem, unknowns, model.unknown_names, unknowns.file_jacobian())
    verdict = "identifiable" if report["condition_number"] is not None else "rank-deficient"
    print(
        f"Identifiability of drive, stroke scale and {model.kind} instrument from {len(strokes)} poses: {verdict} "
        f"(rank {report['rank']}/{report['unknowns']}; condition number "
        f"{report['condition_number'] or float('inf'):.4g})"
    )
    print(report["gauge"])
    print("predicted standard deviation per unknown (Cramér–Rao; mm, dimensionless k, degrees):")
    items = list(report["predicted_stddev"].items())
    for start in range(0, len(items), 7):
        print(
            "  "
            + "  ".join(f"{name} {'not id' if sd is None else f'{sd:.3g}'}" for name, sd in items[start : start + 7])
        )
    if args.json:
        io.atomic_write_text(
            args.json, json.dumps({"format": "stewart-calib/identifiability-instrument@1", **report}, indent=2) + "\n"
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("identifiability", argv)
