"""The in-situ tracker (paper §2, Table 2): six grating rulers between base and platform.

Ruler i reads ``s_i`` with ``‖t + R h_i − z_i‖ = ls_i + s_i`` — the drive's leg geometry
(:func:`stewart_calib.model.kinematics.leg_residual`) with the tracker's joints ``z_i`` (in {J}),
``h_i`` (in {D}) and zero-reading lengths ``ls_i``. Both couplings:

* tight: one residual per ruler, ``r_i = ‖t + R h_i − z_i‖ − (ls_i + s_i)`` [mm], σ_s each;
* loose: forward kinematics of the six readings (Newton, warm-started) with the covariance
  ``Σ_ξ = σ_s² (JᵀJ)⁻¹`` propagated from the rulers (``J`` = ``∂ lengths/∂ξ``).

Its unknowns: none when the geometry is known exactly (the paper's assumption; the default), or
the 42 values ``[z_i | h_i | ls_i]`` per ruler under the prior N(nominal, σ²) with
``[tracker] geometry_sigma_mm = σ`` (spec §7). Those move exactly as the drive's joints under
a rigid motion of all base or all platform joints, so the block shares both gauges; known to
micrometres where the drive is known to millimetres, the tracker holds them
(``UnknownBlock.holds_gauge``): {J} and {D} stay the frames its calibration defined.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import NoiseConfig
from ..errors import SampleRejected, number
from ..model import _kernels
from ..model import kinematics as kin
from ..model.platform import INSTRUMENT_SECTIONS, Instrument, LegGeometry, Platform
from ..model.unknowns import UnknownBlock
from .base import InstrumentModel, PoseObservation, Residual, Spread

#: the log columns of the six readings s_i [mm] (spec §3).
TRACKER_COLUMNS = INSTRUMENT_SECTIONS["tracker"].log_columns(0)
#: the seven values of one ruler ``[z_i | h_i | ls_i]`` as (paper Table 2 symbol, axis)
_RULER_FIELDS = (("z", "x"), ("z", "y"), ("z", "z"), ("h", "x"), ("h", "y"), ("h", "z"), ("ls", ""))


def tracker_parameter_names(legs: LegGeometry) -> tuple[str, ...]:
    """The names of the tracker's own values when they are unknowns (spec §7): ``z1x … ls6`` for six rulers."""
    return tuple(f"{field}{leg}{axis}" for leg in range(1, legs.n_legs + 1) for field, axis in _RULER_FIELDS)


class TrackerModel(InstrumentModel):
    """The in-situ tracker as a measurement model (:class:`~.base.InstrumentModel`): part of the
    robot, its readings a leg set's (:meth:`reading_legs`), which offers compiled kernels where the
    geometry is known (``compiled_legs``).

    Args:
        legs: the tracker geometry ``(z_i, h_i, ls_i)`` (platform file ``[tracker]``).
        reading_sigma_mm: σ_s of one reading [mm] (``[noise] reading_sigma_mm``).
        reading_range: ``(min, max)`` of a reading [mm] (``[tracker] reading_range_mm``), or None.
        geometry_sigma_mm: prior σ of the geometry as an unknown [mm]; 0: known exactly.
    """

    kind = "tracker"
    columns = TRACKER_COLUMNS
    compiled_unknown_legs = True

    @classmethod
    def build(cls, platform: Platform, noise: NoiseConfig) -> TrackerModel:
        """The platform's ``[tracker]`` legs, reading range and geometry σ (else ``noise``'s), σ_s of ``noise``."""
        return cls(
            platform.required_tracker("the tracker instrument"),
            noise.reading_sigma_mm,
            platform.reading_range,
            platform.tracker_geometry_sigma_mm or noise.tracker_geometry_sigma_mm,
        )

    @staticmethod
    def columns_of(instrument: Instrument) -> tuple[str, ...]:
        return TRACKER_COLUMNS

    @staticmethod
    def reading_legs(platform: Platform) -> LegGeometry:
        return platform.required_tracker("the tracker instrument")

    @staticmethod
    def spreads(platform: Platform, R: np.ndarray, t: np.ndarray, readings: np.ndarray) -> list[Spread]:
        """The readings' spread against the tracker's inverse kinematics of the poses (:class:`~.base.Spread`)."""
        expected = kin.inverse_kinematics(platform.required_tracker("the diagnosis"), R, t)
        measured_spread = float(np.sqrt(np.nanmean(np.nansum((readings - np.nanmean(readings, axis=0)) ** 2, axis=1))))
        expected_spread = float(np.sqrt(np.mean(np.sum((expected - expected.mean(axis=0)) ** 2, axis=1))))
        return [Spread("tracker readings", slice(None), measured_spread, expected_spread)]

    def __init__(
        self,
        legs: LegGeometry,
        reading_sigma_mm: float,
        reading_range: tuple[float, float] | None = None,
        geometry_sigma_mm: float = 0.0,
    ):
        self.legs = legs
        self._params = legs.params  # (6, 7) [z_i | h_i | ls_i], read once per factor linearisation
        self._rulers = [np.array([i]) for i in range(legs.n_legs)]
        self.reading_range = reading_range
        self.channel_sigma = np.full(legs.n_legs, float(reading_sigma_mm))
        self.unknowns = None
        #: its readings are a leg set's of known geometry: estimators observe through it in compiled code
        self.compiled_legs: LegGeometry | None = legs if geometry_sigma_mm <= 0.0 else None
        if geometry_sigma_mm > 0.0:
            self.unknowns = UnknownBlock(
                "instrument",
                tracker_parameter_names(legs),
                legs.as_vector(),
                np.full(legs.n_params, geometry_sigma_mm),
                gauge=("base", "platform"),
                holds_gauge=True,
                joints=legs.gauge_columns,
            )

    def check(self, z: np.ndarray, t_s: float) -> np.ndarray:
        """The six readings as floats, or :class:`SampleRejected` (shape, non-finite, out of range)."""
        readings = np.asarray(z, dtype=float)
        lo, hi = self.reading_range if self.reading_range is not None else (-math.inf, math.inf)
        # One compiled check for the common valid sample; any doubt goes to the wording below.
        if readings.shape == self.channel_sigma.shape and _kernels.all_within(readings, float(lo), float(hi)):
            return readings
        if readings.shape != self.channel_sigma.shape:
            expected = len(self.channel_sigma)
            raise SampleRejected(
                f"sample at t = {number(t_s)} s: expected {expected} reading s values, got shape {readings.shape}",
                SampleRejected.NON_FINITE,
            )
        bad = np.flatnonzero(~np.isfinite(readings))
        if bad.size:
            raise SampleRejected(
                f"sample at t = {number(t_s)} s: reading s{bad[0] + 1} is not finite", SampleRejected.NON_FINITE
            )
        i = int(np.flatnonzero((readings < lo) | (readings > hi))[0])
        raise SampleRejected(
            f"sample at t = {number(t_s)} s: reading s{i + 1} = {readings[i]:.6g} mm outside [{lo}, {hi}] mm",
            SampleRejected.OUT_OF_RANGE,
        )

    def surely_pass(self, readings: np.ndarray) -> np.ndarray:
        """Rows finite and within ``reading_range``."""
        lo, hi = self.reading_range if self.reading_range is not None else (-math.inf, math.inf)
        with np.errstate(invalid="ignore"):
            return np.isfinite(readings).all(axis=1) & ((readings >= lo) & (readings <= hi)).all(axis=1)

    def groups(self, z: np.ndarray) -> list[np.ndarray]:
        """One group per ruler: a robust kernel down-weights one bad reading, not the sample."""
        return self._rulers

    def geometry(self, theta: np.ndarray) -> LegGeometry:
        """The tracker legs for ``θ`` (the nominal ones when the geometry is known)."""
        return self.legs if len(theta) == 0 else LegGeometry.from_params(theta)

    def residual(
        self, R: np.ndarray, t: np.ndarray, theta: np.ndarray, z: np.ndarray, channels: np.ndarray
    ) -> Residual:
        """``‖t + R h_i − z_i‖ − (ls_i + s_i)`` for the rulers ``channels`` [mm]."""
        channels = np.asarray(channels, dtype=np.int64)
        params = self._params if len(theta) == 0 else np.reshape(theta, self._params.shape)
        r, J_pose, H_legs = kin.leg_residual(R, t, params[channels], np.asarray(z, dtype=float)[channels])
        J_theta = np.zeros((len(channels), 0 if self.unknowns is None else self._params.size))
        if self.unknowns is not None:
            per_leg = self._params.shape[1]
            J_theta[np.arange(len(channels))[:, None], per_leg * channels[:, None] + np.arange(per_leg)] = H_legs
        return Residual(r, J_pose, J_theta, channels)

    def pose(self, z: np.ndarray, theta: np.ndarray, guess: tuple[np.ndarray, np.ndarray] | None) -> PoseObservation:
        """Forward kinematics of the readings (warm-started from ``guess``) and its covariance.

        ``∂ξ/∂θ = −J⁻¹ ∂lengths/∂θ`` (implicit function theorem on the six ruler residuals).

        Raises:
            SampleRejected: forward kinematics converges from neither ``guess`` nor the cold start.
        """
        legs = self.geometry(theta)
        R, t = kin.solve_fk(legs, z, guess, "tracker")
        covariance = kin.pose_covariance_from_legs(legs, R, t, float(self.channel_sigma[0]))
        J_theta = np.zeros((6, 0))
        if self.unknowns is not None:
            rulers = self.residual(R, t, theta, z, np.arange(len(self._params)))
            J_theta = -np.linalg.solve(rulers.J_pose, rulers.J_instrument)
        return PoseObservation(R, t, covariance, J_theta)
