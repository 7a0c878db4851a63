"""``stewart-calib track``: calibrate online from a log as it is written.

    stewart-calib track --platform P.toml --method {paper-ekf,ekf,isam2} [--log FILE | -]
                        [--follow] [--idle-timeout S] [--checkpoint C.npz] [--every N]
                        --out R.json [--config C.toml] [--set section.key=value ...]
                        [--skip-bad-rows]

Reads the header, then the CSV rows as they arrive (``--log -`` or no ``--log``: standard input),
updates the estimator with each row, and every ``--every`` rows and at the end replaces ``--out``
(spec §5 result, plus ``samples_rejected``) and ``--checkpoint`` atomically. The rows of each
read are parsed as one block when every one is a plain good row
(:meth:`~stewart_calib.io.LogRowParser.parse_block`), one by one otherwise, and the good rows go to
the estimator in blocks (:meth:`OnlineCalibrator.update_block`, split at the ``--every`` rows and at
bad rows): the same estimates, writes and messages as row by row.

When it stops:
  * at the end of the input (end of file; with ``--follow``, a file is polled for new rows
    until ``--idle-timeout`` seconds pass without one — without it, until a signal);
  * on Ctrl-C or SIGTERM: finishes the rows already read, writes the final estimate and
    checkpoint, exits 0;
  * at a bad row (spec §3) without ``--skip-bad-rows``: writes the checkpoint at the last good
    row (so no state is lost), then exits 2 with the reader's message naming the row and
    column. ``--out`` is NOT written on a refusal: what it holds is the last periodic result
    of the run (``"final": false``) or what was there before. With ``--skip-bad-rows`` the row
    is counted, reported, and tracking goes on — what a live tracker should use.

Every result ``track`` writes carries the added field ``"final"``: false for the periodic
writes while tracking, true for the one written when tracking ended normally (end of input,
idle timeout, signal).

A line is a row only once its line break has arrived (or the input has truly ended): the
unfinished tail of the last read, when a signal or the idle timeout stops tracking, is left
unread, so a resume reads it whole.

A sample the estimator refuses (gated outlier, FK not converging) never stops tracking: it
is counted by reason and reported on stderr and in the result.

Resume: when ``--checkpoint`` names an existing checkpoint, tracking continues from it (its
method, platform and config must match the command line's) and skips the first rows it had
already read — feed the same log from its start (the growing file itself, or its replay on
standard input).
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import os
import select
import signal
import stat
import sys
import time
from collections.abc import Callable, Iterator
from itertools import chain
from pathlib import Path

import numpy as np

from .. import io
from ..config import load_estimator_config
from ..errors import CalibError
from ..online import ONLINE_METHODS, OnlineCalibrator
from ..platform import load_platform, platform_to_toml
from ..samples import Log, Sample
from . import add_config_arguments, run_command
from .calibrate import _check_writable_dir

#: how often an idle input is polled [s]: latency of noticing new rows and signals.
POLL_S = 0.1
#: the most read at a time: a log read faster than it is written (a replay, a reader catching up)
#: is parsed and folded in a few thousand rows a block.
READ_BYTES = 1 << 20


def lines(fd: int, follow: bool, idle_timeout_s: float | None, stopped: Callable[[], bool]) -> Iterator[bytes]:
    """The lines of :func:`line_chunks` one at a time."""
    return chain.from_iterable(line_chunks(fd, follow, idle_timeout_s, stopped))


def line_chunks(
    fd: int, follow: bool, idle_timeout_s: float | None, stopped: Callable[[], bool]
) -> Iterator[list[bytes]]:
    """Complete lines of ``fd`` as they arrive (the line break removed), a list per read.

    Ends at the end of the input (a pipe closed by its writer; a regular file's end unless
    ``follow``), when ``stopped()``, or after ``idle_timeout_s`` without new data. A last line
    without a line break is yielded only at the end of the input: when stopped or timed out it
    may be a row still being written (or cut by the read size), so it is not yielded. Never
    blocks longer than :data:`POLL_S`, so a signal is noticed within that.
    """
    wait_at_end = follow and stat.S_ISREG(os.fstat(fd).st_mode)  # a pipe's end is final
    pending = b""
    last_data_s = time.monotonic()
    while not stopped():
        if idle_timeout_s is not None and time.monotonic() - last_data_s >= idle_timeout_s:
            return
        ready, _, _ = select.select([fd], [], [], POLL_S)
        if not ready:
            continue
        chunk = os.read(fd, READ_BYTES)
        if chunk:
            last_data_s = time.monotonic()
            *complete, pending = (pending + chunk).split(b"\n")
            if complete:
                yield complete
        elif wait_at_end:
            time.sleep(POLL_S)  # select() always reports a regular file ready
        else:
            if pending and not stopped():  # a stop may come between the last read and this end
                yield [pending]
            return


class _StopRequest:
    """Signal handler for SIGINT/SIGTERM: the loop finishes the rows already read, then the final write."""

    def __init__(self):
        self.requested = False

    def __call__(self, signum, frame) -> None:
        self.requested = True


def _decode(raw: bytes, source: str, row: int) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise CalibError(
            f"{source}: row {row}: not UTF-8 text (byte 0x{raw[err.start]:02x}); expected a UTF-8 CSV row"
        ) from None


def _open_input(log: str | None) -> tuple[int, str]:
    if log in (None, "-"):
        return sys.stdin.fileno(), "<stdin>"
    try:
        fd = os.open(log, os.O_RDONLY)
    except FileNotFoundError:
        raise CalibError(f"{log}: log file not found") from None
    except OSError as err:
        raise CalibError(f"{log}: cannot read log file ({err.strerror})") from None
    if stat.S_ISDIR(os.fstat(fd).st_mode):  # Linux opens a directory read-only; reading it fails later
        os.close(fd)
        raise CalibError(f"{log}: is a directory; expected a log file (spec §3)")
    return fd, log


def _remove_debris(path: Path) -> None:
    """Delete the temporaries of ``path`` that a killed writer left (``io.atomic_path`` names
    them ``.<name>.<random>.tmp`` beside it); only a run that owns ``path`` may call this."""
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        tmp.unlink(missing_ok=True)


def _start(args: argparse.Namespace) -> OnlineCalibrator:
    """A fresh calibrator, or the one in ``--checkpoint`` when that file exists (checked against the arguments)."""
    platform = load_platform(args.platform)
    config = load_estimator_config(args.config, args.set)
    checkpoint = args.checkpoint and Path(args.checkpoint)
    if not (checkpoint and checkpoint.exists()):
        return OnlineCalibrator(platform, args.method, config)
    calib = OnlineCalibrator.load(checkpoint)
    if calib.method != args.method:
        raise CalibError(f"--checkpoint {checkpoint}: written by method '{calib.method}', not '{args.method}'")
    if platform_to_toml(calib.platform) != platform_to_toml(platform):
        raise CalibError(f"--checkpoint {checkpoint}: written for another platform than {args.platform}")
    if (args.config or args.set) and calib.config != config:
        differ = [
            f.name for f in dataclasses.fields(config) if getattr(config, f.name) != getattr(calib.config, f.name)
        ]
        raise CalibError(
            f"--checkpoint {checkpoint}: its estimator config differs from --config/--set in [{', '.join(differ)}]"
        )
    return calib


def _write(
    calib: OnlineCalibrator, writer: io.BackgroundWriter, out: Path | None, checkpoint: Path | None, final: bool = False
) -> None:
    """The result (unless ``out`` is None) and the checkpoint, through ``writer``; ``final`` marks
    the result of a run that ended normally (the added field ``"final"``).

    The state is taken here (the result's plain lists, the checkpoint's bytes); only the result's
    JSON text and the file writes are left to the writer's thread.
    """
    if out is not None and calib.estimate().samples_used:  # before any, there is only the prior
        result = calib.result()
        result["final"] = final
        writer.submit(out, lambda: io.result_text(result, str(out)).encode("utf-8"))
    if checkpoint:
        state = calib.checkpoint_bytes()
        writer.submit(checkpoint, lambda: state)


def follow_log(
    calib: OnlineCalibrator,
    chunks: Iterator[list[bytes]],
    source: str,
    every: int,
    write: Callable[[], None],
    skip_bad_rows: bool,
) -> str | None:
    """Feed the lines of ``chunks`` (header first) to ``calib``, calling ``write()`` every ``every`` data rows.

    Rows the checkpoint had already read (``calib.rows_read``) are parsed (time order is still
    checked across them) but not used again.

    Returns:
        The first bad row's message when rows were skipped, else None.
    Raises:
        CalibError: no header or a bad one; a bad row without ``skip_bad_rows``.
    """
    chunks = iter(chunks)
    first = next(chunks, None)
    if first is None:
        raise CalibError(f"{source}: no header row; expected a CSV header and sample rows (spec §3)")
    parser = io.LogRowParser(source, _decode(first[0], source, 1), calib.platform)
    feed = _Feed(calib, every, write, skip_bad_rows)
    line_number = 2
    for chunk in chain([first[1:]], chunks):
        block = parser.parse_block(chunk)
        if block is None:  # a row that is not plain: one by one, the good rows between bad ones in blocks
            good: list[Sample] = []
            for row, raw in enumerate(chunk, start=line_number):
                try:
                    sample = parser.parse(_decode(raw, source, row), row)
                except CalibError as err:
                    feed.block(_log_of(good))
                    good = []
                    feed.bad_row(str(err))
                else:
                    if sample is not None:  # a blank line is no row
                        good.append(sample)
            block = _log_of(good)
        feed.block(block)
        line_number += len(chunk)
    return feed.first_bad


def _log_of(samples: list[Sample]) -> Log:
    """``samples`` (rows of one log, so with the same optional fields) as a :class:`Log`."""
    first = samples[0] if samples else Sample(0.0, np.zeros(6), np.zeros(0))
    stack = lambda values: np.array(values, dtype=float).reshape(len(samples), -1)  # noqa: E731
    return Log(
        np.array([sample.t_s for sample in samples], dtype=float),
        stack([sample.strokes for sample in samples]),
        stack([sample.readings for sample in samples]),
        None if first.desired_pose is None else stack([sample.desired_pose for sample in samples]),
        [sample.stage for sample in samples],
        None if first.load_kg is None else np.array([sample.load_kg for sample in samples], dtype=float),
    )


class _Feed:
    """The data rows of a log to a calibrator, in order: the rows a resumed checkpoint had read are
    passed over, the others counted in ``rows_read`` and folded in, and ``write()`` called after
    every ``every``-th — a block is split there, so the writes come at the same rows either way."""

    def __init__(self, calib: OnlineCalibrator, every: int, write: Callable[[], None], skip_bad_rows: bool):
        self.calib, self.every, self.write, self.skip_bad_rows = calib, every, write, skip_bad_rows
        self.already, self.data_rows = calib.rows_read, 0
        self.first_bad: str | None = None

    def block(self, block: Log) -> None:
        """The good rows ``block``, one after the other."""
        start = min(len(block), max(self.already - self.data_rows, 0))
        self.data_rows += len(block)
        while start < len(block):
            stop = min(len(block), start + self.every - self.calib.rows_read % self.every)
            self.calib.update_block(block if (start, stop) == (0, len(block)) else block.select(slice(start, stop)))
            self.calib.rows_read += stop - start
            self._write_when_due()
            start = stop

    def bad_row(self, message: str) -> None:
        """One bad row: skipped and counted with ``skip_bad_rows``, else the refusal."""
        if self._passed_over():
            return
        if not self.skip_bad_rows:
            raise CalibError(message)  # not counted as read: a resume parses this row again
        self.calib.rows_read += 1
        self.calib.rows_skipped += 1
        self.first_bad = self.first_bad or message
        self._write_when_due()

    def _passed_over(self) -> bool:
        self.data_rows += 1
        return self.data_rows <= self.already

    def _write_when_due(self) -> None:
        if self.calib.rows_read % self.every == 0:
            self.write()


def run(args: argparse.Namespace) -> int:
    if args.method not in ONLINE_METHODS:
        raise CalibError(
            f"--method: '{args.method}' is not an online method; expected one of {', '.join(ONLINE_METHODS)}"
        )
    if args.every < 1:
        raise CalibError(f"--every: expected a whole number ≥ 1, got {args.every}")
    if args.idle_timeout is not None and not args.idle_timeout > 0:
        raise CalibError(f"--idle-timeout: expected a positive number of seconds, got {args.idle_timeout}")
    out, checkpoint = Path(args.out), args.checkpoint and Path(args.checkpoint)
    for path, option in ((out, "--out"), (checkpoint, "--checkpoint")):
        _check_writable_dir(path, option)
    calib = _start(args)
    fd, source = _open_input(args.log)
    for path in (out, checkpoint):
        if path:
            _remove_debris(path)
    stop = _StopRequest()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    writer = io.BackgroundWriter()
    try:
        with writer:
            chunks = line_chunks(fd, args.follow, args.idle_timeout, lambda: stop.requested)
            first_bad = follow_log(
                calib, chunks, source, args.every, lambda: _write(calib, writer, out, checkpoint), args.skip_bad_rows
            )
            if calib.estimate().samples_used:
                _write(calib, writer, out, checkpoint, final=True)
    except CalibError:
        # the state at the last good row is kept, no result; then the refusal (the writer has
        # finished: nothing it still held can land after this checkpoint)
        if checkpoint:
            calib.save(checkpoint)
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if source != "<stdin>":
            os.close(fd)
    if not calib.estimate().samples_used:
        raise CalibError(
            f"{source}: no usable samples ({calib.rows_read} rows read, "
            f"{calib.rows_skipped} skipped, {calib.rejections.count} rejected)"
        )
    report = lambda what, count, first: print(  # noqa: E731
        f"stewart-calib track: {what} {count} of {calib.rows_read} (first: {first})", file=sys.stderr
    )
    if calib.rows_skipped:
        report("skipped bad log rows:", calib.rows_skipped, first_bad or "in an earlier run")
    if calib.rejections.count:
        report(f"{args.method} rejected samples:", calib.rejections.count, calib.rejections.first)
    estimate = calib.estimate()
    print(
        f"stewart-calib track: wrote {out} ({args.method}: {estimate.samples_used} samples used, "
        f"{calib.rows_skipped + calib.rejections.count} skipped{', stopped by signal' if stop.requested else ''})",
        file=sys.stderr,
    )
    return 0


def add_parser(subparsers) -> None:
    parser = subparsers.add_parser(
        "track",
        description=__doc__.split("\n\n")[0].split(": ", 1)[1]
        + " Stops at the end of input, after --idle-timeout with --follow, or on Ctrl-C/SIGTERM (final estimate"
        " and checkpoint written); resumes from an existing --checkpoint when fed the same log from its start.",
    )
    parser.add_argument("--platform", required=True, metavar="P.toml", help="platform file (spec §2)")
    parser.add_argument("--method", required=True, metavar="METHOD", help=f"one of {', '.join(ONLINE_METHODS)}")
    parser.add_argument("--log", metavar="FILE", help="measurement log (spec §3); '-' or absent: standard input")
    parser.add_argument(
        "--follow",
        action="store_true",
        help="at the end of FILE, wait for more rows (stop with a signal or --idle-timeout)",
    )
    parser.add_argument("--idle-timeout", type=float, metavar="S", help="stop after S seconds without new data")
    parser.add_argument(
        "--checkpoint", metavar="C.npz", help="resume from this checkpoint if it exists; keep it current"
    )
    parser.add_argument(
        "--every", type=int, default=100, metavar="N", help="write the result and checkpoint every N rows (default 100)"
    )
    parser.add_argument("--out", required=True, metavar="R.json", help="result file (spec §5), replaced atomically")
    parser.add_argument(
        "--skip-bad-rows", action="store_true", help="skip bad rows (counted, reported) instead of stopping"
    )
    add_config_arguments(parser, "ekf.gate_probability=0.9999")
    parser.set_defaults(func=run)


def main(argv: list[str] | None = None) -> int:
    return run_command("track", argv)
