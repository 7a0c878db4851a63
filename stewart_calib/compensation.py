"""Compensation (paper Fig. 3 step 4): command strokes from IK with the estimated model.

The controller's nominal IK misses because the real drive is ``M + δM``; commanding
``IK_{M + δM̂}(pose)`` instead puts the real robot at the desired pose to the extent that
``δM̂ = δM``.
"""

from __future__ import annotations

import numpy as np

from . import kinematics as kin
from .errors import CalibError
from .estimate import Estimate
from .platform import LegGeometry, Platform


def compensate(
    estimate_or_drive: Estimate | LegGeometry,
    desired_poses: np.ndarray,
    nominal: Platform | LegGeometry | None = None,
) -> np.ndarray:
    """Strokes that put the estimated drive at ``desired_poses``.

    Args:
        estimate_or_drive: the drive geometry ``M + δM`` itself, or an :class:`Estimate`
            (then ``nominal`` supplies ``M``).
        desired_poses: ``(N, 6)`` ``[x, y, z [mm], roll, pitch, yaw [rad]]`` (or ``(6,)``).
        nominal: the platform or nominal drive; required with an :class:`Estimate`.
    Returns:
        ``(N, 6)`` strokes q_i [mm] (same leading shape as ``desired_poses``).
    Raises:
        CalibError: an Estimate without ``nominal``, or non-finite poses.
    """
    if isinstance(estimate_or_drive, Estimate):
        if nominal is None:
            raise CalibError("compensate: an Estimate needs the nominal platform to build M + δM")
        drive = estimate_or_drive.drive(nominal)
    else:
        drive = estimate_or_drive
    poses = np.asarray(desired_poses, dtype=float)
    if poses.shape[-1:] != (6,) or not np.all(np.isfinite(poses)):
        raise CalibError(f"compensate: expected finite poses of shape (N, 6), got shape {poses.shape}")
    return kin.inverse_kinematics(drive, *kin.pose_to_rt(poses))
