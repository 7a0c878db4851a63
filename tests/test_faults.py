"""The catalogue of faulty inputs (issue 30): every case ends in one line — a refusal naming the
cause, exit 2, nothing written and no input touched — or a result that accounts for every row.

:data:`REFUSALS` holds the cases that must be refused: one row per case of the issue and our own
beside them, each run in-process with the directory's files compared before and after. The cases
that must succeed (rotation, resume, row accounting, disk full) have their own tests below.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import read_result, write_log
from stewart_calib.pipelines.track import line_chunks
from tests.synthetic import NIM_STEWART, ROOT, tracked_log

N = 40


@pytest.fixture(scope="module")
def log():
    return tracked_log(30, N)


@pytest.fixture
def work(tmp_path, log):
    """A directory with ``log.csv`` (N rows of nim-stewart), ``P.toml`` (its platform) and ``R.json``
    (a result of it)."""
    write_log(tmp_path / "log.csv", log)
    (tmp_path / "P.toml").write_text(NIM_STEWART.read_text())
    assert (
        cli.main(
            [
                "calibrate",
                "--platform",
                str(NIM_STEWART),
                "--log",
                str(tmp_path / "log.csv"),
                "--method",
                "ekf",
                "--out",
                str(tmp_path / "R.json"),
            ]
        )
        == 0
    )
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
    code = cli.main(argv)
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
    ("paths", "plan --platform {d}/P.toml --n 5 --out {d}/P.toml", "--out {d}/P.toml: is the --platform input"),
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
]


@pytest.mark.parametrize(
    "family, argv, message", REFUSALS, ids=[f"{family}-{k}" for k, (family, *_) in enumerate(REFUSALS)]
)
def test_refused_in_one_line_with_nothing_written(work, capsys, family, argv, message):
    (work / "header.csv").write_text((work / "log.csv").read_text().splitlines()[0] + "\n")
    (work / "empty.csv").write_text("")
    os.link(work / "log.csv", work / "link.csv")
    _refused(capsys, work, argv.format(d=work).split(), message.format(d=work))


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


@pytest.mark.parametrize("method", ["ekf", "isam2"])
def test_a_lock_out_recovery_accounts_for_every_row(tmp_path, capsys, method):
    """The quick experiment's log, where ekf and isam2 recover from a lock-out (issue 30: 34 rows unmentioned)."""
    sim = tmp_path / "sim"
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(sim)]) == 0
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
    line = capsys.readouterr().err.splitlines()[-1]
    result = read_result(out)
    assert result["recovery"]["count"] >= 1 and "lock-out recover" in line and line.endswith("of 120 rows)")
    _accounted(result, 120)
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
