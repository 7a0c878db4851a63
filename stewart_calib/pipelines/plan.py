"""``stewart-calib plan``: choose N calibration poses and write them as a pose list CSV.

The pose list has the log's pose columns (``x_mm y_mm z_mm roll_deg pitch_deg yaw_deg``,
spec §3) and a ``t_s`` column (one pose per ``--dwell-s``), so a user can drive the robot
through it and ``stewart-calib identifiability --poses`` reads it back.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from .. import io
from ..analysis.accuracy import PREDICTION_HEAD, predicted_error
from ..config import load_estimator_config
from ..errors import CalibError
from ..inputs import MAX_TIME_S
from ..instruments import instrument_kind
from ..io.platform_file import load_platform
from ..workflows.diagnosis import require_poses
from ..workflows.planning import (
    CRITERIA,
    default_criterion,
    design_covariance,
    extreme_poses,
    noise_words,
    plan_poses,
    plan_warning,
    reading_margin_mm,
    with_stroke_margin,
)
from . import add_config_arguments, positive_number, run_command


def add_platform_and_noise_arguments(parser: argparse.ArgumentParser) -> None:
    """``--platform``, and ``--config``/``--set``: the estimator config whose ``[noise]`` weights the Jacobian."""
    parser.add_argument("--platform", required=True, metavar="P.toml")
    add_config_arguments(parser, "noise.reading_sigma_mm=0.005")


def _positive_seconds(text: str) -> float:
    return positive_number(text, "number of seconds")


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value < 2**128:  # what numpy's SeedSequence takes
        raise argparse.ArgumentTypeError(f"expected a whole number ≥ 0, got {text!r}")
    return value


#: most candidate poses a plan draws: each holds its information matrix (an outside instrument's
#: 48 × 48: 18 KB, so 10⁵ are 1.8 GB); 10¹¹ were an out-of-memory, 10⁴⁰⁰ a traceback
MAX_CANDIDATES = 100_000


def _candidates(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if not 1 <= value <= MAX_CANDIDATES:
        raise argparse.ArgumentTypeError(f"expected a whole number of poses from 1 to {MAX_CANDIDATES}, got {text!r}")
    return value


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "plan",
        description="Pick N poses from reachable workspace poses that best identify the drive (and, for an "
        "outside instrument, the stroke scale and the instrument's frame and targets).",
    )
    add_platform_and_noise_arguments(parser)
    parser.add_argument("--n", required=True, type=int, metavar="N", help="number of poses to plan")
    parser.add_argument("--out", required=True, metavar="poses.csv")
    parser.add_argument(
        "--criterion",
        choices=CRITERIA,
        default=None,
        help="I: smallest predicted closed-loop pose error over the workspace (default for pose and points "
        "instruments); A: smallest mean parameter variance (default for the tracker); D: log det; O1: "
        "Borm–Menq O1 of the paper's J_p form (tracker only); E: weakest direction",
    )
    parser.add_argument(
        "--candidates",
        type=_candidates,
        default=2000,
        metavar="M",
        help=f"random candidate poses (2000; ≤ {MAX_CANDIDATES})",
    )
    parser.add_argument("--seed", type=_seed, default=None, help="seed of the candidate draw (a whole number ≥ 0)")
    parser.add_argument(
        "--dwell-s", type=_positive_seconds, default=1.0, help="t_s step between poses in the file [s], > 0"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    platform = load_platform(args.platform)
    require_poses(platform, args.n, "--n", "pose(s) asked", "poses")
    if not (args.n - 1) * args.dwell_s <= MAX_TIME_S:  # what a log's t_s may hold (spec §3's reader)
        raise CalibError(
            f"--dwell-s {args.dwell_s!r}: expected a step that ends {args.n} poses within {MAX_TIME_S:g} s, "
            f"got a last t_s of {(args.n - 1) * args.dwell_s:.4g} s"
        )
    criterion = args.criterion or default_criterion(platform)
    noise = load_estimator_config(args.config, args.set).noise
    start = time.perf_counter()
    poses = plan_poses(platform, args.n, criterion, np.random.default_rng(args.seed), args.candidates, noise)
    elapsed_s = time.perf_counter() - start
    io.write_pose_list(args.out, poses, args.dwell_s)
    extremes = ""
    if instrument_kind(platform).outside:
        extremes = f" and {len(extreme_poses(platform))} box extremes"
        narrowed, _, unit = io.drive_range(with_stroke_margin(platform, noise))
        bounds = io.drive_range(platform)[0]
        if bounds is not None and narrowed is not None:
            what = "strokes" if unit == "mm" else "angles"
            extremes += f"; {what} {narrowed[0] - bounds[0]:.3g} {unit} inside the range, for the true robot's offsets"
    reading_margin = reading_margin_mm(platform, noise)
    if reading_margin is not None:
        extremes += f"; tracker readings {reading_margin:.3g} mm inside their range, for the true robot's offsets"
    print(
        f"stewart-calib plan: planned {len(poses)} poses ({criterion} from {args.candidates} candidates{extremes}, "
        f"{elapsed_s:.2f} s) -> {args.out}"
    )
    covariance = design_covariance(platform, poses, noise)
    if covariance is not None:
        prediction = predicted_error(platform, covariance)
        noise_named = noise_words(platform, noise, args.config)
        print(f"stewart-calib plan: {PREDICTION_HEAD} ({noise_named}): {prediction.describe()}")
        warning = plan_warning(platform, noise, prediction, len(poses))
        if warning:
            print(f"stewart-calib plan: {warning}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("plan", argv)
