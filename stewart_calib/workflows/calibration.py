"""Calibration as a library: one estimator over a log in memory (:func:`run_calibration`) or
streamed from its file a block at a time (:func:`stream_calibration`), and the machinery of the
stream — a read-ahead thread that parses the next block while the estimator works on this one
(:func:`read_ahead`), a spool of the good samples for a second pass (:class:`SampleSpool`), an
evenly spread sample of the log for the conditioning checks (:class:`EvenlySpacedSamples`).

``stewart-calib calibrate`` (:mod:`stewart_calib.pipelines.calibrate`), scripts and the benchmarks
use these; the pipelines stay thin commands that import nothing private from each other.
"""

from __future__ import annotations

import itertools
import queue
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from .. import estimators, instruments, io
from ..config import EstimatorConfig
from ..errors import CalibError, SampleRejected, shown
from ..estimate import Estimate
from ..estimators import BatchEstimator, KalmanFiltered, Relinearising
from ..estimators.base import accounted_estimate, late_index, take_late_rejections, update_block
from ..io import logs
from ..model.platform import Platform
from ..progress import log_progress_bar, progress_bar
from ..samples import CHANNEL_SHAPES, HeldPoseSamples, Log
from . import diagnosis
from .diagnosis import diagnose_log
from .online import Rejections

#: the result's conditioning section (and a streamed run's plausibility check) look at between
#: this many and twice this many samples, evenly spaced over the log (:class:`EvenlySpacedSamples`).
CHECKED_SAMPLES = 1000
#: sample times a streamed run remembers to place a late rejection (a robust start-up batch
#: decides on its first samples, after an outside instrument's registration held some).
LATE_LOOKBACK = 4096


@dataclass(frozen=True)
class Calibration:
    """One estimator run over a log.

    Attributes:
        estimate: at the last sample (online) or the fit to the whole log (batch).
        trace: ``(N, n_params)`` estimated absolute parameters [mm] after each sample, or None.
        rejected: ``(sample index, SampleRejected)`` of samples the estimator refused.
        stddev: ``(N, n_params)`` σ of the parameters after each sample [mm] (NaN: no covariance), or None.
        nis: ``(N,)`` normalised innovation squared of each sample (Kalman methods; NaN where
            refused), or None.
        noise_scale: the estimator's measurement noise estimated from the data, as a multiple
            of the configured σ (None when it does not estimate it).
        relinearised: with ``relinearise``, an online method's estimate with the covariance its recursion
            gives the samples it used, every one observed at that estimate
            (:class:`~stewart_calib.estimators.Relinearising`); None otherwise.
    """

    estimate: Estimate
    trace: np.ndarray | None
    rejected: list[tuple[int, SampleRejected]]
    stddev: np.ndarray | None = None
    nis: np.ndarray | None = None
    noise_scale: float | None = None
    relinearised: Estimate | None = None


def run_calibration(
    platform: Platform,
    log: Log,
    method: str,
    config: EstimatorConfig | None = None,
    trace: bool = False,
    progress: bool = False,
    diagnostics: bool = False,
    relinearise: bool = False,
) -> Calibration:
    """Run ``method`` over ``log``; see :class:`Calibration`. ``diagnostics`` (implies ``trace``)
    also keeps σ and the NIS per sample — the covariance costs isam2 ~0.3 ms a sample. ``relinearise``:
    an online method's covariance is also taken again at its estimate (one more pass over the samples it used).

    Raises:
        CalibError: an unknown method, or a method that rejected every sample.
    """
    # an outside instrument's frame may be anywhere: start from its registration
    platform = instruments.registered(platform, log.strokes, log.readings)
    estimator = estimators.make_estimator(method, platform, config)
    nominal = platform.drive.as_vector()
    if isinstance(estimator, BatchEstimator):
        estimate = estimator.fit(iter(log))  # a sample at a time: ls holds its compact rows, not 10⁶ Samples
        rejected = list(estimator.rejected)
        # a batch fit holds for the whole log: one constant row per sample time
        rows = np.tile(nominal + estimate.error, (len(log), 1)) if trace or diagnostics else None
        _refuse_if_all_rejected(method, rejected, len(log))
        sigma = np.tile(_stddev_or_nan(estimate), (len(log), 1)) if diagnostics else None
        return Calibration(estimate, rows, rejected, sigma)
    rows = np.empty((len(log), len(nominal))) if trace or diagnostics else None
    sigma = np.empty_like(rows) if diagnostics else None
    kalman = estimator if diagnostics and isinstance(estimator, KalmanFiltered) else None
    nis = np.full(len(log), np.nan) if kalman is not None else None
    rejected = []
    bar = progress_bar(log, desc=f"calibrate {method}", show=progress)
    for k, sample in enumerate(bar):
        try:
            estimator.update(sample)
            if nis is not None and kalman is not None:
                nis[k] = kalman.filter.nis
        except SampleRejected as err:
            rejected.append((k, err))
        for late in take_late_rejections(estimator):  # a robust start-up batch left it out
            rejected.append((late_index(log.t_s[: k + 1].tolist(), late.t_s), late))
        if sigma is not None and rows is not None:  # rows: kept whenever sigma is
            now = estimator.estimate()
            rows[k], sigma[k] = nominal + now.error, _stddev_or_nan(now)
        elif rows is not None:
            rows[k] = nominal + estimator.current_error()  # a rejected sample leaves the estimate in force
    _refuse_if_all_rejected(method, rejected, len(log))
    relinearised = None
    if relinearise and isinstance(estimator, Relinearising):
        used = np.ones(len(log), dtype=bool)
        used[[k for k, _ in rejected]] = False
        relinearised = estimator.relinearised(iter(log.select(used)))
    return Calibration(
        accounted_estimate(estimator),
        rows,
        rejected,
        sigma,
        nis,
        getattr(estimator, "noise_scale", lambda: None)(),
        relinearised,
    )


def _stddev_or_nan(estimate: Estimate) -> np.ndarray:
    return np.full(len(estimate.error), np.nan) if estimate.stddev is None else estimate.stddev


def _refuse_if_all_rejected(method: str, rejected: list[tuple[int, SampleRejected]], n_samples: int) -> None:
    if rejected and len(rejected) == n_samples:
        raise CalibError(f"{method} rejected all {n_samples} samples (first: {rejected[0][1]})")


class EvenlySpacedSamples:
    """Every ``stride``-th sample of a stream, the stride doubling whenever more than
    ``2 · capacity`` are kept: between ``capacity`` and ``2 · capacity`` samples evenly spread
    over the whole stream (all of a short one), without knowing its length in advance.

    Conditioning (rank, condition number, weakest directions) depends on which poses were
    visited, not on how long each was held, so these stand for the whole log.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.stride = 1
        self.seen = 0
        self._index = np.zeros(0, dtype=np.int64)
        self._log: Log | None = None

    def add(self, block: Log) -> None:
        index = self.seen + np.arange(len(block))
        pick = index % self.stride == 0
        kept = block.select(pick)
        self._index = np.concatenate([self._index, index[pick]])
        self._log = kept if self._log is None else Log.concatenate([self._log, kept])
        self.seen += len(block)
        while len(self._index) > 2 * self.capacity:
            self.stride *= 2
            pick = self._index % self.stride == 0
            self._index, self._log = self._index[pick], self._log.select(pick)

    @property
    def log(self) -> Log:
        """The samples kept, in order."""
        if self._log is None:  # no block seen: no columns known either
            return Log(np.zeros(0), np.zeros((0, 0)), np.zeros((0, 0)))
        return self._log


@dataclass
class Tally:
    """How many items were seen, and the first."""

    count: int = 0
    first: Any = None  # whatever is counted: a (row, reason) of a skipped row

    def add(self, items) -> None:
        if items and self.first is None:
            self.first = items[0]
        self.count += len(items)


@dataclass
class StreamedRun:
    """What a streamed calibration keeps: the estimate, counts, and a bounded sample of the log.

    Attributes:
        samples: good samples read. skipped: bad rows ``(row, reason)`` (count, first).
        rejected: indices (among the good samples) the estimator refused, with their reasons
            in ``rejections`` and the first one's time in ``first_rejected_t_s``.
        checked: :class:`EvenlySpacedSamples` of the log.
        noise_scale: as :attr:`Calibration.noise_scale`.
        config: the configuration the estimator ran with.
    """

    estimate: Estimate
    samples: int
    skipped: Tally
    rejected: list[int]
    rejections: Rejections
    first_rejected_t_s: float | None
    checked: EvenlySpacedSamples
    noise_scale: float | None = None
    config: EstimatorConfig | None = None


def feed_online(
    estimator,
    blocks: Iterable[Log],
    on_rejected: Callable[[int, float, SampleRejected], None],
    on_block: Callable[[Log, np.ndarray], None] | None = None,
    bar=None,
) -> int:
    """Update an online ``estimator`` with every sample of ``blocks``; returns how many there were.

    Args:
        on_rejected: called with ``(sample index, t_s, error)`` for each sample refused, also
            those refused late (a robust start-up batch: among the last :data:`LATE_LOOKBACK`).
        on_block: called after each block with it and the ``(n, n_params)`` estimated parameter
            errors δM [mm] after each of its samples (a rejected sample leaves the estimate in
            force); None: not kept.
        bar: ticked per block (:func:`~stewart_calib.progress.progress_bar`), or None.
    """
    k = 0
    recent_t_s: deque[float] = deque(maxlen=LATE_LOOKBACK)
    n_params = len(estimator.current_error()) if on_block is not None else 0  # δM's size, the estimator's own
    for block in blocks:
        rows = np.empty((len(block), n_params)) if on_block is not None else None
        refused, late = update_block(estimator, block, rows)
        for j, err in refused:
            on_rejected(k + j, float(block.t_s[j]), err)
        for j, err in late:  # one older than the lookback is counted at the sample it came after
            times = (list(recent_t_s) + block.t_s[: j + 1].tolist())[-LATE_LOOKBACK:]
            back = late_index(times, err.t_s) if err.t_s in times else len(times) - 1
            on_rejected(k + j + 1 - len(times) + back, err.t_s, err)
        recent_t_s.extend(block.t_s[-LATE_LOOKBACK:].tolist())
        k += len(block)
        if bar is not None:
            bar.update(len(block))
        if on_block is not None and rows is not None:  # rows: kept for on_block
            on_block(block, rows)
    return k


class SampleSpool:
    """The good samples of a streamed log (``t_s``, strokes, readings, the input channels the log has
    (``Log.inputs``), and per-sample extra columns as float64 rows) in an unnamed temporary file, read back
    a block at a time: the second pass over the log (the exact residual RMS at the final estimate)
    without parsing the CSV again and without holding the log in memory. The file is deleted when
    closed (or the process ends). The channels are kept because the model's residuals depend on them
    (an elastic drive's on the payload, a thermal one's on the temperatures): without them the
    second pass would take every row as unloaded at the reference temperature.

    Its size: 8 bytes × (1 + the strokes + the readings + the channels + the extra) a good sample —
    152 bytes for the tracker (six strokes, six readings, six residuals; 160 with ``load_kg``),
    ~150 MB for a log of 10⁶ rows; the README says so under ``calibrate``.

    Args:
        directory: where the file goes (the output's: a disk the user chose, not a RAM ``/tmp``).
    Raises:
        CalibError: the file cannot be made or written (a full disk): one line naming the directory.
    """

    def __init__(self, directory: Path):
        self._directory = directory
        try:
            self._file = tempfile.TemporaryFile(dir=directory)
        except OSError as err:
            raise self._refusal(err) from None
        self._widths = (0, 0, 0, 0)
        self._channels: tuple[str, ...] = ()

    def _refusal(self, err: OSError) -> CalibError:
        return CalibError(
            f"--out: cannot hold the temporary copy of the log's samples (152 bytes a row) in "
            f"{shown(self._directory)} ({err.strerror or err.__class__.__name__})"
        )

    def add(self, block: Log, extra: np.ndarray) -> None:
        """The samples of ``block`` with ``extra``, ``(len(block), k)`` values of each."""
        self._channels = tuple(name for name in CHANNEL_SHAPES if name in block.inputs)
        channels = [np.asarray(block.inputs[name], dtype=float).reshape(len(block), -1) for name in self._channels]
        rows = np.column_stack([block.t_s, block.strokes, block.readings, *channels, extra])
        width = sum(column.shape[1] for column in channels)
        self._widths = (block.strokes.shape[1], block.readings.shape[1], width, extra.shape[1])
        try:
            self._file.write(np.ascontiguousarray(rows, dtype=np.float64).tobytes())
        except OSError as err:
            raise self._refusal(err) from None

    def blocks(self) -> Iterable[tuple[Log, np.ndarray]]:
        """The samples added, in order, as ``(Log, extra)`` blocks of at most the log reader's
        block size in bytes (:data:`stewart_calib.io.logs.BLOCK_BYTES`)."""
        self._file.seek(0)
        legs, readings, packed, extra = self._widths
        width = 1 + legs + readings + packed + extra
        row_bytes = 8 * width
        while readings and (data := self._file.read(max(logs.BLOCK_BYTES // row_bytes, 1) * row_bytes)):
            rows = np.frombuffer(data).reshape(-1, width)
            end = 1 + legs + readings
            channels = {}
            for name in self._channels:
                shape = CHANNEL_SHAPES[name]
                size = int(np.prod(shape, dtype=int))
                channels[name] = rows[:, end : end + size].reshape(len(rows), *shape)
                end += size
            yield (
                Log(rows[:, 0], rows[:, 1 : 1 + legs], rows[:, 1 + legs : 1 + legs + readings], inputs=channels),
                rows[:, width - extra :],
            )

    def close(self) -> None:
        self._file.close()


T = TypeVar("T")


def read_ahead(items: Iterable[T]) -> Iterator[T]:
    """The items of ``items``, each made in a background thread while the caller works on the one
    before: a long log's parsing, checks and spooling overlap the estimator on a second core
    (pyarrow and the compiled kernels let go of the GIL). An exception of ``items`` is raised
    where its item would have come; leaving the loop early stops the thread after the item it is making."""
    handed: queue.Queue = queue.Queue(maxsize=1)
    stop, end = threading.Event(), object()

    def hand(entry) -> bool:
        while not stop.is_set():
            try:
                handed.put(entry, timeout=0.05)
                return True
            except queue.Full:
                pass
        return False

    def make() -> None:
        try:
            for item in items:
                if not hand((item, None)):
                    return
            hand((end, None))
        except BaseException as err:
            hand((end, err))

    thread = threading.Thread(target=make, name="stewart-calib read-ahead", daemon=True)
    thread.start()
    try:
        while (entry := handed.get())[0] is not end:
            yield entry[0]
        if entry[1] is not None:
            raise entry[1]
    finally:
        stop.set()
        thread.join()


def stream_calibration(
    platform: Platform,
    path: str,
    method: str,
    config: EstimatorConfig,
    skip_bad_rows: bool,
    trace_file=None,
    on_read: Callable[[Log], None] | None = None,
    digest: Callable[[bytes], None] | None = None,
    configure: tuple[Callable[[Log], bool], Callable[[Log], EstimatorConfig]] | None = None,
) -> StreamedRun:
    """An online ``method`` over the log at ``path``, read a block at a time (memory independent
    of its length); the trace rows (spec §6) are written to the open ``trace_file`` as they come,
    and ``on_read`` gets each block of good samples as it is read, on the read-ahead thread (e.g.
    :meth:`SampleSpool.add` for a second pass); ``digest`` the log's bytes (:func:`stewart_calib.io.read_log`).
    ``configure = (complete, function)``: the estimator is built with ``function(head)``'s configuration
    instead, ``head`` the log's first blocks up to the one after which ``complete(block)`` (called with each
    block in turn) is true, or the whole log (held, so the log is still read once: a pipe or FIFO as well as a
    file).

    Raises:
        CalibError: a bad log (as :func:`stewart_calib.io.read_log`), a method that rejected every sample.
    """
    if configure is None:  # a configuration the method refuses is refused before the log is read
        estimator = estimators.make_estimator(method, platform, config)
    nominal, names = platform.drive.as_vector(), platform.drive.parameter_names
    checked, skipped, rejections = EvenlySpacedSamples(CHECKED_SAMPLES), Tally(), Rejections()
    rejected: list[int] = []
    first_t_s: list[float] = []

    # whether the log moves is judged on its first samples counting HELD_SAMPLES of a held pose: a robot
    # that rests for longer than a block before it moves is no log at rest
    moving = HeldPoseSamples(CHECKED_SAMPLES)
    picked: list[tuple[np.ndarray, np.ndarray]] = []  # the picked samples' (strokes, readings), block by block

    def check_moves() -> None:
        strokes, readings = (np.concatenate(arrays) for arrays in zip(*picked, strict=True))
        diagnosis.check_moves(platform, strokes, readings, path, moving.seen)

    def read(block: Log) -> Log:
        if not checked.seen:  # the first block (the whole of a short log) stands for the log's units and wiring
            diagnose_log(platform, block.strokes, block.readings, path, count=False)
        if not moving.complete:
            seen, before = moving.seen, len(moving.indices)
            moving.add(block.strokes)
            new = np.asarray(moving.indices[before:], dtype=int) - seen
            picked.append((block.strokes[new], block.readings[new]))
            if moving.complete:
                check_moves()
        checked.add(block)
        skipped.add(block.skipped)
        if on_read is not None:
            on_read(block)
        return block

    def refused(k: int, t_s: float, err: SampleRejected) -> None:
        rejected.append(k)
        rejections.add(err)
        first_t_s[:] = first_t_s or [t_s]

    written: list[int] = []

    def write_trace(block: Log, errors_mm: np.ndarray) -> None:
        params = io.parameters_to_file(nominal + errors_mm, platform.drive)  # a rotary drive's angles in degrees
        trace_file.write(io.trace_text(block.t_s, params, header=not written, names=names))
        written.append(len(block))

    def read_all() -> Iterator[Log]:
        for block in io.read_log_blocks(path, platform, skip_bad_rows, digest=digest):
            yield read(block)
        if not moving.complete and picked:  # a log of fewer samples than the pick: all of them
            check_moves()

    blocks: Iterable[Log] = read_ahead(read_all())
    if configure is not None:
        complete, configured = configure
        head = []
        for block in blocks:
            head.append(block)
            if complete(block):
                break
        config = configured(Log.concatenate(head))
        estimator = estimators.make_estimator(method, platform, config)
        blocks = itertools.chain(head, blocks)
    with log_progress_bar(path, f"calibrate {method}") as bar:
        n = feed_online(estimator, blocks, refused, write_trace if trace_file is not None else None, bar)
    if rejections.count == n:
        raise CalibError(f"{method} rejected all {n} samples (first: {rejections.first})")
    return StreamedRun(
        accounted_estimate(estimator),
        n,
        skipped,
        rejected,
        rejections,
        first_t_s[0] if first_t_s else None,
        checked,
        getattr(estimator, "noise_scale", lambda: None)(),
        config,
    )
