"""Faults of ``track`` found by the adversarial pass (issue 14): a signal mid-row, a directory as
``--log``, what a refusal leaves, debris of a killed writer."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from stewart_calib import cli
from stewart_calib.io import read_result, write_log
from stewart_calib.pipelines.track import lines
from stewart_calib.workflows.online import OnlineCalibrator
from tests.synthetic import NIM_STEWART, ROOT, tracked_log
from tests.test_track_cli import assert_equal_to_rounding

N = 30


@pytest.fixture(scope="module")
def log():
    return tracked_log(21, N)


@pytest.fixture
def log_path(tmp_path, log):
    path = tmp_path / "log.csv"
    write_log(path, log)
    return path


def _track(capsys, *argv):
    code = cli.main(["track", "--platform", str(NIM_STEWART), "--method", "ekf", *argv])
    return code, capsys.readouterr().err.strip().splitlines()


def test_a_stop_does_not_hand_on_the_unfinished_tail_as_a_row():
    read_fd, write_fd = os.pipe()
    os.write(write_fd, b"h\n1,2\n3,")  # the writer is in the middle of row 3
    stop = []
    rows = []
    for row in lines(read_fd, follow=False, idle_timeout_s=None, stopped=lambda: bool(stop)):
        rows.append(row)
        stop.append(True)  # a signal arrives while the first chunk is handed on
    assert rows == [b"h", b"1,2"]
    os.close(write_fd)
    os.close(read_fd)


def test_an_idle_timeout_leaves_an_unterminated_tail_unread(tmp_path):
    path = tmp_path / "grow.csv"
    path.write_bytes(b"h\n1\n2")
    fd = os.open(path, os.O_RDONLY)
    assert list(lines(fd, follow=True, idle_timeout_s=0.2, stopped=lambda: False)) == [b"h", b"1"]
    os.close(fd)


def test_sigterm_mid_row_exits_0_and_the_resume_loses_no_row(tmp_path, log_path, log):
    """The process reads a row cut in half from a pipe, is stopped, and resumes from the file."""
    out, ckpt, whole = tmp_path / "r.json", tmp_path / "c.npz", tmp_path / "whole.json"
    text = log_path.read_bytes()
    cut = text.rindex(b"\n", 0, len(text) - 1) + 10  # nine bytes into the last row
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "stewart_calib",
            "track",
            "--platform",
            str(NIM_STEWART),
            "--method",
            "ekf",
            "--every",
            "1",
            "--out",
            str(out),
            "--checkpoint",
            str(ckpt),
            "--skip-bad-rows",
        ],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    proc.stdin.write(text[:cut])
    proc.stdin.flush()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:  # wait until every complete row is read
        if ckpt.exists() and OnlineCalibrator.load(ckpt, None).rows_read == N - 1:
            break
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_skipped"], result["final"]) == (N - 1, 0, True)
    assert (
        cli.main(
            [
                "track",
                "--platform",
                str(NIM_STEWART),
                "--method",
                "ekf",
                "--log",
                str(log_path),
                "--out",
                str(out),
                "--checkpoint",
                str(ckpt),
                "--skip-bad-rows",
            ]
        )
        == 0
    )
    assert (
        cli.main(
            ["track", "--platform", str(NIM_STEWART), "--method", "ekf", "--log", str(log_path), "--out", str(whole)]
        )
        == 0
    )
    resumed = read_result(out)
    assert (resumed["samples_used"], resumed["samples_skipped"]) == (N, 0)
    assert_equal_to_rounding(resumed["error"], read_result(whole)["error"])  # the first part ran in another process


def test_periodic_results_are_marked_not_final(tmp_path, log_path, capsys):
    half = tmp_path / "half.csv"
    half.write_text("".join(log_path.read_text().splitlines(keepends=True)[: 1 + 12]) + "1e9,nan\n")
    out = tmp_path / "r.json"
    code, err = _track(capsys, "--log", str(half), "--out", str(out), "--every", "5")
    assert code == 2 and len(err) == 1 and "row 14" in err[0]
    result = read_result(out)
    assert (result["samples_used"], result["final"]) == (10, False)  # the periodic write at row 10, no more


def test_a_directory_as_log_is_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "r.json"
    code, err = _track(capsys, "--log", str(tmp_path), "--out", str(out))
    assert (code, err) == (
        2,
        [f"stewart-calib track: error: {tmp_path}: is a directory; expected a log file (spec §3)"],
    )
    assert not out.exists()


def test_a_resume_removes_the_temporaries_a_killed_writer_left(tmp_path, log_path, capsys):
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    debris = [tmp_path / ".c.npz.k1ll3d.tmp", tmp_path / ".r.json.x9.tmp"]
    for path in debris:
        path.write_bytes(b"half a file")
    keep = tmp_path / ".other.npz.a.tmp"  # not ours
    keep.write_bytes(b"")
    assert _track(capsys, "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    assert not any(path.exists() for path in debris) and keep.exists()
