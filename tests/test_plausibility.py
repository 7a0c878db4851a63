"""A log of another platform ends in a refusal with the RMS residual, never a confident result (issue 14)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.analysis.plausibility import PRIOR_SIGMAS, RESIDUAL_SIGMAS, check_plausible, rms_leg_residual_mm
from stewart_calib.config import NoiseConfig, config_from_dict
from stewart_calib.errors import CalibError
from stewart_calib.estimators.base import feed
from stewart_calib.io import write_log
from stewart_calib.io.platform_file import platform_to_toml
from stewart_calib.model import kinematics as kin
from stewart_calib.model.platform import LegGeometry
from stewart_calib.workflows.online import OnlineCalibrator
from tests.synthetic import make_log, nim_stewart, numpy_legs, random_error, random_poses

N = 60


def _other_platform(platform):
    """A different 6-6 drive (base joints on 0.8×, platform joints on 1.2× the radius), same tracker."""
    base, top = platform.drive.base_joints.copy(), platform.drive.platform_joints.copy()
    base[:, :2] *= 0.8
    top[:, :2] *= 1.2
    R, t = kin.pose_to_rt(platform.workspace.home)
    lengths = kin.leg_lengths(LegGeometry(base, top, np.ones(6)), R, t)
    return dataclasses.replace(platform, name="other", drive=LegGeometry(base, top, lengths))


@pytest.fixture(scope="module")
def logs():
    platform = nim_stewart()
    other = _other_platform(platform)
    rng = np.random.default_rng(8)
    poses = random_poses(platform, N, rng)
    own, _ = make_log(platform, random_error(rng, 1.0), poses, rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001)
    foreign, _ = make_log(other, random_error(rng, 1.0), poses, rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001)
    return platform, other, own, foreign


@pytest.mark.parametrize("method", ["ekf", "isam2"])
def test_calibrate_refuses_a_log_of_another_platform_naming_the_residual(tmp_path, capsys, logs, method):
    platform, other, own, foreign = logs
    for name, plat in (("p.toml", platform), ("other.toml", other)):
        (tmp_path / name).write_text(platform_to_toml(plat))
    for platform_file, log, code in (("p.toml", own, 0), ("p.toml", foreign, 2), ("other.toml", own, 2)):
        write_log(tmp_path / "log.csv", log)
        out = tmp_path / f"{platform_file}-{code}.json"
        argv = [
            "calibrate",
            "--platform",
            str(tmp_path / platform_file),
            "--log",
            str(tmp_path / "log.csv"),
            "--method",
            method,
            "--out",
            str(out),
            "--set",
            "isam2.window_samples=10",
        ]
        assert cli.main(argv) == code
        err = capsys.readouterr().err.strip().splitlines()
        if code:
            assert len(err) == 1 and "does not fit platform" in err[0] and "RMS leg residual" in err[0], err
            assert not out.exists()


def test_the_right_platform_passes_with_noise_five_times_mismatched(logs):
    platform, _, own, _ = logs
    for reading_sigma_mm in (0.0004, 0.01):  # the log's 2 µm, taken 5× too small and too large
        noise = NoiseConfig(reading_sigma_mm=reading_sigma_mm)
        calib = OnlineCalibrator(platform, "ekf", config_from_dict({"noise": {"reading_sigma_mm": reading_sigma_mm}}))
        for sample in own:
            calib.update(sample)
        check_plausible(platform, calib.estimate().error, noise, own.strokes, own.readings, "ekf")
        # far inside both limits: the residual within a few σ, the parameters within a few prior σ
        assert rms_leg_residual_mm(platform, calib.estimate().error, own.strokes, own.readings) < 10 * 0.002
        assert np.abs(calib.estimate().error).max() < PRIOR_SIGMAS / 2 * noise.prior_sigma_mm


def test_the_online_result_is_refused_and_track_exits_2(tmp_path, capsys, logs):
    platform, _, _, foreign = logs
    calib = OnlineCalibrator(platform, "ekf")
    feed(calib, foreign)
    with pytest.raises(CalibError, match="does not fit platform 'nim-stewart': RMS leg residual"):
        calib.result()
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    write_log(tmp_path / "log.csv", foreign)
    out = tmp_path / "r.json"
    assert (
        cli.main(
            [
                "track",
                "--platform",
                str(tmp_path / "p.toml"),
                "--method",
                "ekf",
                "--log",
                str(tmp_path / "log.csv"),
                "--out",
                str(out),
                "--every",
                "20",
            ]
        )
        == 2
    )
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not out.exists()


def test_limits_are_in_units_of_the_configured_sigmas(logs):
    platform, _, own, _ = logs
    noise = NoiseConfig()
    error = np.zeros(42)
    error[6] = (PRIOR_SIGMAS + 0.1) * noise.prior_sigma_mm  # l1 just past the prior limit
    with pytest.raises(CalibError, match=r"largest parameter error l1 = 50\.5 mm \(10\.1 × the prior σ 5 mm"):
        check_plausible(platform, error, noise, own.strokes[:0], own.readings[:0], "ekf")  # no samples: parameters only
    assert RESIDUAL_SIGMAS * max(noise.reading_sigma_mm, noise.stroke_sigma_mm) == pytest.approx(2.0)


def test_the_rms_residual_is_the_drive_residual_at_the_tracker_fk_pose(logs):
    """The compiled pass (tracker FK warm-started from the sample before) against its definition:
    batch FK of the readings from the level guess, then the drive's leg residuals. The poses are
    random, so most warm starts lie far away and the guard must fall back to the cold start."""
    platform, _other, own, foreign = logs
    error = random_error(np.random.default_rng(3), 1.0)

    def by_definition(strokes, readings):
        solution = kin.forward_kinematics(platform.tracker, readings, strict=False)
        ok = np.asarray(solution.converged)
        residuals = kin.leg_residuals(platform.drive.perturbed(error), solution.R[ok], solution.t[ok], strokes[ok])
        return np.sqrt(np.mean(np.square(residuals)))

    unreachable = own.readings.copy()
    unreachable[[5, 6, 30], 0] += 5000.0  # one leg 5 m longer than the others: out of reach, no FK, left out
    assert not kin.forward_kinematics(platform.tracker, unreachable[[5, 6, 30]], strict=False).converged.any()
    for strokes, readings in (
        (own.strokes, own.readings),
        (own.strokes, unreachable),
        (foreign.strokes, foreign.readings),
    ):
        assert rms_leg_residual_mm(platform, error, strokes, readings) == pytest.approx(
            by_definition(strokes, readings), rel=1e-9, abs=1e-9
        )
    assert np.isnan(rms_leg_residual_mm(platform, error, own.strokes[5:7], unreachable[5:7]))
    assert np.isnan(rms_leg_residual_mm(platform, error, np.zeros((0, 6)), np.zeros((0, 6))))


def test_without_tracker_samples_the_refusal_names_no_leg_residual():
    """An outside instrument's estimate is checked on its parameters alone: the refusal names the
    parameter, not a leg residual it never computed (was 'RMS leg residual nan mm')."""
    platform = nim_stewart()
    noise = NoiseConfig()
    error = np.zeros(42)
    error[9] = 20 * PRIOR_SIGMAS * noise.prior_sigma_mm
    with pytest.raises(CalibError) as refused:
        check_plausible(platform, error, noise, np.zeros((0, 6)), np.zeros((0, 6)), "lm")
    assert "largest parameter error j2z = 1000 mm" in str(refused.value) and "residual" not in str(refused.value)


def test_any_leg_model_gets_the_compiled_leg_residual():
    # the drive's residual at the tracker's poses through the drive model (any leg model) is the
    # compiled pass's, whose roles of the two leg sets are swapped
    platform = nim_stewart()
    error = random_error(np.random.default_rng(6), 0.2)
    poses = random_poses(platform, 30, np.random.default_rng(4))
    log, _ = make_log(platform, random_error(np.random.default_rng(5)), poses, np.random.default_rng(7))
    legs = platform.drive
    generic = dataclasses.replace(platform, drive=numpy_legs(legs))
    compiled = rms_leg_residual_mm(platform, error, log.strokes, log.readings)
    assert rms_leg_residual_mm(generic, error, log.strokes, log.readings) == pytest.approx(compiled, rel=1e-9)


def test_an_estimate_beyond_the_prior_says_the_robot_is_built_looser_than_it(tmp_path, capsys):
    """A laser tracker's three reflectors on a hand-built hobby hexapod whose encoder zeros are ~15 mm off,
    calibrated under the laser-tracker config's 5 mm prior: lm's largest error reaches 4.1 prior σ, beyond the
    3.7 the largest of 42 errors of a robot built to the prior stays within in 99 % of robots, and calibrate
    says so with the σ to give; the same robot built to 3 mm (largest 1.1 σ), and ls, say nothing."""
    from stewart_calib.analysis.plausibility import prior_reach_warning
    from stewart_calib.config import load_estimator_config
    from stewart_calib.workflows.calibration import run_calibration
    from tests.instrument_data import hobby, make_case
    from tests.test_instrument_ls import POINTS, POINTS_TRUTH

    platform = hobby(POINTS)
    config = load_estimator_config("laser-tracker", ["noise.stroke_sigma_mm=0.001"])
    loose, built = (make_case(platform, 100, 300, POINTS_TRUTH, length_spread_mm=s) for s in (15.0, 3.0))
    for case, warns in ((loose, True), (built, False)):
        estimate = run_calibration(platform, case.log, "lm", config).estimate
        line = prior_reach_warning(platform, estimate.error, config.noise, "lm")
        assert (line is not None) == warns, line
    assert prior_reach_warning(platform, np.full(42, 50.0), config.noise, "ls") is None
    assert "--set noise.prior_sigma_mm=" in _prior_line(tmp_path, capsys, platform, loose.log)


def _prior_line(tmp_path, capsys, platform, log) -> str:
    """calibrate's line on the prior, lm with the laser-tracker config, on ``log`` of ``platform`` (files in
    ``tmp_path``; the stroke range as wide as the robot's 15 mm zeros take its strokes)."""
    (tmp_path / "p.toml").write_text(platform_to_toml(dataclasses.replace(platform, stroke_range=(-50.0, 150.0))))
    write_log(tmp_path / "log.csv", log, platform)
    argv = ["calibrate", "--platform", tmp_path / "p.toml", "--log", tmp_path / "log.csv", "--method", "lm"]
    argv += ["--config", "laser-tracker", "--set", "noise.stroke_sigma_mm=0.001", "--out", tmp_path / "r.json"]
    assert cli.main([str(a) for a in argv]) == 0
    (line,) = [text for text in capsys.readouterr().err.splitlines() if "× the prior σ" in text]
    return line
