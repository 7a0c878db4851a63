"""numba kernels behind the factors' ``gtsam.CustomFactor`` callbacks.

iSAM2 linearises every measurement factor about twice (when it enters and when its pose is
relinearised), two factors a sample: tens of thousands of callbacks a log. Written with numpy,
one callback makes ~10 small arrays (fancy indexing, ``np.put``, ``np.zeros``, the rotation and
translation apart) around a compiled core. Here each callback is one compiled call from what
gtsam hands over (the pose as ``Pose3.matrix()``, the unknown vector) to the arrays it takes
back: a linearisation in 0.4× (drive legs) and 0.35× (tracker) the numpy one's time, gtsam's own
part included. The arithmetic is :func:`stewart_calib.model.kinematics.leg_residual`'s (the same kernel,
:func:`stewart_calib.model._kernels.leg_rows`), so the numbers are bit for bit the same.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .._jit import F8_1, F8_2, F8_2F, I8_1, I8_2, Tuple, njit
from ..model._kernels import _adjoint, _rotation, _tangent_from_pose6, leg_rows

# as stewart_calib.model._kernels: x / 0 gives inf/NaN as numpy does
_JIT: dict[str, Any] = {"nogil": True, "error_model": "numpy"}


@njit(entry=(F8_2F, F8_1, I8_1, F8_2, I8_2, Tuple((I8_1, F8_1, F8_1, F8_2, I8_2)), F8_1), **_JIT)
def drive_leg_rows(pose, unknowns, legs_of, nominal, columns, terms, inputs):
    """Drive-leg residuals of ``k`` legs and their Jacobians on the pose and the unknown vector.

    Args:
        pose: ``(4, 4)`` homogeneous pose of {D} in {J} [mm] (``Pose3.matrix()``).
        unknowns: ``(size,)`` the unknown vector (the drive's ``x_drive`` first).
        legs_of: ``(k,)`` the rows' leg indices (0…5 on a six-legged drive).
        nominal: ``(k, 7)`` nominal ``[j_i | d_i | l_i]`` [mm]; columns: ``(k, 7)`` their δ_i's
            columns in ``unknowns``.
        terms: the drive's extension terms ``(starts, gains, offsets, values (b, legs), columns (b, legs))``
            (:meth:`stewart_calib.model.drive.DriveModel.kernel_terms`; a column −1: the value is known).
        inputs: the sample's drive inputs ``u``.
    Returns:
        ``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂unknowns (k, size))``.
    """
    starts, gains, offsets, values, term_columns = terms
    k, per_leg = nominal.shape
    legs = np.empty((k, per_leg))
    extensions = np.empty(k)
    gain = np.empty((starts.shape[0], k))  # ∂e_i/∂v_{b,i} = g_b u_{b,i}
    for i in range(k):
        leg = legs_of[i]
        for j in range(per_leg):
            legs[i, j] = nominal[i, j] + unknowns[columns[i, j]]
        e = 0.0
        for b in range(starts.shape[0]):
            value = values[b, leg]
            if term_columns[b, leg] >= 0:
                value = values[b, leg] + unknowns[term_columns[b, leg]]
            u = inputs[starts[b] + leg]
            gain[b, i] = u if gains[b] == 1.0 else gains[b] * u
            part = (offsets[b] + value) * gain[b, i]
            e = part if b == 0 else e + part
        extensions[i] = e
    r, J_pose, J_legs = _legs_at(pose, legs, extensions)
    H = _in_columns(J_legs, columns, unknowns.shape[0])
    for i in range(k):
        for b in range(starts.shape[0]):
            if term_columns[b, legs_of[i]] >= 0:
                H[i, term_columns[b, legs_of[i]]] = -gain[b, i]
    return r, J_pose, H


def drive_leg_rows_numpy(pose, unknowns, drive, legs_of, inputs):
    """:func:`drive_leg_rows` of a drive whose legs have no compiled kernels, from its leg model
    (:class:`~stewart_calib.model.drive.DriveModel`'s residual and Jacobians, numpy), each row over its
    ``|J_e,i| = |∂r_i/∂e_i|``: a residual in the unit of the leg's coordinate, whose noise is one
    logged coordinate's σ at every pose (:meth:`~stewart_calib.model.drive.DriveModel.coordinate_sigma`;
    prismatic legs: ``|J_e| = 1``, the compiled rows).

    Args:
        pose: ``(4, 4)`` homogeneous pose; unknowns: ``(size,)``, the drive's ``x_drive`` first.
        drive: the :class:`~stewart_calib.model.drive.DriveModel`.
        legs_of: ``(k,)`` the rows' leg indices; inputs: the sample's drive inputs ``u``.
    Returns:
        ``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂unknowns (k, size))``.
    """
    R, t = pose[:3, :3], pose[:3, 3]
    x_drive = unknowns[: drive.size]
    extensions, lengthening = drive.extensions(inputs, x_drive), drive.lengthening(inputs, x_drive)
    r, J_pose, J_M, J_e = drive.leg_rows(x_drive, R, t, extensions, lengthening)
    J_x = drive.with_terms(J_M, inputs, J_e)
    scale = 1.0 / np.abs(J_e[legs_of])
    H = np.zeros((len(legs_of), len(unknowns)))
    H[:, : drive.size] = J_x[legs_of] * scale[:, None]
    return r[legs_of] * scale, J_pose[legs_of] * scale[:, None], H


@njit(**_JIT)
def _legs_at(pose, legs, extensions):
    """:func:`~stewart_calib.model._kernels.leg_rows` of ``legs (k, 7)`` with ``extensions`` at the homogeneous
    ``pose (4, 4)`` (``Pose3.matrix()``): ``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂leg (k, 7))``."""
    k = legs.shape[0]
    R = np.ascontiguousarray(pose[:3, :3])
    t = np.ascontiguousarray(pose[:3, 3])
    r, J_pose, J_legs = np.empty(k), np.empty((k, 6)), np.empty(legs.shape)
    leg_rows(legs, R, t, extensions, r, J_pose, J_legs)
    return r, J_pose, J_legs


@njit(**_JIT)
def _in_columns(J_legs, columns, size):
    """``(k, size)`` zeros with row i's ``∂r_i/∂leg`` in the unknowns' ``columns[i]``."""
    H = np.zeros((J_legs.shape[0], size))
    for i in range(J_legs.shape[0]):
        for j in range(J_legs.shape[1]):
            H[i, columns[i, j]] = J_legs[i, j]
    return H


@njit(entry=(F8_2F, F8_2, F8_1), **_JIT)
def known_leg_rows(pose, legs, extensions):
    """Residuals of ``k`` legs of known geometry ``legs (k, 7)`` = ``[j_i | d_i | l_i]`` with
    extensions ``e_i`` (a tracker's rulers and their readings) at ``pose`` ``(4, 4)``, and their
    Jacobian on the pose: ``(r (k,), ∂r/∂ξ (k, 6))``."""
    r, J_pose, _ = _legs_at(pose, legs, extensions)
    return r, J_pose


@njit(entry=(F8_2F, F8_1, I8_2, F8_1), **_JIT)
def unknown_leg_rows(pose, params, columns, extensions):
    """Residuals of ``k`` legs whose rows ``[j_i | d_i | l_i]`` are ``params[columns]`` (``columns (k, 7)``:
    a leg set whose geometry is unknown, the tracker's θ₀ + p in the unknown vector ``params``) with
    extensions ``e_i`` at ``pose`` ``(4, 4)``, and their Jacobians: ``(r (k,), ∂r/∂ξ (k, 6), ∂r/∂params
    (k, len(params)))`` (TrackerModel.residual's arithmetic, its J_instrument put in the rows' columns)."""
    k, per_leg = columns.shape
    legs = np.empty((k, per_leg))
    for i in range(k):
        for j in range(per_leg):
            legs[i, j] = params[columns[i, j]]
    r, J_pose, J_legs = _legs_at(pose, legs, extensions)
    return r, J_pose, _in_columns(J_legs, columns, params.shape[0])


@njit(**_JIT)
def _so3_log(R, phi):
    """``Log(R)`` into ``phi (3,)`` [rad] (model.rotations.so3_log: the series below sin θ = 1e-9, the
    axis from ``(R + Rᵀ)/2 + I`` near π)."""
    phi[0] = 0.5 * (R[2, 1] - R[1, 2])
    phi[1] = 0.5 * (R[0, 2] - R[2, 0])
    phi[2] = 0.5 * (R[1, 0] - R[0, 1])
    sin_theta = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    cos_theta = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    theta = math.atan2(sin_theta, cos_theta)
    if sin_theta >= 1e-9:
        scale = theta / sin_theta
    elif cos_theta >= 0.0:
        scale = 1.0 + theta**2 / 6.0
    else:
        column, largest = 0, -np.inf
        for c in range(3):
            if R[c, c] + 1.0 > largest:
                column, largest = c, R[c, c] + 1.0
        norm = 0.0
        for a in range(3):
            phi[a] = 0.5 * (R[a, column] + R[column, a]) + (1.0 if a == column else 0.0)
            norm += phi[a] * phi[a]
        scale = np.pi / math.sqrt(norm)
    for a in range(3):
        phi[a] *= scale


@njit(**_JIT)
def _right_jacobian_inverse(phi, J):
    """``J_r⁻¹(φ) = I + [φ]×/2 + c [φ]×²`` into ``J (3, 3)`` (model.rotations.so3_right_jacobian_inverse;
    ``[φ]×² = φ φᵀ − θ² I``)."""
    theta2 = phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2]
    if theta2 < 1e-8:
        c = 1.0 / 12.0 + theta2 / 720.0
    else:
        theta = math.sqrt(theta2)
        c = 1.0 / theta**2 - (1.0 + math.cos(theta)) / (2.0 * theta * math.sin(theta))
    for a in range(3):
        for b in range(3):
            J[a, b] = c * phi[a] * phi[b]
        J[a, a] += 1.0 - c * theta2
    J[0, 1] -= 0.5 * phi[2]
    J[0, 2] += 0.5 * phi[1]
    J[1, 0] += 0.5 * phi[2]
    J[1, 2] -= 0.5 * phi[0]
    J[2, 0] -= 0.5 * phi[1]
    J[2, 1] += 0.5 * phi[0]


@njit(**_JIT)
def _product(A, B, sign, out):
    """``out ← sign · A B`` for small matrices (the pose tangent's ``(6, 6)``), in loops."""
    for a in range(out.shape[0]):
        for b in range(out.shape[1]):
            s = 0.0
            for c in range(A.shape[1]):
                s += A[a, c] * B[c, b]
            out[a, b] = sign * s


@njit(**_JIT)
def pose_reading_rows(pose, theta, z):
    """The pose instrument's residual of one reading and its Jacobians, in one call
    (instruments.pose.PoseModel.residual on all six channels): with frame ``F = θ[:6]`` and target
    ``G = θ[6:12]`` (pose6 [mm, rad]), the predicted reading ``P = F⁻¹ X G`` at the platform pose
    ``X`` and the reading ``M = z``, ``e = [Log(R_Mᵀ R_P), t_P − t_M]``.

    Args:
        pose: ``(4, 4)`` homogeneous pose X of {D} in {J} [mm] (``Pose3.matrix()``).
    Returns:
        ``(e (6,), ∂e/∂ξ_X (6, 6), ∂e/∂θ (6, 12))``: ``∂e/∂ξ_X = H Ad_{G⁻¹}``, on the tangents of F and G
        ``[−H Ad_{P⁻¹}, H]`` with ``H = diag(J_r⁻¹(e_rot), R_P)``, carried to θ by ``(∂θ/∂[φ, γ])⁻¹``.
    """
    R_X, t_X = pose[:3, :3], pose[:3, 3]
    R_F, R_G, R_M = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    _rotation(theta[0:6], R_F)
    _rotation(theta[6:12], R_G)
    _rotation(z, R_M)
    R_P, t_P, R_MP = np.empty((3, 3)), np.empty(3), np.empty((3, 3))
    R_XG, t_XG = np.empty((3, 3)), np.empty(3)
    for a in range(3):  # X G: R_X R_G, R_X t_G + t_X − t_F
        t_XG[a] = R_X[a, 0] * theta[6] + R_X[a, 1] * theta[7] + R_X[a, 2] * theta[8] + t_X[a] - theta[a]
        for b in range(3):
            R_XG[a, b] = R_X[a, 0] * R_G[0, b] + R_X[a, 1] * R_G[1, b] + R_X[a, 2] * R_G[2, b]
    for a in range(3):  # P = F⁻¹ X G: R_Fᵀ R_XG, R_Fᵀ t_XG
        t_P[a] = R_F[0, a] * t_XG[0] + R_F[1, a] * t_XG[1] + R_F[2, a] * t_XG[2]
        for b in range(3):
            R_P[a, b] = R_F[0, a] * R_XG[0, b] + R_F[1, a] * R_XG[1, b] + R_F[2, a] * R_XG[2, b]
    for a in range(3):
        for b in range(3):
            R_MP[a, b] = R_M[0, a] * R_P[0, b] + R_M[1, a] * R_P[1, b] + R_M[2, a] * R_P[2, b]
    e = np.empty(6)
    e_rot, J_r = np.empty(3), np.empty((3, 3))
    _so3_log(R_MP, e_rot)
    _right_jacobian_inverse(e_rot, J_r)
    H = np.zeros((6, 6))
    for a in range(3):
        e[a], e[3 + a] = e_rot[a], t_P[a] - z[a]
        for b in range(3):
            H[a, b], H[3 + a, 3 + b] = J_r[a, b], R_P[a, b]
    R_inv, t_inv = np.empty((3, 3)), np.empty(3)
    for a in range(3):  # G⁻¹
        t_inv[a] = -(R_G[0, a] * theta[6] + R_G[1, a] * theta[7] + R_G[2, a] * theta[8])
        for b in range(3):
            R_inv[a, b] = R_G[b, a]
    J_pose = np.empty((6, 6))
    _product(H, _adjoint(R_inv, t_inv), 1.0, J_pose)
    for a in range(3):  # P⁻¹
        t_inv[a] = -(R_P[0, a] * t_P[0] + R_P[1, a] * t_P[1] + R_P[2, a] * t_P[2])
        for b in range(3):
            R_inv[a, b] = R_P[b, a]
    H_frame, J_block = np.empty((6, 6)), np.empty((6, 6))
    _product(H, _adjoint(R_inv, t_inv), -1.0, H_frame)
    J_theta = np.empty((6, 12))
    for block in range(2):
        if block == 0:
            _product(H_frame, _tangent_from_pose6(theta[0:6], R_F), 1.0, J_block)
        else:
            _product(H, _tangent_from_pose6(theta[6:12], R_G), 1.0, J_block)
        for a in range(J_block.shape[0]):
            for b in range(J_block.shape[1]):
                J_theta[a, J_block.shape[1] * block + b] = J_block[a, b]
    return e, J_pose, J_theta
