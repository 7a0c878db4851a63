"""``stewart-calib calibrate``: a measurement log → a calibration result (spec §6).

    stewart-calib calibrate --platform P.toml --log L.csv --method METHOD --out R.json
                            [--trace T.csv] [--rerun R.rrd] [--platform-out C.toml] [--report DIR]
                            [--skip-bad-rows]
                            [--config C.toml] [--set section.key=value ...]

Batch methods (those with ``fit``) see the whole log at once; online methods get
``update(sample)`` sample by sample, and the result holds their estimate at the last sample.
With an online method on the tracker and neither ``--rerun`` nor ``--report`` (which show every
sample), the log is streamed: read a block at a time, the trace written as it grows, so memory
does not grow with the log. Nothing is written unless the whole run succeeds.

``--platform-out`` writes the calibrated platform (spec §8: the drive replaced by the estimate),
which every command takes as a nominal platform; ``--report DIR`` a static HTML page
``DIR/index.html`` (residuals per channel before and after, δM ± σ, correlations, conditioning,
config, versions).
"""

from __future__ import annotations

import argparse
import math
import queue
import sys
import tempfile
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from .. import __version__, estimators, io
from .. import kinematics as kin
from ..accuracy import estimate_summary
from ..config import EstimatorConfig, load_estimator_config
from ..diagnosis import diagnose_log
from ..drive import drive_model
from ..errors import CalibError, SampleRejected, shown
from ..estimate import Estimate
from ..estimators import BatchEstimator, KalmanFiltered
from ..estimators.base import (
    accounted_estimate,
    accounting_words,
    late_index,
    skipped_count,
    take_late_rejections,
    update_block,
)
from ..identifiability import conditioning_summary, identifiability_report, measured_poses, warning_line
from ..io import logs
from ..online import Rejections
from ..planning import noise_floor
from ..platform import N_LEGS, Platform, load_platform
from ..plausibility import check_plausible
from ..progress import MIN_LOG_ROWS, log_progress_bar, progress_bar
from ..samples import Log
from . import add_config_arguments, handover, run_command
from .validate import measurement_residuals, nominal_model, tracker_residuals

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
        trace: ``(N, 42)`` estimated absolute parameters [mm] after each sample, or None.
        rejected: ``(sample index, SampleRejected)`` of samples the estimator refused.
        stddev: ``(N, 42)`` σ of the parameters after each sample [mm] (NaN: no covariance), or None.
        nis: ``(N,)`` normalised innovation squared of each sample (Kalman methods; NaN where
            refused), or None.
        noise_scale: the estimator's measurement noise estimated from the data, as a multiple
            of the configured σ (None when it does not estimate it).
    """

    estimate: Estimate
    trace: np.ndarray | None
    rejected: list[tuple[int, SampleRejected]]
    stddev: np.ndarray | None = None
    nis: np.ndarray | None = None
    noise_scale: float | None = None


def run_calibration(
    platform: Platform,
    log: Log,
    method: str,
    config: EstimatorConfig | None = None,
    trace: bool = False,
    progress: bool = False,
    diagnostics: bool = False,
) -> Calibration:
    """Run ``method`` over ``log``; see :class:`Calibration`. ``diagnostics`` (implies ``trace``)
    also keeps σ and the NIS per sample — the covariance costs isam2 ~0.3 ms a sample.

    Raises:
        CalibError: an unknown method, or a method that rejected every sample.
    """
    if (
        platform.instrument.kind != "tracker"
    ):  # an outside instrument's frame may be anywhere: start from its registration
        from ..instruments.external import registered_platform

        platform = registered_platform(platform, log.strokes, log.readings)
    estimator = estimators.make_estimator(method, platform, config)
    nominal = platform.drive.as_vector()
    if isinstance(estimator, BatchEstimator):
        estimate = estimator.fit(list(log))
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
    return Calibration(
        accounted_estimate(estimator), rows, rejected, sigma, nis, getattr(estimator, "noise_scale", lambda: None)()
    )


def _stddev_or_nan(estimate: Estimate) -> np.ndarray:
    return np.full(len(estimate.error), np.nan) if estimate.stddev is None else estimate.stddev


def _refuse_if_all_rejected(method: str, rejected: list[tuple[int, SampleRejected]], n_samples: int) -> None:
    if rejected and len(rejected) == n_samples:
        raise CalibError(f"{method} rejected all {n_samples} samples (first: {rejected[0][1]})")


def calibrate(
    platform: Platform, log: Log, method: str, config: EstimatorConfig | None = None, trace: bool = False
) -> tuple[Estimate, np.ndarray | None, int]:
    """``(estimate, trace (N, 42) [mm] or None, samples rejected)`` of ``method`` on ``log``."""
    run = run_calibration(platform, log, method, config, trace)
    return run.estimate, run.trace, len(run.rejected)


def _check_writable_dir(path: Path | None, option: str) -> None:
    """Fail before a long run, not after it, when an output cannot be placed."""
    if path is not None:
        io.check_writable_directory(path.parent, f"{option} {shown(path)}")


def _summary(what: str, count: int, total: int, first: str) -> str:
    return f"stewart-calib calibrate: {what} {count} of {total} (first: {first})"


def _write_rerun(path: Path, platform: Platform, method: str, log: Log, run: Calibration, batch: bool) -> None:
    """A rerun ``.rrd``: the platform geometry, the parameter errors δM over time with their ±σ
    bands [mm], and the method's diagnostics: drive-leg residuals after each sample and, for an
    online method, before it (the innovation), and the NIS of a Kalman method."""
    from ..viz import recording as viz  # rerun is slow to import; only --rerun needs it

    nominal, trace = platform.drive.as_vector(), run.trace
    if trace is None:
        raise ValueError("--rerun draws the trace: run_calibration(..., diagnostics=True) keeps it")
    residual = innovation = None
    if platform.instrument.kind == "tracker":  # the drive-leg residuals need the tracker's pose of each sample
        poses = kin.forward_kinematics(platform.required_tracker("--rerun"), log.readings, strict=False)
        residual = kin.leg_residuals_per_sample(trace, poses.R, poses.t, log.strokes)
        if not batch:
            before = np.vstack([nominal, trace[:-1]])  # the model in force when each sample arrived
            innovation = kin.leg_residuals_per_sample(before, poses.R, poses.t, log.strokes)
    series = {"residual": residual, "innovation": innovation, "nis": run.nis}
    kinds = {kind for kind, values in series.items() if values is not None}
    with io.atomic_path(path) as tmp, viz.open_recording(tmp) as rec:
        viz.log_platform_geometry(rec, platform)
        viz.log_parameters(rec, method, trace - nominal, log.t_s)
        viz.log_parameter_band(rec, method, trace - nominal, run.stddev, log.t_s)
        viz.log_diagnostics(rec, method, log.t_s, residual, innovation, run.nis)
        if platform.elastic is not None:  # the legs' forces at the calibrated model's poses, and c ± σ
            drive = drive_model(platform).calibrated_by(run.estimate)
            _, inputs = drive.settled_kinematics(log.strokes, log.load_kg, strict=False)
            block = run.estimate.block_results().get("compliance", {})
            sigma = None if block.get("stddev") is None else np.asarray(block["stddev"])
            c = drive.term_values()[-1]  # the compliance term comes last: identified, or [elastic]'s held value
            viz.log_elastic(rec, method, inputs[:, drive.input_width - 6 :], c, sigma, log.t_s)
        viz.send_blueprint(rec, [method], [], {method: kinds})


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
        return self._log if self._log is not None else Log(np.zeros(0), np.zeros((0, 6)), np.zeros((0, 6)))


@dataclass
class _Tally:
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
    """

    estimate: Estimate
    samples: int
    skipped: _Tally
    rejected: list[int]
    rejections: Rejections
    first_rejected_t_s: float | None
    checked: EvenlySpacedSamples
    noise_scale: float | None = None


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
        on_block: called after each block with it and the ``(n, 42)`` estimated parameter
            errors δM [mm] after each of its samples (a rejected sample leaves the estimate in
            force); None: not kept.
        bar: ticked per block (:func:`~stewart_calib.progress.progress_bar`), or None.
    """
    k = 0
    recent_t_s: deque[float] = deque(maxlen=LATE_LOOKBACK)
    for block in blocks:
        rows = np.empty((len(block), 42)) if on_block is not None else None
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
    """The good samples of a streamed log (``t_s``, strokes, readings and per-sample extra columns
    as float64 rows) in an unnamed temporary file, read back a block at a time: the second pass
    over the log (the exact residual RMS at the final estimate) without parsing the CSV again
    and without holding the log in memory. The file is deleted when closed (or the process ends).

    Its size: 8 bytes × (1 + 6 + the readings + 6) a good sample — 152 bytes for the tracker,
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
        self._widths = (0, 0)

    def _refusal(self, err: OSError) -> CalibError:
        return CalibError(
            f"--out: cannot hold the temporary copy of the log's samples (152 bytes a row) in "
            f"{shown(self._directory)} ({err.strerror or err.__class__.__name__})"
        )

    def add(self, block: Log, extra: np.ndarray) -> None:
        """The samples of ``block`` with ``extra``, ``(len(block), k)`` values of each."""
        rows = np.column_stack([block.t_s, block.strokes, block.readings, extra])
        self._widths = (block.readings.shape[1], extra.shape[1])
        try:
            self._file.write(np.ascontiguousarray(rows, dtype=np.float64).tobytes())
        except OSError as err:
            raise self._refusal(err) from None

    def blocks(self) -> Iterable[tuple[Log, np.ndarray]]:
        """The samples added, in order, as ``(Log, extra)`` blocks of at most the log reader's
        block size in bytes (:data:`stewart_calib.io.logs.BLOCK_BYTES`)."""
        self._file.seek(0)
        readings, extra = self._widths
        width = 1 + N_LEGS + readings + extra
        row_bytes = 8 * width
        while readings and (data := self._file.read(max(logs.BLOCK_BYTES // row_bytes, 1) * row_bytes)):
            rows = np.frombuffer(data).reshape(-1, width)
            yield (
                Log(rows[:, 0], rows[:, 1 : 1 + N_LEGS], rows[:, 1 + N_LEGS : width - extra]),
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
    spool: SampleSpool | None = None,
) -> StreamedRun:
    """An online ``method`` over the log at ``path``, read a block at a time (memory independent
    of its length); the trace rows (spec §6) are written to the open ``trace_file`` as they come,
    the good samples to ``spool`` (for a second pass).

    Raises:
        CalibError: a bad log (as :func:`stewart_calib.io.read_log`), a method that rejected every sample.
    """
    estimator = estimators.make_estimator(method, platform, config)
    nominal = platform.drive.as_vector()
    checked, skipped, rejections = EvenlySpacedSamples(CHECKED_SAMPLES), _Tally(), Rejections()
    rejected: list[int] = []
    first_t_s: list[float] = []

    def read(block: Log) -> Log:
        if not checked.seen:  # the first block (the whole of a short log) stands for the log
            diagnose_log(platform, block.strokes, block.readings, path)
        checked.add(block)
        skipped.add(block.skipped)
        if spool is not None:
            spool.add(block, nominal_residuals(platform, block))
        return block

    def refused(k: int, t_s: float, err: SampleRejected) -> None:
        rejected.append(k)
        rejections.add(err)
        first_t_s[:] = first_t_s or [t_s]

    written: list[int] = []

    def write_trace(block: Log, errors_mm: np.ndarray) -> None:
        trace_file.write(io.trace_text(block.t_s, nominal + errors_mm, header=not written))
        written.append(len(block))

    blocks = read_ahead(read(block) for block in io.read_log_blocks(path, platform, skip_bad_rows=skip_bad_rows))
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
    )


def nominal_poses(platform: Platform, log: Log) -> np.ndarray:
    """``(n, 6)`` the nominal drive's FK poses of a log's strokes (those that converge): where an
    outside instrument's log put the robot, for a platform without ``[workspace]``."""
    drive = drive_model(platform)
    fk, _ = drive.settled_kinematics(log.strokes, log.load_kg, strict=False)
    return fk.pose6[fk.converged]


def nominal_residuals(platform: Platform, block: Log) -> np.ndarray:
    """``(len(block), 6)`` the tracker's readings minus what the nominal model predicts [mm], NaN
    where its FK fails: the residual RMS "before", which needs no estimate, so is spooled with the
    samples on the first pass (on the read-ahead thread) and only the calibrated model's is left
    for the second."""
    before = tracker_residuals(platform, block, [(nominal_model(platform), "the nominal platform")])
    return np.full((len(block), N_LEGS), np.nan) if before is None else before[0]


def streamed_residual_rms(
    platform: Platform, spooled: Iterable[tuple[Log, np.ndarray]], result: dict, rejected: list[int]
) -> dict:
    """:func:`~.handover.residual_rms_field` of a streamed tracker log without its ``rejected``
    samples, from the ``(block, before)`` pairs of its :class:`SampleSpool` (``before``: the
    :func:`nominal_residuals` of each sample): the calibrated
    model's residuals are computed here, and the per-channel sums of squares add up over the blocks.
    """
    sums, counts, k = {"before": 0.0, "after": 0.0}, {"before": 0, "after": 0}, 0
    left_out = np.asarray(rejected, dtype=np.int64)
    for block, before in spooled:
        used = ~np.isin(k + np.arange(len(block)), left_out)
        k += len(block)
        if not used.any():
            continue
        block, before = block.select(used), before[used]
        after = tracker_residuals(platform, block, [(result, "the result")])
        if after is None or np.isnan(before).any():  # an FK failed: validate's path words it
            residuals = measurement_residuals(platform, block, result)
            before, after = residuals.before, residuals.after[None]
        for when, values in (("before", before), ("after", after[0])):
            finite = np.isfinite(values)
            sums[when] = sums[when] + np.sum(np.where(finite, values, 0.0) ** 2, axis=0)
            counts[when] = counts[when] + finite.sum(axis=0)
    field: dict[str, list] = {"channels": list(io.reading_columns(platform))}
    for when in ("before", "after"):
        with np.errstate(invalid="ignore", divide="ignore"):
            rms = np.sqrt(sums[when] / counts[when])
        field[when] = [float(v) if math.isfinite(v) else None for v in rms]
    return field


def run(args: argparse.Namespace) -> int:
    if args.method not in estimators.METHODS:
        raise CalibError(f"--method: unknown method '{args.method}'; expected one of {', '.join(estimators.METHODS)}")
    out, trace_path, rerun_path = Path(args.out), args.trace and Path(args.trace), args.rerun and Path(args.rerun)
    platform_out, report_dir = args.platform_out and Path(args.platform_out), args.report and Path(args.report)
    for path, option in (
        (out, "--out"),
        (trace_path, "--trace"),
        (rerun_path, "--rerun"),
        (platform_out, "--platform-out"),
    ):
        _check_writable_dir(path, option)
    handover.check_report_dir(report_dir)
    platform = load_platform(args.platform)
    config = load_estimator_config(args.config, args.set)
    tracker = platform.instrument.kind == "tracker"
    streamed = tracker and estimators.method_spec(args.method).online and not (rerun_path or report_dir)

    # Everything is rendered (so validated) before anything is written; a streamed trace goes to
    # a temporary that becomes the file only when the stack closes without error.
    with ExitStack() as stack:
        skipped = _Tally()
        residuals = None
        if streamed:
            trace_file = None
            if trace_path:
                trace_file = stack.enter_context(
                    open(stack.enter_context(io.atomic_path(trace_path)), "w", encoding="utf-8", newline="")
                )
            spool = SampleSpool(out.parent)
            stack.callback(spool.close)
            streaming = stream_calibration(
                platform, args.log, args.method, config, args.skip_bad_rows, trace_file, spool
            )
            estimate, n_samples, skipped = streaming.estimate, streaming.samples, streaming.skipped
            rejections, first_rejected_t_s = streaming.rejections, streaming.first_rejected_t_s
            noise_scale = streaming.noise_scale
            checked = streaming.checked.log
        else:
            log = io.read_log(args.log, platform, skip_bad_rows=args.skip_bad_rows)
            skipped.add(log.skipped)
            diagnose_log(platform, log.strokes, log.readings, args.log)
            # isam2 costs milliseconds a sample (a pose instrument's whole session in the smoother: ~15 ms),
            # so a few hundred samples take seconds: its bar shows whatever the log's length
            progress = sys.stderr.isatty() and (len(log) >= MIN_LOG_ROWS or args.method == "isam2")
            result = run_calibration(platform, log, args.method, config, bool(trace_path), progress, bool(rerun_path))
            estimate, n_samples, noise_scale = result.estimate, len(log), result.noise_scale
            rejections = Rejections.of(err for _, err in result.rejected)
            first_rejected_t_s = float(log.t_s[result.rejected[0][0]]) if result.rejected else None
            sample = EvenlySpacedSamples(CHECKED_SAMPLES)
            sample.add(log)
            checked = sample.log
        if skipped.count:
            line, reason = skipped.first
            print(
                _summary("skipped bad log rows:", skipped.count, n_samples + skipped.count, f"row {line}: {reason}"),
                file=sys.stderr,
            )
        # the leg residual it checks is the tracker's; an outside instrument's fit reports its own residuals
        check_plausible(
            platform,
            estimate.error,
            config.noise,
            checked.strokes if tracker else np.zeros((0, 6)),
            checked.readings if tracker else np.zeros((0, 6)),
            args.method,
            noise_scale,
        )
        if rejections.count:
            print(
                _summary(
                    f"{args.method} rejected samples:",
                    rejections.count,
                    n_samples,
                    f"t_s={first_rejected_t_s!r}: {rejections.first}",
                ),
                file=sys.stderr,
            )

        extra: dict[str, object] = {"samples_rejected": rejections.summary()}
        warning = None
        if tracker:  # the tracker's FK gives the poses to assess
            poses = measured_poses(platform, checked)
            report = identifiability_report(platform, poses, config.noise, paper_form=False)
            warning = warning_line(report)
            extra["conditioning"] = conditioning_summary(report)
        else:
            poses = nominal_poses(platform, checked)
        # the tracker's methods carry a random walk and the paper's forms: their covariances are not the
        # static Cramér–Rao bound the noise floor is, so only an outside instrument's is compared with it
        floor = None if tracker else noise_floor(platform, estimate.samples_used, config.noise)
        predicted, line, warns = estimate_summary(platform, estimate, floor, poses)
        extra["predicted_closed_loop"] = predicted
        if warning and warns:  # one warning line: the poses' conditioning, then what it leaves
            print(f"stewart-calib calibrate: {warning}; {line.removeprefix('warning: ')}", file=sys.stderr)
        else:
            for text in (warning, line):
                if text:
                    print(f"stewart-calib calibrate: {text}", file=sys.stderr)

        samples_skipped = skipped_count(skipped.count, rejections.count, estimate)
        created = handover.created_now()
        extra.update(
            {
                "covariance": handover.covariance_field(estimate),
                "config": handover.config_field(config),
                "version": __version__,
                "created": created,
            }
        )
        result_data = io.result_dict(estimate, platform, samples_skipped, extra)
        if streamed:
            result_data["residual_rms"] = streamed_residual_rms(
                platform, spool.blocks(), result_data, streaming.rejected
            )
        else:
            used = np.ones(len(log), dtype=bool)
            used[[k for k, _ in result.rejected]] = False  # e.g. readings the tracker's FK cannot solve
            residuals = measurement_residuals(platform, log.select(used), result_data)
            result_data["residual_rms"] = handover.residual_rms_field(residuals)
        result_json = io.result_text(result_data, str(out))
        trace_csv = (
            io.trace_text(log.t_s, result.trace) if trace_path and not streamed and result.trace is not None else None
        )
        platform_toml = (
            handover.calibrated_platform_text(platform, estimate, args.method, Path(args.log).name, created)
            if platform_out
            else None
        )
        page = None
        if report_dir:
            from ..viz.html_report import report_html

            inputs = {"platform file": str(args.platform), "log": str(args.log)}
            page = report_html(
                f"Calibration of {platform.name} with {args.method}", result_data, residuals, None, inputs
            )
        if rerun_path:
            _write_rerun(rerun_path, platform, args.method, log, result, not estimators.method_spec(args.method).online)
    if trace_csv is not None:
        io.atomic_write_text(trace_path, trace_csv)
    if platform_toml is not None:
        io.atomic_write_text(platform_out, platform_toml)
    if page is not None:
        handover.write_report(report_dir, page)
    io.atomic_write_text(out, result_json)
    print(
        f"stewart-calib calibrate: wrote {out} ({args.method}: {estimate.samples_used} samples used, "
        f"{samples_skipped} skipped{accounting_words(estimate.details or {})}, of {n_samples + skipped.count} rows)",
        file=sys.stderr,
    )
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        description="Read a platform file and a measurement log, run one estimator, write a result JSON (spec §5).",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="platform file (spec §2)")
    parser.add_argument("--log", required=True, metavar="L.csv", help="measurement log (spec §3)")
    # Checked in run() rather than by argparse choices, so the message is ours and names the methods.
    parser.add_argument("--method", required=True, metavar="METHOD", help=f"one of {', '.join(estimators.METHODS)}")
    parser.add_argument("--out", required=True, metavar="R.json", help="result file (spec §5)")
    parser.add_argument("--trace", metavar="T.csv", help="also write t_s + the 42 estimated parameters per sample")
    parser.add_argument(
        "--rerun", metavar="R.rrd", help="also write a rerun recording of the parameter errors over time"
    )
    parser.add_argument(
        "--platform-out",
        metavar="C.toml",
        help="also write the calibrated platform (a nominal platform for every command)",
    )
    parser.add_argument("--report", metavar="DIR", help="also write a static HTML report DIR/index.html")
    parser.add_argument(
        "--skip-bad-rows", action="store_true", help="skip bad log rows (reported) instead of refusing the log"
    )
    add_config_arguments(parser)
    parser.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    return run_command("calibrate", argv)
