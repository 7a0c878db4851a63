"""What every estimator returns: :class:`Estimate`, the identified parameter errors δM.

Kept below :mod:`stewart_calib.io`, the estimators and the simulator, which all pass it around.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .platform import LegGeometry, Platform


@dataclass(frozen=True)
class Estimate:
    """Identified kinematic parameter errors δM (paper eq. 9, Table 4).

    Attributes:
        error: ``(42,)`` δM [mm], paper order.
        covariance: ``(42, 42)`` [mm²] or None when the method gives none.
        method: the method's name (``ls``, ``paper-ekf``, ``ekf``, ``isam2``, ``lm``).
        samples_used: samples folded in.
        t_s: time of the last sample folded in [s] (nan if none).
    """

    error: np.ndarray
    covariance: np.ndarray | None
    method: str
    samples_used: int = 0
    t_s: float = float("nan")

    @property
    def stddev(self) -> np.ndarray | None:
        """``sqrt(diag(covariance))`` [mm], or None."""
        return None if self.covariance is None else np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def drive(self, nominal: LegGeometry | Platform) -> LegGeometry:
        """The estimated drive geometry ``M + δM``."""
        legs = nominal.drive if isinstance(nominal, Platform) else nominal
        return legs.perturbed(self.error)
