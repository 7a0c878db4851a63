"""Drive-leg factor: platform pose ↔ one leg's seven parameter errors (paper eq. 1).

Residual of drive leg i (the leg-length model of design.md)::

    r_i = ‖t + R d_i − j_i‖ − (l_i + q_i),    (j_i, d_i, l_i) = nominal_i + δ_i

with q_i the executed stroke [mm] and δ_i = (δj_i, δd_i, δl_i) the leg's slice of δM
(paper eq. 9). The factor's variables are the pose ``X_k`` (``gtsam.Pose3``) and the
42-vector δM of the current parameter window; the leg touches only its own seven columns.
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


def _error(leg_index: int, nominal_leg: np.ndarray, stroke_mm: float, this: gtsam.CustomFactor, values: gtsam.Values, H):
    pose = values.atPose3(this.keys()[0])
    cols = slice(N_PARAMS_PER_LEG * leg_index, N_PARAMS_PER_LEG * (leg_index + 1))
    delta_leg = values.atVector(this.keys()[1])[cols]
    r, H_pose, H_leg = residual(pose.rotation().matrix(), pose.translation(), nominal_leg, delta_leg, stroke_mm, H is not None)
    if H is not None:
        H[0] = H_pose.reshape(1, 6)
        H_params = np.zeros((1, N_PARAMS))
        H_params[0, cols] = H_leg
        H[1] = H_params
    return np.array([r])


def factor(
    pose_key: int, params_key: int, leg_index: int, nominal_leg: np.ndarray, stroke_mm: float, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` on ``(Pose3 pose_key, 42-vector δM params_key)`` for leg ``leg_index`` (0-based)."""
    nominal_leg = np.array(nominal_leg, dtype=float)
    return gtsam.CustomFactor(noise, [pose_key, params_key], partial(_error, leg_index, nominal_leg, float(stroke_mm)))
