"""The in-situ tracker (paper §2, Table 2, §4.1): six grating-ruler legs between base and platform.

True readings are the tracker IK of the *true* pose on the tracker's *true* geometry, which may
differ from the nominal Table 2 geometry (that estimators are given) by a residual error —
the tracker was calibrated by stereo vision [27], not perfectly; this residual is what makes its
pose accuracy against a reference instrument 0.036 mm / 0.022° (paper §4.1). Then white ruler
noise, the 50 nm quantisation of the reading head, and the reading range (−276…318 mm):
a reading outside it is lost (NaN), as a real head loses count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..instruments.tracker import tracker_parameter_names
from ..model import kinematics as kin
from ..model.platform import LegGeometry


@dataclass(frozen=True)
class Tracker:
    """A simulated tracker.

    Attributes:
        geometry: the *true* tracker legs (nominal Table 2 + residual) — unknown to estimators.
        noise_mm: white ruler noise σ [mm].
        quantum_mm: reading resolution [mm] (50 nm = 5e-5 mm); 0 = none.
        reading_range_mm: ``(min, max)`` [mm] or None.
        geometry_residual_mm: σ of the residual drawn on its nominal values [mm] (0: the nominal geometry).
    """

    geometry: LegGeometry
    noise_mm: float
    quantum_mm: float
    reading_range_mm: tuple[float, float] | None
    geometry_residual_mm: float = 0.0

    @classmethod
    def with_residual(cls, nominal: LegGeometry, residual_mm: float, rng: np.random.Generator, **kw) -> Tracker:
        """True geometry = nominal + i.i.d. normal residual σ = ``residual_mm`` on all its values (42 for six legs)."""
        delta = rng.normal(0.0, residual_mm, nominal.n_params) if residual_mm > 0 else np.zeros(nominal.n_params)
        return cls(nominal.perturbed(delta), geometry_residual_mm=residual_mm, **kw)

    def truth(self) -> tuple[tuple[str, ...], np.ndarray] | None:
        """``(names, values)`` of its own 42 values (``z1x … ls6`` [mm], spec §4) where they are off their
        nominal, else None: the truth of the frames its joints define."""
        if self.geometry_residual_mm <= 0.0:
            return None
        return tracker_parameter_names(self.geometry), self.geometry.as_vector()

    def true_readings(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Noise-free readings ``s_i = ‖t + R h_i − z_i‖ − l_si`` on the true geometry, ``(..., 6)`` [mm]."""
        return kin.inverse_kinematics(self.geometry, R, t)

    def read(self, R: np.ndarray, t: np.ndarray, unit_noise: np.ndarray) -> np.ndarray:
        """Readings as logged: true + σ·``unit_noise``, quantised, NaN outside the range, ``(..., 6)`` [mm].

        ``unit_noise`` are standard normal draws of the readings' shape, drawn by the caller up
        front so that results do not depend on how the samples are batched.
        """
        s = self.true_readings(R, t) + self.noise_mm * unit_noise
        if self.quantum_mm > 0:
            s = np.round(s / self.quantum_mm) * self.quantum_mm
        if self.reading_range_mm is not None:
            lo, hi = self.reading_range_mm
            s = np.where((s >= lo) & (s <= hi), s, np.nan)
        return s
