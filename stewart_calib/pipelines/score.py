"""``stewart-calib score``: a calibration result against a simulation's truth (spec §4, §5).

    stewart-calib score --platform DIR/platform.toml --result R.json --truth DIR/truth.csv [--json S.json]

Prints, against the true parameters of the truth file's last row (the values an online method
reports are those at the last sample; a batch fit's hold for the whole log):

* **parameter errors** — RMS and largest of ``estimate − truth`` over the 42 parameters [mm] (and
  the largest of each drive term's, e.g. the stroke scale, where both give it), the largest one named;
* **z²** — the mean of ``((estimate − truth) / σ)²`` with the result's own σ: 1 when the reported
  error bars are honest, far above 1 when they are too small;
* **closed loop** — the mean position [mm] and orientation [deg] error over the fixed reachable
  workspace poses of :func:`stewart_calib.analysis.accuracy.evaluation_poses` when the controller commands
  IK of the estimate and the true robot executes the strokes; beside it, the same with the
  nominal model (uncalibrated).

With ``[elastic]`` (spec §10) the truth's rows are the parameters in force at each sample, loaded (the
platform's weight and the payload moved the joints and shortened the legs), while an elastic
calibration estimates the unloaded legs and their compliance. ``simulate`` writes the robot's unloaded
drive beside them (``unloaded_j1x …``) and its legs' true compliance into the platform file
(``[elastic] true_compliance_mm_per_kN``); with both, the true robot is that elastic one: an elastic
result's parameters and compliance are scored against them (a rigid result's against the last row,
the drive in force it estimates), and the closed loop commands each model's strokes under the
platform's weight (an elastic model's compensate its legs' give) and lets the true robot settle under
it (the fixed point of its leg forces and pose, the simulator's own), as ``benchmarks.elastic`` does.
A line on stderr says so. Without them (a truth file of an older simulate) an elastic result gets a
warning that neither score is its error.

With an instrument outside the robot the 12 directions of a rigid move of all base (or all
platform) joints are not identified (spec §7): the truth is moved into the estimate's gauge first
(:func:`stewart_calib.instruments.gauge.to_gauge`), so the scores are those of what a calibration
can know.

With an in-situ tracker whose own geometry the simulator drew off its nominal (the truth file's
``z1x … ls6``, spec §4), the frames {J} and {D} are those the tracker's joints define: where they best
fit their nominal positions (:func:`tracker_frames`), the frames a calibration that identifies the
tracker's geometry holds (it keeps the joints' common rigid motion at nominal) and the closest ones to
where one taking it as exact puts them. The truth is moved into them first (``tracker_frames``: true in
the scores). The simulator's own frames differ by the rigid part of the tracker's draw (12 directions
no reading shows: a translation of σ/√6 per axis for σ on each of six joints' coordinates, and a rotation
of about σ over the joints' radius), which would otherwise count as the calibration's error though no
calibration through that tracker can know it.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import replace

import numpy as np

from .. import io
from ..errors import CalibError, without_noise
from ..io.platform_file import load_platform
from ..model import kinematics as kin
from ..model.drive import COMPLIANCE, DriveModel, drive_model
from ..model.rotations import motion_error
from . import run_command

#: the score of a drive term's values (its block key before it): the largest error of the six
TERM_ERROR = "_max_error"
#: a term's unit where it has one, as the score line prints it
TERM_UNITS = {COMPLIANCE: " mm/kN"}
#: what the parameters are scored against (the scores' ``"truth"``): the truth file's last row, or an elastic
#: robot's unloaded drive (spec §4, §10)
TRUTH_LAST_ROW, TRUTH_UNLOADED = "last row", "unloaded"


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


def closed_loop_poses(commanded: DriveModel, true: DriveModel, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(R (N, 3, 3), t (N, 3))`` the ``true`` drive reaches at ``poses`` ``[mm, rad]`` when IK of the
    ``commanded`` drive gives the strokes (an elastic one's under the platform's weight, spec §10), where it
    settles (an elastic one under its weight: the fixed point of its leg forces and its pose); NaN where the
    commanded model reaches no stroke (a rotary drive's horn, spec §15: the controller refuses the pose).

    Raises:
        CalibError: the true robot cannot reach strokes the commanded model gives.
    """
    R_d, t_d = kin.pose_to_rt(poses)
    logged = commanded.inverse_kinematics(R_d, t_d)
    commanded_ok = np.all(np.isfinite(logged), axis=-1)
    strokes = np.where(commanded_ok[:, None], logged, 0.0)
    reached, _ = true.settled_kinematics(strokes, guess=(R_d, t_d), strict=False)
    if not reached.converged[commanded_ok].all():
        raise CalibError("the true robot cannot reach the strokes the estimate commands at some workspace pose")
    return np.where(commanded_ok[:, None, None], reached.R, np.nan), np.where(commanded_ok[:, None], reached.t, np.nan)


def closed_loop_error(
    commanded: DriveModel, true: DriveModel, poses: np.ndarray, home: np.ndarray | None = None
) -> tuple[float, float, float, float]:
    """Mean ``(position [mm], orientation [deg])`` error at ``poses`` ``[mm, rad]`` when IK of the
    ``commanded`` drive gives the strokes and the ``true`` drive executes them, absolute in {J} and
    of the motion from ``home`` (spec §15; NaN without a home), over the poses the commanded model
    reaches (:func:`closed_loop_poses`)."""
    R_d, t_d = kin.pose_to_rt(poses)
    R, t = closed_loop_poses(commanded, true, poses)
    position_mm, orientation_deg = kin.pose_error(R_d, t_d, R, t)
    motion = (np.nan, np.nan)
    if home is not None:
        R_h, t_h = closed_loop_poses(commanded, true, np.asarray(home)[None])
        motion_mm, motion_deg = motion_error(kin.pose_to_rt(home), (R_d, t_d), (R_h[0], t_h[0]), (R, t))
        motion = (float(np.nanmean(motion_mm)), float(np.nanmean(motion_deg)))
    return float(np.nanmean(position_mm)), float(np.nanmean(orientation_deg)), *motion


def elastic_truth(platform, truth) -> bool:
    """Whether ``truth`` is of an elastic robot it can be unloaded from: its unloaded drive (spec §4) and the
    platform's true compliance (spec §10, ``[elastic] true_compliance_mm_per_kN``) both given."""
    elastic = platform.elastic
    return elastic is not None and elastic.true_compliance_mm_per_kN is not None and truth.unloaded is not None


def scores(platform, result: dict, truth) -> dict:
    """The scores of ``result`` against ``truth`` (see the module)."""
    from ..analysis.accuracy import evaluation_poses
    from ..instruments import gauge, instrument_kind

    elastic = elastic_truth(platform, truth)
    # the true robot's drive: rigid, spec §4's last row; elastic, its unloaded drive (its compliance beside it)
    true_drive_params = truth.unloaded if elastic else truth.params[-1]
    loaded_params = truth.params[-1]
    frames = tracker_frames(platform, truth)
    if instrument_kind(platform).outside:  # its fit leaves the drive's gauge directions where the gauge puts them
        true_drive_params, _, _ = gauge.to_gauge(platform.drive, true_drive_params)
        loaded_params, _, _ = gauge.to_gauge(platform.drive, loaded_params)
    elif frames is not None:  # {J} and {D} where the true tracker's joints best fit its nominal ones
        true_drive_params = gauge.moved_into(platform.drive, true_drive_params, *frames)
        loaded_params = gauge.moved_into(platform.drive, loaded_params, *frames)
    # an elastic result estimates the unloaded drive; a rigid one the drive in force, loaded
    unloaded = elastic and COMPLIANCE in result
    true_params = true_drive_params if unloaded else loaded_params
    estimate = io.parameters_from_file(result["estimate"], platform.drive)
    e = io.parameters_to_file(estimate - true_params, platform.drive)  # mm, and a rotary drive's angles in deg
    worst = int(np.argmax(np.abs(e)))
    out = {
        "parameter_rms_mm": float(np.sqrt(np.mean(e**2))),
        "parameter_max_mm": float(abs(e[worst])),
        "parameter_max_name": platform.drive.parameter_names[worst],
    }
    stddev = result.get("stddev")
    if stddev is not None and np.all(np.asarray(stddev, dtype=float) > 0):
        out["z2"] = float(np.mean((e / np.asarray(stddev, dtype=float)) ** 2))
    nominal = drive_model(platform if elastic else replace(platform, elastic=None))
    true_terms = dict(truth.drive_terms)
    if elastic:
        true_terms[COMPLIANCE] = platform.elastic.true_compliance_mm_per_kN
    fitted = {
        term.key: np.array(result[term.key]["estimate"], dtype=float) for term in nominal.terms if term.key in result
    }
    for key, values in fitted.items():
        if key in true_terms:
            out[f"{key}{TERM_ERROR}"] = float(np.max(np.abs(values - true_terms[key])))
    nominal_params = platform.drive.as_vector()
    true = nominal.true_drive(true_drive_params - nominal_params, true_terms)
    calibrated = nominal.calibrated(estimate - nominal_params, fitted)
    poses = evaluation_poses(platform)
    R, t = kin.pose_to_rt(poses)
    # the poses both models command (a rotary drive's calibrated horns may not reach an edge pose the nominal ones do)
    poses = poses[np.all(np.isfinite(calibrated.inverse_kinematics(R, t)), axis=-1)]
    home = None if platform.workspace is None else platform.workspace.home
    for key, drive in (("closed_loop", calibrated), ("closed_loop_nominal", nominal)):
        errors = closed_loop_error(drive, true, poses, home)
        out[f"{key}_mm"], out[f"{key}_deg"], out[f"{key}_motion_mm"], out[f"{key}_motion_deg"] = errors
    out["poses"] = len(poses)
    out["truth"] = TRUTH_UNLOADED if unloaded else TRUTH_LAST_ROW
    out["closed_loop_settled"] = elastic
    out["tracker_frames"] = frames is not None
    return out


def tracker_frames(platform, truth) -> tuple[tuple, tuple] | None:
    """The rigid motions ``((R_J, t_J), (R_D, t_D))`` from the simulator's frames {J} and {D} to those in which
    the true in-situ tracker's base and platform joints best fit (Kabsch) their nominal ones, where the truth
    gives the tracker's own values off their nominal (spec §4); else None."""
    from ..instruments import gauge
    from ..instruments.tracker import tracker_parameter_names

    if platform.tracker is None or truth.instrument is None:
        return None
    names, values = truth.instrument
    if tuple(names) != tracker_parameter_names(platform.tracker):
        return None
    return gauge.best_fit_frames(platform.tracker, np.asarray(values, dtype=float))


def run(args: argparse.Namespace) -> int:
    platform = load_platform(args.platform)
    result = io.read_result(args.result)
    truth = io.read_truth(args.truth, platform)
    gap = io.nominal_gap(result, platform)
    if gap > io.NOMINAL_TOLERANCE_MM:
        raise CalibError(
            f"{args.result}: key 'nominal': expected the nominal drive of {args.platform}; it differs by {gap:.3g} mm"
        )
    s = scores(platform, result, truth)
    z2 = f"z² {s['z2']:.3g}" if "z2" in s else "z² — (no σ in the result)"
    terms = "".join(
        f", {key.removesuffix(TERM_ERROR).replace('_', ' ')} within {value:.2g}"
        f"{TERM_UNITS.get(key.removesuffix(TERM_ERROR), '')}"
        for key, value in s.items()
        if key.endswith(TERM_ERROR)
    )
    motion = (
        f"; motion from home {s['closed_loop_motion_mm']:.4g} mm / {s['closed_loop_motion_deg']:.4g}° (nominal model "
        f"{s['closed_loop_nominal_motion_mm']:.4g} mm / {s['closed_loop_nominal_motion_deg']:.4g}°)"
        if math.isfinite(s["closed_loop_motion_mm"])
        else ""
    )
    names = platform.drive.parameter_names
    unit = io.parameter_unit(platform.drive)  # a rotary drive's angles in deg
    worst_unit = "deg" if platform.drive.parameter_degrees[names.index(s["parameter_max_name"])] else "mm"
    print(
        f"stewart-calib score: parameters RMS {s['parameter_rms_mm']:.4g} {unit}, max {s['parameter_max_mm']:.4g} "
        f"{worst_unit} "
        f"({s['parameter_max_name']}){terms}; {z2}; closed loop {s['closed_loop_mm']:.4g} mm / "
        f"{s['closed_loop_deg']:.4g}° (nominal model {s['closed_loop_nominal_mm']:.4g} mm / "
        f"{s['closed_loop_nominal_deg']:.4g}°, mean over {s['poses']} workspace poses){motion}"
    )
    if s["closed_loop_settled"]:
        against = (
            "its unloaded drive (truth.csv's unloaded_*) and the platform's true_compliance_mm_per_kN"
            if s["truth"] == TRUTH_UNLOADED
            else "those in force at the truth's last sample, loaded, as a rigid result estimates them"
        )
        print(
            f"stewart-calib score: the robot is elastic (spec §10): parameters scored against {against}; closed "
            "loop: each model's strokes under the platform's weight, executed by the true robot, which settles "
            "under it",
            file=sys.stderr,
        )
    elif platform.elastic is not None and COMPLIANCE in result:
        print(
            "stewart-calib score: warning: the truth's parameters are those in force at its last sample, loaded "
            "(spec §10), and the closed loop takes the robot rigid; the elastic result estimates the unloaded legs "
            "and their compliance, so neither score is its error (the truth file has no unloaded_* columns or the "
            "platform no [elastic] true_compliance_mm_per_kN: simulate it again to score it)",
            file=sys.stderr,
        )
    if args.json:
        finite = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in s.items()}
        io.atomic_write_text(args.json, json.dumps(without_noise(finite), indent=1) + "\n")
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_command("score", argv)
