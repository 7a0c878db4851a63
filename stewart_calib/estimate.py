"""What every estimator returns: :class:`Estimate`, the identified parameter errors δM and,
where the unknown vector has more blocks (stroke scale, instrument unknowns), theirs.

Kept below :mod:`stewart_calib.io`, the estimators and the simulator, which all pass it around.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from .model.drive import PAYLOAD
from .model.legs import LegModel
from .model.platform import Platform
from .model.unknowns import UnknownLayout


@dataclass(frozen=True)
class Estimate:
    """Identified kinematic parameter errors δM (paper eq. 9, Table 4).

    Attributes:
        error: ``(n_params,)`` δM [mm], paper order (42 for the paper's 6-6 drive).
        covariance: ``(n_params, n_params)`` [mm²] or None when the method gives none.
        method: the method's name (``ls``, ``paper-ekf``, ``ekf``, ``isam2``, ``lm``).
        samples_used: samples folded in.
        t_s: time of the last sample folded in [s] (nan if none).
        layout: the blocks after δM in the unknown vector (not given: δM alone, as long as ``error``).
        block_error: ``(layout.size − n_params,)`` the blocks' errors from nominal [code units].
        full_covariance: ``(layout.size, layout.size)`` over ``[δM | blocks]`` [code units], or None.
        details: optional JSON-ready result fields the method adds (e.g. how it fixed the gauge,
            the noise it estimated); :func:`stewart_calib.io.result_dict` writes them.
    """

    error: np.ndarray
    covariance: np.ndarray | None
    method: str
    samples_used: int = 0
    t_s: float = float("nan")
    layout: UnknownLayout = field(default=None)  # type: ignore[assignment]  # None: δM alone, set in __post_init__
    block_error: np.ndarray = field(default_factory=lambda: np.zeros(0))
    full_covariance: np.ndarray | None = None
    details: dict | None = None

    def __post_init__(self) -> None:
        if self.layout is None:
            object.__setattr__(self, "layout", UnknownLayout(n_params=len(self.error)))

    @classmethod
    def of_state(
        cls,
        x: np.ndarray,
        P: np.ndarray | None,
        layout: UnknownLayout,
        method: str,
        samples_used: int = 0,
        t_s: float = float("nan"),
    ) -> Estimate:
        """The estimate of a whole unknown vector ``x = [δM | blocks]`` with covariance ``P`` (copied)."""
        x = np.array(x, dtype=float)
        P = None if P is None else np.array(P, dtype=float)
        n = layout.n_params
        return cls(
            x[:n],
            None if P is None else P[:n, :n],
            method,
            samples_used,
            t_s,
            layout,
            x[n:],
            None if layout.blocks == () else P,
        )

    @property
    def stddev(self) -> np.ndarray | None:
        """``sqrt(diag(covariance))`` [mm], or None."""
        return None if self.covariance is None else np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    def drive(self, nominal: LegModel | Platform) -> LegModel:
        """The estimated drive geometry ``M + δM``."""
        legs = nominal.drive if isinstance(nominal, Platform) else nominal
        return legs.perturbed(self.error)

    def block_values(self, key: str) -> np.ndarray | None:
        """Nominal + error of block ``key`` [code units], or None when the estimate has no such block."""
        block, columns = self.layout.block(key), self.layout.slice(key)
        if block is None or columns is None:  # both or neither
            return None
        start = columns.start - self.layout.n_params
        return block.nominal + self.block_error[start : start + block.size]

    def unannounced_payload_kg(self) -> float:
        """The payload [kg] the estimator found beyond the one the log announced (an elastic drive's
        ``payload`` block, ``[elastic] payload_sigma_kg``); 0 without that block."""
        values = self.block_values(PAYLOAD)
        return 0.0 if values is None else float(values[0])

    def block_results(self) -> dict[str, dict]:
        """``{key: {"names", "estimate", "stddev"}}`` of every block, in file units (spec §7)."""
        stddev = None
        if self.full_covariance is not None:
            stddev = np.sqrt(np.clip(np.diag(self.full_covariance)[self.layout.n_params :], 0.0, None))
        out, start = {}, 0
        for block in self.layout.blocks:
            cols = slice(start, start + block.size)
            out[block.key] = block.to_file(self.block_error[cols], None if stddev is None else stddev[cols])
            start += block.size
        return out


@runtime_checkable
class MeanEstimator(Protocol):
    """What an estimator may offer beside :class:`~stewart_calib.estimators.Estimator` (every
    built-in one does; a plugin need not: callers fall back to ``estimate()``). Here, below the
    estimators, so that the closed-loop simulator can ask for it."""

    def current_estimate(self) -> Estimate:
        """What ``estimate()`` gives, its covariance left out where that costs extra (isam2):
        the whole unknown vector (δM and the blocks: an elastic drive's compliance) for a caller
        that needs the model, not its error bars, once per sample."""


def model_estimate(estimator) -> Estimate:
    """``estimator``'s estimate for a caller that needs the model, not its error bars, once per sample:
    ``current_estimate()`` where it offers one (:class:`MeanEstimator`; isam2's ``estimate()`` costs a
    marginal), else ``estimate()``."""
    return estimator.current_estimate() if isinstance(estimator, MeanEstimator) else estimator.estimate()
