"""Pose algebra: rotations, pose6 vectors and the body tangent; pure functions, mm and rad.

Conventions (spec §1, paper §3.1): a pose is the platform frame {D} in the base frame {J},
``(R, t)`` or a *pose6* ``[x, y, z [mm], roll, pitch, yaw [rad]]`` with
``R = Rz(yaw) Ry(pitch) Rx(roll)`` (paper eq. 20–21); perturbations are in the body tangent
``ξ = [ω, v]`` (rotation first, GTSAM's order). Nothing here knows about legs or platforms, so
every layer may use it (:mod:`stewart_calib.model.kinematics` re-exports it with the leg functions).
"""

from __future__ import annotations

import numpy as np

# ----------------------------------------------------------------------------- rotations


def rpy_to_rotation(rpy: np.ndarray) -> np.ndarray:
    """``R = Rz(γ) Ry(β) Rx(α)`` for ``rpy = [α, β, γ]`` [rad] (paper eq. 5, 20–21).

    Args:
        rpy: ``(..., 3)`` roll, pitch, yaw [rad].
    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    rpy = np.asarray(rpy, dtype=float)
    ca, cb, cg = np.cos(rpy[..., 0]), np.cos(rpy[..., 1]), np.cos(rpy[..., 2])
    sa, sb, sg = np.sin(rpy[..., 0]), np.sin(rpy[..., 1]), np.sin(rpy[..., 2])
    R = np.empty(rpy.shape[:-1] + (3, 3))
    R[..., 0, 0] = cb * cg
    R[..., 0, 1] = sa * sb * cg - sg * ca
    R[..., 0, 2] = sb * ca * cg + sa * sg
    R[..., 1, 0] = sg * cb
    R[..., 1, 1] = sa * sb * sg + ca * cg
    R[..., 1, 2] = sb * sg * ca - sa * cg
    R[..., 2, 0] = -sb
    R[..., 2, 1] = sa * cb
    R[..., 2, 2] = ca * cb
    return R


def rotation_to_rpy(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`rpy_to_rotation` for pitch in (−90°, 90°) [rad]."""
    R = np.asarray(R, dtype=float)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """``(..., 3)`` → ``(..., 3, 3)`` with ``skew(a) @ b = a × b``."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: ``(..., 3)`` rotation vector [rad] → ``(..., 3, 3)``."""
    omega = np.asarray(omega, dtype=float)
    theta2 = np.sum(omega * omega, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-12
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(omega)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle of a rotation ``(..., 3, 3)`` [rad], accurate near 0 and π."""
    R = np.asarray(R, dtype=float)
    # atan2(|axis·sinθ|, cosθ) keeps precision at small angles where arccos(trace) loses it.
    sin_part = 0.5 * np.linalg.norm(
        np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1),
        axis=-1,
    )
    cos_part = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    return np.arctan2(sin_part, cos_part)


# ----------------------------------------------------------------------------- poses


def pose_to_rt(pose6: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(..., 6)`` ``[x, y, z [mm], roll, pitch, yaw [rad]]`` → ``(R, t)``."""
    pose6 = np.asarray(pose6, dtype=float)
    return rpy_to_rotation(pose6[..., 3:]), pose6[..., :3].copy()


def rt_to_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(R, t)`` → ``(..., 6)`` ``[x, y, z [mm], roll, pitch, yaw [rad]]``."""
    return np.concatenate([np.asarray(t, dtype=float), rotation_to_rpy(R)], axis=-1)


def retract(R: np.ndarray, t: np.ndarray, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``R Exp(ω)``, ``t + R v`` for body tangent ``ξ = [ω, v]`` ``(..., 6)`` (``Pose3.retract`` to first order)."""
    xi = np.asarray(xi, dtype=float)
    return R @ so3_exp(xi[..., :3]), t + np.einsum("...ij,...j->...i", R, xi[..., 3:])


def transform_points(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map ``(..., K, 3)`` points of frame b into frame a with ``(R_a_b, t_a_b)``."""
    return np.einsum("...ij,...kj->...ki", R, points) + t[..., None, :]


def pose_error(R_desired, t_desired, R_actual, t_actual) -> tuple[np.ndarray, np.ndarray]:
    """Pose-error metrics in local coordinates (never raw Euler differences).

    Returns:
        ``(position_error_mm, orientation_error_deg)``: ``‖t_actual − t_desired‖`` [mm] and the
        rotation angle of ``R_desiredᵀ R_actual`` [deg], each of shape ``(...)``.
    """
    position_error_mm = np.linalg.norm(np.asarray(t_actual) - np.asarray(t_desired), axis=-1)
    relative = np.swapaxes(np.asarray(R_desired), -1, -2) @ np.asarray(R_actual)
    return position_error_mm, np.degrees(rotation_angle(relative))


def motion_error(desired_home, desired, reached_home, reached) -> tuple[np.ndarray, np.ndarray]:
    """The error of a motion from home (spec §15): :func:`pose_error` of ``T_home⁻¹ T`` reached against
    ``X_home⁻¹ X`` desired — the position of {D}'s origin and the rotation angle of the relative pose.

    Args:
        desired_home, reached_home: ``(R (3, 3), t (3,))`` the desired and the reached pose at home.
        desired, reached: ``(R (..., 3, 3), t (..., 3))`` the desired and the reached poses.
    Returns:
        ``(position_error_mm (...), orientation_error_deg (...))``.
    """

    def relative(home, pose):  # T_home⁻¹ T
        (R_h, t_h), (R, t) = home, pose
        return np.swapaxes(R_h, -1, -2) @ R, np.einsum("ji,...j->...i", R_h, np.asarray(t) - t_h)

    return pose_error(*relative(desired_home, desired), *relative(reached_home, reached))
