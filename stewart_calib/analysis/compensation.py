"""Compensation (paper Fig. 3 step 4): command strokes from IK with the estimated model.

The controller's nominal IK misses because the real drive is ``M + δM``; commanding
``IK_{M + δM̂}(pose)`` instead puts the real robot at the desired pose to the extent that
``δM̂ = δM``.
"""

from __future__ import annotations

import numpy as np

from ..errors import CalibError
from ..estimate import Estimate
from ..model import kinematics as kin
from ..model.drive import DriveModel, drive_model, plain_drive
from ..model.platform import LegGeometry, Platform
from ..samples import Inputs


class PoseOutOfRange(CalibError):
    """A desired pose lies outside the platform's workspace box or needs a stroke outside its
    stroke range; nothing is returned.

    Attributes:
        pose_index: 0-based index of the first such pose in the request.
        reason: what is out of range, in words (callers prefix where: a file row, an API call).
    """

    def __init__(self, pose_index: int, reason: str):
        self.pose_index, self.reason = pose_index, reason
        super().__init__(f"pose {pose_index}: {reason}")


_AXES = ("x", "y", "z", "roll", "pitch", "yaw")


def check_reachable(poses_mm_rad: np.ndarray, strokes_mm: np.ndarray, platform: Platform) -> None:
    """Refuse the first pose outside ``platform.workspace`` (± limits about home per axis), one a leg
    cannot reach (its stroke NaN: a rotary drive's horn and rod do not close, or no horn solution is in
    its angle range) or whose strokes leave ``platform.coordinate_range`` (inclusive: the stroke range,
    a rotary drive's commanded angles' range); limits the platform lacks are not checked.

    Raises:
        PoseOutOfRange: naming the pose, the axis or leg, the value and the limits.
    """
    poses = np.asarray(poses_mm_rad, dtype=float).reshape(-1, 6)
    ws = platform.workspace
    if ws is not None:
        offset = poses - ws.home
        offset[:, 3:] = (offset[:, 3:] + np.pi) % (2 * np.pi) - np.pi
        limit = np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
        bad = np.argwhere(np.abs(offset) > limit * (1 + 1e-12))
        if bad.size:
            k, axis = (int(v) for v in bad[0])
            if axis < 3:
                reason = (
                    f"{_AXES[axis]} = {poses[k, axis]:.6g} mm is {offset[k, axis]:+.6g} mm from home, beyond the "
                    f"workspace's ±{ws.translation_limit:g} mm"
                )
            else:
                reason = (
                    f"{_AXES[axis]} = {poses[k, axis]:.6g} rad ({np.degrees(poses[k, axis]):.4g}°) is beyond the "
                    f"workspace's ±{np.degrees(ws.rotation_limit):.4g}° about home (angles in rad, not degrees?)"
                )
            raise PoseOutOfRange(k, reason)
    strokes = np.asarray(strokes_mm, dtype=float).reshape(-1, platform.drive.n_legs)
    bad = np.argwhere(~np.isfinite(strokes))
    if bad.size:
        k, i = (int(v) for v in bad[0])
        raise PoseOutOfRange(k, f"leg {i + 1} cannot reach the pose (no coordinate of it closes the leg in range)")
    bounds = platform.coordinate_range
    if bounds is not None:
        unit = platform.drive.coordinate_unit
        to_file = np.degrees if unit == "deg" else np.asarray  # a rotary drive's commanded angles [rad] → deg
        lo, hi = (float(v) for v in to_file(bounds))
        bad = np.argwhere((strokes < bounds[0]) | (strokes > bounds[1]))
        if bad.size:
            k, i = (int(v) for v in bad[0])
            raise PoseOutOfRange(
                k,
                f"the pose needs q{i + 1}_{unit} = {float(to_file(strokes[k, i])):.6g}, outside the "
                f"{'stroke' if unit == 'mm' else 'angle'} range [{lo}, {hi}] {unit}",
            )


def compensate(
    drive: DriveModel | Estimate | LegGeometry,
    desired_poses_mm_rad: np.ndarray,
    nominal: Platform | LegGeometry | None = None,
    limits: Platform | None = None,
    inputs: Inputs | None = None,
) -> np.ndarray:
    """Strokes that put the estimated drive at ``desired_poses_mm_rad`` under the input channels
    ``inputs`` (an elastic drive: its platform's weight and the payload ``load_kg``, spec §10; a
    thermal one: the legs' ``temperature_C``, spec §17).

    Args:
        drive: the calibrated drive model (:meth:`~stewart_calib.model.drive.DriveModel.calibrated`),
            an :class:`Estimate` (then ``nominal`` supplies ``M`` and the drive's nominal terms,
            which the estimate's identified blocks replace), or legs ``M + δM`` alone (their
            strokes are their length changes).
        desired_poses_mm_rad: ``(N, 6)`` ``[x, y, z [mm], roll, pitch, yaw [rad]]`` (or ``(6,)``).
        nominal: the platform or nominal drive; required with an :class:`Estimate`.
        limits: the platform whose workspace and stroke range the poses and strokes must
            respect (:func:`check_reachable`), or None for no check.
        inputs: the channels at the poses, each a scalar or ``(N, ...)``
            (:data:`~stewart_calib.samples.CHANNEL_SHAPES`; None: none, 0 kg at the reference
            temperature). An elastic drive's legs are ``c_i f_i / 1000`` shorter under the forces
            ``f`` they hold under the payload, so the strokes are longer by that over ``1 + k_i``; a
            warm leg is longer by ``α_i ΔT_i L_i``, so its stroke is shorter. A drive without the
            term ignores its channel.
    Returns:
        ``(N, legs)`` strokes q_i [mm] (same leading shape as ``desired_poses_mm_rad``).
    Raises:
        PoseOutOfRange: see :func:`check_reachable` (a roll of 5 meant as degrees, given
            to this radian argument, is refused here).
        CalibError: an Estimate without ``nominal``, or non-finite poses.
    """
    if isinstance(drive, Estimate):
        if nominal is None:
            raise CalibError("compensate: an Estimate needs the nominal platform to build M + δM")
        drive = (drive_model(nominal) if isinstance(nominal, Platform) else plain_drive(nominal)).calibrated_by(drive)
    elif not isinstance(drive, DriveModel):  # a leg model alone
        drive = plain_drive(drive)
    poses = np.asarray(desired_poses_mm_rad, dtype=float)
    if poses.shape[-1:] != (6,) or not np.all(np.isfinite(poses)):
        raise CalibError(f"compensate: expected finite poses of shape (N, 6), got shape {poses.shape}")
    strokes = drive.inverse_kinematics(*kin.pose_to_rt(poses), channels=inputs)
    if limits is not None:
        check_reachable(poses, strokes, limits)
    return strokes
