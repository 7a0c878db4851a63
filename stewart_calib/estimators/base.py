"""What every estimator shares: the :class:`Estimate` it returns and the small protocol.

The protocol is two methods (plus ``fit`` for batch methods)::

    est.update(sample)      # fold in one Sample; raises SampleRejected and stays untouched
    est.estimate()          # -> Estimate (42 errors δM [mm], 42×42 covariance or None)

Parameters are always the paper's δM (eq. 9) in the paper's order: ``estimate = nominal + error``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Protocol, runtime_checkable

import numpy as np

from ..errors import CalibError, SampleRejected
from ..platform import LegGeometry, Platform
from ..samples import Sample


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


@runtime_checkable
class Estimator(Protocol):
    """The one protocol all methods share (``fit`` is optional, for batch methods)."""

    name: str

    def update(self, sample: Sample) -> None: ...

    def estimate(self) -> Estimate: ...


def current_error(estimator: Estimator) -> np.ndarray:
    """δM now [mm], without the covariance: an estimator whose covariance is costly (isam2's
    marginal, ~0.3 ms) may offer ``current_error()``; any other gives ``estimate().error``.
    For callers that need only the model, once per sample (traces, the controller's IK)."""
    fast = getattr(estimator, "current_error", None)
    return fast() if fast is not None else estimator.estimate().error


def feed(estimator: Estimator, samples: Iterable[Sample]) -> list[tuple[int, SampleRejected]]:
    """``update`` with every sample, skipping refused ones: their ``(index, SampleRejected)``."""
    rejected = []
    for k, sample in enumerate(samples):
        try:
            estimator.update(sample)
        except SampleRejected as err:
            rejected.append((k, err))
    return rejected


def fit_all(estimator: Estimator, samples: Iterable[Sample]) -> Estimate:
    """Feed every sample (batch methods use their own ``fit``) and return the estimate."""
    fit = getattr(estimator, "fit", None)
    if fit is not None:
        return fit(samples)
    for sample in samples:
        estimator.update(sample)
    return estimator.estimate()


def state_array(state: dict, key: str, shape: tuple[int, ...]) -> np.ndarray:
    """``state[key]`` as a float array of ``shape`` (a copy), for ``import_state`` methods.

    Raises:
        CalibError: the key is missing or has another shape (a corrupt or foreign checkpoint).
    """
    if key not in state:
        raise CalibError(f"estimator state: key '{key}' missing")
    value = np.array(state[key], dtype=float)
    if value.shape != shape:
        raise CalibError(f"estimator state: key '{key}': expected shape {shape}, got {value.shape}")
    return value
