"""SO(3) and SE(3) pieces the instrument models need, vectorised numpy, GTSAM conventions.

Tangent order is GTSAM's ``Pose3``: ``ξ = [ω, v]``, rotation first, body frame, and a pose is
perturbed as ``R Exp(ω)``, ``t + R v`` (:func:`stewart_calib.model.kinematics.retract`).
"""

from __future__ import annotations

import numpy as np

from ..model.rotations import pose_to_rt, skew


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector ``φ`` with ``Exp(φ) = R``, ``(..., 3)`` [rad], accurate near 0 (and up to π)."""
    R = np.asarray(R, dtype=float)
    axis_sin = 0.5 * np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1
    )
    sin_theta = np.linalg.norm(axis_sin, axis=-1)
    cos_theta = 0.5 * (np.trace(R, axis1=-2, axis2=-1) - 1.0)
    theta = np.arctan2(sin_theta, cos_theta)
    small = sin_theta < 1e-9
    scale = np.where(small, 1.0 + theta**2 / 6.0, theta / np.where(small, 1.0, sin_theta))
    phi = axis_sin * scale[..., None]
    near_pi = small & (cos_theta < 0)
    if np.any(near_pi):  # sin θ ≈ 0 at θ ≈ π: the axis from the symmetric part R + Rᵀ = 2 a aᵀ − ... instead
        B = 0.5 * (R[near_pi] + np.swapaxes(R[near_pi], -1, -2)) + np.eye(3)
        column = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), axis=-1)
        axis = B[np.arange(len(B)), :, column]
        phi[near_pi] = np.pi * axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    return phi


def so3_right_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """``J_r⁻¹(φ)``: ``Log(Exp(φ) Exp(δ)) ≈ φ + J_r⁻¹(φ) δ``, ``(..., 3, 3)``."""
    phi = np.asarray(phi, dtype=float)
    theta2 = np.sum(phi * phi, axis=-1)[..., None, None]
    theta = np.sqrt(theta2)
    small = theta2 < 1e-8
    safe = np.where(small, 1.0, theta)
    coef = np.where(
        small, 1.0 / 12.0 + theta2 / 720.0, 1.0 / safe**2 - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe))
    )
    K = skew(phi)
    return np.eye(3) + 0.5 * K + coef * (K @ K)


def adjoint(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``Ad_T`` in the ``[ω, v]`` order: ``T Exp(ξ) T⁻¹ = Exp(Ad_T ξ)``, ``(..., 6, 6)``."""
    R = np.asarray(R, dtype=float)
    Ad = np.zeros(R.shape[:-2] + (6, 6))
    Ad[..., :3, :3] = R
    Ad[..., 3:, 3:] = R
    Ad[..., 3:, :3] = skew(t) @ R
    return Ad


def inverse(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``T⁻¹`` of ``(R, t)``."""
    Rt = np.swapaxes(R, -1, -2)
    return Rt, -np.einsum("...ij,...j->...i", Rt, t)


def compose(
    R_a_b: np.ndarray, t_a_b: np.ndarray, R_b_c: np.ndarray, t_b_c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``T_a_c = T_a_b T_b_c`` (broadcasting)."""
    return R_a_b @ R_b_c, t_a_b + np.einsum("...ij,...j->...i", R_a_b, t_b_c)


def project_to_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation nearest to ``M`` in the Frobenius norm (SVD, determinant +1), ``(..., 3, 3)``."""
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


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
