"""The one list of instrument kinds: ``[instrument] kind`` (spec §7) → the model that reads it.

Adding an instrument: its model module in this package, its factor module in
:mod:`stewart_calib.factors` where the generic instrument factor does not fit, and one entry in
:data:`MODELS` (docs/architecture.md). The estimators build whatever :func:`instrument_model`
returns and never name a kind.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from ..config import NoiseConfig
from ..errors import CalibError
from ..platform import Platform
from . import points, pose, tracker
from .base import InstrumentModel
from .external import model_for, registered_platform


def _tracker(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    geometry_sigma_mm = platform.tracker_geometry_sigma_mm or noise.tracker_geometry_sigma_mm
    return tracker.TrackerModel(
        platform.required_tracker("the tracker instrument"),
        noise.reading_sigma_mm,
        platform.reading_range,
        geometry_sigma_mm,
    )


def _pose(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return pose.PoseModel(platform.instrument, model_for(platform).block())


def _points(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return points.PointsModel(platform.instrument, model_for(platform).block())


class InstrumentKind(NamedTuple):
    """One instrument kind.

    Attributes:
        build: ``(platform, noise) -> model``.
        register: ``(platform, strokes (N, 6), readings (N, M)) -> platform`` with the instrument's
            nominal unknowns replaced by a closed-form registration on those samples, for a kind
            whose unknowns may start far from the truth (a frame 100 mm and any rotation away);
            None where the nominal values are good starting points.
    """

    build: Callable[[Platform, NoiseConfig], InstrumentModel]
    register: Callable[[Platform, np.ndarray, np.ndarray], Platform] | None = None


#: kind → its builder and registration.
MODELS: dict[str, InstrumentKind] = {
    "tracker": InstrumentKind(_tracker),
    "pose": InstrumentKind(_pose, registered_platform),
    "points": InstrumentKind(_points, registered_platform),
}


def instrument_model(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    """The measurement model of ``platform``'s instrument (``[instrument] kind``; the tracker by default).

    Raises:
        CalibError: a kind without a model here.
    """
    return _kind(platform).build(platform, noise)


def needs_registration(platform: Platform) -> bool:
    """Whether ``platform``'s instrument is registered on the data before estimation starts."""
    return _kind(platform).register is not None


def registered(platform: Platform, strokes: np.ndarray, readings: np.ndarray) -> Platform:
    """``platform`` with its instrument registered on ``(strokes, readings)`` (unchanged for a kind
    without registration).

    Raises:
        CalibError: the samples cannot register the instrument (e.g. fewer than 3 distinct poses).
    """
    register = _kind(platform).register
    return platform if register is None else register(platform, np.asarray(strokes, float), np.asarray(readings, float))


def _kind(platform: Platform) -> InstrumentKind:
    kind = platform.instrument.kind
    if kind not in MODELS:
        raise CalibError(f"instrument kind '{kind}' has no measurement model: expected one of {', '.join(MODELS)}")
    return MODELS[kind]
