"""Measurement models, one module per instrument, all following :mod:`.base`'s protocol;
:mod:`.registry` lists them by ``[instrument] kind``."""

from .base import InstrumentModel, PoseObservation, Residual, instrument_theta
from .registry import MODELS, instrument_model

__all__ = ["MODELS", "InstrumentModel", "PoseObservation", "Residual", "instrument_model", "instrument_theta"]
