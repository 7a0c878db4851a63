"""Measurement models, one module per instrument, each a subclass of :class:`.base.InstrumentModel`
(the one instrument interface; :class:`.external.OutsideModel` for those outside the robot);
:mod:`.registry` lists them by ``[instrument] kind``. The instruments outside the robot (spec §7
``pose``, ``points``) start their fit in closed form (:mod:`.registration`) and leave 12
directions to :mod:`.gauge`."""

from .base import InstrumentModel, PoseObservation, Residual, instrument_theta
from .external import OutsideModel
from .registry import (
    MODELS,
    InstrumentKind,
    instrument_kind,
    instrument_model,
    needs_registration,
    outside_model,
    registered,
)

__all__ = [
    "MODELS",
    "InstrumentKind",
    "InstrumentModel",
    "OutsideModel",
    "PoseObservation",
    "Residual",
    "instrument_kind",
    "instrument_model",
    "instrument_theta",
    "needs_registration",
    "outside_model",
    "registered",
]
