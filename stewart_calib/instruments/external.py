"""The instruments outside the robot (spec §7 ``pose`` and ``points``) behind one interface.

:func:`model_for` gives, for a platform whose ``[instrument]`` is not the tracker, what an
estimator needs: the log columns, the residual and its Jacobians (the kind's module), the
noise of a reading's components and the channels they belong to, the unknowns' names and
nominal values, the closed-form registration and the per-sample checks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import ModuleType

import numpy as np

from ..errors import CalibError, SampleRejected
from ..kinematics import pose_to_rt, rt_to_pose
from ..platform import N_PARAMS, Instrument, Platform
from ..samples import Sample
from ..unknowns import UnknownBlock
from . import lie, points, pose, registration

#: prior σ of the instrument's unknowns for the methods that take one (ekf, isam2, lm), about the
#: nominal that calibrate sets by the closed-form registration (:func:`registered_platform`): what
#: registration leaves is the drive errors' share, some mm and a degree or two, so 20 mm / 0.2 rad
#: cover it 3× over while keeping the normal equations of a hard-gauged graph within double
#: precision (a 1 m / π prior beside a 1e-6 mm gauge tie made lm's Cholesky indeterminate)
PRIOR_SIGMA_MM = 20.0
PRIOR_SIGMA_RAD = 0.2


@dataclass(frozen=True)
class ExternalModel:
    """A ``pose`` or ``points`` instrument of a platform (see the module docstring).

    Attributes:
        platform: the platform whose ``[instrument]`` this is.
        module: :mod:`.pose` or :mod:`.points` (``residual``, ``predict``, unknowns' class).
        sigmas: ``(m,)`` σ of a reading's components (rad for angles, mm).
        channels: ``(m,)`` noise channel of each component; ``channel_names`` name them.
    """

    platform: Platform
    module: ModuleType
    sigmas: np.ndarray
    channels: np.ndarray
    channel_names: tuple[str, ...]

    @property
    def kind(self) -> str:
        return self.platform.instrument.kind

    @property
    def unknown_names(self) -> tuple[str, ...]:
        return self.module.names(self.platform.instrument)

    def nominal_unknowns(self):
        return self.module.nominal(self.platform.instrument)

    def _angles(self) -> np.ndarray:
        """``(n,)`` True where θ holds an angle [rad]: roll, pitch, yaw of the frame (and target)."""
        angles = np.zeros(self.nominal_unknowns().size, dtype=bool)
        angles[3:6] = True
        if self.kind == "pose":
            angles[9:12] = True
        return angles

    def theta(self, unknowns) -> np.ndarray:
        """The unknowns as the vector θ of the unknown layout (code units): the frame's pose6
        ``[x, y, z mm, roll, pitch, yaw rad]``, then the target's pose6 or the targets [mm]."""
        parts = [rt_to_pose(unknowns.R_frame, unknowns.t_frame)]
        parts.append(
            rt_to_pose(unknowns.R_target, unknowns.t_target) if self.kind == "pose" else unknowns.targets.reshape(-1)
        )
        return np.concatenate(parts)

    def theta_jacobian(self, unknowns) -> np.ndarray:
        """``∂θ/∂(tangent)`` of :meth:`theta` for the body perturbations of ``retract``."""
        J = np.eye(unknowns.size)
        J[:6, :6] = lie.pose6_tangent_jacobian(self.theta(unknowns)[:6])
        if self.kind == "pose":
            J[6:12, 6:12] = lie.pose6_tangent_jacobian(self.theta(unknowns)[6:12])
        return J

    def block(self) -> UnknownBlock:
        """The instrument's :class:`~stewart_calib.unknowns.UnknownBlock` (spec §7 ``"instrument"``):
        it shares both gauges with the drive (frame ↔ base joints, target(s) ↔ platform joints)."""
        angles = self._angles()
        return UnknownBlock(
            "instrument",
            self.unknown_names,
            self.theta(self.nominal_unknowns()),
            np.where(angles, PRIOR_SIGMA_RAD, PRIOR_SIGMA_MM),
            np.where(angles, 180.0 / np.pi, 1.0),
            gauge=("base", "platform"),
        )

    def predicted_readings(self, unknowns, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        """``(N, m)`` the readings at platform poses X, code units (every target, seen or not)."""
        predicted = self.module.predict(unknowns, R_X, t_X)
        return rt_to_pose(*predicted) if self.kind == "pose" else predicted.reshape(len(R_X), -1)

    def seen_channels(self, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        """``(N, m)`` True where the instrument reads the channel at platform pose X (a points
        target out of its cone of visibility is not read: :func:`visible_targets`)."""
        if self.kind == "pose":
            return np.ones((len(R_X), self.sigmas.size), dtype=bool)
        return np.repeat(visible_targets(self.platform, R_X, t_X), 3, axis=-1)

    def prediction_errors(
        self, unknowns, R_X: np.ndarray, t_X: np.ndarray, readings: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The readings predicted at platform poses X and the log's errors against them (spec §7
        validation columns): ``(predicted (N, m) code units, NaN where the log saw nothing;
        position error (N,) [mm]; orientation error (N,) [deg], None for points, which give none)``."""
        if self.kind == "pose":
            R_P, t_P = self.module.predict(unknowns, R_X, t_X)
            R_m, t_m = pose_to_rt(readings)
            position, orientation = self.module.errors(R_m, t_m, R_P, t_P)
            return rt_to_pose(R_P, t_P), position, orientation
        predicted = self.module.predict(unknowns, R_X, t_X)
        seen = np.isfinite(readings.reshape(predicted.shape))
        return np.where(seen, predicted, np.nan).reshape(len(R_X), -1), self.module.errors(readings, predicted), None

    def position_differences(self, readings: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """``(n, 3)`` measured minus predicted positions [mm]: one row a sample for a pose (in the
        instrument's axes), one a target seen for points."""
        if self.kind == "pose":
            return readings[:, :3] - predicted[:, :3]
        difference = (readings - predicted).reshape(-1, 3)
        return difference[np.all(np.isfinite(difference), axis=1)]

    def platform_poses(self, unknowns, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(R (N, 3, 3), t (N, 3))`` the platform poses ``X = F M G⁻¹`` the readings put the
        platform at, frame and target at ``unknowns``; None for points, whose one reading fixes no
        orientation (only a fit over the targets seen would)."""
        if self.kind != "pose":
            return None
        R_M, t_M = pose_to_rt(readings)
        return lie.compose(
            *lie.compose(unknowns.R_frame, unknowns.t_frame, R_M, t_M),
            *lie.inverse(unknowns.R_target, unknowns.t_target),
        )

    def instrument_at(self, theta: np.ndarray) -> Instrument:
        """The platform file's ``[instrument]`` with its frame and target(s) at ``θ`` (:meth:`theta`'s layout)."""
        if self.kind == "pose":
            return replace(self.platform.instrument, frame=theta[:6], target=theta[6:12])
        return replace(self.platform.instrument, frame=theta[:6], targets=theta[6:].reshape(-1, 3))

    def register(self, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray):
        """Closed-form frame and target(s) mapping platform poses X onto the readings."""
        if self.kind == "pose":
            return registration.register_pose(R_X, t_X, *pose_to_rt(measured), self.sigmas)
        return registration.register_points(R_X, t_X, measured, self.platform.instrument.position_sigma_mm)

    def refit_frame(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray):
        """The frame fitted again, target(s) held (``validate --register-instrument``)."""
        return registration.refit_frame(self.module, unknowns, measured, R_X, t_X, self.sigmas)

    def unknowns_from_file(self, values) -> object:
        """Unknowns from their file values (a result's ``"instrument"`` block)."""
        values = np.asarray(values, dtype=float)
        frame = np.r_[values[:3], np.radians(values[3:6])]
        if self.kind == "pose":
            return pose.PoseUnknowns.from_pose6(frame, np.r_[values[6:9], np.radians(values[9:12])])
        return points.PointsUnknowns(*pose_to_rt(frame), values[6:].reshape(-1, 3))

    def check(self, sample: Sample) -> tuple[np.ndarray, np.ndarray]:
        """Strokes and readings of ``sample``, or :class:`SampleRejected` (non-finite, out of range,
        a pose reading with a missing value, a points reading that saw no target)."""
        strokes = np.asarray(sample.strokes, dtype=float)
        readings = np.asarray(sample.readings, dtype=float)
        where = f"sample at t = {sample.t_s} s"
        if not math.isfinite(sample.t_s):
            raise SampleRejected(f"{where}: non-finite time", SampleRejected.NON_FINITE)
        if strokes.shape != (6,) or not np.all(np.isfinite(strokes)):
            raise SampleRejected(f"{where}: expected 6 finite strokes q", SampleRejected.NON_FINITE)
        bounds = self.platform.stroke_range
        if bounds is not None and np.any((strokes < bounds[0]) | (strokes > bounds[1])):
            i = int(np.flatnonzero((strokes < bounds[0]) | (strokes > bounds[1]))[0])
            raise SampleRejected(
                f"{where}: stroke q{i + 1} = {strokes[i]:.6g} mm outside {list(bounds)} mm", SampleRejected.OUT_OF_RANGE
            )
        if readings.shape != self.sigmas.shape:
            raise SampleRejected(
                f"{where}: expected {self.sigmas.size} {self.kind} readings, got shape {readings.shape}",
                SampleRejected.NON_FINITE,
            )
        if self.kind == "pose" and not np.all(np.isfinite(readings)):
            raise SampleRejected(f"{where}: the pose reading is not finite", SampleRejected.NON_FINITE)
        if self.kind == "points" and not np.any(np.isfinite(readings)):
            raise SampleRejected(f"{where}: no target seen", SampleRejected.NON_FINITE)
        return strokes, readings


def registered_platform(platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
    """``platform`` with its instrument's nominal frame and target(s) replaced by the closed-form
    registration of the nominal forward-kinematics poses onto the readings
    (:mod:`.registration`): every method then starts within the drive's errors of the answer, not
    a frame 100 mm and any rotation away, and no prior needs widening.

    Raises:
        CalibError: the log cannot be registered (fewer than 3 distinct poses, no rotation), or
            the nominal drive reaches none of its strokes.
    """
    from ..drive import drive_model

    model = model_for(platform)
    drive = drive_model(platform)
    # an elastic drive settles under the platform's weight alone here: a payload moves the legs by
    # micrometres to a millimetre, within what registration is for (the fit starts from it)
    fk, _ = drive.settled_kinematics(strokes, strict=False)
    usable = fk.converged & np.any(np.isfinite(readings), axis=1)
    if not np.any(usable):
        raise CalibError("cannot register the instrument: nominal forward kinematics converged for no sample")
    unknowns = model.register(fk.R[usable], fk.t[usable], np.asarray(readings)[usable])
    return replace(platform, instrument=model.instrument_at(model.theta(unknowns)))


def model_for(platform: Platform) -> ExternalModel:
    """The outside instrument of ``platform``.

    Raises:
        CalibError: the platform's instrument is the tracker.
    """
    instrument = platform.instrument
    if instrument.kind == "pose":
        return ExternalModel(
            platform, pose, pose.sigmas(instrument), np.r_[0, 0, 0, 1, 1, 1], ("orientation_rad", "position_mm")
        )
    if instrument.kind == "points":
        return ExternalModel(
            platform, points, points.sigmas(instrument), np.zeros(3 * instrument.n_targets, dtype=int), ("position_mm",)
        )
    raise CalibError(f"{platform.source}: the instrument is the tracker, not an instrument outside the robot")


def information_rows(
    platform: Platform, poses: np.ndarray, seen: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Each pose's whitened rows of the identification Jacobian of an outside instrument, at the
    nominal drive and the platform file's instrument: what the batch fit (``ls``) would see, the
    Fisher information of a pose set being ``Σ_k A_kᵀ A_k``.

    The unknowns are reduced as the batch fit reduces them: the 30 drive directions the gauge
    leaves free (:func:`~stewart_calib.instruments.gauge.free_basis`), the stroke scale ``k1…k6``
    and the instrument's tangent; ``lift`` maps them to ``[x_drive, instrument]`` (``x_drive`` of the
    drive model with every term unknown: δM, then the stroke scale and any other term).

    Args:
        poses: ``(N, 6)`` pose6 ``[mm, rad]`` the robot is driven to.
        seen: points only, ``(N, K)`` which targets the instrument saw (a log's finite readings);
            default :func:`visible_targets`.
    Returns:
        ``(rows (N, m, p), lift (drive size + n_instrument, p))``; a target the instrument cannot see at a
        pose (:func:`visible_targets`) has zero rows there.
    """
    from ..drive import drive_model
    from . import gauge

    model = model_for(platform)
    drive = drive_model(platform).identifying()
    R, t = pose_to_rt(np.asarray(poses, dtype=float).reshape(-1, 6))
    unknowns = model.nominal_unknowns()
    readings = model.predicted_readings(unknowns, R, t)
    _, H_X, H_u = model.module.residual(unknowns, readings, R, t, jacobians=True)
    dxi = drive.pose_jacobian(None, R, t, drive.inputs_near(drive.inverse_kinematics(R, t), None, (R, t)))
    basis = gauge.free_basis(platform.drive)
    columns = [H_X @ dxi[..., :N_PARAMS] @ basis, H_X @ dxi[..., N_PARAMS:], H_u]
    rows = np.concatenate(columns, axis=-1) / model.sigmas[:, None]
    if model.kind == "points":
        seen = visible_targets(platform, R, t) if seen is None else np.asarray(seen, dtype=bool)
        rows = np.where(np.repeat(seen, 3, axis=-1)[..., None], rows, 0.0)
    n_free, n_rest = basis.shape[1], drive.size - N_PARAMS + unknowns.size
    lift = np.zeros((N_PARAMS + n_rest, n_free + n_rest))
    lift[:N_PARAMS, :n_free] = basis
    lift[N_PARAMS:, n_free:] = np.eye(n_rest)
    return rows, lift


def visible_targets(platform: Platform, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(N, K)`` True where a points instrument sees target k at platform pose ``(R, t)``: always
    without ``[instrument] visibility_cone_deg``; with it, where the line from the target to the
    instrument's nominal origin lies within that half-angle of the target's axis
    (``target_axes``, in {D}; default {D}'s z)."""
    instrument = platform.instrument
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
