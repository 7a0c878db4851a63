"""The poll loop of a controller link (stewart_calib.links.Link) against a scripted connection:
torn reads, counter jumps and falls, a link without a counter, writes refused and retried."""

from __future__ import annotations

import math

import pytest

from stewart_calib.errors import CalibError
from stewart_calib.links import Link, LinkDown, LinkFile, NewStream, WriteFailed

READ = {"t_s": "T", "q1_mm": "Q"}


class Script:
    """A connection whose reads return ``reads`` in turn (a :class:`LinkDown` instance is raised),
    then the last one for ever; time passes only in :meth:`wait`."""

    def __init__(self, reads, refuse_writes: int = 0):
        self.reads, self.now, self.written, self.refuse_writes = list(reads), 0.0, [], refuse_writes
        self.connects = 0

    def clock(self) -> float:
        return self.now

    def connector(self, link):
        self.connects += 1
        return self

    def check(self, reads, stamp, writes, lengths) -> None:
        self.stamp = stamp

    def read(self):
        value = self.reads.pop(0) if len(self.reads) > 1 else self.reads[0]
        if isinstance(value, Exception):
            raise value
        return value

    def write(self, values) -> None:
        if self.refuse_writes:
            self.refuse_writes -= 1
            raise WriteFailed("BadUserAccessDenied")
        self.written.append(values)

    def wait(self, seconds: float) -> None:
        self.now += seconds

    def close(self) -> None:
        pass


def _link(script, sample="N", write=None, record=None):
    spec = LinkFile("L.toml", "opc.tcp://127.0.0.1:4840/", 100.0, sample, READ, write or {})
    return Link(spec, {"parameters": 2}, record, idle_timeout_s=1.0, clock=script.clock, connector=script.connector)


def _rows(link):
    return [item if isinstance(item, NewStream) else item[0].decode() for item in link.rows()]


def test_a_torn_read_is_read_again_and_a_repeated_counter_is_no_new_sample():
    script = Script([[1, 0.1, 5.0, 1], [1, 0.1, 5.0, 1], [2, 0.2, 6.0, 3], [3, 0.3, 7.0, 3]])
    link = _link(script)
    assert _rows(link) == ["0.1,5.0", "0.3,7.0"]
    assert (link.torn, link.samples_missed, link.counter) == (1, 1, 3)  # sample 2 was never read whole


def test_a_jump_counts_the_samples_between_as_missed_and_a_fall_starts_a_new_stream(capsys):
    script = Script([[1, 0.1, 5.0, 1], [4, 0.4, 6.0, 4], [2, 0.0, 7.0, 2], [3, 0.1, 8.0, 3]])
    link = _link(script)
    rows = _rows(link)
    assert rows[:2] == ["0.1,5.0", "0.4,6.0"] and isinstance(rows[2], NewStream) and rows[3:] == ["0.0,7.0", "0.1,8.0"]
    assert link.samples_missed == 2
    assert "the controller's sample counter fell from 4 to 2: the controller restarted; a new stream" in (
        capsys.readouterr().err
    )


def test_without_a_counter_a_sample_is_new_when_its_time_changes():
    script = Script([[0.1, 0.1, 5.0, 0.1], [0.1, 0.1, 5.0, 0.1], [0.2, 0.2, 6.0, 0.2]])
    link = _link(script, sample=None)
    assert _rows(link) == ["0.1,5.0", "0.2,6.0"] and script.stamp == "T"


def test_a_resumed_link_passes_over_the_samples_its_checkpoint_read_and_counts_those_it_missed():
    record = {"link": "opc.tcp://127.0.0.1:4840/", "rows": 7, "counter": 7, "t_s": 0.7, "samples_missed": 1}
    script = Script([[7, 0.7, 5.0, 7], [9, 0.9, 6.0, 9]])
    link = _link(script, record=record)
    assert _rows(link) == ["0.9,6.0"]
    assert (link.rows_read, link.samples_missed) == (8, 2)


def test_a_lost_link_is_retried_and_its_gap_reported(capsys):
    script = Script([[1, 0.1, 5.0, 1], LinkDown("connection reset"), LinkDown("refused"), [5, 0.5, 6.0, 5]])
    link = _link(script)
    assert _rows(link) == ["0.1,5.0", "0.5,6.0"]
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "stewart-calib track: lost the link to opc.tcp://127.0.0.1:4840/ (connection reset); reconnecting"
    assert err[1].startswith("stewart-calib track: the link to opc.tcp://127.0.0.1:4840/ is back after ")
    assert err[1].endswith(" s down; 3 samples missed (counter 1 → 5)")
    assert link.samples_missed == 3 and script.connects == 3


def test_a_refused_write_is_reported_and_retried_at_the_next_poll(capsys):
    script = Script([[1, 0.1, 5.0, 1], [2, 0.2, 6.0, 2]], refuse_writes=2)
    link = _link(script, write={"parameters": "P"})
    rows = link.rows()
    assert next(rows) == [b"0.1,5.0"]
    link.hand_back({"estimate": [1.0, 2.0]})
    assert next(rows) == [b"0.2,6.0"]  # the retry at this poll was refused too: tracking goes on
    assert list(rows) == [] and script.written == [{"parameters": [1.0, 2.0]}]
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "stewart-calib track: writing the estimate into opc.tcp://127.0.0.1:4840/ failed (BadUserAccessDenied); "
        "retrying",
        "stewart-calib track: writing the estimate into opc.tcp://127.0.0.1:4840/ succeeded again",
    ]


def test_a_counter_that_is_no_whole_number_is_refused():
    link = _link(Script([[1.5, 0.1, 5.0, 1.5]]))
    with pytest.raises(CalibError, match=r"link.sample: the controller's counter holds 1.5; expected a whole number"):
        _rows(link)


def test_a_value_that_is_not_finite_reaches_the_log_parser_as_such():
    link = _link(Script([[1, 0.1, math.nan, 1]]))
    assert _rows(link) == ["0.1,nan"]


def test_a_counter_still_at_zero_has_published_no_sample():
    link = _link(Script([[0, 0.0, 0.0, 0], [0, 0.0, 0.0, 0], [1, 0.1, 5.0, 1]]))
    assert _rows(link) == ["0.1,5.0"] and link.samples_missed == 0


def test_joining_a_running_controller_counts_the_samples_before_as_missed(capsys):
    link = _link(Script([[41, 4.1, 5.0, 41], [42, 4.2, 6.0, 42]]))
    assert _rows(link) == ["4.1,5.0", "4.2,6.0"] and link.samples_missed == 40
    assert "joined opc.tcp://127.0.0.1:4840/ at its sample 41: the 40 before it are missed" in capsys.readouterr().err


def test_the_idle_time_counts_from_a_link_that_is_up_not_from_the_start_of_connecting():
    script = Script([[0, 0.0, 0.0, 0], [0, 0.0, 0.0, 0], [1, 0.1, 5.0, 1]])  # the first sample comes later
    slow = script.connector

    def connector(link):
        script.now += 5.0  # a controller slow to answer its first connection: 5 × the idle timeout
        return slow(link)

    spec = LinkFile("L.toml", "opc.tcp://127.0.0.1:4840/", 100.0, "N", READ, {})
    link = Link(spec, {}, None, idle_timeout_s=1.0, clock=script.clock, connector=connector)
    assert _rows(link) == ["0.1,5.0"]
