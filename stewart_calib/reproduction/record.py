"""reproduce.rrd: the reproduction as one rerun recording (entity paths of :mod:`stewart_calib.viz.recording`).

* 3D scene (``world/…``) of the :data:`SCENE_METHOD` run, decimated to keep the file small: one
  row per held static pose (its last sample) and every :data:`SCENE_CIRCLE_STRIDE`-th circle
  point; the drive legs drawn are the true unloaded ones (load drift is sub-mm, invisible here).
* ``params/leg{i}/{field}/{method}`` — δM the controller used, per method, and the truth's δM in
  force (pose- and load-dependent) of the scene run (Figs. 5–6), every :func:`parameter_stride`-th
  sample: 42 × 5 full-rate series of the paper run alone would take ~15 MB.
* ``params/leg{i}/{field}/{method}/upper|lower`` — the ±σ band of each method's δM, same rows;
  ``diagnostics/{method}/…`` — drive-leg residuals at the tracker's pose with the δM after each
  sample and (online methods) before it, and the NIS of the Kalman methods, same rows.
* ``errors/position_mm|orientation_deg/{method}`` — true pose error of every sample (Fig. 7);
  ``nominal`` is left out: its ~3 mm would flatten the others' curves.
* ``trajectories/{stage}/{method}`` and ``polar/{stage}/{method}`` — every circle point, desired
  vs actual (truth view), per stage and method, plus ``nominal`` at the first stage (Figs. 8–9).
* A blueprint with tabs: scene, parameters per method, pose errors, trajectories, diagnostics per method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model import kinematics as kin
from ..model.platform import LegGeometry, Platform
from ..viz import recording as viz
from .metrics import held_pose_ends
from .runs import BATCH_METHOD, NOMINAL, MethodRun, Reproduction, parameter_stride

SCENE_METHOD = "isam2"
SCENE_CIRCLE_STRIDE = 5
#: polar plot (Fig. 9): radius = base + gain · deviation [mm]; the base keeps 0 mm off the centre.
POLAR_BASE_RADIUS_MM = 0.5
POLAR_GAIN = 1.0


def entity_name(run: str) -> str:
    """The recording's name of a run (``paper-ekf`` → ``paper_ekf``, as viz's colours expect;
    ``ekf+tracker`` → ``ekf_tracker``)."""
    return run.replace("-", "_").replace("+", "_")


def scene_rows(reproduction: Reproduction) -> np.ndarray:
    """Sample indices of the decimated 3D scene (see the module docstring)."""
    result = reproduction.runs[SCENE_METHOD].result
    ends = held_pose_ends(result)
    circle = result.kinds == "circle"
    return np.flatnonzero((ends & ~circle) | (circle & (result.pose_index % SCENE_CIRCLE_STRIDE == 0)))


def write_recording(path: str | Path, reproduction: Reproduction) -> None:
    """Write the whole recording to ``path``."""
    platform = reproduction.platform
    nominal = platform.drive.as_vector()
    scene = reproduction.runs[SCENE_METHOD].result
    with viz.open_recording(path) as rec:
        viz.log_platform_geometry(rec, platform)
        rows = scene_rows(reproduction)
        R, t = kin.pose_to_rt(scene.actual_poses[rows])
        viz.log_platform_pose(
            rec,
            platform,
            R,
            t,
            scene.log.t_s[rows],
            samples=rows,
            drive_legs=LegGeometry.from_params(scene.robot.base_params),
            desired=kin.pose_to_rt(scene.desired_poses[rows]),
        )
        kept = np.arange(0, len(scene.log), parameter_stride(len(scene.log)))
        viz.log_parameters(rec, viz.TRUTH, scene.truth.params[kept] - nominal, scene.log.t_s[kept], samples=kept)
        diagnostics = {}
        for method in reproduction.calibrated:
            run = reproduction.runs[method]
            result = run.result
            name, t_kept = entity_name(method), result.log.t_s[kept]
            viz.log_parameters(rec, name, run.trace[kept], t_kept, samples=kept)
            if run.stddev is not None:  # every method's run has σ (the nominal run has none)
                viz.log_parameter_band(rec, name, run.trace[kept], run.stddev[kept], t_kept, samples=kept)
            series = _diagnostics(platform, run, kept, online=method != BATCH_METHOD)
            viz.log_diagnostics(rec, name, t_kept, *series, samples=kept)
            diagnostics[name] = {
                kind for kind, values in zip(viz.DIAGNOSTICS, series, strict=True) if values is not None
            }
            R_d, t_d = kin.pose_to_rt(result.desired_poses)
            R_a, t_a = kin.pose_to_rt(result.actual_poses)
            viz.log_pose_errors(rec, entity_name(method), result.log.t_s, *kin.pose_error(R_d, t_d, R_a, t_a))
        first_stage = reproduction.stage_names[0]
        runs = ((NOMINAL, [first_stage]), *((m, reproduction.stage_names) for m in reproduction.calibrated))
        for method, stages in runs:
            result = reproduction.runs[method].result
            for stage in stages:
                circle = (result.stages == stage) & (result.kinds == "circle")
                viz.log_trajectory(
                    rec,
                    stage,
                    entity_name(method),
                    result.desired_poses[circle, :3],
                    result.actual_poses[circle, :3],
                    POLAR_BASE_RADIUS_MM,
                    POLAR_GAIN,
                )
        viz.send_blueprint(
            rec,
            platform.drive.n_legs,
            [entity_name(m) for m in reproduction.calibrated],
            reproduction.stage_names,
            diagnostics,
        )


def _diagnostics(
    platform: Platform, run: MethodRun, kept: np.ndarray, online: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """``(residual, innovation or None, NIS or None)`` at the rows ``kept``: the drive-leg residuals
    at the tracker's pose of each sample with the δM in force after it and (online) before it."""
    log = run.result.log
    poses = kin.forward_kinematics(platform.required_tracker("the diagnostics"), log.readings[kept], strict=False)
    nominal = platform.drive.as_vector()
    after = kin.leg_residuals_per_sample(nominal + run.trace[kept], poses.R, poses.t, log.strokes[kept])
    innovation = None
    if online:
        before = np.vstack([np.zeros_like(run.trace[:1]), run.trace[:-1]])[kept]  # the model when the sample came
        innovation = kin.leg_residuals_per_sample(nominal + before, poses.R, poses.t, log.strokes[kept])
    return after, innovation, None if run.nis is None else run.nis[kept]
