"""Tracker-leg factor (tight coupling): one grating reading constrains the pose alone.

Residual of tracker leg i with known geometry (paper Table 2)::

    r_i = ‖t + R h_i − z_i‖ − (ls_i + s_i)

No forward kinematics: each reading is its own factor, so a robust kernel down-weights a
single bad reading rather than the whole sample. Same geometry as the drive leg
(:func:`stewart_calib.kinematics.leg_residual`) with nothing to estimate.
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from ..kinematics import leg_residual


def residual(
    R: np.ndarray, t: np.ndarray, tracker_leg: np.ndarray, reading_mm: float, jacobians: bool = False
) -> tuple[float, np.ndarray | None]:
    """Tracker-leg residual ``r_i`` [mm] and, if asked, ``∂r/∂ξ`` ``(6,)`` (ξ = [ω, v]).

    Args:
        R, t: platform pose ``(3, 3)``, ``(3,)`` [mm].
        tracker_leg: ``(7,)`` ``[z_i | h_i | ls_i]`` [mm].
        reading_mm: grating reading s_i [mm].
    """
    r, H_pose, _ = leg_residual(R, t, tracker_leg, reading_mm, jacobians)
    return r, H_pose


def _error(tracker_leg: np.ndarray, reading_mm: float, this: gtsam.CustomFactor, values: gtsam.Values, H):
    pose = values.atPose3(this.keys()[0])
    r, H_pose = residual(pose.rotation().matrix(), pose.translation(), tracker_leg, reading_mm, H is not None)
    if H is not None:
        H[0] = H_pose.reshape(1, 6)
    return np.array([r])


def factor(pose_key: int, tracker_leg: np.ndarray, reading_mm: float, noise: gtsam.noiseModel.Base) -> gtsam.CustomFactor:
    """A unary ``CustomFactor`` on ``Pose3 pose_key`` for one reading."""
    return gtsam.CustomFactor(noise, [pose_key], partial(_error, np.array(tracker_leg, dtype=float), float(reading_mm)))
