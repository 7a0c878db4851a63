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

from .. import kinematics as kin
from ..instruments import gauge, points, pose
from ..platform import Instrument, LegGeometry


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
        unknowns: pose.PoseUnknowns | points.PointsUnknowns
        if instrument.kind == "pose":
            unknowns = pose.PoseUnknowns.from_pose6(frame, instrument.target + offset(truth.target_offset))
        else:
            targets = instrument.targets + rng.normal(0.0, truth.target_spread_mm, instrument.targets.shape)
            unknowns = points.PointsUnknowns(*kin.pose_to_rt(frame), targets)
        return cls(instrument, unknowns, truth.dropout_probability)

    def names(self) -> tuple[str, ...]:
        return pose.UNKNOWN_NAMES if self.instrument.kind == "pose" else points.unknown_names(self.instrument.n_targets)

    def draw(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Standard normal noise and uniform dropout draws for ``n`` readings, ``(n, m + K)``,
        drawn up front so that results do not depend on how the samples are batched."""
        width = 6 if self.instrument.kind == "pose" else 4 * self.instrument.n_targets
        draws = rng.standard_normal((n, width))
        if self.instrument.kind == "points":
            draws[:, 3 * self.instrument.n_targets :] = rng.random((n, self.instrument.n_targets))
        return draws

    def read(self, R: np.ndarray, t: np.ndarray, draws: np.ndarray) -> np.ndarray:
        """Readings ``(..., m)`` at true platform poses with :meth:`draw`'s draws, code units
        (NaN: a target not seen)."""
        sigma_pos = self.instrument.position_sigma_mm
        if isinstance(self.unknowns, pose.PoseUnknowns):  # kind "pose"
            R_P, t_P = pose.predict(self.unknowns, R, t)
            R_m = R_P @ kin.so3_exp(self.instrument.orientation_sigma_rad * draws[..., :3])
            return kin.rt_to_pose(R_m, t_P + sigma_pos * draws[..., 3:])
        K = self.instrument.n_targets
        m = points.predict(self.unknowns, R, t) + sigma_pos * draws[..., : 3 * K].reshape(draws.shape[:-1] + (K, 3))
        m[draws[..., 3 * K :] < self.dropout_probability] = np.nan
        return m.reshape(draws.shape[:-1] + (3 * K,))


def truth_in_gauge(nominal: LegGeometry, true_params: np.ndarray, unknowns) -> tuple[np.ndarray, object]:
    """A simulator's truth in the gauge of :func:`stewart_calib.instruments.gauge.free_basis`:
    ``(δM (42), the instrument's unknowns moved alike)`` for true absolute parameters ``(42,)``
    and true instrument unknowns (``PoseUnknowns`` or ``PointsUnknowns``)."""
    params, (R_J, t_J), (R_D, t_D) = gauge.to_gauge(nominal, true_params)
    u = unknowns
    moved: pose.PoseUnknowns | points.PointsUnknowns
    if isinstance(u, pose.PoseUnknowns):
        moved = pose.PoseUnknowns(R_J @ u.R_frame, R_J @ u.t_frame + t_J, R_D @ u.R_target, R_D @ u.t_target + t_D)
    else:
        moved = points.PointsUnknowns(R_J @ u.R_frame, R_J @ u.t_frame + t_J, u.targets @ R_D.T + t_D)
    return params - nominal.as_vector(), moved
