"""The catalogue of faulty inputs (issue 30): every case ends in one line — a refusal naming the
cause, exit 2, nothing written and no input touched — or a result that accounts for every row.

:data:`REFUSALS` holds the cases that must be refused: one row per case of the issue and our own
beside them, each run in-process with the directory's files compared before and after. The cases
that must succeed (rotation, resume, row accounting, disk full) have their own tests below.
"""

from __future__ import annotations

import io as io_module
import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from stewart_calib import cli
from stewart_calib.errors import CalibError
from stewart_calib.io import read_result, write_log
from stewart_calib.pipelines.track import follow_log, line_chunks
from stewart_calib.samples import Log, Sample
from stewart_calib.workflows.online import OnlineCalibrator, npz_bytes
from tests.synthetic import NIM_STEWART, ROOT, nim_stewart, tracked_log

N = 40


@pytest.fixture(scope="module")
def log():
    return tracked_log(30, N)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, log) -> Path:
    """``log.csv``, ``P.toml`` and ``R.json`` (its ekf result) once for the module: ~90 cases read
    them, and a calibration each cost more than the refusals themselves."""
    directory = tmp_path_factory.mktemp("calibrated")
    write_log(directory / "log.csv", log)
    (directory / "P.toml").write_text(NIM_STEWART.read_text())
    argv = ["calibrate", "--platform", str(NIM_STEWART), "--log", str(directory / "log.csv"), "--method", "ekf"]
    assert cli.main([*argv, "--out", str(directory / "R.json")]) == 0
    return directory


@pytest.fixture
def work(tmp_path, calibrated):
    """A directory of its own with ``log.csv`` (N rows of nim-stewart), ``P.toml`` (its platform) and
    ``R.json`` (a result of it): copies of :func:`calibrated`'s (R.json names no path), in the order
    they were written there."""
    for name in ("log.csv", "P.toml", "R.json"):
        shutil.copyfile(calibrated / name, tmp_path / name)
    return tmp_path


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {
        str(path.relative_to(directory)): path.read_bytes() if path.is_file() else b"<dir>"
        for path in sorted(directory.rglob("*"))
        if not path.is_fifo()
    }


def _refused(capsys, directory: Path, argv: list[str], message: str) -> None:
    """``stewart-calib ARGV`` exits 2 with one line holding ``message``; ``directory`` is as it was."""
    capsys.readouterr()
    before = _snapshot(directory)
    try:
        code = cli.main(argv)
    except SystemExit as exit:  # argparse's usage errors: one line, exit 2 too
        code = exit.code
    err = capsys.readouterr().err.splitlines()
    assert code == 2, err
    assert len(err) == 1 and message in err[0], err
    assert _snapshot(directory) == before


# --------------------------------------------------------------------------------------- refusals
# (family, argv with {d} for the work directory, what the one line must say)
REFUSALS = [
    # no output over an input (issue: calibrate --out = --log, --platform-out = --platform, --trace = --out)
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/log.csv",
        "--out {d}/log.csv: is the --log input",
    ),
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --platform-out {d}/P.toml",
        "--platform-out {d}/P.toml: is the --platform input",
    ),
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --trace {d}/r.json",
        "--trace {d}/r.json: is also the --out output",
    ),
    (
        "paths",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/c.npz --checkpoint {d}/c.npz",
        "--checkpoint {d}/c.npz: is also the --out output",
    ),
    # ours: every command, by another path or a link
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/./log.csv",
        "is the --log input",
    ),
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/R.json --trace {d}/P.toml",
        "--trace {d}/P.toml: is the --platform input",
    ),
    (
        "paths",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/x.json --rerun {d}/x.json",
        "is also the --out output",
    ),
    (
        "paths",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/log.csv",
        "--out {d}/log.csv: is the --log input",
    ),
    (
        "paths",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --checkpoint {d}/P.toml",
        "--checkpoint {d}/P.toml: is the --platform input",
    ),
    (
        "paths",
        "validate --platform {d}/P.toml --result {d}/R.json --log {d}/log.csv --out {d}/R.json",
        "--out {d}/R.json: is the --result input",
    ),
    (
        "paths",
        "validate --platform {d}/P.toml --result {d}/R.json --log {d}/log.csv --out {d}/link.csv",
        "--out {d}/link.csv: is the --log input",
    ),
    (
        "paths",
        "compensate --platform {d}/P.toml --result {d}/R.json --poses {d}/log.csv --out {d}/log.csv",
        "is the --poses input",
    ),
    (
        "paths",
        "identifiability --platform {d}/P.toml --log {d}/log.csv --json {d}/log.csv",
        "--json {d}/log.csv: is the --log input",
    ),
    ("paths", "plan --platform {d}/P.toml --n 10 --out {d}/P.toml", "--out {d}/P.toml: is the --platform input"),
    (
        "paths",
        "simulate --experiment quick --out {d} --controller frozen --result {d}/log.csv",
        "--out {d}/log.csv: is the --result input",
    ),
    # track: the idle timeout must end
    (
        "track",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --follow --idle-timeout inf",
        "--idle-timeout: expected a finite positive number",
    ),
    (
        "track",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --follow --idle-timeout nan",
        "--idle-timeout: expected a finite positive number",
    ),
    (
        "track",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --idle-timeout -1",
        "--idle-timeout: expected a finite positive number",
    ),
    (
        "track",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --every 0",
        "--every: expected a whole number ≥ 1",
    ),
    (
        "track",
        "track --platform {d}/P.toml --log {d}/header.csv --method ekf --out {d}/r.json",
        "no usable samples (0 rows read",
    ),
    ("track", "track --platform {d}/P.toml --log {d}/empty.csv --method ekf --out {d}/r.json", "no header row"),
    ("track", "track --platform {d}/P.toml --log {d}/missing.csv --method ekf --out {d}/r.json", "log file not found"),
    ("track", "track --platform {d}/P.toml --log {d} --method ekf --out {d}/r.json", "is a directory"),
    ("track", "track --platform {d}/P.toml --log {d}/log.csv --method lm --out {d}/r.json", "is not an online method"),
    ("track", "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/no/r.json", "does not exist"),
    # writes
    (
        "write",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/none/r.json",
        "--out {d}/none/r.json: directory {d}/none does not exist",
    ),
    (
        "write",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --trace {d}/none/t.csv",
        "--trace {d}/none/t.csv: directory {d}/none does not exist",
    ),
    (
        "write",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --report {d}/log.csv",
        "exists and is not a directory",
    ),
    ("write", "simulate --experiment quick --out {d}/log.csv", "--out {d}/log.csv: cannot create the output directory"),
    # sizes that exhaust the machine (found fuzzing the numeric options)
    (
        "nonsense",
        "plan --platform {d}/P.toml --n 10 --candidates 1{zeros} --out {d}/p.csv",
        "argument --candidates: expected",
    ),
    ("nonsense", "plan --platform {d}/P.toml --n 10 --candidates 100000000000 --out {d}/p.csv", "from 1 to 100000"),
    ("nonsense", "sweep --spec {d}/seeds.toml --out {d}/sweep --workers 1{zeros}", "argument --workers: expected"),
    ("nonsense", "sweep --spec {d}/seeds.toml --out {d}/sweep --workers 0", "worker processes from 1 to"),
    # an output that is a FIFO is written through, not replaced (a device alike: as root, --out /dev/null
    # swapped the null device for a file): one no process reads is refused, not waited on for ever
    ("write", "export --platform {d}/P.toml --format json --out {d}/fifo", "{d}/fifo: cannot write (a FIFO no process"),
    # an output folder no file can be made in, whoever runs it: procfs takes no file, and says yes to
    # root's os.access — every command refuses before its work, not only when it writes at the end
    *(
        ("write", argv, f"{option} /proc/{name}: directory /proc is not writable")
        for argv, option, name in (
            ("calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out /proc/r.json", "--out", "r.json"),
            ("{calibrate} --platform-out /proc/c.toml", "--platform-out", "c.toml"),
            ("{calibrate} --report /proc/report", "--report", "report/index.html"),
            ("track --platform {d}/P.toml --log {d}/log.csv --method ekf --out /proc/r.json", "--out", "r.json"),
            (
                "validate --platform {d}/P.toml --result {d}/R.json --log {d}/log.csv --out /proc/v.csv",
                "--out",
                "v.csv",
            ),
            ("identifiability --platform {d}/P.toml --log {d}/log.csv --json /proc/i.json", "--json", "i.json"),
            ("plan --platform {d}/P.toml --n 10 --out /proc/p.csv", "--out", "p.csv"),
            ("export --platform {d}/P.toml --format json --out /proc/e.json", "--out", "e.json"),
            ("simulate --experiment quick --out /proc/sim", "--out", "sim/platform.toml"),
            ("sweep --spec {d}/seeds.toml --out /proc/sweep", "--out", "sweep/results.parquet"),
            ("reproduce --quick --out /proc/out", "--out", "out/results.json"),
            ("import-bag {d}/none.bag --strokes /a --readings /b --out /proc/l.csv", "--out", "l.csv"),
        )
    ),
    # bounded reads: /dev/zero and a FIFO nobody writes to, as any path argument
    (
        "read",
        "calibrate --platform /dev/zero --log {d}/log.csv --method ekf --out {d}/r.json",
        "/dev/zero: a line longer than",
    ),
    (
        "read",
        "calibrate --platform {d}/P.toml --log /dev/zero --method ekf --out {d}/r.json",
        "/dev/zero: a line longer than",
    ),
    (
        "read",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --config /dev/zero",
        "/dev/zero: a line longer than",
    ),
    (
        "read",
        "compensate --platform {d}/P.toml --result /dev/zero --poses {d}/log.csv --out {d}/s.csv",
        "/dev/zero: a line longer than",
    ),
    (
        "read",
        "compensate --platform {d}/P.toml --result {d}/R.json --poses /dev/zero --out {d}/s.csv",
        "/dev/zero: a line longer than",
    ),
    ("read", "identifiability --platform {d}/P.toml --poses /dev/zero", "/dev/zero: a line longer than"),
    (
        "read",
        "track --platform {d}/P.toml --log /dev/zero --method ekf --out {d}/r.json",
        "/dev/zero: a line longer than",
    ),
    (  # read and replaced: refused as an output that is a device (it was read bounded, then would be replaced)
        "read",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --checkpoint /dev/zero",
        "--checkpoint /dev/zero: is a device, not a regular file",
    ),
    ("read", "simulate --experiment /dev/zero --out {d}/sim", "/dev/zero: a line longer than"),
    ("read", "sweep --spec /dev/zero --out {d}/sw", "/dev/zero: a line longer than"),
    (
        "read",
        "calibrate --platform {d}/fifo --log {d}/log.csv --method ekf --out {d}/r.json",
        "{d}/fifo: no data for 0.3 s from this FIFO (no writer?)",
    ),
    (
        "read",
        "calibrate --platform {d}/P.toml --log {d}/fifo --method ekf --out {d}/r.json",
        "{d}/fifo: no data for 0.3 s",
    ),
    (
        "read",
        "validate --platform {d}/P.toml --result {d}/fifo --log {d}/log.csv --out {d}/v.csv",
        "{d}/fifo: no data for 0.3 s",
    ),
    (
        "read",
        "track --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --checkpoint {d}/fifo",
        "--checkpoint {d}/fifo: is a FIFO, not a regular file",
    ),
    (
        "read",
        "calibrate --platform {d}/deep.toml --log {d}/log.csv --method ekf --out {d}/r.json",
        "nested deeper than 32 levels",
    ),
    (
        "read",
        "compensate --platform {d}/P.toml --result {d}/deep.json --poses {d}/log.csv --out {d}/s.csv",
        "nested deeper than 32 levels",
    ),
    (
        "read",
        "compensate --platform {d}/P.toml --result {d}/big_int.json --poses {d}/log.csv --out {d}/s.csv",
        "integer",
    ),
    (
        "read",
        "calibrate --platform {d}/P.toml --log {d}/log.csv --method ekf --out {d}/r.json --config {d}/big_int.toml",
        "integer",
    ),
    (
        "read",
        "{calibrate} --set ekf.gate_probability=1{zeros}",
        "--set",
    ),
    ("read", "simulate --experiment {d}/big_int.toml --out {d}/sim", "an integer of more than 4300 digits"),
    (
        "read",
        "calibrate --platform {d}/P.toml --log {d}/long_header.csv --method ekf --out {d}/r.json",
        "a line longer than 1048576 bytes",
    ),
    (
        "read",
        "track --platform {d}/P.toml --log {d}/long_header.csv --method ekf --out {d}/r.json",
        "a line longer than 1048576 bytes",
    ),
    # sweeps: absurd sizes refused by the plan (the studies issue plans them)
    ("sweep", "sweep --spec {d}/seeds.toml --out {d}/sw", "is more than the limit of 100,000; shrink the grid"),
    ("sweep", "sweep --spec {d}/samples.toml --out {d}/sw", "grid.samples"),
    ("sweep", "sweep --spec {d}/grid.toml --out {d}/sw", "is more than the limit of 100,000; shrink the grid"),
    ("sweep", "sweep --spec {d}/first_seed.toml --out {d}/sw", "key 'first_seed'"),
    # nonsense accepted before (issue), and ours beside
    (
        "nonsense",
        "compensate --platform {d}/P.toml --result {d}/k_minus_2.json --poses {d}/log.csv --out {d}/s.csv",
        "key 'stroke_scale.estimate': expected scale errors k_i within ±0.5",
    ),
    (
        "nonsense",
        "calibrate --platform {d}/P.toml --log {d}/t_1e308.csv --method ekf --out {d}/r.json",
        "row 6: column 't_s': expected a time within ±1e12 s, got 1e+308",
    ),
    (
        "nonsense",
        "calibrate --platform {d}/P.toml --log {d}/underscore.csv --method ekf --out {d}/r.json",
        "row 4: column 'q1_mm': expected a number, got '2_12.97'",
    ),
    (
        "nonsense",
        "track --platform {d}/P.toml --log {d}/underscore.csv --method ekf --out {d}/r.json",
        "row 4: column 'q1_mm': expected a number, got '2_12.97'",
    ),
    (
        "nonsense",
        "identifiability --platform {d}/P.toml --poses {d}/one_zero.csv",
        "column 'x_mm': expected a number, got '1_0'",
    ),
    (
        "nonsense",
        "identifiability --platform {d}/P.toml --poses {d}/nan_poses.csv",
        "column 'x_mm': expected a finite number, got nan",
    ),
    (
        "nonsense",
        "{calibrate} --set noise.reading_sigma_mm=1e-300",
        "key 'noise.reading_sigma_mm': expected a σ within [1e-09, 1000] mm",
    ),
    (
        "nonsense",
        "{calibrate} --set noise.stroke_sigma_mm=1e300",
        "key 'noise.stroke_sigma_mm': expected a σ within",
    ),
    (
        "nonsense",
        "calibrate --platform {d}/sigma.toml --log {d}/log.csv --method ekf --out {d}/r.json",
        "key 'instrument.position_sigma_mm': expected a σ within",
    ),
    (
        "nonsense",
        "plan --platform {d}/zero_workspace.toml --n 10 --out {d}/p.csv",
        "key 'workspace': a box of zero size holds one pose only",
    ),
    (
        "nonsense",
        "plan --platform {d}/P.toml --n 10 --out {d}/p.csv --seed -1",
        "argument --seed: expected a whole number ≥ 0",
    ),
    (
        "nonsense",
        "simulate --experiment {d}/reach.toml --out {d}/sim",
        "samples need strokes outside the platform's drive.stroke_range_mm [0, 90]",
    ),
    (
        "nonsense",
        "calibrate --platform {d}/k_platform.toml --log {d}/log.csv --method ekf --out {d}/r.json",
        "key 'drive.stroke_scale': expected 6 scale errors k_i within ±0.5",
    ),
    (
        "nonsense",
        "import-bag {d}/none.bag --strokes /joints --readings /joints --out {d}/l.csv",
        "--readings /joints: the same topic as --strokes",
    ),
]

#: the files :data:`REFUSALS` name beside the log, platform and result
CRAFTED = {
    "header.csv": lambda d: (d / "log.csv").read_text().splitlines()[0] + "\n",
    "empty.csv": lambda d: "",
    "deep.toml": lambda d: "a = " + "[" * 100 + "]" * 100 + "\n",
    "deep.json": lambda d: "[" * 50000 + "]" * 50000,
    "big_int.json": lambda d: '{"format": 1' + "0" * 5000 + "}",
    "big_int.toml": lambda d: "seed = 1" + "0" * 5000 + "\n",
    "long_header.csv": lambda d: "t_s" + ",x" * (1 << 20) + "\n1\n",
    "seeds.toml": lambda d: 'name = "s"\nmethods = ["ekf"]\nseeds = 1000000000\n',
    "samples.toml": lambda d: 'name = "s"\nmethods = ["ekf"]\nseeds = 1\n[grid]\nsamples = 100000000000\n',
    "grid.toml": lambda d: (
        'name = "s"\nmethods = ["ekf"]\nseeds = 1\n[grid]\nsamples = ['
        + ", ".join(str(k) for k in range(1, 1001))
        + "]\nrate_hz = ["
        + ", ".join(str(k) for k in range(1, 1001))
        + "]\n"
    ),
    "first_seed.toml": lambda d: f'name = "s"\nmethods = ["ekf"]\nseeds = 2\nfirst_seed = {2**63 - 1}\n',
    "k_minus_2.json": lambda d: json.dumps(
        {
            **json.loads((d / "R.json").read_text()),
            "stroke_scale": {"names": [f"k{i}" for i in range(1, 7)], "estimate": [-2.0] + [0.0] * 5, "stddev": None},
        }
    ),
    "t_1e308.csv": lambda d: _with_field(d, 4, 0, "1e308"),
    "underscore.csv": lambda d: _with_field(d, 2, 1, "2_12.97"),
    "one_zero.csv": lambda d: "x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n1_0,0,1000,0,0,0\n",
    "nan_poses.csv": lambda d: "x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\nnan,0,1000,0,0,0\n",
    "sigma.toml": lambda d: (d / "P.toml").read_text() + '\n[instrument]\nkind = "pose"\nposition_sigma_mm = 1e-300\n',
    "zero_workspace.toml": lambda d: re.sub(
        r"(translation_limit_mm|rotation_limit_deg) = [^#\n]*", r"\1 = 0.0 ", (d / "P.toml").read_text()
    ),
    "reach.toml": lambda d: (
        (ROOT / "configs" / "experiments" / "quick.toml").read_text().replace('"nim-stewart"', '"hobby-hexapod"')
    ),
    "k_platform.toml": lambda d: (
        (d / "P.toml").read_text().replace("\n[drive]\n", "\n[drive]\nstroke_scale = [-2.0, 0, 0, 0, 0, 0]\n")
    ),
}


def _with_field(directory: Path, row: int, column: int, value: str) -> str:
    """The log of ``directory`` with field ``column`` of data row ``row`` (0-based) set to ``value``."""
    lines = (directory / "log.csv").read_text().splitlines()
    fields = lines[1 + row].split(",")
    fields[column] = value
    lines[1 + row] = ",".join(fields)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    "family, argv, message", REFUSALS, ids=[f"{family}-{k}" for k, (family, *_) in enumerate(REFUSALS)]
)
def test_refused_in_one_line_with_nothing_written(work, capsys, monkeypatch, family, argv, message):
    for name, text in CRAFTED.items():
        if name in argv:
            (work / name).write_text(text(work))
    os.link(work / "log.csv", work / "link.csv")
    os.mkfifo(work / "fifo")
    monkeypatch.setattr("stewart_calib.inputs.FIRST_DATA_S", 0.3)
    calibrate = f"calibrate --platform {work}/P.toml --log {work}/log.csv --method ekf --out {work}/r.json"
    _refused(capsys, work, argv.format(d=work, zeros="0" * 5000, calibrate=calibrate).split(), message.format(d=work))


# ------------------------------------------------------------------------------- track loses nothing


def _track(capsys, *argv: str) -> tuple[int, list[str]]:
    capsys.readouterr()
    code = cli.main(["track", "--platform", str(NIM_STEWART), "--method", "ekf", *argv])
    return code, capsys.readouterr().err.splitlines()


def test_the_idle_timer_runs_only_while_the_file_has_nothing_unread(tmp_path, monkeypatch):
    """The caller takes longer over each chunk than the idle timeout: every row is still read."""
    path = tmp_path / "log.csv"
    path.write_bytes(b"h\n" + b"".join(b"%d\n" % k for k in range(50)))
    monkeypatch.setattr("stewart_calib.pipelines.track.READ_BYTES", 16)  # many reads
    fd = os.open(path, os.O_RDONLY)
    rows = []
    for chunk in line_chunks(fd, follow=True, idle_timeout_s=0.05, stopped=lambda: False):
        rows += chunk
        time.sleep(0.06)  # slower than the timeout
    os.close(fd)
    assert rows == [b"h"] + [b"%d" % k for k in range(50)]


def test_a_follower_reads_a_replaced_and_a_truncated_file_from_their_start(tmp_path):
    path = tmp_path / "grow.csv"
    path.write_bytes(b"h\n1\n2\n")
    fd = os.open(path, os.O_RDONLY)
    events: list = []

    def rotate():
        time.sleep(0.3)
        os.rename(path, tmp_path / "grow.csv.1")
        path.write_bytes(b"h\n3\n4\n")
        time.sleep(0.4)
        path.write_bytes(b"")  # copy-truncate
        time.sleep(0.3)
        path.write_bytes(b"5\n")

    writer = threading.Thread(target=rotate)
    writer.start()
    for chunk in line_chunks(fd, True, 1.0, lambda: False, str(path)):
        events += [getattr(chunk, "why", None)] if not chunk else chunk
    writer.join()
    os.close(fd)
    assert events == [b"h", b"1", b"2", "replaced", b"h", b"3", b"4", "truncated", b"5"]


def test_track_follows_a_rotation_and_counts_every_row(tmp_path, log, capsys):
    first, second = tmp_path / "a.csv", tmp_path / "b.csv"
    write_log(first, log.select(slice(0, 20)))
    write_log(second, log.select(slice(20, N)))
    path, out = tmp_path / "log.csv", tmp_path / "r.json"
    os.link(first, path)

    def rotate():
        time.sleep(1.0)
        os.replace(second, path)

    writer = threading.Thread(target=rotate)
    writer.start()
    code, err = _track(capsys, "--log", str(path), "--follow", "--idle-timeout", "2", "--out", str(out))
    writer.join()
    assert (
        code == 0
        and err[0] == f"stewart-calib track: {path} was replaced after 20 rows; reading the new file from its start"
    )
    assert err[-1].endswith(f"of {N} rows)")
    assert read_result(out)["samples_used"] == N


def test_resuming_on_another_log_is_refused_naming_both_or_read_from_its_start(tmp_path, log, capsys):
    first, second, out, ckpt = tmp_path / "a.csv", tmp_path / "b.csv", tmp_path / "r.json", tmp_path / "c.npz"
    write_log(first, log.select(slice(0, 20)))
    write_log(second, log.select(slice(20, N)))  # the next rows, as after a rotation
    assert _track(capsys, "--log", str(first), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    saved = ckpt.read_bytes()
    code, err = _track(capsys, "--log", str(second), "--out", str(out), "--checkpoint", str(ckpt))
    assert code == 2 and err == [
        f"stewart-calib track: error: {second}: not the log the checkpoint read ({first}, 20 rows; its first rows "
        f"differ); feed that log from its start, or give --new-log to read {second} from its start"
    ]
    assert ckpt.read_bytes() == saved
    code, err = _track(capsys, "--log", str(second), "--out", str(out), "--checkpoint", str(ckpt), "--new-log")
    assert code == 0 and "reading it from its start (--new-log)" in err[0]
    assert read_result(out)["samples_used"] == N


def test_the_same_log_replayed_on_stdin_resumes(tmp_path, log, capsys, monkeypatch):
    path, out, ckpt = tmp_path / "log.csv", tmp_path / "r.json", tmp_path / "c.npz"
    write_log(path, log.select(slice(0, 25)))
    assert _track(capsys, "--log", str(path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    write_log(path, log)
    read, write = os.pipe()
    os.write(write, path.read_bytes())
    os.close(write)
    monkeypatch.setattr(sys, "stdin", os.fdopen(read))
    code, err = _track(capsys, "--out", str(out), "--checkpoint", str(ckpt))
    assert code == 0 and err[-1].endswith(f"of {N} rows)")
    assert read_result(out)["samples_used"] == N


def test_a_log_shorter_than_the_checkpoint_read_is_refused(tmp_path, log, capsys):
    path, out, ckpt = tmp_path / "log.csv", tmp_path / "r.json", tmp_path / "c.npz"
    write_log(path, log)
    assert _track(capsys, "--log", str(path), "--out", str(out), "--checkpoint", str(ckpt))[0] == 0
    write_log(path, log.select(slice(0, 30)))
    code, err = _track(capsys, "--log", str(path), "--out", str(out), "--checkpoint", str(ckpt))
    assert code == 2 and err == [
        f"stewart-calib track: error: {path}: ended after 30 rows, before the {N} rows the checkpoint had read "
        "of it; feed that log from its start"
    ]


def test_a_second_track_on_one_checkpoint_is_refused(tmp_path):
    """One run holds the lock (it waits on a FIFO for its log); the second is refused at once."""
    fifo, ckpt = tmp_path / "log.fifo", tmp_path / "c.npz"
    os.mkfifo(fifo)
    argv = [sys.executable, "-m", "stewart_calib", "track", "--platform", str(NIM_STEWART), "--method", "ekf"]
    first = subprocess.Popen(
        [*argv, "--log", str(fifo), "--out", str(tmp_path / "a.json"), "--checkpoint", str(ckpt)],
        cwd=ROOT,
        stderr=subprocess.PIPE,
    )
    lock = tmp_path / ".c.npz.lock"
    deadline = time.monotonic() + 60
    while not lock.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    second = subprocess.run(
        [*argv, "--log", str(fifo), "--out", str(tmp_path / "b.json"), "--checkpoint", str(ckpt)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    first.send_signal(signal.SIGTERM)
    first.communicate(timeout=60)
    assert second.returncode == 2 and second.stderr.splitlines() == [
        f"stewart-calib track: error: --checkpoint {ckpt}: in use (another track run is writing it; "
        f"its lock {lock} is held)"
    ]
    assert not (tmp_path / "b.json").exists() and not lock.exists()


@pytest.mark.parametrize("bad", ["nan", "", "1,2"])
@pytest.mark.parametrize("where", [0, 1, N - 1])
def test_track_takes_a_bad_row_anywhere_with_skip_bad_rows(tmp_path, log, capsys, bad, where):
    path, out = tmp_path / "log.csv", tmp_path / "r.json"
    write_log(path, log)
    lines = path.read_text().splitlines()
    fields = lines[1 + where].split(",")
    fields[1] = bad
    lines[1 + where] = ",".join(fields) if bad != "1,2" else "1,2"
    lines.insert(1 + where, ",".join(fields))  # and twice in a row
    path.write_text("\n".join(lines) + "\n")
    code, err = _track(capsys, "--log", str(path), "--out", str(out), "--skip-bad-rows")
    assert code == 0 and err[-1].endswith(f"of {N + 1} rows)")
    result = read_result(out)
    assert result["samples_used"] + result["samples_skipped"] == N + 1


# ------------------------------------------------------------------------------------ row accounting


def _accounted(result: dict, rows: int) -> None:
    recovery = result.get("recovery") or {}
    total = (
        result["samples_used"]
        + result["samples_skipped"]
        + recovery.get("samples_dropped", 0)
        + result.get("samples_held", 0)
    )
    assert total == rows, result
    # the refused are those not taken back in: the count the skipped hold (no bad rows here), the gated less
    # the readmitted by reason, and each taken back counted once, among the readmitted
    readmitted = recovery.get("samples_readmitted", 0) + (result.get("payload_change") or {}).get(
        "samples_readmitted", 0
    )
    rejected = result["samples_rejected"]
    assert rejected["count"] == result["samples_skipped"] == sum(rejected["by_reason"].values()), result
    assert rejected.get("readmitted", 0) == readmitted


@pytest.mark.parametrize("method", ["ekf", "isam2"])
def test_a_lock_out_recovery_accounts_for_every_row(tmp_path, capsys, method):
    """The quick experiment's log, where ekf and isam2 recover from a lock-out (issue 30: 34 rows unmentioned).
    The platform is taken rigid: the lock-out comes from the load step the rigid model cannot follow (with the
    [elastic] that simulate now writes, the compliance predicts the step and nothing locks out)."""
    import dataclasses

    from stewart_calib.io.platform_file import load_platform, platform_to_toml

    sim = tmp_path / "sim"
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(sim)]) == 0
    rigid = dataclasses.replace(load_platform(sim / "platform.toml"), elastic=None)
    (sim / "platform.toml").write_text(platform_to_toml(rigid), encoding="utf-8")
    out = tmp_path / "r.json"
    capsys.readouterr()
    assert (
        cli.main(
            [
                "calibrate",
                "--platform",
                str(sim / "platform.toml"),
                "--log",
                str(sim / "log.csv"),
                "--method",
                method,
                "--out",
                str(out),
            ]
        )
        == 0
    )
    *printed, line, verdict = capsys.readouterr().err.splitlines()  # calibrate ends with its verdict
    result = read_result(out)
    assert verdict.startswith("stewart-calib calibrate: verdict: ")
    assert result["recovery"]["count"] >= 1 and "lock-out recover" in line and line.endswith("of 120 rows)")
    _accounted(result, 120)
    # every refusal of this log is taken back by a recovery: none is printed or written as rejected
    assert result["recovery"]["samples_readmitted"] > 0 and result["samples_rejected"]["count"] == 0
    assert f"took back {result['recovery']['samples_readmitted']} it had refused" in line
    assert not any("rejected samples" in text for text in printed)
    if method == "ekf":
        assert _track(capsys, "--log", str(sim / "log.csv"), "--out", str(out))[0] == 0
        _accounted(read_result(out), 120)


def test_the_registration_replay_counts_the_samples_it_refuses(tmp_path, capsys):
    """paper-ekf on the hobby motion-capture example: every row used, refused or held."""
    import csv

    from scipy.spatial.transform import Rotation

    raw = np.genfromtxt(ROOT / "examples" / "hobby-mocap" / "fit_raw.csv", delimiter=",", names=True)
    yaw, pitch, roll = (
        Rotation.from_quat(np.column_stack([raw["qx"], raw["qy"], raw["qz"], raw["qw"]]))
        .as_euler("ZYX", degrees=True)
        .T
    )
    columns = {
        "t_s": raw["time_s"],
        **{f"q{i}_mm": raw[f"enc{i}"] * 8.0 / 4096 for i in range(1, 7)},
        "mx_mm": raw["x_m"] * 1000.0,
        "my_mm": raw["y_m"] * 1000.0,
        "mz_mm": raw["z_m"] * 1000.0,
        "mroll_deg": roll,
        "mpitch_deg": pitch,
        "myaw_deg": yaw,
    }
    path, out = tmp_path / "fit.csv", tmp_path / "r.json"
    with open(path, "w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(columns)
        writer.writerows(zip(*columns.values(), strict=True))
    assert (
        cli.main(
            ["calibrate", "--platform", "hobby-hexapod", "--log", str(path), "--method", "paper-ekf", "--out", str(out)]
        )
        == 0
    )
    _accounted(read_result(out), len(raw))


# ----------------------------------------------------------------------------------- write errors


def _limited(limit_bytes: int):
    def start():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return start


def test_simulate_on_a_full_disk_leaves_no_folder(tmp_path):
    """A file-size limit fails the writes mid-run as a full disk does."""
    out = tmp_path / "sim" / "deep"
    proc = subprocess.run(
        [sys.executable, "-m", "stewart_calib", "simulate", "--experiment", "quick", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        preexec_fn=_limited(20_000),
        timeout=120,
    )
    assert proc.returncode == 2 and proc.stderr.splitlines() == [
        f"stewart-calib simulate: error: {out}: cannot write (File too large)"
    ]
    assert list(tmp_path.iterdir()) == []


def test_calibrate_on_a_full_disk_writes_nothing(tmp_path, log):
    path = tmp_path / "log.csv"
    write_log(path, log)
    before = _snapshot(tmp_path)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "stewart_calib",
            "calibrate",
            "--platform",
            str(NIM_STEWART),
            "--log",
            str(path),
            "--method",
            "ekf",
            "--out",
            str(tmp_path / "r.json"),
            "--trace",
            str(tmp_path / "t.csv"),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        preexec_fn=_limited(len(path.read_bytes()) + 1000),
        timeout=120,
    )
    assert proc.returncode == 2 and len(proc.stderr.splitlines()) == 1 and "File too large" in proc.stderr
    assert _snapshot(tmp_path) == before


# ------------------------------------------------------------------------------- streams and parsing


@pytest.mark.parametrize("command", ["calibrate", "identifiability"])
def test_a_log_from_a_fifo_is_read_once_without_seeking(tmp_path, log, capsys, command):
    path, fifo, out = tmp_path / "log.csv", tmp_path / "log.fifo", tmp_path / "r.json"
    write_log(path, log)
    os.mkfifo(fifo)
    writer = threading.Thread(target=lambda: fifo.write_bytes(path.read_bytes()))
    writer.start()
    argv = ["--platform", str(NIM_STEWART), "--log", str(fifo)]
    argv += ["--method", "ekf", "--out", str(out)] if command == "calibrate" else ["--json", str(out)]
    assert cli.main([command, *argv]) == 0
    writer.join()
    assert out.exists()


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    faults=st.lists(
        st.tuples(st.integers(0, 11), st.sampled_from(["nan", "", "cut", "text", "blank"])), min_size=1, max_size=5
    )
)
def test_the_stream_parser_takes_bad_rows_anywhere(log, faults):
    """NaN, empty, truncated or text rows at any position (the first included), alone or in runs:
    with --skip-bad-rows every row is used or counted as skipped; nothing raises."""
    text = log.select(slice(0, 12))
    lines = [line.encode() for line in _log_lines(text)]
    header, rows = lines[0], lines[1:]
    bad = 0
    for where, kind in sorted(faults, reverse=True):
        fields = rows[where].split(b",")
        broken = {
            "nan": b",".join([fields[0], b"nan", *fields[2:]]),
            "": b",".join([fields[0], b"", *fields[2:]]),
            "cut": rows[where][: len(rows[where]) // 2],
            "text": b",".join([fields[0], b"abc", *fields[2:]]),
            "blank": b"",
        }[kind]
        rows.insert(where, broken)
        bad += kind != "blank"
    calib = OnlineCalibrator(nim_stewart(), "ekf")
    chunks = iter([[header, *rows[:5]], rows[5:9], rows[9:]])
    feed = follow_log(calib, chunks, "<test>", 4, lambda: None, skip_bad_rows=True)
    assert (calib.rows_read, calib.rows_skipped) == (12 + bad, bad)
    assert feed.data_rows == 12 + bad


def _log_lines(log) -> list[str]:
    from stewart_calib.io import log_text

    return log_text(log).splitlines()


def test_header_only_stdin_is_refused_in_one_line(tmp_path, log, capsys, monkeypatch):
    read, write = os.pipe()
    os.write(write, _log_lines(log)[0].encode() + b"\n")
    os.close(write)
    monkeypatch.setattr(sys, "stdin", os.fdopen(read))
    code, err = _track(capsys, "--out", str(tmp_path / "r.json"))
    assert code == 2 and err == [
        "stewart-calib track: error: <stdin>: no usable samples (0 rows read, 0 skipped, 0 rejected)"
    ]
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------- checkpoints


@pytest.fixture(scope="module")
def checkpoint_arrays(log, tmp_path_factory):
    calib = OnlineCalibrator(nim_stewart(), "ekf")
    calib.update_block(log)
    path = tmp_path_factory.mktemp("ckpt") / "c.npz"
    calib.save(path)
    with np.load(path) as npz:
        return {name: npz[name] for name in npz.files}


def _negative(arrays):
    arrays["state/robust/filter/P"] = -arrays["state/robust/filter/P"]


def _asymmetric(arrays):
    arrays["state/robust/filter/P"] = arrays["state/robust/filter/P"] + np.triu(np.ones((42, 42)), 1)


def _nan_noise(arrays):
    arrays["state/robust/noise"] = np.array([np.nan, 1.0])


def _far_time(arrays):
    arrays["state/robust/filter/t_s"] = np.float64(1e18)


def _nan_walk(arrays):
    arrays["state/robust/filter/Q"] = np.full((42, 42), np.nan)


@pytest.mark.parametrize(
    "corrupt, message",
    [
        (_negative, "key 'P': expected a positive semi-definite covariance"),
        (_asymmetric, "key 'P': expected a symmetric covariance"),
        (_nan_noise, "key 'noise': expected a finite positive noise scale"),
        (_far_time, "key 't_s': 1e+18 s is no time of a log"),
        (_nan_walk, "key 'Q': expected a finite covariance"),
    ],
)
def test_a_well_formed_but_corrupt_checkpoint_state_is_refused(tmp_path, capsys, checkpoint_arrays, corrupt, message):
    arrays = dict(checkpoint_arrays)
    corrupt(arrays)
    path = tmp_path / "c.npz"
    path.write_bytes(npz_bytes(arrays))
    log_path = tmp_path / "log.csv"
    log_path.write_text("t_s\n")
    argv = f"track --platform {NIM_STEWART} --method ekf --log {log_path} --out {tmp_path}/r.json --checkpoint {path}"
    _refused(capsys, tmp_path, argv.split(), f"{path}: corrupt checkpoint: estimator state: {message}")


def _member(name: str, header_shape: tuple, data: bytes) -> bytes:
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    header["shape"] = header_shape
    buffer = io_module.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue() + data


@pytest.mark.parametrize(
    "member, message",
    [
        (lambda: _member("x", (10**6, 10**6), b"\0" * 8), "declares a float64 array of shape (1000000, 1000000)"),
        (lambda: None, "unpacks to 314572800 bytes; too large"),
    ],
)
def test_a_checkpoint_member_is_bounded_before_anything_is_allocated(
    tmp_path, capsys, checkpoint_arrays, member, message
):
    path = tmp_path / "c.npz"
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        for name, array in checkpoint_arrays.items():
            buffer = io_module.BytesIO()
            np.lib.format.write_array(buffer, array)
            archive.writestr(f"{name}.npy", buffer.getvalue())
        data = member()
        if data is None:  # 300 MB of zeros deflate to 300 kB
            with archive.open("big.npy", "w", force_zip64=True) as file:
                for _ in range(300):
                    file.write(bytes(1 << 20))
        else:
            archive.writestr("huge.npy", data)
    with pytest.raises(CalibError, match=re.escape(f"{path}: not a readable checkpoint (") + ".*" + re.escape(message)):
        OnlineCalibrator.load(path, None)


def test_load_takes_the_platform_and_refuses_another_robots_checkpoint(tmp_path, log):
    path = tmp_path / "c.npz"
    calib = OnlineCalibrator(NIM_STEWART, "ekf", "paper")  # a path and a shipped config name
    calib.update_block(log)
    calib.save(path)
    assert OnlineCalibrator.load(path, "nim-stewart").rows_read == 0
    with pytest.raises(
        CalibError, match=f"^{re.escape(str(path))}: written for platform 'nim-stewart', not for 'hobby-hexapod'"
    ):
        OnlineCalibrator.load(path, "hobby-hexapod")
    with pytest.raises(TypeError):
        OnlineCalibrator.load(path)  # the platform is not optional: the README's pattern passes it


@pytest.mark.parametrize(
    "bad",
    [
        lambda log: Sample(0.0, log.strokes[0] + 1j, log.readings[0]),
        lambda log: Sample(0.0, log.strokes[0][:5], log.readings[0]),
        lambda log: Sample(0.0, "strokes", log.readings[0]),
        lambda log: Log(log.t_s[:3], log.strokes[:3], log.readings[:2]),
        lambda log: Log(log.t_s[:3], log.strokes[:3], log.readings[:3].astype(complex)),
        lambda log: Log(log.t_s[:3], log.strokes[:3, :5], log.readings[:3]),
    ],
)
def test_the_api_refuses_malformed_samples_before_counting_anything(log, bad):
    calib = OnlineCalibrator(nim_stewart(), "ekf")
    sample = bad(log)
    with pytest.raises(CalibError, match=r"^samples: "):
        (calib.update_block if isinstance(sample, Log) else calib.update)(sample)
    assert (calib.rejections.count, calib.estimate().samples_used) == (0, 0)


# ----------------------------------------------------------------------------------------- security


def test_the_local_dask_cluster_listens_on_the_loopback_only(monkeypatch):
    """Scheduler, workers and dashboard take no authentication: never on all interfaces."""
    import distributed

    from stewart_calib.sweep.runner import connect

    made = {}
    monkeypatch.setattr(distributed, "LocalCluster", lambda **kwargs: made.update(kwargs) or "cluster")
    monkeypatch.setattr(distributed, "Client", lambda cluster, **kwargs: cluster)
    assert connect(None, 1) == "cluster"
    assert made["host"] == "127.0.0.1" and made["dashboard_address"].startswith("127.0.0.1:")


NAMES = [
    "bell\u0007",
    "two\nFAKE: all good",
    "esc\u001b[31mred",
    "osc\u001b]0;title\u0007",
    'quote"back\\slash',
    "del\u007f",
]


@pytest.mark.parametrize("name", NAMES)
def test_a_platform_name_reads_back_and_is_escaped_in_messages(tmp_path, log, capsys, name):
    """--platform-out writes TOML that reads back for any name; messages show it escaped, one line."""
    from stewart_calib.io.platform_file import load_platform, platform_to_toml

    platform = nim_stewart()
    path = tmp_path / "P.toml"
    path.write_text(platform_to_toml(type(platform)(**{**platform.__dict__, "name": name})))
    assert load_platform(path).name == name
    log_path, out, ckpt = tmp_path / "log.csv", tmp_path / "r.json", tmp_path / "c.npz"
    write_log(log_path, log)
    argv = ["--platform", str(path), "--log", str(log_path), "--method", "ekf", "--out", str(out)]
    assert cli.main(["calibrate", *argv, "--platform-out", str(tmp_path / "C.toml")]) == 0
    assert load_platform(tmp_path / "C.toml").name == name
    assert cli.main(["track", *argv, "--checkpoint", str(ckpt)]) == 0
    assert OnlineCalibrator.load(ckpt, path).platform.name == name  # the checkpoint reads back too
    capsys.readouterr()
    # its result given for another platform: the message names both, escaped
    code = cli.main(
        [
            "compensate",
            "--platform",
            str(NIM_STEWART),
            "--result",
            str(out),
            "--poses",
            str(log_path),
            "--out",
            str(tmp_path / "s.csv"),
        ]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "\u001b" not in err and "\u0007" not in err


# --------------------------------------------------------------------------- track against calibrate


@pytest.mark.parametrize("every", ["7", "50"])
def test_track_isam2_is_calibrate_to_its_documented_bound(tmp_path, capsys, every):
    """The bound track.py states: ≤ 1e-4 σ on a clean log (a resume mid-way included), ≤ 0.05 σ
    where a lock-out recovery restarts the graph (the quick experiment's log)."""
    clean, quick = tmp_path / "clean.csv", tmp_path / "quick"
    write_log(clean, tracked_log(5, 150))
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(quick)]) == 0
    for path, platform, bound in ((clean, NIM_STEWART, 1e-4), (quick / "log.csv", quick / "platform.toml", 0.05)):
        common = ["--platform", str(platform), "--method", "isam2"]
        assert cli.main(["calibrate", *common, "--log", str(path), "--out", str(tmp_path / "c.json")]) == 0
        calibrated = read_result(tmp_path / "c.json")
        # track reads no log ahead: it takes the tracker's geometry σ calibrate measured on the log, as documented
        noise = calibrated["config"]["noise"]
        for key in ("tracker_geometry_sigma_mm", "reading_sigma_mm"):
            common += ["--set", f"noise.{key}={noise[key]!r}"]
        half = tmp_path / "half.csv"
        half.write_text("".join(path.read_text().splitlines(keepends=True)[:61]))
        ckpt, out = tmp_path / "ck.npz", tmp_path / "t.json"
        ckpt.unlink(missing_ok=True)
        for log in (half, path):  # a resume at row 60
            argv = [*common, "--log", str(log), "--out", str(out), "--checkpoint", str(ckpt), "--every", every]
            assert cli.main(["track", *argv]) == 0
        gap = np.abs(np.array(read_result(out)["error"]) - np.array(calibrated["error"]))
        assert np.max(gap / np.array(calibrated["stddev"])) <= bound
