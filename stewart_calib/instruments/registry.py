"""The one list of instrument kinds: ``[instrument] kind`` (spec §7) → the model that reads it.

Adding an instrument: its model module in this package, its factor module in
:mod:`stewart_calib.factors` where the generic instrument factor does not fit, and one entry in
:data:`MODELS` (docs/architecture.md). The estimators build whatever :func:`instrument_model`
returns and never name a kind.
"""

from __future__ import annotations

from typing import Callable

from ..config import NoiseConfig
from ..errors import CalibError
from ..platform import Platform
from . import points, pose, tracker
from .base import InstrumentModel
from .external import model_for


def _tracker(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return tracker.TrackerModel(
        platform.tracker, noise.reading_sigma_mm, platform.reading_range, platform.tracker_geometry_sigma_mm
    )


def _pose(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return pose.PoseModel(platform.instrument, model_for(platform).block())


def _points(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    return points.PointsModel(platform.instrument, model_for(platform).block())


#: kind → builder ``(platform, noise) -> model``.
MODELS: dict[str, Callable[[Platform, NoiseConfig], InstrumentModel]] = {
    "tracker": _tracker,
    "pose": _pose,
    "points": _points,
}


def instrument_model(platform: Platform, noise: NoiseConfig) -> InstrumentModel:
    """The measurement model of ``platform``'s instrument (``[instrument] kind``; the tracker by default).

    Raises:
        CalibError: a kind without a model here.
    """
    kind = platform.instrument.kind
    if kind not in MODELS:
        raise CalibError(f"instrument kind '{kind}' has no measurement model: expected one of {', '.join(MODELS)}")
    return MODELS[kind](platform, noise)
