"""``stewart-calib track``: the same estimate as calibrate, bad rows, resume, follow, signals, refusals."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from stewart_calib import cli
from stewart_calib.errors import CalibError
from stewart_calib.io import LogRowParser, read_log, read_result, write_log
from stewart_calib.io.logs import ARROW_MIN_ROWS
from stewart_calib.pipelines.track import lines
from stewart_calib.samples import Sample
from stewart_calib.workflows.calibration import run_calibration
from stewart_calib.workflows.online import OnlineCalibrator
from tests.faults import INDETERMINANT, degenerate_sample
from tests.synthetic import NIM_STEWART, ROOT, make_log, nim_stewart, random_error, random_poses, tracked_log

N = 40


def assert_equal_to_rounding(actual, expected) -> None:
    """Equal but for the last bits: track feeds ekf's compiled block recursion, ``calibrate`` in
    memory (or another process) may take the per-sample path or another compilation of it, and with
    fastmath reassociation those sum in different orders (measured ≤ 2e-12 mm on δM, whose σ here is
    ~1e-3 mm)."""
    np.testing.assert_allclose(actual, expected, rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def log():
    return tracked_log(11, N)


@pytest.fixture
def log_path(tmp_path, log):
    path = tmp_path / "log.csv"
    write_log(path, log)
    return path


def _track(capsys, *argv):
    code = cli.main(["track", "--platform", str(NIM_STEWART), *argv])
    return code, capsys.readouterr().err.strip().splitlines()


def _error(path):
    return np.array(read_result(path)["error"])


def test_track_gives_calibrates_estimate_and_keeps_a_checkpoint(tmp_path, log_path, log, capsys):
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    code, err = _track(
        capsys, "--method", "ekf", "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt), "--every", "7"
    )
    assert code == 0 and err == [f"stewart-calib track: wrote {out} (ekf: {N} samples used, 0 skipped, of {N} rows)"]
    estimate = run_calibration(nim_stewart(), log, "ekf").estimate
    assert_equal_to_rounding(_error(out), estimate.error)  # same samples, same filter
    assert read_result(out)["samples_rejected"] == {"count": 0, "by_reason": {}, "first": None}
    assert_equal_to_rounding(OnlineCalibrator.load(ckpt, None).estimate().error, estimate.error)


def test_resume_skips_the_rows_already_read(tmp_path, log_path, capsys):
    whole, part, resumed, ckpt = (tmp_path / name for name in ("whole.json", "part.csv", "resumed.json", "c.npz"))
    assert _track(capsys, "--method", "ekf", "--log", str(log_path), "--out", str(whole))[0] == 0
    part.write_text("".join(log_path.read_text().splitlines(keepends=True)[: 1 + 25]))  # the log as it was at row 26
    assert (
        _track(capsys, "--method", "ekf", "--log", str(part), "--out", str(resumed), "--checkpoint", str(ckpt))[0] == 0
    )
    assert read_result(resumed)["samples_used"] == 25
    assert (
        _track(capsys, "--method", "ekf", "--log", str(log_path), "--out", str(resumed), "--checkpoint", str(ckpt))[0]
        == 0
    )
    assert read_result(resumed)["samples_used"] == N
    np.testing.assert_array_equal(_error(resumed), _error(whole))


def _with_bad_row(log_path, row):
    text = log_path.read_text().splitlines(keepends=True)
    fields = text[row - 1].split(",")
    fields[3] = "nan"  # q3_mm
    text[row - 1] = ",".join(fields)
    log_path.write_text("".join(text))


def test_a_bad_row_stops_track_keeping_the_last_good_checkpoint_and_no_result(tmp_path, log_path, capsys):
    _with_bad_row(log_path, 12)
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    code, err = _track(
        capsys,
        "--method",
        "ekf",
        "--log",
        str(log_path),
        "--out",
        str(out),
        "--checkpoint",
        str(ckpt),
        "--every",
        "1000",
    )
    assert code == 2
    assert err == [f"stewart-calib track: error: {log_path}: row 12: column 'q3_mm': expected a finite number, got nan"]
    assert not out.exists()  # nothing that looks like a final result
    assert OnlineCalibrator.load(ckpt, None).estimate().samples_used == 10  # rows 2..11


def test_resume_after_a_bad_row_stop_reads_that_row_again(tmp_path, log_path, capsys):
    # The user fixes (or chooses to skip) the row that stopped tracking and resumes: that row
    # must be parsed again, not counted as read — otherwise a sample is silently lost.
    _with_bad_row(log_path, 12)
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    assert (
        _track(capsys, "--method", "ekf", "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 2
    )
    code, err = _track(
        capsys,
        "--method",
        "ekf",
        "--log",
        str(log_path),
        "--out",
        str(out),
        "--checkpoint",
        str(ckpt),
        "--skip-bad-rows",
    )
    assert code == 0, err
    result = read_result(out)
    assert (result["samples_used"], result["samples_skipped"]) == (N - 1, 1)


def test_skip_bad_rows_counts_and_goes_on(tmp_path, log_path, capsys):
    _with_bad_row(log_path, 12)
    out = tmp_path / "r.json"
    code, err = _track(
        capsys,
        "--method",
        "isam2",
        "--set",
        "isam2.window_samples=5",
        "--log",
        str(log_path),
        "--out",
        str(out),
        "--skip-bad-rows",
    )
    assert code == 0
    assert (
        err[0] == f"stewart-calib track: skipped bad log rows: 1 of {N} (first: {log_path}: row 12: column 'q3_mm': "
        "expected a finite number, got nan)"
    )
    result = read_result(out)
    assert (result["samples_used"], result["samples_skipped"]) == (N - 1, 1)


def test_a_sample_gtsam_fails_on_is_rejected_and_tracking_goes_on(tmp_path, log_path, capsys, monkeypatch):
    t_bad = float(read_log(log_path).t_s[35])  # as track parses it
    degenerate_sample(monkeypatch, t_bad)
    out = tmp_path / "r.json"
    code, err = _track(
        capsys, "--method", "isam2", "--set", "isam2.window_samples=5", "--log", str(log_path), "--out", str(out)
    )
    assert code == 0
    first = f"sample at t = {t_bad} s: gtsam failed in the iSAM2 update ({INDETERMINANT}"
    assert len(err) == 2 and err[0].startswith(f"stewart-calib track: isam2 rejected samples: 1 of {N} (first: {first}")
    assert err[1] == f"stewart-calib track: wrote {out} (isam2: {N - 1} samples used, 1 skipped, of {N} rows)"
    result = read_result(out)
    assert result["samples_rejected"]["by_reason"] == {"solver failed": 1}
    assert result["samples_rejected"]["first"].startswith(first)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--method", "ls"], "--method: 'ls' is not an online method; expected one of paper-ekf, ekf, isam2"),
        (["--method", "ekf", "--every", "0"], "--every: expected a whole number ≥ 1, got 0"),
        (["--method", "ekf", "--log", "missing.csv"], "missing.csv: log file not found"),
        (["--method", "ekf", "--set", "ekf.gate=1"], "--set: unknown key 'ekf.gate': expected one of gate_probability"),
    ],
)
def test_refusals_are_one_line_and_write_nothing(tmp_path, log_path, capsys, argv, message):
    out = tmp_path / "r.json"
    argv = [a.replace("missing.csv", str(tmp_path / "missing.csv")) for a in argv]
    code, err = _track(capsys, *(["--log", str(log_path)] if "--log" not in argv else []), *argv, "--out", str(out))
    assert (
        code == 2 and len(err) == 1 and err[0].endswith(message.replace("missing.csv", str(tmp_path / "missing.csv")))
    )
    assert list(tmp_path.iterdir()) == [log_path]


def test_a_checkpoint_of_another_method_is_refused(tmp_path, log_path, capsys):
    ckpt = tmp_path / "c.npz"
    assert (
        _track(
            capsys,
            "--method",
            "ekf",
            "--log",
            str(log_path),
            "--out",
            str(tmp_path / "a.json"),
            "--checkpoint",
            str(ckpt),
        )[0]
        == 0
    )
    code, err = _track(
        capsys,
        "--method",
        "paper-ekf",
        "--log",
        str(log_path),
        "--out",
        str(tmp_path / "b.json"),
        "--checkpoint",
        str(ckpt),
    )
    assert code == 2 and err == [
        f"stewart-calib track: error: --checkpoint {ckpt}: written by method 'ekf', not 'paper-ekf'"
    ]
    assert not (tmp_path / "b.json").exists()


def test_lines_of_a_pipe_and_of_a_growing_file(tmp_path):
    read_fd, write_fd = os.pipe()
    os.write(write_fd, b"a,b\n1,2\n3,")
    os.write(write_fd, b"4")
    os.close(write_fd)
    assert list(lines(read_fd, follow=False, idle_timeout_s=None, stopped=lambda: False)) == [b"a,b", b"1,2", b"3,4"]
    os.close(read_fd)

    path = tmp_path / "grow.csv"
    path.write_bytes(b"h\n1\n")

    def grow():
        time.sleep(0.3)
        with open(path, "ab") as f:
            f.write(b"2\n")

    writer = threading.Thread(target=grow)
    writer.start()
    fd = os.open(path, os.O_RDONLY)
    started = time.monotonic()
    assert list(lines(fd, follow=True, idle_timeout_s=0.6, stopped=lambda: False)) == [b"h", b"1", b"2"]
    assert time.monotonic() - started >= 0.3 + 0.6  # it waited for the late row, then for the idle timeout
    os.close(fd)
    writer.join()


def test_sigterm_finishes_with_a_final_estimate_and_checkpoint(tmp_path, log_path):
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
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
            "--log",
            str(log_path),
            "--follow",
            "--every",
            "10",
            "--out",
            str(out),
            "--checkpoint",
            str(ckpt),
        ],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not out.exists() and time.monotonic() < deadline:  # it has read the log and waits for more
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert err.strip().splitlines()[-1].endswith(f"(ekf: {N} samples used, 0 skipped, of {N} rows, stopped by signal)")
    assert read_result(out)["samples_used"] == N
    assert OnlineCalibrator.load(ckpt, None).rows_read == N


def test_blocks_give_calibrates_estimate_whatever_the_writes_and_bad_rows(tmp_path, capsys):
    """Past the start-up (the noise windows), with a glitch the filter gates and a bad row skipped:
    track parses and feeds its rows in blocks, split at every --every row and at the bad row, and
    gives calibrate's estimate of the same rows (to rounding), however split."""
    platform, n = nim_stewart(), 400
    log = tracked_log(12, n)
    log.readings[250, 2] += 5.0  # a glitch 2500 σ off: gated, counted in samples_rejected
    log_path = tmp_path / "log.csv"
    write_log(log_path, log)
    _with_bad_row(log_path, 300)  # skipped: its chunk is parsed row by row
    run = run_calibration(platform, read_log(log_path, platform, skip_bad_rows=True), "ekf")
    estimate, rejected = run.estimate, len(run.rejected)
    assert rejected >= 1
    for every in ("7", "1000"):
        out, ckpt = tmp_path / f"track-{every}.json", tmp_path / f"track-{every}.npz"
        code, err = _track(
            capsys,
            "--method",
            "ekf",
            "--log",
            str(log_path),
            "--out",
            str(out),
            "--checkpoint",
            str(ckpt),
            "--every",
            every,
            "--skip-bad-rows",
        )
        assert code == 0, err
        result = read_result(out)
        assert_equal_to_rounding(result["error"], estimate.error)
        assert_equal_to_rounding(result["stddev"], estimate.stddev)
        assert (result["samples_used"], result["samples_skipped"]) == (n - 1 - rejected, 1 + rejected)
        assert result["samples_rejected"]["count"] == rejected
        saved = OnlineCalibrator.load(ckpt, None)
        assert (saved.rows_read, saved.rows_skipped) == (n, 1)
        assert_equal_to_rounding(saved.estimate().error, estimate.error)


def _log_lines() -> list[str]:
    rng = np.random.default_rng(13)
    log, _ = make_log(
        nim_stewart(),
        random_error(rng, 1.0),
        random_poses(nim_stewart(), ARROW_MIN_ROWS + 2, rng),
        rng,
        reading_sigma_mm=0.002,
        stroke_sigma_mm=0.001,
    )
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "log.csv"
        write_log(path, log)
        return path.read_text().splitlines()


_HEADER, *_PLAIN_ROWS = _log_lines()


@st.composite
def _row_blocks(draw):
    """A block of a real log's rows (enough for pyarrow's path or not), a few fields replaced by
    numbers written other ways or by junk, perhaps a blank line, a CR or a time going back."""
    rows = [line.split(",") for line in _PLAIN_ROWS[: draw(st.sampled_from([3, ARROW_MIN_ROWS + 2]))]]
    for _ in range(draw(st.integers(0, 2))):
        row, column = draw(st.integers(0, len(rows) - 1)), draw(st.integers(0, len(rows[0]) - 1))
        value = float(_PLAIN_ROWS[row].split(",")[column])
        rows[row][column] = draw(
            st.one_of(
                st.sampled_from(
                    [
                        f"{value:.3e}",
                        f" {value}",
                        f"{value}\r",
                        f"+{value}",
                        f"{value:.20f}",
                        str(value).upper(),
                        "1_0",
                        "nan",
                        "inf",
                        "",
                        " ",
                        "0x10",
                        '"1"',
                        "١",
                        "1e999",
                        "-1e3",
                        "9e2",
                    ]
                ),
                st.text(max_size=4),
            )
        )
    lines = [",".join(row) for row in rows]
    if draw(st.booleans()):
        lines.insert(draw(st.integers(0, len(lines))), draw(st.sampled_from(["", " ", "\r", lines[0]])))
    return lines


@settings(max_examples=150, deadline=None)
@given(lines=_row_blocks())
def test_a_block_parses_as_its_rows_one_by_one(lines):
    """LogRowParser.parse_block takes a block only when parse would take every row by itself,
    giving the same samples bit for bit; otherwise it leaves the parser as it was."""
    platform = nim_stewart()
    by_block, one_by_one = LogRowParser("<stdin>", _HEADER, platform), LogRowParser("<stdin>", _HEADER, platform)
    block = by_block.parse_block([line.encode("utf-8", "surrogatepass") for line in lines])
    samples = []
    for row, line in enumerate(lines, start=2):
        try:
            samples.append(one_by_one.parse(line, row))
        except CalibError:
            samples.append("bad")
    if block is None:
        return
    assert all(isinstance(sample, Sample) for sample in samples)  # no blank line, no bad row
    assert len(block) == len(samples)
    for mine, theirs in zip(block, samples, strict=True):
        assert mine.t_s == theirs.t_s
        for name in ("strokes", "readings", "desired_pose"):
            np.testing.assert_array_equal(getattr(mine, name), getattr(theirs, name))
        assert mine.stage == theirs.stage and mine.inputs.keys() == theirs.inputs.keys()
        for name, values in mine.inputs.items():
            np.testing.assert_array_equal(values, theirs.inputs[name])
