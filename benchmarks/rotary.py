"""The rotary (servo-horn, 6-RSS) hexapod of spec §15: calibration accuracy against the Cramér–Rao bound.

The shipped servo experiment (``configs/experiments/servo.toml``: configs/platforms/servo-hexapod.toml
measured by motion capture with its frame and rigid-body target unknown, 150 calibration poses, the
errors of a hobby servo build) with a few seeds. Each method calibrates with the default config
(``run_calibration``, as ``calibrate --method M`` runs it); its result's IK commands fresh poses (what
``compensate`` gives) and the true robot executes them. Two errors, apart (spec §15): the **motion from
home** (``T_home⁻¹ T`` against ``X_home⁻¹ X``: position of {D}'s origin, rotation angle) and the
**absolute** place in {J} — the truth moved into the estimate's gauge first (the frames where the crank
centres and the platform joints best fit their nominal places, ``instruments.gauge.to_gauge``), which is
also the nominal model at its best registration. Beside them the **Cramér–Rao bound**: the predicted
error (``accuracy.predicted_error``) of the batch fit's Cramér–Rao covariance at the truth with the
instrument's noise (``estimators.batch.cramer_rao``; the servos' own angle noise, 0.05°, is left out of
it) — and the **nominal** model's errors. Means over the seeds of each run's mean over the fresh poses.

``python -m benchmarks.rotary [--seeds N]`` prints the table; ``python -m benchmarks --only rotary`` saves
it as the section of BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np

from benchmarks.common import Row, Section, Table, markdown
from stewart_calib import io
from stewart_calib.analysis.accuracy import predicted_error
from stewart_calib.analysis.compensation import compensate
from stewart_calib.config import load_estimator_config
from stewart_calib.estimators.batch import BatchProblem, cramer_rao
from stewart_calib.instruments import gauge, registered
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import drive_model
from stewart_calib.model.rotations import motion_error
from stewart_calib.simulation import load_experiment, run_experiment
from stewart_calib.simulation.instrument import truth_in_gauge
from stewart_calib.workflows.calibration import run_calibration

METHODS = ("ls", "lm", "ekf", "isam2")
SEEDS = (20261201, 1, 2)
N_FRESH = 200
#: the fresh poses fill this fraction of the workspace box (the calibration poses: 80 %)
FRESH_FRACTION = 0.7


def errors(commanded, true, platform, poses: np.ndarray) -> tuple[float, float, float, float]:
    """Mean ``(motion mm, motion deg, absolute mm, absolute deg)`` of the ``true`` drive commanded with IK of
    ``commanded`` at home and at ``poses``."""
    desired = np.vstack([platform.workspace.home, poses])
    R_d, t_d = kin.pose_to_rt(desired)
    reached = true.forward_kinematics(true.inputs(compensate(commanded, desired, limits=platform)), guess=(R_d, t_d))
    motion_mm, motion_deg = motion_error(
        (R_d[0], t_d[0]), (R_d[1:], t_d[1:]), (reached.R[0], reached.t[0]), (reached.R[1:], reached.t[1:])
    )
    absolute_mm, absolute_deg = kin.pose_error(R_d[1:], t_d[1:], reached.R[1:], reached.t[1:])
    return tuple(float(np.mean(v)) for v in (motion_mm, motion_deg, absolute_mm, absolute_deg))


def run_seed(seed: int, quick: bool) -> dict:
    """One seed's errors ``{method | "nominal" | "bound": (motion mm, motion deg, absolute mm, absolute deg)}``
    and each method's seconds (``"seconds": {method: s}``)."""
    experiment = load_experiment("servo")
    if quick:
        experiment = replace(experiment, poses=replace(experiment.poses, calibration=40, validation=0))
    run = run_experiment(replace(experiment, seed=seed))
    platform = experiment.platform
    log = run.log.select(run.kinds == "calibration")
    nominal = drive_model(platform)
    legs = platform.drive
    true_params, _, _ = gauge.to_gauge(legs, run.truth.params[0])
    true = nominal.true_drive(true_params - legs.as_vector(), run.truth.drive_terms)
    ws = platform.workspace
    half = FRESH_FRACTION * np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
    poses = ws.home + np.random.default_rng(seed + 7).uniform(-1.0, 1.0, (N_FRESH, 6)) * half
    models, out = {"nominal": nominal}, {"seconds": {}}
    for method in METHODS:
        start = time.perf_counter()
        estimate = run_calibration(platform, log, method, load_estimator_config(None, [])).estimate
        out["seconds"][method] = time.perf_counter() - start
        models[method] = io.calibrated_drive(platform, io.result_dict(estimate, platform), method)
    # the poses every model commands (an edge pose may leave a horn of a calibrated model without an angle)
    R, t = kin.pose_to_rt(np.vstack([ws.home, poses]))
    reached = np.all(
        [np.all(np.isfinite(model.inverse_kinematics(R, t)), axis=-1) for model in models.values()], axis=0
    )
    if not reached[0]:
        raise RuntimeError(f"seed {seed}: a calibrated model cannot command home")
    poses = poses[reached[1:]]
    out.update({name: errors(model, true, platform, poses) for name, model in models.items()})
    out["poses"] = len(poses)
    # the bound at the truth in the gauge, the instrument's noise alone
    delta, unknowns = truth_in_gauge(legs, run.truth.params[0], run.robot.instrument.unknowns)
    at = registered(platform, log.strokes, log.readings)
    problem = BatchProblem.of_log(at, log.strokes, log.readings, log.t_s)
    x_drive = np.r_[delta, run.truth.drive_terms["stroke_scale"]]
    bound = predicted_error(platform, cramer_rao(problem, x_drive, unknowns), poses, ws.home)
    out["bound"] = (bound.motion_position_mm, bound.motion_orientation_deg, bound.position_mm, bound.orientation_deg)
    return out


def section(quick: bool = False, seeds: tuple[int, ...] = SEEDS) -> Section:
    runs = [run_seed(seed, quick) for seed in (seeds[:1] if quick else seeds)]
    names = ("bound", *METHODS, "nominal")
    mean = {name: np.mean([r[name] for r in runs], axis=0) for name in names}
    seconds = {m: float(np.mean([r["seconds"][m] for r in runs])) for m in METHODS}
    label = {"bound": "Cramér–Rao bound (instrument noise)", "nominal": "nominal model"}
    cells = [
        [
            label.get(name, name),
            f"{1000 * mean[name][0]:.0f} µm / {mean[name][1]:.3f}°",
            f"{mean[name][0] / mean['bound'][0]:.2f}",
            f"{mean[name][2]:.2f} mm / {mean[name][3]:.2f}°",
            f"{seconds[name]:.1f} s" if name in seconds else "",
        ]
        for name in names
    ]
    rows = [
        Row(
            f"{method}: motion from home within 1.5× the Cramér–Rao bound",
            f"{mean[method][0] / mean['bound'][0]:.2f}×",
            "≤ 1.5×",
            bool(mean[method][0] <= 1.5 * mean["bound"][0]),
            {"errors": mean[method].tolist(), "seconds": seconds[method]},
        )
        for method in METHODS
    ]
    raw = {
        "runs": [{k: (list(v) if isinstance(v, tuple) else v) for k, v in r.items()} for r in runs],
        "seeds": list(seeds),
    }
    note = __doc__.split("\n\n")[1].replace("\n", " ")
    table = Table(
        f"Mean over {len(runs)} seed(s), {min(r['poses'] for r in runs)}–{N_FRESH} fresh poses each "
        "(those every model commands)",
        ["model", "motion from home", "motion / bound", "absolute in {J}", "time"],
        cells,
    )
    return Section("The rotary (servo-horn) hexapod", note, rows, raw, [table])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=len(SEEDS))
    parser.add_argument("--quick", action="store_true")
    args = parser.parse_args()
    print(markdown(section(args.quick, SEEDS[: args.seeds])))


if __name__ == "__main__":
    main()
