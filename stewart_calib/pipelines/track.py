"""``stewart-calib track``: calibrate online from a log as it is written.

    stewart-calib track --platform P.toml --method {paper-ekf,ekf,isam2} [--log FILE | - | --link L.toml]
                        [--follow] [--idle-timeout S] [--checkpoint C.npz] [--every N]
                        --out R.json [--config C.toml] [--set section.key=value ...]
                        [--skip-bad-rows]

Reads the header, then the CSV rows as they arrive (``--log -`` or no ``--log``: standard input),
updates the estimator with each row, and every ``--every`` rows and at the end replaces ``--out``
(spec §5 result, plus ``samples_rejected``) and ``--checkpoint`` atomically. The rows of each
read are parsed as one block when every one is a plain good row
(:meth:`~stewart_calib.io.LogRowParser.parse_block`), one by one otherwise, and the good rows go to
the estimator in blocks (:meth:`OnlineCalibrator.update_block`, split at the ``--every`` rows and at
bad rows): the same writes and messages as row by row, and the same estimates as ``calibrate`` —
exactly for ``ekf`` and ``paper-ekf`` (to rounding), whatever ``--every`` and wherever a resume
happens. ``isam2`` adds a parameter window's samples in one smoother update where a block allows
(within its relinearisation threshold: measured ≤ 5e-5 σ on a clean 300-row log at --every 1 to 100),
but where its front end recovers from a lock-out the graph restarts at a point that depends on how
the rows were blocked: measured up to 0.024 σ (0.068 mm) from ``calibrate`` on the quick
experiment's log at --every 7 to 100. The bound is tested (tests/test_faults.py). ``calibrate``
measures the in-situ tracker's own geometry error on the log before it runs
(:mod:`stewart_calib.workflows.tracker_geometry`); ``track`` reads no log ahead and takes the geometry
as the settings give it: the same estimates where it is given the σ ``calibrate`` measured (its
result's ``config``: ``--set noise.tracker_geometry_sigma_mm=… --set noise.reading_sigma_mm=…``).

``--link L.toml`` takes the samples from a controller instead (spec §16, :mod:`stewart_calib.links`:
OPC UA, TwinCAT ADS): the link's rows go through the same parser, feed, writes and checkpoint as a
log's (:func:`follow_link`), the estimate goes back into the controller's ``[write]`` variables at
every write, and the result adds ``samples_missed``. The checkpoint's record of the source is then
the link's last counter, so a resume passes over the samples already read by their counter, not by
the first lines of a file. ``--idle-timeout`` ends a link that brought no new sample, or stayed
down, for that long.

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
idle timeout, signal). The final one of a log (not of a link) adds ``"log_sha256"``, as ``calibrate``'s:
the SHA-256 of the lines read, which are the log's bytes where it was read to its end.

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
import contextlib
import dataclasses
import glob
import hashlib
import math
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

from .. import io, links
from ..analysis.plausibility import payload_walk_warning
from ..config import load_estimator_config
from ..errors import CalibError, shown
from ..estimators.base import accounting_words, skipped_count
from ..inputs import MAX_LINE_BYTES
from ..io.platform_file import load_platform
from ..samples import Log, Sample
from ..workflows.calibration import EvenlySpacedSamples
from ..workflows.diagnosis import DIAGNOSED_SAMPLES, diagnose_log
from ..workflows.online import ONLINE_METHODS, OnlineCalibrator
from . import add_config_arguments, check_output_path, run_command

#: how often an idle input is polled [s]: latency of noticing new rows and signals.
POLL_S = 0.1
#: the most read at a time: a log read faster than it is written (a replay, a reader catching up)
#: is parsed and folded in a few thousand rows a block.
READ_BYTES = 1 << 20


def lines(
    fd: int, follow: bool, idle_timeout_s: float | None, stopped: Callable[[], bool], path: str | None = None
) -> Iterator[bytes]:
    """The lines of :func:`line_chunks` one at a time (a rotation's marker left out)."""
    return chain.from_iterable(chunk for chunk in line_chunks(fd, follow, idle_timeout_s, stopped, path) if chunk)


class Rotated(list):
    """What :func:`line_chunks` yields (an empty chunk) when the followed file was replaced or
    truncated: the lines after it are the new file's, from its start. ``why`` says what happened."""

    def __init__(self, why: str):
        super().__init__()
        self.why = why


def line_chunks(
    fd: int,
    follow: bool,
    idle_timeout_s: float | None,
    stopped: Callable[[], bool],
    path: str | None = None,
    digest: Callable[[bytes], None] | None = None,
) -> Iterator[list[bytes]]:
    """Complete lines of ``fd`` as they arrive (the line break removed), a list per read.

    Ends at the end of the input (a pipe closed by its writer; a regular file's end unless
    ``follow``), when ``stopped()``, or after ``idle_timeout_s`` without new data: the idle time
    is counted only from a read that found nothing (rows waiting in the file, the time the caller
    spends on them, or a SIGSTOP never count). A last line without a line break is yielded only at
    the end of the input: when stopped or timed out it may be a row still being written (or cut
    by the read size), so it is not yielded. Never blocks longer than :data:`POLL_S`, so a signal
    is noticed within that.

    With ``follow`` on the regular file at ``path``: when the file there is replaced (renamed,
    deleted and created again), truncated, or rewritten from its start, the old file's last line
    is yielded, then a :class:`Rotated` marker, then the new content's lines from its start.

    ``digest`` (as :func:`~stewart_calib.io.read_log`'s) is handed the bytes of each line as it is yielded,
    its line break included: a log read to its end whole, the file's bytes (an unfinished last line left
    unread is not among them; after a rotation the new file's follow the old one's).
    """
    hand_on = digest or (lambda data: None)
    regular = stat.S_ISREG(os.fstat(fd).st_mode)
    wait_at_end = follow and regular  # a pipe's end is final
    own_fd = None  # a replacement opened here (the caller closes the first)
    # the unfinished line; the first and the last bytes read of the file (what a rewrite changes)
    pending, head, tail = b"", b"", b""
    idle_since: float | None = None
    # the last read found the file's end: before the next, look for a rotation or a rewrite (a
    # file rewritten since would be read on from the old offset, in the middle of a row)
    at_end = False
    try:
        while not stopped():
            if at_end and path is not None:
                replaced = _replacement(fd, path, head, tail)
                if replaced is not None:
                    new_fd, why = replaced
                    if pending:  # the old file's last line, ended by the rotation
                        hand_on(pending)
                        yield [pending]
                    pending, head, tail, idle_since, at_end = b"", b"", b"", None, False
                    if new_fd != fd:
                        if own_fd is not None:
                            os.close(own_fd)
                        fd = own_fd = new_fd
                    yield Rotated(why)
                    continue
            chunk = _read_ready(fd, regular)
            at_end = wait_at_end and chunk == b""
            if chunk:
                idle_since = None
                head += chunk[: max(HEAD_BYTES - len(head), 0)]
                tail = (tail + chunk)[-HEAD_BYTES:]
                joined = pending + chunk
                *complete, pending = joined.split(b"\n")
                if len(pending) > MAX_LINE_BYTES:  # /dev/zero, or no CSV at all: not held for ever
                    raise CalibError(
                        f"{shown(path or '<stdin>')}: a line longer than {MAX_LINE_BYTES} bytes (no line break); "
                        "expected CSV rows"
                    )
                if complete:
                    hand_on(joined[: len(joined) - len(pending)])
                    yield complete
                continue
            if chunk == b"" and not wait_at_end:
                if pending and not stopped():  # a stop may come between the last read and this end
                    hand_on(pending)
                    yield [pending]
                return
            now = time.monotonic()
            if idle_since is None:
                idle_since = now
            elif idle_timeout_s is not None and now - idle_since >= idle_timeout_s:
                return
            if regular:
                time.sleep(POLL_S)  # select() always reports a regular file ready
    finally:
        if own_fd is not None:
            os.close(own_fd)


#: bytes at the start of a followed file, and before the point read, compared at its end: a file
#: rewritten from its start (truncated and written again faster than it is polled) differs at its
#: start; one rewritten in place with its first rows kept differs before the point read.
HEAD_BYTES = 4096


def _read_ready(fd: int, regular: bool) -> bytes | None:
    """The next bytes of ``fd``: ``b""`` at its end, None when a pipe has none within :data:`POLL_S`."""
    if not regular and not select.select([fd], [], [], POLL_S)[0]:
        return None
    try:
        return os.read(fd, READ_BYTES)
    except BlockingIOError:  # a FIFO opened without blocking, its writer gone quiet
        return None


def _replacement(fd: int, path: str, head: bytes, tail: bytes = b"") -> tuple[int, str] | None:
    """``(descriptor, what happened)`` when the file at ``path`` is no longer what ``fd`` has read:
    another file there (its own new descriptor), or this one truncated or rewritten (``fd`` back at
    its start); None when it is (or no file is there yet: a rotation between its rename and create).

    Raises:
        CalibError: the file was rewritten in place, its start kept and the bytes last read
            (``tail``) changed: the rows already used are no longer the file's, and its rows
            from here on would be read from the middle of one.
    """
    try:
        now = os.stat(path)
    except OSError:
        return None
    read = os.fstat(fd)
    if (now.st_dev, now.st_ino) != (read.st_dev, read.st_ino):
        try:
            return os.open(path, os.O_RDONLY | os.O_NONBLOCK), "replaced"
        except OSError:
            return None
    if now.st_size < os.lseek(fd, 0, os.SEEK_CUR):
        os.lseek(fd, 0, os.SEEK_SET)
        return fd, "truncated"
    if head and os.pread(fd, len(head), 0) != head:
        os.lseek(fd, 0, os.SEEK_SET)
        return fd, "rewritten"
    at = os.lseek(fd, 0, os.SEEK_CUR)
    if tail and os.pread(fd, len(tail), at - len(tail)) != tail:
        raise CalibError(
            f"{shown(path)}: the log was rewritten in place while followed (its bytes {at - len(tail)}–{at}, "
            "already read, changed; its first rows did not); expected rows appended at its end only — "
            "a log rewritten is a new log: track it afresh"
        )
    return None


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


def _identity(path: str) -> dict:
    """Device, inode and size of the file at ``path`` now (the checkpoint's record; {} when gone)."""
    try:
        now = os.stat(path)
    except OSError:
        return {}
    return {"device": now.st_dev, "inode": now.st_ino, "size": now.st_size}


def _open_input(log: str | None) -> tuple[int, str]:
    if log in (None, "-"):
        return sys.stdin.fileno(), "<stdin>"
    try:
        fd = os.open(log, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO without a writer yet: no wait here
    except FileNotFoundError:
        raise CalibError(f"{shown(log)}: log file not found") from None
    except OSError as err:
        raise CalibError(f"{shown(log)}: cannot read log file ({err.strerror})") from None
    if stat.S_ISDIR(os.fstat(fd).st_mode):  # Linux opens a directory read-only; reading it fails later
        os.close(fd)
        raise CalibError(f"{shown(log)}: is a directory; expected a log file (spec §3)")
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
    calib = OnlineCalibrator.load(checkpoint, platform)
    if calib.source is not None:  # written by track, which counts every row it reads
        try:
            calib.check_counts()
        except CalibError as err:
            raise CalibError(f"--checkpoint {shown(checkpoint)}: does not match its own estimate: {err}") from None
    if calib.method != args.method:
        raise CalibError(f"--checkpoint {shown(checkpoint)}: written by method '{calib.method}', not '{args.method}'")
    if (args.config or args.set) and calib.config != config:
        differ = [
            f.name for f in dataclasses.fields(config) if getattr(config, f.name) != getattr(calib.config, f.name)
        ]
        raise CalibError(
            f"--checkpoint {checkpoint}: its estimator config differs from --config/--set in [{', '.join(differ)}]"
        )
    return calib


def _write(
    calib: OnlineCalibrator,
    writer: io.BackgroundWriter,
    out: Path | None,
    checkpoint: Path | None,
    final: bool = False,
    log_digest: io.LogDigest | None = None,
) -> None:
    """The result (unless ``out`` is None) and the checkpoint, through ``writer``; ``final`` marks
    the result of a run that ended normally (the added field ``"final"``), which adds the ``"log_sha256"``
    of ``log_digest``, the lines read (a log's, not a link's): the estimate has had every one of them,
    where a periodic result, written within a read, has not had the read's later lines.

    The state is taken here (the result's plain lists, the checkpoint's bytes); only the result's
    JSON text and the file writes are left to the writer's thread.
    """
    if out is not None and calib.estimate().samples_used:  # before any, there is only the prior
        result = calib.result()
        result["final"] = final
        if calib.source is not None and "samples_missed" in calib.source:  # a link's (spec §16)
            result["samples_missed"] = calib.source["samples_missed"]
        if final and log_digest is not None:
            result.update(log_digest.field())
        writer.submit(out, lambda: io.result_text(result, str(out)).encode("utf-8"))
    if checkpoint:
        state = calib.checkpoint_bytes()
        writer.submit(checkpoint, lambda: state)


#: data lines after the header that identify a log in a checkpoint (their SHA-256 with the header's)
HEAD_LINES = 16


class NotTheLog(CalibError):
    """The log given is not the one a checkpoint read (refused before any row is used)."""


class _Head:
    """The header and first :data:`HEAD_LINES` lines of one file, as read: its identity."""

    def __init__(self, header: bytes):
        self.lines = [header]

    def add(self, lines: list[bytes]) -> None:
        self.lines += lines[: max(HEAD_LINES + 1 - len(self.lines), 0)]

    def digest(self, count: int | None = None) -> str:
        """SHA-256 of the header and the first ``count`` lines (default: all held)."""
        lines = self.lines if count is None else self.lines[: count + 1]
        return hashlib.sha256(b"\n".join(lines)).hexdigest()


class _Reader:
    """The lines of one or more files (a rotation starts another) fed to a calibrator.

    Rows a resumed checkpoint had read of the same file are passed over; a file whose first
    lines differ from the checkpoint's is refused (:class:`NotTheLog`) or, with ``new_log``, read
    from its start.
    """

    def __init__(self, calib: OnlineCalibrator, source: str, identity: Callable[[], dict], new_log: bool):
        self.calib, self.source, self.identity, self.new_log = calib, source, identity, new_log
        self.head: _Head | None = None
        self.header_line = b""
        self.feed: _Feed | None = None

    def source_record(self) -> dict:
        """The checkpoint's record of the file being read (:attr:`OnlineCalibrator.source`)."""
        assert self.head is not None and self.feed is not None
        return {
            **self.identity(),
            "path": self.source,
            "head_lines": len(self.head.lines) - 1,
            "head_sha256": self.head.digest(),
            "rows": self.feed.data_rows,
        }

    def already_read(self, head: _Head, ended: bool) -> int:
        """Rows of this file the checkpoint had read (0 for a new file), once ``head`` holds as many
        lines as the checkpoint's record (or the input ``ended``).

        Raises:
            NotTheLog: the checkpoint read another file, and no ``new_log``.
        """
        record = self.calib.source
        if record is None:  # a checkpoint of an earlier version, or made through the API: the same log assumed
            return self.calib.rows_read
        count = int(record["head_lines"])
        if len(head.lines) - 1 >= count and head.digest(count) == record["head_sha256"]:
            return int(record["rows"])
        old = f"{shown(str(record['path']))}, {record['rows']} rows"
        if not self.new_log:
            why = "it ends sooner" if ended and len(head.lines) - 1 < count else "its first rows differ"
            raise NotTheLog(
                f"{shown(self.source)}: not the log the checkpoint read ({old}; {why}); feed that log from its "
                f"start, or give --new-log to read {shown(self.source)} from its start"
            )
        print(
            f"stewart-calib track: {shown(self.source)} is not the log the checkpoint read ({old}); "
            "reading it from its start (--new-log)",
            file=sys.stderr,
        )
        return 0


def follow_log(
    calib: OnlineCalibrator,
    chunks: Iterator[list[bytes]],
    source: str,
    every: int,
    write: Callable[[], None],
    skip_bad_rows: bool,
    identity: Callable[[], dict] = dict,
    new_log: bool = False,
) -> _Feed:
    """Feed the lines of ``chunks`` (header first) to ``calib``, calling ``write()`` every ``every`` data rows.

    Rows the checkpoint had already read of this file are parsed (time order is still checked
    across them) but not used again. A :class:`Rotated` marker starts a new file: its first line
    is skipped when it repeats the header, and no rows of it count as read before.

    Returns:
        The feed: its counts and the first bad row's message (when rows were skipped).
    Raises:
        CalibError: no header or a bad one; a bad row without ``skip_bad_rows``.
        NotTheLog: the checkpoint read another file (see :class:`_Reader`).
    """
    reader = _Reader(calib, source, identity, new_log)
    chunks = iter(chunks)
    first = next((chunk for chunk in chunks if chunk), None)
    if first is None:
        raise CalibError(f"{shown(source)}: no header row; expected a CSV header and sample rows (spec §3)")
    reader.header_line = first[0]
    parser = io.LogRowParser(source, _decode(first[0], source, 1), calib.platform)
    reader.head = _Head(first[0])
    reader.head.add(first[1:])
    held = [first[1:]]
    wanted = 0 if calib.source is None else int(calib.source["head_lines"])
    while len(reader.head.lines) <= wanted:  # the checkpoint's head of the file first: nothing is used before
        chunk = next(chunks, None)
        if chunk is None or isinstance(chunk, Rotated):
            chunks = chain([] if chunk is None else [chunk], chunks)
            break
        reader.head.add(chunk)
        held.append(chunk)
    feed = reader.feed = _Feed(calib, every, lambda: _recorded(reader, write), skip_bad_rows, source)
    feed.already = reader.already_read(reader.head, ended=len(reader.head.lines) <= wanted)
    line_number = 2
    for chunk in held:
        _feed_chunk(parser, feed, chunk, source, line_number)
        line_number += len(chunk)
    for chunk in chunks:
        if isinstance(chunk, Rotated):
            print(
                f"stewart-calib track: {shown(source)} was {chunk.why} after {feed.data_rows} rows; "
                "reading the new file from its start",
                file=sys.stderr,
            )
            feed.rotated()
            reader.head, line_number = None, 1
            continue
        if reader.head is None and chunk:  # a new file's first line: its header when it repeats ours
            repeats = chunk[0] == reader.header_line
            reader.head = _Head(chunk[0] if repeats else b"")
            if repeats:
                chunk, line_number = chunk[1:], 2
        if reader.head is not None:
            reader.head.add(chunk)
        _feed_chunk(parser, feed, chunk, source, line_number)
        line_number += len(chunk)
    feed.diagnose()  # a log that ended before a write was due
    if reader.head is not None:
        calib.source = reader.source_record()
    return feed


def _recorded(reader: _Reader, write: Callable[[], None]) -> None:
    """``write()`` with the checkpoint's record of the file read brought up to date."""
    if reader.head is not None:
        reader.calib.source = reader.source_record()
    write()


def follow_link(
    calib: OnlineCalibrator, link: links.Link, every: int, write: Callable[[], None], skip_bad_rows: bool
) -> _Feed:
    """Feed the rows of a controller ``link`` (spec §16) to ``calib`` as :func:`follow_log` feeds a
    log's: the same parser, gating, accounting and writes. A resumed link has already passed over
    the samples its checkpoint read (by their counter), so none counts as read before."""
    parser = io.LogRowParser(link.name, link.header.decode("utf-8"), calib.platform)

    def recorded() -> None:
        calib.source = link.record()
        write()

    feed = _Feed(calib, every, recorded, skip_bad_rows, link.name)
    for chunk in link.rows():
        if isinstance(chunk, links.NewStream):  # its time may start again
            parser = io.LogRowParser(link.name, link.header.decode("utf-8"), calib.platform)
            continue
        _feed_chunk(parser, feed, chunk, link.name, link.rows_read + 1)
    calib.source = link.record()
    return feed


def _feed_chunk(parser: io.LogRowParser, feed: _Feed, chunk: list[bytes], source: str, line_number: int) -> None:
    """The lines ``chunk`` (the first is line ``line_number`` of the file) to ``feed``: as one
    block when every row is plain, else one by one with the good rows between bad ones in blocks."""
    block = parser.parse_block(chunk)
    if block is None:
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


def _log_of(samples: list[Sample]) -> Log | None:
    """``samples`` (rows of one log, so with the same optional fields) as a :class:`Log`; None for none."""
    if not samples:
        return None
    first = samples[0]
    stack = lambda values: np.array(values, dtype=float).reshape(len(samples), -1)  # noqa: E731
    return Log(
        np.array([sample.t_s for sample in samples], dtype=float),
        stack([sample.strokes for sample in samples]),
        stack([sample.readings for sample in samples]),
        None if first.desired_pose is None else stack([sample.desired_pose for sample in samples]),
        [sample.stage for sample in samples],
        {
            name: stack([sample.inputs[name] for sample in samples]).reshape(len(samples), *np.shape(value))
            for name, value in first.inputs.items()
        },
    )


class _Feed:
    """The data rows of a log to a calibrator, in order: the first ``already`` rows of the file (read
    by the checkpoint resumed) are passed over, the others counted in ``rows_read`` and folded in,
    and ``write()`` called after every ``every``-th — a block is split there, so the writes come at
    the same rows either way."""

    def __init__(
        self, calib: OnlineCalibrator, every: int, write: Callable[[], None], skip_bad_rows: bool, source: str = ""
    ):
        self.calib, self.every, self.write, self.skip_bad_rows = calib, every, write, skip_bad_rows
        self.source = source
        self.already, self.data_rows = 0, 0  # of the file being read
        self.first_bad: str | None = None
        # the run's good rows, evenly spread, until the diagnosis has looked at them
        self.undiagnosed: EvenlySpacedSamples | None = EvenlySpacedSamples(DIAGNOSED_SAMPLES)

    def diagnose(self) -> None:
        """:func:`~stewart_calib.workflows.diagnosis.diagnose_log` on the run's good rows so far (at most
        ``2 ×`` :data:`~stewart_calib.workflows.diagnosis.DIAGNOSED_SAMPLES`, evenly spread), once the estimator
        uses samples: ``calibrate``'s check of the log, which names a mistake's cause (a unit, swapped
        columns) where the estimate would go wrong. Not before: an outside instrument's estimator
        holds its samples until poses that register it arrive, and rows at rest before them are no
        evidence (their spread is the noise's: they "do not match the strokes")."""
        held = self.undiagnosed
        if held is None or not held.seen or not self.calib.estimate().samples_used:
            return
        self.undiagnosed = None
        diagnose_log(self.calib.platform, held.log.strokes, held.log.readings, self.source, count=False)

    def rotated(self) -> None:
        """The next rows are a new file's, none of them read before."""
        self.already, self.data_rows = 0, 0

    def block(self, block: Log | None) -> None:
        """The good rows ``block``, one after the other."""
        if block is None or not len(block):
            return
        first = self.data_rows  # the file's rows before this block
        start = min(len(block), max(self.already - first, 0))
        # a write within the block records the rows folded in up to it, not the whole block: a
        # resume from that checkpoint reads the block's rest again (a kill -9 left it unused)
        self.data_rows = first + start
        if self.undiagnosed is not None and start < len(block):
            self.undiagnosed.add(block if start == 0 else block.select(slice(start, len(block))))
        while start < len(block):
            stop = min(len(block), start + self.every - self.calib.rows_read % self.every)
            self.calib.update_block(block if (start, stop) == (0, len(block)) else block.select(slice(start, stop)))
            self.calib.rows_read += stop - start
            self.data_rows = first + stop
            self._write_when_due()
            start = stop

    def bad_row(self, message: str) -> None:
        """One bad row: skipped and counted with ``skip_bad_rows``, else the refusal."""
        self.data_rows += 1
        if self.data_rows <= self.already:
            return
        if not self.skip_bad_rows:
            self.data_rows -= 1  # not counted as read: a resume parses this row again
            raise CalibError(message)
        self.calib.rows_read += 1
        self.calib.rows_skipped += 1
        self.first_bad = self.first_bad or message
        self._write_when_due()

    def _write_when_due(self) -> None:
        if self.calib.rows_read % self.every == 0:
            self.diagnose()  # before the first result
            self.write()


def run(args: argparse.Namespace) -> int:
    if args.method not in ONLINE_METHODS:
        raise CalibError(
            f"--method: '{args.method}' is not an online method; expected one of {', '.join(ONLINE_METHODS)}"
        )
    if args.every < 1:
        raise CalibError(f"--every: expected a whole number ≥ 1, got {args.every}")
    if args.idle_timeout is not None and not 0 < args.idle_timeout < math.inf:
        raise CalibError(
            f"--idle-timeout: expected a finite positive number of seconds, got {args.idle_timeout} "
            "(without it, --follow waits until a signal)"
        )
    out, checkpoint = Path(args.out), args.checkpoint and Path(args.checkpoint)
    for path, option in ((out, "--out"), (checkpoint, "--checkpoint")):
        check_output_path(path, option)
    with contextlib.ExitStack() as locks:
        for path, option in ((checkpoint, "--checkpoint"), (out, "--out")):
            if path:  # two runs writing one file: the last writer would win
                locks.enter_context(io.exclusive_lock(path, option, "another track run is writing it"))
        return _track(args, out, checkpoint)


def _track(args: argparse.Namespace, out: Path, checkpoint: Path | None) -> int:
    calib = _start(args)
    stop = _StopRequest()
    link = _open_link(args, calib, lambda: stop.requested) if args.link else None
    fd, source = _open_input(args.log) if link is None else (-1, link.name)
    for path in (out, checkpoint):
        if path:
            _remove_debris(io.written_target(path).file)  # beside the file a link names: where its writes are
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    writer = io.BackgroundWriter()
    log_digest = io.LogDigest()  # of a log's lines read: validate knows the log
    identity = (lambda: {}) if source == "<stdin>" else (lambda: _identity(source))
    try:
        with writer:
            if link is not None:
                feed = follow_link(
                    calib,
                    link,
                    args.every,
                    lambda: _write_and_hand_back(calib, writer, out, checkpoint, link),
                    args.skip_bad_rows,
                )
            else:
                chunks = line_chunks(
                    fd,
                    args.follow,
                    args.idle_timeout,
                    lambda: stop.requested,
                    None if source == "<stdin>" else source,
                    log_digest.update,
                )
                feed = follow_log(
                    calib,
                    chunks,
                    source,
                    args.every,
                    lambda: _write(calib, writer, out, checkpoint),
                    args.skip_bad_rows,
                    identity,
                    args.new_log,
                )
            if feed.data_rows < feed.already and not stop.requested:
                raise NotTheLog(
                    f"{shown(source)}: ended after {feed.data_rows} rows, before the {feed.already} rows the "
                    "checkpoint had read of it; feed that log from its start"
                )
            if calib.estimate().samples_used:
                _write(calib, writer, out, checkpoint, final=True, log_digest=None if link is not None else log_digest)
                if link is not None:
                    _hand_back(calib, link, final=True)
    except NotTheLog:
        raise  # nothing was used: the checkpoint stays as it was
    except CalibError:
        # the state at the last good row is kept, no result; then the refusal (the writer has
        # finished: nothing it still held can land after this checkpoint)
        if checkpoint:
            calib.save(checkpoint)
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if link is not None:
            link.close()
        elif source != "<stdin>":
            os.close(fd)
    first_bad = feed.first_bad
    if not calib.estimate().samples_used:
        raise CalibError(
            f"{shown(source)}: no usable samples ({calib.rows_read} rows read, "
            f"{calib.rows_skipped} skipped, {calib.rejections.count} rejected)"
        )
    report = lambda what, count, first: print(  # noqa: E731
        f"stewart-calib track: {what} {count} of {calib.rows_read} (first: {first})", file=sys.stderr
    )
    if calib.rows_skipped:
        report("skipped bad log rows:", calib.rows_skipped, first_bad or "in an earlier run")
    estimate = calib.estimate()
    rejected = calib.rejections.in_result(estimate)  # those taken back in are among the used
    if rejected["count"]:
        report(f"{args.method} rejected samples:", rejected["count"], rejected["first"])
    payload = payload_walk_warning(calib.platform.elastic, estimate)
    if payload:
        print(f"stewart-calib track: {payload}", file=sys.stderr)
    skipped = skipped_count(calib.rows_skipped, calib.rejections.count, estimate)
    stopped = ", stopped by signal" if stop.requested else ""
    missed = f"; {link.samples_missed} samples missed" if link is not None and link.link.sample else ""
    print(
        f"stewart-calib track: wrote {out} ({args.method}: {estimate.samples_used} samples used, "
        f"{skipped} skipped{accounting_words(estimate.details or {})}, of {calib.rows_read} rows{stopped}{missed})",
        file=sys.stderr,
    )
    return 0


#: how long the final estimate is tried into a controller that is down or refuses it [s].
FINAL_WRITE_S = 5.0


def _open_link(args: argparse.Namespace, calib: OnlineCalibrator, stopped: Callable[[], bool]) -> links.Link:
    """The controller link of ``--link`` (spec §16), resumed at the checkpoint's last counter."""
    if args.log is not None:
        raise CalibError("--link: give either --link or --log (a link takes samples from the controller)")
    if args.follow:
        raise CalibError("--follow: a link follows its controller; --follow is for a log file")
    spec = links.load_link(args.link, calib.platform)
    prior = io.result_dict(calib.estimate(), calib.platform)  # the arrays' lengths, as every result has them
    return links.Link(spec, links.write_lengths(spec, prior), calib.source, args.idle_timeout, stopped)


def _write_and_hand_back(
    calib: OnlineCalibrator, writer: io.BackgroundWriter, out: Path, checkpoint: Path | None, link: links.Link
) -> None:
    _write(calib, writer, out, checkpoint)
    _hand_back(calib, link)


def _hand_back(calib: OnlineCalibrator, link: links.Link, final: bool = False) -> None:
    """The estimate into the controller's ``[write]`` variables; the final one tried for :data:`FINAL_WRITE_S`."""
    if not link.link.write or not calib.estimate().samples_used:
        return
    link.hand_back(calib.result())
    if final and not link.finish(FINAL_WRITE_S):
        print(
            f"stewart-calib track: the final estimate could not be written into {shown(link.link.url)}", file=sys.stderr
        )


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
        "--link",
        metavar="L.toml",
        help="take samples from a controller (OPC UA, TwinCAT ADS) named by this link file, and write the estimate"
        " back (docs/howto/controller.md)",
    )
    parser.add_argument(
        "--follow",
        action="store_true",
        help="at the end of FILE, wait for more rows (stop with a signal or --idle-timeout)",
    )
    parser.add_argument(
        "--idle-timeout",
        type=float,
        metavar="S",
        help="stop after S seconds in which the log had no new data (a link: no new sample, or the connection down)",
    )
    parser.add_argument(
        "--new-log",
        action="store_true",
        help="resuming on a log whose first rows differ from the one the checkpoint read: read it from its start"
        " (default: refuse it)",
    )
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
