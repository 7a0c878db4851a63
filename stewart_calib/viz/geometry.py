"""A leg set drawn as lines: the points of each leg at a pose, for the rerun scene and the HTML report.

A prismatic leg is one segment, base joint ``j_i`` → platform joint ``t + R d_i``; a rotary leg
(spec §15) two, crank centre ``a_i`` → horn joint ``b_i`` (at the angle that closes the leg at the
pose) → platform joint. Lengths in mm, in {J}.
"""

from __future__ import annotations

import numpy as np

from ..instruments.gauge import joint_columns
from ..kinematics import transform_points
from ..platform import LegGeometry
from ..rotations import pose_to_rt
from .html_report import Robot


def leg_joints(legs) -> tuple[np.ndarray, np.ndarray]:
    """``(base-side points (L, 3) in {J}, platform joints (L, 3) in {D})`` [mm] of a leg set, the entries
    of its parameter vector that hold them (a prismatic leg's ``j_i`` and ``d_i``, a rotary leg's crank
    centre ``a_i`` and ``d_i``)."""
    M = legs.as_vector()
    base, platform = joint_columns(legs)
    return M[base].reshape(-1, 3), M[platform].reshape(-1, 3)


def leg_polylines(legs, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N·L, k, 3)`` each leg's polyline at each pose ``(R (N, 3, 3), t (N, 3))``, in {J} [mm]: base
    joint → platform joint of a prismatic leg (k = 2); a rotary leg's crank centre → horn joint →
    platform joint (k = 3). A rotary leg that cannot reach the pose has NaN horn joint."""
    base, platform = leg_joints(legs)
    platform_joints = transform_points(R, t, platform)
    points = [np.broadcast_to(base, platform_joints.shape), platform_joints]
    if type(legs) is not LegGeometry and legs.kind == "rotary":  # the horn between crank and rod
        points.insert(1, legs.horn_joints(legs.coordinates(R, t)))
    return np.stack(points, axis=-2).reshape(-1, len(points), 3)


def robot_at(platform, calibrated) -> Robot | None:
    """The :class:`~stewart_calib.viz.html_report.Robot` of ``platform``'s nominal drive and the
    ``calibrated`` legs (a leg model of the same kind) at the workspace's home, or without a
    ``[workspace]`` at the pose the nominal drive reaches for zero coordinates; None where a leg
    cannot reach that pose."""
    nominal = platform.drive
    if platform.workspace is not None:
        R, t = pose_to_rt(np.asarray(platform.workspace.home, dtype=float)[None])
        pose = "the workspace's home"
    else:
        fk = nominal.forward_kinematics(np.zeros((1, nominal.n_legs)), strict=False)
        if not np.all(fk.converged):
            return None
        R, t, pose = fk.R, fk.t, "zero stroke (or angle)"
    drawn = leg_polylines(nominal, R, t), leg_polylines(calibrated, R, t)
    if not all(np.all(np.isfinite(lines)) for lines in drawn):
        return None
    return Robot(nominal.kind, pose, *drawn, np.asarray(nominal.parameter_degrees, dtype=bool))
