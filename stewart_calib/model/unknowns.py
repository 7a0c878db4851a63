"""The unknown vector: the drive parameters δM first, then optional named blocks.

Layout (spec §5 and §7)::

    x = [ δM (n_params: 42 for the paper's 6-6 drive, paper order) | block 1 | block 2 | … ]

Every entry is an *error from its nominal value* in code units (mm, rad, dimensionless), so
``x = 0`` is the nominal model and each estimator's prior is ``N(0, diag(σ²))``. A block is an
:class:`UnknownBlock`: a drive model's (:mod:`stewart_calib.model.drive`: the stroke scale ``k1…k6``) or
an instrument's own unknowns (frame, targets, the tracker's geometry; declared by its model in
:mod:`stewart_calib.instruments`). The result keeps the drive values of §5 and adds one
``{"names", "estimate", "stddev"}`` entry per block under the block's ``key``, in file units.

Gauge. An instrument frame {I} in {J} moves its predictions exactly as a rigid motion of all
base joints ``j_i`` does, and a target in {D} exactly as a rigid motion of all platform joints
``d_i``: 6 + 6 directions no data can tell apart. A block says which of the two it shares
(``gauge``); :meth:`UnknownLayout.gauge_rows` then gives the linear constraints ``C x = 0``
that hold the mean rigid motion of those joints at nominal (translation: the mean of ``δj_i``;
rotation: ``Σ (j_i − j̄) × δj_i``), which defines {J} and {D} by the nominal joints, as the
platform file does. Each estimator imposes ``C x = 0`` in its own way and says so
(docs/architecture.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:  # the annotation's type: the leg models sit above the unknown layout
    from .legs import LegModel

#: the two rigid motions a block may share with the drive (see the module docstring).
GAUGES = ("base", "platform")


@dataclass(frozen=True)
class UnknownBlock:
    """A named group of unknowns after the drive parameters δM.

    Attributes:
        key: the result's key for the block (``"stroke_scale"``, ``"instrument"``).
        names: one name per unknown, as the result lists them.
        nominal: ``(n,)`` nominal values [code units: mm, rad or dimensionless].
        prior_sigma: ``(n,)`` prior σ of the error from nominal [code units], all > 0.
        file_scale: ``(n,)`` file value = code value × file_scale (``180/π`` for an angle).
        gauge: which of :data:`GAUGES` the block shares with the drive.
        random_walk: whether the block drifts with the drive's random walk (else constant).
        holds_gauge: the gauge rows hold this block's own joints (``joints``) at their nominal mean
            rigid motion instead of the drive's — for a block
            known far better than the drive: the in-situ tracker's calibrated geometry then defines
            {J} and {D}, and the drive's own rigid error (millimetres, Table 4) is identified
            against it rather than pushed into the tracker, millimetres off its 15 µm prior.
        joints: where it holds the gauge, ``(base, platform)`` ``(n, 3)`` int columns of its values
            holding those joints (its leg set's :attr:`~stewart_calib.model.legs.LegModel.gauge_columns`).
    """

    key: str
    names: tuple[str, ...]
    nominal: np.ndarray
    prior_sigma: np.ndarray
    file_scale: np.ndarray = field(default=None)  # type: ignore[arg-type]  # None: ones, set in __post_init__
    gauge: tuple[str, ...] = ()
    random_walk: bool = False
    holds_gauge: bool = False
    joints: tuple[np.ndarray, np.ndarray] | None = None

    def __post_init__(self) -> None:
        if self.holds_gauge and self.joints is None:
            raise ValueError(f"block '{self.key}' holds the gauge: it must name its joints' columns")
        n = len(self.names)
        scale = np.ones(n) if self.file_scale is None else self.file_scale
        for name, value in (("nominal", self.nominal), ("prior_sigma", self.prior_sigma), ("file_scale", scale)):
            array = np.array(value, dtype=float).reshape(-1)
            if array.shape != (n,):
                raise ValueError(f"block '{self.key}': {name} must have {n} values, got {array.shape}")
            array.setflags(write=False)
            object.__setattr__(self, name, array)
        if not np.all(self.prior_sigma > 0):
            raise ValueError(f"block '{self.key}': every prior σ must be positive")
        unknown = set(self.gauge) - set(GAUGES)
        if unknown:
            raise ValueError(f"block '{self.key}': gauge {sorted(unknown)} not one of {GAUGES}")

    @property
    def size(self) -> int:
        return len(self.names)

    def to_file(self, error: np.ndarray, stddev: np.ndarray | None) -> dict:
        """The result entry ``{"names", "estimate", "stddev"}`` in file units (spec §7)."""
        estimate = (self.nominal + np.asarray(error, dtype=float)) * self.file_scale
        return {
            "names": list(self.names),
            "estimate": estimate.tolist(),
            "stddev": None if stddev is None else (np.asarray(stddev, dtype=float) * np.abs(self.file_scale)).tolist(),
        }


@dataclass(frozen=True)
class UnknownLayout:
    """Where each block sits in the unknown vector ``x = [δM | blocks…]``.

    Attributes:
        blocks: the named blocks after δM, in order.
        n_params: entries of δM, the drive's leg set's (:attr:`~stewart_calib.model.drive.DriveModel.n_params`,
            42 for the paper's 6-6 drive); a keyword, the layout names no leg set of its own.
    """

    blocks: tuple[UnknownBlock, ...] = ()
    n_params: int = field(kw_only=True)

    def __post_init__(self) -> None:
        keys = [block.key for block in self.blocks]
        if len(set(keys)) != len(keys):
            raise ValueError(f"unknown blocks must have distinct keys, got {keys}")

    @property
    def size(self) -> int:
        """``n_params + Σ block sizes``."""
        return self.n_params + sum(block.size for block in self.blocks)

    def slice(self, key: str) -> slice | None:
        """The columns of block ``key`` in ``x``, or None when the layout has no such block."""
        start = self.n_params
        for block in self.blocks:
            if block.key == key:
                return slice(start, start + block.size)
            start += block.size
        return None

    def block(self, key: str) -> UnknownBlock | None:
        return next((block for block in self.blocks if block.key == key), None)

    def prior_sigma(self, drive_sigma_mm: float | np.ndarray) -> np.ndarray:
        """``(size,)`` prior σ: ``drive_sigma_mm`` on δM (one for all, or ``(n_params,)`` entry by entry),
        then each block's own [code units]."""
        return np.concatenate([np.full(self.n_params, drive_sigma_mm), *(block.prior_sigma for block in self.blocks)])

    def walks(self) -> np.ndarray:
        """``(size,)`` bool: which unknowns follow the parameter random walk (δM always)."""
        return np.concatenate([np.ones(self.n_params, bool), *(np.full(b.size, b.random_walk) for b in self.blocks)])

    def walk_scales(self, drive_walk: np.ndarray, rate: float) -> np.ndarray | None:
        """``(size,)`` each walking unknown's random walk over the common ``rate`` [per √s]: δM's
        ``drive_walk`` ``(n_params,)`` (the drive's :meth:`~stewart_calib.model.drive.DriveModel.walk_sigmas`)
        over it, 1 on the blocks; None where every entry walks at the rate itself (a prismatic drive)."""
        drive_walk = np.asarray(drive_walk, dtype=float)
        if not rate > 0.0 or np.all(drive_walk == rate):
            return None
        return np.concatenate([drive_walk / rate, np.ones(self.size - self.n_params)])

    def gauge_rows(self, drive: LegModel) -> np.ndarray:
        """``(g, size)`` constraints ``C x = 0`` fixing the gauge the blocks share with the drive.

        Three rows hold the mean translation and three the mean rotation of the base joints
        (when a block's ``gauge`` has ``"base"``), and the same for the platform joints; g is 0,
        6 or 12: the drive's joints, or those of a block that ``holds_gauge``. Rows are scaled to
        unit norm so that a constraint weight means the same on each.
        """
        shared = {gauge for block in self.blocks for gauge in block.gauge}
        holder = next((block for block in self.blocks if block.holds_gauge), None)
        start, values, joints = 0, drive.as_vector(), drive.gauge_columns
        if holder is not None and holder.joints is not None and (columns := self.slice(holder.key)) is not None:
            start, values, joints = columns.start, holder.nominal, holder.joints
        rows = []
        for gauge, columns_of in zip(("base", "platform"), joints, strict=True):
            if gauge in shared:
                rows.append(_rigid_motion_rows(values, np.asarray(columns_of), start, self.size))
        return np.vstack(rows) if rows else np.zeros((0, self.size))

    def split(self, x: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """``x`` → ``(δM (n_params,), {key: block error})``."""
        x = np.asarray(x, dtype=float)
        return x[: self.n_params], {block.key: x[self.slice(block.key)] for block in self.blocks}


def _rigid_motion_rows(values: np.ndarray, joints: np.ndarray, start: int, size: int) -> np.ndarray:
    """Rows whose span is the rigid motions ``δp_i = a + ω × (p_i − p̄)`` of the joints
    ``p_i = values[joints[i]]`` (``joints`` ``(n, 3)`` int columns of the parameter vector ``values``),
    laid out from column ``start`` of ``x`` as ``values`` is (``p_i`` at ``start + joints[i]``):
    translation ``Σ δp_i`` and rotation ``Σ (p_i − p̄) × δp_i``, each row scaled to unit norm."""
    C = np.zeros((6, size))
    points = values[joints]
    arms = points - points.mean(axis=0)
    for i in range(len(joints)):
        cols = start + joints[i]
        C[0:3, cols] = np.eye(3)
        r = arms[i]
        C[3:6, cols] = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return C / np.linalg.norm(C, axis=1, keepdims=True)


def gauge_conditioned(covariance: np.ndarray, C: np.ndarray) -> np.ndarray:
    """``Σ − Σ Cᵀ (C Σ Cᵀ)⁺ C Σ``: the Gaussian ``N(0, Σ)`` conditioned on ``C x = 0``.

    A filter started from it (and whose process noise is conditioned too) keeps ``C x = 0``
    exactly: every gain ``K = P Hᵀ S⁻¹`` then satisfies ``C K = 0``. ``Σ`` itself when C has no rows.
    The pseudo-inverse covers a ``Σ`` that already satisfies some rows (``C Σ = 0`` there: a
    random walk of δM when a constant block holds the gauge), which it leaves as it is.
    """
    if len(C) == 0:
        return covariance
    SC = covariance @ C.T
    conditioned = covariance - SC @ np.linalg.pinv(C @ SC, hermitian=True) @ SC.T
    return 0.5 * (conditioned + conditioned.T)
