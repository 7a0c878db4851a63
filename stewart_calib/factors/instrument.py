"""Instrument factor (tight coupling): one channel group of any measurement model.

Residual and analytic Jacobians come from the model (:class:`~stewart_calib.instruments.base.
InstrumentModel.residual`): ``r = h(pose, θ) − z`` on the group's channels, ``∂r/∂ξ`` on the
pose's body tangent ``[ω, v]`` (GTSAM's order) and ``∂r/∂θ`` on the model's own unknowns. This
module only adapts them to ``gtsam.CustomFactor``:

* a model without unknowns gives a unary factor on the pose ``x_k``;
* a model with unknowns gives a factor on ``(x_k, p_w)``, reading ``θ = θ₀ + p_w[block]`` from
  the unknown vector's instrument columns.

One factor per group (``model.groups``): for the tracker one per ruler, so a robust kernel
down-weights a single bad reading rather than the whole sample.
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from ..instruments.base import InstrumentModel

_KNOWN = np.zeros(0)  # θ of a model without unknowns


def _error(model: InstrumentModel, z: np.ndarray, channels: np.ndarray, block: slice | None, size: int,
           this: gtsam.CustomFactor, values: gtsam.Values, H):
    pose = values.atPose3(this.keys()[0])
    theta = _KNOWN if block is None else model.unknowns.nominal + values.atVector(this.keys()[1])[block]
    res = model.residual(pose.rotation().matrix(), pose.translation(), theta, z, channels)
    if H is not None:
        H[0] = res.J_pose
        if block is not None:
            H_params = np.zeros((len(channels), size))
            H_params[:, block] = res.J_instrument
            H[1] = H_params
    return res.r


def factor(
    model: InstrumentModel, pose_key: int, z: np.ndarray, channels: np.ndarray, noise: gtsam.noiseModel.Base,
    params_key: int | None = None, block: slice | None = None, size: int = 0,
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` for ``channels`` of the measurement ``z``.

    Args:
        params_key, block, size: the unknown-vector variable, the model's columns in it and its
            length; all three when the model has unknowns, none otherwise.
    """
    keys = [pose_key] if block is None else [pose_key, params_key]
    error = partial(_error, model, np.asarray(z, dtype=float), np.asarray(channels), block, size)
    return gtsam.CustomFactor(noise, keys, error)
