"""Live links to a controller (spec §16): samples polled from the controller's variables, the
estimate written back into them.

A link file names the controller (``[link] url``), how often to poll it (``rate_hz``), the
variable that counts its samples (``sample``, optional), the variable behind each log column
(``[read]``) and where the estimate goes (``[write]``, optional). A controller kind is one module
with a ``connect(url, timeout_s)`` returning a :class:`Connection`, and one line of
:data:`LINK_KINDS`; :class:`Link` does the rest the same for every kind:

* every poll reads the stamp (the counter, or ``t_s`` without one), every ``[read]`` variable and
  the stamp again in **one** request; where the two stamps differ the controller moved on in the
  middle of the request and the sample is read again, so no row mixes two controller cycles;
* a counter that rises by one is the next sample; a jump of k counts k − 1 samples as missed (the
  poll was too slow, or the link was down), a fall is a controller that restarted: a new stream.
  A counter still at 0 has published no sample yet (the first is 1): the variables a controller
  starts with are not taken for a sample; a run that joins a controller at its sample c (and no
  checkpoint of this link says where it stopped) counts the c − 1 before it as missed;
* a lost connection is retried with a growing wait (up to :data:`BACKOFF_MAX_S`), and the gap is
  reported with its length and the samples missed in it; no sample is ever made up;
* the rows go to ``track`` as spec §3 CSV lines (each value as ``repr`` of its double, which
  parses back to the same double), so they meet exactly the checks, gating and accounting a log's
  rows meet.
"""

from __future__ import annotations

import hashlib
import importlib
import math
import sys
import time
import tomllib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from ..errors import CalibError, number, shown, without_noise
from ..io import drive_columns, reading_columns
from ..io.logs import POSE_COLUMNS

#: controller kinds by the scheme of ``[link] url``: the module that speaks to them.
LINK_KINDS = {
    "opc.tcp": "stewart_calib.links.opcua",
    "ads": "stewart_calib.links.ads",
}

#: what ``[write]`` may name: the estimate (spec §5 order), its σ, the samples it used, and the
#: result's other blocks (§7, §10, §17) by their keys.
WRITE_KEYS = ("parameters", "stddev", "samples_used", "stroke_scale", "compliance", "thermal", "instrument")
#: the ``[write]`` keys that take an array (the others a number).
ARRAY_KEYS = tuple(key for key in WRITE_KEYS if key != "samples_used")

#: longest wait between two attempts to reach a controller that is down [s].
BACKOFF_MAX_S = 2.0
#: first wait after a lost connection [s] (doubled at each failure).
BACKOFF_FIRST_S = 0.05
#: how long one request may take before the connection counts as lost [s].
REQUEST_TIMEOUT_S = 2.0
#: the longest a wait between polls lasts before a signal is looked at again [s].
WAIT_SLICE_S = 0.1
#: a torn read (the stamp changed within the request) is read again at once, at most this often.
TORN_RETRIES = 10


class LinkDown(Exception):
    """The controller cannot be reached, or stopped answering (retried, never fatal)."""


class WriteFailed(Exception):
    """The controller refused a write (reported and retried; tracking goes on)."""


class Connection(Protocol):
    """An open connection to a controller; what a kind's ``connect(url, timeout_s)`` returns.

    ``check`` refuses (:class:`~stewart_calib.errors.CalibError`, one line naming the key and the
    variable) what the controller lacks or declares of another type; ``read`` and ``write`` raise
    :class:`LinkDown` when the connection is lost, ``write`` :class:`WriteFailed` when refused.
    """

    def check(self, reads: dict[str, str], stamp: str | None, writes: dict[str, str], lengths: dict[str, int]) -> None:
        """Resolve the variables: ``reads`` (label → name) numeric scalars, ``stamp`` (a counter's name)
        an integer, ``writes`` (key → name) arrays of ``lengths[key]`` numbers where the key takes an
        array, a number otherwise. Fixes the order :meth:`read` returns."""
        ...

    def read(self) -> list[float]:
        """Stamp, every read variable (in ``check``'s order), stamp again: one request."""
        ...

    def write(self, values: dict[str, Sequence[float] | float]) -> None:
        """``values`` (key → value) into the ``[write]`` variables, each in the type the controller declares."""
        ...

    def wait(self, seconds: float) -> None:
        """Sleep, letting the client's own housekeeping run meanwhile."""
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class LinkFile:
    """A link file (spec §16), checked."""

    path: str
    url: str
    rate_hz: float
    sample: str | None
    read: dict[str, str]
    write: dict[str, str]

    @property
    def scheme(self) -> str:
        return self.url.split("://", 1)[0]


def load_link(path: str | Path, platform=None) -> LinkFile:
    """Read and check a link file; with ``platform``, ``[read]`` must give every column its instrument needs.

    Raises:
        CalibError: one line naming the file, the key and what was expected.
    """
    name = shown(path)
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibError(f"{name}: link file not found") from None
    except (OSError, UnicodeDecodeError) as err:
        raise CalibError(f"{name}: cannot read link file ({err})") from None
    except tomllib.TOMLDecodeError as err:
        raise CalibError(f"{name}: not a TOML file ({err})") from None
    for key in data:
        if key not in ("link", "read", "write"):
            raise CalibError(f"{name}: unknown table [{shown(key)}]; expected [link], [read] and [write] (spec §16)")
    link = _table(data, "link", name)
    for key in link:
        if key not in ("url", "rate_hz", "sample"):
            raise CalibError(f"{name}: unknown key 'link.{shown(key)}'; expected url, rate_hz, sample (spec §16)")
    url = link.get("url")
    if not isinstance(url, str) or "://" not in url:
        raise CalibError(
            f"{name}: link.url: expected a controller's URL (opc.tcp://HOST:PORT/ or ads://HOST/NETID:PORT)"
        )
    if url.split("://", 1)[0] not in LINK_KINDS:
        raise CalibError(
            f"{name}: link.url: unknown scheme '{shown(url.split('://', 1)[0])}'; expected one of "
            + ", ".join(f"{scheme}://" for scheme in LINK_KINDS)
        )
    rate_hz = link.get("rate_hz")
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, int | float) or not 0 < rate_hz < math.inf:
        raise CalibError(f"{name}: link.rate_hz: expected a finite number of polls a second > 0, got {rate_hz!r}")
    sample = link.get("sample")
    if sample is not None and (not isinstance(sample, str) or not sample):
        raise CalibError(f"{name}: link.sample: expected the name of the controller's sample counter")
    read = _names(_table(data, "read", name), "read", name)
    write = _names(data.get("write", {}), "write", name)
    for key in write:
        if key not in WRITE_KEYS:
            raise CalibError(f"{name}: unknown key 'write.{shown(key)}'; expected one of {', '.join(WRITE_KEYS)}")
    if "t_s" not in read:
        raise CalibError(f"{name}: [read] lacks t_s, the sample's time (spec §3)")
    if platform is not None:
        needed = ("t_s", *drive_columns(platform), *reading_columns(platform))
        missing = [column for column in needed if column not in read]
        if missing:
            raise CalibError(
                f"{name}: [read] lacks {', '.join(missing)} (every column the platform's instrument needs, spec §3, §7)"
            )
        pose = [column for column in POSE_COLUMNS if column in read]
        if pose and len(pose) != len(POSE_COLUMNS):
            raise CalibError(f"{name}: [read] gives {', '.join(pose)} of the desired pose; expected all six or none")
    return LinkFile(str(path), url, float(rate_hz), sample, read, write)


def _table(data: dict, key: str, name: str) -> dict:
    table = data.get(key)
    if not isinstance(table, dict):
        raise CalibError(f"{name}: missing table [{key}] (spec §16)")
    return table


def _names(table: Any, section: str, name: str) -> dict[str, str]:
    if not isinstance(table, dict):
        raise CalibError(f"{name}: [{section}]: expected a table of names")
    for key, value in table.items():
        if not isinstance(value, str) or not value:
            raise CalibError(f"{name}: {section}.{shown(key)}: expected the name of a controller variable")
        if any(ch in key for ch in ',"\r\n'):
            raise CalibError(f"{name}: {section}.{shown(key)}: not a log column name")
    return dict(table)


def connect(link: LinkFile, timeout_s: float = REQUEST_TIMEOUT_S) -> Connection:
    """An open connection to ``link``'s controller (its kind's module, by the URL's scheme).

    Raises:
        LinkDown: the controller cannot be reached.
    """
    module = importlib.import_module(LINK_KINDS[link.scheme])
    return module.connect(link.url, timeout_s)


class NewStream:
    """What :meth:`Link.rows` yields when the controller restarted its counter: the rows after it
    are a new stream (its time may start again)."""

    def __init__(self, why: str):
        self.why = why


def say(message: str) -> None:
    print(f"stewart-calib track: {message}", file=sys.stderr, flush=True)


class Link:
    """The samples of a controller, polled at ``rate_hz``, as spec §3 rows; and the estimate handed back.

    Args:
        link: the link file.
        lengths: the length of each ``[write]`` array the estimate has (``parameters``: 42, …).
        record: the checkpoint's record of an earlier run on this link (its last counter), or None.
        idle_timeout_s: end after this long without a new sample (connection down or not); None: never.
        stopped: asked before every poll; True ends the rows.
        clock, connector: the time and the connection (tests replace them).
    """

    def __init__(
        self,
        link: LinkFile,
        lengths: dict[str, int],
        record: dict | None = None,
        idle_timeout_s: float | None = None,
        stopped: Callable[[], bool] = lambda: False,
        clock: Callable[[], float] = time.monotonic,
        connector: Callable[[LinkFile], Connection] = connect,
    ):
        self.link, self.lengths, self.idle_timeout_s, self.stopped = link, lengths, idle_timeout_s, stopped
        self.clock, self.connector = clock, connector
        self.columns = list(link.read)
        self.header = ",".join(self.columns).encode("utf-8")
        record = record if record is not None and record.get("link") == link.url else None
        self.counter: int | None = None if record is None else record.get("counter")
        self.t_s: float | None = None if record is None else record.get("t_s")
        self.rows_read = 0 if record is None else int(record["rows"])
        self.samples_missed = 0 if record is None else int(record.get("samples_missed", 0))
        self.torn = 0  # reads taken again because the stamp moved within the request
        self.conn: Connection | None = None
        self._pending: dict[str, Sequence[float] | float] | None = None  # a write not yet through
        self._write_error: str | None = None

    @property
    def name(self) -> str:
        return self.link.path

    def record(self) -> dict:
        """The checkpoint's record: the link, the last counter (or time) read, the rows and samples missed.

        It has the keys of a log file's record (``path``, ``head_lines``, ``head_sha256``, ``rows``),
        so a checkpoint of either kind reads the same way; its digest is of the link, not of any
        file's lines, so a log file fed to its checkpoint is told apart (refused, or ``--new-log``)."""
        return {
            "path": self.link.url,
            "link": self.link.url,
            "head_lines": 0,
            "head_sha256": hashlib.sha256(b"link " + self.link.url.encode("utf-8")).hexdigest(),
            "rows": self.rows_read,
            "counter": self.counter,
            "t_s": self.t_s,
            "samples_missed": self.samples_missed,
        }

    # -- connection -------------------------------------------------------------------------
    def _open(self) -> Connection:
        conn = self.connector(self.link)
        try:
            stamp = self.link.sample if self.link.sample is not None else self.link.read["t_s"]
            conn.check(self.link.read, stamp, self.link.write, self.lengths)
        except CalibError as err:
            conn.close()
            raise CalibError(f"{shown(self.link.path)}: {err}") from None
        except BaseException:
            conn.close()
            raise
        return conn

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    def _wait(self, seconds: float) -> None:
        """Wait ``seconds`` in slices, ending early on a stop."""
        end = self.clock() + seconds
        while not self.stopped():
            left = end - self.clock()
            if left <= 0:
                return
            step = min(left, WAIT_SLICE_S)
            if self.conn is not None:
                self.conn.wait(step)
            else:
                time.sleep(step)

    # -- the samples --------------------------------------------------------------------------
    def rows(self) -> Iterator[list[bytes] | NewStream]:
        """One-row chunks (spec §3 CSV lines, without line breaks) as the controller's samples come.

        Ends on a stop, or after ``idle_timeout_s`` without a new sample.

        Raises:
            CalibError: a variable missing or of the wrong type (at the first connection, or a
                reconnection to a controller whose variables changed).
        """
        period = 1.0 / self.link.rate_hz
        last_new = self.clock()
        down_since: float | None = None
        down_counter = self.counter
        backoff = BACKOFF_FIRST_S
        next_poll = self.clock()
        connected = False
        while not self.stopped():
            now = self.clock()
            if self.idle_timeout_s is not None and now - last_new >= self.idle_timeout_s:
                return
            if self.conn is None:
                try:
                    self.conn = self._open()
                except LinkDown as err:
                    if down_since is None:
                        down_since = now
                        say(f"cannot reach {shown(self.link.url)} ({err}); retrying")
                    self._wait(backoff)
                    backoff = min(2 * backoff, BACKOFF_MAX_S)
                    continue
                backoff = BACKOFF_FIRST_S
                if not connected:  # the idle time counts from a link that is up (connecting is no silence)
                    connected, last_new = True, self.clock()
            try:
                self._flush_write()
                values = self._read_whole()
            except LinkDown as err:
                self.close()
                if down_since is None:
                    down_since, down_counter = self.clock(), self.counter
                    say(f"lost the link to {shown(self.link.url)} ({err}); reconnecting")
                continue
            if values is not None:
                row, event = self._new_sample(*values)
                if down_since is not None:
                    self._report_gap(self.clock() - down_since, down_counter, row is not None)
                    down_since = None
                if event is not None:
                    yield event
                if row is not None:
                    last_new = self.clock()
                    self.rows_read += 1
                    yield [row]
            next_poll += period
            now = self.clock()
            if next_poll < now:  # behind: poll at once, and keep the rate from here
                next_poll = now
            else:
                self._wait(next_poll - now)

    def _read_whole(self) -> tuple[float, list[float]] | None:
        """One poll's stamp and values, read again where the stamp moved within the request
        (None: torn :data:`TORN_RETRIES` times running)."""
        assert self.conn is not None
        for _ in range(TORN_RETRIES):
            values = self.conn.read()
            if values[0] == values[-1]:
                return values[0], values[1:-1]
            self.torn += 1
        return None

    def _new_sample(self, stamp: float, values: list[float]) -> tuple[bytes | None, NewStream | None]:
        """The row of ``values`` when they are a new sample (else None), and a new stream's marker."""
        event = None
        t_s = values[self.columns.index("t_s")]
        if self.link.sample is not None:
            counter = _whole(stamp)
            if counter == 0 and not self.counter:  # a counter that has not risen yet: no sample published
                return None, None
            if self.counter is None and counter > 1:
                # joined a running controller: its samples 1 … counter − 1 came before this run
                self.samples_missed += counter - 1
                say(f"joined {shown(self.link.url)} at its sample {counter}: the {counter - 1} before it are missed")
            elif self.counter is not None:
                if counter == self.counter:
                    return None, None
                if counter < self.counter:
                    event = NewStream(f"the controller's sample counter fell from {self.counter} to {counter}")
                elif counter > self.counter + 1:
                    self.samples_missed += counter - self.counter - 1
            self.counter = counter
        elif self.t_s is not None:
            if t_s == self.t_s or (not math.isfinite(t_s) and not math.isfinite(self.t_s)):
                return None, None
            if t_s < self.t_s:
                event = NewStream(f"the controller's time fell from {number(self.t_s)} to {number(t_s)}")
        self.t_s = t_s
        if event is not None:
            say(f"{event.why}: the controller restarted; a new stream")
        return ",".join(map(_field, values)).encode("utf-8"), event

    def _report_gap(self, seconds: float, counter_before: int | None, got_row: bool) -> None:
        missed = ""
        if self.link.sample is not None and counter_before is not None and self.counter is not None:
            lost = max(self.counter - counter_before - (1 if got_row else 0), 0)
            missed = f"; {lost} samples missed (counter {counter_before} → {self.counter})"
        say(f"the link to {shown(self.link.url)} is back after {seconds:.2f} s down{missed}")

    # -- writing back -------------------------------------------------------------------------
    def hand_back(self, result: dict) -> None:
        """Write the result's estimate, σ and samples used into ``[write]``: now, or at the next poll
        where the controller is down or refuses (reported, never fatal)."""
        if not self.link.write:
            return
        self._pending = {key: written(result, key) for key in self.link.write}
        if self.conn is not None:
            try:
                self._flush_write()
            except LinkDown:
                self.close()

    def _flush_write(self) -> None:
        if self._pending is None or self.conn is None:
            return
        try:
            self.conn.write(self._pending)
        except WriteFailed as err:
            if str(err) != self._write_error:
                say(f"writing the estimate into {shown(self.link.url)} failed ({err}); retrying")
            self._write_error = str(err)
            return
        if self._write_error is not None:
            say(f"writing the estimate into {shown(self.link.url)} succeeded again")
        self._pending, self._write_error = None, None

    def finish(self, attempts_s: float) -> bool:
        """Try for up to ``attempts_s`` seconds to write what is pending (the final estimate); True when written."""
        end = self.clock() + attempts_s
        backoff = BACKOFF_FIRST_S
        while self._pending is not None and self.clock() < end:
            try:
                if self.conn is None:
                    self.conn = self._open()
                self._flush_write()
            except LinkDown:
                self.close()
            if self._pending is not None:
                time.sleep(min(backoff, max(end - self.clock(), 0)))
                backoff = min(2 * backoff, BACKOFF_MAX_S)
        return self._pending is None


def _whole(value: float) -> int:
    if not math.isfinite(value) or value != int(value):
        raise CalibError(f"link.sample: the controller's counter holds {value!r}; expected a whole number")
    return int(value)


def _field(value: Any) -> str:
    """A CSV field of a controller's value: a number as the log's writers write it (its double's 15
    significant digits, :func:`~stewart_calib.errors.without_noise`: a float32's every digit)."""
    if isinstance(value, str):
        return '"' + value.replace('"', '""') + '"'
    return repr(without_noise(float(value)))


def write_lengths(link: LinkFile, result: dict) -> dict[str, int]:
    """The length of each ``[write]`` array in ``result`` (a result of the calibration to come).

    Raises:
        CalibError: ``[write]`` names a block the calibration does not identify.
    """
    lengths = {}
    for key in link.write:
        if key in ARRAY_KEYS:
            if key not in ("parameters", "stddev") and result.get(key) is None:
                raise CalibError(f"{shown(link.path)}: write.{key}: this calibration identifies no {key} to hand back")
            lengths[key] = len(written(result, key))  # type: ignore[arg-type]
    return lengths


def written(result: dict, key: str) -> Sequence[float] | float:
    """What ``[write] key`` gets of a spec §5 result: the numbers its file holds (15 significant digits,
    :func:`~stewart_calib.errors.without_noise`), so that the controller holds the result value for value."""
    if key == "parameters":
        return without_noise(result["estimate"])
    if key == "stddev":
        stddev = result["stddev"]
        return without_noise(stddev) if stddev is not None else [math.nan] * len(result["estimate"])
    if key == "samples_used":
        return result["samples_used"]
    block = result.get(key)
    if block is None:
        raise CalibError(f"write.{key}: this calibration identifies no {key} block to hand back")
    return without_noise(block["estimate"])
