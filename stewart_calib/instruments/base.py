"""The one instrument interface, :class:`InstrumentModel`: what an instrument observes of the
platform pose, and what its kind is.

Every estimator talks to the instrument only through an instance of a subclass, and the rest of
the package asks the subclass itself (:mod:`.registry`: kind → class), so adding an instrument
touches :mod:`stewart_calib.instruments`, one entry in :mod:`.registry` and one in
:data:`stewart_calib.model.platform.INSTRUMENT_SECTIONS` — never an estimator (docs/architecture.md,
with the tracker as the worked example). An instrument outside the robot subclasses
:class:`~.external.OutsideModel`, which adds what its registration, validation, diagnosis and
simulation ask.

A model is a description, not a state: it holds its geometry and noise and answers pure
functions of the pose ``(R, t)`` of {D} in {J} (mm, rad), its own unknowns ``θ`` and one
measurement ``z``:

* ``kind`` — the ``[instrument] kind`` of the platform file (spec §7);
* ``columns`` — the log columns it reads, in the order of ``z`` (``Sample.readings`` holds
  ``z`` in code units: mm and rad; a channel not measured in a row, e.g. a hidden target, is NaN);
  the kind's ``angle_columns`` name those that hold angles (degrees in the file, radians in ``z``:
  the log reader and writers convert them), every other one a length (mm in both);
* ``unknowns`` — its own :class:`~stewart_calib.model.unknowns.UnknownBlock` (names, nominal ``θ₀``
  in code units, prior σ, which gauge directions the drive shares), or None when it is known
  exactly. ``θ`` passed to the functions is always absolute: ``θ₀ + error``; ``()`` when None;
* ``channel_sigma`` — ``(M,)`` σ of each channel of ``z`` [code units]: white, independent;
* ``compiled_legs`` — where the model offers compiled kernels: the :class:`~stewart_calib.model.platform.LegGeometry`
  of known geometry whose extensions the readings are (σ ``channel_sigma[0]`` each), so that the EKF
  solves the pose and observes through it in compiled code (:class:`~stewart_calib.estimators.measurement.LegSetPose`);
  None otherwise;
* :meth:`~InstrumentModel.check` — refuse an unusable measurement before any state is touched;
* :meth:`~InstrumentModel.groups` — the channels of ``z`` that go into one factor each (a
  robust kernel weighs a group as a whole: one ruler, one pose, one target);
* :meth:`~InstrumentModel.residual` — tight coupling: predicted minus measured for some
  channels, with ``∂r/∂ξ`` on the body tangent ``ξ = [ω, v]`` of the pose (GTSAM's order:
  rotation first; ``R ← R Exp(ω)``, ``t ← t + R v``) and ``∂r/∂θ``;
* :meth:`~InstrumentModel.pose` — loose coupling where the measurement fixes a pose: that pose
  with its covariance on the same tangent and ``∂ξ/∂θ``; None where it does not (a points
  instrument seeing fewer than three targets).

A residual is a *function of the pose*, which is what both estimator families need: the factor
graph puts it on the pose variable (:mod:`stewart_calib.factors.instrument`), and an EKF can
evaluate it at the pose the drive model predicts, chaining ``∂ξ/∂x`` of the drive's forward
kinematics (implicit function theorem on the drive-leg residuals).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, NamedTuple

import numpy as np

from ..config import NoiseConfig
from ..model import rotations
from ..model.platform import Instrument, LegGeometry, Platform
from ..model.unknowns import UnknownBlock


class Residual(NamedTuple):
    """Tight coupling: ``r = h(pose, θ) − z`` for some channels of one measurement (a tuple:
    it is made once per factor linearisation).

    Attributes:
        r: ``(m,)`` predicted minus measured [code units of the channels].
        J_pose: ``(m, 6)`` ``∂r/∂ξ``, body tangent ``[ω, v]``.
        J_instrument: ``(m, n)`` ``∂r/∂θ`` (n = 0 for a model without unknowns).
        channels: ``(m,)`` indices into ``channel_sigma`` / ``z`` of the rows.
    """

    r: np.ndarray
    J_pose: np.ndarray
    J_instrument: np.ndarray
    channels: np.ndarray


class Redundant(NamedTuple):
    """The part of one measurement the pose it implies leaves over: the residual at that pose along the
    directions no pose can move (a points instrument's 3K − 6 beyond the pose's six: the distances between
    its targets). Only the model's unknowns and the noise move it, and to first order its noise is
    independent of the pose's.

    Attributes:
        r: ``(k,)`` [code units of the channels].
        J_instrument: ``(k, n)`` ``∂r/∂θ``.
        covariance: ``(k, k)``.
    """

    r: np.ndarray
    J_instrument: np.ndarray
    covariance: np.ndarray


class PoseObservation(NamedTuple):
    """Loose coupling: the pose of {D} in {J} one measurement implies.

    Attributes:
        R, t: ``(3, 3)``, ``(3,)`` [mm].
        covariance: ``(6, 6)`` on the body tangent ``[ω, v]`` [rad², mm²], from ``channel_sigma``.
        J_instrument: ``(6, n)`` ``∂ξ/∂θ``: how the implied pose moves with the model's unknowns.
        redundant: what the measurement holds beyond the pose (:class:`Redundant`), None where it
            holds nothing more (six channels for six pose coordinates).
    """

    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    J_instrument: np.ndarray
    redundant: Redundant | None = None


class InstrumentModel(ABC):
    """A measurement model (see the module docstring), one subclass per kind.

    The class is the kind: what the code above this package asks of an instrument without naming
    it is answered by its class attributes and class methods (:func:`~.registry.instrument_kind`),
    what an estimator observes through by an instance (:meth:`build`).

    Class attributes:
        kind: the ``[instrument] kind`` it reads (spec §7).
        outside: whether the instrument stands outside the robot, in a frame of its own: the
            drive's gauge directions are then unobserved (fixed by :mod:`.gauge`), the encoders'
            scale is an unknown, and the fit starts from a registration (:meth:`registered_platform`).
        registers: whether :meth:`registered_platform` moves the instrument's unknowns (a frame
            that may start 100 mm and any rotation away); the nominal values are good starts otherwise.
        unseen_channels: whether a reading may leave channels empty (a points target not seen: all
            three of its coordinates), read as NaN rather than refused.
        measures_orientation: whether a reading tells the platform's orientation, so that
            ``validate`` reports an orientation error (points, each a position, do not).
        angle_columns: which of its log columns (:meth:`columns_of`) hold angles: degrees in the
            file, radians in ``z`` (spec §1); every other column holds millimetres in both.
    """

    kind: ClassVar[str]
    outside: ClassVar[bool] = False
    registers: ClassVar[bool] = False
    unseen_channels: ClassVar[bool] = False
    measures_orientation: ClassVar[bool] = True
    angle_columns: ClassVar[frozenset[str]] = frozenset()

    columns: tuple[str, ...]
    unknowns: UnknownBlock | None
    channel_sigma: np.ndarray
    #: the leg set whose readings the measurement is, where the model offers compiled kernels
    #: (see the module docstring), else None
    compiled_legs: LegGeometry | None = None
    #: whether a whole reading is the pose of a target on the platform seen from a frame of its
    #: own, θ = [frame pose6 | target pose6]: the model then offers the compiled kernel of its
    #: residual rows (:func:`stewart_calib.factors._kernels.pose_reading_rows`)
    compiled_pose_reading: ClassVar[bool] = False
    #: whether the readings are the extensions of a leg set whose rows ``[j_i | d_i | l_i]`` are the unknowns
    #: θ (seven a leg, in leg order) when it has unknowns: the model then offers the compiled kernel of its
    #: residual rows (:func:`stewart_calib.factors._kernels.unknown_leg_rows`)
    compiled_unknown_legs: ClassVar[bool] = False

    # ------------------------------------------------------------------ the kind

    @classmethod
    @abstractmethod
    def build(cls, platform: Platform, noise: NoiseConfig) -> InstrumentModel:
        """The model of ``platform``'s instrument of this kind, with ``noise``'s σ where the
        platform file has none."""

    @staticmethod
    @abstractmethod
    def columns_of(instrument: Instrument) -> tuple[str, ...]:
        """The log columns of a reading of ``instrument``, in the order of ``z`` (spec §3, §7)."""

    @staticmethod
    @abstractmethod
    def spreads(platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray) -> list[Spread]:
        """How a log's readings spread against the nominal instrument's at the nominal poses
        ``(R, t)`` of its strokes (:class:`Spread`)."""

    @staticmethod
    def reading_legs(platform: Platform) -> LegGeometry | None:
        """The leg set of known nominal geometry whose extensions a reading is (its forward
        kinematics gives the pose of each sample, its inverse kinematics the reading of a pose;
        ``[tracker] reading_range_mm`` bounds them), or None."""
        return None

    @classmethod
    def registered_platform(cls, platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
        """``platform`` with the instrument's nominal unknowns replaced by a closed-form
        registration on ``(strokes (N, 6), readings (N, M))`` where the kind :attr:`registers`
        (unchanged otherwise).

        Raises:
            CalibError: the samples cannot register the instrument.
        """
        return platform

    @staticmethod
    def placed_on(
        platform: Platform, position_sigma_mm: float, orientation_sigma_rad: float, n_targets: int
    ) -> Instrument:
        """A nominal instrument of the kind for a simulated study of ``platform`` (the sweep's
        cells); the platform's own by default."""
        return platform.instrument

    # ------------------------------------------------------------------ one instrument

    @abstractmethod
    def check(self, z: np.ndarray, t_s: float) -> np.ndarray:
        """``z`` as a float array, or :class:`~stewart_calib.errors.SampleRejected` (wrong shape,
        a non-finite required channel, a value outside the instrument's range)."""

    def surely_pass(self, readings: np.ndarray) -> np.ndarray:
        """``(N,)`` True for the rows of ``readings (N, M)`` that :meth:`check` surely passes, in one
        vectorised pass for a block of samples; a row in doubt is False and goes through
        :meth:`check` one at a time (the default: every row)."""
        return np.zeros(len(readings), dtype=bool)

    @abstractmethod
    def groups(self, z: np.ndarray) -> list[np.ndarray]:
        """The channel groups of ``z`` that are measured, one factor each."""

    @abstractmethod
    def residual(
        self, R: np.ndarray, t: np.ndarray, theta: np.ndarray, z: np.ndarray, channels: np.ndarray
    ) -> Residual:
        """``h(pose, θ) − z`` on ``channels`` with its Jacobians."""

    @abstractmethod
    def pose(
        self, z: np.ndarray, theta: np.ndarray, guess: tuple[np.ndarray, np.ndarray] | None
    ) -> PoseObservation | None:
        """The pose ``z`` implies (``guess``: the previous one, a warm start), or None where ``z``
        does not fix a pose. Raises :class:`~stewart_calib.errors.SampleRejected` when it should
        but cannot (e.g. forward kinematics does not converge)."""


class Spread(NamedTuple):
    """How far some channels of a log's readings spread against what the nominal instrument would
    read at the nominal drive's poses of its strokes: their ratio names a unit the columns were
    written in (``diagnose_log``).

    Attributes:
        what: the channels in words ("positions", "target 2 positions").
        channels: which columns of the readings.
        measured, expected: the spreads [mm, or degrees where ``angle``].
        angle: whether they are angles (else lengths).
    """

    what: str
    channels: slice
    measured: float
    expected: float
    angle: bool = False


def position_spread_mm(points: np.ndarray) -> float:
    """RMS distance of ``(N, 3)`` points from their centroid [mm] (NaN rows left out)."""
    points = points[np.all(np.isfinite(points), axis=1)]
    if not len(points):
        return float("nan")
    return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=1))))


def rotation_spread_rad(R: np.ndarray) -> float:
    """RMS angle [rad] of ``(N, 3, 3)`` rotations from their chordal mean: the same for
    ``F R_k G`` as for ``R_k`` (the mean moves with them), so it needs no frame."""
    mean = rotations.project_to_rotation(np.mean(R, axis=0))
    return float(np.sqrt(np.mean(np.sum(rotations.so3_log(np.einsum("ji,kjl->kil", mean, R)) ** 2, axis=-1))))


def instrument_theta(model: InstrumentModel, block_error: np.ndarray | None) -> np.ndarray:
    """Absolute ``θ = θ₀ + error`` of ``model`` (``()`` for a model without unknowns)."""
    if model.unknowns is None:
        return np.zeros(0)
    return model.unknowns.nominal + (0.0 if block_error is None else np.asarray(block_error, dtype=float))
