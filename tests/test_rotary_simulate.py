"""``simulate`` of a rotary (servo-horn) drive (spec §15): the shipped servo experiment's files, and a
log whose forward kinematics with the true model reproduces what the motion capture read, within
the instrument's noise."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from stewart_calib import io
from stewart_calib.errors import CalibError, without_noise
from stewart_calib.instruments.pose import predict
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import STROKE_SCALE, drive_model
from stewart_calib.simulation import load_experiment, run_experiment
from stewart_calib.simulation.experiment import RotaryRobotConfig
from tests.synthetic import ROOT


@pytest.fixture(scope="module")
def servo_run():
    return run_experiment(load_experiment("servo"))


@pytest.fixture(scope="module")
def exact_servo_run():
    """The servo experiment with servos that hold their commands exactly: the log's angles are then all
    there is between the true model and the true pose."""
    experiment = load_experiment("servo")
    return run_experiment(replace(experiment, robot=replace(experiment.robot, angle_noise_deg=0.0)))


def test_true_errors_are_a_servo_builds(servo_run):
    robot = servo_run.robot
    legs = robot.nominal
    delta = robot.base_params - legs.as_vector()
    names = np.array(legs.parameter_names)
    offsets = np.char.startswith(names, "o")
    assert np.max(np.abs(np.degrees(delta[offsets]))) <= 2.0  # a trimmed spline tooth's fraction
    tilts = np.char.startswith(names, "t")
    assert 0.2 < np.degrees(np.std(delta[tilts])) < 1.5
    assert 0.005 < np.std(robot.stroke_scale) < 0.04  # ±2 % angle scale
    np.testing.assert_array_equal(servo_run.truth.params, np.tile(robot.base_params, (len(servo_run.log), 1)))


def _true_fk(run):
    """``(platform, nominal drive, FK of the log's angles with the true drive)`` of a simulated run."""
    platform = load_experiment("servo").platform
    nominal = drive_model(platform)
    true = nominal.true_drive(run.truth.params[0] - platform.drive.as_vector(), run.truth.drive_terms)
    R_d, t_d = kin.pose_to_rt(run.log.desired_poses)
    return platform, nominal, true.forward_kinematics(run.log.strokes, guess=(R_d, t_d))


def test_fk_of_the_log_with_the_true_model_reproduces_the_instrument_within_its_noise(exact_servo_run):
    run = exact_servo_run
    platform, nominal, fk = _true_fk(run)
    # the pose the true model gives the logged angles is the true one, to the FK's tolerance
    R_true, t_true = kin.pose_to_rt(run.truth.true_poses)
    position_mm, rotation_deg = kin.pose_error(R_true, t_true, fk.R, fk.t)
    assert position_mm.max() < 1e-6 and rotation_deg.max() < 1e-6
    # ... and the instrument's reading of it is the measured one, to the instrument's noise
    R_P, t_P = predict(run.robot.instrument.unknowns, fk.R, fk.t)
    R_m, t_m = kin.pose_to_rt(run.log.readings)
    sigma = platform.instrument
    per_coordinate = np.sqrt(np.mean((t_m - t_P) ** 2))
    assert sigma.position_sigma_mm * 0.85 < per_coordinate < sigma.position_sigma_mm * 1.15
    angle = np.radians(kin.pose_error(R_P, t_P, R_m, t_m)[1])  # ‖Exp⁻¹‖ of three σ_rot draws
    assert sigma.orientation_sigma_rad * 0.85 < np.sqrt(np.mean(angle**2) / 3) < sigma.orientation_sigma_rad * 1.15
    # the nominal model does not: the errors are the calibration's to find
    R_d, t_d = kin.pose_to_rt(run.log.desired_poses)
    nominal_fk = nominal.forward_kinematics(run.log.strokes, guess=(R_d, t_d))
    assert np.sqrt(np.mean(kin.pose_error(R_true, t_true, nominal_fk.R, nominal_fk.t)[0] ** 2)) > 0.3


def test_servos_hold_their_commands_to_the_experiments_angle_noise(servo_run, exact_servo_run):
    """The shipped experiment's servos hold 0.05° (σ): the true pose leaves the true model's FK of the
    commands by what that moves the platform, and the commands are the exact run's (the same draws)."""
    np.testing.assert_array_equal(servo_run.log.strokes, exact_servo_run.log.strokes)
    _, _, fk = _true_fk(servo_run)
    R_true, t_true = kin.pose_to_rt(servo_run.truth.true_poses)
    position_mm, rotation_deg = kin.pose_error(R_true, t_true, fk.R, fk.t)
    assert 0.02 < np.sqrt(np.mean(position_mm**2)) < 0.2 and np.sqrt(np.mean(rotation_deg**2)) < 0.1


def test_simulate_writes_rotary_files_that_read_back(tmp_path, servo_run):
    from stewart_calib.pipelines import simulate

    assert simulate.main(["--experiment", "servo", "--out", str(tmp_path)]) == 0
    platform = load_platform(tmp_path / "platform.toml")
    assert platform.drive.kind == "rotary" and platform.elastic is None
    text = (tmp_path / "log.csv").read_text()
    assert text.startswith("t_s,q1_deg,q2_deg,q3_deg,q4_deg,q5_deg,q6_deg,mx_mm")
    log = io.read_log(tmp_path / "log.csv", platform)
    np.testing.assert_allclose(log.strokes, servo_run.log.strokes, rtol=5e-15, atol=1e-17)  # 15 digits
    low, high = platform.drive.angle_range
    assert np.all((log.strokes >= low) & (log.strokes <= high))
    truth = io.read_truth(tmp_path / "truth.csv", platform)
    assert (tmp_path / "truth.csv").read_text().split(",", 12)[1:12] == list(platform.drive.parameter_names[:11])
    np.testing.assert_allclose(truth.params, servo_run.truth.params, rtol=5e-15, atol=1e-16)
    np.testing.assert_array_equal(
        truth.drive_terms[STROKE_SCALE], without_noise(servo_run.truth.drive_terms[STROKE_SCALE])
    )
    degrees = platform.drive.parameter_degrees
    first = np.array([float(v) for v in (tmp_path / "truth.csv").read_text().split("\n")[1].split(",")[1:67]])
    np.testing.assert_allclose(first[degrees], np.degrees(servo_run.truth.params[0, degrees]), rtol=5e-15)


def test_rotary_experiment_refuses_a_load_table_and_prismatic_robot_keys(tmp_path):
    text = (
        (ROOT / "configs" / "experiments" / "servo.toml")
        .read_text()
        .replace('platform = "servo-hexapod"', f'platform = "{ROOT / "configs" / "platforms" / "servo-hexapod.toml"}"')
    )
    for extra, expected in (
        ("\n[load]\nplatform_mass_kg = 0.4\n", "key 'load': expected no [load] table"),
        ("", "key 'robot.scale_lengths': unknown key"),
    ):
        changed = text + extra if extra else text.replace("[robot]\n", "[robot]\nscale_lengths = 1.0\n")
        (tmp_path / "e.toml").write_text(changed)
        with pytest.raises(CalibError) as info:
            load_experiment(tmp_path / "e.toml")
        assert expected in str(info.value) and "\n" not in str(info.value)


def test_rotary_robot_defaults_are_the_documented_servo_errors():
    config = RotaryRobotConfig()
    assert (config.angle_offset_limit_deg, config.horn_spread_mm, config.rod_spread_mm) == (2.0, 0.2, 0.3)
    assert (config.joint_spread_mm, config.axis_tilt_spread_deg, config.angle_scale_spread) == (0.5, 0.75, 0.02)
    assert math.isclose(load_experiment("servo").robot.angle_noise_deg, 0.05)


def test_compensate_writes_commanded_angles_after_the_pose_columns(tmp_path, servo_run):
    """On the nominal platform, compensate's angles are those the simulated nominal controller commanded."""
    from stewart_calib.pipelines import compensate, simulate

    assert simulate.main(["--experiment", "servo", "--out", str(tmp_path)]) == 0
    poses = servo_run.log.desired_poses[:5]
    io.write_pose_list(tmp_path / "poses.csv", poses)
    assert (
        compensate.main(
            [
                "--platform",
                str(tmp_path / "platform.toml"),
                "--poses",
                str(tmp_path / "poses.csv"),
                "--out",
                str(tmp_path / "angles.csv"),
            ]
        )
        == 0
    )
    header, *rows = (tmp_path / "angles.csv").read_text().strip().split("\n")
    assert header.split(",")[1:] == [*io.POSE_COLUMNS, *(f"q{i}_deg" for i in range(1, 7))]
    angles = np.array([[float(v) for v in row.split(",")[7:]] for row in rows])
    np.testing.assert_allclose(angles, np.degrees(servo_run.log.strokes[:5]), rtol=0, atol=1e-9)


def test_export_json_writes_the_servos_geometry_and_zero_trim_and_linuxcnc_is_refused(tmp_path, capsys):
    import json
    from dataclasses import replace as replaced

    from stewart_calib.io.platform_file import platform_to_toml
    from stewart_calib.pipelines import export

    platform = load_platform("servo-hexapod")
    trimmed = replaced(platform, drive=platform.drive.perturbed(np.radians(np.tile([0] * 8 + [1.5, 0, 0], 6))))
    (tmp_path / "p.toml").write_text(platform_to_toml(trimmed))
    assert (
        export.main(["--platform", str(tmp_path / "p.toml"), "--format", "json", "--out", str(tmp_path / "k.json")])
        == 0
    )
    document = json.loads((tmp_path / "k.json").read_text())
    assert document["kind"] == "rotary" and document["angle_range_deg"] == [-75.0, 75.0]
    servo = document["legs"][0]
    assert servo["zero_trim_deg"] == pytest.approx(1.5, abs=1e-12) and servo["horn_length"] == 25.0
    np.testing.assert_allclose(servo["crank_axis"], platform.drive.crank_axes[0], atol=1e-12)
    assert servo["angle_per_commanded_degree"] == 1.0
    capsys.readouterr()
    assert (
        export.main(["--platform", str(tmp_path / "p.toml"), "--format", "linuxcnc", "--out", str(tmp_path / "k.hal")])
        != 0
    )
    error = capsys.readouterr().err.strip()
    assert (
        error.endswith(
            "genhexkins models prismatic struts; "
            + str(tmp_path / "p.toml")
            + " has a rotary drive (spec §15): use --format json"
        )
        and "\n" not in error
    )
    assert not (tmp_path / "k.hal").exists()


def test_a_pose_no_horn_reaches_refuses_the_experiment_naming_its_sample(tmp_path):
    text = (ROOT / "configs" / "experiments" / "servo.toml").read_text()
    text = text.replace(
        'platform = "servo-hexapod"', f'platform = "{ROOT / "configs" / "platforms" / "servo-hexapod.toml"}"'
    )
    text = text.replace('segments = ["calibration", "validation"]', 'segments = ["calibration", "circle"]')
    (tmp_path / "e.toml").write_text(text + "\n[circle]\nradius_mm = 90.0\npoints = 12\n")
    with pytest.raises(CalibError) as info:
        run_experiment(load_experiment(tmp_path / "e.toml"))
    assert str(info.value) == (
        f"{tmp_path / 'e.toml'}: sample 151 (t_s = 75 s, circle pose 1): the controller's model has no drive "
        "coordinate within range for its desired pose (a rotary drive's drive.angle_range_deg); expected poses within "
        "reach (a smaller workspace or trajectory)"
    )
