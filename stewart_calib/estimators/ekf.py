"""EKF on the leg-length model: the same model and noise as the factor graph.

State ``X = δM`` (42, paper order). Observation per sample: the six drive-leg residuals
``r_i = ‖t + R d_i − j_i‖ − (l_i + q_i)`` at the tracker's pose (FK of the readings), with
``(j_i, d_i, l_i)`` of the current model ``M + X``; the expected value is 0, so the
innovation is ``−r`` and ``H = ∂r/∂M``.

Measurement covariance: ``J_x Σ_x J_xᵀ + σ_q² I`` (full 6×6), with ``Σ_x`` the tracker pose
covariance from i.i.d. reading noise ``σ_s`` (``pose_covariance_from_legs``) and ``J_x`` the
residuals' pose Jacobian — all six residuals share the one tracker pose, so their errors
are correlated; with ``σ² I`` alone this filter diverges (docs/measured-facts.md).

Process noise: a random walk per parameter, ``Q = ρ² Δt I`` with ``ρ`` =
``noise.random_walk_mm_per_sqrt_s`` and ``Δt`` between samples (``t_s``), as in the graph.
"""

from __future__ import annotations

import math

import numpy as np

from .. import kinematics as kin
from ..errors import SampleRejected
from ..platform import Platform
from ..samples import Sample
from ..estimate import Estimate
from ..config import EstimatorConfig
from .kalman import FilterState
from .measurement import WarmFK, check_sample


class LegEKF:
    """Leg-length EKF; ``update(sample)`` then ``estimate()``.

    Attributes:
        filter: the :class:`FilterState` (``x``, ``P``, ``Q``, last NIS).
    """

    name = "ekf"

    def __init__(self, platform: Platform, config: EstimatorConfig):
        self.platform = platform
        self.noise = config.noise
        self.filter = FilterState(self.name, config.noise.prior_sigma_mm, config.ekf.gate_probability)
        self._tracker_fk = WarmFK()

    def update(self, sample: Sample) -> None:
        """Fold in one sample; ``SampleRejected`` leaves the state untouched."""
        strokes, readings = check_sample(self.platform, sample)
        last_t_s = self.filter.t_s
        dt_s = 0.0 if math.isnan(last_t_s) else sample.t_s - last_t_s
        if dt_s < 0.0:
            raise SampleRejected(
                f"ekf: sample at t = {sample.t_s} s is older than the last one ({last_t_s} s)", SampleRejected.TIME_BACK
            )
        R_v, t_v = self._tracker_fk.solve(self.platform.tracker, readings, "tracker")
        # r, H = ∂r/∂M and R_meas = J_x Σ_x J_xᵀ + σ_q² I at the model M + X, in one compiled call.
        residual, H, R_meas = kin.leg_ekf_observation(
            self.platform.drive, self.filter.x, self.platform.tracker, R_v, t_v, strokes,
            self.noise.reading_sigma_mm, self.noise.stroke_sigma_mm,
        )
        np.fill_diagonal(self.filter.Q, self.noise.random_walk_mm_per_sqrt_s**2 * dt_s)
        self.filter.update(H, -residual, R_meas, sample.t_s)

    def estimate(self) -> Estimate:
        """``δM`` and ``P`` after the last accepted sample."""
        return self.filter.estimate()

    def current_error(self) -> np.ndarray:
        """δM [mm] after the last accepted sample."""
        return self.filter.x.copy()

    def export_state(self) -> dict:
        """Filter and FK warm start as arrays (checkpoints; :meth:`import_state` restores)."""
        return {"filter": self.filter.export_state(), "tracker_fk": self._tracker_fk.export_state()}

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state` exactly. Raises ``CalibError`` on a bad key or shape."""
        self.filter.import_state(state.get("filter", {}))
        self._tracker_fk.import_state(state.get("tracker_fk", {}))
