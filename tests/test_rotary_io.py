"""A rotary (servo-horn, 6-RSS) drive's files (spec §15): its platform table, every refusal one line
naming file and key or row, the round trip of a calibrated table, the log's ``q{i}_deg`` columns, and
results and truth files holding the 66 parameters with their angles in degrees."""

from __future__ import annotations

import copy
import math
import tomllib

import numpy as np
import pytest

from stewart_calib.errors import CalibError, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import (
    calibrated_drive,
    log_text,
    read_log,
    read_result,
    read_truth,
    result_dict,
    truth_text,
    write_log,
    write_result,
)
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.samples import Log, Truth
from tests.synthetic import ROOT, nim_stewart

SERVO = ROOT / "configs" / "platforms" / "servo-hexapod.toml"
SOURCE = "servo.toml"


def _doc(workspace: bool = False) -> dict:
    """The shipped servo platform's document; without ``[workspace]`` unless asked (its home check
    needs the legs' inverse kinematics, which the file tests here do not)."""
    doc = tomllib.loads(SERVO.read_text())
    if not workspace:
        del doc["workspace"]
    return doc


def _servo(workspace: bool = False):
    return parse_platform(_doc(workspace), SOURCE)


def _refusal(doc: dict) -> str:
    with pytest.raises(CalibError) as info:
        parse_platform(doc, SOURCE)
    message = str(info.value)
    assert message.startswith(f"{SOURCE}: ") and "\n" not in message
    return message


def test_servo_platform_parses_into_rotary_legs():
    platform = _servo()
    legs = platform.drive
    assert legs.kind == "rotary" and legs.n_params == 66 and platform.stroke_range is None
    assert legs.angle_range == pytest.approx((math.radians(-75.0), math.radians(75.0)))
    np.testing.assert_allclose(np.linalg.norm(legs.crank_axes, axis=1), 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.einsum("ij,ij->i", legs.crank_axes, legs.zero_directions), 0.0, atol=1e-15)
    # a positive angle lifts every horn (the file's header says so)
    np.testing.assert_allclose(legs.w_directions, np.tile([0.0, 0.0, 1.0], (6, 1)), atol=1e-6)
    np.testing.assert_array_equal(legs.horn_lengths, 25.0)
    np.testing.assert_array_equal(legs.angle_offsets, 0.0)


def _tilt_zero_direction(doc: dict, row: int, along: float) -> None:
    """Add ``along`` times its axis to a zero direction of ``doc`` (``asin(along)`` off orthogonal)."""
    drive = doc["drive"]
    drive["crank_zero_directions"][row] = (
        np.array(drive["crank_zero_directions"][row]) + along * np.array(drive["crank_axes"][row])
    ).tolist()


def test_axes_are_normalised_and_zero_directions_made_orthogonal():
    doc = _doc()
    doc["drive"]["crank_axes"][0] = [-9.65926, 2.58819, 0.0]  # ten times as long
    _tilt_zero_direction(doc, 1, 0.01)  # 0.57° off orthogonal
    legs = parse_platform(doc, SOURCE).drive
    np.testing.assert_allclose(legs.crank_axes[0], _servo().drive.crank_axes[0], atol=1e-15)
    assert abs(legs.crank_axes[1] @ legs.zero_directions[1]) < 1e-15
    assert np.linalg.norm(legs.zero_directions[1]) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (
            lambda d: d["drive"]["crank_axes"].__setitem__(2, [0.0, 0.0, 0.0]),
            "key 'drive.crank_axes[3]': expected a direction [x, y, z] of nonzero length",
        ),
        (
            lambda d: d["drive"]["crank_zero_directions"].__setitem__(4, [0.0, 0.0, 0.0]),
            "key 'drive.crank_zero_directions[5]': expected a direction [x, y, z] of nonzero length",
        ),
        (
            lambda d: _tilt_zero_direction(d, 1, 0.02),
            "key 'drive.crank_zero_directions[2]': expected a direction within 1° of orthogonal to its axis "
            "(crank_axes row 2), got one 1.146° from orthogonal",
        ),
        (
            lambda d: d["drive"]["crank_zero_directions"].__setitem__(0, [-0.965926, 0.258819, 0.0]),
            "key 'drive.crank_zero_directions[1]': expected a direction within 1° of orthogonal to its axis "
            "(crank_axes row 1), got one 90° from orthogonal",
        ),
        (
            lambda d: d["drive"].pop("angle_range_deg"),
            "key 'drive.angle_range_deg': expected [min, max] in degrees: the commanded angles the servos accept "
            '(missing; required with kind = "rotary")',
        ),
        (
            lambda d: d["drive"].update(angle_range_deg=[60.0, -60.0]),
            "key 'drive.angle_range_deg': expected [min, max] with min < max, got [60.0, -60.0]",
        ),
        (
            lambda d: d["drive"].update(angle_range_deg=[-200.0, 200.0]),
            "key 'drive.angle_range_deg': expected [min, max] at most 360 deg apart, got [-200.0, 200.0]",
        ),
        (
            lambda d: d["drive"].update(angle_offsets_deg=[0.0, 0.0, 190.0, 0.0, 0.0, 0.0]),
            "key 'drive.angle_offsets_deg': expected 6 zero trims within ±180 deg",
        ),
        (
            lambda d: d["drive"]["horn_lengths_mm"].__setitem__(3, 0.0),
            "key 'drive.horn_lengths_mm': expected 6 positive lengths in mm",
        ),
        (
            lambda d: d["drive"].update(rod_lengths_mm=[150.0] * 5),
            "key 'drive.rod_lengths_mm': expected a list of 6 numbers, got shape (5,)",
        ),
        (lambda d: d["drive"].pop("crank_centres_mm"), "key 'drive.crank_centres_mm': expected 6 rows"),
        (
            lambda d: d["drive"].update(kind="crank"),
            "key 'drive.kind': expected one of 'prismatic', 'rotary', got 'crank'",
        ),
        (
            lambda d: d.update(elastic={"platform_mass_kg": 0.5}),
            "key 'elastic': expected no [elastic] table with [drive] kind = \"rotary\"",
        ),
        (
            lambda d: d["drive"].update(
                crank_centres_mm=(np.array(d["drive"]["crank_centres_mm"]) / 1000).tolist(),
                platform_joints_mm=(np.array(d["drive"]["platform_joints_mm"]) / 1000).tolist(),
                horn_lengths_mm=[0.025] * 6,
                rod_lengths_mm=[0.15] * 6,
            ),
            "[drive]: the geometry looks like metres",
        ),
        (
            lambda d: d["drive"].update(platform_joints_mm=[[10.0, 0.0, 0.0]] * 6),
            "key 'drive.platform_joints_mm': expected 6 joints spread in a plane; joints 1–6 all coincide",
        ),
    ],
)
def test_every_refusal_is_one_line_naming_the_key_or_row(change, expected):
    doc = _doc()
    change(doc)
    assert expected in _refusal(doc)


def test_unknown_key_suggests_the_rotary_key():
    doc = _doc()
    doc["drive"]["horn_length_mm"] = doc["drive"].pop("horn_lengths_mm")
    message = _refusal(doc)
    assert "unknown key 'drive.horn_length_mm' (did you mean 'horn_lengths_mm'?)" in message
    assert "initial_lengths_mm" not in message


def test_unknown_key_of_a_drive_without_kind_names_the_rotary_kind():
    """The issue's new user: a servo table without ``kind`` is a prismatic one; the refusal says which
    kind its keys, and the key a misspelt one meant, belong to — not a prismatic key it resembles."""
    doc = _doc()
    del doc["drive"]["kind"]
    assert _refusal(doc).startswith(
        f"{SOURCE}: unknown key 'drive.crank_centres_mm' (a key of [drive] kind = \"rotary\", spec §15; this [drive] "
        'is kind = "prismatic"); expected one of base_joints_mm'
    )
    prismatic = tomllib.loads((ROOT / "configs" / "platforms" / "hobby-hexapod.toml").read_text())
    prismatic["drive"]["horn_length_mm"] = [25.0] * 6
    message = _refusal(prismatic)
    assert (
        "unknown key 'drive.horn_length_mm' (did you mean 'horn_lengths_mm'? it is a key of [drive] kind = "
        '"rotary" (spec §15); this [drive] is kind = "prismatic")' in message
    )
    assert "initial_lengths_mm'?" not in message


def test_prismatic_key_in_a_rotary_drive_is_refused():
    doc = _doc()
    doc["drive"]["stroke_range_mm"] = [0.0, 90.0]
    message = _refusal(doc)
    assert "unknown key 'drive.stroke_range_mm'" in message and 'this [drive] is kind = "rotary"' in message


def test_explicit_prismatic_kind_is_the_default():
    doc = tomllib.loads((ROOT / "configs" / "platforms" / "nim-stewart.toml").read_text())
    doc["drive"]["kind"] = "prismatic"
    platform = parse_platform(doc, "nim.toml")
    np.testing.assert_array_equal(platform.drive.as_vector(), nim_stewart().drive.as_vector())


def _calibrated_legs(legs, seed: int = 3):
    """``legs`` turned and moved as a calibration would: every entry of δM, tilts and trims included."""
    rng = np.random.default_rng(seed)
    delta = rng.normal(0.0, 0.3, legs.n_params)
    delta[legs.parameter_degrees] = np.radians(rng.normal(0.0, 1.5, int(legs.parameter_degrees.sum())))
    return legs.perturbed(delta)


def _assert_same_legs(a, b, atol: float = 0.0) -> None:
    for name in (
        "crank_centres",
        "crank_axes",
        "zero_directions",
        "horn_lengths",
        "rod_lengths",
        "platform_joints",
        "angle_offsets",
    ):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=atol, err_msg=name)
    np.testing.assert_allclose(a.angle_range, b.angle_range, rtol=0, atol=atol)


def test_rotary_platform_round_trips_through_toml():
    from dataclasses import replace

    platform = _servo()
    calibrated = replace(platform, drive=_calibrated_legs(platform.drive), stroke_scale=np.full(6, 0.01))
    text = platform_to_toml(calibrated)
    assert 'kind = "rotary"' in text and "angle_offsets_deg = [" in text and "base_joints_mm" not in text
    back = parse_platform(tomllib.loads(text), SOURCE)
    # every number to its 15 significant digits (positions of a few hundred mm to 1e-12): positions and lengths
    # exactly those; directions normalised again, angles through degrees
    _assert_same_legs(back.drive, calibrated.drive, atol=1e-12)
    for name in ("crank_centres", "horn_lengths", "rod_lengths", "platform_joints"):
        np.testing.assert_array_equal(getattr(back.drive, name), without_noise(getattr(calibrated.drive, name)))
    np.testing.assert_array_equal(back.stroke_scale, calibrated.stroke_scale)
    assert back.instrument.kind == "pose" and back.name == platform.name
    # the turned axes are written as turned: not the nominal ones
    assert np.max(np.abs(back.drive.crank_axes - platform.drive.crank_axes)) > 1e-3


# ----------------------------------------------------------------------------- logs


def _angle_log(n: int = 5, seed: int = 1) -> Log:
    rng = np.random.default_rng(seed)
    return Log(
        t_s=np.arange(n) * 0.1,
        strokes=np.radians(rng.uniform(-60.0, 60.0, (n, 6))),
        readings=np.c_[rng.normal(0.0, 10.0, (n, 3)), np.radians(rng.normal(0.0, 3.0, (n, 3)))],
    )


def test_rotary_log_columns_are_degrees_and_read_back_in_rad(tmp_path):
    platform = _servo()
    log = _angle_log()
    text = log_text(log, platform)
    header = text.split("\n", 1)[0].split(",")
    assert header[:7] == ["t_s", *(f"q{i}_deg" for i in range(1, 7))]
    first = [float(v) for v in text.split("\n")[1].split(",")]
    np.testing.assert_allclose(first[1:7], np.degrees(log.strokes[0]), rtol=5e-15)  # 15 digits
    write_log(tmp_path / "log.csv", log, platform)
    back = read_log(tmp_path / "log.csv", platform)
    np.testing.assert_allclose(back.strokes, log.strokes, rtol=5e-15, atol=0)
    np.testing.assert_allclose(back.readings, log.readings, rtol=5e-15, atol=1e-18)


def test_rotary_log_with_stroke_columns_is_refused_naming_the_angles(tmp_path):
    platform = _servo()
    text = log_text(_angle_log(), platform).replace("_deg,", "_mm,", 6)
    (tmp_path / "log.csv").write_text(text)
    with pytest.raises(CalibError) as info:
        read_log(tmp_path / "log.csv", platform)
    message = str(info.value)
    assert "\n" not in message
    assert message == (
        f"{tmp_path / 'log.csv'}: row 1: columns q1_mm … q6_mm are another drive's; the platform's [drive] "
        '(kind = "rotary") expects q1_deg … q6_deg (commanded angles [deg], spec §15)'
    )


def test_prismatic_log_with_angle_columns_is_refused_naming_the_strokes(tmp_path):
    text = log_text(_angle_log(), _servo()).split("\n", 1)
    (tmp_path / "log.csv").write_text(text[0].replace("q1_deg", "q1_mm") + "\n" + text[1])
    platform = nim_stewart()
    with pytest.raises(CalibError, match=r"row 1: columns q2_deg … q6_deg are another drive's"):
        read_log(tmp_path / "log.csv", platform)  # a mixed header: the other kind's columns named
    (tmp_path / "log.csv").write_text("\n".join(text))
    with pytest.raises(CalibError) as info:
        read_log(tmp_path / "log.csv", platform)
    assert str(info.value).endswith(
        "row 1: columns q1_deg … q6_deg are another drive's; the platform's [drive] (kind = \"prismatic\") "
        "expects q1_mm … q6_mm (strokes [mm], spec §15)"
    )


def test_rotary_log_angle_outside_the_range_is_refused_or_skipped(tmp_path):
    platform = _servo()
    log = _angle_log()
    log.strokes[2, 4] = math.radians(80.0)
    write_log(tmp_path / "log.csv", log, platform)
    with pytest.raises(CalibError) as info:
        read_log(tmp_path / "log.csv", platform)
    assert "row 4: column 'q5_deg': expected a commanded angle within [-75.0, 75.0] deg (drive.angle_range_deg)" in str(
        info.value
    )
    kept = read_log(tmp_path / "log.csv", platform, skip_bad_rows=True)
    assert len(kept) == 4 and kept.skipped[0][0] == 4


def test_rotary_log_rows_one_at_a_time_match_the_file_reader(tmp_path):
    from stewart_calib.io import LogRowParser

    platform = _servo()
    text = log_text(_angle_log(70), platform)
    header, *rows = text.rstrip("\n").split("\n")
    parser = LogRowParser("live", header, platform)
    one = [parser.parse(row, k + 2) for k, row in enumerate(rows[:5])]
    block = parser.parse_block([row.encode() for row in rows[5:]])
    (tmp_path / "log.csv").write_text(text)
    whole = read_log(tmp_path / "log.csv", platform)
    np.testing.assert_array_equal(np.array([s.strokes for s in one]), whole.strokes[:5])
    np.testing.assert_array_equal(block.strokes, whole.strokes[5:])


# ----------------------------------------------------------------------------- results and truth


def _estimate(legs, seed: int = 5) -> Estimate:
    rng = np.random.default_rng(seed)
    error = rng.normal(0.0, 0.2, legs.n_params)
    error[legs.parameter_degrees] = np.radians(rng.normal(0.0, 1.0, int(legs.parameter_degrees.sum())))
    root = rng.normal(0.0, 1e-2, (legs.n_params, legs.n_params))
    return Estimate(error, root @ root.T, "lm", samples_used=150)


def test_rotary_result_holds_66_names_with_angles_in_degrees(tmp_path):
    platform = _servo()
    legs = platform.drive
    estimate = _estimate(legs)
    result = result_dict(estimate, platform)
    assert len(result["parameter_names"]) == 66 and result["parameter_names"][:11] == [
        "a1x",
        "a1y",
        "a1z",
        "d1x",
        "d1y",
        "d1z",
        "h1",
        "r1",
        "o1",
        "tu1",
        "tw1",
    ]
    degrees = legs.parameter_degrees
    np.testing.assert_allclose(np.array(result["error"])[degrees], np.degrees(estimate.error[degrees]), rtol=1e-15)
    np.testing.assert_array_equal(np.array(result["error"])[~degrees], estimate.error[~degrees])
    np.testing.assert_allclose(np.array(result["stddev"])[degrees], np.degrees(estimate.stddev[degrees]), rtol=1e-14)
    write_result(tmp_path / "r.json", result)
    back = read_result(tmp_path / "r.json")
    assert back == without_noise(result)
    # read back in rad: the same calibrated legs, turned axes and trims included
    _assert_same_legs(calibrated_drive(platform, back, "r.json").legs, legs.perturbed(estimate.error), atol=1e-12)


def test_rotary_result_refused_on_a_prismatic_platform():
    platform = _servo()
    result = result_dict(_estimate(platform.drive), platform)
    with pytest.raises(
        CalibError,
        match="key 'parameter_names': expected the 42 parameters of the prismatic drive of platform 'nim-stewart', "
        "got 66",
    ):
        calibrated_drive(nim_stewart(), result, "r.json")


def test_rotary_covariance_is_scaled_to_degrees():
    from stewart_calib.pipelines.handover import covariance_field

    legs = _servo().drive
    estimate = _estimate(legs)
    covariance = np.array(covariance_field(estimate, legs))
    scale = np.where(legs.parameter_degrees, 180.0 / math.pi, 1.0)
    np.testing.assert_allclose(covariance, estimate.covariance * np.outer(scale, scale), rtol=1e-14)


def test_rotary_truth_round_trips_with_66_names_in_degrees(tmp_path):
    platform = _servo()
    legs = platform.drive
    rng = np.random.default_rng(2)
    params = legs.as_vector() + rng.normal(0.0, 0.01, (4, 66))
    truth = Truth(np.arange(4) * 0.1, params, None, {"stroke_scale": np.full(6, 0.02)})
    text = truth_text(truth, platform=platform)
    header = text.split("\n", 1)[0].split(",")
    assert header[:12] == ["t_s", *legs.parameter_names[:11]] and header[-6:] == [f"k{i}" for i in range(1, 7)]
    row = np.array([float(v) for v in text.split("\n")[1].split(",")])
    np.testing.assert_allclose(row[9], math.degrees(params[0, 8]), rtol=1e-15)  # o1 in degrees
    (tmp_path / "truth.csv").write_text(text)
    back = read_truth(tmp_path / "truth.csv", platform)
    np.testing.assert_allclose(back.params, params, rtol=5e-15, atol=1e-18)  # 15 digits
    np.testing.assert_array_equal(back.drive_terms["stroke_scale"], 0.02)
    with pytest.raises(CalibError, match=r"missing required column\(s\) j1x"):
        read_truth(tmp_path / "truth.csv")  # a prismatic reader: the 42 names are not there


def test_prismatic_files_unchanged_by_the_drive_kind():
    """The default kind writes what it always wrote: ``q1_mm …`` and the 42 names in mm."""
    platform = nim_stewart()
    log = Log(np.zeros(1), np.full((1, 6), 3.5), np.zeros((1, 6)))
    assert log_text(log, platform).split("\n")[1].startswith("0.0,3.5,3.5")
    truth = Truth(np.zeros(1), platform.drive.as_vector()[None])
    assert truth_text(truth, platform=platform) == truth_text(truth)
    assert copy.deepcopy(result_dict(Estimate(np.zeros(42), None, "ls"), platform))["nominal"] == list(
        platform.drive.as_vector()
    )


def test_servo_home_is_reachable_and_an_unreachable_home_is_refused():
    from stewart_calib.model.kinematics import pose_to_rt

    platform = _servo(workspace=True)
    angles = platform.drive.coordinates(*pose_to_rt(platform.workspace.home))
    np.testing.assert_allclose(np.degrees(angles), 0.0, atol=1e-3)  # every horn horizontal at home
    doc = _doc(workspace=True)
    doc["workspace"]["home"] = [0.0, 0.0, 190.0, 0.0, 0.0, 0.0]  # beyond horn + rod
    assert _refusal(doc).endswith(
        "key 'workspace.home': expected a home pose every crank reaches with a commanded angle within [-75, 75] deg "
        "(drive.angle_range_deg); leg 1 cannot"
    )


def test_a_link_file_reads_a_rotary_drives_commanded_angles(tmp_path):
    from stewart_calib.links import load_link

    platform = _servo()
    columns = ["t_s", *(f"q{i}_mm" for i in range(1, 7)), "mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg"]
    read = "".join(f'{column} = "ns=2;s=Robot.{column}"\n' for column in [*columns, "myaw_deg"])
    (tmp_path / "link.toml").write_text(f'[link]\nurl = "opc.tcp://127.0.0.1:4840/"\nrate_hz = 10.0\n[read]\n{read}')
    with pytest.raises(CalibError, match=r"\[read\] lacks q1_deg, q2_deg, q3_deg, q4_deg, q5_deg, q6_deg \("):
        load_link(tmp_path / "link.toml", platform)
    (tmp_path / "link.toml").write_text(
        (tmp_path / "link.toml").read_text().replace('_mm = "ns=2;s=Robot.q', '_deg = "ns=2;s=Robot.q')
    )
    assert "q1_deg" in load_link(tmp_path / "link.toml", platform).read


def test_platform_out_of_a_rotary_calibration_is_the_turned_table(tmp_path):
    """``--platform-out`` (spec §8, §15): the estimate as the same table — axes and zero directions turned,
    ``angle_offsets_deg`` filled — which reads back as the calibrated legs."""
    from stewart_calib.pipelines.handover import calibrated_platform_text

    platform = _servo(workspace=True)
    estimate = _estimate(platform.drive, seed=9)
    text = calibrated_platform_text(platform, estimate, "lm", "log.csv", "2026-12-01T23:00:00Z")
    back = parse_platform(tomllib.loads(text), SOURCE)
    _assert_same_legs(back.drive, platform.drive.perturbed(estimate.error), atol=1e-12)
    offsets = tomllib.loads(text)["drive"]["angle_offsets_deg"]
    np.testing.assert_allclose(offsets, np.degrees(estimate.error[8::11]), atol=1e-12)
    assert "calibrated by stewart-calib" in back.description


def test_a_prismatic_only_path_refuses_a_rotary_drive_naming_the_kind():
    from stewart_calib.errors import CalibError
    from stewart_calib.io.platform_file import load_platform
    from stewart_calib.resources import resolve

    platform = load_platform(resolve("servo-hexapod", "platforms"))
    with pytest.raises(
        CalibError, match=r"key 'drive.kind': the statics check takes prismatic legs; this drive is rotary"
    ):
        platform.prismatic_drive("the statics check")
    assert load_platform(resolve("nim-stewart", "platforms")).prismatic_drive("x").n_params == 42
