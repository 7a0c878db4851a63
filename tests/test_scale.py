"""Scale properties asserted without a clock: the identifiability report from the accumulated
42 × 42 information equals the SVD of the stacked N-sized Jacobian (to a bound derived from
the round-off of both), whatever the blocking; a log read in blocks is the log read whole;
the memory of a streaming run does not grow with the log; start-up imports only what the
command run needs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.analysis import identifiability as ident
from stewart_calib.config import NoiseConfig
from stewart_calib.errors import CalibError
from tests.synthetic import nim_stewart, random_poses

NOISE = NoiseConfig()
UNIT_ROUNDOFF = np.finfo(float).eps / 2


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


def svd_of_stacked_rows(platform, poses):
    """What the report was computed from before: the full SVD of the (6N × 42) whitened rows."""
    A = ident.whitened_leg_jacobian(platform, poses, NOISE).reshape(-1, 42)
    _, s, Vt = np.linalg.svd(A, full_matrices=True)
    return A, np.r_[s, np.zeros(42 - len(s))], Vt


def roundoff_bound(A: np.ndarray, n_blocks: int) -> float:
    """|σ_i(computed) − σ_i(A)| for either path, by Weyl's theorem: Householder QR and the SVD are
    backward stable, ‖ΔA‖ ≤ m·n·u·‖A‖_F (Higham, Thm 19.4, c = 1), with m the rows factored —
    the N-sized stack, or all blocks plus the 42-row factor carried into each."""
    rows = A.shape[0] + 42 * n_blocks
    return rows * 42 * UNIT_ROUNDOFF * np.linalg.norm(A)


@pytest.mark.parametrize("block_poses", [7, 2048])
def test_accumulated_information_gives_the_stacked_svd(platform, monkeypatch, block_poses):
    monkeypatch.setattr(ident, "BLOCK_POSES", block_poses)
    poses = random_poses(platform, 40, np.random.default_rng(11))
    A, s, _ = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    tol = 2 * roundoff_bound(A, n_blocks=-(-40 // block_poses))  # both paths' errors
    np.testing.assert_allclose(report.singular_values, s, rtol=0, atol=tol)
    # (AᵀA)⁻¹ moves by at most 2‖ΔA‖/σmin relative (first order); its square root by half that.
    np.testing.assert_allclose(
        report.predicted_stddev_mm, np.sqrt(np.diag(np.linalg.inv(A.T @ A))), rtol=2 * tol / s[-1]
    )
    assert report.observability == ident.observability_indices(report.singular_values, A.shape[0])


def test_a_rank_deficient_stream_keeps_rank_and_null_space(platform, monkeypatch):
    # Translations only: the 18 directions d_i − j_i are unseen (tests/test_identifiability.py);
    # blocks of 4 poses hold fewer rows (24) than parameters, so the factor starts short.
    monkeypatch.setattr(ident, "BLOCK_POSES", 4)
    rng = np.random.default_rng(12)
    poses = platform.workspace.home + np.c_[rng.uniform(-200, 200, (30, 3)), np.zeros((30, 3))]
    _A, s, Vt = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    assert report.rank == int(np.sum(s > ident.RANK_RTOL * s[0])) == 24
    projector = Vt[24:].T @ Vt[24:]
    np.testing.assert_allclose(projector @ report.null_space, report.null_space, atol=1e-9)


def test_fewer_poses_than_parameters(platform):
    poses = random_poses(platform, 3, np.random.default_rng(13))
    A, s, _ = svd_of_stacked_rows(platform, poses)
    report = ident.identifiability_report(platform, poses, NOISE)
    assert report.rank == 18 and report.null_space_dimension == 24
    np.testing.assert_allclose(report.singular_values, s, rtol=0, atol=2 * roundoff_bound(A, 1))


def test_information_streams_in_pieces(platform):
    poses = random_poses(platform, 25, np.random.default_rng(14))
    whole = ident.identifiability_report(platform, poses, NOISE)
    information = ident.InformationAccumulator(platform, NOISE)
    for piece in np.array_split(poses, 6):
        information.add(piece)
    pieces = information.report()
    A, _, _ = svd_of_stacked_rows(platform, poses)
    assert pieces.n_poses == 25
    np.testing.assert_allclose(pieces.singular_values, whole.singular_values, rtol=0, atol=2 * roundoff_bound(A, 6))
    P = ident.scaled_paper_jacobian(platform, poses).reshape(-1, 42)
    np.testing.assert_allclose(
        pieces.paper_singular_values, whole.paper_singular_values, rtol=0, atol=2 * roundoff_bound(P, 6)
    )


# ----------------------------------------------------------------------------- reading in blocks


def _write_log_with_faults(path, n: int = 60) -> None:
    """A log of ``n`` rows with a bad value, a backwards time step and a quoted stage holding a line break."""
    from stewart_calib.io import write_log
    from stewart_calib.samples import Log

    platform = nim_stewart()
    rng = np.random.default_rng(15)
    poses = random_poses(platform, n, rng)
    from stewart_calib.model import kinematics as kin

    R, t = kin.pose_to_rt(poses)
    log = Log(
        np.arange(n) * 0.1,
        kin.inverse_kinematics(platform.drive, R, t),
        kin.inverse_kinematics(platform.tracker, R, t),
        poses,
        [f"stage {k // 20}" for k in range(n)],
    )
    write_log(path, log)
    lines = path.read_text().splitlines()
    lines[10] = lines[10].replace(lines[10].split(",")[3], "nan", 1)  # row 11: q3 not finite
    fields = lines[30].split(",")
    lines[30] = ",".join(["0.5", *fields[1:]])  # row 31: time goes back
    lines[45] = lines[45].replace("stage 2", '"stage\n2"')  # a quoted field spanning two lines
    path.write_text("\n".join(lines) + "\n")


def test_blocks_give_the_whole_log(tmp_path):
    from stewart_calib.io import read_log, read_log_blocks

    path = tmp_path / "log.csv"
    _write_log_with_faults(path)
    whole = read_log(path, nim_stewart(), skip_bad_rows=True)
    blocks = list(read_log_blocks(path, nim_stewart(), skip_bad_rows=True, block_bytes=600))  # ~2 rows a block
    assert len(blocks) > 20
    assert [row for b in blocks for row in b.skipped] == whole.skipped
    assert [row for row, _ in whole.skipped] == [11, 31]  # file lines, counted across blocks
    for field in ("t_s", "strokes", "readings", "desired_poses"):
        np.testing.assert_array_equal(np.concatenate([getattr(b, field) for b in blocks]), getattr(whole, field))
    assert [s for b in blocks for s in b.stages] == whole.stages and "stage\n2" in whole.stages
    # without skipping, the refusal names the same row whatever the blocking
    for block_bytes in (700, 1 << 22):
        with pytest.raises(CalibError, match=r"row 11: column 'q3_mm'"):
            list(read_log_blocks(path, nim_stewart(), block_bytes=block_bytes))


def test_time_going_back_across_a_block_boundary_is_flagged(tmp_path):
    from stewart_calib.io import read_log_blocks

    path = tmp_path / "log.csv"
    _write_log_with_faults(path)
    lines = path.read_text().splitlines()
    lines[31] = ",".join(["0.0", *lines[31].split(",")[1:]])  # row 32 back to t = 0 (row 31 already skipped)
    path.write_text("\n".join(lines) + "\n")
    for block_bytes in (1, 700, 1 << 22):  # one row a block, a few, all
        skipped = [row for b in read_log_blocks(path, nim_stewart(), True, block_bytes) for row, _ in b.skipped]
        assert skipped == [11, 31, 32]


def test_a_long_numeric_log_read_by_pyarrow_is_the_log_read_as_text(tmp_path, monkeypatch):
    # Without a text column, a log longer than a block is parsed by pyarrow from the file's bytes;
    # read as one block (the file shorter than it) it takes the text path. Both see the same
    # samples and skip the same rows, numbered alike — with CRLF line breaks, a non-finite
    # value, time going back and a lone carriage return (a line break to pyarrow alone).
    from stewart_calib.io import logs, read_log_blocks, tables

    by_arrow = []
    monkeypatch.setattr(
        logs, "numbers_by_arrow", lambda *a: by_arrow.append(tables.numbers_by_arrow(*a)) or by_arrow[-1]
    )
    path = tmp_path / "log.csv"
    _write_log_with_faults(path)
    lines = [",".join(line.split(",")[:-1]) for line in path.read_text().splitlines()]  # no stage column
    lines.remove("")  # what is left of the quoted stage's second line
    lines[20] = lines[20].replace(",", "\r,", 1)  # row 21
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode())
    size = path.stat().st_size

    def read(block_bytes):
        blocks = list(read_log_blocks(path, nim_stewart(), skip_bad_rows=True, block_bytes=block_bytes))
        return blocks, [row for b in blocks for row, _ in b.skipped]

    (whole,), _skipped = read(size + 1)
    assert [row for row, _ in whole.skipped] == [11, 21, 31] and not by_arrow
    for block_bytes in (1, 700, size // 2):
        by_arrow.clear()
        blocks, skipped_by_blocks = read(block_bytes)
        assert any(table is not None for table in by_arrow) and None in by_arrow  # the lone \r's block: the text path
        assert skipped_by_blocks == [row for row, _ in whole.skipped]
        assert [b.skipped for b in blocks if b.skipped] and sum(map(len, blocks)) == len(whole)
        for field in ("t_s", "strokes", "readings", "desired_poses"):
            np.testing.assert_array_equal(np.concatenate([getattr(b, field) for b in blocks]), getattr(whole, field))


def test_read_ahead_hands_on_items_and_errors_in_order():
    # calibrate reads, checks and spools the next block on a second thread while the estimator
    # works: the items come in order, a refusal where its block would have come, and leaving the
    # loop stops the thread
    import threading

    from stewart_calib.workflows.calibration import read_ahead

    def items():
        yield from (1, 2)
        raise CalibError("log.csv: row 9: bad")

    got = []
    with pytest.raises(CalibError, match="row 9"):
        for item in read_ahead(items()):
            got.append(item)
    assert got == [1, 2]
    endless = read_ahead(iter(range(10**9)))
    assert [next(endless) for _ in range(3)] == [0, 1, 2]
    endless.close()
    assert not [thread for thread in threading.enumerate() if thread.name == "stewart-calib read-ahead"]


# ----------------------------------------------------------------------------- memory of a run

LOG_BYTES_PER_ROW = 8 * (1 + 6 + 6 + 6)  # t_s, strokes, readings, desired pose as float64


@pytest.fixture(scope="module")
def long_logs(tmp_path_factory):
    """A 10 Hz Lissajous log of N = 400 and of 4N samples (the benchmark's stream)."""
    from benchmarks.common import synthetic_stream
    from stewart_calib.io import write_log

    root = tmp_path_factory.mktemp("logs")
    log, _ = synthetic_stream(nim_stewart(), 1600, np.random.default_rng(16), 10.0, smooth=True, noise=NOISE)
    paths = {}
    for n in (400, 1600):
        paths[n] = root / f"log-{n}.csv"
        write_log(paths[n], log.select(slice(0, n)))
    return paths


def _peak_bytes(argv) -> int:
    import tracemalloc

    from stewart_calib import cli

    tracemalloc.start()
    try:
        assert cli.main(argv) == 0
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("command", ["calibrate", "identifiability"])
def test_online_commands_hold_no_more_at_4n_samples(long_logs, tmp_path, monkeypatch, command):
    # Blocks of ~12 rows, so both logs span many, and calibrate's conditioning sample and the head the
    # tracker's geometry is measured on of at most 100 (both fixed, whatever N: the head holds at most
    # HEAD_LIMIT × ESTIMATE_SAMPLES samples while a held pose counts 50 of them); the first run also
    # loads caches and imports.
    from stewart_calib.io import logs
    from stewart_calib.workflows import calibration, tracker_geometry

    monkeypatch.setattr(logs, "BLOCK_BYTES", 1 << 12)
    monkeypatch.setattr(calibration, "CHECKED_SAMPLES", 100)
    monkeypatch.setattr(tracker_geometry, "ESTIMATE_SAMPLES", 100)
    monkeypatch.setattr(tracker_geometry, "HEAD_LIMIT", 1)
    platform = str(nim_stewart().source)

    def argv(n):
        args = ["--platform", platform, "--log", str(long_logs[n])]
        return (
            [command, *args, "--method", "ekf", "--out", str(tmp_path / "r.json")]
            if command == "calibrate"
            else [command, *args]
        )

    from stewart_calib import cli

    assert cli.main(argv(400)) == 0
    growth = _peak_bytes(argv(1600)) - _peak_bytes(argv(400))
    # Holding the log would add at least its 1200 more rows of arrays (~180 kB, and parsing
    # several times that); a streaming run holds one block and a fixed sample whatever N. Half
    # of the arrays is left for the peak's run-to-run spread (~±20 kB measured).
    assert growth < 0.5 * 1200 * LOG_BYTES_PER_ROW


# ----------------------------------------------------------------------------- start-up

#: never needed to start: recording (rerun), graph methods (gtsam), statistics, the reproduction.
HEAVY = ("rerun", "gtsam", "scipy.stats", "stewart_calib.reproduction")


def _modules_after(argv: list[str]) -> set[str]:
    """The modules a fresh interpreter holds after ``stewart-calib ARGV`` (run in it)."""
    root = Path(__file__).resolve().parents[1]
    script = (
        "import json, sys\nfrom stewart_calib import cli\n"
        f"try:\n    cli.main({argv!r})\nexcept SystemExit:\n    pass\n"
        "print(json.dumps(sorted(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, check=True).stdout
    return set(json.loads(out.splitlines()[-1]))


def test_help_imports_no_pipeline_and_nothing_heavy():
    modules = _modules_after(["--help"])
    assert not {m for m in modules if m.startswith("stewart_calib.pipelines.")}
    assert not set(HEAVY + ("numpy", "numba")) & modules


def test_an_ekf_calibration_imports_only_its_own_command(long_logs, tmp_path):
    modules = _modules_after(
        [
            "calibrate",
            "--platform",
            str(nim_stewart().source),
            "--log",
            str(long_logs[400]),
            "--method",
            "ekf",
            "--out",
            str(tmp_path / "r.json"),
        ]
    )
    assert (tmp_path / "r.json").exists()
    assert not set(HEAVY) & modules
    # calibrate shares validate's residuals; the commands it does not use are not loaded
    others = ("simulate", "reproduce", "track", "identifiability", "plan", "compensate", "import_bag", "sweep")
    assert not {f"stewart_calib.pipelines.{name}" for name in others} & modules


def test_row_parser_gives_the_samples_of_read_log(tmp_path):
    # Plain rows take the fast path, the faulty ones the careful path: the samples and the
    # refusals must be read_log's either way.
    from stewart_calib.io import LogRowParser, read_log

    path = tmp_path / "log.csv"
    _write_log_with_faults(path)
    lines = path.read_text().replace('"stage\n2"', "stage 2").splitlines()  # one sample a line
    path.write_text("\n".join(lines) + "\n")
    whole = read_log(path, nim_stewart(), skip_bad_rows=True)
    parser = LogRowParser(str(path), lines[0], nim_stewart())
    samples, refused = [], []
    for row, line in enumerate(lines[1:], start=2):
        try:
            samples.append(parser.parse(line, row))
        except CalibError as err:
            refused.append(str(err))
    assert refused == [f"{path}: row {row}: {reason}" for row, reason in whole.skipped]
    assert len(samples) == len(whole)
    for sample, expected in zip(samples, whole, strict=True):
        assert (sample.t_s, sample.stage) == (expected.t_s, expected.stage)
        assert sample.inputs.keys() == expected.inputs.keys()
        for name, values in sample.inputs.items():
            np.testing.assert_array_equal(values, expected.inputs[name])
        for field in ("strokes", "readings", "desired_pose"):
            np.testing.assert_array_equal(getattr(sample, field), getattr(expected, field))


def test_a_spooled_log_reads_back_as_it_was_read(long_logs, tmp_path, monkeypatch):
    # calibrate's second pass (the residual RMS at the final estimate) reads the samples back from
    # its spool, with values of each computed on the first pass, in blocks of the reader's size,
    # instead of parsing the CSV again
    from stewart_calib.io import logs, read_log
    from stewart_calib.workflows.calibration import SampleSpool

    monkeypatch.setattr(logs, "BLOCK_BYTES", 1 << 12)
    spool = SampleSpool(tmp_path)
    for block in logs.read_log_blocks(long_logs[400], nim_stewart()):
        spool.add(block, block.strokes[:, :2] - block.t_s[:, None])  # two extra columns
    back, extra = zip(*spool.blocks(), strict=True)
    spool.close()
    assert len(back) > 1 and max(8 * 15 * len(b) for b in back) <= 1 << 12
    whole = read_log(long_logs[400], nim_stewart())
    for field in ("t_s", "strokes", "readings"):
        np.testing.assert_array_equal(np.concatenate([getattr(b, field) for b in back]), getattr(whole, field))
    np.testing.assert_array_equal(np.concatenate(extra), whole.strokes[:, :2] - whole.t_s[:, None])
    assert not list(tmp_path.iterdir())  # an unnamed file: nothing left beside the output
