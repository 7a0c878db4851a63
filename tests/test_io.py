"""Logs, truth files, results and traces: round trips (exact of every number's 15 significant digits)
and every refusal of spec §3–§5."""

from __future__ import annotations

import itertools
import json
import os

import numpy as np
import pytest

from stewart_calib.errors import CalibError, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import (
    BackgroundWriter,
    atomic_write_text,
    read_log,
    read_result,
    read_truth,
    result_dict,
    write_log,
    write_result,
    write_trace,
    write_truth,
)
from stewart_calib.model.platform import PARAMETER_NAMES
from stewart_calib.samples import GRAVITY, LOAD_KG, TEMPERATURE_C, Log, Truth, packed_inputs, unpacked_inputs
from tests.synthetic import nim_stewart

HEADER = "t_s," + ",".join(f"q{i}_mm" for i in range(1, 7)) + "," + ",".join(f"s{i}_mm" for i in range(1, 7))


def _row(t: float, q: float = 1.0, s: float = 2.0) -> str:
    return ",".join([repr(t), *[repr(q)] * 6, *[repr(s)] * 6])


def _write(tmp_path, text: str, name: str = "log.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def _refusal(path, *args, **kwargs) -> str:
    with pytest.raises(CalibError) as info:
        read_log(path, *args, **kwargs)
    message = str(info.value)
    assert "\n" not in message and message.startswith(str(path))
    return message


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


def _random_log(n: int, rng: np.random.Generator, poses: bool = True) -> Log:
    return Log(
        t_s=np.cumsum(rng.uniform(0.0, 0.1, n)),
        strokes=rng.uniform(-100, 100, (n, 6)),
        readings=rng.uniform(-100, 100, (n, 6)),
        desired_poses=np.c_[rng.normal(0, 100, (n, 3)), rng.normal(0, 0.2, (n, 3))] if poses else None,
        stages=[rng.choice(["no-load", "20kg", 'odd, "quoted" label']) for _ in range(n)] if poses else None,
        inputs={LOAD_KG: rng.choice([0.0, 20.0, np.nan], n)} if poses else {},
    )


# ----------------------------------------------------------------------------- round trips


def test_log_round_trip_is_exact_to_15_digits(tmp_path):
    log = _random_log(200, np.random.default_rng(1))
    write_log(tmp_path / "log.csv", log)
    back = read_log(tmp_path / "log.csv")
    np.testing.assert_array_equal(back.t_s, without_noise(log.t_s))
    np.testing.assert_array_equal(back.strokes, without_noise(log.strokes))
    np.testing.assert_array_equal(back.readings, without_noise(log.readings))
    np.testing.assert_array_equal(back.inputs[LOAD_KG], log.inputs[LOAD_KG])
    assert back.stages == log.stages
    # positions are exact; angles pass through degrees (15 digits) and back, within one rounding [rad]
    np.testing.assert_array_equal(back.desired_poses[:, :3], without_noise(log.desired_poses[:, :3]))
    angles = np.radians(without_noise(np.degrees(log.desired_poses[:, 3:])))
    np.testing.assert_allclose(back.desired_poses[:, 3:], angles, rtol=4e-16, atol=0)
    assert back.skipped == []


def test_packed_inputs_round_trip_a_buffer_of_samples_with_and_without_channels():
    rng = np.random.default_rng(3)
    temperatures, gravity = rng.uniform(15.0, 30.0, (3, 6)), rng.normal(size=3)
    samples = [
        {LOAD_KG: 12.5, TEMPERATURE_C: temperatures[0]},
        {},
        {TEMPERATURE_C: temperatures[2], GRAVITY: gravity},
    ]
    channels = unpacked_inputs(np.array([packed_inputs(sample) for sample in samples]))
    assert set(channels) == {LOAD_KG, TEMPERATURE_C, GRAVITY}
    np.testing.assert_array_equal(channels[LOAD_KG], [12.5, 0.0, 0.0])  # no payload: 0 kg
    np.testing.assert_array_equal(channels[TEMPERATURE_C], [temperatures[0], np.full(6, np.nan), temperatures[2]])
    np.testing.assert_array_equal(channels[GRAVITY], [np.full(3, np.nan), np.full(3, np.nan), gravity])
    # a channel no sample has is left out (a payload is never so: its default is 0 kg, not NaN)
    assert set(unpacked_inputs(np.array([packed_inputs({LOAD_KG: 1.0})]))) == {LOAD_KG}


def test_log_header_is_spec_order_and_degrees(tmp_path):
    log = Log(np.array([0.0]), np.zeros((1, 6)), np.zeros((1, 6)), np.array([[1.0, 2.0, 3.0, np.pi / 2, 0.0, 0.0]]))
    write_log(tmp_path / "log.csv", log)
    header, row = (tmp_path / "log.csv").read_text().splitlines()
    assert header == HEADER + ",x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg"
    assert row.split(",")[13:17] == ["1.0", "2.0", "3.0", "90.0"]


def test_log_minimal_columns_order_free_unknown_ignored(tmp_path):
    names = HEADER.split(",")
    order = names[::-1] + ["comment"]
    values = {"t_s": "0.5", **{n: str(i) for i, n in enumerate(names[1:])}}
    path = _write(tmp_path, ",".join(order) + "\n" + ",".join([values[n] for n in names[::-1]] + ["hello"]) + "\n")
    log = read_log(path)
    assert log.t_s.tolist() == [0.5]
    assert log.strokes.tolist() == [[0, 1, 2, 3, 4, 5]]
    assert log.readings.tolist() == [[6, 7, 8, 9, 10, 11]]
    assert log.desired_poses is None and log.stages is None and log.inputs == {}


def test_log_tolerates_bom_crlf_and_blank_lines(tmp_path):
    text = "\ufeff" + HEADER + "\r\n" + _row(0.0) + "\r\n\r\n" + _row(1.0) + "\r\n"
    log = read_log(_write(tmp_path, text))
    assert log.t_s.tolist() == [0.0, 1.0]


def test_truth_round_trip_is_exact_to_15_digits(tmp_path):
    rng = np.random.default_rng(2)
    truth = Truth(
        np.arange(5) * 0.1, rng.normal(0, 500, (5, 42)), np.c_[rng.normal(0, 100, (5, 3)), rng.normal(0, 0.2, (5, 3))]
    )
    write_truth(tmp_path / "truth.csv", truth)
    back = read_truth(tmp_path / "truth.csv")
    assert back.t_s.tolist() == [0.0, 0.1, 0.2, 0.3, 0.4]  # not 0.30000000000000004
    np.testing.assert_array_equal(back.params, without_noise(truth.params))
    np.testing.assert_allclose(back.true_poses, truth.true_poses, rtol=5e-15, atol=0)  # half the 15th digit
    header = (tmp_path / "truth.csv").read_text().splitlines()[0].split(",")
    assert header[:43] == ["t_s", *PARAMETER_NAMES] and header[43] == "true_x_mm" and header[-1] == "true_yaw_deg"
    write_truth(tmp_path / "bare.csv", Truth(truth.t_s, truth.params))
    assert read_truth(tmp_path / "bare.csv").true_poses is None


def test_truth_refuses_missing_parameter_column_and_nan(tmp_path):
    path = _write(tmp_path, "t_s," + ",".join(PARAMETER_NAMES[:-1]) + "\n" + ",".join(["0"] * 42) + "\n", "truth.csv")
    with pytest.raises(CalibError, match=r"truth\.csv: row 1: missing required column\(s\) l6$"):
        read_truth(path)
    path = _write(
        tmp_path, "t_s," + ",".join(PARAMETER_NAMES) + "\n" + ",".join(["0"] * 42 + ["nan"]) + "\n", "truth.csv"
    )
    with pytest.raises(CalibError, match=r"truth\.csv: row 2: column 'l6': expected a finite number, got nan"):
        read_truth(path)


def test_trace_has_t_and_42_parameters(tmp_path):
    params = np.random.default_rng(3).normal(0, 1, (4, 42))
    write_trace(tmp_path / "trace.csv", np.arange(4.0), params)
    rows = [line.split(",") for line in (tmp_path / "trace.csv").read_text().splitlines()]
    assert rows[0] == ["t_s", *PARAMETER_NAMES]
    np.testing.assert_array_equal(np.array(rows[1:], dtype=float), without_noise(np.c_[np.arange(4.0), params]))
    with pytest.raises(ValueError, match="trace needs"):
        write_trace(tmp_path / "bad.csv", np.arange(3.0), params)


# ----------------------------------------------------------------------------- log refusals


def test_refuses_missing_and_unreadable_files(tmp_path):
    assert _refusal(tmp_path / "nope.csv") == f"{tmp_path / 'nope.csv'}: log file not found"
    assert "is a directory; expected a log file" in _refusal(tmp_path)
    path = tmp_path / "latin1.csv"
    path.write_bytes((HEADER + ",stage\n" + _row(0.0) + ",caf\xe9\n").encode("latin-1"))
    assert "not UTF-8 text (byte 0xe9 at offset" in _refusal(path)


@pytest.mark.parametrize("text", ["", "\n", HEADER + "\n"])
def test_refuses_log_without_sample_rows(tmp_path, text):
    assert "no sample rows" in _refusal(_write(tmp_path, text))


def test_refuses_missing_required_column(tmp_path):
    header = HEADER.replace("q3_mm,", "").replace(",s6_mm", "")
    message = _refusal(_write(tmp_path, header + "\n" + ",".join(["0"] * 11) + "\n"))
    assert message.endswith("row 1: missing required column(s) q3_mm, s6_mm")


def test_refuses_duplicate_column(tmp_path):
    message = _refusal(_write(tmp_path, HEADER + ",q1_mm\n" + _row(0.0) + ",1\n"))
    assert message.endswith("row 1: column 'q1_mm' appears twice; expected unique column names")


def test_refuses_partial_pose_columns(tmp_path):
    message = _refusal(_write(tmp_path, HEADER + ",x_mm,y_mm,z_mm,roll_deg\n" + _row(0.0) + ",0,0,0,0\n"))
    assert "row 1: columns x_mm, y_mm, z_mm, roll_deg, pitch_deg, yaw_deg come all six or none" in message
    assert message.endswith("missing pitch_deg, yaw_deg")


@pytest.mark.parametrize(
    ("bad_row", "expected"),
    [
        ("0.2,1,1,1", "row 4: expected 13 fields as in the header, got 4"),
        (_row(0.2) + ",7", "row 4: expected 13 fields as in the header, got 14"),
        (_row(0.2).replace("2.0", "nan", 1), "row 4: column 's1_mm': expected a finite number, got nan"),
        (_row(0.2).replace("1.0", "inf", 1), "row 4: column 'q1_mm': expected a finite number, got inf"),
        (_row(0.2).replace("1.0", "", 1), "row 4: column 'q1_mm': expected a number, got an empty field"),
        (_row(0.2).replace("2.0", "abc", 1), "row 4: column 's1_mm': expected a number, got 'abc'"),
        (_row(0.05), "row 4: column 't_s': expected time non-decreasing, got 0.05 after 0.1"),
    ],
)
def test_refuses_bad_row_naming_row_and_column(tmp_path, bad_row, expected):
    text = "\n".join([HEADER, _row(0.0), _row(0.1), bad_row, _row(0.3)]) + "\n"
    message = _refusal(_write(tmp_path, text))
    assert message == f"{tmp_path / 'log.csv'}: {expected}"


def test_refuses_rows_all_one_field_short_of_the_header(tmp_path):
    """Every row alike but one field short (numpy's reader compares rows with each other only;
    found by tests/test_fuzz.py)."""
    short = lambda t: _row(t).rsplit(",", 1)[0]  # noqa: E731
    message = _refusal(_write(tmp_path, "\n".join([HEADER, short(0.0), short(0.1)]) + "\n"))
    assert message == f"{tmp_path / 'log.csv'}: row 2: expected 13 fields as in the header, got 12"


def test_refuses_readings_and_strokes_out_of_range_inclusive(tmp_path, platform):
    lo_s, hi_s = platform.reading_range
    lo_q, hi_q = platform.stroke_range
    at_bounds = "\n".join([HEADER, _row(0.0, q=lo_q, s=lo_s), _row(0.1, q=hi_q, s=hi_s)]) + "\n"
    assert len(read_log(_write(tmp_path, at_bounds), platform)) == 2
    reading = _refusal(_write(tmp_path, at_bounds + _row(0.2, s=hi_s + 0.001) + "\n"), platform)
    assert reading.endswith(
        "row 4: column 's1_mm': expected a reading within [-276.0, 318.0] mm (tracker.reading_range_mm), got 318.001"
    )
    stroke = _refusal(_write(tmp_path, at_bounds + _row(0.2, q=lo_q - 1.0) + "\n"), platform)
    assert stroke.endswith(
        "row 4: column 'q1_mm': expected a stroke within [-420.0, 520.0] mm (drive.stroke_range_mm), got -421.0"
    )
    assert len(read_log(_write(tmp_path, at_bounds + _row(0.2, s=hi_s + 0.001) + "\n"))) == 3  # no platform, no ranges


def test_refuses_bad_value_in_quoted_file_with_its_line(tmp_path):
    text = HEADER + ",stage\n" + _row(0.0) + ',"two\nlines"\n' + _row(0.1).replace("1.0", "x", 1) + ",a\n"
    assert _refusal(_write(tmp_path, text)).endswith("row 4: column 'q1_mm': expected a number, got 'x'")


# ----------------------------------------------------------------------------- skipping bad rows


def test_skip_mode_counts_and_reasons(tmp_path, platform):
    rows = [
        _row(0.0),
        _row(0.1, s=400.0),  # out of range
        _row(0.2).replace("1.0", "nan", 1),  # non-finite
        "0.3,1,1",  # field count
        _row(5.0),  # a glitch forward in time: kept, so what follows it...
        _row(0.4),  # ... goes backwards and is skipped
        _row(6.0),
    ]
    log = read_log(_write(tmp_path, "\n".join([HEADER, *rows]) + "\n"), platform, skip_bad_rows=True)
    assert log.t_s.tolist() == [0.0, 5.0, 6.0]
    assert [line for line, _ in log.skipped] == [3, 4, 5, 7]
    reasons = [reason for _, reason in log.skipped]
    assert reasons[0].startswith("column 's1_mm': expected a reading within")
    assert reasons[1] == "column 'q1_mm': expected a finite number, got nan"
    assert reasons[2] == "expected 13 fields as in the header, got 3"
    assert reasons[3] == "column 't_s': expected time non-decreasing, got 0.4 after 5.0"


def test_skip_mode_still_refuses_file_level_problems(tmp_path):
    assert "missing required column(s) t_s" in _refusal(_write(tmp_path, HEADER[4:] + "\n1\n"), skip_bad_rows=True)
    assert "no sample rows" in _refusal(_write(tmp_path, HEADER + "\n"), skip_bad_rows=True)
    all_bad = "\n".join([HEADER, _row(0.0).replace("1.0", "nan"), "1,2"]) + "\n"
    message = _refusal(_write(tmp_path, all_bad), skip_bad_rows=True)
    assert message.endswith(
        "all 2 sample rows are bad (first: row 2: column 'q1_mm': expected a finite number, got nan)"
    )


def test_quoted_log_round_trips_through_the_careful_path(tmp_path, platform):
    log = _random_log(2_000, np.random.default_rng(4))
    log.stages = ["20kg"] * len(log)  # quoting sends the reader down its careful path
    write_log(tmp_path / "big.csv", log)
    back = read_log(tmp_path / "big.csv", platform)
    np.testing.assert_array_equal(back.readings, without_noise(log.readings))
    assert back.stages == log.stages


# ----------------------------------------------------------------------------- results


def _estimate(rng, covariance: bool = True) -> Estimate:
    return Estimate(rng.normal(0, 1, 42), np.diag(rng.uniform(0.01, 1, 42)) if covariance else None, "ekf", 123)


def test_result_round_trip(tmp_path, platform):
    estimate = _estimate(np.random.default_rng(5))
    result = result_dict(estimate, platform, samples_skipped=4, extra={"condition_number": 12.5})
    write_result(tmp_path / "r.json", result)
    back = read_result(tmp_path / "r.json")
    assert back == without_noise(result)
    assert back["format"] == "stewart-calib/result@1" and back["method"] == "ekf" and back["platform"] == "nim-stewart"
    assert back["parameter_names"] == list(PARAMETER_NAMES)
    np.testing.assert_array_equal(back["error"], without_noise(estimate.error))
    np.testing.assert_array_equal(back["estimate"], without_noise(platform.drive.as_vector() + estimate.error))
    np.testing.assert_array_equal(back["stddev"], without_noise(np.sqrt(np.diag(estimate.covariance))))
    assert (back["samples_used"], back["samples_skipped"], back["condition_number"]) == (123, 4, 12.5)
    no_cov = result_dict(_estimate(np.random.default_rng(6), covariance=False), platform)
    write_result(tmp_path / "r2.json", no_cov)
    assert read_result(tmp_path / "r2.json")["stddev"] is None
    with pytest.raises(ValueError, match="may not replace spec fields: method"):
        result_dict(estimate, platform, extra={"method": "other"})


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda r: r.update(format="stewart-calib/result@2"), "key 'format': expected 'stewart-calib/result@1'"),
        (lambda r: r.pop("error"), "key 'error': expected a value (missing)"),
        (lambda r: r.update(nominal=r["nominal"][:41]), "key 'nominal': expected a list of 42 finite numbers"),
        (lambda r: r["estimate"].__setitem__(3, float("nan")), "key 'estimate': expected a list of 42 finite numbers"),
        (lambda r: r["stddev"].__setitem__(0, "1"), "key 'stddev': expected a list of 42 finite numbers or null"),
        (lambda r: r["stddev"].__setitem__(0, -1.0), "key 'stddev': expected non-negative numbers"),
        (lambda r: r.update(parameter_names=r["parameter_names"][::-1]), "key 'parameter_names': expected the 42"),
        (lambda r: r.update(samples_used=-1), "key 'samples_used': expected a non-negative whole number, got -1"),
        (lambda r: r.update(method=""), "key 'method': expected a non-empty string"),
        (lambda r: r["estimate"].__setitem__(6, r["estimate"][6] + 0.01), "l1 differs by 0.01 mm"),
    ],
)
def test_result_validation_names_the_key(tmp_path, platform, change, expected):
    result = result_dict(_estimate(np.random.default_rng(7)), platform)
    change(result)
    path = tmp_path / "r.json"
    path.write_text(json.dumps(result))
    with pytest.raises(CalibError, match=f"^{path}: ") as info:
        read_result(path)
    assert expected in str(info.value)
    with pytest.raises(CalibError):
        write_result(tmp_path / "out.json", result)
    assert not (tmp_path / "out.json").exists()


def test_read_result_refuses_non_json(tmp_path):
    path = _write(tmp_path, "{not json", "r.json")
    with pytest.raises(CalibError, match=r"r\.json: not valid JSON \(line 1, column 2"):
        read_result(path)


# ----------------------------------------------------------------------------- atomic writes


def test_atomic_write_replaces_whole_file_and_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    atomic_write_text(target, "first")
    atomic_write_text(target, "second")
    assert target.read_text() == "second"
    assert oct(target.stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    (tmp_path / "adir").mkdir()
    with pytest.raises(CalibError, match="adir: is a directory; expected a file path"):
        atomic_write_text(tmp_path / "adir", "x")  # refused before a temporary file exists
    with pytest.raises(CalibError, match="cannot write"):
        atomic_write_text(tmp_path / "missing" / "out.txt", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir", "out.txt"]
    assert list((tmp_path / "adir").iterdir()) == []


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@pytest.mark.parametrize("chunk_rows", [3, 4096])
def test_csv_text_writes_what_the_csv_module_writes(monkeypatch, chunk_rows):
    # Columns of numbers (and empty fields) are joined directly, a few rows at a time; anything
    # else goes through the csv module. Both must give the csv module's text.
    import csv
    import io as text_io

    from stewart_calib.io import tables

    def reference(header, columns):
        buffer = text_io.StringIO()
        writer = csv.writer(buffer, lineterminator="\n")
        writer.writerow(header)
        # every float as its 15 significant digits
        rows = zip(*(without_noise(c.tolist() if isinstance(c, np.ndarray) else list(c)) for c in columns), strict=True)
        writer.writerows(rows)
        return buffer.getvalue()

    monkeypatch.setattr(tables, "CSV_CHUNK_ROWS", chunk_rows)
    rng = np.random.default_rng(3)
    cases = [
        (["t_s", "x", "y"], [rng.normal(size=10), np.arange(10), [*rng.normal(size=9).tolist(), ""]]),
        (["a", "b"], [np.array([1.5, np.nan, np.inf, -0.0, 1e-300]), [1.0, "", 3, 2.5e300, -7]]),
        (["a", "b"], [np.zeros(0), []]),
        (["a", "stage"], [np.arange(3.0), ["x", "y,z", ""]]),  # text: the csv module quotes
        (["a", "b"], [np.array([True, False]), np.ones(2)]),
        # runs of floats between integers and text, one float column alone, float32, text quoted
        # or not (quotes, line breaks, spaces, a lone empty field), repeated over the rows
        (
            ["t", "i", "x", "y", "stage", "z"],
            [
                rng.normal(size=8) * 1e5,
                np.arange(8),
                rng.normal(size=8),
                rng.normal(size=8).astype(np.float32),
                ['a "b"', "c\nd", "e\rf", " g ", "", "ü,v", "x", "x"],
                np.r_[np.nan, -np.inf, rng.normal(size=6)],
            ],
        ),
        (["x", "stage"], [np.array([0.1, 2.0 / 3.0]), ["", ""]]),
    ]
    for header, columns in cases:
        assert tables.csv_text(header, columns) == reference(header, columns)
        assert tables.csv_text(header, columns, with_header=False) == reference(header, columns).split("\n", 1)[1]


def test_blocks_write_csv_texts_file_whatever_their_sizes(monkeypatch, tmp_path):
    """write_csv_blocks gives csv_text's bytes with blocks of any size: a large file's remainders
    (rows after the last whole chunk of a block) are written by pyarrow too, small files by repr."""
    from stewart_calib.io import tables

    monkeypatch.setattr(tables, "CSV_CHUNK_ROWS", 4)
    rng = np.random.default_rng(5)
    columns = [
        np.r_[rng.normal(size=20) * 10.0 ** rng.integers(-8, 17, 20), 0.0, -0.0, 1e9, 123.0],
        rng.normal(size=24),
    ]
    columns[1][[3, 17]] = np.nan
    expected = tables.csv_text(["a", "b"], [columns[0], ["" if np.isnan(v) else v for v in columns[1]]])
    for sizes in ([2, 1, 21], [7, 5, 1, 11], [24]):
        edges = np.cumsum([0, *sizes])
        blocks = [[c[lo:hi] for c in columns] for lo, hi in itertools.pairwise(edges)]
        assert tables.write_csv_blocks(tmp_path / "t.csv", ["a", "b"], blocks, blank=(1,)) == 24
        assert (tmp_path / "t.csv").read_text() == expected, sizes


def test_background_writer_writes_in_order_and_raises_a_failure_on_the_next_call(tmp_path):
    target = tmp_path / "out.txt"
    with BackgroundWriter() as writer:
        for k in range(50):
            writer.submit(target, lambda k=k: f"write {k}".encode())
    assert target.read_text() == "write 49"
    writer = BackgroundWriter()
    writer.submit(tmp_path / "missing" / "out.txt", lambda: b"x")
    writer.submit(target, lambda: b"after the failure")  # may be taken before the failure is known
    with pytest.raises(CalibError, match=r"missing/out\.txt: cannot write"):
        writer.close()
    assert target.read_text() == "write 49"  # nothing written after a failed write
    with pytest.raises(CalibError, match="cannot write"):
        writer.submit(target, lambda: b"x")  # the failure stays raised


def test_background_writer_lets_the_callers_error_through_and_finishes_first(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(ValueError, match="the caller's"):
        with BackgroundWriter() as writer:
            writer.submit(tmp_path / "missing" / "out.txt", lambda: b"x")
            writer.submit(target, lambda: b"y")
            raise ValueError("the caller's")
    assert not target.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == []
