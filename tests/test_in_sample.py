"""``validate`` on the very log a result was calibrated from says so: calibrate writes the log's SHA-256
(``log_sha256``, of the bytes it read, standard input's too) and validate compares its own log's with it."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest

from stewart_calib import io
from stewart_calib.cli import main
from stewart_calib.io.platform_file import platform_to_toml
from stewart_calib.pipelines.validate import IN_SAMPLE_LINE
from tests.synthetic import ROOT, make_log, nim_stewart, random_error, random_poses


def _log(path, seed: int) -> None:
    platform = nim_stewart()
    poses = random_poses(platform, 60, np.random.default_rng(seed))
    log, _ = make_log(platform, random_error(np.random.default_rng(4)), poses, np.random.default_rng(seed + 1))
    io.write_log(path, log, platform)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A platform file, the log ``ls`` was calibrated from and its result, and another log of the robot."""
    folder = tmp_path_factory.mktemp("in-sample")
    (folder / "p.toml").write_text(platform_to_toml(nim_stewart()))
    _log(folder / "fit.csv", 5)
    _log(folder / "held.csv", 15)
    argv = ["calibrate", "--platform", str(folder / "p.toml"), "--log", str(folder / "fit.csv"), "--method", "ls"]
    assert main([*argv, "--out", str(folder / "r.json")]) == 0
    return folder


def _validate(capsys, folder, log: str, result: str = "r.json", *more: str) -> tuple[list[str], list[str]]:
    capsys.readouterr()
    argv = ["validate", "--platform", str(folder / "p.toml"), "--result", str(folder / result)]
    assert main([*argv, "--log", str(folder / log), "--out", str(folder / "V.csv"), *more]) == 0
    printed = capsys.readouterr()
    return printed.out.splitlines(), printed.err.splitlines()


def test_calibrate_writes_the_sha256_of_the_log_it_read(calibrated, tmp_path):
    digest = hashlib.sha256((calibrated / "fit.csv").read_bytes()).hexdigest()
    assert io.read_result(calibrated / "r.json")["log_sha256"] == digest
    # an online method streams the log a block at a time: the same bytes, the same digest
    argv = ["calibrate", "--platform", str(calibrated / "p.toml"), "--log", str(calibrated / "fit.csv")]
    assert main([*argv, "--method", "ekf", "--out", str(tmp_path / "ekf.json")]) == 0
    assert io.read_result(tmp_path / "ekf.json")["log_sha256"] == digest


def _from_standard_input(calibrated, command: str, method: str, out) -> dict:
    """The result ``command --method method`` writes to ``out`` reading the calibration's log from standard input."""
    argv = [command, "--platform", str(calibrated / "p.toml"), "--log", "-", "--method", method]
    with open(calibrated / "fit.csv", "rb") as log:
        done = subprocess.run(
            [sys.executable, "-m", "stewart_calib", *argv, "--out", str(out)],
            stdin=log,
            capture_output=True,
            cwd=ROOT,
            timeout=300,
        )
    assert done.returncode == 0, done.stderr
    return json.loads(out.read_text())


def test_calibrate_digests_the_bytes_it_reads_from_standard_input(calibrated, tmp_path):
    written = _from_standard_input(calibrated, "calibrate", "ls", tmp_path / "r.json")
    assert written["log_sha256"] == io.read_result(calibrated / "r.json")["log_sha256"]


@pytest.mark.parametrize("more", [(), ("--report", "report")])  # by blocks, and the whole log for the report
def test_validate_on_the_calibrations_own_log_says_it_is_in_sample(calibrated, capsys, more):
    more = tuple(str(calibrated / m) if m == "report" else m for m in more)
    out, err = _validate(capsys, calibrated, "fit.csv", "r.json", *more)
    assert f"stewart-calib validate: {IN_SAMPLE_LINE}" in err
    verdict = out[-1]
    assert verdict.startswith("stewart-calib validate: verdict: ") and "in-sample" in verdict


def test_validate_on_another_log_or_an_older_result_says_nothing_of_it(calibrated, capsys):
    out, err = _validate(capsys, calibrated, "held.csv")
    assert not any("in-sample" in line or "calibration's own" in line for line in out + err)
    older = io.read_result(calibrated / "r.json")
    del older["log_sha256"]
    io.write_result(calibrated / "older.json", older)
    out, err = _validate(capsys, calibrated, "fit.csv", "older.json")
    assert not any("in-sample" in line or "calibration's own" in line for line in out + err)


@pytest.mark.parametrize("ending", ["\n", ""], ids=["line-break", "no-final-line-break"])
def test_track_writes_the_sha256_of_the_log_it_read_and_validate_knows_it(calibrated, tmp_path, capsys, ending):
    # track's final result names its log as calibrate's does, read to its end in lines (a last one without its
    # line break too): validate on that log says it is in-sample, as the online estimate has had every row of it
    text = (calibrated / "fit.csv").read_text(encoding="utf-8").removesuffix("\n") + ending
    (tmp_path / "fit.csv").write_bytes(text.encode("utf-8"))
    argv = ["track", "--platform", str(calibrated / "p.toml"), "--method", "ekf", "--log", str(tmp_path / "fit.csv")]
    assert main([*argv, "--every", "7", "--out", str(tmp_path / "t.json")]) == 0
    written = io.read_result(tmp_path / "t.json")
    assert written["final"] and written["log_sha256"] == hashlib.sha256(text.encode("utf-8")).hexdigest()
    io.write_result(calibrated / "track.json", written)
    (calibrated / "track-fit.csv").write_bytes(text.encode("utf-8"))
    out, err = _validate(capsys, calibrated, "track-fit.csv", "track.json")
    assert f"stewart-calib validate: {IN_SAMPLE_LINE}" in err and "in-sample" in out[-1]
    out, err = _validate(capsys, calibrated, "held.csv", "track.json")
    assert not any("in-sample" in line or "calibration's own" in line for line in out + err)


def test_track_digests_the_lines_it_reads_from_standard_input(calibrated, tmp_path):
    written = _from_standard_input(calibrated, "track", "ekf", tmp_path / "t.json")
    assert written["log_sha256"] == io.read_result(calibrated / "r.json")["log_sha256"]
