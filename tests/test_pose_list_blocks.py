"""Pose lists read and written a block at a time (``compensate`` streams its list, issue 15): the
same poses, bytes and refusals as the whole-file reading and ``csv_text`` writing they replace."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import io
from stewart_calib.analysis.compensation import PoseOutOfRange, compensate
from stewart_calib.cli import main
from stewart_calib.errors import CalibError, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import logs
from stewart_calib.io.tables import csv_text, float_rows_csv
from tests.synthetic import NIM_STEWART, nim_stewart, random_error, random_poses

HEADER = "t_s,x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg"


def _pose_list_text(poses: np.ndarray, newline: str = "\n") -> str:
    """A pose list's text [mm, deg] written by hand with ``repr`` (not by the code under test)."""
    values = np.column_stack([np.arange(len(poses)), poses[:, :3], np.degrees(poses[:, 3:])]).tolist()
    rows = [",".join(map(repr, row)) for row in values]
    return newline.join([HEADER, *rows]) + newline


def _file_poses(text: str) -> np.ndarray:
    """The poses of a pose list's text [mm, rad] by ``float`` on each field, as the reader must give them."""
    rows = [line.split(",")[1:] for line in text.replace("\r\n", "\n").split("\n")[1:] if line]
    poses = np.array(rows, dtype=float)
    poses[:, 3:] = np.radians(poses[:, 3:])
    return poses


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """The platform, a result file with a drive error, the drive, and 3000 reachable poses."""
    platform = nim_stewart()
    rng = np.random.default_rng(15)
    delta = random_error(rng)
    path = tmp_path_factory.mktemp("result") / "r.json"
    io.write_result(path, io.result_dict(Estimate(delta, None, "ekf", 1), platform))
    return platform, path, io.read_calibrated_drive(path, platform), random_poses(platform, 3000, rng)


def _compensate_cli(result, poses_path, out) -> int:
    return main(
        [
            "compensate",
            "--platform",
            str(NIM_STEWART),
            "--result",
            str(result),
            "--poses",
            str(poses_path),
            "--out",
            str(out),
        ]
    )


@pytest.mark.parametrize("newline, block_bytes", [("\n", 4096), ("\r\n", 4096), ("\n", 10**7)])
def test_streamed_compensate_writes_the_whole_file_texts_bytes(calibrated, tmp_path, monkeypatch, newline, block_bytes):
    platform, result, drive, poses = calibrated
    text = _pose_list_text(poses, newline)
    (tmp_path / "poses.csv").write_bytes(text.encode())
    monkeypatch.setattr(logs, "POSE_BLOCK_BYTES", block_bytes)  # ~35 blocks, not a whole number of them
    assert _compensate_cli(result, tmp_path / "poses.csv", tmp_path / "q.csv") == 0
    # the former command: the whole list, its IK at once, csv_text of every column
    expected = _file_poses(text)
    strokes = compensate(drive, expected, limits=platform)
    header = ["t_s", *io.POSE_COLUMNS, *io.STROKE_COLUMNS]
    columns = [np.arange(len(expected)) * 1.0, *expected[:, :3].T, *np.degrees(expected[:, 3:]).T, *strokes.T]
    assert (tmp_path / "q.csv").read_text() == csv_text(header, [c.tolist() for c in columns])  # the csv module's repr


def test_a_refusal_in_a_late_block_leaves_no_output_and_names_its_row(calibrated, tmp_path, monkeypatch, capsys):
    platform, result, drive, poses = calibrated
    monkeypatch.setattr(logs, "POSE_BLOCK_BYTES", 4096)
    out = tmp_path / "q.csv"
    out.write_text("the previous output\n")
    lines = _pose_list_text(poses).splitlines(keepends=True)
    lines[2901] = lines[2901].replace(",", ",nan,", 1).rsplit(",", 1)[0] + "\n"  # row 2902: x_mm not finite
    (tmp_path / "bad.csv").write_text("".join(lines))
    assert _compensate_cli(result, tmp_path / "bad.csv", out) == 2
    message = f"{tmp_path / 'bad.csv'}: row 2902: column 'x_mm': expected a finite number, got nan"
    assert capsys.readouterr().err.strip() == f"stewart-calib compensate: error: {message}"
    with pytest.raises(CalibError, match=f"^{message}$"):
        io.read_pose_list(tmp_path / "bad.csv")

    far = poses.copy()
    far[2950, 3] = 5.0  # 5 rad: beyond the workspace
    (tmp_path / "far.csv").write_text(_pose_list_text(far))
    with pytest.raises(PoseOutOfRange) as whole:
        compensate(drive, _file_poses(_pose_list_text(far)), limits=platform)
    assert whole.value.pose_index == 2950
    assert _compensate_cli(result, tmp_path / "far.csv", out) == 2
    assert capsys.readouterr().err.strip() == (
        f"stewart-calib compensate: error: {tmp_path / 'far.csv'}: row 2952: {whole.value.reason}"
    )
    assert out.read_text() == "the previous output\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv", "far.csv", "q.csv"]  # no temporary left


def test_a_bad_row_after_an_unreachable_pose_is_refused_first(calibrated, tmp_path, monkeypatch, capsys):
    """The whole list was read before any pose was compensated: a bad row anywhere came first."""
    _platform, result, _drive, poses = calibrated
    monkeypatch.setattr(logs, "POSE_BLOCK_BYTES", 4096)
    lines = _pose_list_text(poses).splitlines(keepends=True)
    lines[10] = lines[10].replace(",", ",1e9,", 1).rsplit(",", 1)[0] + "\n"  # unreachable, in the first block
    lines[2990] = "1,2,3\n"
    (tmp_path / "poses.csv").write_text("".join(lines))
    assert _compensate_cli(result, tmp_path / "poses.csv", tmp_path / "q.csv") == 2
    assert capsys.readouterr().err.strip().endswith("row 2991: expected 7 fields as in the header, got 3")


@pytest.mark.parametrize("block_bytes", [1, 37, 1000, 10**7])
def test_blocks_give_the_whole_lists_poses(tmp_path, block_bytes):
    poses = random_poses(nim_stewart(), 40, np.random.default_rng(1))
    text = _pose_list_text(poses).replace("\n", "\n\n", 3)  # blank lines are skipped, rows numbered past them
    (tmp_path / "poses.csv").write_text(text)
    blocks = list(io.read_pose_list_blocks(tmp_path / "poses.csv", block_bytes))
    assert sum(len(b) for b in blocks) == 40 and (block_bytes > len(text) or len(blocks) > 1)
    np.testing.assert_array_equal(np.concatenate(blocks), _file_poses(text))
    lines = text.splitlines(keepends=True)
    lines[40] = "-inf," + lines[40]
    (tmp_path / "late.csv").write_text("".join(lines))
    with pytest.raises(CalibError, match=r"late.csv: row 41: expected 7 fields as in the header, got 8$"):
        list(io.read_pose_list_blocks(tmp_path / "late.csv", block_bytes))


def test_one_row_and_header_only_files(tmp_path):
    (tmp_path / "one.csv").write_text(f"{HEADER}\n0,1,2,3,4,5,6")  # no final line break
    np.testing.assert_array_equal(io.read_pose_list(tmp_path / "one.csv"), [[1, 2, 3, *np.radians([4, 5, 6])]])
    (tmp_path / "head.csv").write_text(f"{HEADER}\n\n")
    with pytest.raises(
        CalibError, match=r"head.csv: no sample rows; expected a header row and at least one sample row$"
    ):
        io.read_pose_list(tmp_path / "head.csv")
    (tmp_path / "empty.csv").write_text(" \n\n")
    with pytest.raises(CalibError, match=r"empty.csv: empty file, no sample rows"):
        io.read_pose_list(tmp_path / "empty.csv")
    with pytest.raises(CalibError, match=r"none.csv: pose list not found$"):
        io.read_pose_list(tmp_path / "none.csv")


def test_bytes_that_are_not_utf8_are_refused_before_any_other_problem(tmp_path):
    """As when the whole file was decoded first: the byte's offset in the file, whatever comes before it."""
    body = "".join(f"{k},1,2,3,4,5,6\n" for k in range(3000))
    data = f"{HEADER}\nnot,a,number,row,at,row,two\n{body}".encode() + b"9,1,2,3,\xff,5,6\n"
    (tmp_path / "poses.csv").write_bytes(data)
    offset = data.index(b"\xff")
    with pytest.raises(
        CalibError,
        match=rf"poses.csv: pose list is not UTF-8 text \(byte 0xff at offset {offset}\); "
        "expected a UTF-8 CSV file$",
    ):
        list(io.read_pose_list_blocks(tmp_path / "poses.csv", 4096))
    (tmp_path / "columns.csv").write_bytes(b"x_mm,y_mm\n" + data[len(HEADER) + 1 :])  # a missing column, too
    with pytest.raises(CalibError, match=r"columns.csv: pose list is not UTF-8 text"):
        io.read_pose_list(tmp_path / "columns.csv")


@pytest.mark.parametrize("rows", [10, 4100])  # by repr and by pyarrow
def test_float_rows_are_repr_joined(rows):
    """Each float written as the ``repr`` of its 15 significant digits, by either path."""
    rng = np.random.default_rng(7)
    edges = [
        0.0,
        -0.0,
        1e-4,
        np.nextafter(1e-4, 0),
        1e9,
        np.nextafter(1e9, 0),
        1e16,
        5e-324,
        np.inf,
        -np.inf,
        np.nan,
        0.1,
        2.0**53,
    ]
    n = 3 * rows - 2 * len(edges)
    values = rng.choice([-1, 1], n) * 10.0 ** rng.uniform(-9, 20, n) * rng.uniform(1, 10, n)
    values[::7] = np.round(values[::7])
    columns = list(np.r_[edges, values, edges[::-1]].reshape(3, -1))
    assert float_rows_csv(columns).decode() == "".join(
        ",".join(map(repr, row)) + "\n" for row in zip(*(without_noise(c).tolist() for c in columns), strict=True)
    )
    assert float_rows_csv([np.empty(0), np.empty(0)]) == b""


def test_a_failing_block_leaves_the_file_as_it_was(tmp_path):
    (tmp_path / "q.csv").write_text("old\n")

    def blocks():
        yield np.zeros((2, 6)), np.ones((2, 1))
        raise CalibError("refused")

    with pytest.raises(CalibError, match=r"^refused$"):
        io.write_pose_list_blocks(tmp_path / "q.csv", blocks(), ("q1_mm",))
    assert (tmp_path / "q.csv").read_text() == "old\n" and len(list(tmp_path.iterdir())) == 1
    assert io.write_pose_list_blocks(tmp_path / "q.csv", iter([(np.zeros((2, 6)), np.ones((2, 1)))]), ("q1_mm",)) == 2
    assert (tmp_path / "q.csv").read_text() == f"{HEADER},q1_mm\n" + "".join(
        f"{k}.0,{'0.0,' * 6}1.0\n" for k in range(2)
    )
