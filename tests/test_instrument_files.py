"""Files of spec §7: ``[instrument]`` in the platform file, the pose and points log columns, the
result's blocks, and the ``calibrate --method ls`` → ``validate`` path on a simulated pose log."""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import io
from stewart_calib.cli import main
from stewart_calib.errors import CalibError, without_noise
from stewart_calib.instruments.pose import PoseModel
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.model.platform import Instrument
from stewart_calib.samples import Truth
from stewart_calib.simulation.instrument import InstrumentTruth
from tests.instrument_data import HOBBY, hobby, make_case


def _doc() -> dict:
    return tomllib.loads(HOBBY.read_text())


def test_hobby_platform_reads_the_pose_instrument_without_a_tracker():
    platform = hobby()
    assert platform.tracker is None
    assert platform.instrument.kind == "pose"
    assert platform.instrument.position_sigma_mm == 0.2
    assert math.isclose(math.degrees(platform.instrument.orientation_sigma_rad), 0.05)


@pytest.mark.parametrize(
    "instrument",
    [
        {
            "kind": "pose",
            "frame": [100.0, -20.0, 5.0, 10.0, -170.0, 45.0],
            "target": [1.0, 2.0, 3.0, 4.0, 5.0, 6.0],
            "position_sigma_mm": 0.3,
            "orientation_sigma_deg": 0.07,
        },
        {
            "kind": "points",
            "frame": [1.0, 2.0, 3.0, 0.0, 0.0, 90.0],
            "targets_mm": [[10.0, 0.0, 5.0], [-10.0, 3.0, 5.0]],
            "position_sigma_mm": 0.02,
        },
    ],
)
def test_instrument_round_trips_through_platform_to_toml(instrument):
    doc = _doc()
    doc["instrument"] = instrument
    doc["drive"]["stroke_scale"] = [0.01, -0.02, 0.0, 0.03, 0.0, 0.0]
    platform = parse_platform(doc, "p.toml")
    again = parse_platform(tomllib.loads(platform_to_toml(platform)), "again.toml")
    for name in ("frame", "target", "targets"):
        np.testing.assert_allclose(
            getattr(again.instrument, name), getattr(platform.instrument, name), rtol=1e-15, atol=1e-15
        )
    assert again.instrument.kind == platform.instrument.kind
    assert again.instrument.position_sigma_mm == platform.instrument.position_sigma_mm
    assert math.isclose(
        again.instrument.orientation_sigma_rad, platform.instrument.orientation_sigma_rad, rel_tol=1e-15
    )
    np.testing.assert_array_equal(again.stroke_scale, platform.stroke_scale)


def test_tracker_geometry_sigma_round_trips():
    from tests.synthetic import NIM_STEWART

    doc = tomllib.loads(NIM_STEWART.read_text())
    doc["tracker"]["geometry_sigma_mm"] = 0.015
    platform = parse_platform(doc, "p.toml")
    assert platform.tracker_geometry_sigma_mm == 0.015
    assert parse_platform(tomllib.loads(platform_to_toml(platform))).tracker_geometry_sigma_mm == 0.015


def test_tracker_geometry_sigma_from_the_estimator_config_where_the_platform_gives_none():
    from stewart_calib.config import NoiseConfig, load_estimator_config
    from stewart_calib.estimators.measurement import drive_only_model
    from stewart_calib.instruments import instrument_model
    from tests.synthetic import NIM_STEWART

    platform = parse_platform(tomllib.loads(NIM_STEWART.read_text()), "p.toml")
    assert instrument_model(platform, NoiseConfig()).unknowns is None
    from_config = instrument_model(platform, NoiseConfig(tracker_geometry_sigma_mm=0.015)).unknowns
    np.testing.assert_array_equal(from_config.prior_sigma, np.full(42, 0.015))
    stated = replace(platform, tracker_geometry_sigma_mm=0.004)  # the platform file's own statement wins
    from_platform = instrument_model(stated, NoiseConfig(tracker_geometry_sigma_mm=0.015)).unknowns
    np.testing.assert_array_equal(from_platform.prior_sigma, np.full(42, 0.004))
    config = load_estimator_config(None, ["noise.tracker_geometry_sigma_mm=0.015"])
    with pytest.raises(CalibError, match="ls identifies the 42 drive parameters only, not instrument"):
        drive_only_model("ls", platform, config)


@pytest.mark.parametrize(
    "change, key",
    [
        ({"kind": "lidar"}, "instrument.kind"),
        ({"position_sigma_mm": 0.0}, "instrument.position_sigma_mm"),
        ({"orientation_sigma_deg": -1.0}, "instrument.orientation_sigma_deg"),
        ({"frame": [1.0, 2.0, 3.0]}, "instrument.frame"),
        ({"targets_mm": [[0.0, 0.0, 0.0]]}, "instrument.targets_mm"),
        ({"colour": "red"}, "instrument.colour"),
    ],
)
def test_bad_instrument_is_refused_naming_the_key(change, key):
    doc = _doc()
    doc["instrument"].update(change)
    with pytest.raises(CalibError, match=f"key '{key}'"):
        parse_platform(doc, "p.toml")


def test_tracker_is_required_only_for_the_tracker_instrument():
    doc = _doc()
    doc["instrument"] = {"kind": "tracker"}
    with pytest.raises(CalibError, match="key 'tracker'"):
        parse_platform(doc, "p.toml")
    doc["instrument"] = {"kind": "points"}
    with pytest.raises(CalibError, match=r"key 'instrument\.targets_mm'"):
        parse_platform(doc, "p.toml")


def _points_platform(n_targets: int = 2):
    return hobby(
        Instrument(
            "points", np.zeros(6), np.zeros(6), np.array([[30.0, 0.0, 20.0], [-20.0, 25.0, 20.0]])[:n_targets], 0.05
        )
    )


def test_points_log_round_trips_with_targets_not_seen(tmp_path):
    platform = _points_platform()
    case = make_case(platform, 8, 1, InstrumentTruth(np.zeros(6), np.zeros(6), dropout_probability=0.3))
    assert np.isnan(case.log.readings).any()
    io.write_log(tmp_path / "log.csv", case.log, platform)
    text = (tmp_path / "log.csv").read_text()
    assert text.splitlines()[0].startswith("t_s,q1_mm,q2_mm,q3_mm,q4_mm,q5_mm,q6_mm,p1x_mm,p1y_mm,p1z_mm,p2x_mm")
    back = io.read_log(tmp_path / "log.csv", platform)
    np.testing.assert_array_equal(np.isnan(back.readings), np.isnan(case.log.readings))
    np.testing.assert_array_equal(
        back.readings[np.isfinite(back.readings)], without_noise(case.log.readings[np.isfinite(case.log.readings)])
    )


def test_pose_log_holds_degrees_in_the_file_and_radians_in_code(tmp_path):
    platform = hobby()
    case = make_case(platform, 5, 2, InstrumentTruth(np.zeros(6), np.zeros(6)))
    io.write_log(tmp_path / "log.csv", case.log, platform)
    back = io.read_log(tmp_path / "log.csv", platform)
    np.testing.assert_allclose(back.readings, case.log.readings, rtol=1e-14)
    rows = (tmp_path / "log.csv").read_text().splitlines()
    header = rows[0].split(",")
    yaw_file = float(rows[1].split(",")[header.index("myaw_deg")])
    assert math.isclose(yaw_file, math.degrees(case.log.readings[0, 5]), rel_tol=1e-12)


def test_the_log_columns_in_degrees_are_those_the_instrument_model_declares(tmp_path, monkeypatch):
    """Which reading columns hold degrees in the file is the instrument model's to say
    (``InstrumentModel.angle_columns``, issue 29): the log writer and reader ask it, and so follow
    a model that declared other columns."""
    platform = hobby()
    assert io.angle_columns(platform) == ("mroll_deg", "mpitch_deg", "myaw_deg")
    assert io.angle_columns(_points_platform(2)) == ()
    assert io.angle_columns(None) == ()  # the tracker's s1_mm … s6_mm
    case = make_case(platform, 5, 2, InstrumentTruth(np.zeros(6), np.zeros(6)))
    monkeypatch.setattr(PoseModel, "angle_columns", frozenset({"myaw_deg"}))
    io.write_log(tmp_path / "log.csv", case.log, platform)
    rows = (tmp_path / "log.csv").read_text().splitlines()
    header, first = rows[0].split(","), rows[1].split(",")
    assert float(first[header.index("mroll_deg")]) == without_noise(case.log.readings[0, 3])  # no longer converted
    assert math.isclose(float(first[header.index("myaw_deg")]), math.degrees(case.log.readings[0, 5]), rel_tol=1e-12)
    np.testing.assert_allclose(io.read_log(tmp_path / "log.csv", platform).readings, case.log.readings, rtol=1e-14)


def test_a_partial_target_is_refused_naming_row_and_column(tmp_path):
    platform = _points_platform(1)
    path = tmp_path / "log.csv"
    path.write_text(
        "t_s,q1_mm,q2_mm,q3_mm,q4_mm,q5_mm,q6_mm,p1x_mm,p1y_mm,p1z_mm\n"
        "0,40,40,40,40,40,40,1,2,3\n0.1,40,40,40,40,40,40,,,\n0.2,40,40,40,40,40,40,1,,3\n"
    )
    with pytest.raises(
        CalibError, match=r"log.csv: row 4: column 'p1y_mm': expected all three coordinates of target 1"
    ):
        io.read_log(path, platform)


def test_columns_not_matching_the_instrument_are_named_in_one_line(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text(
        "t_s,q1_mm,q2_mm,q3_mm,q4_mm,q5_mm,q6_mm,s1_mm,s2_mm,s3_mm,s4_mm,s5_mm,s6_mm\n0,1,1,1,1,1,1,0,0,0,0,0,0\n"
    )
    with pytest.raises(CalibError) as err:
        io.read_log(path, hobby())
    message = str(err.value)
    assert "\n" not in message
    assert "missing column(s) mx_mm, my_mm, mz_mm, mroll_deg, mpitch_deg, myaw_deg of the pose instrument" in message


def test_truth_file_carries_stroke_scale_and_instrument(tmp_path):
    truth = Truth(
        np.arange(2.0),
        np.zeros((2, 42)),
        drive_terms={"stroke_scale": np.arange(6) / 100},
        instrument=(("frame_x_mm", "frame_y_mm"), np.array([1.5, -2.0])),
    )
    io.write_truth(tmp_path / "truth.csv", truth)
    back = io.read_truth(tmp_path / "truth.csv")
    np.testing.assert_array_equal(back.drive_terms["stroke_scale"], truth.drive_terms["stroke_scale"])
    assert back.instrument[0] == ("frame_x_mm", "frame_y_mm")
    np.testing.assert_array_equal(back.instrument[1], [1.5, -2.0])


def test_result_with_a_bad_block_is_refused(tmp_path):
    platform = hobby()
    from stewart_calib.estimate import Estimate

    result = io.result_dict(Estimate(np.zeros(42), None, "ls", 3), platform)
    result["stroke_scale"] = {"names": ["k1"], "estimate": [0.0], "stddev": None}
    with pytest.raises(CalibError, match=r"key 'stroke_scale\.names'"):
        io.result_text(result, "r.json")


EXPERIMENT = """
name = "mocap"
seed = 11
platform = "{platform}"
[robot]
errors = "random"
random_spread_mm = 0.5
stroke_scale_spread = 0.03
encoder_zero_spread_mm = 5.0
[load]
platform_mass_kg = 0.0
[poses]
calibration = 40
validation = 20
workspace_fraction = 0.5
[instrument]
kind = "pose"
position_sigma_mm = 0.2
orientation_sigma_deg = 0.05
frame_offset = [60.0, -30.0, 20.0, 10.0, -5.0, 120.0]
target_offset = [10.0, 5.0, 30.0, 0.0, 0.0, -90.0]
[[stages]]
name = "fit"
segments = ["calibration"]
[[stages]]
name = "held-out"
segments = ["validation"]
"""


def _simulated_fit_and_held_out(tmp_path, experiment: str) -> Path:
    """Simulate ``experiment`` into ``tmp_path/sim`` and split its log into ``fit.csv`` and
    ``held.csv`` by stage; returns the simulated platform file."""
    (tmp_path / "e.toml").write_text(experiment.format(platform=HOBBY.as_posix()))
    assert main(["simulate", "--experiment", str(tmp_path / "e.toml"), "--out", str(tmp_path / "sim")]) == 0
    text = (tmp_path / "sim" / "log.csv").read_text().splitlines()
    stage = text[0].split(",").index("stage")
    fit = [text[0]] + [row for row in text[1:] if row.split(",")[stage] == "fit"]
    held = [text[0]] + [row for row in text[1:] if row.split(",")[stage] == "held-out"]
    (tmp_path / "fit.csv").write_text("\n".join(fit) + "\n")
    (tmp_path / "held.csv").write_text("\n".join(held) + "\n")
    return tmp_path / "sim" / "platform.toml"


def test_simulate_calibrate_validate_end_to_end(tmp_path, capsys):
    """The batch path of issue 13 through the command line: a simulated motion-capture log, ``ls``,
    then ``validate`` on the held-out rows, with the error at the noise floor."""
    platform_path = _simulated_fit_and_held_out(tmp_path, EXPERIMENT)
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "calibrate",
                "--platform",
                str(platform_path),
                "--log",
                str(tmp_path / "fit.csv"),
                "--method",
                "ls",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    result = json.loads(out.read_text())
    assert result["stroke_scale"]["names"] == [f"k{i}" for i in range(1, 7)]
    assert result["instrument"]["names"][0] == "frame_x_mm"
    assert "gauge" in result
    truth = io.read_truth(tmp_path / "sim" / "truth.csv")
    k_error = np.array(result["stroke_scale"]["estimate"]) - truth.drive_terms["stroke_scale"]
    assert np.all(np.abs(k_error) < 4.0 * np.array(result["stroke_scale"]["stddev"]))
    capsys.readouterr()
    assert (
        main(
            [
                "validate",
                "--platform",
                str(platform_path),
                "--result",
                str(out),
                "--log",
                str(tmp_path / "held.csv"),
                "--out",
                str(tmp_path / "V.csv"),
            ]
        )
        == 0
    )
    line = capsys.readouterr().out.strip()
    assert line.startswith("stewart-calib validate: 20 rows: position RMS")
    rows = (tmp_path / "V.csv").read_text().splitlines()
    header = rows[0].split(",")
    assert header[:7] == ["t_s", "mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg"]
    assert "pred_myaw_deg" in header and header[-2:] == ["position_error_mm", "orientation_error_deg"]
    position = np.array([float(r.split(",")[header.index("position_error_mm")]) for r in rows[1:]])
    # the held-out error of a noise-limited fit: the reading noise (√3 σ per pose) plus the fit's own
    # prediction error, which with 40 poses for 48 unknowns is of the same order: 2× the floor
    assert np.sqrt(np.mean(position**2)) < 2.0 * math.sqrt(3) * 0.2


def test_paper_ekf_on_a_pose_log_predicts_held_out_poses_at_the_noise_floor(tmp_path, capsys):
    """The paper's EKF with motion capture (issue 13): δM alone, the frame and target fixed at their
    registration — their errors are rigid motions of all base or all platform joints, which δM
    absorbs — so with exact encoder scales it predicts held-out poses as well as ``ls`` does."""
    experiment = EXPERIMENT.replace("stroke_scale_spread = 0.03", "stroke_scale_spread = 0.0")
    platform_path = _simulated_fit_and_held_out(tmp_path, experiment)
    out = tmp_path / "r.json"
    # R of the paper's form matched to the instrument: 0.04 mm² (σ 0.2 mm), orientation in degrees
    assert (
        main(
            [
                "calibrate",
                "--platform",
                str(platform_path),
                "--log",
                str(tmp_path / "fit.csv"),
                "--method",
                "paper-ekf",
                "--set",
                "paper_ekf.angle_unit=deg",
                "--set",
                "paper_ekf.measurement_noise=0.04",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "validate",
                "--platform",
                str(platform_path),
                "--result",
                str(out),
                "--log",
                str(tmp_path / "held.csv"),
                "--register-instrument",
                "--out",
                str(tmp_path / "V.csv"),
            ]
        )
        == 0
    )
    rows = (tmp_path / "V.csv").read_text().splitlines()
    header = rows[0].split(",")
    position = np.array([float(r.split(",")[header.index("position_error_mm")]) for r in rows[1:]])
    assert np.sqrt(np.mean(position**2)) < 2.0 * math.sqrt(3) * 0.2  # as ls above


def test_paper_ekf_refuses_a_stroke_scale_to_identify():
    from stewart_calib.config import config_from_dict
    from stewart_calib.estimators import make_estimator

    with pytest.raises(CalibError, match="paper-ekf identifies the 42 drive parameters only, not the stroke scale"):
        make_estimator("paper-ekf", hobby(), config_from_dict({"noise": {"stroke_scale_sigma": 0.01}}))


def test_validate_refuses_register_instrument_for_the_tracker(tmp_path):
    from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_poses

    platform = nim_stewart()
    log, _ = make_log(
        platform, np.zeros(42), random_poses(platform, 5, np.random.default_rng(1)), np.random.default_rng(2)
    )
    io.write_log(tmp_path / "log.csv", log)
    from stewart_calib.estimate import Estimate

    io.write_result(tmp_path / "r.json", io.result_dict(Estimate(np.zeros(42), None, "ls", 5), platform))
    args = [
        "validate",
        "--platform",
        str(NIM_STEWART),
        "--result",
        str(tmp_path / "r.json"),
        "--log",
        str(tmp_path / "log.csv"),
        "--out",
        str(tmp_path / "V.csv"),
    ]
    assert main(args) == 0
    assert main([*args, "--register-instrument"]) == 2
    assert not (tmp_path / "V.csv").with_name("V2.csv").exists()


@pytest.mark.parametrize("name", ["motion-capture", "laser-tracker", "in-situ-tracker"])
def test_instrument_presets_load(name):
    from stewart_calib.config import load_estimator_config
    from stewart_calib.resources import CONFIGS

    config = load_estimator_config(CONFIGS / "estimators" / f"{name}.toml")
    assert config.noise.prior_sigma_mm > 0


def test_howto_motion_capture_conversion(tmp_path, monkeypatch, capsys):
    """The motion-capture how-to's conversion in numpy, as written: raw CSV → log → ls → validate
    on another day."""
    from pathlib import Path

    howto = (Path(__file__).resolve().parents[1] / "docs" / "howto" / "motion-capture.md").read_text()
    start = howto.index("```python\nimport csv")
    code = howto[start + len("```python\n") : howto.index("```", start + 10)]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").symlink_to(Path(__file__).resolve().parents[1] / "examples")
    exec(compile(code, "motion-capture.md", "exec"), {})
    assert (
        main(
            [
                "calibrate",
                "--platform",
                "hobby-hexapod",
                "--log",
                "fit.csv",
                "--method",
                "ls",
                "--out",
                "result.json",
                "--config",
                "motion-capture",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(
            [
                "validate",
                "--platform",
                "hobby-hexapod",
                "--result",
                "result.json",
                "--log",
                "heldout.csv",
                "--out",
                "V.csv",
                "--register-instrument",
            ]
        )
        == 0
    )
    line = capsys.readouterr().out
    rms = float(line.split("position RMS ")[1].split(" mm")[0])
    assert rms <= 0.75  # issue 13's target for the re-registered held-out day


def test_identifiability_of_a_pose_log_covers_stroke_scale_and_instrument(tmp_path, capsys):
    """``identifiability`` on an outside instrument: the bound for all unknowns, equal to the ls
    covariance at the same point (both are the inverse information of the same whitened rows)."""
    platform = hobby()
    case = make_case(platform, 60, 21, InstrumentTruth(np.array([30.0, 10.0, -5.0, 0.0, 0.0, 45.0]), np.zeros(6)))
    io.write_log(tmp_path / "log.csv", case.log, platform)
    assert (
        main(
            [
                "identifiability",
                "--platform",
                str(HOBBY),
                "--log",
                str(tmp_path / "log.csv"),
                "--json",
                str(tmp_path / "i.json"),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "i.json").read_text())
    assert report["rank"] == report["unknowns"] == 30 + 6 + 12
    assert report["stroke_scale_identifiable"]
    sd = report["predicted_stddev"]
    assert all(sd[name] is not None and sd[name] > 0 for name in ("k1", "frame_yaw_deg", "target_z_mm", "l3"))
    assert "rank 48/48" in capsys.readouterr().out


def test_track_on_a_pose_log_writes_a_result_with_the_instrument(tmp_path):
    """``track`` (online) on a motion-capture log: no tracker to check residuals with, the result
    still carries the stroke scale and instrument blocks."""
    platform = hobby()
    case = make_case(platform, 40, 31, InstrumentTruth(np.array([30.0, 10.0, -5.0, 0.0, 0.0, 45.0]), np.zeros(6)))
    io.write_log(tmp_path / "log.csv", case.log, platform)
    assert (
        main(
            [
                "track",
                "--platform",
                str(HOBBY),
                "--method",
                "ekf",
                "--log",
                str(tmp_path / "log.csv"),
                "--out",
                str(tmp_path / "cur.json"),
            ]
        )
        == 0
    )
    result = json.loads((tmp_path / "cur.json").read_text())
    assert result["instrument"]["names"][0] == "frame_x_mm" and result["stroke_scale"]["names"][0] == "k1"


@pytest.mark.parametrize("kind", ["pose", "points"])
def test_an_outside_instruments_result_carries_the_conditioning_identifiability_reports(tmp_path, kind):
    """calibrate's "conditioning" of a pose or points log is what ``identifiability --log`` reports of
    the same samples (48 unknowns: 30 drive directions, 6 stroke scales, the instrument's 12)."""
    platform = hobby() if kind == "pose" else _points_platform()
    truth = InstrumentTruth(np.array([30.0, 10.0, -5.0, 0.0, 0.0, 45.0]), np.zeros(6 if kind == "pose" else 3))
    case = make_case(platform, 60, 22, truth)
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    io.write_log(tmp_path / "log.csv", case.log, platform)
    given = ["--platform", str(tmp_path / "p.toml"), "--log", str(tmp_path / "log.csv")]
    assert main(["calibrate", *given, "--method", "ls", "--out", str(tmp_path / "r.json")]) == 0
    assert main(["identifiability", *given, "--json", str(tmp_path / "i.json")]) == 0
    conditioning = json.loads((tmp_path / "r.json").read_text())["conditioning"]
    report = json.loads((tmp_path / "i.json").read_text())
    assert conditioning == {key: report[key] for key in conditioning}
    assert conditioning["unknowns"] == conditioning["rank"] == 48
    assert conditioning["null_space"] == [] and conditioning["null_space_dimension"] == 0
    assert (conditioning["condition_number_equilibrated"] > 1e3) == (conditioning["verdict"] == "poorly conditioned")
    assert len(conditioning["weakest_directions"]) == 3 and all("·" in d for d in conditioning["weakest_directions"])


def test_poses_that_do_not_rotate_leave_named_directions_unidentified(tmp_path, capsys):
    """A pose list that only translates: rank-deficient, the null space's directions named."""
    platform = hobby()
    ws = platform.workspace
    rng = np.random.default_rng(4)
    poses = ws.home + np.c_[rng.uniform(-10.0, 10.0, (40, 3)), np.zeros((40, 3))]
    io.write_pose_list(tmp_path / "poses.csv", poses)
    assert (
        main(
            [
                "identifiability",
                "--platform",
                str(HOBBY),
                "--poses",
                str(tmp_path / "poses.csv"),
                "--json",
                str(tmp_path / "i.json"),
            ]
        )
        == 0
    )
    report = json.loads((tmp_path / "i.json").read_text())
    assert report["verdict"] == "rank-deficient"
    assert report["null_space_dimension"] == report["unknowns"] - report["rank"] == len(report["null_space"]) > 0
    assert "not identified: " in capsys.readouterr().out
