"""``stewart-calib score``: a calibration result against a simulation's truth (spec §4, §5).

    stewart-calib score --platform DIR/platform.toml --result R.json --truth DIR/truth.csv [--json S.json]

Prints, against the true parameters of the truth file's last row (the values an online method
reports are those at the last sample; a batch fit's hold for the whole log):

* **parameter errors** — RMS and largest of ``estimate − truth`` over the 42 parameters [mm] (and
  of the stroke scale where both identify it), the largest one named;
* **z²** — the mean of ``((estimate − truth) / σ)²`` with the result's own σ: 1 when the reported
  error bars are honest, far above 1 when they are too small;
* **closed loop** — the mean position [mm] and orientation [deg] error over the fixed reachable
  workspace poses of :func:`stewart_calib.accuracy.evaluation_poses` when the controller commands
  IK of the estimate and the true robot executes the strokes; beside it, the same with the
  nominal model (uncalibrated).

With an instrument outside the robot the 12 directions of a rigid move of all base (or all
platform) joints are not identified (spec §7): the truth is moved into the estimate's gauge first
(:func:`stewart_calib.instruments.gauge.to_gauge`), so the scores are those of what a calibration
can know.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace

import numpy as np

from .. import io
from .. import kinematics as kin
from ..drive import STROKE_SCALE, DriveModel, drive_model
from ..errors import CalibError
from ..platform import N_LEGS, PARAMETER_NAMES, load_platform
from . import run_command


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "score",
        description="Score a calibration result against a simulation's truth.csv: parameter errors, z² of the "
        "reported σ, closed-loop pose error with the estimate and with the nominal model (spec §4, §5).",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="the simulated platform (spec §2)")
    parser.add_argument("--result", required=True, metavar="R.json", help="calibration result (spec §5)")
    parser.add_argument("--truth", required=True, metavar="T.csv", help="the simulation's truth (spec §4)")
    parser.add_argument("--json", metavar="S.json", help="also write the scores as JSON")
    parser.set_defaults(func=run)


def closed_loop_error(commanded: DriveModel, true: DriveModel, poses: np.ndarray) -> tuple[float, float]:
    """Mean position [mm] and orientation [deg] error at ``poses`` ``[mm, rad]`` when IK of the
    ``commanded`` drive gives the logged strokes and the ``true`` drive executes them."""
    R_d, t_d = kin.pose_to_rt(poses)
    logged = commanded.inverse_kinematics(R_d, t_d)
    reached = true.forward_kinematics(true.inputs(logged), guess=(R_d, t_d), strict=False)
    if not reached.converged.all():
        raise CalibError("the true robot cannot reach the strokes the estimate commands at some workspace pose")
    position_mm, orientation_deg = kin.pose_error(R_d, t_d, reached.R, reached.t)
    return float(np.mean(position_mm)), float(np.mean(orientation_deg))


def scores(platform, result: dict, truth) -> dict:
    """The scores of ``result`` against ``truth`` (see the module)."""
    from ..accuracy import evaluation_poses
    from ..instruments import gauge, instrument_kind

    true_params = truth.params[-1]
    if instrument_kind(platform).outside:  # its fit leaves the drive's gauge directions where the gauge puts them
        true_params, _, _ = gauge.to_gauge(platform.drive, true_params)
    estimate = np.asarray(result["estimate"], dtype=float)
    e = estimate - true_params
    worst = int(np.argmax(np.abs(e)))
    out = {
        "parameter_rms_mm": float(np.sqrt(np.mean(e**2))),
        "parameter_max_mm": float(abs(e[worst])),
        "parameter_max_name": PARAMETER_NAMES[worst],
    }
    stddev = result.get("stddev")
    if stddev is not None and np.all(np.asarray(stddev, dtype=float) > 0):
        out["z2"] = float(np.mean((e / np.asarray(stddev, dtype=float)) ** 2))
    # the rigid drive of spec §4's truth: δM and the stroke scale (the truth file's one term)
    nominal = drive_model(replace(platform, elastic=None))
    scale_block = result.get(STROKE_SCALE)
    scale = None if scale_block is None else np.array(scale_block["estimate"], dtype=float)
    if scale is not None and truth.stroke_scale is not None:
        out["stroke_scale_max_error"] = float(np.max(np.abs(scale - truth.stroke_scale)))
    nominal_params = platform.drive.as_vector()
    true_scale = np.zeros(N_LEGS) if truth.stroke_scale is None else truth.stroke_scale
    true = nominal.calibrated(true_params - nominal_params, {STROKE_SCALE: true_scale})
    poses = evaluation_poses(platform)
    out["closed_loop_mm"], out["closed_loop_deg"] = closed_loop_error(
        nominal.calibrated(estimate - nominal_params, {STROKE_SCALE: scale}), true, poses
    )
    out["closed_loop_nominal_mm"], out["closed_loop_nominal_deg"] = closed_loop_error(nominal, true, poses)
    out["poses"] = len(poses)
    return out


def run(args: argparse.Namespace) -> int:
    platform = load_platform(args.platform)
    result = io.read_result(args.result)
    truth = io.read_truth(args.truth)
    gap = float(np.max(np.abs(np.array(result["nominal"]) - platform.drive.as_vector())))
    if gap > io.NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{args.result}: key 'nominal': expected the nominal drive of {args.platform}; it differs by {gap:.3g} mm"
        )
    s = scores(platform, result, truth)
    z2 = f"z² {s['z2']:.3g}" if "z2" in s else "z² — (no σ in the result)"
    scale = f", stroke scale within {s['stroke_scale_max_error']:.2g}" if "stroke_scale_max_error" in s else ""
    print(
        f"stewart-calib score: parameters RMS {s['parameter_rms_mm']:.4g} mm, max {s['parameter_max_mm']:.4g} mm "
        f"({s['parameter_max_name']}){scale}; {z2}; closed loop {s['closed_loop_mm']:.4g} mm / "
        f"{s['closed_loop_deg']:.4g}° (nominal model {s['closed_loop_nominal_mm']:.4g} mm / "
        f"{s['closed_loop_nominal_deg']:.4g}°, mean over {s['poses']} workspace poses)"
    )
    if args.json:
        finite = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in s.items()}
        io.atomic_write_text(args.json, json.dumps(finite, indent=1) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("score", argv)
