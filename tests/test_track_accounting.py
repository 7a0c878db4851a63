"""``stewart-calib track``'s accounting of rows: a resume after a kill, checkpoints that do not
match their estimate or their log, and the checks ``calibrate`` makes of a log."""

from __future__ import annotations

import dataclasses
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import read_result, write_log
from stewart_calib.io.platform_file import load_platform, platform_to_toml
from stewart_calib.pipelines import track
from stewart_calib.workflows.online import OnlineCalibrator, npz_bytes
from tests.synthetic import NIM_STEWART, tracked_log

N = 40
EVERY = 7


@pytest.fixture(scope="module")
def log():
    return tracked_log(11, N)


@pytest.fixture
def log_path(tmp_path, log):
    path = tmp_path / "log.csv"
    write_log(path, log)
    return path


def _track(capsys, *argv: str, method: str = "ekf") -> tuple[int, list[str]]:
    capsys.readouterr()
    code = cli.main(["track", "--platform", str(NIM_STEWART), "--method", method, *argv])
    return code, capsys.readouterr().err.strip().splitlines()


def _checkpoints_of_a_run(log_path: Path, method: str) -> list[bytes]:
    """The checkpoints a track run of ``log_path`` writes, every :data:`EVERY` rows, in order —
    what a run killed (``kill -9``) after any of them leaves on disk. The log is read in one
    block, so each is written while that block is being folded in."""
    calib = OnlineCalibrator(NIM_STEWART, method)
    written: list[bytes] = []
    fd = os.open(log_path, os.O_RDONLY)
    try:
        chunks = track.line_chunks(fd, False, None, lambda: False, str(log_path))
        identity = lambda: track._identity(str(log_path))  # noqa: E731
        track.follow_log(
            calib, chunks, str(log_path), EVERY, lambda: written.append(calib.checkpoint_bytes()), False, identity
        )
    finally:
        os.close(fd)
    return written


@pytest.mark.parametrize("method", ["ekf", "isam2"])
def test_a_resume_after_a_kill_mid_block_reads_the_rest_of_that_block(tmp_path, log_path, capsys, method):
    whole, resumed, ckpt = tmp_path / "whole.json", tmp_path / "resumed.json", tmp_path / "c.npz"
    assert _track(capsys, "--log", str(log_path), "--out", str(whole), "--every", str(EVERY), method=method)[0] == 0
    killed_at = _checkpoints_of_a_run(log_path, method)[0]  # after row 7 of the 40 read as one block
    assert OnlineCalibrator.load(_written(ckpt, killed_at), None).rows_read == EVERY
    code, err = _track(
        capsys,
        "--log",
        str(log_path),
        "--out",
        str(resumed),
        "--checkpoint",
        str(ckpt),
        "--every",
        str(EVERY),
        method=method,
    )
    assert code == 0 and err[-1].endswith(f"of {N} rows)")
    assert read_result(resumed)["samples_used"] == N
    # ekf resumes bit for bit; isam2 rebuilds its graph from the checkpoint's window prior and replay
    # buffer, within its relinearisation threshold of one run (≤ 5e-5 σ measured: track's module doc)
    sigma = np.array(read_result(whole)["stddev"])
    tolerance = 0.0 if method == "ekf" else 1e-4 * sigma
    assert np.all(np.abs(np.array(read_result(resumed)["error"]) - read_result(whole)["error"]) <= tolerance)


def test_two_runs_through_a_symlink_to_one_checkpoint_are_one_run(tmp_path, log_path, capsys):
    """A link to the checkpoint is the checkpoint: its lock is the file's, and the write keeps the link."""
    (tmp_path / "real").mkdir()
    ckpt, link = tmp_path / "real" / "c.npz", tmp_path / "link.npz"
    link.symlink_to(ckpt)
    debris = tmp_path / "real" / ".c.npz.k1ll3d.tmp"  # a killed writer's, beside the file written
    debris.write_bytes(b"half a checkpoint")
    assert _track(capsys, "--log", str(log_path), "--out", str(tmp_path / "a.json"), "--checkpoint", str(link))[0] == 0
    assert link.is_symlink() and OnlineCalibrator.load(ckpt, None).rows_read == N and not debris.exists()
    with track.io.exclusive_lock(ckpt, "--checkpoint", "a test"):
        code, err = _track(capsys, "--log", str(log_path), "--out", str(tmp_path / "b.json"), "--checkpoint", str(link))
    assert code == 2 and len(err) == 1 and "in use (another track run is writing it" in err[0]


def _written(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _edited(ckpt: Path, **changes) -> None:
    """``ckpt`` with some of its arrays replaced."""
    with np.load(ckpt) as npz:
        arrays = {name: npz[name] for name in npz.files}
    arrays.update({name: np.asarray(value) for name, value in changes.items()})
    ckpt.write_bytes(npz_bytes(arrays))


def test_a_checkpoint_whose_counts_its_estimate_does_not_account_for_is_refused(tmp_path, log_path, capsys):
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    assert _track(capsys, "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    _edited(ckpt, rows_read=np.array(10**12))
    code, err = _track(capsys, "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))
    assert code == 2 and err == [
        f"stewart-calib track: error: --checkpoint {ckpt}: does not match its own estimate: array 'rows_read': "
        f"1000000000000 rows read, but its estimate accounts for {N} ({N} used, 0 skipped, 0 dropped, 0 held); "
        "expected the counters of the state saved with them"
    ]


@pytest.mark.parametrize("config_json", ["[]", "null", "1", '"ekf"'])
def test_a_checkpoint_whose_config_is_no_table_is_refused_in_one_line(tmp_path, log_path, capsys, config_json):
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    assert _track(capsys, "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    _edited(ckpt, config_json=np.array(config_json))
    code, err = _track(capsys, "--log", str(log_path), "--out", str(out), "--checkpoint", str(ckpt))
    assert code == 2 and len(err) == 1
    assert err[0].startswith(f"stewart-calib track: error: {ckpt}: corrupt checkpoint: array 'config_json': expected")


def test_a_checkpoint_resumes_on_its_platform_described_anew_but_not_on_another_geometry(tmp_path, log, capsys):
    platform = load_platform(NIM_STEWART)
    renamed = tmp_path / "renamed.toml"
    renamed.write_text(platform_to_toml(dataclasses.replace(platform, name="lab-2", description="moved to hall 2")))
    first, whole = tmp_path / "first.csv", tmp_path / "whole.csv"
    write_log(first, log.select(slice(0, 25)))
    write_log(whole, log)
    out, ckpt = tmp_path / "r.json", tmp_path / "c.npz"
    assert _track(capsys, "--log", str(first), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    capsys.readouterr()
    argv = ["track", "--platform", str(renamed), "--method", "ekf", "--log", str(whole), "--out", str(out)]
    assert cli.main([*argv, "--checkpoint", str(ckpt)]) == 0
    assert read_result(out)["samples_used"] == N and read_result(out)["platform"] == "lab-2"
    moved = dataclasses.replace(
        platform, drive=dataclasses.replace(platform.drive, initial_lengths=platform.drive.initial_lengths + 1.0)
    )
    other = tmp_path / "other.toml"
    other.write_text(platform_to_toml(moved))
    capsys.readouterr()
    argv[2] = str(other)
    assert cli.main([*argv, "--checkpoint", str(ckpt)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].endswith(": its [drive] values differ")


def test_a_log_rewritten_in_place_under_follow_is_named_so(tmp_path, log, capsys):
    """Its first rows kept and later ones changed: read on from where it was, the follower would
    land in the middle of a row and blame the file's content."""
    whole = tmp_path / "whole.csv"
    write_log(whole, log)
    lines = whole.read_bytes().splitlines(keepends=True)
    path = tmp_path / "log.csv"
    path.write_bytes(b"".join(lines[:31]))
    rewritten = b"".join(lines[:21] + [line.replace(b",", b"0,", 1) for line in lines[21:]])  # longer rows

    def rewrite():
        time.sleep(1.0)
        with open(path, "r+b") as file:
            file.write(rewritten)

    writer = threading.Thread(target=rewrite)
    writer.start()
    code, err = _track(capsys, "--log", str(path), "--follow", "--idle-timeout", "3", "--out", str(tmp_path / "r.json"))
    writer.join()
    assert code == 2 and len(err) == 1
    assert err[0].startswith(f"stewart-calib track: error: {path}: the log was rewritten in place while followed")


def test_track_refuses_a_log_with_the_diagnosis_calibrate_makes(tmp_path, log, capsys):
    """Strokes logged in metres: ``calibrate`` names the unit before any solver runs; so does ``track``."""
    path = tmp_path / "metres.csv"
    write_log(path, dataclasses.replace(log, strokes=log.strokes / 1000.0))
    capsys.readouterr()
    assert (
        cli.main(
            [
                "calibrate",
                "--platform",
                str(NIM_STEWART),
                "--method",
                "ekf",
                "--log",
                str(path),
                "--out",
                str(tmp_path / "c.json"),
            ]
        )
        == 2
    )
    calibrate_says = capsys.readouterr().err.strip().splitlines()
    code, err = _track(capsys, "--log", str(path), "--out", str(tmp_path / "r.json"))
    assert code == 2 and len(err) == 1 and "metres" in err[0]
    assert err[0].split("error: ", 1)[1] == calibrate_says[-1].split("error: ", 1)[1]
