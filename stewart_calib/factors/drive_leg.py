"""Drive-leg factor: platform pose ↔ one leg's seven parameter errors (paper eq. 1).

Residual of drive leg i (the leg-length model of design.md)::

    r_i = ‖t + R d_i − j_i‖ − (l_i + (1 + k_i) q_i),    (j_i, d_i, l_i) = nominal_i + δ_i

with q_i the executed stroke [mm], δ_i = (δj_i, δd_i, δl_i) the leg's slice of δM (paper
eq. 9) and k_i its stroke scale (spec §7): the platform's nominal value plus, where identified,
the unknown vector's error (``∂r/∂k_i = −q_i``). The
factor's variables are the pose ``X_k`` (``gtsam.Pose3``) and the unknown vector of the current
parameter window (δM first); the leg touches only its own seven columns and its k_i.
(One 42-vector variable measured faster than six 7-vector variables; see
:mod:`stewart_calib.estimators.isam2`.)

Jacobians, body tangent ``ξ = [ω, v]`` (GTSAM order): with ``n`` the unit leg vector and
``n_b = Rᵀ n``, ``∂r/∂ξ = [(d × n_b)ᵀ, n_bᵀ]`` and ``∂r/∂(j, d, l) = [−nᵀ, n_bᵀ, −1]``
(the rows of paper eq. 8 in the leg-length form).
"""

from __future__ import annotations

import math
from functools import partial

import gtsam
import numpy as np

from ..kinematics import leg_residual
from ..platform import N_PARAMS, N_PARAMS_PER_LEG


def residual(
    R: np.ndarray, t: np.ndarray, nominal_leg: np.ndarray, delta_leg: np.ndarray, stroke_mm: float, jacobians: bool = False
) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """Drive-leg residual ``r_i`` [mm] and its Jacobians ``(6,)`` on ξ, ``(7,)`` on δ_i.

    Args:
        R, t: platform pose.
        nominal_leg: ``(7,)`` nominal ``[j_i | d_i | l_i]`` [mm].
        delta_leg: ``(7,)`` errors δ_i, same layout [mm].
        stroke_mm: executed stroke q_i [mm].
    """
    return leg_residual(R, t, nominal_leg + delta_leg, stroke_mm, jacobians)


def _error(
    leg_index: int, nominal_leg: np.ndarray, stroke_mm: float, size: int, scale_column: int | None, nominal_scale: float,
    this: gtsam.CustomFactor, values: gtsam.Values, H,
):
    pose = values.atPose3(this.keys()[0])
    cols = slice(N_PARAMS_PER_LEG * leg_index, N_PARAMS_PER_LEG * (leg_index + 1))
    unknowns = values.atVector(this.keys()[1])
    scale = nominal_scale if scale_column is None else nominal_scale + unknowns[scale_column]
    extension = stroke_mm if scale == 0.0 else (1.0 + scale) * stroke_mm
    r, H_pose, H_leg = residual(pose.rotation().matrix(), pose.translation(), nominal_leg, unknowns[cols], extension, H is not None)
    if H is not None:
        H[0] = H_pose.reshape(1, 6)
        H_params = np.zeros((1, size))
        H_params[0, cols] = H_leg
        if scale_column is not None:
            H_params[0, scale_column] = -stroke_mm
        H[1] = H_params
    return np.array([r])


def factor(
    pose_key: int, params_key: int, leg_index: int, nominal_leg: np.ndarray, stroke_mm: float, noise: gtsam.noiseModel.Base,
    size: int = N_PARAMS, scale_column: int | None = None, nominal_scale: float = 0.0,
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` on ``(Pose3 pose_key, unknown vector params_key)`` for leg ``leg_index`` (0-based).

    Args:
        size: length of the unknown vector (42 + its blocks).
        scale_column: the column of this leg's error of k_i, or None without a stroke-scale block.
        nominal_scale: the platform's nominal k_i.
    """
    nominal_leg = np.array(nominal_leg, dtype=float)
    error = partial(_error, leg_index, nominal_leg, float(stroke_mm), int(size), scale_column, float(nominal_scale))
    return gtsam.CustomFactor(noise, [pose_key, params_key], error)
