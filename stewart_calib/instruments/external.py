"""What the instruments outside the robot (spec §7 ``pose`` and ``points``) share.

:class:`OutsideModel` is the :class:`~.base.InstrumentModel` of an instrument in a frame of its
own, with everything its callers need beyond what an estimator observes: the log's vectorised
residual (the batch fit), the unknowns' values and their layout θ, the closed-form registration,
the predicted readings and their errors (validation), the platform poses a reading fixes
(diagnosis) and a simulation's truth. What is common is written here once; what differs by kind
is an abstract method its subclass (:class:`~.pose.PoseModel`, :class:`~.points.PointsModel`)
answers, so nothing here asks which kind it is.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from dataclasses import replace
from typing import Any, ClassVar

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..model.kinematics import pose_to_rt
from ..model.platform import Instrument, Platform
from ..model.unknowns import UnknownBlock
from . import gauge, registration
from .base import InstrumentModel

#: prior σ of the instrument's unknowns for the methods that take one (ekf, isam2, lm), about the
#: nominal that calibrate sets by the registration (:meth:`OutsideModel.registered_platform`):
#: what registration leaves is the drive errors' share, some mm and a degree or two, so 20 mm / 0.2 rad
#: cover it 3× over while keeping the normal equations of a hard-gauged graph within double
#: precision (a 1 m / π prior beside a 1e-6 mm gauge tie made lm's Cholesky indeterminate)
PRIOR_SIGMA_MM = 20.0
PRIOR_SIGMA_RAD = 0.2
#: how far from the robot an instrument's origin may stand [mm] (a laser tracker on its stand, motion
#: capture's origin on the floor). The frame's orientation turns about that origin, so what registration
#: leaves of it moves the origin's place by the lever arm: its prior σ there is
#: ``hypot(PRIOR_SIGMA_MM, PRIOR_SIGMA_RAD · reach)``, 0.6 m: a prior of 20 mm there pulls the fit of a
#: robot seen from metres away (tests/test_instrument_methods.py)
INSTRUMENT_REACH_MM = 3000.0


class OutsideModel(InstrumentModel):
    """An instrument outside the robot, of ``platform`` (see the module docstring).

    Its unknowns (``Any`` below: :class:`~.pose.PoseUnknowns` or :class:`~.points.PointsUnknowns`)
    are a frame ``F = T_J_I`` and target(s) in {D}; θ (:meth:`theta`) holds them in code units,
    the frame's pose6 first.

    Attributes:
        platform: the platform whose ``[instrument]`` this is.
        instrument: that ``[instrument]``.
        noise_channels: ``(m,)`` the noise channel of each component of a reading;
            ``noise_channel_names`` name them (the batch fit estimates a σ each).
    """

    outside = True
    registers = True
    unknowns: UnknownBlock
    noise_channels: np.ndarray
    noise_channel_names: ClassVar[tuple[str, ...]]

    def __init__(self, platform: Platform):
        self.platform = platform
        self.instrument = platform.instrument
        self.columns = self.columns_of(self.instrument)
        self.channel_sigma = self.sigmas_of(self.instrument)
        self.unknowns = self._block()

    @classmethod
    def build(cls, platform: Platform, noise: NoiseConfig) -> OutsideModel:
        """Its σ are the platform file's: ``noise`` is the tracker's."""
        return cls(platform)

    # ------------------------------------------------------------------ per kind

    @staticmethod
    @abstractmethod
    def sigmas_of(instrument: Instrument) -> np.ndarray:
        """``(m,)`` σ of a reading's components (rad for angles, mm)."""

    @staticmethod
    @abstractmethod
    def names_of(instrument: Instrument) -> tuple[str, ...]:
        """The names of the unknowns in file units (spec §7 result ``"instrument"`` block)."""

    @abstractmethod
    def nominal_unknowns(self) -> Any:
        """The platform file's frame and target(s)."""

    @abstractmethod
    def theta(self, unknowns) -> np.ndarray:
        """The unknowns as the vector θ of the unknown layout (code units): the frame's pose6
        ``[x, y, z mm, roll, pitch, yaw rad]``, then the target's pose6 or the targets [mm]."""

    @abstractmethod
    def theta_jacobian(self, unknowns) -> np.ndarray:
        """``∂θ/∂(tangent)`` of :meth:`theta` for the body perturbations of ``retract``."""

    @abstractmethod
    def _angles(self) -> np.ndarray:
        """``(n,)`` True where θ holds an angle [rad]."""

    @abstractmethod
    def readings_residual(self, unknowns, measured: np.ndarray, R_X: np.ndarray, t_X: np.ndarray, jacobians=False):
        """Predicted minus measured ``e (..., m)`` (NaN where a channel was not read) of readings
        at platform poses X and, if asked, ``(∂e/∂ξ_X (..., m, 6), ∂e/∂(tangent) (..., m, n))``, else
        ``(e, None, None)``."""

    @abstractmethod
    def predicted_readings(self, unknowns, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        """``(N, m)`` the readings at platform poses X, code units (every channel, read or not)."""

    @abstractmethod
    def prediction_errors(
        self, unknowns, R_X: np.ndarray, t_X: np.ndarray, readings: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """The readings predicted at platform poses X and the log's errors against them (spec §7
        validation columns): ``(predicted (N, m) code units, NaN where the log read nothing;
        position error (N,) [mm]; orientation error (N,) [deg], None where the kind gives none)``."""

    @abstractmethod
    def error_weights(self, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """Each reading component's weight in one row's squared errors of :meth:`prediction_errors`,
        ``(position (N, m) [1], orientation (N, m) [deg²/rad²] or None where the kind gives none)``,
        the components ``seen`` (N, m) read: a row's squared error is ``Σ_j w_j e_j²`` of its residual
        ``e`` (validate's noise, :func:`~stewart_calib.workflows.validation.noise_squares`)."""

    @abstractmethod
    def position_differences(self, readings: np.ndarray, predicted: np.ndarray) -> np.ndarray:
        """``(n, 3)`` measured minus predicted positions [mm]: one row a position read."""

    @abstractmethod
    def instrument_at(self, theta: np.ndarray) -> Instrument:
        """The platform file's ``[instrument]`` with its frame and target(s) at ``θ`` (:meth:`theta`'s layout)."""

    @abstractmethod
    def register(self, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> Any:
        """Closed-form frame and target(s) mapping platform poses X onto the readings.

        Raises:
            CalibError: fewer than 3 distinct poses, or poses too poor to fix them.
        """

    @abstractmethod
    def refit_frame(self, unknowns, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray) -> Any:
        """The frame fitted again, target(s) held (``validate --register-instrument``)."""

    @abstractmethod
    def unknowns_from_file(self, values) -> Any:
        """Unknowns from their file values (a result's ``"instrument"`` block)."""

    def best_registration(self, R_X: np.ndarray, t_X: np.ndarray, measured: np.ndarray, plain: bool = False) -> Any:
        """The frame and target(s) that best map platform poses X onto the readings: the closed
        form (:meth:`register`), then least squares over all of them (:func:`~.registration.refine`)
        — the same instrument unknowns a calibration fits, so that the nominal model's errors here
        are what it leaves at its best, not where the cameras and the rigid body's origin happen to
        be. Weighed by the instrument's σ (the maximum-likelihood registration), or ``plain``:
        unweighted in SI units (position [m], rotation [rad]), the registration a user computes
        without a noise model — the "before" every command prints, so that it never looks better
        or worse than that by the choice of weights.

        Raises:
            CalibError: as :meth:`register`.
        """
        start = self.register(R_X, t_X, measured)
        scale = registration.si_scale(self) if plain else None
        return registration.refine(self, start, measured, R_X, t_X, frame_only=False, scale=scale)

    def file_values(self, unknowns) -> np.ndarray:
        """The unknowns in file units (a result's ``"instrument"`` block): :meth:`unknowns_from_file`'s inverse."""
        return self.theta(unknowns) * self.unknowns.file_scale

    def seen_channels(self, R_X: np.ndarray, t_X: np.ndarray) -> np.ndarray:
        """``(N, m)`` True where the instrument reads the channel at platform pose X: all of them,
        unless the kind can lose a channel from view."""
        return np.ones((len(R_X), self.channel_sigma.size), dtype=bool)

    def platform_poses(self, unknowns, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(R (N, 3, 3), t (N, 3))`` the platform poses the readings put the platform at, frame
        and target(s) at ``unknowns``; None where one reading fixes no pose."""
        return None

    # a simulation's truth (simulation/instrument.py)

    @staticmethod
    @abstractmethod
    def true_unknowns(instrument: Instrument, frame: np.ndarray, target_offset: np.ndarray, target_spread_mm, rng):
        """A simulation's true frame (pose6 ``frame``) and target(s) about ``instrument``'s."""

    @staticmethod
    @abstractmethod
    def noise_draws(instrument: Instrument, n: int, rng: np.random.Generator) -> np.ndarray:
        """``(n, ·)`` the random draws of ``n`` simulated readings' noise (and losses from view)."""

    @staticmethod
    @abstractmethod
    def simulated_readings(
        instrument: Instrument, u, R: np.ndarray, t: np.ndarray, draws: np.ndarray, dropout: float
    ) -> np.ndarray:
        """Readings ``(..., m)`` at true platform poses with :meth:`noise_draws`' draws."""

    # ------------------------------------------------------------------ shared

    @property
    def unknown_names(self) -> tuple[str, ...]:
        return self.names_of(self.instrument)

    def _block(self) -> UnknownBlock:
        """The instrument's :class:`~stewart_calib.model.unknowns.UnknownBlock` (spec §7 ``"instrument"``):
        it shares both gauges with the drive (frame ↔ base joints, target(s) ↔ platform joints)."""
        angles = self._angles()
        sigma = np.where(angles, PRIOR_SIGMA_RAD, PRIOR_SIGMA_MM)
        sigma[:3] = math.hypot(PRIOR_SIGMA_MM, PRIOR_SIGMA_RAD * INSTRUMENT_REACH_MM)  # θ: the frame's place first
        return UnknownBlock(
            "instrument",
            self.unknown_names,
            self.theta(self.nominal_unknowns()),
            sigma,
            np.where(angles, 180.0 / np.pi, 1.0),
            gauge=("base", "platform"),
        )

    @classmethod
    def registered_platform(cls, platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
        """``platform`` with its instrument's nominal frame and target(s) replaced by the registration
        of the nominal forward-kinematics poses onto the readings (:meth:`best_registration`: the closed
        form refined by least squares): every method then starts within the drive's errors of the
        answer, not a frame 100 mm and any rotation away. The closed form alone, from orientations that
        the drive's errors turn by a degree or two, can leave the frame's orientation 0.25 rad off,
        metres at the robot where the instrument stands metres away.

        Raises:
            CalibError: the log cannot be registered (fewer than 3 distinct poses, no rotation), or
                the nominal drive reaches none of its strokes.
        """
        from ..model.drive import drive_model

        model = cls(platform)
        # an elastic drive settles under the platform's weight alone here: a payload moves the legs by
        # micrometres to a millimetre, within what registration is for (the fit starts from it)
        fk, _ = drive_model(platform).settled_kinematics(strokes, strict=False)
        usable = fk.converged & np.any(np.isfinite(readings), axis=1)
        if not np.any(usable):
            raise CalibError("cannot register the instrument: nominal forward kinematics converged for no sample")
        unknowns = model.best_registration(fk.R[usable], fk.t[usable], np.asarray(readings)[usable])
        return replace(platform, instrument=model.instrument_at(model.theta(unknowns)))

    def information_rows(
        self, poses: np.ndarray, seen: np.ndarray | None = None, channels=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each pose's whitened rows of the identification Jacobian, at the nominal drive and the
        platform file's instrument: what the batch fit (``ls``) would see, the Fisher information
        of a pose set being ``Σ_k A_kᵀ A_k``.

        The unknowns are reduced as the batch fit reduces them: the 30 drive directions the gauge
        leaves free (:func:`~stewart_calib.instruments.gauge.free_basis`), the drive's terms (the
        stroke scale ``k1…k6`` and any other) and the instrument's tangent; ``lift`` maps them to
        ``[x_drive, instrument]`` (``x_drive`` of the drive model with every term unknown).

        Args:
            poses: ``(N, 6)`` pose6 ``[mm, rad]`` the robot is driven to.
            seen: ``(N, m)`` which channels the instrument read (a log's finite readings); default
                :meth:`seen_channels`.
            channels: the poses' input channels (a log's ``inputs``, row for row: its payloads, whose
                leg forces let the compliance be told from the leg lengths, spec §10; temperatures);
                default none, the platform's own weight at the reference temperature.
        Returns:
            ``(rows (N, m, p), lift (drive size + n_instrument, p))``; a channel not read at a pose
            has zero rows there.
        """
        from ..model.drive import drive_model

        drive = drive_model(self.platform).identifying()
        R, t = pose_to_rt(np.asarray(poses, dtype=float).reshape(-1, 6))
        unknowns = self.nominal_unknowns()
        readings = self.predicted_readings(unknowns, R, t)
        _, H_X, H_u = self.readings_residual(unknowns, readings, R, t, jacobians=True)
        strokes = drive.inverse_kinematics(R, t, channels=channels)
        # the fit's own rows: the leg forces move with the pose and the joints, a deflection c f(ξ, M) the
        # weak leg-length directions see at a nominal compliance c ≠ 0 (the rigid rows where c = 0)
        inputs = drive.inputs_near(strokes, channels, (R, t))
        dxi = drive.settled_pose_jacobian(None, R, t, inputs, channels)
        basis = gauge.free_basis(self.platform.drive)
        m = drive.n_params
        columns = [H_X @ dxi[..., :m] @ basis, H_X @ dxi[..., m:], H_u]
        rows = np.concatenate(columns, axis=-1) / self.channel_sigma[:, None]
        seen = self.seen_channels(R, t) if seen is None else np.asarray(seen, dtype=bool)
        rows = np.where(seen[..., None], rows, 0.0)
        n_free, n_rest = basis.shape[1], drive.size - m + unknowns.size
        lift = np.zeros((m + n_rest, n_free + n_rest))
        lift[:m, :n_free] = basis
        lift[m:, n_free:] = np.eye(n_rest)
        return rows, lift
