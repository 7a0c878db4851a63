"""``validate`` streams its log (issue 15): V.csv and the summary line are those of the whole log
predicted at once and written by ``csv_text``, block boundaries anywhere."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import io
from stewart_calib.cli import main
from stewart_calib.estimate import Estimate
from stewart_calib.io import logs
from stewart_calib.io.platform_file import platform_to_toml
from stewart_calib.io.tables import csv_text
from stewart_calib.model.platform import Instrument
from stewart_calib.pipelines.validate import _summary
from stewart_calib.simulation.instrument import InstrumentTruth
from stewart_calib.workflows.validation import validate
from tests.instrument_data import hobby, make_case
from tests.synthetic import make_log, nim_stewart, random_error, random_poses


def _tracker_case(n: int):
    platform = nim_stewart()
    log, _ = make_log(
        platform,
        random_error(np.random.default_rng(4)),
        random_poses(platform, n, np.random.default_rng(5)),
        np.random.default_rng(6),
        reading_sigma_mm=0.01,
    )
    return platform, log


def _points_case(n: int):
    targets = np.array([[30.0, 0.0, 20.0], [-20.0, 25.0, 20.0]])
    platform = hobby(Instrument("points", np.zeros(6), np.zeros(6), targets, 0.05))
    case = make_case(
        platform, n, 8, InstrumentTruth(np.array([3.0, 1.0, -2.0, 0.0, 0.0, 5.0]), np.zeros(6), dropout_probability=0.3)
    )
    return platform, case.log


def _pose_case(n: int):
    platform = hobby()
    return platform, make_case(
        platform, n, 9, InstrumentTruth(np.array([3.0, 1.0, -2.0, 0.0, 0.0, 5.0]), np.zeros(6))
    ).log


def _files(tmp_path, platform, log):
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    io.write_log(tmp_path / "log.csv", log, platform)
    result = io.result_dict(Estimate(random_error(np.random.default_rng(3), 0.2), None, "ls", 1), platform)
    io.write_result(tmp_path / "r.json", result)
    argv = [
        "validate",
        "--platform",
        str(tmp_path / "p.toml"),
        "--result",
        str(tmp_path / "r.json"),
        "--log",
        str(tmp_path / "log.csv"),
        "--out",
        str(tmp_path / "V.csv"),
    ]
    return io.read_result(tmp_path / "r.json"), argv


def _whole_file(platform, result, path, register: bool = False) -> tuple[str, str]:
    """V.csv's text and the summary as the command wrote them from the whole log: one prediction,
    ``csv_text`` of the columns (an empty field for a target not seen and its error)."""
    log = io.read_log(path, platform)
    predicted, position, orientation = validate(platform, result, log, register, "result")
    columns = io.reading_columns(platform)
    header = ["t_s", *columns, *(f"pred_{name}" for name in columns), "position_error_mm"]
    values = [
        log.t_s,
        *io.readings_to_file(log.readings, platform),
        *io.readings_to_file(predicted, platform),
        ["" if not np.isfinite(v) else float(v) for v in position],
    ]
    if orientation is not None:
        header.append("orientation_error_deg")
        values.append(orientation)
    values = [v.tolist() if isinstance(v, np.ndarray) else v for v in values]  # each float by the csv module's repr
    return csv_text(header, values), _summary(position, orientation, len(log))


@pytest.mark.parametrize(
    "case, n, block_bytes",
    [
        (_tracker_case, 5000, 1_500_000),
        (_tracker_case, 300, 8192),
        (_points_case, 5000, 800_000),
        (_pose_case, 200, 4096),
    ],
)
def test_streamed_validate_writes_the_whole_logs_file(tmp_path, monkeypatch, capsys, case, n, block_bytes):
    platform, log = case(n)
    result, argv = _files(tmp_path, platform, log)
    monkeypatch.setattr(logs, "BLOCK_BYTES", block_bytes)  # a first block of more than 4096 rows, or many small ones
    assert len(list(io.read_log_blocks(tmp_path / "log.csv", platform))) > 1
    assert main(argv) == 0
    text, summary = _whole_file(platform, result, tmp_path / "log.csv")
    assert (tmp_path / "V.csv").read_text() == text
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"stewart-calib validate: {summary}"
    # an outside instrument's check adds the line on what it cannot see (tests/test_accuracy.py); the verdict ends
    assert len(lines) == (2 if platform.instrument.kind == "tracker" else 3)
    assert lines[-1].startswith("stewart-calib validate: verdict: ")


def test_register_instrument_writes_the_whole_logs_file(tmp_path, monkeypatch, capsys):
    platform, log = _points_case(300)
    result, argv = _files(tmp_path, platform, log)
    monkeypatch.setattr(logs, "BLOCK_BYTES", 4096)
    assert main([*argv, "--register-instrument"]) == 0
    text, summary = _whole_file(platform, result, tmp_path / "log.csv", register=True)
    assert (tmp_path / "V.csv").read_text() == text
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == f"stewart-calib validate: {summary} (instrument re-registered)" and len(lines) == 3


def test_a_bad_row_in_a_late_block_leaves_no_output(tmp_path, monkeypatch, capsys):
    platform, log = _tracker_case(300)
    _, argv = _files(tmp_path, platform, log)
    lines = (tmp_path / "log.csv").read_text().splitlines(keepends=True)
    lines[290] = lines[290].replace(",", ",nan,", 1).rsplit(",", 1)[0] + "\n"  # row 291: q1_mm not a number
    (tmp_path / "log.csv").write_text("".join(lines))
    (tmp_path / "V.csv").write_text("the previous output\n")
    monkeypatch.setattr(logs, "BLOCK_BYTES", 4096)
    assert main(argv) == 2
    assert capsys.readouterr().err.strip() == (
        f"stewart-calib validate: error: {tmp_path / 'log.csv'}: row 291: "
        "column 'q1_mm': expected a finite number, got nan"
    )
    assert (tmp_path / "V.csv").read_text() == "the previous output\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["V.csv", "log.csv", "p.toml", "r.json"]


def test_distinct_rows_are_counted_as_one_by_one_clustering_does():
    """The count :func:`registration.distinct_count` vectorises: each row against every distinct one before it."""
    from stewart_calib.instruments.registration import distinct_count

    rng = np.random.default_rng(12)
    readings = rng.integers(0, 4, (400, 3)) + rng.normal(0, 0.01, (400, 3))  # 64 clusters of near-equal rows
    readings[rng.random((400, 3)) < 0.1] = np.nan  # a target not seen: close to anything in that component
    scale = np.full(3, 0.1)
    distinct: list[np.ndarray] = []
    for row in readings:
        if not any(np.all((np.abs(row - rep) <= scale) | ~np.isfinite(row - rep)) for rep in distinct):
            distinct.append(row)
    assert 10 < len(distinct) < 64
    assert [distinct_count(readings, scale, enough) for enough in (3, len(distinct), 1000)] == [
        3,
        len(distinct),
        len(distinct),
    ]
    assert distinct_count(np.empty((0, 3)), scale, 3) == 0
