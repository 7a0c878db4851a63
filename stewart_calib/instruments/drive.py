"""The platform pose as the drive puts it: forward kinematics with stroke scale, and its implicit
Jacobian with respect to the drive's unknowns.

A drive leg with stroke scale (spec §7)::

    r_i = ‖t + R d_i − j_i‖ − l_i − (1 + k_i) q_i = 0

FK solves ``r(ξ; M, k) = 0`` for the pose; by the implicit function theorem the pose moves with
the unknowns ``θ = (δM, k)`` as ``∂ξ/∂θ = −(∂r/∂ξ)⁻¹ ∂r/∂θ`` (body tangent ``ξ = [ω, v]``), where
``∂r/∂ξ`` is :func:`~stewart_calib.kinematics.leg_pose_jacobian`, ``∂r/∂M`` the leg rows of paper
eq. 8 (:func:`~stewart_calib.kinematics.leg_residual_jacobians`) and ``∂r_i/∂k_i = −q_i``.
"""

from __future__ import annotations

import numpy as np

from .. import kinematics as kin
from ..platform import LegGeometry


def scaled_strokes(strokes: np.ndarray, stroke_scale: np.ndarray) -> np.ndarray:
    """``(1 + k_i) q_i`` [mm]: the length change the logged strokes ``q_i`` really make."""
    return np.asarray(strokes, dtype=float) * (1.0 + np.asarray(stroke_scale, dtype=float))


def pose_jacobian(
    drive: LegGeometry, strokes: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(∂ξ/∂M (N, 6, 42), ∂ξ/∂k (N, 6, 6))`` at FK poses ``(R, t)`` of ``drive``.

    Args:
        strokes: ``(N, 6)`` the logged strokes q [mm] (``∂r_i/∂k_i = −q_i``).
    Raises:
        numpy.linalg.LinAlgError: a pose at a singularity of the drive (``∂r/∂ξ`` singular).
    """
    J_x, J_M = kin.leg_residual_jacobians(drive, R, t)
    J_k = -np.asarray(strokes, dtype=float)[..., None, :] * np.eye(6)
    dxi = -np.linalg.solve(J_x, np.concatenate([J_M, J_k], axis=-1))
    return dxi[..., :42], dxi[..., 42:]
