"""What a calibration hands on (spec §8): the calibrated platform, the result's optional fields,
the HTML report — and their refusals before any work."""

from __future__ import annotations

import base64
import dataclasses
import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import __version__
from stewart_calib.cli import main
from stewart_calib.config import load_estimator_config
from stewart_calib.io import read_result
from stewart_calib.io.platform_file import load_platform
from stewart_calib.pipelines import calibrate as calibrate_pipeline
from tests.browser import browser, screenshot

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("handover") / "sim"
    assert main(["simulate", "--experiment", "quick", "--out", str(out)]) == 0
    return out


def _calibrate(sim: Path, out: Path, method: str, *extra: str, platform: Path | None = None) -> int:
    return main(
        [
            "calibrate",
            "--platform",
            str(platform or sim / "platform.toml"),
            "--log",
            str(sim / "log.csv"),
            "--method",
            method,
            "--config",
            "paper",
            "--out",
            str(out),
            *extra,
        ]
    )


@pytest.fixture(scope="module")
def ekf_run(sim, tmp_path_factory):
    work = tmp_path_factory.mktemp("ekf")
    code = _calibrate(
        sim, work / "r.json", "ekf", "--platform-out", str(work / "C.toml"), "--report", str(work / "report")
    )
    assert code == 0
    return work


def test_result_has_the_optional_fields(ekf_run):
    result = read_result(ekf_run / "r.json")
    covariance = np.array(result["covariance"])
    assert covariance.shape == (48, 48)  # δM, then the compliance of simulate's [elastic] (spec §10)
    np.testing.assert_allclose(covariance, covariance.T, atol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diag(covariance))[:42], result["stddev"], rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diag(covariance))[42:], result["compliance"]["stddev"], rtol=1e-12)
    assert np.linalg.eigvalsh(covariance).min() > 0
    rms = result["residual_rms"]
    assert rms["channels"] == [f"s{i}_mm" for i in range(1, 7)]
    # the simulated drive is millimetres off its nominal; the calibrated one predicts the readings
    # far better on every channel
    assert all(after < 0.5 * before for before, after in zip(rms["before"], rms["after"], strict=True))
    assert result["config"] == dataclasses.asdict(load_estimator_config("paper"))
    assert result["version"] == __version__
    created = datetime.fromisoformat(result["created"].replace("Z", "+00:00"))
    assert created.tzinfo == UTC and abs(datetime.now(UTC) - created) < timedelta(hours=1)


def test_calibrated_platform_holds_the_estimate(ekf_run, sim):
    result = read_result(ekf_run / "r.json")
    calibrated, nominal = load_platform(ekf_run / "C.toml"), load_platform(sim / "platform.toml")
    np.testing.assert_array_equal(calibrated.drive.as_vector(), result["estimate"])
    np.testing.assert_array_equal(calibrated.tracker.as_vector(), nominal.tracker.as_vector())
    assert calibrated.stroke_range == nominal.stroke_range and calibrated.name == nominal.name
    assert "calibrated by stewart-calib" in calibrated.description and "(ekf) from log.csv" in calibrated.description


@pytest.mark.parametrize("method", ["ls", "ekf"])
def test_recalibrating_from_the_calibrated_platform_finds_errors_within_their_stddev(sim, tmp_path, method):
    assert _calibrate(sim, tmp_path / "first.json", method, "--platform-out", str(tmp_path / "C.toml")) == 0
    assert _calibrate(sim, tmp_path / "again.json", method, platform=tmp_path / "C.toml") == 0
    again = read_result(tmp_path / "again.json")
    error, stddev = np.array(again["error"]), np.array(again["stddev"])
    assert np.all(np.abs(error) <= stddev), f"worst |δM|/σ = {np.max(np.abs(error) / stddev):.3g}"


def test_every_command_takes_the_calibrated_platform(ekf_run, sim, tmp_path):
    calibrated = str(ekf_run / "C.toml")
    assert main(["plan", "--platform", calibrated, "--n", "7", "--out", str(tmp_path / "poses.csv")]) == 0
    assert main(["identifiability", "--platform", calibrated, "--log", str(sim / "log.csv")]) == 0


@pytest.mark.parametrize("option", ["--platform-out", "--report"])
def test_outputs_into_a_missing_directory_are_refused_before_any_work(sim, tmp_path, capsys, monkeypatch, option):
    def no_work(*args, **kwargs):
        raise AssertionError("calibration ran although an output could not be placed")

    monkeypatch.setattr(calibrate_pipeline, "run_calibration", no_work)
    target = tmp_path / "missing" / ("C.toml" if option == "--platform-out" else "report")
    assert _calibrate(sim, tmp_path / "r.json", "ekf", option, str(target)) == 2
    err = capsys.readouterr().err
    assert f"{option} {target}: directory {target.parent} does not exist" in err and err.count("\n") == 1
    assert not (tmp_path / "r.json").exists()


def test_residual_rms_is_that_of_validate_predictions(sim, ekf_run):
    # calibrate's residual pass (one compiled FK + IK pass per block, warm-started; the nominal
    # model's on the first pass, spooled) gives what validate's predictions (a batch FK per model
    # from the level guess) give, within what FK's tolerance leaves open; the streamed RMS over
    # blocks without the rejected samples is the RMS of those samples' residuals
    from stewart_calib.io import read_log
    from stewart_calib.model import kinematics as kin
    from stewart_calib.pipelines import handover
    from stewart_calib.workflows.validation import (
        measurement_residuals,
        nominal_residuals,
        streamed_residual_rms,
        validate,
    )
    from tests.test_kinematics import fk_tolerance_bound

    platform = load_platform(sim / "platform.toml")
    log = read_log(sim / "log.csv", platform)
    result = read_result(ekf_run / "r.json")
    nominal = {"nominal": result["nominal"], "error": [0.0] * 42}
    residuals = measurement_residuals(platform, log, result)
    rejected = [3, 4, len(log) // 2]
    kept = log.select(np.delete(np.arange(len(log)), rejected))
    blocks = [log.select(slice(start, start + 7)) for start in range(0, len(log), 7)]
    spooled = [(block, nominal_residuals(platform, block)) for block in blocks]
    streamed = streamed_residual_rms(platform, spooled, result, rejected)
    expected_rms = handover.residual_rms_field(measurement_residuals(platform, kept, result))
    for model, got, when in ((nominal, residuals.before, "before"), (result, residuals.after, "after")):
        drive = platform.drive.perturbed(np.array(model["error"]))
        fk = kin.forward_kinematics(drive, log.strokes)
        bound = fk_tolerance_bound(platform.tracker, drive, fk.R, fk.t)
        assert np.abs(got - (log.readings - validate(platform, model, log, False, errors=False)[0])).max() <= bound
        # an RMS moves by no more than its largest element
        np.testing.assert_allclose(streamed[when], expected_rms[when], rtol=0, atol=2 * bound)
        kept_validate = kept.readings - validate(platform, model, kept, False, errors=False)[0]
        assert np.abs(np.array(expected_rms[when]) - np.sqrt(np.mean(kept_validate**2, axis=0))).max() <= bound


# ----------------------------------------------------------------------------- the report


def test_report_is_one_static_self_contained_page(ekf_run):
    page = (ekf_run / "report" / "index.html").read_text(encoding="utf-8")
    assert "<script" not in page.lower()
    assert not re.search(r"""(src|href)\s*=\s*["'](?!data:)""", page)  # nothing fetched: no server, no network
    for heading in (
        "Residuals per measured channel",
        "Parameter errors δM ± σ",
        "Correlation matrix",
        "Conditioning",
        "Leg forces",  # simulate's platform has [elastic] (spec §10)
        "Config",
        "Versions",
    ):
        assert f"<h2>{heading}</h2>" in page
    images = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(images) == 6  # the robot, residual RMS, residuals over time, δM ± σ, correlations, leg forces
    assert all(base64.b64decode(data).startswith(PNG_MAGIC) for data in images)
    result = read_result(ekf_run / "r.json")
    # the page shows the result's numbers: every RMS before and after, to 4 significant digits
    for before, after in zip(result["residual_rms"]["before"], result["residual_rms"]["after"], strict=True):
        assert f"<td>{before:.4g}</td><td>{after:.4g}</td>" in page
    assert result["conditioning"]["weakest_directions"][0] in page


@pytest.mark.skipif(browser() is None, reason="no headless Chromium installed")
def test_report_renders_in_a_headless_browser(ekf_run, tmp_path):
    pixels = screenshot(ekf_run / "report" / "index.html", tmp_path / "report.png", 1200, 3000)
    assert pixels.shape[:2] == (3000, 1200)
    # the figures rendered: the bars' red (before) and blue (after) are on the page
    red = np.all(np.abs(pixels - (196, 78, 82)) < 8, axis=-1).sum()
    blue = np.all(np.abs(pixels - (76, 114, 176)) < 8, axis=-1).sum()
    assert red > 2000 and blue > 2000


# ----------------------------------------------------------------------------- the rerun recording


def test_rerun_recording_has_sigma_bands_and_diagnostics(sim, tmp_path):
    readback = pytest.importorskip("tests.readback")
    from stewart_calib.io import read_log
    from stewart_calib.model import kinematics as kin

    rrd = tmp_path / "r.rrd"
    assert _calibrate(sim, tmp_path / "r.json", "ekf", "--rerun", str(rrd)) == 0
    result, log = read_result(tmp_path / "r.json"), read_log(sim / "log.csv")
    n = len(log)
    # the band's edges at the last sample are δM ± σ of the result
    _, upper = readback.read_scalars(rrd, "params/leg2/l/ekf/upper")
    _, lower = readback.read_scalars(rrd, "params/leg2/l/ekf/lower")
    k = 13  # l2
    assert len(upper) == len(lower) == n
    assert upper[-1] == pytest.approx(result["error"][k] + result["stddev"][k], abs=1e-9)
    assert lower[-1] == pytest.approx(result["error"][k] - result["stddev"][k], abs=1e-9)
    assert np.all(upper >= lower)
    # residual after the last sample: the calibrated drive's leg residuals at the tracker's pose
    # (kinematics' own function); innovation of the first sample: the nominal drive's
    pose = kin.forward_kinematics(load_platform(sim / "platform.toml").tracker, log.readings[[0, -1]])
    nominal = load_platform(sim / "platform.toml").drive
    calibrated = nominal.perturbed(np.array(result["error"]))
    last = kin.leg_residuals(calibrated, pose.R[1], pose.t[1], log.strokes[-1])
    first = kin.leg_residuals(nominal, pose.R[0], pose.t[0], log.strokes[0])
    for leg in range(6):
        _, residual = readback.read_scalars(rrd, f"diagnostics/ekf/residual/leg{leg + 1}")
        _, innovation = readback.read_scalars(rrd, f"diagnostics/ekf/innovation/leg{leg + 1}")
        assert len(residual) == len(innovation) == n
        assert residual[-1] == pytest.approx(last[leg], abs=1e-9)
        assert innovation[0] == pytest.approx(first[leg], abs=1e-9)
    _, nis = readback.read_scalars(rrd, "diagnostics/ekf/nis")
    assert len(nis) == n and np.all(np.isfinite(nis)) and np.all(nis >= 0)
    assert "diagnostics ekf" in readback.read_blueprint_names(rrd)


# ----------------------------------------------------------------------------- a motion-capture platform


@pytest.fixture(scope="module")
def pose_run(tmp_path_factory):
    """The hobby hexapod with a motion-capture pose (spec §7): a fit log and a held-out log."""
    from tests.instrument_data import HOBBY
    from tests.test_instrument_files import EXPERIMENT

    work = tmp_path_factory.mktemp("pose")
    (work / "e.toml").write_text(EXPERIMENT.format(platform=HOBBY.as_posix()))
    assert main(["simulate", "--experiment", str(work / "e.toml"), "--out", str(work / "sim")]) == 0
    lines = (work / "sim" / "log.csv").read_text().splitlines()
    stage = lines[0].split(",").index("stage")
    for name, label in (("fit.csv", "fit"), ("held.csv", "held-out")):
        (work / name).write_text("\n".join([lines[0], *(r for r in lines[1:] if r.split(",")[stage] == label)]) + "\n")
    platform = work / "sim" / "platform.toml"
    assert (
        main(
            [
                "calibrate",
                "--platform",
                str(platform),
                "--log",
                str(work / "fit.csv"),
                "--method",
                "ls",
                "--out",
                str(work / "r.json"),
                "--platform-out",
                str(work / "C.toml"),
                "--report",
                str(work / "report"),
            ]
        )
        == 0
    )
    return work


def test_pose_instrument_hands_on_its_frame_target_and_stroke_scale(pose_run):
    result, calibrated = read_result(pose_run / "r.json"), load_platform(pose_run / "C.toml")
    np.testing.assert_allclose(calibrated.stroke_scale, result["stroke_scale"]["estimate"], rtol=0, atol=1e-15)
    frame_target = np.r_[calibrated.instrument.frame, calibrated.instrument.target]
    in_file_units = np.r_[
        frame_target[:3], np.degrees(frame_target[3:6]), frame_target[6:9], np.degrees(frame_target[9:])
    ]
    np.testing.assert_allclose(in_file_units, result["instrument"]["estimate"], atol=1e-9)
    names = result["parameter_names"] + result["stroke_scale"]["names"] + result["instrument"]["names"]
    covariance = np.array(result["covariance"])
    assert covariance.shape == (len(names), len(names))
    # file units: the diagonal's roots are the blocks' stddev as the result lists them
    np.testing.assert_allclose(np.sqrt(np.diag(covariance))[42:48], result["stroke_scale"]["stddev"], rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(covariance))[48:], result["instrument"]["stddev"], rtol=1e-9)
    rms = result["residual_rms"]
    assert rms["channels"] == ["mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg"]
    assert all(after < before for before, after in zip(rms["before"], rms["after"], strict=True))


def test_recalibrating_a_pose_platform_from_its_calibration(pose_run):
    out = pose_run / "again.json"
    assert (
        main(
            [
                "calibrate",
                "--platform",
                str(pose_run / "C.toml"),
                "--log",
                str(pose_run / "fit.csv"),
                "--method",
                "ls",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    again = read_result(out)
    error, stddev = np.array(again["error"]), np.array(again["stddev"])
    assert np.all(np.abs(error) <= stddev), f"worst |δM|/σ = {np.max(np.abs(error) / stddev):.3g}"


def test_validate_report_shows_the_held_out_errors(pose_run):
    assert (
        main(
            [
                "validate",
                "--platform",
                str(pose_run / "sim" / "platform.toml"),
                "--result",
                str(pose_run / "r.json"),
                "--log",
                str(pose_run / "held.csv"),
                "--out",
                str(pose_run / "V.csv"),
                "--report",
                str(pose_run / "vreport"),
            ]
        )
        == 0
    )
    page = (pose_run / "vreport" / "index.html").read_text(encoding="utf-8")
    assert "<h2>Held-out errors</h2>" in page and "<script" not in page.lower()
    assert "before = the nominal platform, its instrument frame and target(s) fitted to this log" in page
    rows = (pose_run / "V.csv").read_text().splitlines()
    header = rows[0].split(",")
    position = np.array([float(r.split(",")[header.index("position_error_mm")]) for r in rows[1:]])
    assert f"<td>{np.sqrt(np.mean(position**2)):.4g}</td><td>{position.max():.4g}</td>" in page
    assert len(re.findall(r'src="data:image/png;base64,', page)) == 6  # the robot, + the held-out errors over time


def test_report_without_matplotlib_is_refused_before_any_work(sim, tmp_path, capsys, monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_matplotlib(name, *args, **kwargs):
        if name.split(".")[0] == "matplotlib":
            raise ImportError("No module named 'matplotlib'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_matplotlib)
    monkeypatch.setattr(calibrate_pipeline, "run_calibration", lambda *a, **k: pytest.fail("calibration ran"))
    assert _calibrate(sim, tmp_path / "r.json", "ekf", "--report", str(tmp_path / "report")) == 2
    err = capsys.readouterr().err
    assert "--report: the report needs matplotlib (pip install 'stewart-calib[report]')" in err
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "report").exists()
