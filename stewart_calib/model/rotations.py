"""Pose algebra, the package's one SO(3)/SE(3) module: rotations, quaternions, pose6 vectors and
the body tangent; pure vectorised numpy, mm and rad.

Conventions (spec §1, paper §3.1): a pose is the platform frame {D} in the base frame {J},
``(R, t)`` or a *pose6* ``[x, y, z [mm], roll, pitch, yaw [rad]]`` with
``R = Rz(yaw) Ry(pitch) Rx(roll)`` (paper eq. 20–21); perturbations are in the body tangent
``ξ = [ω, v]`` (rotation first, GTSAM's ``Pose3`` order), a pose perturbed as ``R Exp(ω)``,
``t + R v`` (:func:`retract`). Nothing here knows about legs, platforms or instruments, so every
layer may use it (:mod:`stewart_calib.model.kinematics` re-exports part of it with the leg
functions). The compiled kernels (``model/_kernels.py``, ``factors/_kernels.py``) write the same
formulas per pose for numba and name the function here that each one follows.

Reference: J. Solà, J. Deray, D. Atchuthan, "A micro Lie theory for state estimation in
robotics" (2018), appendices on SO(3) (``Exp``, ``Log``, ``J_r⁻¹``) and SE(3) (``Ad``, there in
the ``[v, ω]`` order: its blocks swap places here).
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


def _angle(phi: np.ndarray, series_below: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(θ², θ, θ² < series_below)`` of rotation vectors ``(..., 3)``, each ``(..., 1, 1)`` to scale
    3 × 3 matrices; ``θ`` is 1 where the series is used, so the closed form never divides by 0."""
    theta2 = np.sum(phi * phi, axis=-1)[..., None, None]
    small = theta2 < series_below
    return theta2, np.where(small, 1.0, np.sqrt(theta2)), small


def so3_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues: ``(..., 3)`` rotation vector [rad] → ``(..., 3, 3)``."""
    omega = np.asarray(omega, dtype=float)
    theta2, safe, small = _angle(omega, 1e-12)
    a = np.where(small, 1.0 - theta2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    K = skew(omega)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_axis_sin(R: np.ndarray) -> np.ndarray:
    """``sin θ · a`` of a rotation by ``θ`` about the unit axis ``a``: the vector of ``(R − Rᵀ) / 2``,
    ``(..., 3, 3)`` → ``(..., 3)``; exact in ``R`` (no trigonometry), and 0 at θ = 0 and θ = π."""
    R = np.asarray(R, dtype=float)
    return 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1
    )


def _sin_cos(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(sin θ · a, sin θ, cos θ)`` of rotations ``(..., 3, 3)``: the axis part, its norm, and
    ``(tr R − 1) / 2``."""
    axis_sin = rotation_axis_sin(R)
    return axis_sin, np.linalg.norm(axis_sin, axis=-1), 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle of a rotation ``(..., 3, 3)`` [rad], accurate near 0 and π."""
    # atan2(|axis·sinθ|, cosθ) keeps precision at small angles where arccos(trace) loses it.
    _, sin_theta, cos_theta = _sin_cos(np.asarray(R, dtype=float))
    return np.arctan2(sin_theta, cos_theta)


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``φ`` with ``Exp(φ) = R`` (inverse of :func:`so3_exp`), ``(..., 3)`` [rad],
    accurate near 0 (and up to π)."""
    R = np.asarray(R, dtype=float)
    axis_sin, sin_theta, cos_theta = _sin_cos(R)
    theta = np.arctan2(sin_theta, cos_theta)
    small = sin_theta < 1e-9
    scale = np.where(small, 1.0 + theta**2 / 6.0, theta / np.where(small, 1.0, sin_theta))
    phi = axis_sin * scale[..., None]
    near_pi = small & (cos_theta < 0)
    if np.any(near_pi):  # sin θ ≈ 0 at θ ≈ π: the axis from the symmetric part (R + Rᵀ)/2 + I = 2 a aᵀ instead
        B = 0.5 * (R[near_pi] + np.swapaxes(R[near_pi], -1, -2)) + np.eye(3)
        column = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(len(B)), :, column]
        phi[near_pi] = np.pi * axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return phi


def so3_right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r⁻¹(φ)``: ``Log(Exp(φ) Exp(δ)) ≈ φ + J_r⁻¹(φ) δ``, ``(..., 3)`` [rad] → ``(..., 3, 3)``."""
    phi = np.asarray(phi, dtype=float)
    theta2, safe, small = _angle(phi, 1e-8)
    coef = np.where(
        small, 1.0 / 12.0 + theta2 / 720.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe))
    )
    K = skew(phi)
    return np.eye(3) + 0.5 * K + coef * (K @ K)


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (SVD, determinant +1), ``(..., 3, 3)``."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def quaternion_to_rotation(q: np.ndarray, order: str) -> np.ndarray:
    """``(..., 4)`` quaternions in ``order`` (``"wxyz"``, scalar first, or ``"xyzw"``, scalar last as
    ROS, rerun and Motive write them) → ``(..., 3, 3)`` rotations; ``q`` is normalised first, and
    ``q`` and ``−q`` give the same rotation (Hamilton's convention, as scipy's ``Rotation``)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = (q[..., order.index(axis)] for axis in "wxyz")
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, :] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1)
    R[..., 1, :] = np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1)
    R[..., 2, :] = np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1)
    return R


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


def inverse(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T⁻¹`` of ``(R, t)``: ``(Rᵀ, −Rᵀ t)``."""
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -np.einsum("...ij,...j->...i", Rt, t)


def compose(
    R_a_b: np.ndarray, t_a_b: np.ndarray, R_b_c: np.ndarray, t_b_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``T_a_c = T_a_b T_b_c`` (broadcasting)."""
    return R_a_b @ R_b_c, t_a_b + np.einsum("...ij,...j->...i", R_a_b, t_b_c)


def adjoint(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``Ad_T = [[R, 0], [[t]× R, R]]`` in the ``[ω, v]`` order: ``T Exp(ξ) T⁻¹ = Exp(Ad_T ξ)``, ``(..., 6, 6)``."""
    R = np.asarray(R, dtype=float)
    Ad = np.zeros(R.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., 3:, :3] = skew(t) @ R
    return Ad


def pose6_tangent_jacobian(pose6: np.ndarray) -> np.ndarray:
    """``∂ pose6 / ∂ξ`` at ``ξ = 0`` for the body perturbation ``R Exp(ω)``, ``t + R v``, ``(..., 6, 6)``.

    ``pose6 = [x, y, z, roll, pitch, yaw]``: ``δt = R v`` and, with the base-frame rate
    ``R ω = T δθ`` (paper eq. 4–5: ``T = [[cβ cγ, −sγ, 0], [cβ sγ, cγ, 0], [−sβ, 0, 1]]``),
    ``δθ = T⁻¹ R ω``. Used to carry a tangent covariance into file coordinates.
    """
    pose6 = np.asarray(pose6, dtype=float)
    R, _ = pose_to_rt(pose6)
    cb, sb = np.cos(pose6[..., 4]), np.sin(pose6[..., 4])
    cg, sg = np.cos(pose6[..., 5]), np.sin(pose6[..., 5])
    T = np.zeros(pose6.shape[:-1] + (3, 3))
    T[..., 0, 0], T[..., 0, 1] = cb * cg, -sg
    T[..., 1, 0], T[..., 1, 1] = cb * sg, cg
    T[..., 2, 0], T[..., 2, 2] = -sb, 1.0
    J = np.zeros(pose6.shape[:-1] + (6, 6))
    J[..., :3, 3:] = R
    J[..., 3:, :3] = np.linalg.solve(T, R)
    return J


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
