"""3-D targets (laser-tracker reflectors, photogrammetry markers): spec §7 ``kind = "points"``.

The instrument reports the position of K targets fixed on the platform, in its own frame {I}::

    m_k = F⁻¹ (X p_k) = R_Fᵀ (R_X p_k + t_X − t_F)      F = T_J_I, X = T_J_D, p_k in {D}

F (6 tangent directions) and the targets p_k (3K) are unknowns of the calibration. A target
not seen in a reading is NaN (all three coordinates) and contributes nothing. Residual
``e_k = m_k(pred) − m_k(meas)`` [mm], whitened by ``σ_pos``.

Jacobians (body perturbations ``X Exp(ξ)``, ``F Exp(φ)``)::

    ∂e_k/∂ξ = R_Fᵀ R_X [−[p_k]×, I],   ∂e_k/∂φ = [[m_k]×, −I],   ∂e_k/∂p_k = R_Fᵀ R_X
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import CalibError, SampleRejected, number
from ..model import kinematics as kin
from ..model import rotations
from ..model.kinematics import skew
from ..model.platform import INSTRUMENT_SECTIONS, Instrument, Platform
from . import registration
from .base import PoseObservation, Redundant, Residual, Spread, position_spread_mm
from .external import OutsideModel
from .gauge import kabsch

FRAME_NAMES: tuple[str, ...] = tuple(
    f"frame_{axis}" for axis in ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
)


#: the seen targets fix a pose (loose coupling) only where they leave the rotation about their best
#: line at most this σ [rad]: σ_pos / √(their squared distances off it). Collinear or coincident
#: targets leave it free (an exact line: a singular fit whose "pose" sent ekf, lm and isam2 off
#: to NaN); at 0.01 rad the linearised rotation errs by ~σ²/2 = 5e-5 of itself.
LOOSE_ROTATION_SIGMA_RAD = 0.01


def unknown_names(n_targets: int) -> tuple[str, ...]:
    """Frame then targets in file units: ``frame_x_mm … frame_yaw_deg, p1x_mm, p1y_mm, p1z_mm, …``."""
    return FRAME_NAMES + tuple(f"p{k}{axis}_mm" for k in range(1, n_targets + 1) for axis in "xyz")


#: log columns of ``K`` targets (spec §7): ``p1x_mm p1y_mm p1z_mm … pKx_mm pKy_mm pKz_mm``
columns = INSTRUMENT_SECTIONS["points"].log_columns


@dataclass(frozen=True)
class PointsUnknowns:
    """Current values: frame ``F = T_J_I`` and targets ``(K, 3)`` in {D} [mm]."""

    R_frame: np.ndarray
    t_frame: np.ndarray
    targets: np.ndarray

    @property
    def size(self) -> int:
        return 6 + self.targets.size

    def retract(self, delta: np.ndarray) -> PointsUnknowns:
        """``F Exp(φ)``, ``p + δp`` for ``delta = [φ (6), δp (3K)]``."""
        return PointsUnknowns(
            *kin.retract(self.R_frame, self.t_frame, delta[:6]), self.targets + delta[6:].reshape(-1, 3)
        )

    def in_frames(self, R_J: np.ndarray, t_J: np.ndarray, R_D: np.ndarray, t_D: np.ndarray) -> PointsUnknowns:
        """The frame and targets moved with a rigid motion ``(R_J, t_J)`` of {J} and ``(R_D, t_D)`` of {D}."""
        return PointsUnknowns(R_J @ self.R_frame, R_J @ self.t_frame + t_J, self.targets @ R_D.T + t_D)

    def file_values(self) -> np.ndarray:
        frame = kin.rt_to_pose(self.R_frame, self.t_frame)
        return np.concatenate([frame[:3], np.degrees(frame[3:]), self.targets.reshape(-1)])

    def file_jacobian(self) -> np.ndarray:
        n = 6 + self.targets.size
        J = np.eye(n)
        J[:6, :6] = rotations.pose6_tangent_jacobian(kin.rt_to_pose(self.R_frame, self.t_frame))
        J[3:6] = np.degrees(J[3:6])
        return J


def nominal(instrument: Instrument) -> PointsUnknowns:
    return PointsUnknowns(*kin.pose_to_rt(instrument.frame), np.array(instrument.targets, dtype=float))


def predict(u: PointsUnknowns, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
    """``(..., K, 3)`` target positions in {I} at platform pose X [mm]."""
    in_base = kin.transform_points(R_X, t_X, u.targets)
    return np.einsum("ji,...kj->...ki", u.R_frame, in_base - u.t_frame)


def residual(u: PointsUnknowns, measured: np.ndarray, R_X: np.ndarray, t_X: np.ndarray, jacobians: bool = False):
    """``e = m(pred) − m(meas)`` ``(..., 3K)``, NaN where a target was not seen, and if asked
    ``(∂e/∂ξ_X (..., 3K, 6), ∂e/∂[φ, p] (..., 3K, 6 + 3K))`` (rows of unseen targets are whatever
    the formula gives; the caller drops them with the NaN mask of ``e``).

    Args:
        measured: ``(..., 3K)`` readings [mm] (NaN: not seen).
    """
    K = len(u.targets)
    pred = predict(u, R_X, t_X)
    e = (pred - np.asarray(measured, dtype=float).reshape(pred.shape)).reshape(pred.shape[:-2] + (3 * K,))
    if not jacobians:
        return e, None, None
    RFt_RX = np.einsum("ji,...jk->...ik", u.R_frame, R_X)  # R_Fᵀ R_X, (..., 3, 3)
    batch = pred.shape[:-2]
    H_X = np.empty(batch + (K, 3, 6))
    H_X[..., :3] = -RFt_RX[..., None, :, :] @ skew(u.targets)
    H_X[..., 3:] = RFt_RX[..., None, :, :]
    H_u = np.zeros(batch + (K, 3, 6 + 3 * K))
    H_u[..., :3] = skew(pred)
    H_u[..., 3:6] = -np.eye(3)
    for k in range(K):
        H_u[..., k, :, 6 + 3 * k : 9 + 3 * k] = RFt_RX
    return e, H_X.reshape(batch + (3 * K, 6)), H_u.reshape(batch + (3 * K, 6 + 3 * K))


def errors(measured: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """Per reading, the RMS over its seen targets of ``‖m(pred) − m(meas)‖`` [mm] (NaN if none seen)."""
    K = pred.shape[-2]
    distance = np.linalg.norm(pred - np.asarray(measured).reshape(pred.shape[:-2] + (K, 3)), axis=-1)
    seen = np.isfinite(distance)
    total = np.where(seen, distance**2, 0.0).sum(axis=-1)
    count = seen.sum(axis=-1)
    return np.where(count > 0, np.sqrt(total / np.maximum(count, 1)), np.nan)


def register_points(R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray, sigma_mm: float) -> PointsUnknowns:
    """Frame F and targets ``p_j`` in {D} with ``F⁻¹ X_k p_j ≈ m_kj``, in closed form.

    Args:
        measured: ``(N, 3K)`` readings [mm], NaN where a target was not seen.
    Raises:
        CalibError: fewer than 3 distinct poses, or poses too poor to fix the frame and targets.
    """
    n = len(R_X)
    m = np.asarray(measured, dtype=float).reshape(n, -1, 3)
    K = m.shape[1]
    registration.require_distinct(m.reshape(n, -1), np.full(3 * K, sigma_mm), "points instrument")
    seen = np.all(np.isfinite(m), axis=2)
    poses, targets = np.nonzero(seen)
    for k in range(K):
        if registration.distinct_count(m[seen[:, k], k], np.full(3, registration.DISTINCT_SIGMAS * sigma_mm), 2) < 2:
            raise CalibError(
                f"cannot register the points instrument: target {k + 1} is seen at fewer than 2 distinct poses"
            )
    eqs = len(poses)

    def system(R_F: np.ndarray | None):
        """Rows of ``R_F m + t_F − R_X p_j = t_X`` (3 per seen target); R_F unknown when None."""
        width = (9 if R_F is None else 0) + 3 + 3 * K
        A = np.zeros((eqs, 3, width))
        col = 0
        if R_F is None:
            A[:, :, :9] = np.einsum("ea,ij->eija", m[poses, targets], np.eye(3)).reshape(eqs, 3, 9)
            col = 9
        A[:, :, col : col + 3] = np.eye(3)
        for j in range(K):
            mine = targets == j
            A[mine, :, col + 3 + 3 * j : col + 6 + 3 * j] = -R_X[poses[mine]]
        b = t_X[poses] if R_F is None else t_X[poses] - m[poses, targets] @ R_F.T
        return A.reshape(3 * eqs, width), b.reshape(-1)

    A, b = system(None)
    solution, _, rank, _ = np.linalg.lstsq(A, b, rcond=None)
    if rank < A.shape[1]:
        raise CalibError(
            f"cannot register the points instrument: its {A.shape[1]} linear unknowns have rank {rank} over these "
            "poses; expected poses that translate and rotate the targets in three dimensions"
        )
    R_F = rotations.project_to_rotation(solution[:9].reshape(3, 3))  # row-major: R_F[i, a] at 3i + a
    A, b = system(R_F)
    solution, *_ = np.linalg.lstsq(A, b, rcond=None)
    return PointsUnknowns(R_F, solution[:3], solution[3:].reshape(K, 3))


class PointsModel(OutsideModel):
    """The points instrument as a measurement model (:class:`~.external.OutsideModel`).

    Its unknowns θ are the frame's pose6 ``[x, y, z mm, roll, pitch, yaw rad]`` then the targets in
    {D} [mm] (6 + 3K values, the block ``"instrument"``; both gauges shared with the drive). Each
    seen target is one channel group; a target may go unseen (its three coordinates NaN).
    """

    kind = "points"
    unseen_channels = True
    measures_orientation = False
    noise_channel_names = ("position_mm",)

    def __init__(self, platform: Platform):
        super().__init__(platform)
        self.noise_channels = np.zeros(3 * self.instrument.n_targets, dtype=int)
        self._triples = [np.arange(3 * k, 3 * k + 3) for k in range(self.instrument.n_targets)]

    @staticmethod
    def columns_of(instrument: Instrument) -> tuple[str, ...]:
        return columns(instrument.n_targets)

    @staticmethod
    def sigmas_of(instrument: Instrument) -> np.ndarray:
        """``(3K,)`` σ of the residual's components [mm]."""
        return np.full(3 * instrument.n_targets, instrument.position_sigma_mm)

    @staticmethod
    def names_of(instrument: Instrument) -> tuple[str, ...]:
        """The names of the unknowns in file units (:func:`unknown_names`)."""
        return unknown_names(instrument.n_targets)

    @staticmethod
    def placed_on(
        platform: Platform, position_sigma_mm: float, orientation_sigma_rad: float, n_targets: int
    ) -> Instrument:
        """A nominal points instrument for a simulated study: frame at {J}'s origin, ``n_targets`` (≤ 3)
        targets halfway out towards platform joints 1, 3, 5 and 25 mm above them (a position
        instrument has no orientation σ)."""
        legs = platform.drive
        joints = legs.as_vector()[legs.gauge_columns[1]]  # the platform joints d_i (n, 3)
        targets = 0.5 * joints[0::2][:n_targets] + np.array([0.0, 0.0, 25.0])
        return Instrument("points", targets=targets, position_sigma_mm=position_sigma_mm)

    @staticmethod
    def true_unknowns(
        instrument: Instrument, frame: np.ndarray, target_offset: np.ndarray, target_spread_mm: float, rng
    ) -> PointsUnknowns:
        """A simulation's true frame (pose6 ``frame``) and targets: the nominal ones with i.i.d. normal
        errors of σ ``target_spread_mm`` a coordinate; ``target_offset`` is the pose instrument's."""
        targets = instrument.targets + rng.normal(0.0, target_spread_mm, instrument.targets.shape)
        return PointsUnknowns(*kin.pose_to_rt(frame), targets)

    @staticmethod
    def noise_draws(instrument: Instrument, n: int, rng: np.random.Generator) -> np.ndarray:
        """``(n, 4K)``: standard normal draws of each target coordinate's noise, then a uniform draw
        per target that loses it from view (:meth:`simulated_readings`)."""
        K = instrument.n_targets
        draws = rng.standard_normal((n, 4 * K))
        draws[:, 3 * K :] = rng.random((n, K))
        return draws

    @staticmethod
    def simulated_readings(
        instrument: Instrument, u: PointsUnknowns, R: np.ndarray, t: np.ndarray, draws: np.ndarray, dropout: float
    ) -> np.ndarray:
        """Readings ``(..., 3K)`` at true platform poses: ``m + σ_pos n``, a target NaN where its
        uniform draw falls below ``dropout`` (its probability of being lost from view)."""
        K = instrument.n_targets
        m = predict(u, R, t) + instrument.position_sigma_mm * draws[..., : 3 * K].reshape(draws.shape[:-1] + (K, 3))
        m[draws[..., 3 * K :] < dropout] = np.nan
        return m.reshape(draws.shape[:-1] + (3 * K,))

    @staticmethod
    def spreads(platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray) -> list[Spread]:
        """Each target's measured positions' spread against its nominal positions at the poses
        (:class:`~.base.Spread`; independent of the instrument's frame)."""
        measured = readings.reshape(len(readings), -1, 3)
        expected = kin.transform_points(R, t, platform.instrument.targets)
        return [
            Spread(
                f"target {k + 1} positions",
                slice(3 * k, 3 * k + 3),
                position_spread_mm(measured[:, k]),
                position_spread_mm(expected[:, k]),
            )
            for k in range(measured.shape[1])
        ]

    def check(self, z: np.ndarray, t_s: float) -> np.ndarray:
        reading = np.asarray(z, dtype=float)
        if reading.shape != self.channel_sigma.shape:
            raise SampleRejected(
                f"sample at t = {number(t_s)} s: expected {self.channel_sigma.size} target coordinates",
                SampleRejected.NON_FINITE,
            )
        if not np.any(np.isfinite(reading)):
            raise SampleRejected(f"sample at t = {number(t_s)} s: no target seen", SampleRejected.NON_FINITE)
        return reading

    def groups(self, z: np.ndarray) -> list[np.ndarray]:
        """One group per target seen in ``z``."""
        return [triple for triple in self._triples if np.all(np.isfinite(z[triple]))]

    def _unknowns(self, theta: np.ndarray) -> PointsUnknowns:
        return PointsUnknowns(*kin.pose_to_rt(theta[:6]), np.reshape(theta[6:], (-1, 3)))

    def _theta_jacobian_inverse(self, theta: np.ndarray) -> np.ndarray:
        J = np.eye(len(theta))
        J[:6, :6] = np.linalg.inv(rotations.pose6_tangent_jacobian(theta[:6]))
        return J

    def residual(self, R: np.ndarray, t: np.ndarray, theta: np.ndarray, z: np.ndarray, channels: np.ndarray):
        """Predicted minus measured target coordinates on ``channels`` [mm], ``∂/∂ξ``, ``∂/∂θ``."""
        e, H_X, H_u = residual(self._unknowns(theta), z, R, t, jacobians=True)
        J_theta = H_u @ self._theta_jacobian_inverse(theta)
        return Residual(e[channels], H_X[channels], J_theta[channels], np.asarray(channels))

    def pose(self, z: np.ndarray, theta: np.ndarray, guess):
        """The platform pose that puts the seen targets where they were read (Kabsch of the targets
        in {D} onto ``F m_k``), its covariance ``σ² (Σ J_kᵀ J_k)⁻¹`` and ``∂ξ/∂θ`` (implicit function
        theorem on the fit's normal equations); None with fewer than 3 targets seen, or targets
        (nearly) on one line (:data:`LOOSE_ROTATION_SIGMA_RAD`): the drive's kinematics then carry
        the pose, as with one or two targets."""
        u = self._unknowns(theta)
        m = np.reshape(z, (-1, 3))
        seen = np.all(np.isfinite(m), axis=1)
        if seen.sum() < 3:
            return None
        targets = u.targets[seen]
        off_line = np.linalg.svd(targets - targets.mean(axis=0), compute_uv=False)[1:]
        if self.instrument.position_sigma_mm > LOOSE_ROTATION_SIGMA_RAD * np.sqrt(np.sum(off_line**2)):
            return None
        in_base = kin.transform_points(u.R_frame, u.t_frame, m[seen])
        R_X, t_X = kabsch(u.targets[seen], in_base)
        rows = np.flatnonzero(np.repeat(seen, 3))
        e, H_X, H_u = residual(u, z, R_X, t_X, jacobians=True)
        A = H_X[rows]
        information = A.T @ A
        sigma2 = self.instrument.position_sigma_mm**2
        covariance = sigma2 * np.linalg.inv(information)
        J_u = H_u[rows] @ self._theta_jacobian_inverse(theta)
        J_theta = -np.linalg.solve(information, A.T @ J_u)
        # the readings' 3k − 6 directions no pose moves (the targets' distances): left out, the targets'
        # shape is seen only through the drive's legs, and its error there bends the implied pose
        left_over = np.linalg.svd(A, full_matrices=True)[0][:, 6:].T
        redundant = Redundant(left_over @ e[rows], left_over @ J_u, sigma2 * np.eye(len(left_over)))
        return PoseObservation(R_X, t_X, covariance, J_theta, redundant)

    # what the callers of an outside instrument ask (external.OutsideModel)

    def nominal_unknowns(self) -> PointsUnknowns:
        return nominal(self.instrument)

    def _angles(self) -> np.ndarray:
        angles = np.zeros(6 + 3 * self.instrument.n_targets, dtype=bool)
        angles[3:6] = True
        return angles

    def theta(self, unknowns: PointsUnknowns) -> np.ndarray:
        return np.concatenate([kin.rt_to_pose(unknowns.R_frame, unknowns.t_frame), unknowns.targets.reshape(-1)])

    def theta_jacobian(self, unknowns: PointsUnknowns) -> np.ndarray:
        J = np.eye(unknowns.size)
        J[:6, :6] = rotations.pose6_tangent_jacobian(kin.rt_to_pose(unknowns.R_frame, unknowns.t_frame))
        return J

    def readings_residual(self, unknowns, measured, R_X, t_X, jacobians=False):
        return residual(unknowns, measured, R_X, t_X, jacobians)

    def predicted_readings(self, unknowns, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        return predict(unknowns, R_X, t_X).reshape(len(R_X), -1)

    def seen_channels(self, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        """A target out of its cone of visibility is not read (:func:`visible_targets`)."""
        return np.repeat(visible_targets(self.instrument, R_X, t_X), 3, axis=-1)

    def prediction_errors(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, readings: np.ndarray):
        """Points give no orientation error."""
        predicted = predict(unknowns, R_X, t_X)
        seen = np.isfinite(readings.reshape(predicted.shape))
        return np.where(seen, predicted, np.nan).reshape(len(R_X), -1), errors(readings, predicted), None

    def error_weights(self, seen: np.ndarray) -> tuple[np.ndarray, None]:
        """A row's squared error is the mean over its targets seen of theirs (:func:`errors`)."""
        targets = np.all(seen.reshape(len(seen), -1, 3), axis=-1)
        per_target = 1.0 / np.maximum(targets.sum(axis=-1, keepdims=True), 1)
        return np.repeat(np.where(targets, per_target, 0.0), 3, axis=-1), None

    def position_differences(self, readings: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """One row a target seen."""
        difference = (readings - predicted).reshape(-1, 3)
        return difference[np.all(np.isfinite(difference), axis=1)]

    def instrument_at(self, theta: np.ndarray) -> Instrument:
        return replace(self.instrument, frame=theta[:6], targets=theta[6:].reshape(-1, 3))

    def register(self, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> PointsUnknowns:
        return register_points(R_X, t_X, measured, self.instrument.position_sigma_mm)

    def refit_frame(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> PointsUnknowns:
        """Kabsch of the targets seen onto their readings for F, then :func:`~.registration.refine`.

        Raises:
            CalibError: fewer than 3 distinct poses.
        """
        n = len(R_X)
        m = np.asarray(measured, dtype=float).reshape(n, -1, 3)
        registration.require_distinct(
            m.reshape(n, -1), np.full(m.shape[1] * 3, self.channel_sigma[0]), "points instrument"
        )
        in_base = kin.transform_points(R_X, t_X, unknowns.targets)
        seen = np.all(np.isfinite(m), axis=2)
        R_F, t_F = kabsch(m[seen], in_base[seen])  # y = R_F m + t_F
        start = PointsUnknowns(R_F, t_F, unknowns.targets)
        return registration.refine(self, start, measured, R_X, t_X)

    def unknowns_from_file(self, values) -> PointsUnknowns:
        values = np.asarray(values, dtype=float)
        return PointsUnknowns(*kin.pose_to_rt(np.r_[values[:3], np.radians(values[3:6])]), values[6:].reshape(-1, 3))


def visible_targets(instrument: Instrument, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N, K)`` True where a points instrument sees target k at platform pose ``(R, t)``: always
    without ``[instrument] visibility_cone_deg``; with it, where the line from the target to the
    instrument's nominal origin lies within that half-angle of the target's axis
    (``target_axes``, in {D}; default {D}'s z)."""
    n = len(np.reshape(t, (-1, 3)))
    if instrument.visibility_cone_deg is None:
        return np.ones((n, instrument.n_targets), dtype=bool)
    R, t = np.reshape(R, (-1, 3, 3)), np.reshape(t, (-1, 3))
    in_base = np.einsum("nij,kj->nki", R, instrument.targets) + t[:, None, :]
    sight = instrument.frame[:3] - in_base
    axes = np.einsum("nij,kj->nki", R, instrument.target_axes)
    cosine = np.sum(sight * axes, axis=-1) / (
        np.linalg.norm(sight, axis=-1) * np.linalg.norm(axes, axis=-1) + np.finfo(float).tiny
    )
    return cosine >= np.cos(np.radians(instrument.visibility_cone_deg))
