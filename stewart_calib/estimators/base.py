"""The protocols every estimator follows, checked with ``isinstance`` (never by probing names).

:class:`Estimator` — every method::

    est = Class(platform, config)   # the one constructor signature (estimators/registry.py builds it)
    est.update(sample)              # fold in one Sample; raises SampleRejected and stays untouched
    est.estimate()                  # -> Estimate (δM [mm], covariance or None)
    est.current_error()             # -> δM [mm] alone, for per-sample callers (traces, the controller)

:class:`BatchEstimator` — a method that fits a whole log at once adds ``fit(samples)`` and lists
the samples it skipped in ``rejected``. :class:`KalmanFiltered` — a Kalman method shows its
``filter`` (the NIS of the last update, for diagnostics). :class:`Checkpointable` — a method whose state can be
saved and restored exactly adds ``export_state()`` / ``import_state(state)`` (nested dicts of
arrays; ``stewart_calib.workflows.online`` writes them to checkpoints). :class:`BlockUpdating` — a method
that folds in a block of samples faster than one ``update`` at a time adds ``update_block``;
callers go through :func:`update_block`, which falls back to :func:`update_each`.

Parameters are always the paper's δM (eq. 9) in the paper's order: ``estimate = nominal + error``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from typing import Protocol, runtime_checkable

import numpy as np

from ..errors import CalibError, SampleRejected, number
from ..estimate import Estimate
from ..inputs import MAX_TIME_S
from ..samples import Log, Sample


@runtime_checkable
class Estimator(Protocol):
    """What every method offers."""

    name: str

    def update(self, sample: Sample) -> None:
        """Fold in one sample; :class:`SampleRejected` leaves the estimator untouched."""

    def estimate(self) -> Estimate:
        """δM [mm] with its covariance after the samples folded in so far."""

    def current_error(self) -> np.ndarray:
        """δM [mm] alone: what ``estimate().error`` gives, without the covariance, which some
        methods pay for (isam2's marginal, ~0.3 ms); callers that need only the model once
        per sample use this."""


@runtime_checkable
class BatchEstimator(Estimator, Protocol):
    """A method that fits the whole log at once."""

    #: ``(index in the fitted samples, SampleRejected)`` of the samples :meth:`fit` skipped.
    rejected: list[tuple[int, SampleRejected]]

    def fit(self, samples: Iterable[Sample]) -> Estimate:
        """Fold in every usable sample, listing the others in ``rejected``, and solve."""


@runtime_checkable
class Checkpointable(Protocol):
    """A method whose state can be exported and restored exactly (equal states, equal futures)."""

    def export_state(self) -> dict:
        """The state as a nested dict of numpy arrays."""

    def import_state(self, state: dict) -> None:
        """Restore :meth:`export_state` on a freshly built estimator; ``CalibError`` on a bad state."""


@runtime_checkable
class CheckpointableEstimator(Estimator, Checkpointable, Protocol):
    """An estimator whose state can be checkpointed: every online method (``track`` resumes them)."""


class _NIS(Protocol):
    """What diagnostics read of a :class:`~stewart_calib.estimators.kalman.FilterState`."""

    nis: float


@runtime_checkable
class KalmanFiltered(Protocol):
    """A method whose updates are Kalman updates (``ekf``, ``paper-ekf``): its ``filter`` (a
    :class:`~stewart_calib.estimators.kalman.FilterState`) holds the last accepted sample's
    normalised innovation squared, ``filter.nis``, for diagnostics."""

    filter: _NIS


@runtime_checkable
class Relinearising(Protocol):
    """An online method whose estimate and covariance sum each sample's information at the state it stood at
    when the sample came (``ekf``; ``isam2``, whose factors keep their linearisation within its threshold), so
    that a caller holding the whole log can ask what the log holds: its optimum, found from that estimate."""

    def relinearised(self, samples: Iterable[Sample]) -> Estimate | None:
        """The MAP of the method's prior and ``samples`` (those it used) by Gauss–Newton from ``estimate()``, with
        the method's own model, noise and walk, and its covariance there; None where it does not settle."""


def take_late_rejections(estimator: Estimator) -> list[SampleRejected]:
    """Samples an estimator took provisionally and has since left out (a robust start-up batch,
    :mod:`.robust`), or refused in an update that moved its state all the same (an unannounced payload's
    step taken at a sample it does not take), each reported once; ``err.t_s`` is the sample's time. Empty
    for others."""
    take = getattr(estimator, "take_late_rejections", None)
    return take() if take is not None else []


def payload_change_field(dropped: int, readmitted: int) -> dict | None:
    """The result's ``"payload_change"`` from the samples an unannounced payload's steps left out of the estimate
    (taken while the payload moved) and took back in after a refusal; None where they moved none."""
    if not (dropped or readmitted):
        return None
    return {"samples_dropped": dropped, "samples_readmitted": readmitted}


def row_accounting(estimator: Estimator) -> dict:
    """The result fields that account for the samples an estimator took but its estimate's
    ``samples_used`` does not count: ``"samples_held"`` (waiting to register the instrument) and
    ``"recovery"`` (lock-out recoveries: samples dropped from the estimate, and readmitted after a
    refusal) and ``"payload_change"`` (an unannounced payload's steps, alike), each only when not empty.
    With them, rows = used + skipped + dropped + held, where skipped counts the bad rows and the refused
    samples not readmitted (:func:`skipped_count`)."""
    fields: dict = {}
    held = getattr(estimator, "samples_held", lambda: 0)()
    if held:
        fields["samples_held"] = held
    recovery = getattr(estimator, "recovery_summary", lambda: None)()
    if recovery:
        fields["recovery"] = recovery
    change = getattr(estimator, "payload_change_summary", lambda: None)()
    if change:
        fields["payload_change"] = change
    return fields


def readmitted_count(estimate: Estimate) -> int:
    """The refused samples a lock-out recovery or an unannounced payload's step took back in (``estimate``'s
    details, :func:`row_accounting`): among the used (or dropped again), no longer among the refused. The gate
    had refused each (reason ``gated outlier``): only its refusals are tried again."""
    details = estimate.details or {}
    return sum(int((details.get(key) or {}).get("samples_readmitted", 0)) for key in ("recovery", "payload_change"))


def skipped_count(bad_rows: int, refused: int, estimate: Estimate) -> int:
    """The result's ``samples_skipped``: bad rows and refused samples, less those taken back in
    (:func:`readmitted_count`): they are among the used."""
    return bad_rows + refused - readmitted_count(estimate)


def accounted_estimate(estimator: Estimator) -> Estimate:
    """``estimator.estimate()`` with :func:`row_accounting`'s fields among its result details."""
    estimate = estimator.estimate()
    fields = row_accounting(estimator)
    return dataclasses.replace(estimate, details={**(estimate.details or {}), **fields}) if fields else estimate


def accounting_words(fields: dict) -> str:
    """:func:`row_accounting`'s fields for a summary line: ``", 34 dropped by 1 lock-out recovery"``…"""
    words = ""
    recovery = fields.get("recovery")
    if recovery:
        plural = "y" if recovery["count"] == 1 else "ies"
        words += f", {recovery['samples_dropped']} dropped by {recovery['count']} lock-out recover{plural}"
        if recovery["samples_readmitted"]:
            words += f" (which took back {recovery['samples_readmitted']} it had refused)"
    change = fields.get("payload_change")
    if change and change["samples_dropped"]:
        words += f", {change['samples_dropped']} taken while an unannounced payload changed left out"
    if change and change["samples_readmitted"]:
        words += f", {change['samples_readmitted']} refused before a payload step took back"
    if fields.get("samples_held"):
        words += f", {fields['samples_held']} held to register the instrument (too few distinct poses)"
    return words


#: ``(index of the sample, SampleRejected)`` pairs.
Refusals = list[tuple[int, SampleRejected]]


@runtime_checkable
class BlockUpdating(Protocol):
    """A method that folds in a block of samples faster than :meth:`Estimator.update` one by one."""

    def update_block(self, block: Log, errors_out: np.ndarray | None = None) -> tuple[Refusals, Refusals]:
        """What :func:`update_each` does with ``block``: the same refusals and, to rounding, the same
        estimates (a compiled recursion may sum in another order than ``update``'s kernels); where
        ``errors_out`` is None, ``isam2`` takes a parameter window's samples in one smoother update,
        within its relinearisation threshold of one update a sample (~1e-6 mm)."""


def update_each(
    estimator: Estimator, samples: Iterable[Sample], errors_out: np.ndarray | None = None, first: int = 0
) -> tuple[Refusals, Refusals]:
    """``update`` with each of ``samples`` in turn.

    Args:
        errors_out: ``(len(samples), n_params)``: δM [mm] after each sample (the estimate in force
            after a refused one), or None.
        first: the index of the first sample (added to the indices returned).
    Returns:
        ``(refused, late)``: the samples ``update`` refused, and those refused late
        (:func:`take_late_rejections`, ``err.t_s`` their time) each with the index of the sample
        after which they were.
    """
    refused: Refusals = []
    late: Refusals = []
    for j, sample in enumerate(samples):
        try:
            estimator.update(sample)
        except SampleRejected as err:
            refused.append((first + j, err))
        late.extend((first + j, err) for err in take_late_rejections(estimator))
        if errors_out is not None:
            errors_out[j] = estimator.current_error()
    return refused, late


def update_block(estimator: Estimator, block: Log, errors_out: np.ndarray | None = None) -> tuple[Refusals, Refusals]:
    """:func:`update_each` over the samples of ``block``, by the estimator's own faster way where it has one."""
    if isinstance(estimator, BlockUpdating):
        return estimator.update_block(block, errors_out)
    return update_each(estimator, block, errors_out)


def feed(estimator: Estimator, samples: Iterable[Sample]) -> list[tuple[int, SampleRejected]]:
    """``update`` with every sample, skipping refused ones: their ``(index, SampleRejected)``,
    including those refused late (:func:`take_late_rejections`), in the order they were refused."""
    rejected, times = [], []
    for k, sample in enumerate(samples):
        times.append(sample.t_s)
        try:
            estimator.update(sample)
        except SampleRejected as err:
            rejected.append((k, err))
        for late in take_late_rejections(estimator):
            rejected.append((late_index(times, late.t_s), late))
    return rejected


def late_index(times: list[float], t_s: float) -> int:
    """Index of the latest sample at ``t_s`` in ``times`` (the times fed so far)."""
    return next(k for k in range(len(times) - 1, -1, -1) if times[k] == t_s)


class BufferedFit:
    """``fit`` and ``current_error`` of a batch method whose ``update`` buffers a sample and
    whose ``estimate`` solves everything buffered (``ls``, ``lm``); it keeps ``rejected``."""

    rejected: list[tuple[int, SampleRejected]]

    def current_error(self: BatchEstimator) -> np.ndarray:
        """δM [mm] of a solve over every buffered sample (as ``estimate``)."""
        return self.estimate().error

    def current_estimate(self: BatchEstimator) -> Estimate:
        """``estimate()``: the covariance comes with the solve."""
        return self.estimate()

    def fit(self: BatchEstimator, samples: Iterable[Sample]) -> Estimate:
        """Buffer every usable sample, listing the others in ``rejected``, and solve."""
        self.rejected.extend(feed(self, samples))
        return self.estimate()


def fit_all(estimator: Estimator, samples: Iterable[Sample]) -> Estimate:
    """Feed every sample (a :class:`BatchEstimator` uses its own ``fit``) and return the estimate."""
    if isinstance(estimator, BatchEstimator):
        return estimator.fit(samples)
    for sample in samples:
        estimator.update(sample)
    return estimator.estimate()


def checked_covariance(matrix: np.ndarray, key: str) -> np.ndarray:
    """``matrix`` when it is a covariance — finite, symmetric and positive semi-definite (a gauge
    leaves some directions at 0), to rounding; else refused naming ``key``.

    Raises:
        CalibError: a corrupt checkpoint's state.
    """
    scale = float(np.max(np.abs(matrix), initial=0.0)) if np.all(np.isfinite(matrix)) else math.nan
    if not math.isfinite(scale):
        raise CalibError(f"estimator state: key '{key}': expected a finite covariance")
    if not np.allclose(matrix, matrix.T, rtol=1e-9, atol=1e-12 * scale):
        raise CalibError(f"estimator state: key '{key}': expected a symmetric covariance")
    if len(matrix) and float(np.linalg.eigvalsh(0.5 * (matrix + matrix.T))[0]) < -1e-9 * scale:
        raise CalibError(f"estimator state: key '{key}': expected a positive semi-definite covariance")
    return matrix


def checked_time(t_s: float, key: str) -> float:
    """``t_s`` [s] when NaN (no sample yet) or a plausible time (within ±:data:`~stewart_calib.inputs.MAX_TIME_S`)."""
    if not (math.isnan(t_s) or abs(t_s) <= MAX_TIME_S):
        raise CalibError(f"estimator state: key '{key}': {number(t_s)} s is no time of a log (expected within ±1e12 s)")
    return t_s


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
