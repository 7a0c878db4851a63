"""Gauge constraint on a parameter variable: ``C x = 0`` with a near-hard σ.

Where an instrument's unknowns (its frame in {J}, its target in {D}, the tracker's geometry)
move the predictions exactly as a rigid motion of all base or all platform joints does, those
directions are fixed by holding the joints' mean rigid motion at nominal
(:meth:`stewart_calib.model.unknowns.UnknownLayout.gauge_rows`). The constraint is linear, so the
residual is ``C x`` and its Jacobian ``C``; σ = :data:`SIGMA` makes it hard next to any prior
(µm to mm) while keeping the system well conditioned in double precision.
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

#: σ of the constraint [code units]: 1e-4, four orders below the tightest prior (1e-2 mm) and below any
#: instrument's noise, so a violation stays ~1e-8 mm; 1e-6 puts the whitened Jacobian's condition number
#: past 1e7 beside a 20 mm prior, where gtsam's Cholesky marginals (lm) fail as 'indeterminate'.
SIGMA = 1e-4


def _error(C: np.ndarray, this: gtsam.CustomFactor, values: gtsam.Values, H):
    x = values.atVector(this.keys()[0])
    if H is not None:
        H[0] = C
    return C @ x


def factor(params_key: int, C: np.ndarray) -> gtsam.CustomFactor:
    """A unary ``CustomFactor`` ``C x = 0`` on the unknown vector ``params_key``."""
    C = np.array(C, dtype=float)
    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(len(C), SIGMA), [params_key], partial(_error, C))
