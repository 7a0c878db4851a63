"""The one list of instrument kinds: ``[instrument] kind`` (spec §7) → the model class that reads it.

Adding an instrument: its model module in this package (a subclass of
:class:`~.base.InstrumentModel`, or of :class:`~.external.OutsideModel` for one outside the robot),
one entry in :data:`MODELS` and one in :data:`stewart_calib.model.platform.INSTRUMENT_SECTIONS` (what it
reads of the platform file: the file layer lies below this package) (docs/architecture.md). The
estimators build whatever :func:`instrument_model` returns; every other question about an
instrument is asked of its class (:func:`instrument_kind`), so nothing outside this package
compares a kind.
"""

from __future__ import annotations

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..model.platform import Instrument, Platform
from .base import InstrumentModel
from .external import OutsideModel
from .points import PointsModel
from .pose import PoseModel
from .tracker import TrackerModel

#: what the code above this package asks of an instrument without naming it: its model's class
InstrumentKind = type[InstrumentModel]

#: kind → its model (the one list of kinds; ``[instrument] kind``, spec §7).
MODELS: dict[str, InstrumentKind] = {model.kind: model for model in (TrackerModel, PoseModel, PointsModel)}


def instrument_model(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    """The measurement model of ``platform``'s instrument (``[instrument] kind``; the tracker by default).

    Raises:
        CalibError: a kind without a model here.
    """
    return instrument_kind(platform).build(platform, noise)


def outside_model(platform: Platform) -> OutsideModel:
    """The model of ``platform``'s instrument outside the robot (its σ are the platform file's).

    Raises:
        CalibError: the instrument is part of the robot, or a kind without a model here.
    """
    model = instrument_model(platform, NoiseConfig())
    if not isinstance(model, OutsideModel):
        raise CalibError(f"{platform.source}: the {model.kind} instrument is part of the robot, not outside it")
    return model


def needs_registration(platform: Platform) -> bool:
    """Whether ``platform``'s instrument is registered on the data before estimation starts."""
    return instrument_kind(platform).registers


def registered(platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
    """``platform`` with its instrument registered on ``(strokes, readings)`` (unchanged for a kind
    without registration: :meth:`~.base.InstrumentModel.registered_platform`).

    Raises:
        CalibError: the samples cannot register the instrument (e.g. fewer than 3 distinct poses).
    """
    return instrument_kind(platform).registered_platform(
        platform, np.asarray(strokes, float), np.asarray(readings, float)
    )


def instrument_kind(platform: Platform) -> InstrumentKind:
    """What ``platform``'s instrument is: its model's class (:class:`~.base.InstrumentModel`).

    Raises:
        CalibError: a kind without a model here.
    """
    return kind_of(platform.instrument)


def kind_of(instrument: Instrument) -> InstrumentKind:
    """What ``instrument`` (a platform file's ``[instrument]``) is: its model's class.

    Raises:
        CalibError: a kind without a model here.
    """
    kind = instrument.kind
    if kind not in MODELS:
        raise CalibError(f"instrument kind '{kind}' has no measurement model: expected one of {', '.join(MODELS)}")
    return MODELS[kind]
