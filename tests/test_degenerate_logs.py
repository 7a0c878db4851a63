"""Logs no robot can have written are refused in one line naming the cause, by every command."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import write_log
from stewart_calib.io.platform_file import platform_to_toml
from stewart_calib.model.platform import Instrument
from stewart_calib.samples import Log
from stewart_calib.simulation.instrument import InstrumentTruth
from stewart_calib.workflows.online import OnlineCalibrator
from tests.instrument_data import hobby, make_case
from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_poses

POSE = Instrument(kind="pose", position_sigma_mm=0.2, orientation_sigma_rad=np.radians(0.05))


@pytest.fixture(scope="module")
def pose_case():
    """40 samples of the hobby robot measured by motion capture (σ 0.2 mm, 0.05°)."""
    truth = InstrumentTruth(np.array([60.0, -30.0, 20.0, 10.0, -5.0, 120.0]), np.array([10.0, 5.0, 30.0, 0, 0, -90]))
    return make_case(hobby(POSE), 40, 11, truth)


def _files(tmp_path, case, readings=None) -> tuple[str, str]:
    platform, log = case.platform, case.log
    if readings is not None:
        log = Log(log.t_s, log.strokes, readings)
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    write_log(tmp_path / "log.csv", log, platform)
    return str(tmp_path / "p.toml"), str(tmp_path / "log.csv")


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("command", ["calibrate ls", "calibrate ekf", "track ekf", "track isam2", "validate"])
def test_a_pose_log_whose_positions_stand_still_is_refused_by_every_command(tmp_path, capsys, pose_case, command):
    """Position columns all 0 while the strokes move the platform by ~15 mm: calibrate and validate
    ended in a math domain error, track used every row and reported a stroke scale of −0.15."""
    readings = pose_case.log.readings.copy()
    readings[:, :3] = 0.0
    platform, log = _files(tmp_path, pose_case, readings)
    name, *method = command.split()
    if name == "validate":
        good = tmp_path / "good"
        good.mkdir()
        fit_platform, fit_log = _files(good, pose_case)
        args = [
            "calibrate",
            "--platform",
            fit_platform,
            "--log",
            fit_log,
            "--method",
            "ls",
            "--out",
            str(good / "r.json"),
        ]
        assert cli.main(args) == 0
        capsys.readouterr()
        argv = ["validate", "--platform", platform, "--result", str(good / "r.json"), "--log", log]
        argv += ["--out", str(tmp_path / "v.csv")]
    else:
        argv = [name, "--platform", platform, "--log", log, "--method", *method, "--out", str(tmp_path / "r.json")]
    assert cli.main(argv) == 2
    err = _one_line(capsys)
    assert "positions mx_mm…mz_mm do not follow the platform: they spread 0 mm" in err
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "v.csv").exists()


def test_a_robot_dwelling_at_its_last_pose_is_not_taken_for_readings_that_stand_still(pose_case):
    """track checks its last 100 samples: a robot that ends by resting at one pose moves neither its
    strokes nor the readings beyond their noise, and its result stands."""
    case = pose_case
    rest = 120  # more than the samples the check keeps
    rng = np.random.default_rng(3)
    strokes = np.vstack([case.log.strokes, np.repeat(case.log.strokes[-1:], rest, axis=0)])
    noise = np.r_[[POSE.position_sigma_mm] * 3, [POSE.orientation_sigma_rad] * 3]  # a reading's [mm, rad]
    still = case.log.readings[-1] + rng.normal(0.0, 1.0, (rest, 6)) * noise
    readings = np.vstack([case.log.readings, still])
    log = Log(np.arange(len(strokes)) * 0.1, strokes, readings)
    calib = OnlineCalibrator(case.platform, "ekf")
    calib.update_block(log)
    assert calib.result()["samples_used"] > len(case.log)


@pytest.mark.parametrize("method", ["ls", "ekf"])  # the whole log, and a stream of it
@pytest.mark.parametrize("instrument", ["tracker", "pose"])
def test_a_thousand_samples_at_rest_are_refused_as_a_log_that_does_not_move(
    tmp_path, capsys, pose_case, instrument, method
):
    """One pose held for 1 000 samples, the readings scattering by their noise only: refused with the
    span of the poses and what a calibration needs, not with a spread ratio of 10⁹ or a solver's failure."""
    rng = np.random.default_rng(5)
    if instrument == "pose":
        platform = pose_case.platform
        first = pose_case.log.readings[0]
        noise = np.r_[[POSE.position_sigma_mm] * 3, [POSE.orientation_sigma_rad] * 3]
        first_strokes = pose_case.log.strokes[0]
    else:
        platform = nim_stewart()
        log, _ = make_log(platform, np.zeros(42), random_poses(platform, 1, rng), rng)
        first, first_strokes, noise = log.readings[0], log.strokes[0], np.full(6, 0.002)
    strokes = np.repeat(first_strokes[None], 1000, axis=0)
    readings = first + rng.normal(0.0, 1.0, (1000, 6)) * noise
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    write_log(tmp_path / "log.csv", Log(np.arange(1000) * 0.1, strokes, readings), platform)
    argv = ["calibrate", "--platform", str(tmp_path / "p.toml"), "--log", str(tmp_path / "log.csv"), "--method", method]
    assert cli.main([*argv, "--out", str(tmp_path / "r.json")]) == 2
    err = _one_line(capsys)
    assert (
        f"{tmp_path / 'log.csv'}: the log does not move: its 1000 samples' strokes span 0 mm and their poses 0 mm / 0°"
        in err
    )
    assert "distinct poses spread over the workspace" in err


def test_a_robot_that_rests_longer_than_a_block_before_it_moves_is_calibrated(tmp_path, capsys, monkeypatch):
    """1000 samples at one pose (a robot waiting at home), then 60 poses: an online method reads the log a
    block at a time. Before, its first block stood for the log, and a log that moves was refused as one
    that does not ("the log does not move: its 1000 samples' strokes span 0 mm")."""
    from stewart_calib.io import logs

    monkeypatch.setattr(logs, "BLOCK_BYTES", 1 << 14)  # ~100 rows a block
    rng = np.random.default_rng(6)
    platform = nim_stewart()
    log, _ = make_log(platform, rng.normal(0.0, 0.5, 42), random_poses(platform, 60, rng), rng)
    rest = 1000
    strokes = np.vstack([np.repeat(log.strokes[:1], rest, axis=0), log.strokes])
    readings = np.vstack([log.readings[0] + rng.normal(0.0, 0.002, (rest, 6)), log.readings])
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    write_log(tmp_path / "log.csv", Log(np.arange(rest + 60) * 0.1, strokes, readings), platform)
    argv = ["calibrate", "--platform", str(tmp_path / "p.toml"), "--log", str(tmp_path / "log.csv"), "--method", "ekf"]
    assert cli.main([*argv, "--out", str(tmp_path / "r.json")]) == 0, capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, expected",
    [
        (
            ["--n", "1"],
            "--n: too few poses: 1 pose(s) asked for 42 unknowns (42 drive parameters); expected at least 7",
        ),
        (["--n", "6"], "--n: too few poses: 6 pose(s) asked for 42 unknowns"),
        # one pose a dwell: the seventh would be written at t_s = inf, which no log reader takes
        (["--n", "7", "--dwell-s", "1e308"], "--dwell-s 1e+308: expected a step that ends 7 poses within 1e+12 s"),
    ],
)
def test_plan_refuses_fewer_poses_than_the_unknowns_need_and_times_beyond_a_log(tmp_path, capsys, argv, expected):
    out = tmp_path / "p.csv"
    assert cli.main(["plan", "--platform", str(NIM_STEWART), "--out", str(out), "--candidates", "50", *argv]) == 2
    assert expected in _one_line(capsys) and not out.exists()


def test_identifiability_refuses_a_pose_list_of_one_pose(tmp_path, capsys, pose_case):
    """One pose (listed twice) fixes 6 of the 42 directions; the report answered with 'rank 6'."""
    (tmp_path / "poses.csv").write_text("x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n0,0,1000,0,0,0\n0,0,1000,0,0,0\n")
    for platform, unknowns, needed in ((str(NIM_STEWART), 42, 7), (None, 48, 8)):
        if platform is None:
            platform, _ = _files(tmp_path, pose_case)
        assert cli.main(["identifiability", "--platform", platform, "--poses", str(tmp_path / "poses.csv")]) == 2
        err = _one_line(capsys)
        assert f"poses.csv: too few poses: 1 distinct pose(s) for {unknowns} unknowns" in err
        assert f"expected at least {needed} distinct poses" in err


def test_a_borderline_condition_number_gets_one_verdict_whatever_its_last_bits(monkeypatch):
    """The kernels' compiled forms round the whitened rows differently in the last bit (5.5e-16, condition
    numbers 1e-13 apart): rows whose condition number is 1000 within that get one verdict, not two."""
    from stewart_calib.analysis import identifiability
    from stewart_calib.config import NoiseConfig

    platform = nim_stewart()
    poses = random_poses(platform, 30, np.random.default_rng(1))
    rows = identifiability.whitened_leg_jacobian(platform, poses, NoiseConfig())
    U, s, Vt = np.linalg.svd(rows.reshape(-1, rows.shape[-1]), full_matrices=False)
    verdicts, conditions = set(), []
    for relative in np.linspace(-3e-13, 3e-13, 7):
        s_border = s.copy()
        s_border[-1] = s[0] / (identifiability.CONDITION_POOR * (1.0 + relative))
        border = ((U * s_border) @ Vt).reshape(rows.shape)
        monkeypatch.setattr(identifiability, "whitened_leg_jacobian", lambda *_, rows=border: rows)
        report = identifiability.identifiability_report(platform, poses, NoiseConfig(), False)
        verdicts.add(report.verdict)
        conditions.append(report.condition_number)
    assert np.allclose(conditions, identifiability.CONDITION_POOR, rtol=1e-11, atol=0)  # on both sides of it
    assert min(conditions) < identifiability.CONDITION_POOR < max(conditions)
    assert verdicts == {"identifiable"}


@pytest.fixture(scope="module")
def at_rest(tmp_path_factory):
    """nim-stewart: a calibration of 60 random poses, and 200 samples at one pose (readings with their
    2 µm noise, the strokes exactly repeated: an encoder that holds its count)."""
    platform = nim_stewart()
    rng = np.random.default_rng(9)
    directory = tmp_path_factory.mktemp("rest")
    (directory / "p.toml").write_text(platform_to_toml(platform))
    error = rng.normal(0.0, 1.0, 42)
    moving, _ = make_log(platform, error, random_poses(platform, 60, rng), rng, 0.002, 0.001)
    write_log(directory / "fit.csv", moving)
    still, _ = make_log(platform, error, np.repeat(random_poses(platform, 1, rng), 200, axis=0), rng, 0.002)
    write_log(directory / "still.csv", still)
    argv = ["calibrate", "--platform", str(directory / "p.toml"), "--log", str(directory / "fit.csv")]
    assert cli.main([*argv, "--method", "ls", "--out", str(directory / "r.json")]) == 0
    return directory


def test_a_held_out_log_at_one_pose_is_validated_not_taken_for_readings_in_another_unit(at_rest, capsys):
    """Its readings spread by their noise where the strokes give the platform no motion: the spread
    ratio (2e9 here) that names a unit means nothing without motion, and validate refused the log."""
    capsys.readouterr()
    d = at_rest
    argv = ["validate", "--platform", str(d / "p.toml"), "--result", str(d / "r.json"), "--log", str(d / "still.csv")]
    assert cli.main([*argv, "--out", str(d / "v.csv")]) == 0
    assert len((d / "v.csv").read_text().splitlines()) == 1 + 200


def test_an_implausible_estimate_from_samples_at_rest_names_them_first(at_rest):
    """track checks its estimate on its last samples: when those hold one pose, the refusal says so
    before the solver's symptom (a 3 mm leg residual on the quick experiment's log held at a pose)."""
    from stewart_calib.analysis.plausibility import PRIOR_SIGMAS, check_plausible
    from stewart_calib.config import NoiseConfig
    from stewart_calib.errors import CalibError
    from stewart_calib.io import read_log

    platform = nim_stewart()
    still = read_log(at_rest / "still.csv", platform)
    error = np.zeros(42)
    error[6] = 2 * PRIOR_SIGMAS * NoiseConfig().prior_sigma_mm  # l1 far beyond its prior
    with pytest.raises(CalibError) as err:
        check_plausible(platform, error, NoiseConfig(), still.strokes[:100], still.readings[:100], "ekf")
    message = str(err.value)
    assert message.startswith("ekf: the last 100 samples it used do not move (their strokes span 0 mm, within 0.01")
    assert "a robot at rest fixes no parameter; the log does not fit platform" in message
