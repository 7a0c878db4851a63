"""Progress of long work (issue 15): a bar with the rate on a terminal, nothing when piped —
here for ``validate``, which reads and predicts its log a block at a time for it."""

from __future__ import annotations

import io as text_io
import sys

import numpy as np
import pytest

from stewart_calib import io, progress
from stewart_calib.cli import main
from stewart_calib.estimate import Estimate
from stewart_calib.io import logs
from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_error, random_poses


class _Terminal(text_io.StringIO):
    """stderr as a terminal sees it: what is written, and ``isatty()`` true."""

    def isatty(self) -> bool:
        return True


@pytest.fixture(scope="module")
def held_out(tmp_path_factory):
    """A 40-row log of a platform with 0.5 mm errors and a result holding them (half of them, so
    the predictions differ from the readings)."""
    path = tmp_path_factory.mktemp("progress")
    platform = nim_stewart()
    rng = np.random.default_rng(5)
    error = random_error(rng, 0.5)
    log, _ = make_log(platform, error, random_poses(platform, 40, rng), rng)
    io.write_log(path / "log.csv", log)
    io.write_result(path / "r.json", io.result_dict(Estimate(0.5 * error, None, "ls", 40), platform))
    return path


def _validate(path, out: str) -> list[str]:
    return [
        "validate",
        "--platform",
        str(NIM_STEWART),
        "--result",
        str(path / "r.json"),
        "--log",
        str(path / "log.csv"),
        "--out",
        str(path / out),
    ]


def test_validate_is_quiet_when_piped_and_shows_a_bar_on_a_terminal(held_out, monkeypatch, capsys):
    monkeypatch.setattr(progress, "MIN_LOG_ROWS", 10)
    assert main(_validate(held_out, "piped.csv")) == 0
    err = capsys.readouterr().err  # pytest's stderr is no terminal: no bar, only the result's lines
    assert (
        "sample/s" not in err
        and "\r" not in err
        and all(line.startswith("stewart-calib validate: ") for line in err.splitlines())
    )
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(_validate(held_out, "terminal.csv")) == 0
    assert "validate" in terminal.getvalue() and "sample/s" in terminal.getvalue()
    assert (held_out / "terminal.csv").read_text() == (held_out / "piped.csv").read_text()


def test_validate_in_blocks_writes_what_one_block_writes(held_out, monkeypatch):
    assert main(_validate(held_out, "whole.csv")) == 0
    monkeypatch.setattr(logs, "BLOCK_BYTES", 1000)  # a few rows a block
    assert len(list(logs.read_log_blocks(held_out / "log.csv", nim_stewart()))) > 5
    assert main(_validate(held_out, "blocks.csv")) == 0
    assert (held_out / "blocks.csv").read_text() == (held_out / "whole.csv").read_text()
