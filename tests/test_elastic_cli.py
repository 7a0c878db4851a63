"""The elastic robot through the command line as a user meets it (spec §10, issue 24's checklist): a pose
where the statics matrix is singular refused in one line naming the file and the row, writing nothing;
the HTML report's leg forces."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.io import log_text
from stewart_calib.io.platform_file import platform_to_toml


@pytest.fixture(scope="module")
def check(tmp_path_factory):
    """benchmarks.elastic's check, small: 20 poses a stage at 0 / 20 / 40 kg."""
    from benchmarks.elastic import check_run

    _, run, platform = check_run(tmp_path_factory.mktemp("check"), 20, validation=5)
    return run, platform


def _parallel_legs(platform):
    """``platform`` with its drive's base joints typed straight under its platform joints: every leg along z
    at every level pose, no leg force can hold the weight's moment about z — singular statics at each
    sample's pose (the tracker still finds the poses)."""
    drive = platform.drive
    base = drive.platform_joints + np.array([0.0, 0.0, 35.0 - drive.platform_joints[0, 2]])
    lengths = np.linalg.norm(platform.workspace.home[:3] + drive.platform_joints - base, axis=-1)
    return dataclasses.replace(
        platform, drive=dataclasses.replace(drive, base_joints=base, initial_lengths=lengths), stroke_range=None
    )


@pytest.mark.parametrize("method", ["ekf", "ls"])
def test_a_singular_pose_in_a_log_is_refused_naming_the_file_and_row(check, tmp_path, capsys, method):
    run, platform = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(_parallel_legs(platform)))
    (tmp_path / "log.csv").write_text(log_text(run.log, platform))
    platform, log = str(tmp_path / "platform.toml"), str(tmp_path / "log.csv")
    out = tmp_path / "out"
    out.mkdir()
    code = main(
        ["calibrate", "--platform", platform, "--log", log, "--method", method, "--out", str(out / "r.json")]
        + ["--platform-out", str(out / "c.toml")]
    )
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    assert err.startswith(f"stewart-calib calibrate: error: {log}: row 2: the statics matrix Aᵀ is singular"), err
    assert not any(out.iterdir())  # nothing partial


def test_a_singular_pose_in_a_pose_list_is_refused_naming_the_file_and_row(check, tmp_path, capsys):
    _, platform = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(platform))
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n0,0,760,0,0,0\n0,0,760,0,0,90\n")
    out = tmp_path / "q.csv"
    argv = ["compensate", "--platform", str(tmp_path / "platform.toml"), "--poses", str(poses), "--out", str(out)]
    # the quarter turn is beyond the workspace, refused as such first: a platform without one
    (tmp_path / "platform.toml").write_text(
        platform_to_toml(dataclasses.replace(platform, workspace=None, stroke_range=None))
    )
    assert main([*argv, "--payload-kg", "40"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"stewart-calib compensate: error: {poses}: row 3: the statics matrix Aᵀ is singular"), err
    assert not out.exists()


def test_the_html_report_shows_each_legs_force_and_give(check, tmp_path):
    """The report's leg forces are the statics of the rows' loads (60 kg platform, 0 / 20 / 40 kg: the six
    legs carry 590–1180 N of weight along z between them) and the give c_i f_i their compliance takes."""

    run, platform = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(platform))
    (tmp_path / "log.csv").write_text(log_text(run.log, platform))
    argv = ["calibrate", "--platform", str(tmp_path / "platform.toml"), "--log", str(tmp_path / "log.csv")]
    assert main([*argv, "--method", "ekf", "--out", str(tmp_path / "r.json"), "--report", str(tmp_path / "rep")]) == 0
    page = (tmp_path / "rep" / "index.html").read_text()
    section = page[page.index("<h2>Leg forces</h2>") :]
    rows = re.findall(r"<tr><td>leg (\d)</td>((?:<td>[^<]*</td>){5})</tr>", section)
    assert [int(leg) for leg, _ in rows] == [1, 2, 3, 4, 5, 6]
    values = np.array([[float(v) for v in re.findall(r"<td>([^<]*)</td>", cells)] for _, cells in rows])
    low, mean, high, give_low, give_high = values.T
    assert np.all((0 < give_low) & (give_low < give_high))
    assert np.all((0 < low) & (low < mean) & (mean < high))
    assert 9.80665 * 60.0 / 6 < np.mean(mean) < 9.80665 * 100.0 / 6 * 1.5  # the legs lean: a little over their share
    np.testing.assert_allclose(give_high / high, 1.0, rtol=0.05)  # c ≈ 1 mm/kN: 1 µm a newton
    assert "data:image/png;base64," in section


def test_validate_with_a_report_predicts_each_row_at_its_own_payload(check, tmp_path, capsys):
    """``validate --report`` reads the log whole for its plots: it kept the payloads, as the streamed
    validate does — the same errors, not the 20 and 40 kg rows predicted unloaded (benchmarks.elastic's
    check at 60 poses a stage, ekf: position RMS 4.0 µm streamed, 79 µm with --report); its page shows
    the held-out log's leg forces too."""
    run, platform = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(platform))
    (tmp_path / "log.csv").write_text(log_text(run.log, platform))
    files = {"--platform": str(tmp_path / "platform.toml"), "--log": str(tmp_path / "log.csv")}
    argv = [
        "calibrate",
        *[x for pair in files.items() for x in pair],
        "--method",
        "ls",
        "--out",
        str(tmp_path / "r.json"),
    ]
    assert main(argv) == 0
    validate = ["validate", "--platform", files["--platform"], "--result", str(tmp_path / "r.json"), "--log"]
    capsys.readouterr()
    assert main([*validate, files["--log"], "--out", str(tmp_path / "V1.csv")]) == 0
    streamed = capsys.readouterr().out
    assert main([*validate, files["--log"], "--out", str(tmp_path / "V2.csv"), "--report", str(tmp_path / "rep")]) == 0
    whole = capsys.readouterr().out
    assert "position RMS 0.00" in streamed and whole == streamed
    errors = [
        np.genfromtxt(tmp_path / name, delimiter=",", names=True)["position_error_mm"] for name in ("V1.csv", "V2.csv")
    ]
    np.testing.assert_allclose(errors[1], errors[0], atol=1e-9)
    assert "<h2>Leg forces</h2>" in (tmp_path / "rep" / "index.html").read_text()


def test_a_streamed_calibration_takes_each_rows_payload_in_its_residuals(check, tmp_path):
    """calibrate ekf streams a tracker log and computes the residual RMS at the final estimate from its
    spool, which kept no payload: every row then counted as unloaded (after: 21–72 µm a channel on a
    0 / 20 / 40 kg log, 1 µm read whole). Both paths give the same residuals."""
    import json

    run, platform = check
    (tmp_path / "platform.toml").write_text(platform_to_toml(platform))
    (tmp_path / "log.csv").write_text(log_text(run.log, platform))
    argv = ["calibrate", "--platform", str(tmp_path / "platform.toml"), "--log", str(tmp_path / "log.csv")]
    argv += ["--method", "ekf", "--out"]
    assert main([*argv, str(tmp_path / "streamed.json")]) == 0
    assert main([*argv, str(tmp_path / "whole.json"), "--report", str(tmp_path / "rep")]) == 0  # read whole
    rms = [json.loads((tmp_path / f"{name}.json").read_text())["residual_rms"] for name in ("streamed", "whole")]
    np.testing.assert_allclose(rms[0]["after"], rms[1]["after"], rtol=1e-6)
    assert max(rms[0]["after"]) < 0.003  # the tracker's 1 µm, not the payload's give


def test_drawn_check_geometries_are_plausible_hexapods():
    """benchmarks.elastic --geometry-seed: each drawn 6-6 platform reads as a platform file, stands away
    from a singular pose at home (statics' Hadamard ratio > 1e-3), reaches its workspace's limits within
    its stroke range, and its legs' series compliance is 1 mm/kN ± 30 %; the default is the check's own
    geometry."""
    import tomllib

    from benchmarks.elastic import CheckGeometry, check_platform_toml, draw_geometry
    from stewart_calib.io.platform_file import parse_platform
    from stewart_calib.model import kinematics as kin
    from stewart_calib.model.statics import statics_matrix, statics_ratios

    assert "base r 420 mm, platform r 270 mm" in check_platform_toml(CheckGeometry())
    for seed in range(1, 7):
        geometry = draw_geometry(seed)
        assert 0.7 <= geometry.compliance_mm_per_kN <= 1.3
        platform = parse_platform(tomllib.loads(check_platform_toml(geometry)), f"seed {seed}")
        R, t = kin.pose_to_rt(platform.workspace.home[None])
        assert statics_ratios(platform.drive, statics_matrix(platform.drive, R, t))[0] > 1e-3
        ws = platform.workspace
        reach = np.r_[[ws.translation_limit] * 3, [ws.rotation_limit] * 3]
        corners = ws.home + np.concatenate([np.diag(reach), -np.diag(reach)])  # each axis to its limit
        assert np.all(np.abs(kin.inverse_kinematics(platform.drive, *kin.pose_to_rt(corners))) < 250.0)


def test_identifiability_of_an_outside_instrument_names_the_compliance_it_covers(tmp_path, capsys):
    """A motion-capture log of an elastic hobby hexapod: the report's heading named the drive, the stroke
    scale and the instrument but not the compliance its bound covers (c1…c6 listed below it, unnamed)."""
    from benchmarks.hobby import SOFT_LEGS, simulate

    data = simulate(0, build=SOFT_LEGS)
    (tmp_path / "platform.toml").write_text(platform_to_toml(data.elastic))
    (tmp_path / "log.csv").write_text(log_text(data.fit, data.elastic))
    assert (
        main(["identifiability", "--platform", str(tmp_path / "platform.toml"), "--log", str(tmp_path / "log.csv")])
        == 0
    )
    out = capsys.readouterr().out
    assert "Identifiability of drive, stroke scale, compliance and pose instrument from 108 poses" in out
    assert "c in mm/kN" in out
    sigma = {name: float(v) for name, v in re.findall(r"\b(c[1-6]) ([0-9.e+-]+)", out)}
    assert sorted(sigma) == [f"c{i}" for i in range(1, 7)] and all(0 < v < 150.0 for v in sigma.values())


def test_export_says_what_the_controller_leaves_out_of_an_elastic_calibration(check, tmp_path, capsys):
    """genhexkins and the plain JSON hold no compliance: an elastic calibration exported lost its legs' give
    without a word. Now one warning line with how much (the check's 60 kg platform at 1 mm/kN: a leg gives
    up to ~0.2 mm); none where the compliance is 0 (a rigid or a paper-ekf calibration)."""
    _, platform = check
    calibrated = dataclasses.replace(
        platform, elastic=dataclasses.replace(platform.elastic, compliance_mm_per_kN=np.full(6, 1.0))
    )
    for label, p in (("elastic", calibrated), ("held at 0", platform)):
        (tmp_path / f"{label}.toml").write_text(platform_to_toml(p))
        argv = ["export", "--platform", str(tmp_path / f"{label}.toml"), "--format", "json"]
        assert main([*argv, "--out", str(tmp_path / "drive.json")]) == 0
        err = capsys.readouterr().err
        warned = re.search(r"warning: json has no leg compliance: .* give c_i f_i .*, ([0-9.e-]+)–([0-9.e-]+) mm", err)
        if label == "elastic":
            assert warned and err.count("\n") == 2, err
            assert 0.0 < float(warned[1]) < float(warned[2]) < 0.5
        else:
            assert warned is None and "warning" not in err


def test_score_says_what_an_elastic_robots_results_are_scored_against(tmp_path, capsys):
    """simulate's truth holds each sample's loaded parameters and, beside them, the robot's unloaded drive
    (spec §10): an elastic ekf result is scored against that and the closed loop settles under the
    platform's weight, a paper-ekf result (no compliance) against the last row, and one line on stderr says
    which. A truth file without the unloaded drive (an older simulate's) keeps the warning that neither
    score is an elastic result's error."""
    from benchmarks.elastic import check_experiment_toml, check_platform_toml
    from stewart_calib.io import read_truth, write_truth
    from stewart_calib.io.platform_file import load_platform

    (tmp_path / "elastic-check.toml").write_text(check_platform_toml())
    (tmp_path / "experiment.toml").write_text(check_experiment_toml(20, validation=5))
    sim = tmp_path / "sim"
    assert main(["simulate", "--experiment", str(tmp_path / "experiment.toml"), "--out", str(sim)]) == 0
    files = ["--platform", str(sim / "platform.toml")]
    older = tmp_path / "older-truth.csv"
    platform = load_platform(sim / "platform.toml")
    write_truth(older, dataclasses.replace(read_truth(sim / "truth.csv", platform), unloaded=None), platform)
    for method in ("ekf", "paper-ekf"):
        out = str(tmp_path / f"{method}.json")
        assert main(["calibrate", *files, "--log", str(sim / "log.csv"), "--method", method, "--out", out]) == 0
        capsys.readouterr()
        assert main(["score", *files, "--result", out, "--truth", str(sim / "truth.csv")]) == 0
        err = capsys.readouterr().err
        against = "its unloaded drive" if method == "ekf" else "those in force at the truth's last sample"
        assert f"parameters scored against {against}" in err and "warning" not in err, err
        assert main(["score", *files, "--result", out, "--truth", str(older)]) == 0
        err = capsys.readouterr().err
        assert ("neither score is its error" in err) == (method == "ekf"), err


def test_simulate_refuses_a_load_centre_every_other_command_would(tmp_path, capsys):
    """An experiment's [load] centre of mass in metres typed as mm (90 m off the axis) was simulated — the
    robot 20 mm off its poses — and written into the platform's [elastic], which calibrate then refused.
    simulate refuses it by [elastic]'s rule, in one line naming the key, and writes nothing."""
    from benchmarks.elastic import CheckGeometry, check_experiment_toml, check_platform_toml

    (tmp_path / "elastic-check.toml").write_text(check_platform_toml())
    far = dataclasses.replace(CheckGeometry(), payload_com_mm=(90000.0, -60.0, 120.0))
    (tmp_path / "experiment.toml").write_text(check_experiment_toml(20, validation=5, geometry=far))
    out = tmp_path / "sim"
    assert main(["simulate", "--experiment", str(tmp_path / "experiment.toml"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "key 'load.payload_com_mm': expected [x, y, z] in mm within 10 platform radii" in err
    assert not out.exists()
