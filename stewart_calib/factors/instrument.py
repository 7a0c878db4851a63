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

A tracker of known geometry (the default) is a set of legs with fixed rows ``[z_i | h_i | ls_i]``:
its factors take those rows once and are linearised in one compiled call
(:func:`._kernels.known_leg_rows`, the arithmetic of ``TrackerModel.residual``), a third of
the model's per-call cost (fancy indexing and a residual tuple per linearisation). A model
whose reading is a target's pose (``compiled_pose_reading``: the pose instrument), likewise, is one
compiled call (:func:`._kernels.pose_reading_rows`, the arithmetic of ``PoseModel.residual``, where
~30 small numpy calls a linearisation cost most of iSAM2's time with the motion-capture preset:
BENCHMARKS.md), and so is a ruler whose geometry is unknown (``compiled_unknown_legs``: the tracker
identified, :func:`._kernels.unknown_leg_rows`).
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np

from ..instruments.base import InstrumentModel
from . import pose_misfit
from ._kernels import known_leg_rows, pose_reading_rows, unknown_leg_rows

_KNOWN = np.zeros(0)  # θ of a model without unknowns


def _error(
    model: InstrumentModel,
    z: np.ndarray,
    channels: np.ndarray,
    block: slice | None,
    size: int,
    keys: tuple,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    H,
):
    pose = values.atPose3(keys[0]).matrix()  # one conversion, not rotation() and translation()
    unknowns = model.unknowns
    theta = _KNOWN if block is None or unknowns is None else unknowns.nominal + values.atVector(keys[1])[block]
    res = model.residual(pose[:3, :3], pose[:3, 3], theta, z, channels)
    if H is not None:
        H[0] = res.J_pose
        if block is not None:
            H_params = np.zeros((len(channels), size))
            H_params[:, block] = res.J_instrument
            H[1] = H_params
    return res.r


def _known_legs_error(
    legs: np.ndarray, readings: np.ndarray, pose_key: int, this: gtsam.CustomFactor, values: gtsam.Values, H
):
    r, H_pose = known_leg_rows(values.atPose3(pose_key).matrix(), legs, readings)
    if H is not None:
        H[0] = H_pose
    return r


def _unknown_legs_error(
    readings: np.ndarray,
    nominal: np.ndarray,
    block: slice,
    columns: np.ndarray,
    keys: tuple,
    this: gtsam.CustomFactor,
    values: gtsam.Values,
    H,
):
    """:func:`_error` of rulers whose geometry is unknown (``compiled_unknown_legs``) in one compiled call
    (:func:`._kernels.unknown_leg_rows`): the unknown vector with θ = θ₀ + p in the model's columns."""
    params = values.atVector(keys[1])
    params[block] += nominal
    r, J_pose, H_params = unknown_leg_rows(values.atPose3(keys[0]).matrix(), params, columns, readings)
    if H is not None:
        H[0] = J_pose
        H[1] = H_params
    return r


def _pose_reading_error(
    z: np.ndarray, nominal: np.ndarray, block: slice, size: int, keys: tuple, this: gtsam.CustomFactor, values, H
):
    """:func:`_error` of a pose instrument's reading (its six channels, frame and target unknown) in one
    compiled call (:func:`._kernels.pose_reading_rows`, the arithmetic of ``PoseModel.residual``)."""
    theta = nominal + values.atVector(keys[1])[block]
    r, J_pose, J_theta = pose_reading_rows(values.atPose3(keys[0]).matrix(), theta, z)
    if H is not None:
        H[0] = J_pose
        H_params = np.zeros((len(r), size))
        H_params[:, block] = J_theta
        H[1] = H_params
    return r


def known_legs(model: InstrumentModel, channels: np.ndarray) -> np.ndarray | None:
    """``(k, 7)`` rows ``[z_i | h_i | ls_i]`` of the legs ``channels`` of a leg set of known
    geometry (:attr:`~stewart_calib.instruments.base.InstrumentModel.compiled_legs`: the tracker's
    rulers), what its factors share across samples; None for any other model."""
    legs = model.compiled_legs
    if legs is None:
        return None
    return np.ascontiguousarray(legs.params[np.asarray(channels, dtype=np.int64)], dtype=float)


def factor(
    model: InstrumentModel,
    pose_key: int,
    z: np.ndarray,
    channels: np.ndarray,
    noise: gtsam.noiseModel.Base,
    params_key: int | None = None,
    block: slice | None = None,
    size: int = 0,
    legs: np.ndarray | None = None,
    misfit: tuple[int, np.ndarray] | None = None,
) -> gtsam.CustomFactor:
    """A ``CustomFactor`` for ``channels`` of the measurement ``z``.

    Args:
        params_key, block, size: the unknown-vector variable, the model's columns in it and its
            length; all three when the model has unknowns, none otherwise.
        legs: :func:`known_legs` of ``channels`` where the caller keeps them (else found here).
        misfit: ``(key, rows)``: a static pose's misfit variable and its rows of these channels, added to
            the residual (:mod:`.pose_misfit`); None: none.
    """
    channels = np.asarray(channels, dtype=np.int64)
    z = np.asarray(z, dtype=float)
    legs = known_legs(model, channels) if legs is None else legs
    if legs is not None:
        return pose_misfit.custom(noise, [pose_key], partial(_known_legs_error, legs, z[channels], pose_key), misfit)
    keys = [pose_key] if block is None or params_key is None else [pose_key, params_key]
    unknowns = model.unknowns
    if (
        model.compiled_pose_reading
        and unknowns is not None
        and block is not None
        and len(keys) == 2
        and len(channels) == len(z)  # the whole reading, in one compiled call
    ):
        nominal = np.ascontiguousarray(unknowns.nominal, dtype=float)
        return pose_misfit.custom(
            noise, keys, partial(_pose_reading_error, np.array(z), nominal, block, size, tuple(keys)), misfit
        )
    if model.compiled_unknown_legs and unknowns is not None and block is not None and len(keys) == 2:
        nominal = np.ascontiguousarray(unknowns.nominal, dtype=float)
        per_leg = unknowns.size // len(model.columns)  # the unknowns: one leg's row a reading channel
        columns = block.start + per_leg * channels[:, None] + np.arange(per_leg)
        readings = np.ascontiguousarray(z[channels])
        return pose_misfit.custom(
            noise, keys, partial(_unknown_legs_error, readings, nominal, block, columns, tuple(keys)), misfit
        )
    return pose_misfit.custom(noise, keys, partial(_error, model, z, channels, block, size, tuple(keys)), misfit)
