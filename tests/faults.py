"""Fault injection: a sample on which gtsam itself fails inside the iSAM2 update."""

from __future__ import annotations

import gtsam
import numpy as np

from stewart_calib.model.platform import N_PARAMS

#: what gtsam 4.3.0 says first when it throws IndeterminantLinearSystemException.
INDETERMINANT = "Indeterminate linear system detected while working near variable"


def _first_component(this, values, H):
    """A 1-dim error on a 42-vector: 41 directions of the variable stay unconstrained."""
    if H is not None:
        H[0] = np.eye(1, N_PARAMS)
    return values.atVector(this.keys()[0])[:1]


def degenerate_sample(monkeypatch, t_s: float) -> None:
    """Make the sample at ``t_s`` degenerate for every smoother built from now on.

    The update that adds it also gets a variable that one factor leaves underdetermined, so the
    real smoother takes the new factors and then throws ``IndeterminantLinearSystemException``
    (a ``RuntimeError``) from inside gtsam — a half-done update, as on a genuinely degenerate
    sample, every time that sample is fed.
    """

    class Smoother(gtsam.IncrementalFixedLagSmoother):
        def update(self, factors, values, timestamps):
            if t_s in timestamps.values():
                # a parameter-type key: iSAM2's per-type relinearisation thresholds must know it
                z = gtsam.symbol("p", 10**6)
                values.insert(z, np.zeros(N_PARAMS))
                factors.add(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, 1.0), [z], _first_component))
                timestamps = {**timestamps, z: t_s}
            return super().update(factors, values, timestamps)

    monkeypatch.setattr(gtsam, "IncrementalFixedLagSmoother", Smoother)
