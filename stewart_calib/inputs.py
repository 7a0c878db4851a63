"""Reading input files safely: any readable stream, with every read bounded.

Every path argument may name a regular file, a pipe or FIFO (``--log <(ssh robot cat log)``), or a
device. A regular file is read as it is. Anything else is read once, never seeked: a command that
needs to read it twice gets a copy in an unnamed temporary file (:func:`open_input`). A stream that
gives no byte within :data:`FIRST_DATA_S` (a FIFO nobody writes to) or none for
:data:`STALL_S` after that is refused in one line, not waited on for ever.

Bounds, each refused in one line naming the file (and the key) rather than exhausting memory or
the stack: a document (TOML, JSON) of at most :data:`MAX_DOCUMENT_BYTES`, nested at most
:data:`MAX_NESTING` deep, integers within ±2⁶³; a line of a text file of at most
:data:`MAX_LINE_BYTES` (``/dev/zero`` has none); a stream of at most :data:`MAX_STREAM_BYTES`.
"""

from __future__ import annotations

import fcntl
import io
import json
import os
import select
import stat
import sys
import tempfile
import tomllib
from pathlib import Path
from typing import BinaryIO

from .errors import CalibError, shown

#: a stream (FIFO, pipe, device) must give its first byte within this [s] …
FIRST_DATA_S = 10.0
#: … and then never pause longer than this [s].
STALL_S = 60.0
#: the most a TOML or JSON document (platform, config, experiment, sweep spec, result) may hold.
MAX_DOCUMENT_BYTES = 64 << 20
#: the longest line of a text input (a CSV row, a header, a TOML line).
MAX_LINE_BYTES = 1 << 20
#: the most read from a stream that is not a regular file (a regular file's size is its own).
MAX_STREAM_BYTES = 64 << 30
#: the deepest nesting of tables/arrays (TOML) or objects/arrays (JSON) in a document.
MAX_NESTING = 32
#: integers in a document must lie within ±this (int64); a float's range is its own.
MAX_INTEGER = 2**63


def open_input(path: str | Path, what: str) -> BinaryIO:
    """``path`` open for reading in binary, seekable: a regular file itself; a pipe, FIFO or device
    read once into an unnamed temporary file (``$TMPDIR``) and handed back from its start.

    Raises:
        CalibError: not found, a directory, unreadable; a stream without data in time, with a
            line longer than :data:`MAX_LINE_BYTES`, or longer than :data:`MAX_STREAM_BYTES`.
    """
    fd = _open(path, what)
    if _regular(fd):
        return os.fdopen(fd, "rb")
    spool = tempfile.TemporaryFile()
    try:
        _copy_stream(fd, spool, path, what, MAX_STREAM_BYTES, lines=True)
    except BaseException:
        spool.close()
        raise
    finally:
        os.close(fd)
    spool.seek(0)
    return spool


def read_input_bytes(path: str | Path, what: str, limit: int = MAX_DOCUMENT_BYTES, lines: bool = True) -> bytes:
    """All bytes of ``path`` (any readable stream, see :func:`open_input`), at most ``limit``.

    ``lines``: a text file, whose lines must be shorter than :data:`MAX_LINE_BYTES`.

    Raises:
        CalibError: as :func:`open_input`, or the file is larger than ``limit``.
    """
    fd = _open(path, what)
    try:
        if _regular(fd):
            size = os.fstat(fd).st_size
            if size > limit:
                raise CalibError(f"{shown(path)}: {what} of {size} bytes; expected at most {limit} bytes")
            sink = io.BytesIO()
            while len(chunk := os.read(fd, 1 << 20)):  # not read(limit): that allocates the limit
                sink.write(chunk)
                if sink.tell() > limit:  # a file that grows while read
                    raise CalibError(f"{shown(path)}: {what} larger than {limit} bytes")
            data = sink.getvalue()
            if lines:
                _check_lines(data, 0, path, what)
            return data
        sink = io.BytesIO()
        _copy_stream(fd, sink, path, what, limit, lines)
        return sink.getvalue()
    finally:
        os.close(fd)


def read_input_text(path: str | Path, what: str, limit: int = MAX_DOCUMENT_BYTES) -> str:
    """:func:`read_input_bytes` as UTF-8 text (a byte-order mark dropped, ``\\r\\n`` made ``\\n``).

    Raises:
        CalibError: as :func:`read_input_bytes`, or the bytes are not UTF-8.
    """
    data = read_input_bytes(path, what, limit)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise CalibError(
            f"{shown(path)}: {what} is not UTF-8 text (byte 0x{data[err.start]:02x} at offset {err.start})"
        ) from None
    return text.replace("\r\n", "\n")


def parse_toml(text: str, source: str | Path) -> dict:
    """The TOML document ``text``, checked by :func:`check_document`.

    Raises:
        CalibError: ``source``: not valid TOML, nested too deep, an integer out of range.
    """
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise CalibError(f"{shown(source)}: not valid TOML ({err})") from None
    except (RecursionError, ValueError, OverflowError, MemoryError) as err:
        raise CalibError(f"{shown(source)}: not a readable TOML document ({_reason(err)})") from None
    check_document(doc, source)
    return doc


def parse_json(text: str, source: str | Path):
    """The JSON document ``text``, checked by :func:`check_document` (``NaN`` is left to the caller's
    check of its values, which names the key).

    Raises:
        CalibError: ``source``: not valid JSON, nested too deep, an integer out of range.
    """
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise CalibError(
            f"{shown(source)}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})"
        ) from None
    except (RecursionError, ValueError, OverflowError, MemoryError) as err:
        raise CalibError(f"{shown(source)}: not a readable JSON document ({_reason(err)})") from None
    check_document(doc, source)
    return doc


def check_document(doc, source: str | Path) -> None:
    """Refuse a parsed document nested deeper than :data:`MAX_NESTING`, or holding an integer
    outside ±:data:`MAX_INTEGER` or a non-finite float given as a number (naming its key)."""
    stack = [(doc, "", 0)]
    while stack:
        value, key, depth = stack.pop()
        if isinstance(value, (dict, list)):
            if depth >= MAX_NESTING:
                raise CalibError(f"{shown(source)}: key '{shown(key)}': nested deeper than {MAX_NESTING} levels")
            items = value.items() if isinstance(value, dict) else enumerate(value)
            stack.extend((item, f"{key}.{name}" if key else str(name), depth + 1) for name, item in items)
        elif isinstance(value, int) and not isinstance(value, bool) and not -MAX_INTEGER <= value < MAX_INTEGER:
            raise CalibError(
                f"{shown(source)}: key '{shown(key)}': integer of {len(str(abs(value)))} digits; expected within ±2^63"
            )


def _reason(err: BaseException) -> str:
    if isinstance(err, RecursionError):
        return f"nested deeper than {MAX_NESTING} levels"
    if "integer string conversion" in str(err):  # Python's own limit, met before ours
        return f"an integer of more than {sys.get_int_max_str_digits()} digits; expected within ±2^63"
    return " ".join(str(err).split()) or err.__class__.__name__


def _open(path: str | Path, what: str) -> int:
    """A descriptor of ``path`` for reading (``-``: standard input, as ``track`` reads it); a FIFO
    without a writer does not block the open."""
    if str(path) == "-" and not os.path.exists(path):
        fd = os.dup(sys.stdin.fileno())
        os.set_blocking(fd, False)
        return fd
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise CalibError(f"{shown(path)}: {what} not found") from None
    except OSError as err:
        raise CalibError(f"{shown(path)}: cannot read {what} ({err.strerror or err.__class__.__name__})") from None
    if stat.S_ISDIR(os.fstat(fd).st_mode):
        os.close(fd)
        article = "an" if what[:1] in "aeiou" else "a"  # an experiment file, a log file
        raise CalibError(f"{shown(path)}: is a directory; expected {article} {what}")
    return fd


def _regular(fd: int) -> bool:
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        return False
    fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
    return True


def _copy_stream(fd: int, sink, path: str | Path, what: str, limit: int, lines: bool) -> None:
    """Everything ``fd`` gives until its end into ``sink``, refused past ``limit`` bytes, past the
    waits of :data:`FIRST_DATA_S` / :data:`STALL_S`, or (``lines``) at a line too long."""
    total, line = 0, 0
    wait_s = FIRST_DATA_S
    while True:
        if not select.select([fd], [], [], wait_s)[0]:
            raise CalibError(
                f"{shown(path)}: no data for {wait_s:g} s from this {'FIFO (no writer?)' if total == 0 else 'stream'}"
                f" that should hold the {what}"
            )
        try:
            chunk = os.read(fd, 1 << 20)
        except BlockingIOError:
            continue
        if not chunk:
            return
        wait_s = STALL_S
        total += len(chunk)
        if total > limit:
            raise CalibError(f"{shown(path)}: {what} larger than {limit} bytes")
        if lines:
            line = _check_lines(chunk, line, path, what)
        sink.write(chunk)


def _check_lines(data: bytes, line: int, path: str | Path, what: str) -> int:
    """The length of the unfinished last line after ``data``, ``line`` bytes of it before;
    refuses a line longer than :data:`MAX_LINE_BYTES`."""
    start = 0
    while True:
        end = data.find(b"\n", start)
        length = line + ((len(data) if end < 0 else end) - start)
        if length > MAX_LINE_BYTES:
            raise CalibError(
                f"{shown(path)}: a line longer than {MAX_LINE_BYTES} bytes (no line break); the {what} must be "
                "text lines"
            )
        if end < 0:
            return length
        start, line = end + 1, 0


#: a time [s] in a log or a state must lie within ±this (~3 × 10⁴ years): t_s = 1e308 is no time of
#: a log, and its gap to the others would blow the random walk's covariance up (σ ~1e152 mm).
MAX_TIME_S = 1e12

#: the σ [mm] a measurement or prior may have: below 1 nm no instrument measures, above 1 m no
#: platform of this kind is (and 1e-300 or 1e300 overflow the filters' squares).
SIGMA_RANGE_MM = (1e-9, 1e3)


def implausible_sigma_mm(value: float) -> str | None:
    """Why a σ of ``value`` mm is implausible (outside :data:`SIGMA_RANGE_MM`), or None."""
    low, high = SIGMA_RANGE_MM
    if not low <= value <= high:
        return f"a σ within [{low:g}, {high:g}] mm, got {value!r}"
    return None
