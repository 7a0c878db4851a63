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

import math
from dataclasses import dataclass, replace
from typing import ClassVar

import numpy as np

from ..errors import CalibError, SampleRejected, number
from ..model import _kernels, rotations
from ..model import kinematics as kin
from ..model.kinematics import rt_to_pose
from ..model.platform import INSTRUMENT_SECTIONS, Instrument, Platform
from . import registration
from .base import PoseObservation, Residual, Spread, position_spread_mm, rotation_spread_rad
from .external import OutsideModel

#: names of the 12 unknowns in file units (spec §7 result ``"instrument"`` block)
UNKNOWN_NAMES: tuple[str, ...] = tuple(
    f"{part}_{axis}"
    for part in ("frame", "target")
    for axis in ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
)
#: log columns (spec §7): the measured pose of {T} in {I}
COLUMNS: tuple[str, ...] = INSTRUMENT_SECTIONS["pose"].log_columns(0)


@dataclass(frozen=True)
class PoseUnknowns:
    """Current values of the instrument's unknowns: frame ``F = T_J_I`` and target ``G = T_D_T``."""

    R_frame: np.ndarray
    t_frame: np.ndarray
    R_target: np.ndarray
    t_target: np.ndarray

    size = 12

    @classmethod
    def from_pose6(cls, frame: np.ndarray, target: np.ndarray) -> PoseUnknowns:
        return cls(*kin.pose_to_rt(frame), *kin.pose_to_rt(target))

    def retract(self, delta: np.ndarray) -> PoseUnknowns:
        """``F Exp(φ)``, ``G Exp(γ)`` for ``delta = [φ (6), γ (6)]`` (first-order chart)."""
        return PoseUnknowns(
            *kin.retract(self.R_frame, self.t_frame, delta[:6]), *kin.retract(self.R_target, self.t_target, delta[6:12])
        )

    def in_frames(self, R_J: np.ndarray, t_J: np.ndarray, R_D: np.ndarray, t_D: np.ndarray) -> PoseUnknowns:
        """The frame and target moved with a rigid motion ``(R_J, t_J)`` of {J} and ``(R_D, t_D)`` of {D}."""
        return PoseUnknowns(
            R_J @ self.R_frame, R_J @ self.t_frame + t_J, R_D @ self.R_target, R_D @ self.t_target + t_D
        )

    def file_values(self) -> np.ndarray:
        """``(12,)`` frame then target as ``[x, y, z mm, roll, pitch, yaw deg]``."""
        pose = np.concatenate(
            [kin.rt_to_pose(self.R_frame, self.t_frame), kin.rt_to_pose(self.R_target, self.t_target)]
        )
        return np.concatenate([pose[:3], np.degrees(pose[3:6]), pose[6:9], np.degrees(pose[9:])])

    def file_jacobian(self) -> np.ndarray:
        """``∂ file_values / ∂[φ, γ]`` ``(12, 12)`` (for the covariance in file units)."""
        J = np.zeros((12, 12))
        for block, (R, t) in enumerate(((self.R_frame, self.t_frame), (self.R_target, self.t_target))):
            rows = slice(6 * block, 6 * block + 6)
            J[rows, rows] = rotations.pose6_tangent_jacobian(kin.rt_to_pose(R, t))
            J[6 * block + 3 : 6 * block + 6] = np.degrees(J[6 * block + 3 : 6 * block + 6])
        return J


def nominal(instrument: Instrument) -> PoseUnknowns:
    """The platform file's frame and target."""
    return PoseUnknowns.from_pose6(instrument.frame, instrument.target)


def predict(u: PoseUnknowns, R_X: np.ndarray, t_X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P = F⁻¹ X G``: the pose of {T} in {I} the instrument should read at platform pose X."""
    R_Fi, t_Fi = rotations.inverse(u.R_frame, u.t_frame)
    return rotations.compose(*rotations.compose(R_Fi, t_Fi, R_X, t_X), u.R_target, u.t_target)


def residual(u: PoseUnknowns, measured: np.ndarray, R_X: np.ndarray, t_X: np.ndarray, jacobians: bool = False):
    """``e = [Log(R_mᵀ R_P), t_P − t_m]`` ``(..., 6)`` and, if asked, ``(∂e/∂ξ_X, ∂e/∂[φ, γ])``.

    Args:
        measured: ``(..., 6)`` readings ``[x, y, z mm, roll, pitch, yaw rad]`` of {T} in {I}.
    Returns:
        ``(e, H_X (..., 6, 6) or None, H_u (..., 6, 12) or None)``.
    """
    R_m, t_m = kin.pose_to_rt(measured)
    R_P, t_P = predict(u, R_X, t_X)
    e_rot = rotations.so3_log(np.swapaxes(R_m, -1, -2) @ R_P)
    e = np.concatenate([e_rot, t_P - t_m], axis=-1)
    if not jacobians:
        return e, None, None
    H_delta = np.zeros(e.shape + (6,))
    H_delta[..., :3, :3] = rotations.so3_right_jacobian_inverse(e_rot)
    H_delta[..., 3:, 3:] = R_P
    H_X = H_delta @ rotations.adjoint(*rotations.inverse(u.R_target, u.t_target))
    H_F = -H_delta @ rotations.adjoint(*rotations.inverse(R_P, t_P))
    return e, H_X, np.concatenate([H_F, H_delta], axis=-1)


def errors(R_m, t_m, R_P, t_P) -> tuple[np.ndarray, np.ndarray]:
    """Per reading ``(‖t_P − t_m‖ [mm], angle of R_mᵀ R_P [deg])`` (spec §7 validation columns)."""
    return kin.pose_error(R_m, t_m, R_P, t_P)


def hand_eye_rotations(R_X: np.ndarray, R_M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The target's and the frame's orientations ``(R_G, R_F)`` with ``R_X R_G ≈ R_F R_M`` in least
    squares, and the singular values of the stacked equations (smallest last).

    ``vec(R_X R_G) − vec(R_F R_M) = 0`` is linear in ``[vec R_G, vec R_F]`` (18 unknowns, 9 rows a
    pose): its least singular vector, projected onto rotations. Poses that rotate about two axes and
    agree with the readings leave one singular value near zero and the next well above it.
    """
    n = len(R_X)
    eye = np.eye(3)
    # column-major vec: vec(A X) = (I ⊗ A) vec X, vec(X B) = (Bᵀ ⊗ I) vec X
    rows = np.concatenate(
        [np.stack([np.kron(eye, R_X[k]) for k in range(n)]), -np.stack([np.kron(R_M[k].T, eye) for k in range(n)])],
        axis=2,
    ).reshape(9 * n, 18)
    _, s, Vt = np.linalg.svd(rows, full_matrices=False)
    v = Vt[-1]
    R_G, R_F = v[:9].reshape(3, 3).T, v[9:].reshape(3, 3).T
    if np.linalg.det(R_F) < 0:
        R_G, R_F = -R_G, -R_F
    return rotations.project_to_rotation(R_G), rotations.project_to_rotation(R_F), s


def register_pose(
    R_X: np.ndarray, t_X: np.ndarray, R_M: np.ndarray, t_M: np.ndarray, sigmas: np.ndarray
) -> PoseUnknowns:
    """Frame F and target G with ``X_k G ≈ F M_k`` (hand-eye AX = YB), in closed form.

    Args:
        R_X, t_X: ``(N, 3, 3)``, ``(N, 3)`` platform poses (nominal FK of the strokes).
        R_M, t_M: the instrument's readings of {T} in {I}.
        sigmas: ``(6,)`` σ of a reading ``[rad ×3, mm ×3]`` (decides which poses are distinct).
    Raises:
        CalibError: fewer than 3 distinct poses, or rotations about fewer than two axes.
    """
    registration.require_distinct(
        np.concatenate([t_M, R_M.reshape(-1, 9)], axis=1), np.r_[sigmas[3:], np.full(9, sigmas[0])], "pose instrument"
    )
    n = len(R_X)
    eye = np.eye(3)
    R_G, R_F, s = hand_eye_rotations(R_X, R_M)
    if s[-2] <= max(3.0 * s[-1], registration.RELATIVE_RANK_TOLERANCE * s[0]):
        raise CalibError(
            "cannot register the pose instrument: the poses do not rotate about two different axes, so its "
            "frame's and its target's orientations cannot be told apart; expected poses with varied rotations"
        )
    A = np.concatenate([R_X, -np.broadcast_to(eye, (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = (np.einsum("ij,kj->ki", R_F, t_M) - t_X).reshape(-1)
    solution, *_ = np.linalg.lstsq(A, b, rcond=None)
    return PoseUnknowns(R_F, solution[3:], R_G, solution[:3])


class PoseModel(OutsideModel):
    """The pose instrument as a measurement model (:class:`~.external.OutsideModel`).

    Its unknowns θ are the frame's and the target's pose6 ``[x, y, z mm, roll, pitch, yaw rad]``
    (12 values, the block ``"instrument"``; both gauges shared with the drive). One reading is one
    channel group: a robust kernel weighs the whole pose.
    """

    kind = "pose"
    angle_columns = frozenset(COLUMNS[3:])  # mroll_deg mpitch_deg myaw_deg
    compiled_pose_reading = True  # the factor graph's rows in one compiled call (base.InstrumentModel)
    noise_channels = np.r_[0, 0, 0, 1, 1, 1]
    noise_channel_names = ("orientation_rad", "position_mm")
    _group: ClassVar[list[np.ndarray]] = [np.arange(len(COLUMNS))]  # the whole reading

    @staticmethod
    def columns_of(instrument: Instrument) -> tuple[str, ...]:
        return COLUMNS

    @staticmethod
    def sigmas_of(instrument: Instrument) -> np.ndarray:
        """``(6,)`` σ of the residual's components ``[rad ×3, mm ×3]``."""
        return np.r_[np.full(3, instrument.orientation_sigma_rad), np.full(3, instrument.position_sigma_mm)]

    @staticmethod
    def names_of(instrument: Instrument) -> tuple[str, ...]:
        """The names of the unknowns in file units (:data:`UNKNOWN_NAMES`)."""
        return UNKNOWN_NAMES

    @staticmethod
    def placed_on(
        platform: Platform, position_sigma_mm: float, orientation_sigma_rad: float, n_targets: int
    ) -> Instrument:
        """A nominal pose instrument for a simulated study: frame at {J}'s origin, target at {D}'s
        (``n_targets`` is the points instrument's)."""
        return Instrument("pose", position_sigma_mm=position_sigma_mm, orientation_sigma_rad=orientation_sigma_rad)

    @staticmethod
    def true_unknowns(
        instrument: Instrument, frame: np.ndarray, target_offset: np.ndarray, target_spread_mm: float, rng
    ) -> PoseUnknowns:
        """A simulation's true frame (pose6 ``frame``) and target (the nominal one plus the pose6
        ``target_offset``); ``target_spread_mm`` and ``rng`` are the points instrument's."""
        return PoseUnknowns.from_pose6(frame, instrument.target + target_offset)

    @staticmethod
    def noise_draws(instrument: Instrument, n: int, rng: np.random.Generator) -> np.ndarray:
        """``(n, 6)`` standard normal draws of :meth:`simulated_readings`' noise, rotation first."""
        return rng.standard_normal((n, 6))

    @staticmethod
    def simulated_readings(
        instrument: Instrument, u: PoseUnknowns, R: np.ndarray, t: np.ndarray, draws: np.ndarray, dropout: float
    ) -> np.ndarray:
        """Readings ``(..., 6)`` at true platform poses: ``(R_P Exp(σ_rot n_ω), t_P + σ_pos n_v)``
        (a pose is never lost from view: ``dropout`` is the points instrument's)."""
        R_P, t_P = predict(u, R, t)
        R_m = R_P @ kin.so3_exp(instrument.orientation_sigma_rad * draws[..., :3])
        return kin.rt_to_pose(R_m, t_P + instrument.position_sigma_mm * draws[..., 3:])

    @staticmethod
    def spreads(platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray) -> list[Spread]:
        """The measured positions' and orientations' spreads against the target's at the poses
        (:class:`~.base.Spread`; neither depends on the instrument's frame)."""
        _, t_G = kin.pose_to_rt(platform.instrument.target)
        t_T = t + np.einsum("kij,j->ki", R, t_G)
        R_M = kin.rpy_to_rotation(readings[:, 3:])
        return [
            Spread("positions", slice(0, 3), position_spread_mm(readings[:, :3]), position_spread_mm(t_T)),
            Spread(
                "orientations",
                slice(3, 6),
                math.degrees(rotation_spread_rad(R_M)),
                math.degrees(rotation_spread_rad(R)),
                angle=True,
            ),
        ]

    def check(self, z: np.ndarray, t_s: float) -> np.ndarray:
        reading = np.asarray(z, dtype=float)
        if reading.shape != (6,) or not np.all(np.isfinite(reading)):
            raise SampleRejected(
                f"sample at t = {number(t_s)} s: expected a finite pose reading (6 values)", SampleRejected.NON_FINITE
            )
        return reading

    def groups(self, z: np.ndarray) -> list[np.ndarray]:
        return self._group

    def residual(self, R: np.ndarray, t: np.ndarray, theta: np.ndarray, z: np.ndarray, channels: np.ndarray):
        """``[Log(R_mᵀ R_P), t_P − t_m]`` on ``channels``, ``∂/∂ξ`` and ``∂/∂θ`` (θ in pose6 coordinates)."""
        u = PoseUnknowns.from_pose6(theta[:6], theta[6:12])
        e, H_X, H_u = residual(u, z, R, t, jacobians=True)
        J_theta = H_u @ np.linalg.inv(theta_tangent_jacobian(theta))
        return Residual(e[channels], H_X[channels], J_theta[channels], np.asarray(channels))

    def pose(self, z: np.ndarray, theta: np.ndarray, guess):
        """``X = F M G⁻¹`` with the reading's covariance carried to X's tangent, and ``∂ξ/∂θ``.

        The reading's noise is ``R_m Exp(n_ω)``, ``t_m + n_v``: on M's body tangent
        ``[n_ω, R_mᵀ n_v]``, and ``X Exp(Ad_G δ) = F M Exp(δ) G⁻¹``; a frame change ``F Exp(φ)`` moves
        X by ``Ad_{G M⁻¹} φ``, a target change ``G Exp(γ)`` by ``−Ad_G γ``.
        """
        R_X, t_X, covariance, J_instrument = _kernels.pose_instrument_observation(
            np.ascontiguousarray(z, dtype=float),
            np.ascontiguousarray(theta[:12], dtype=float),
            self.instrument.orientation_sigma_rad**2,
            self.instrument.position_sigma_mm**2,
        )
        return PoseObservation(R_X, t_X, covariance, J_instrument)

    # what the callers of an outside instrument ask (external.OutsideModel)

    def nominal_unknowns(self) -> PoseUnknowns:
        return nominal(self.instrument)

    def _angles(self) -> np.ndarray:
        return np.r_[np.zeros(3, bool), np.ones(3, bool), np.zeros(3, bool), np.ones(3, bool)]

    def theta(self, unknowns: PoseUnknowns) -> np.ndarray:
        return np.concatenate(
            [rt_to_pose(unknowns.R_frame, unknowns.t_frame), rt_to_pose(unknowns.R_target, unknowns.t_target)]
        )

    def theta_jacobian(self, unknowns: PoseUnknowns) -> np.ndarray:
        return theta_tangent_jacobian(self.theta(unknowns))

    def readings_residual(self, unknowns, measured, R_X, t_X, jacobians=False):
        return residual(unknowns, measured, R_X, t_X, jacobians)

    def predicted_readings(self, unknowns, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        return rt_to_pose(*predict(unknowns, R_X, t_X))

    def prediction_errors(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, readings: np.ndarray):
        R_P, t_P = predict(unknowns, R_X, t_X)
        R_m, t_m = kin.pose_to_rt(readings)
        position, orientation = errors(R_m, t_m, R_P, t_P)
        return rt_to_pose(R_P, t_P), position, orientation

    def error_weights(self, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``‖t_P − t_m‖²`` of the residual's last three, the angle² [deg²] of its first three (small angles)."""
        position = np.where(seen, np.r_[np.zeros(3), np.ones(3)], 0.0)
        orientation = np.where(seen, np.r_[np.full(3, np.degrees(1.0) ** 2), np.zeros(3)], 0.0)
        return position, orientation

    def position_differences(self, readings: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """One row a sample, in the instrument's axes."""
        return readings[:, :3] - predicted[:, :3]

    def platform_poses(self, unknowns, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``X = F M G⁻¹`` of each reading."""
        R_M, t_M = kin.pose_to_rt(readings)
        return rotations.compose(
            *rotations.compose(unknowns.R_frame, unknowns.t_frame, R_M, t_M),
            *rotations.inverse(unknowns.R_target, unknowns.t_target),
        )

    def instrument_at(self, theta: np.ndarray) -> Instrument:
        return replace(self.instrument, frame=theta[:6], target=theta[6:12])

    def register(self, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> PoseUnknowns:
        return register_pose(R_X, t_X, *kin.pose_to_rt(measured), self.channel_sigma)

    def refit_frame(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> PoseUnknowns:
        """Horn's closed form of ``X G = F M`` for F, then :func:`~.registration.refine`.

        Raises:
            CalibError: fewer than 3 distinct poses.
        """
        sigmas = self.channel_sigma
        R_M, t_M = kin.pose_to_rt(measured)
        registration.require_distinct(measured, np.r_[np.full(3, sigmas[3]), np.full(3, sigmas[0])], "pose instrument")
        R_P, t_P = rotations.compose(R_X, t_X, unknowns.R_target, unknowns.t_target)  # X G = F M
        R_F = rotations.project_to_rotation(np.einsum("kij,klj->il", R_P, R_M))
        t_F = np.mean(t_P - np.einsum("ij,kj->ki", R_F, t_M), axis=0)
        start = PoseUnknowns(R_F, t_F, unknowns.R_target, unknowns.t_target)
        return registration.refine(self, start, measured, R_X, t_X)

    def unknowns_from_file(self, values) -> PoseUnknowns:
        values = np.asarray(values, dtype=float)
        return PoseUnknowns.from_pose6(
            np.r_[values[:3], np.radians(values[3:6])], np.r_[values[6:9], np.radians(values[9:12])]
        )


def theta_tangent_jacobian(theta: np.ndarray) -> np.ndarray:
    """``∂θ/∂[φ, γ]`` ``(12, 12)``: pose6 coordinates of frame and target against their body tangents."""
    J = np.zeros((12, 12))
    J[:6, :6] = rotations.pose6_tangent_jacobian(theta[:6])
    J[6:, 6:] = rotations.pose6_tangent_jacobian(theta[6:12])
    return J
