"""The one list of instrument kinds: ``[instrument] kind`` (spec §7) → the model that reads it.

Adding an instrument: its model module in this package, its factor module in
:mod:`stewart_calib.factors` where the generic instrument factor does not fit, one entry in
:data:`MODELS` and one in :data:`stewart_calib.platform.INSTRUMENT_SECTIONS` (what it reads of the
platform file: the file layer lies below this package) (docs/architecture.md). The estimators
build whatever :func:`instrument_model` returns; every other question about an instrument is
asked of its :class:`InstrumentKind` (:func:`instrument_kind`), so nothing outside this package
compares a kind.
"""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import NamedTuple

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..platform import Instrument, LegGeometry, Platform
from . import points, pose, tracker
from .base import InstrumentModel, Spread
from .external import model_for, registered_platform


def _tracker(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    geometry_sigma_mm = platform.tracker_geometry_sigma_mm or noise.tracker_geometry_sigma_mm
    return tracker.TrackerModel(
        _tracker_legs(platform),
        noise.reading_sigma_mm,
        platform.reading_range,
        geometry_sigma_mm,
    )


def _pose(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return pose.PoseModel(platform.instrument, model_for(platform).block())


def _points(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return points.PointsModel(platform.instrument, model_for(platform).block())


def _tracker_legs(platform: Platform) -> LegGeometry:
    return platform.required_tracker("the tracker instrument")


class InstrumentKind(NamedTuple):
    """One instrument kind: what the code above this package asks of an instrument without
    naming it.

    Attributes:
        build: ``(platform, noise) -> model``.
        register: ``(platform, strokes (N, 6), readings (N, M)) -> platform`` with the instrument's
            nominal unknowns replaced by a closed-form registration on those samples, for a kind
            whose unknowns may start far from the truth (a frame 100 mm and any rotation away);
            None where the nominal values are good starting points.
        reading_legs: ``platform -> legs`` where a reading is the extensions of a leg set of known
            nominal geometry (its forward kinematics gives the pose of each sample, its inverse
            kinematics the reading of a pose; ``[tracker] reading_range_mm`` bounds them); None for
            an instrument outside the robot.
        columns: ``[instrument] -> names``: the log columns of a reading, in the order of ``z`` (spec §3, §7).
        spreads: ``(platform, R, t, readings) -> [Spread]``: how the log's readings spread against
            the nominal instrument's at the nominal poses ``(R, t)`` of its strokes (:class:`~.base.Spread`).
        module: the kind's module for an instrument outside the robot (its unknowns, ``predict``,
            ``residual``, ``sigmas``, ``names``, and a simulation's ``true_unknowns``,
            ``noise_draws`` and ``simulated_readings``), else None.
        placed_on: ``(platform, position σ [mm], orientation σ [rad], number of targets) ->
            [instrument]``: a nominal instrument of the kind for a simulated study of ``platform``
            (the sweep's cells): the tracker as the platform file has it; an outside instrument's
            frame at {J}'s origin, a pose target at {D}'s origin, point targets halfway out
            towards platform joints 1, 3, 5 and 25 mm above.
        unseen_channels: whether a reading may leave channels empty (a points target not seen: all
            three of its coordinates), read as NaN rather than refused.
        measures_orientation: whether a reading tells the platform's orientation, so that
            ``validate`` reports an orientation error (points, each a position, do not).
    """

    build: Callable[[Platform, NoiseConfig], InstrumentModel]
    columns: Callable[[Instrument], tuple[str, ...]]
    spreads: Callable[[Platform, np.ndarray, np.ndarray, np.ndarray], list[Spread]]
    register: Callable[[Platform, np.ndarray, np.ndarray], Platform] | None = None
    reading_legs: Callable[[Platform], LegGeometry] | None = None
    module: ModuleType | None = None
    placed_on: Callable[[Platform, float, float, int], Instrument] = lambda platform, *_: platform.instrument
    unseen_channels: bool = False
    measures_orientation: bool = True

    @property
    def outside(self) -> bool:
        """Whether the instrument stands outside the robot, in a frame of its own: the drive's
        gauge directions are then unobserved (fixed by :mod:`.gauge`), the encoders' scale is an
        unknown, and the fit starts from a registration of its frame and target(s)."""
        return self.reading_legs is None


#: kind → what it is made of (the one list of kinds; ``[instrument] kind``, spec §7).
MODELS: dict[str, InstrumentKind] = {
    "tracker": InstrumentKind(
        _tracker, lambda _: tracker.TRACKER_COLUMNS, tracker.reading_spreads, reading_legs=_tracker_legs
    ),
    "pose": InstrumentKind(
        _pose, lambda _: pose.COLUMNS, pose.reading_spreads, registered_platform, module=pose, placed_on=pose.placed_on
    ),
    "points": InstrumentKind(
        _points,
        lambda instrument: points.columns(instrument.n_targets),
        points.reading_spreads,
        registered_platform,
        module=points,
        placed_on=points.placed_on,
        unseen_channels=True,
        measures_orientation=False,
    ),
}


def instrument_model(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    """The measurement model of ``platform``'s instrument (``[instrument] kind``; the tracker by default).

    Raises:
        CalibError: a kind without a model here.
    """
    return instrument_kind(platform).build(platform, noise)


def needs_registration(platform: Platform) -> bool:
    """Whether ``platform``'s instrument is registered on the data before estimation starts."""
    return instrument_kind(platform).register is not None


def registered(platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
    """``platform`` with its instrument registered on ``(strokes, readings)`` (unchanged for a kind
    without registration).

    Raises:
        CalibError: the samples cannot register the instrument (e.g. fewer than 3 distinct poses).
    """
    register = instrument_kind(platform).register
    return platform if register is None else register(platform, np.asarray(strokes, float), np.asarray(readings, float))


def instrument_kind(platform: Platform) -> InstrumentKind:
    """What ``platform``'s instrument is (see :class:`InstrumentKind`).

    Raises:
        CalibError: a kind without a model here.
    """
    return kind_of(platform.instrument)


def kind_of(instrument: Instrument) -> InstrumentKind:
    """What ``instrument`` (a platform file's ``[instrument]``) is (see :class:`InstrumentKind`).

    Raises:
        CalibError: a kind without a model here.
    """
    kind = instrument.kind
    if kind not in MODELS:
        raise CalibError(f"instrument kind '{kind}' has no measurement model: expected one of {', '.join(MODELS)}")
    return MODELS[kind]
