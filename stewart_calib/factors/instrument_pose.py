"""Instrument pose prior (loose coupling): the pose one measurement implies, as a prior on ``x_k``.

For the tracker this is the paper's way (§3.2 step 1: Newton–Raphson FK of the grating readings
gives P_v). The measurement ``T_m`` and its covariance in the body tangent ``[ω, v]`` come from
the instrument model's loose pose (:meth:`~stewart_calib.instruments.base.InstrumentModel.pose`;
for the tracker ``Σ_ξ = σ_s² (JᵀJ)⁻¹`` propagated from the ruler noise). Residual, as GTSAM's
``PriorFactorPose3``::

    e = Log(T_m⁻¹ T)    (6,) [rad, mm],    ∂e/∂ξ = J_r⁻¹(e)  (Pose3.Logmap's derivative)
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from . import pose_misfit


def residual(measured: gtsam.Pose3, pose: gtsam.Pose3, jacobians: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
    """``Log(T_m⁻¹ T)`` ``(6,)`` and, if asked, its Jacobian ``(6, 6)`` on the body tangent of ``pose``."""
    if not jacobians:
        return gtsam.Pose3.Logmap(measured.between(pose)), None
    # T Exp(δ) ⇒ T_m⁻¹ T Exp(δ): the between's own tangent, so only Logmap's derivative remains.
    H = np.zeros((6, 6), order="F")
    e = gtsam.Pose3.Logmap(measured.between(pose), H)
    return e, H


def _error(measured: gtsam.Pose3, this: gtsam.CustomFactor, values: gtsam.Values, H):
    e, H_pose = residual(measured, values.atPose3(this.keys()[0]), H is not None)
    if H is not None:
        H[0] = H_pose
    return e


def factor(
    pose_key: int, measured: gtsam.Pose3, noise: gtsam.noiseModel.Base, misfit: tuple[int, np.ndarray] | None = None
) -> gtsam.CustomFactor:
    """A unary ``CustomFactor`` on ``Pose3 pose_key``: the pose prior ``T_m`` with ``noise``; with ``misfit =
    (key, rows)`` a static pose's misfit variable's rows added to it (:mod:`.pose_misfit`)."""
    return pose_misfit.custom(noise, [pose_key], partial(_error, measured), misfit)
