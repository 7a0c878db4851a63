"""``stewart-calib simulate``: files per the spec, read back by io and by a plain csv reader."""

from __future__ import annotations

import csv
import itertools
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.errors import CalibError, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import read_log, read_truth, result_dict, write_result
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import PARAMETER_NAMES
from stewart_calib.samples import LOAD_KG
from stewart_calib.simulation.closed_loop import FrozenController, run_experiment
from stewart_calib.simulation.experiment import load_experiment

QUICK = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "quick.toml"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "quick"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(out)]) == 0
    return out


def test_output_reads_back_with_the_projects_reader(simulated):
    expected = run_experiment(load_experiment(QUICK))
    platform = load_platform(simulated / "platform.toml")
    nominal = load_experiment(QUICK).platform  # the nominal platform, round-tripped exactly
    np.testing.assert_array_equal(platform.drive.as_vector(), nominal.drive.as_vector())
    np.testing.assert_array_equal(platform.tracker.as_vector(), nominal.tracker.as_vector())
    log = read_log(simulated / "log.csv", platform=platform)  # strict: every row in range
    truth = read_truth(simulated / "truth.csv")
    assert len(log) == len(truth.t_s) == len(expected.log)
    # CSV holds each float's 15 significant digits; degrees ↔ radians may cost an ulp
    np.testing.assert_array_equal(log.strokes, without_noise(expected.log.strokes))
    np.testing.assert_array_equal(log.readings, without_noise(expected.log.readings))
    np.testing.assert_allclose(log.desired_poses, expected.desired_poses, rtol=5e-15, atol=1e-12)
    np.testing.assert_array_equal(truth.params, without_noise(expected.truth.params))
    np.testing.assert_allclose(truth.true_poses, expected.actual_poses, rtol=5e-15, atol=1e-12)
    assert log.stages == list(expected.stages)
    np.testing.assert_array_equal(log.inputs[LOAD_KG], without_noise(expected.payload_kg))


def test_output_reads_back_with_a_plain_csv_reader(simulated):
    with open(simulated / "log.csv", newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    with open(simulated / "truth.csv", newline="", encoding="utf-8") as handle:
        truth_rows = list(csv.DictReader(handle))
    required = ["t_s", *(f"q{i}_mm" for i in range(1, 7)), *(f"s{i}_mm" for i in range(1, 7))]
    assert set(required) <= set(rows[0])
    assert {"x_mm", "roll_deg", "stage", "load_kg"} <= set(rows[0])
    assert {"t_s", *PARAMETER_NAMES, "true_x_mm", "true_yaw_deg"} <= set(truth_rows[0])
    assert len(rows) == len(truth_rows)
    t = [float(r["t_s"]) for r in rows]
    assert t == [float(r["t_s"]) for r in truth_rows] and all(b >= a for a, b in itertools.pairwise(t))
    assert {r["stage"] for r in rows} == {"no-load", "40kg"}
    # a pose in degrees: within the ±20° workspace
    assert max(abs(float(r["roll_deg"])) for r in rows) <= 20.0


def test_same_experiment_same_files(simulated, tmp_path):
    again = tmp_path / "again"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(again)]) == 0
    for name in ("platform.toml", "log.csv", "truth.csv"):
        assert (again / name).read_bytes() == (simulated / name).read_bytes(), name


def test_bad_key_exits_with_one_line_naming_file_and_key(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(QUICK.read_text().replace("[poses]", "[poses]\nsamples_per_poze = 3"))
    assert main(["simulate", "--experiment", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(bad) in err and "'poses.samples_per_poze'" in err
    assert not (tmp_path / "out" / "log.csv").exists()


def test_a_platform_without_a_workspace_is_refused_in_one_line(tmp_path, capsys):
    """The simulated poses are drawn in the platform's [workspace]: without one, simulate ended
    in an AttributeError traceback."""
    nominal = (QUICK.parents[1] / "platforms" / "nim-stewart.toml").read_text()
    (tmp_path / "bare.toml").write_text(nominal[: nominal.index("[workspace]")])
    experiment = tmp_path / "experiment.toml"
    experiment.write_text(QUICK.read_text().replace('platform = "nim-stewart"', 'platform = "bare.toml"'))
    assert main(["simulate", "--experiment", str(experiment), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bare.toml: key 'workspace': expected a [workspace] table" in err
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- --controller frozen


@pytest.fixture(scope="module")
def true_result(tmp_path_factory):
    """A result JSON whose error is the TRUE no-load error of quick's robot (a perfect calibration)."""
    experiment = load_experiment(QUICK)
    drive = run_experiment(experiment).robot.drive_at(experiment.platform.workspace.home, 0.0)
    path = tmp_path_factory.mktemp("result") / "truth.json"
    error = drive.as_vector() - experiment.platform.drive.as_vector()
    write_result(path, result_dict(Estimate(error, None, "truth", 0), experiment.platform))
    return path, drive


def validation_errors(out: Path) -> dict[str, float]:
    """Mean position error [mm] over the validation poses of each stage, from DIR's files."""
    experiment = load_experiment(QUICK)
    kinds = run_experiment(experiment).kinds  # the schedule is the experiment's, whatever drives it
    log, truth = read_log(out / "log.csv"), read_truth(out / "truth.csv")
    position, _ = kin.pose_error(*kin.pose_to_rt(log.desired_poses), *kin.pose_to_rt(truth.true_poses))
    stages = np.array(log.stages)
    return {stage: float(position[(kinds == "validation") & (stages == stage)].mean()) for stage in ("no-load", "40kg")}


def test_frozen_true_model_drives_far_closer_than_nominal(simulated, true_result, tmp_path, capsys):
    path, drive = true_result
    out = tmp_path / "frozen"
    assert (
        main(
            ["simulate", "--experiment", str(QUICK), "--out", str(out), "--controller", "frozen", "--result", str(path)]
        )
        == 0
    )
    # its two status lines name the command, as every command's do
    done, errors = capsys.readouterr().out.splitlines()
    assert done.startswith("stewart-calib simulate: simulated ") and done.endswith(f" (frozen controller) into {out}")
    assert errors.startswith("stewart-calib simulate: pose error RMS (true − desired), nominal → frozen controller: x ")
    # the files are the in-memory run with the same frozen model
    expected = run_experiment(load_experiment(QUICK), FrozenController(drive))
    np.testing.assert_array_equal(read_truth(out / "truth.csv").params, without_noise(expected.truth.params))
    np.testing.assert_array_equal(read_log(out / "log.csv").strokes, without_noise(expected.log.strokes))
    nominal, frozen = validation_errors(simulated), validation_errors(out)
    # the paper's bands (configs/experiments/paper.toml, tests/test_simulation.py), on quick:
    # uncalibrated, no load, within 1.5x of Table 5's 3.92 mm (measured 3.22 mm)
    assert 3.9243 / 1.5 <= nominal["no-load"] <= 3.9243 * 1.5, nominal
    # a perfect no-load model, within 2x of Table 5's LS at no load 0.073 mm (measured 0.080 mm)
    # and at 40 kg 0.385 mm (measured 0.42 mm): the load drift it cannot follow
    assert 0.073 / 2 <= frozen["no-load"] <= 0.073 * 2, frozen
    assert 0.3854 / 2 <= frozen["40kg"] <= 0.3854 * 2, frozen
    # "much smaller": at least 20x at no load (measured 40x), still 5x at 40 kg (measured 8.2x)
    assert frozen["no-load"] * 20 < nominal["no-load"] and frozen["40kg"] * 5 < nominal["40kg"]


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert "\n" not in err, err
    return err


def test_frozen_refuses_a_result_for_another_platform(true_result, tmp_path, capsys):
    experiment = load_experiment(QUICK)
    other = replace(experiment.platform, drive=experiment.platform.drive.perturbed(np.full(42, 0.01)))
    path = tmp_path / "other.json"
    write_result(path, result_dict(Estimate(np.zeros(42), None, "ls", 1), other))
    out = tmp_path / "out"
    assert (
        main(
            ["simulate", "--experiment", str(QUICK), "--out", str(out), "--controller", "frozen", "--result", str(path)]
        )
        == 2
    )
    err = one_line_error(capsys)
    assert str(path) in err and "'nominal'" in err and "0.01 mm" in err
    assert not out.exists()


@pytest.mark.parametrize(
    "extra, message",
    [(["--controller", "frozen"], "needs --result"), (["--result", "r.json"], "only used with --controller frozen")],
)
def test_controller_and_result_go_together(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(out), *extra]) == 2
    assert message in one_line_error(capsys)
    assert not out.exists()


# ----------------------------------------------------------------------------- blocks

POINTS_EXPERIMENT = """
name = "points"
seed = 6
platform = "hobby-hexapod"
[robot]
encoder_noise_mm = 0.01
[poses]
calibration = 11
validation = 0
workspace_fraction = 0.5
[instrument]
kind = "points"
position_sigma_mm = 0.1
targets_mm = [[10.0, 0.0, 5.0], [-10.0, 20.0, 5.0]]
target_spread_mm = 2.0
dropout_probability = 0.2
[[stages]]
name = "one"
segments = ["calibration"]
[[stages]]
name = "two"
load_kg = 3.0
ramp_s = 0.5
segments = ["calibration"]
"""


def whole_run_texts(experiment) -> tuple[str, str]:
    """log.csv and truth.csv of the nominal controller's run in one vectorised pass over the whole
    schedule — what simulate wrote before it worked in blocks — from the model's pure functions."""
    from stewart_calib.io import log_text, truth_text
    from stewart_calib.samples import Log, Truth
    from stewart_calib.simulation.closed_loop import build_robot
    from stewart_calib.simulation.experiment import schedule
    from stewart_calib.simulation.load import settle

    robot_rng, tracker_rng, poses_rng, noise_rng, encoder_rng, instrument_rng = np.random.default_rng(
        experiment.seed
    ).spawn(6)
    robot = build_robot(experiment, robot_rng, tracker_rng, encoder_rng, instrument_rng)
    plan = schedule(experiment, poses_rng)
    n = len(plan.t_s)
    stroke_noise, reading_noise = noise_rng.standard_normal((n, 6)), noise_rng.standard_normal((n, 6))
    instrument_draws = robot.instrument.draw(n, instrument_rng) if robot.instrument is not None else np.zeros((n, 0))
    R_d, t_d = kin.pose_to_rt(plan.desired_poses)
    strokes = kin.inverse_kinematics(experiment.platform.drive, R_d, t_d)
    sol, params = settle(robot.load, robot.base_params, strokes, plan.payload_kg, (R_d, t_d))
    log = Log(
        plan.t_s,
        robot.logged_strokes(strokes, stroke_noise),
        robot.readings(sol.R, sol.t, reading_noise, instrument_draws),
        plan.desired_poses,
        list(plan.stages),
        {LOAD_KG: plan.payload_kg},
    )
    params[:, 6::7] += robot.encoder_zero_mm
    # the outside instrument's truth, or the in-situ tracker's own values where they are off their nominal
    instrument = (
        robot.tracker.truth()
        if robot.instrument is None
        else (robot.instrument.names(), robot.instrument.unknowns.file_values())
    )
    terms = {"stroke_scale": robot.stroke_scale}
    truth = Truth(plan.t_s, params, kin.rt_to_pose(sol.R, sol.t), terms, instrument, robot.unloaded_params)
    return log_text(log, experiment.platform), truth_text(truth)


@pytest.mark.parametrize("text", [None, "pose", POINTS_EXPERIMENT], ids=["quick", "pose", "points"])
def test_files_written_in_blocks_are_the_whole_runs_bit_for_bit(tmp_path, monkeypatch, text):
    # Blocks of 7 samples cut across poses, segments and stages; the noise is drawn whole
    # first, so the same experiment file gives the same bytes whatever the block size.
    from stewart_calib.simulation import closed_loop
    from tests.instrument_data import HOBBY
    from tests.test_instrument_files import EXPERIMENT as POSE_EXPERIMENT  # random errors, stroke scale and zero

    path = QUICK
    if text is not None:
        path = tmp_path / "e.toml"
        path.write_text(POSE_EXPERIMENT.format(platform=HOBBY.as_posix()) if text == "pose" else text)
    experiment = load_experiment(path)
    log_csv, truth_csv = whole_run_texts(experiment)
    assert len(log_csv.splitlines()) > 3 * 7
    monkeypatch.setattr(closed_loop, "BLOCK_SAMPLES", 7)
    assert main(["simulate", "--experiment", str(path), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "log.csv").read_text(encoding="utf-8") == log_csv
    assert (tmp_path / "out" / "truth.csv").read_text(encoding="utf-8") == truth_csv
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["log.csv", "platform.toml", "truth.csv"]


def test_a_model_that_learns_sees_the_same_run_in_blocks(monkeypatch):
    # the per-sample path (a controller whose model may change) in blocks of 5 and in one block
    from stewart_calib.simulation import closed_loop

    experiment = load_experiment(QUICK)

    class Learning(FrozenController):
        adaptive = True

        def observe(self, sample):  # a model that moves with every sample
            self._drive = self._drive.perturbed(np.full(42, 1e-4))

    runs = []
    for block_samples in (5, 10_000):
        monkeypatch.setattr(closed_loop, "BLOCK_SAMPLES", block_samples)
        runs.append(run_experiment(experiment, Learning(experiment.platform.drive)))
    for field in ("strokes", "readings", "desired_poses"):
        np.testing.assert_array_equal(getattr(runs[0].log, field), getattr(runs[1].log, field))
    np.testing.assert_array_equal(runs[0].log.inputs[LOAD_KG], runs[1].log.inputs[LOAD_KG])
    np.testing.assert_array_equal(runs[0].truth.params, runs[1].truth.params)
    np.testing.assert_array_equal(runs[0].actual_poses, runs[1].actual_poses)
    assert runs[0].log.stages == runs[1].log.stages


def test_calibration_poses_from_a_plan_are_the_ones_simulated(tmp_path, capsys):
    """``[poses] calibration_file``: the poses plan wrote are the calibration segment's, in order, on
    the same robot as the seed's random draw; a pose out of range and a count beside it are refused."""
    platform = "nim-stewart"
    assert main(["plan", "--platform", platform, "--n", "9", "--out", str(tmp_path / "p.csv"), "--seed", "1"]) == 0
    planned = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)[:, 1:]  # t_s, then the pose columns
    text = QUICK.read_text().replace("calibration = 12", 'calibration_file = "p.csv"')
    text = text.replace('platform = "nim-stewart"', f'platform = "{platform}"')
    (tmp_path / "e.toml").write_text(text)
    experiment = load_experiment(tmp_path / "e.toml")
    run = run_experiment(experiment)
    kinds = np.asarray(run.kinds)
    first = (np.asarray(run.stages) == "no-load") & (kinds == "calibration")
    desired = run.desired_poses[first][:: experiment.poses.samples_per_pose]
    np.testing.assert_allclose(desired[:, :3], planned[:, :3], atol=1e-9)
    np.testing.assert_allclose(np.degrees(desired[:, 3:]), planned[:, 3:], atol=1e-9)
    random = run_experiment(load_experiment(QUICK))
    np.testing.assert_array_equal(run.robot.base_params, random.robot.base_params)
    (tmp_path / "both.toml").write_text(text.replace("[poses]", "[poses]\ncalibration = 3"))
    with pytest.raises(CalibError, match=r"key 'poses.calibration': expected no count where calibration_file"):
        load_experiment(tmp_path / "both.toml")
    far = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    far[4, 1] += 1000.0
    np.savetxt(
        tmp_path / "p.csv", far, delimiter=",", header="t_s,x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg", comments=""
    )
    with pytest.raises(CalibError, match=r"calibration_file.*pose 5 \(row 6\) is not, nor are 0 other"):
        load_experiment(tmp_path / "e.toml")
