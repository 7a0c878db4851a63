"""``stewart-calib identifiability``: is a pose set (a log's or a planned list) good enough?

Prints :meth:`~stewart_calib.analysis.identifiability.IdentifiabilityReport.format_text`; ``--json``
writes :meth:`~stewart_calib.analysis.identifiability.IdentifiabilityReport.to_dict`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .. import io
from ..analysis.identifiability import CONDITION_POOR, NO_POSE, InformationAccumulator, tracker_samples, warning_line
from ..config import NoiseConfig, load_estimator_config
from ..errors import CalibError, without_noise
from ..instruments import instrument_kind
from ..io import read_pose_list
from ..io.platform_file import load_platform
from ..model.drive import THERMAL, drive_model
from ..model.platform import Platform
from ..samples import TEMPERATURE_C
from ..workflows.diagnosis import require_poses
from . import handover, run_command
from .plan import add_platform_and_noise_arguments


def log_information(platform: Platform, path: str, source: str, noise, skip_bad_rows: bool = False):
    """The :class:`InformationAccumulator` of a log's poses — tracker FK of the readings, or the
    desired pose columns — read a block at a time (memory independent of the log's length), over the
    drive's unknowns as the estimators identify them (the compliance with ``[elastic]``, the expansion
    with ``[thermal]``, the stroke scale where configured: at the samples' strokes and input channels),
    and the expansion's trade-off line with the legs' lengths (:func:`thermal_line`) or None."""
    drive = drive_model(platform, noise)
    information = InformationAccumulator(platform, noise, drive=drive)
    separating = handover.trade_off_drive(drive)
    if separating is not None and separating.size == drive.size:
        separating = None  # every term already free: the report's own σ of the expansion is the one
    free = None if separating is None else InformationAccumulator(platform, noise, False, separating)
    low = high = None
    for block in io.read_log_blocks(path, platform, skip_bad_rows):
        if source == "desired":
            if block.desired_poses is None:
                raise CalibError(
                    f"{path}: no pose columns; expected {', '.join(io.POSE_COLUMNS)} for --pose-source desired"
                )
            samples = (block.desired_poses, block.strokes, block.inputs)
        else:
            samples = tracker_samples(platform, block)
        information.add(*samples)
        if free is not None:
            free.add(*samples)
        span = _span_of(samples[2])
        if span is not None:
            low = span[0] if low is None else np.minimum(low, span[0])
            high = span[1] if high is None else np.maximum(high, span[1])
    if information.n_poses == 0:
        raise CalibError(NO_POSE)
    spans = None if low is None or high is None else high - low
    return information, thermal_line(drive, information if free is None else free, spans)


def _span_of(channels) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lowest, highest)`` temperature of each leg over a block's samples, or None without any."""
    temperatures = channels.get(TEMPERATURE_C)
    if temperatures is None or not len(temperatures):
        return None
    return np.min(temperatures, axis=0), np.max(temperatures, axis=0)


def thermal_line(drive, information: InformationAccumulator, span_K) -> str | None:
    """:func:`handover.thermal_trade_off_line` of the expansion's Cramér–Rao σ in ``information``
    (accumulated with every term of the drive free: :func:`handover.trade_off_drive`)."""
    if handover.trade_off_drive(drive) is None:
        return None
    names, stddev = information.report().block_stddev[THERMAL]
    return handover.thermal_trade_off_line(drive, dict(zip(names, stddev.tolist(), strict=True)), span_K)


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
    config = load_estimator_config(args.config, args.set)
    noise = config.noise
    if instrument_kind(platform).outside:
        return _run_outside_instrument(args, platform, config)
    trade_off = bound = None
    if args.log is not None:
        # the tracker's leg-length rows hardly move with the drive: the bound at the nominal drive, the
        # log streamed (an ls fit would hold it whole)
        information, trade_off = log_information(platform, args.log, args.pose_source, noise, args.skip_bad_rows)
        require_poses(platform, information.n_poses, args.log, "pose(s)", "poses")
        covariance, poses, bound = information.covariance(), None, "at the nominal drive"
    else:
        poses = read_pose_list(args.poses)
        require_poses(platform, _distinct(poses), args.poses, "distinct pose(s)", "poses")
        information = InformationAccumulator(platform, noise, drive=drive_model(platform, noise))
        information.add(poses)  # the strokes of the drive's inverse kinematics, no payload
        covariance = information.covariance()
    report = information.report()
    print(report.format_text())
    warning = warning_line(report)
    for line in (warning, trade_off):
        if line:
            print(f"stewart-calib identifiability: {line}")
    prediction = _prediction(platform, covariance, poses, information.n_poses, noise, args.config, bound)
    if args.json:
        thermal = {} if trade_off is None else {"thermal_trade_off": trade_off}
        document = without_noise({**report.to_dict(), **prediction, **thermal})
        io.atomic_write_text(args.json, json.dumps(document, indent=2) + "\n")
    return 0


def _distinct(poses) -> int:
    """Distinct rows of a pose list ``(N, 6)``: a pose listed twice adds no direction."""
    import numpy as np

    return len(np.unique(np.asarray(poses, dtype=float), axis=0))


def fitted_platform(platform: Platform, log, config, path: str) -> tuple[Platform | None, str]:
    """``(platform, words)``: the platform at the log's own ``ls`` fit — the fit ``calibrate --method ls``
    makes (:func:`~stewart_calib.workflows.calibration.run_calibration`), its drive and the outside
    instrument's frame and target(s) (:func:`handover.calibrated_platform`) — where a log's Cramér–Rao
    bound is linearised, so that it is the covariance ``calibrate`` predicts from at the drive calibrate
    finds, not at the nominal one millimetres away; None where ls cannot fit the log (a fit that diverges
    or is rank-deficient: the bound then at the nominal drive, the words say why)."""
    from ..workflows.calibration import run_calibration

    try:
        estimate = run_calibration(platform, log, "ls", config).estimate
    except CalibError as err:
        return None, f"at the nominal drive: ls cannot fit the log ({err})"
    if estimate.covariance is None:
        return None, "at the nominal drive: the log's ls fit is rank-deficient"
    created = handover.created_now()
    return handover.calibrated_platform(platform, estimate, "ls", Path(path).name, created), "at the log's ls fit"


def _prediction(
    platform: Platform, covariance, poses, n_poses: int, noise, config: str | None, bound: str | None = None
) -> dict:
    """Print the predicted closed-loop error line of a pose set's Cramér–Rao covariance (over the
    workspace, or the poses themselves where the platform has none), warned against the noise
    floor of as many poses, with ``bound``, the words saying where a log's is linearised
    (:func:`fitted_platform`; None: a pose list's, at the nominal drive), and the noise it takes
    (:func:`~stewart_calib.workflows.planning.noise_words`, ``config``: ``--config``'s name); its JSON field."""
    from ..analysis.accuracy import PREDICTION_HEAD, predicted_error, summary_line
    from ..workflows.planning import noise_floor, noise_words

    words = noise_words(platform, noise or NoiseConfig(), config)
    what = f"{PREDICTION_HEAD} ({words})" if bound is None else f"{PREDICTION_HEAD} ({bound}; {words})"
    if covariance is None:
        print(f"stewart-calib identifiability: {what}: none (the poses do not identify every unknown)")
        return {"predicted_closed_loop": None}
    if platform.workspace is None and poses is None:
        print(f"stewart-calib identifiability: {what}: none (no [workspace] to predict over)")
        return {"predicted_closed_loop": None}
    prediction = predicted_error(platform, covariance, None if platform.workspace is not None else poses)
    floor = noise_floor(platform, n_poses, noise)
    line, warn = summary_line(prediction, floor, what=what)
    print(f"stewart-calib identifiability: {line}")
    field = {"noise_floor_mm": None if floor is None else floor.position_mm, "warning": line if warn else None}
    return {"predicted_closed_loop": {**prediction.to_dict(), **field}}


def _run_outside_instrument(args: argparse.Namespace, platform: Platform, config) -> int:
    """An instrument outside the robot (spec §7): the Cramér–Rao σ of drive, stroke scale and
    instrument unknowns together, at the nominal drive and the instrument registered on the log
    (a pose list: the nominal instrument reading the nominal robot at those poses), the drive's
    parameters the poses see no better than their prior (:func:`_weak_against_prior`), and the
    predicted closed-loop error of the bound at the log's ls fit (:func:`fitted_platform`; a pose
    list's at the nominal drive)."""
    import numpy as np

    from ..estimators.batch import instrument_identifiability
    from ..instruments import outside_model, registered
    from ..model import kinematics as kin
    from ..model.drive import COMPLIANCE, drive_model
    from ..workflows.planning import design_covariance

    drive = drive_model(platform).identifying()
    bound = None
    if args.log is not None:
        log = io.read_log(args.log, platform, args.skip_bad_rows)
        strokes, readings, channels = log.strokes, log.readings, log.inputs
        fit, bound = fitted_platform(platform, log, config, args.log)
        platform = registered(platform, strokes, readings)
        model = outside_model(platform)
        fk, _ = drive.settled_kinematics(strokes, channels, strict=False)
        poses = fk.pose6[fk.converged]
        require_poses(platform, len(poses), args.log, "pose(s)", "poses")
        # the bound's rows where the fit put the robot: its poses of the strokes, the channels read there
        at = platform if fit is None else fit
        if fit is not None:
            fk, _ = drive_model(fit).settled_kinematics(strokes, channels, strict=False)
        bound_poses = fk.pose6[fk.converged]
        seen = np.isfinite(readings[fk.converged])
        converged = {name: np.asarray(values)[fk.converged] for name, values in channels.items()}
    else:
        model = outside_model(platform)
        poses = read_pose_list(args.poses)
        require_poses(platform, _distinct(poses), args.poses, "distinct pose(s)", "poses")
        R, t = kin.pose_to_rt(poses)
        channels = {}  # a pose list has none: the platform's own weight, at the reference temperature
        strokes = drive.inverse_kinematics(R, t)
        readings = model.predicted_readings(model.nominal_unknowns(), R, t)
        readings = np.where(model.seen_channels(R, t), readings, np.nan)  # e.g. a target out of its cone
        seen = None  # design_covariance finds the same channels in view
        converged = channels
        at, bound_poses = platform, poses
    report = instrument_identifiability(platform, strokes, readings, channels)
    equilibrated = report["condition_number_equilibrated"]
    # the drive's blocks by name: the compliance too with [elastic] (spec §10), which the report covers
    parts = ["drive", *(_block_name(drive, block) for block in drive.blocks)]
    print(
        f"Identifiability of {', '.join(parts)} and {model.kind} instrument from {len(strokes)} poses: "
        f"{report['verdict']} (rank {report['rank']}/{report['unknowns']}; condition number "
        f"{equilibrated or float('inf'):.4g} with unit columns, poorly conditioned above {CONDITION_POOR:g}; "
        f"{report['condition_number'] or float('inf'):.4g} in mm, rad and k)"
    )
    print(report["gauge"])
    for what, names in (("weakest directions (unit columns)", "weakest_directions"), ("not identified", "null_space")):
        if report[names]:
            print(f"{what}: " + "; ".join(report[names]))
    c = ", c in mm/kN" if any(block.key == COMPLIANCE for block in drive.blocks) else ""
    c += ", α in ppm/K" if any(block.key == THERMAL for block in drive.blocks) else ""
    print(f"predicted standard deviation per unknown (Cramér–Rao; mm, dimensionless k{c}, degrees):")
    items = list(report["predicted_stddev"].items())
    for start in range(0, len(items), 7):
        print(
            "  "
            + "  ".join(f"{name} {'not id' if sd is None else f'{sd:.3g}'}" for name, sd in items[start : start + 7])
        )
    weak = _weak_against_prior(drive.legs, report["predicted_stddev"], config.noise)
    if weak:
        named = ", ".join(f"{name} {sd:.3g} (prior {prior:.3g})" for name, sd, prior in weak)
        print(
            "stewart-calib identifiability: seen no better than their prior σ (a calibration keeps them near "
            f"nominal; poses that see them better: stewart-calib plan): {named}"
        )
    span = handover.temperature_span_K(channels) if args.log is not None else None
    trade_off = handover.thermal_trade_off_line(drive, handover.outside_stddev(drive, report), span)
    if trade_off:
        print(f"stewart-calib identifiability: {trade_off}")
    # at the log's payloads (and temperatures), as the calibration sees them: without them an elastic
    # drive's compliance trades against the leg lengths under the platform's weight alone
    covariance = design_covariance(at, bound_poses, seen=seen, channels=converged)
    prediction = _prediction(platform, covariance, poses, len(poses), None, args.config, bound)
    if args.json:
        document = {
            "format": "stewart-calib/identifiability-instrument@1",
            **report,
            "weak_against_prior": [name for name, _, _ in weak],
            **prediction,
            **({} if trade_off is None else {"thermal_trade_off": trade_off}),
        }
        io.atomic_write_text(args.json, json.dumps(without_noise(document), indent=2) + "\n")
    return 0


def _weak_against_prior(legs, stddev: dict, noise) -> list[tuple[str, float, float]]:
    """``(name, Cramér–Rao σ, prior σ)`` in file units of each drive parameter whose σ from the poses
    alone (``stddev``: the report's, by name) is above its prior σ (the leg model's ``prior_sigmas``;
    a servo's zero offsets and axis tilts in degrees), largest ratio first; none where the poses do
    not identify every unknown (the null space names those)."""
    import numpy as np

    prior = legs.prior_sigmas(noise) * np.where(legs.parameter_degrees, np.degrees(1.0), 1.0)
    weak = [
        (name, stddev[name], float(p))
        for name, p in zip(legs.parameter_names, prior, strict=True)
        if stddev[name] is not None and stddev[name] > p
    ]
    return sorted(weak, key=lambda item: -item[1] / item[2])


def _block_name(drive, block) -> str:
    """A drive block's words (``stroke scale``; a rotary drive's ``angle scale``, spec §15)."""
    name = block.key.replace("_", " ")
    return name.replace("stroke", "angle") if drive.legs.coordinate_unit == "deg" else name


def main(argv: list[str] | None = None) -> int:
    return run_command("identifiability", argv)
