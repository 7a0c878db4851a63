"""Temperature and tilt in the files (spec §17): ``[thermal]`` and ``[elastic] gravity`` in the platform
file, every refusal one line naming file and key; the log's ``temp1_C … temp6_C`` / ``temp_C`` and
``gravity_x/y/z`` columns as input channels in every reader path (the block reader's text, loadtxt and
pyarrow paths, the row parser's plain, careful and block paths), their refusals naming row and column;
the writer's round trip; the result's ``"thermal"`` block; a controller's temperature columns in an
import's mapping."""

from __future__ import annotations

import copy
import tomllib
from dataclasses import replace

import numpy as np
import pytest

from stewart_calib.config import NoiseConfig
from stewart_calib.errors import CalibError, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import (
    GRAVITY_COLUMNS,
    TEMPERATURE_COLUMNS,
    LogRowParser,
    calibrated_drive,
    log_text,
    read_log,
    read_log_blocks,
    read_pose_list,
    read_pose_list_blocks,
    result_dict,
    validate_result,
    write_log,
)
from stewart_calib.io.exports import stroke_columns
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.model.drive import THERMAL, drive_model
from stewart_calib.model.platform import DOWN, Elastic, Thermal
from stewart_calib.model.unknowns import UnknownLayout
from stewart_calib.samples import GRAVITY, LOAD_KG, TEMPERATURE_C, Log
from tests.synthetic import ROOT, nim_stewart

SOURCE = "thermal.toml"
ALPHA = [11.5, 12.0, 10.5, 23.0, -1.0, 0.0]


@pytest.fixture(scope="module")
def doc() -> dict:
    """nim-stewart's document with ``[thermal]`` and ``[elastic]`` (without ``[workspace]``, whose home
    check the file tests here do not need)."""
    document = tomllib.loads(platform_to_toml(replace(nim_stewart(), workspace=None)))
    document["thermal"] = {"reference_temperature_C": 21.5, "expansion_ppm_per_K": ALPHA}
    document["elastic"] = {"platform_mass_kg": 60.0, "platform_com_mm": [0.0, 0.0, -50.0]}
    return document


def _with(doc: dict, table: str, **keys) -> dict:
    changed = copy.deepcopy(doc)
    changed[table].update(keys)
    return changed


def _refusal(doc: dict) -> str:
    with pytest.raises(CalibError) as info:
        parse_platform(doc, SOURCE)
    message = str(info.value)
    assert message.startswith(f"{SOURCE}: ") and "\n" not in message
    return message


# ----------------------------------------------------------------------------- [thermal]


def test_thermal_table_is_read_with_its_defaults(doc):
    minimal = copy.deepcopy(doc)
    minimal["thermal"] = {}
    thermal = parse_platform(minimal, SOURCE).thermal
    assert thermal.reference_temperature_C == 20.0 and thermal.expansion_sigma_ppm_per_K == 20.0
    assert thermal.expansion_ppm_per_K.tolist() == [0.0] * 6 and thermal.true_expansion_ppm_per_K is None
    full = _with(doc, "thermal", expansion_sigma_ppm_per_K=0, true_expansion_ppm_per_K=[12.0] * 6)
    thermal = parse_platform(full, SOURCE).thermal
    assert thermal.reference_temperature_C == 21.5 and thermal.expansion_ppm_per_K.tolist() == ALPHA
    assert thermal.expansion_sigma_ppm_per_K == 0.0 and thermal.true_expansion_ppm_per_K.tolist() == [12.0] * 6
    without = copy.deepcopy(doc)
    del without["thermal"]
    assert parse_platform(without, SOURCE).thermal is None


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        (
            {"reference_temperature_C": 151.0},
            "key 'thermal.reference_temperature_C': expected a temperature within [-50, 150] °C (where the "
            "geometry of [drive] holds), got 151.0",
        ),
        ({"reference_temperature_C": -50.5}, "key 'thermal.reference_temperature_C': expected a temperature within"),
        ({"reference_temperature_C": "20"}, "key 'thermal.reference_temperature_C': expected a finite number"),
        ({"reference_temperature_C": float("nan")}, "key 'thermal.reference_temperature_C': expected a finite number"),
        (
            {"expansion_ppm_per_K": [11.5, 11.5, 11.5, 11.5, 11.5, 100.5]},
            "key 'thermal.expansion_ppm_per_K': expected 6 expansion coefficients α_i within ±100 ppm/K (steel's "
            "is about 11.5, aluminium's 23), got [11.5, 11.5, 11.5, 11.5, 11.5, 100.5]",
        ),
        ({"expansion_ppm_per_K": [11.5] * 5}, "key 'thermal.expansion_ppm_per_K': expected a list of 6 numbers, got"),
        ({"expansion_ppm_per_K": ["11.5"] * 6}, "key 'thermal.expansion_ppm_per_K': expected a list of 6 numbers of"),
        ({"true_expansion_ppm_per_K": [-101.0] * 6}, "key 'thermal.true_expansion_ppm_per_K': expected 6 expansion"),
        (
            {"expansion_sigma_ppm_per_K": -1.0},
            "key 'thermal.expansion_sigma_ppm_per_K': expected a σ ≥ 0 (0: known exactly), got -1.0",
        ),
        ({"expansion_ppm_per_k": ALPHA}, "unknown key 'thermal.expansion_ppm_per_k' (did you mean"),
    ],
)
def test_a_bad_thermal_key_is_refused_naming_it(doc, keys, expected):
    assert _refusal(_with(doc, "thermal", **keys)).startswith(f"{SOURCE}: {expected}")


def test_a_thermal_key_that_is_no_table_is_refused(doc):
    bad = copy.deepcopy(doc)
    bad["thermal"] = 20.0
    assert _refusal(bad) == f"{SOURCE}: key 'thermal': expected a [thermal] table"


def test_a_rotary_drive_reads_thermal_and_its_model_grows_the_rods():
    servo = tomllib.loads((ROOT / "configs" / "platforms" / "servo-hexapod.toml").read_text())
    del servo["workspace"]
    servo["thermal"] = {"expansion_ppm_per_K": ALPHA}
    platform = parse_platform(servo, SOURCE)
    assert platform.thermal.expansion_ppm_per_K.tolist() == ALPHA
    drive = drive_model(platform, NoiseConfig())
    assert [block.key for block in drive.blocks][-1] == "thermal"  # spec §17: the rods grow (model/rotary.py)


# ----------------------------------------------------------------------------- [elastic] gravity


def test_elastic_gravity_is_normalised_and_defaults_down(doc):
    assert parse_platform(doc, SOURCE).elastic.gravity.tolist() == DOWN.tolist()
    tilted = parse_platform(_with(doc, "elastic", gravity=[0.0, 3.0, -4.0]), SOURCE).elastic.gravity
    np.testing.assert_allclose(tilted, [0.0, 0.6, -0.8], rtol=0, atol=1e-16)


@pytest.mark.parametrize(
    ("gravity", "expected"),
    [
        ([0, 0, 0], "key 'elastic.gravity': expected a direction [gx, gy, gz] in {J} of nonzero length (default"),
        ([0.0, -1.0], "key 'elastic.gravity': expected a list of 3 numbers, got shape (2,)"),
        ([0.0, float("inf"), -1.0], "key 'elastic.gravity': expected a list of 3 numbers of finite numbers"),
    ],
)
def test_a_bad_gravity_is_refused_naming_it(doc, gravity, expected):
    assert _refusal(_with(doc, "elastic", gravity=gravity)).startswith(f"{SOURCE}: {expected}")


# ----------------------------------------------------------------------------- round trips


def test_thermal_and_gravity_round_trip_through_the_platform_file(doc):
    rng = np.random.default_rng(17)
    platform = parse_platform(
        _with(
            _with(
                doc,
                "thermal",
                expansion_sigma_ppm_per_K=3.25,
                true_expansion_ppm_per_K=rng.uniform(-90, 90, 6).tolist(),
            ),
            "elastic",
            gravity=rng.normal(size=3).tolist(),
        ),
        SOURCE,
    )
    text = platform_to_toml(platform)
    back = parse_platform(tomllib.loads(text), SOURCE)
    for name in (
        "reference_temperature_C",
        "expansion_ppm_per_K",
        "expansion_sigma_ppm_per_K",
        "true_expansion_ppm_per_K",
    ):
        np.testing.assert_array_equal(getattr(back.thermal, name), without_noise(getattr(platform.thermal, name)))
    # a unit vector, normalised again on reading its 15 digits
    np.testing.assert_allclose(back.elastic.gravity, platform.elastic.gravity, rtol=5e-15, atol=0)
    assert platform_to_toml(back) == text
    # the default direction is not written: a platform without a tilt writes what it always did
    assert "gravity" not in platform_to_toml(parse_platform(doc, SOURCE))


def test_platform_out_writes_the_identified_expansion(doc):
    """``--platform-out``: the calibrated drive onto the platform, then its file, gives the expansion
    the calibration found as ``[thermal] expansion_ppm_per_K``."""
    platform = parse_platform(doc, SOURCE)
    found = np.array([9.0, 10.0, 11.0, 12.0, 13.0, 14.0])
    drive = drive_model(platform).calibrated(np.zeros(42), {THERMAL: found})
    written = tomllib.loads(platform_to_toml(drive.onto(platform)))
    assert written["thermal"]["expansion_ppm_per_K"] == found.tolist()
    assert written["thermal"]["reference_temperature_C"] == 21.5


# ----------------------------------------------------------------------------- logs

HEADER = ["t_s", *(f"q{i}_mm" for i in range(1, 7)), *(f"s{i}_mm" for i in range(1, 7))]


def _thermal_platform(elastic: bool = False):
    platform = replace(nim_stewart(), thermal=Thermal())
    return replace(platform, elastic=Elastic(60.0, np.array([0.0, 0.0, -50.0]))) if elastic else platform


def _csv(tmp_path, extra: list[str], rows: list[list[str]], name: str = "log.csv"):
    """A log of ``rows`` (the extra columns' fields; strokes and readings all 1 and 2) at t = 0, 1, …"""
    lines = [",".join([*HEADER, *extra])]
    lines += [",".join([repr(float(k)), *["1.0"] * 6, *["2.0"] * 6, *fields]) for k, fields in enumerate(rows)]
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _refusal_of_log(path, platform=None, **kwargs) -> str:
    with pytest.raises(CalibError) as info:
        read_log(path, platform, **kwargs)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    return message[len(f"{path}: ") :]


def test_per_leg_temperatures_are_one_channel_and_win_over_temp_c(tmp_path):
    temps = [[str(20.0 + leg + row / 4) for leg in range(6)] for row in range(3)]
    log = read_log(_csv(tmp_path, [*TEMPERATURE_COLUMNS, "temp_C"], [[*t, "99.5"] for t in temps]))
    assert log.inputs.keys() == {TEMPERATURE_C}
    np.testing.assert_array_equal(log.inputs[TEMPERATURE_C], np.array(temps, dtype=float))
    # temp_C beside them is ignored, not read: a text there refuses nothing
    log = read_log(_csv(tmp_path, [*TEMPERATURE_COLUMNS, "temp_C"], [[*t, "warm"] for t in temps]))
    np.testing.assert_array_equal(log.inputs[TEMPERATURE_C], np.array(temps, dtype=float))


def test_one_temperature_is_every_legs(tmp_path):
    log = read_log(_csv(tmp_path, ["temp_C"], [["19.5"], ["31.25"]]))
    np.testing.assert_array_equal(log.inputs[TEMPERATURE_C], [[19.5] * 6, [31.25] * 6])


def test_some_of_the_per_leg_temperatures_are_refused_naming_the_missing(tmp_path):
    path = _csv(tmp_path, ["temp1_C", "temp2_C", "temp4_C", "temp_C"], [["20", "20", "20", "20"]])
    assert _refusal_of_log(path) == (
        "row 1: columns temp1_C, temp2_C, temp3_C, temp4_C, temp5_C, temp6_C come all six or none; "
        "missing temp3_C, temp5_C, temp6_C"
    )


@pytest.mark.parametrize("value", ["150.5", "-51", "inf", "293.15"])
def test_a_temperature_out_of_range_is_refused_or_skipped(tmp_path, value):
    path = _csv(tmp_path, ["temp_C"], [["20"], [value], ["21"]])
    reason = f"column 'temp_C': expected a temperature within [-50, 150] °C (spec §17), got {float(value)!r}"
    assert _refusal_of_log(path) == f"row 3: {reason}"
    assert _refusal_of_log(path, _thermal_platform()) == f"row 3: {reason}"
    log = read_log(path, _thermal_platform(), skip_bad_rows=True)
    assert log.t_s.tolist() == [0.0, 2.0] and log.skipped == [(3, reason)]


def test_thermal_needs_a_temperature_in_every_row(tmp_path):
    platform = _thermal_platform()
    assert _refusal_of_log(_csv(tmp_path, ["load_kg"], [["0"]]), platform) == (
        "row 1: missing column(s) temp1_C … temp6_C or temp_C: each leg's temperature [°C], an input where the "
        "platform has [thermal] (spec §17)"
    )
    path = _csv(tmp_path, list(TEMPERATURE_COLUMNS), [["20"] * 6, ["20", "20", "", "20", "20", "20"], ["21"] * 6])
    reason = (
        "column 'temp3_C': expected each leg's temperature [°C] in every row where the platform has [thermal] "
        "(spec §17), got none"
    )
    assert _refusal_of_log(path, platform) == f"row 3: {reason}"
    assert read_log(path, platform, skip_bad_rows=True).skipped == [(3, reason)]
    # without [thermal] a temperature is not needed: an empty field is one not known
    log = read_log(path, nim_stewart())
    assert np.isnan(log.inputs[TEMPERATURE_C][1, 2]) and np.isfinite(np.delete(log.inputs[TEMPERATURE_C], 8)).all()


def test_gravity_columns_are_normalised_rows(tmp_path):
    rows = [["0", "0", "-9.80665"], ["0", "3", "-4"], ["1e200", "0", "-1e200"], ["0", "1e-320", "0"]]
    log = read_log(_csv(tmp_path, list(GRAVITY_COLUMNS), rows))
    half = np.sqrt(0.5)  # no square of a component overflows or underflows: the largest is scaled out first
    expected = [[0, 0, -1], [0, 0.6, -0.8], [half, 0, -half], [0, 1, 0]]
    np.testing.assert_allclose(log.inputs[GRAVITY], expected, rtol=0, atol=2e-16)


def test_gravity_columns_come_all_three_or_none(tmp_path):
    assert _refusal_of_log(_csv(tmp_path, ["gravity_x", "gravity_z"], [["0", "-1"]])) == (
        "row 1: columns gravity_x, gravity_y, gravity_z come all three or none; missing gravity_y"
    )


@pytest.mark.parametrize(
    ("fields", "reason", "elastic_only"),
    [
        (
            ["0", "0", "0"],
            "columns gravity_x, gravity_y, gravity_z: expected the direction of gravity in {J}, of nonzero length "
            "(spec §17), got [0.0, 0.0, 0.0]",
            False,
        ),
        (
            ["0", "", "-1"],
            "column 'gravity_y': expected all three of gravity_x, gravity_y, gravity_z or none (spec §17)",
            False,
        ),
        (["0", "-inf", "-1"], "column 'gravity_y': expected a finite number, got -inf", False),
        (
            ["", "", ""],
            "column 'gravity_x': expected the direction of gravity in {J} in every row where the platform has "
            "[elastic] and the log its columns (spec §17), got none",
            True,
        ),
    ],
)
def test_a_bad_gravity_row_is_refused_or_skipped(tmp_path, fields, reason, elastic_only):
    path = _csv(tmp_path, list(GRAVITY_COLUMNS), [["0", "0", "-1"], fields])
    elastic = _thermal_platform(elastic=True)
    assert _refusal_of_log(path, replace(elastic, thermal=None)) == f"row 3: {reason}"
    assert read_log(path, replace(elastic, thermal=None), skip_bad_rows=True).skipped == [(3, reason)]
    if elastic_only:
        assert np.isnan(read_log(path).inputs[GRAVITY][1]).all()
    else:
        assert _refusal_of_log(path) == f"row 3: {reason}"


def test_load_kg_keeps_its_meaning_as_a_channel(tmp_path):
    """A payload not known (an empty field) reads as NaN where it is no input, and the channel holds the
    column as read: the semantics of ``load_kg`` unchanged."""
    log = read_log(_csv(tmp_path, ["load_kg"], [["20"], [""], ["nan"]]))
    np.testing.assert_array_equal(log.inputs[LOAD_KG], [20.0, np.nan, np.nan])
    assert read_log(_csv(tmp_path, ["stage"], [["a"]])).inputs == {}


def _channels_log(n: int, rng: np.random.Generator) -> Log:
    direction = rng.normal(size=(n, 3))
    return Log(
        t_s=np.arange(n) * 0.01,
        strokes=rng.uniform(-100, 100, (n, 6)),
        readings=rng.uniform(-100, 100, (n, 6)),
        inputs={
            LOAD_KG: rng.choice([0.0, 20.0, 40.0], n),
            TEMPERATURE_C: rng.uniform(15.0, 35.0, (n, 6)),
            GRAVITY: direction / np.linalg.norm(direction, axis=1, keepdims=True),
        },
    )


def _assert_same_inputs(found, expected) -> None:
    assert found.keys() == expected.keys()
    for name, values in expected.items():
        np.testing.assert_array_equal(found[name], without_noise(values), err_msg=name)  # a file's 15 digits


def test_a_simulated_log_round_trips_its_channels(tmp_path):
    log = _channels_log(50, np.random.default_rng(3))
    write_log(tmp_path / "log.csv", log)
    header = (tmp_path / "log.csv").read_text().split("\n", 1)[0].split(",")
    assert header[13:] == ["load_kg", *TEMPERATURE_COLUMNS, *GRAVITY_COLUMNS]
    _assert_same_inputs(read_log(tmp_path / "log.csv", _thermal_platform(elastic=True)).inputs, log.inputs)


def test_the_writer_leaves_a_temperature_not_known_empty(tmp_path):
    log = _channels_log(2, np.random.default_rng(4))
    log.inputs[TEMPERATURE_C][1, 4] = np.nan
    text = log_text(log)
    assert text.split("\n")[2].split(",")[14 + 4] == ""
    _assert_same_inputs(read_log(_written(tmp_path, text)).inputs, log.inputs)


def _written(tmp_path, text: str, name: str = "log.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_log_with_channels_reads_as_a_pose_list(tmp_path):
    """A simulated log with its channels is also a pose list (``compensate``, ``validate``): its poses,
    by pyarrow where the file is large, whatever the channels hold."""
    rng = np.random.default_rng(5)
    log = replace(_channels_log(3000, rng), desired_poses=np.c_[rng.normal(0, 100, (3000, 3)), np.zeros((3000, 3))])
    path = _written(tmp_path, log_text(log))
    poses = read_pose_list(path)
    np.testing.assert_array_equal(poses[:, :3], without_noise(log.desired_poses[:, :3]))
    assert len(list(read_pose_list_blocks(path, block_bytes=1 << 14))) > 3


def test_every_reader_path_gives_the_same_channels(tmp_path):
    """The block reader (loadtxt on a small file, pyarrow on blocks of a larger one, the csv module
    where a field is quoted) and the row parser (plain rows, the careful path, blocks by pyarrow
    and by float) read the same channels from the same rows."""
    rng = np.random.default_rng(8)
    log = _channels_log(200, rng)
    log.inputs[TEMPERATURE_C][:, 3] = 150.0  # the range's bounds are inclusive
    log.inputs[TEMPERATURE_C][:, 2] = -50.0
    platform = _thermal_platform(elastic=True)
    text = log_text(log)
    path = _written(tmp_path, text)
    expected = without_noise(log.inputs)  # what the file holds: 15 significant digits
    _assert_same_inputs(read_log(path, platform).inputs, expected)  # loadtxt
    blocks = list(read_log_blocks(path, platform, block_bytes=4096))  # pyarrow, block by block
    assert len(blocks) > 3
    _assert_same_inputs(Log.concatenate(blocks).inputs, expected)
    lines = text.splitlines()
    quoted = [lines[0], *(line.replace(",", ',"', 1).replace(",", '",', 2).replace('",', ",", 1) for line in lines[1:])]
    careful = _written(tmp_path, "\n".join(quoted) + "\n", "quoted.csv")
    _assert_same_inputs(read_log(careful, platform).inputs, expected)

    parser = LogRowParser(str(path), lines[0], platform)
    plain = [parser.parse(line, row) for row, line in enumerate(lines[1:], start=2)]
    parser = LogRowParser(str(path), lines[0], platform)
    by_careful = [parser.parse(line, row) for row, line in enumerate(quoted[1:], start=2)]
    for samples in (plain, by_careful):
        for name, values in expected.items():
            np.testing.assert_array_equal(np.array([sample.inputs[name] for sample in samples]), values)
    for size in (200, 40):  # pyarrow from 64 rows on, else float on each field
        parser = LogRowParser(str(path), lines[0], platform)
        block = parser.parse_block([line.encode() for line in lines[1 : 1 + size]])
        assert block is not None
        _assert_same_inputs(block.inputs, {name: values[:size] for name, values in expected.items()})


def test_the_row_parser_refuses_as_read_log(tmp_path):
    """A row the fast paths cannot take goes the careful way, refused in read_log's words; a block
    holding it is left to the rows one by one."""
    platform = _thermal_platform(elastic=True)
    rows = [
        [*["20"] * 6, "0", "0", "-1"],
        [*["20"] * 5, "", "0", "0", "-1"],
        [*["20"] * 5, "151", "0", "0", "-1"],
        [*["20"] * 6, "0", "0", "0"],
        [*["20"] * 6, "", "", ""],
    ]
    path = _csv(tmp_path, [*TEMPERATURE_COLUMNS, *GRAVITY_COLUMNS], rows)
    lines = path.read_text().splitlines()
    whole = read_log(path, platform, skip_bad_rows=True)
    assert [row for row, _ in whole.skipped] == [3, 4, 5, 6]
    parser = LogRowParser(str(path), lines[0], platform)
    assert parser.parse_block([line.encode() for line in lines[1:]]) is None
    refused = []
    for row, line in enumerate(lines[1:], start=2):
        try:
            parser.parse(line, row)
        except CalibError as err:
            refused.append(str(err))
    assert refused == [f"{path}: row {row}: {reason}" for row, reason in whole.skipped]
    with pytest.raises(CalibError, match=r"row 1: missing column\(s\) temp1_C … temp6_C or temp_C"):
        LogRowParser(str(path), ",".join(HEADER), platform)


# ----------------------------------------------------------------------------- results


def _thermal_estimate(platform, sigma_ppm_per_K: float):
    drive = drive_model(
        replace(platform, thermal=replace(platform.thermal, expansion_sigma_ppm_per_K=sigma_ppm_per_K)), NoiseConfig()
    )
    layout = UnknownLayout(drive.blocks, n_params=42)
    rng = np.random.default_rng(2)
    x = rng.normal(0.0, 0.01, layout.size)
    P = np.diag(rng.uniform(1e-4, 1e-2, layout.size))
    return Estimate.of_state(x, P, layout, "ls", 100), x[42:]


def test_the_result_has_the_thermal_block_whenever_thermal_is_declared():
    platform = replace(nim_stewart(), thermal=Thermal(20.0, np.array(ALPHA), 20.0))
    estimate, error = _thermal_estimate(platform, 20.0)
    result = result_dict(estimate, platform)
    assert result[THERMAL]["names"] == [f"alpha{i}" for i in range(1, 7)]
    np.testing.assert_allclose(result[THERMAL]["estimate"], np.array(ALPHA) + error, rtol=0, atol=1e-12)
    validate_result(result, "r.json")
    drive = calibrated_drive(platform, result, "r.json")
    assert drive.terms[-1].key == THERMAL and drive.terms[-1].nominal.tolist() == result[THERMAL]["estimate"]
    # held at nominal (σ 0): the block is the nominal, known exactly
    held = replace(platform, thermal=replace(platform.thermal, expansion_sigma_ppm_per_K=0.0))
    estimate = Estimate(np.zeros(42), np.eye(42), "ls", 10)
    assert result_dict(estimate, held)[THERMAL] == {
        "names": [f"alpha{i}" for i in range(1, 7)],
        "estimate": ALPHA,
        "stddev": [0.0] * 6,
    }
    assert THERMAL not in result_dict(estimate, nim_stewart())


@pytest.mark.parametrize(
    ("block", "expected"),
    [
        ({"names": [f"a{i}" for i in range(1, 7)]}, 'key \'thermal.names\': expected ["alpha1", ..., "alpha6"]'),
        (
            {"estimate": [0.0] * 5 + [101.0]},
            "key 'thermal.estimate': expected expansion coefficients α_i within ±100 ppm/K",
        ),
        ({"stddev": [1.0] * 5}, "key 'thermal.stddev': expected a list of 6 finite numbers or null"),
    ],
)
def test_a_bad_thermal_block_is_refused(block, expected):
    platform = replace(nim_stewart(), thermal=Thermal())
    result = result_dict(Estimate(np.zeros(42), None, "ls", 10), platform)
    result[THERMAL] = {**result[THERMAL], **block}
    with pytest.raises(CalibError) as info:
        validate_result(result, "r.json")
    assert str(info.value).startswith(f"r.json: {expected}")


# ----------------------------------------------------------------------------- import mapping


def test_a_controllers_temperature_columns_map_like_its_strokes(tmp_path):
    mapping = tmp_path / "m.toml"
    table = {"time": "t", "columns": [f"enc{i}" for i in range(1, 7)], "temperatures": ["T"], "temperature_unit": "K"}
    columns = stroke_columns(mapping, table)
    assert columns.read_columns == [*table["columns"], "T"] and columns.log_columns == TEMPERATURE_COLUMNS
    assert "temperatures in K (one for all legs)" in columns.what
    raw = np.array([[1.0, 2, 3, 4, 5, 6, 293.15], [0, 0, 0, 0, 0, 0, 303.15]])
    np.testing.assert_allclose(
        columns.convert_row(raw), np.c_[raw[:, :6], np.full((2, 6), [[20.0], [30.0]])], atol=1e-12
    )
    per_leg = stroke_columns(
        mapping, {**table, "temperatures": [f"T{i}" for i in range(1, 7)], "temperature_unit": "C"}
    )
    np.testing.assert_array_equal(per_leg.convert_row(np.arange(12.0)[None])[0, 6:], np.arange(6.0, 12.0))
    assert stroke_columns(mapping, {k: v for k, v in table.items() if not k.startswith("temp")}).log_columns == ()


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        (
            {"temperatures": ["T1", "T2"]},
            "'strokes.temperatures': expected the temperature column names of legs 1..6, or one for all legs "
            "(spec §17), got ['T1', 'T2']",
        ),
        (
            {"temperatures": ["enc3"]},
            "column 'enc3' is named as 'strokes.columns' and as 'strokes.temperatures'; expected a different "
            "column for each",
        ),
        ({"temperatures": ["T"], "temperature_unit": "F"}, "'strokes.temperature_unit': expected one of C, K, got 'F'"),
    ],
)
def test_a_bad_temperature_mapping_is_refused(tmp_path, keys, expected):
    table = {"time": "t", "columns": [f"enc{i}" for i in range(1, 7)], **keys}
    with pytest.raises(CalibError) as info:
        stroke_columns(tmp_path / "m.toml", table)
    assert str(info.value) == f"{tmp_path / 'm.toml'}: {expected}"
