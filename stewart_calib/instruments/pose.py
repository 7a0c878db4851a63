"""A 6-DOF pose instrument (motion capture, a laser tracker's 6-DOF probe): spec §7 ``kind = "pose"``.

The instrument reports the pose of a body {T} fixed on the platform, in its own frame {I}::

    T_I_T = T_J_I⁻¹ · T_J_D · T_D_T        F = T_J_I (frame), X = T_J_D (platform pose), G = T_D_T (target)

F and G are unknowns of the calibration (12 tangent directions). Residual of one reading
``M = (R_m, t_m)`` against the prediction ``P = F⁻¹ X G``::

    e = [Log(R_mᵀ R_P) [rad], t_P − t_m [mm]]      rotation first, as GTSAM's tangent

whitened by ``σ_rot`` and ``σ_pos`` of the ``[instrument]`` table: position and orientation each
carry their own noise, never a hand-picked trade between the two.

Jacobians (body perturbations ``X Exp(ξ)``, ``F Exp(φ)``, ``G Exp(γ)``): the prediction moves by
the body tangent ``δ = Ad_{G⁻¹} ξ − Ad_{P⁻¹} φ + γ``, and ``∂e/∂δ = diag(J_r⁻¹(e_rot), R_P)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import kinematics as kin
from ..platform import Instrument
from . import lie

#: names of the 12 unknowns in file units (spec §7 result ``"instrument"`` block)
UNKNOWN_NAMES: tuple[str, ...] = tuple(
    f"{part}_{axis}" for part in ("frame", "target") for axis in ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
)
#: log columns (spec §7): the measured pose of {T} in {I}
COLUMNS: tuple[str, ...] = ("mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg")


@dataclass(frozen=True)
class PoseUnknowns:
    """Current values of the instrument's unknowns: frame ``F = T_J_I`` and target ``G = T_D_T``."""

    R_frame: np.ndarray
    t_frame: np.ndarray
    R_target: np.ndarray
    t_target: np.ndarray

    size = 12

    @classmethod
    def from_pose6(cls, frame: np.ndarray, target: np.ndarray) -> "PoseUnknowns":
        return cls(*kin.pose_to_rt(frame), *kin.pose_to_rt(target))

    def retract(self, delta: np.ndarray) -> "PoseUnknowns":
        """``F Exp(φ)``, ``G Exp(γ)`` for ``delta = [φ (6), γ (6)]`` (first-order chart)."""
        return PoseUnknowns(*kin.retract(self.R_frame, self.t_frame, delta[:6]), *kin.retract(self.R_target, self.t_target, delta[6:12]))

    def file_values(self) -> np.ndarray:
        """``(12,)`` frame then target as ``[x, y, z mm, roll, pitch, yaw deg]``."""
        pose = np.concatenate([kin.rt_to_pose(self.R_frame, self.t_frame), kin.rt_to_pose(self.R_target, self.t_target)])
        return np.concatenate([pose[:3], np.degrees(pose[3:6]), pose[6:9], np.degrees(pose[9:])])

    def file_jacobian(self) -> np.ndarray:
        """``∂ file_values / ∂[φ, γ]`` ``(12, 12)`` (for the covariance in file units)."""
        J = np.zeros((12, 12))
        for block, (R, t) in enumerate(((self.R_frame, self.t_frame), (self.R_target, self.t_target))):
            rows = slice(6 * block, 6 * block + 6)
            J[rows, rows] = lie.pose6_tangent_jacobian(kin.rt_to_pose(R, t))
            J[6 * block + 3 : 6 * block + 6] = np.degrees(J[6 * block + 3 : 6 * block + 6])
        return J


def nominal(instrument: Instrument) -> PoseUnknowns:
    """The platform file's frame and target."""
    return PoseUnknowns.from_pose6(instrument.frame, instrument.target)


def predict(u: PoseUnknowns, R_X: np.ndarray, t_X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P = F⁻¹ X G``: the pose of {T} in {I} the instrument should read at platform pose X."""
    R_Fi, t_Fi = lie.inverse(u.R_frame, u.t_frame)
    return lie.compose(*lie.compose(R_Fi, t_Fi, R_X, t_X), u.R_target, u.t_target)


def sigmas(instrument: Instrument) -> np.ndarray:
    """``(6,)`` σ of the residual's components ``[rad ×3, mm ×3]``."""
    return np.r_[np.full(3, instrument.orientation_sigma_rad), np.full(3, instrument.position_sigma_mm)]


def residual(u: PoseUnknowns, measured: np.ndarray, R_X: np.ndarray, t_X: np.ndarray, jacobians: bool = False):
    """``e = [Log(R_mᵀ R_P), t_P − t_m]`` ``(..., 6)`` and, if asked, ``(∂e/∂ξ_X, ∂e/∂[φ, γ])``.

    Args:
        measured: ``(..., 6)`` readings ``[x, y, z mm, roll, pitch, yaw rad]`` of {T} in {I}.
    Returns:
        ``(e, H_X (..., 6, 6) or None, H_u (..., 6, 12) or None)``.
    """
    R_m, t_m = kin.pose_to_rt(measured)
    R_P, t_P = predict(u, R_X, t_X)
    e_rot = lie.so3_log(np.swapaxes(R_m, -1, -2) @ R_P)
    e = np.concatenate([e_rot, t_P - t_m], axis=-1)
    if not jacobians:
        return e, None, None
    H_delta = np.zeros(e.shape + (6,))
    H_delta[..., :3, :3] = lie.so3_right_jacobian_inverse(e_rot)
    H_delta[..., 3:, 3:] = R_P
    H_X = H_delta @ lie.adjoint(*lie.inverse(u.R_target, u.t_target))
    H_F = -H_delta @ lie.adjoint(*lie.inverse(R_P, t_P))
    return e, H_X, np.concatenate([H_F, H_delta], axis=-1)


def errors(R_m, t_m, R_P, t_P) -> tuple[np.ndarray, np.ndarray]:
    """Per reading ``(‖t_P − t_m‖ [mm], angle of R_mᵀ R_P [deg])`` (spec §7 validation columns)."""
    return kin.pose_error(R_m, t_m, R_P, t_P)
