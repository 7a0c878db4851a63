"""Drive-leg factor: platform pose ↔ the legs' seven parameter errors each (paper eq. 1).

Residual of drive leg i (the leg-length model of design.md)::

    r_i = ‖t + R d_i − j_i‖ − (l_i + (1 + k_i) q_i),    (j_i, d_i, l_i) = nominal_i + δ_i

with q_i the executed stroke [mm], δ_i = (δj_i, δd_i, δl_i) the leg's slice of δM (paper
eq. 9) and k_i its stroke scale (spec §7): the platform's nominal value plus, where identified,
the unknown vector's error (``∂r/∂k_i = −q_i``). The
factor's variables are the pose ``X_k`` (``gtsam.Pose3``) and the unknown vector of the current
parameter window (δM first); leg i's row touches only its own seven columns and its k_i.
(One 42-vector variable measured faster than six 7-vector variables; see
:mod:`stewart_calib.estimators.isam2`.) One factor holds the six legs of a sample (one Python
callback per linearisation instead of six, and one Jacobian block for gtsam to eliminate):
with Gaussian noise the six rows are the six scalar factors exactly; a robust kernel weighs a
whole factor, so with one each leg gets a factor of its own.

Jacobians, body tangent ``ξ = [ω, v]`` (GTSAM order): with ``n`` the unit leg vector and
``n_b = Rᵀ n``, ``∂r/∂ξ = [(d × n_b)ᵀ, n_bᵀ]`` and ``∂r/∂(j, d, l) = [−nᵀ, n_bᵀ, −1]``
(the rows of paper eq. 8 in the leg-length form).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import gtsam
import numpy as np

from ..kinematics import leg_residual
from ..platform import N_LEGS, N_PARAMS, N_PARAMS_PER_LEG
from ._kernels import drive_leg_rows


def residual(
    R: np.ndarray, t: np.ndarray, nominal_legs: np.ndarray, delta_legs: np.ndarray, strokes_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drive-leg residuals ``r_i`` [mm] of ``k`` legs and their Jacobians ``(k, 6)`` on ξ, ``(k, 7)`` on δ_i.

    Args:
        R, t: platform pose.
        nominal_legs: ``(k, 7)`` nominal ``[j_i | d_i | l_i]`` [mm].
        delta_legs: ``(k, 7)`` errors δ_i, same layout [mm].
        strokes_mm: ``(k,)`` executed (scaled) strokes ``(1 + k_i) q_i`` [mm].
    """
    return leg_residual(R, t, nominal_legs + delta_legs, strokes_mm)


@dataclass(frozen=True)
class DriveLegs:
    """What the factors of a set of drive legs share across samples (built once, not per sample).

    Attributes:
        legs: ``(k,)`` leg indices (0-based).
        nominal: ``(k, 7)`` their nominal ``[j_i | d_i | l_i]`` [mm].
        columns: ``(k, 7)`` their δ_i's columns in the unknown vector.
        size: length of the unknown vector (42 + its blocks).
        scale_columns: ``(k,)`` columns of their k_i errors, −1 without a stroke-scale block.
        nominal_scale: ``(k,)`` the platform's nominal k_i.
    """

    legs: np.ndarray
    nominal: np.ndarray
    columns: np.ndarray
    size: int
    scale_columns: np.ndarray
    nominal_scale: np.ndarray

    @classmethod
    def of(
        cls,
        legs,
        drive_params: np.ndarray,
        size: int = N_PARAMS,
        scale_start: int | None = None,
        stroke_scale: np.ndarray | float = 0.0,
    ) -> DriveLegs:
        """Legs ``legs`` of a drive with ``(6, 7)`` nominal ``drive_params``; ``scale_start``: the
        column of leg 1's k_i error (leg i at ``scale_start + i``); ``stroke_scale``: nominal k_i."""
        legs = np.asarray(legs, dtype=np.int64).reshape(-1)
        columns = N_PARAMS_PER_LEG * legs[:, None] + np.arange(N_PARAMS_PER_LEG)
        return cls(
            legs,
            np.array(np.asarray(drive_params, dtype=float)[legs]),
            np.ascontiguousarray(columns),
            int(size),
            np.full(len(legs), -1, dtype=np.int64) if scale_start is None else scale_start + legs,
            np.array(np.broadcast_to(np.asarray(stroke_scale, dtype=float), (N_LEGS,))[legs]),
        )


def _error(
    legs: DriveLegs,
    strokes_mm: np.ndarray,
    pose_key: int,
    params_key: int,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    H,
):
    r, H_pose, H_params = drive_leg_rows(
        values.atPose3(pose_key).matrix(),
        values.atVector(params_key),
        legs.nominal,
        legs.columns,
        legs.scale_columns,
        legs.nominal_scale,
        strokes_mm,
    )
    if H is not None:
        H[0] = H_pose
        H[1] = H_params
    return r


def factor(
    pose_key: int, params_key: int, legs: DriveLegs, strokes_mm: np.ndarray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` on ``(Pose3 pose_key, unknown vector params_key)``: one row per leg of
    ``legs`` (all six in one factor unless a robust kernel weighs each alone).

    Args:
        strokes_mm: ``(6,)`` the sample's executed strokes q_i [mm] (those of ``legs`` are used).
        noise: of the ``k`` rows.

    The residual and both Jacobians are one compiled call (:func:`._kernels.drive_leg_rows`,
    the arithmetic of :func:`residual`).
    """
    strokes = np.array(np.asarray(strokes_mm, dtype=float)[legs.legs])
    return gtsam.CustomFactor(noise, [pose_key, params_key], partial(_error, legs, strokes, pose_key, params_key))
