"""A simulated instrument outside the robot (spec §7 ``pose``, ``points``): its true frame and
target(s), white reading noise and, for points, targets lost from view.

The platform file holds the **nominal** instrument (what the user believes, written into the
simulated ``platform.toml``); the truth differs from it by the experiment's offsets:

* ``frame_offset = [x, y, z mm, roll, pitch, yaw deg]`` added to the nominal frame's pose6;
* ``target_offset`` (pose) added to the nominal target's pose6;
* ``target_spread_mm`` (points): σ of i.i.d. normal errors of every target coordinate.

A pose reading is ``(R Exp(n_ω), t + n_v)`` with ``n_ω ~ N(0, σ_rot² I)`` (body) and
``n_v ~ N(0, σ_pos² I)``, the noise model of :mod:`stewart_calib.instruments.pose`; a target
reading is ``m + n``, ``n ~ N(0, σ_pos² I)``, lost (all three NaN) with ``dropout_probability``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..instruments import OutsideModel, gauge, points, pose
from ..instruments.registry import kind_of
from ..model.legs import LegModel
from ..model.platform import Instrument


@dataclass(frozen=True)
class InstrumentTruth:
    """The experiment's ``[instrument]`` truth keys (see the module docstring)."""

    frame_offset: np.ndarray
    target_offset: np.ndarray
    target_spread_mm: float = 0.0
    dropout_probability: float = 0.0


@dataclass(frozen=True)
class SimulatedInstrument:
    """The true instrument: its unknowns and noise.

    Attributes:
        instrument: the nominal instrument (kind, σ used as the true noise).
        unknowns: the true frame and target(s) (:class:`~stewart_calib.instruments.pose.PoseUnknowns`
            or :class:`~stewart_calib.instruments.points.PointsUnknowns`).
        dropout_probability: chance that a target is not seen in a reading.
    """

    instrument: Instrument
    unknowns: pose.PoseUnknowns | points.PointsUnknowns
    dropout_probability: float

    @classmethod
    def build(cls, instrument: Instrument, truth: InstrumentTruth, rng: np.random.Generator) -> SimulatedInstrument:
        offset = lambda values: np.r_[values[:3], np.radians(values[3:])]  # noqa: E731  (file → code units)
        frame = instrument.frame + offset(truth.frame_offset)
        unknowns = _model(instrument).true_unknowns(
            instrument, frame, offset(truth.target_offset), truth.target_spread_mm, rng
        )
        return cls(instrument, unknowns, truth.dropout_probability)

    def names(self) -> tuple[str, ...]:
        return _model(self.instrument).names_of(self.instrument)

    def draw(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Standard normal noise and uniform dropout draws for ``n`` readings, ``(n, m + K)``,
        drawn up front so that results do not depend on how the samples are batched."""
        return _model(self.instrument).noise_draws(self.instrument, n, rng)

    def read(self, R: np.ndarray, t: np.ndarray, draws: np.ndarray) -> np.ndarray:
        """Readings ``(..., m)`` at true platform poses with :meth:`draw`'s draws, code units
        (NaN: a target not seen)."""
        model = _model(self.instrument)
        return model.simulated_readings(self.instrument, self.unknowns, R, t, draws, self.dropout_probability)


def _model(instrument: Instrument) -> type[OutsideModel]:
    """The model class of ``instrument``'s kind (:data:`~stewart_calib.instruments.registry.MODELS`)."""
    model = kind_of(instrument)
    if not issubclass(model, OutsideModel):
        raise ValueError(f"the {instrument.kind} instrument is part of the robot: it has no simulated truth of its own")
    return model


def truth_in_gauge(nominal: LegModel, true_params: np.ndarray, unknowns) -> tuple[np.ndarray, object]:
    """A simulator's truth in the gauge of :func:`stewart_calib.instruments.gauge.free_basis`:
    ``(δM (n_params: 42 prismatic, 66 rotary), the instrument's unknowns moved alike)`` for true absolute
    parameters ``(n_params,)`` of the leg model ``nominal`` and true instrument unknowns (``PoseUnknowns``
    or ``PointsUnknowns``)."""
    params, (R_J, t_J), (R_D, t_D) = gauge.to_gauge(nominal, true_params)
    return params - nominal.as_vector(), unknowns.in_frames(R_J, t_J, R_D, t_D)
