"""GTSAM custom factors: one module per factor type, each a pure residual with analytic
Jacobians plus a thin ``gtsam.CustomFactor`` adapter.

* :mod:`.drive_leg` — pose ↔ δM, one factor per drive leg (stroke q_i).
* :mod:`.instrument` — one channel group of any instrument model (tight coupling; for the
  tracker one factor per grating reading), on the pose and the instrument's unknowns.
* :mod:`.instrument_pose` — pose prior from an instrument's loose pose (for the tracker its FK,
  the paper's way).
* :mod:`.random_walk` — the unknown vector's random walk between parameter windows and its prior.
* :mod:`.gauge` — the gauge constraint ``C x = 0`` where an instrument's unknowns share the drive's.
* :mod:`.pose_misfit` — the in-situ tracker's misfit at a static pose, added to its samples' rows.
"""

import gtsam
import numpy as np


def diagonal_noise(sigmas: np.ndarray) -> gtsam.noiseModel.Base:
    """Independent Gaussian noise with σ per entry (isotropic when all are equal)."""
    sigmas = np.asarray(sigmas, dtype=float)
    if np.all(sigmas == sigmas[0]):
        return gtsam.noiseModel.Isotropic.Sigma(len(sigmas), float(sigmas[0]))
    return gtsam.noiseModel.Diagonal.Sigmas(sigmas)
