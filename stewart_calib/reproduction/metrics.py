"""The numbers of Tables 4–6 from the runs: pose errors in two views, per stage and segment.

Views of the pose error (``position`` [mm], rotation angle [deg], in local coordinates):

* ``tracker`` — the tracker's FK pose (its readings on the platform file's tracker geometry)
  against the desired pose: the paper's measure (§4.1, the in-situ tracker is the reference);
* ``truth`` — the simulator's actual pose against the desired pose.

They differ by the tracker's own error: its geometry residual (``[tracker]
geometry_residual_mm``) is systematic, no drive model can compensate it, and it puts a floor
of about the tracker's accuracy (~0.05 mm) under every method's truth view.

One value per held pose: the **last sample** of each static pose (after settling: an online
method has folded in the pose's earlier samples, as the paper's EKF corrects at each pose) and
each circle point (one sample per point, so an online model there is one point old).
"""

from __future__ import annotations

import numpy as np

from ..instruments import gauge
from ..model import kinematics as kin
from ..model.platform import Platform
from ..simulation import SimulationResult

VIEWS = ("tracker", "truth")
#: segment kinds evaluated: validation poses (Table 5) and the circle (Table 6).
EVALUATED = ("validation", "circle")


def held_pose_ends(result: SimulationResult) -> np.ndarray:
    """``(N,)`` True at the last sample of each held pose (static pose or circle point)."""
    keys = (result.stages, result.kinds, result.pose_index)
    changes = np.zeros(len(result.kinds), dtype=bool)
    for key in keys:
        changes[:-1] |= key[1:] != key[:-1]
    changes[-1] = True
    return changes


def view_errors(result: SimulationResult, platform: Platform) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per view, per sample ``(position error [mm], orientation error [deg])`` against the desired pose."""
    R_d, t_d = kin.pose_to_rt(result.desired_poses)
    R_a, t_a = kin.pose_to_rt(result.actual_poses)
    seen = kin.forward_kinematics(platform.required_tracker("the tracker view"), result.log.readings, guess=(R_d, t_d))
    return {
        "tracker": kin.pose_error(R_d, t_d, seen.R, seen.t),
        "truth": kin.pose_error(R_d, t_d, R_a, t_a),
    }


def tracker_own_error(result: SimulationResult, platform: Platform) -> dict[str, float]:
    """The tracker's own error at the held poses: its FK pose against the true pose, as means
    ``{position_mm, orientation_deg}`` — invisible in the tracker view, a floor under the truth view."""
    ends = held_pose_ends(result)
    R_a, t_a = kin.pose_to_rt(result.actual_poses[ends])
    seen = kin.forward_kinematics(
        platform.required_tracker("the tracker's own error"), result.log.readings[ends], guess=(R_a, t_a)
    )
    position, orientation = kin.pose_error(R_a, t_a, seen.R, seen.t)
    return {"position_mm": float(position.mean()), "orientation_deg": float(orientation.mean())}


def tracker_gauge_error(result: SimulationResult, platform: Platform) -> dict[str, float]:
    """What the truth view charges a perfect identification of drive and tracker, as means
    ``{position_mm, orientation_deg}`` over the held poses.

    A rigid motion of all base joints (drive and tracker together), or of all platform joints,
    changes no stroke and no reading: no data can tell where {J} and {D} are. With the tracker's
    geometry identified its joints hold that gauge (docs/architecture.md "Gauge"): {J} and {D} are
    the frames where its joints' mean rigid motion is nominal, to first order where the true
    joints best fit the nominal ones (Kabsch, ``T_J``, ``T_D``). The simulator's frames differ
    from those by the rigid part of the tracker's residual, so a pose ``X`` that is exact in them
    is ``T_J⁻¹ X T_D`` in the simulator's frames: this error is part of every truth-view number.
    """
    simulated, nominal = result.robot.tracker, platform.required_tracker("the tracker's gauge error")
    if simulated is None:
        raise ValueError("the simulated robot has no tracker: its platform has none")
    true_tracker = simulated.geometry
    true_M, nominal_M = true_tracker.as_vector(), nominal.as_vector()
    (R_J, t_J), (R_D, t_D) = (  # base joints, then platform joints
        gauge.kabsch(true_M[columns].reshape(-1, 3), nominal_M[columns].reshape(-1, 3))
        for columns in gauge.joint_columns(nominal)
    )
    R, t = kin.pose_to_rt(result.actual_poses[held_pose_ends(result)])
    # X' = T_J X T_D⁻¹: the true pose written in the frames the tracker's joints define
    R_gauge = R_J @ R @ R_D.T
    t_gauge = (R_J @ t[..., None])[..., 0] + t_J - (R_gauge @ t_D[:, None])[..., 0]
    position, orientation = kin.pose_error(R, t, R_gauge, t_gauge)
    return {"position_mm": float(position.mean()), "orientation_deg": float(orientation.mean())}


def stage_metrics(result: SimulationResult, platform: Platform, errors=None) -> dict:
    """``{stage: {segment: {view: {position_mm, orientation_deg, max_position_mm, poses}}}}``.

    Means over the held poses of the segment (see the module docstring); ``poses`` counts them.
    """
    errors = errors or view_errors(result, platform)
    ends = held_pose_ends(result)
    metrics: dict = {}
    for stage in dict.fromkeys(result.stages):
        for segment in EVALUATED:
            mask = ends & (result.stages == stage) & (result.kinds == segment)
            if not mask.any():
                continue
            metrics.setdefault(stage, {})[segment] = {
                view: {
                    "position_mm": float(position[mask].mean()),
                    "orientation_deg": float(orientation[mask].mean()),
                    "max_position_mm": float(position[mask].max()),
                    "poses": int(mask.sum()),
                }
                for view, (position, orientation) in errors.items()
            }
    return metrics


def improvement_pct(value: float, reference: float) -> float:
    """How much smaller ``value`` is than ``reference``, in % of ``reference``."""
    return 100.0 * (1.0 - value / reference)


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))
