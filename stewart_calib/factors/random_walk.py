"""Parameter random walk between consecutive parameter variables, and the manufacturing prior.

δM is modelled as a random walk (the paper's ``P + Q``, eq. 15; docs/architecture.md): between the
variables of two parameter windows spaced Δt apart, ``δM_{w+1} − δM_w ~ N(0, σ² I)`` with
``σ = random_walk · √Δt`` [mm]; constant blocks of the unknown vector (stroke scale, the
instrument's unknowns) are tied by the chain's floor σ alone. GTSAM's own ``BetweenFactorVector`` and
``PriorFactorVector`` implement these residuals exactly (``(b − a) − 0`` and ``x − 0``), so no
custom factor is needed: one between factor per window is far below the per-sample cost
whichever form it takes (BENCHMARKS.md for the per-sample times).
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from . import diagonal_noise


def sigma_mm(random_walk_mm_per_sqrt_s: float, dt_s: float, floor_mm: float) -> float:
    """``max(random_walk · √Δt, floor)`` [mm].

    The floor keeps a near-hard tie when the walk is 0 (or Δt is 0): a zero σ is not a valid
    Gaussian, and the fixed-lag smoother needs a chain of variables, not one static variable.
    """
    return max(random_walk_mm_per_sqrt_s * math.sqrt(max(dt_s, 0.0)), floor_mm)


def factor(key_from: int, key_to: int, sigmas: np.ndarray) -> gtsam.BetweenFactorVector:
    """``x_to − x_from ~ N(0, diag(σ²))`` on two unknown vectors; σ per entry [code units]."""
    return gtsam.BetweenFactorVector(key_from, key_to, np.zeros(len(sigmas)), diagonal_noise(sigmas))


def prior(key: int, sigmas: np.ndarray) -> gtsam.PriorFactorVector:
    """``x ~ N(0, diag(σ²))``: the manufacturing tolerance of every parameter (and each block's
    own prior); σ per entry [code units]."""
    return gtsam.PriorFactorVector(key, np.zeros(len(sigmas)), diagonal_noise(sigmas))
