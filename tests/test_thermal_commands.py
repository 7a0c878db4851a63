"""The legs' temperature through every command (spec §17): ``compensate --temperature-C``, ``validate`` at
each row's temperatures, ``track`` and its checkpoints, ``import`` of a controller's temperature columns,
``export``'s warning, the expansion's trade-off with the legs' lengths in ``identifiability`` and
``calibrate``, the HTML report and the rerun recording; every refusal one line, asserted by its text.

The data: nim-stewart with ``[thermal]`` (reference 22 °C, nominal α 0, σ 20 ppm/K), a true drive δM
(σ 0.5 mm) whose legs expand by 10.5…13 ppm/K, and warm-up logs of it — ambient 19 → 31 °C over the
log, each leg within ±1.5 K of it — with strokes from the true drive's inverse kinematics at each row's
temperatures and the in-situ tracker's readings (σ 2 µm, strokes σ 1 µm).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.io import log_text, read_log, read_result
from stewart_calib.io.platform_file import load_platform, platform_to_toml
from stewart_calib.model import kinematics as kin
from stewart_calib.model.drive import THERMAL, drive_model
from stewart_calib.model.platform import Elastic, Thermal
from stewart_calib.samples import TEMPERATURE_C, Log
from tests.synthetic import ROOT, nim_stewart, random_error, random_poses

REFERENCE_C = 22.0
TRUE_ALPHA = np.array([11.5, 12.0, 10.5, 13.0, 11.0, 12.5])  # ppm/K
N = 200
EXAMPLE = ROOT / "examples" / "hobby-mocap"


def thermal_platform(sigma_ppm_per_K: float = 20.0):
    return dataclasses.replace(nim_stewart(), thermal=Thermal(REFERENCE_C, np.zeros(6), sigma_ppm_per_K))


def true_drive(platform, seed: int = 5):
    return drive_model(platform).true_drive(random_error(np.random.default_rng(seed), 0.5), {THERMAL: TRUE_ALPHA})


def warm_log(platform, truth, n: int, seed: int, low_C: float = 19.0, high_C: float = 31.0, spread_K: float = 1.5):
    """A warm-up log of the true drive ``truth``: ambient ``low_C → high_C`` over ``n`` rows, each leg within
    ``±spread_K`` of it."""
    rng = np.random.default_rng(seed)
    poses = random_poses(platform, n, rng)
    temperatures = np.linspace(low_C, high_C, n)[:, None] + rng.uniform(-spread_K, spread_K, (n, 6))
    R, t = kin.pose_to_rt(poses)
    strokes = truth.inverse_kinematics(R, t, channels={TEMPERATURE_C: temperatures}) + rng.normal(0, 0.001, (n, 6))
    readings = kin.inverse_kinematics(platform.tracker, R, t) + rng.normal(0, 0.002, (n, 6))
    return Log(np.arange(n) * 1.0, strokes, readings, poses.copy(), inputs={TEMPERATURE_C: temperatures})


def write_poses(path: Path, poses: np.ndarray) -> None:
    rows = np.c_[poses[:, :3], np.degrees(poses[:, 3:])]
    path.write_text(
        "x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n" + "".join(",".join(map(repr, r)) + "\n" for r in rows.tolist())
    )


def read_strokes(path: Path) -> np.ndarray:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return np.array([[float(row[f"q{i}_mm"]) for i in range(1, 7)] for row in rows])


def run(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out.strip(), captured.err.strip()


@pytest.fixture(scope="module")
def warm(tmp_path_factory):
    """Files of one warm-up: ``p.toml`` (thermal), ``rigid.toml`` (the same without ``[thermal]``), the log
    ``log.csv``, a held-out warm-up ``held.csv``, and ``ls`` calibrations of both platforms on the log."""
    root = tmp_path_factory.mktemp("warm")
    platform = thermal_platform()
    truth = true_drive(platform)
    log, held = warm_log(platform, truth, N, 1), warm_log(platform, truth, 60, 2)
    (root / "p.toml").write_text(platform_to_toml(platform))
    (root / "rigid.toml").write_text(platform_to_toml(dataclasses.replace(platform, thermal=None)))
    (root / "log.csv").write_text(log_text(log, platform))
    (root / "held.csv").write_text(log_text(held, platform))
    for name in ("p", "rigid"):
        argv = ["calibrate", "--platform", root / f"{name}.toml", "--log", root / "log.csv", "--method", "ls"]
        assert (
            main([str(a) for a in [*argv, "--out", root / f"r_{name}.json", "--platform-out", root / f"c_{name}.toml"]])
            == 0
        )
    return root, platform, truth, log


# ----------------------------------------------------------------------------- compensate


def _reached_error_mm(truth, poses: np.ndarray, strokes: np.ndarray, temperature_C: float) -> np.ndarray:
    """Position error [mm] of the true robot, its legs at ``temperature_C``, commanded ``strokes``."""
    channels = {TEMPERATURE_C: np.full((len(poses), 6), temperature_C)}
    reached = truth.forward_kinematics(truth.inputs(strokes, channels))
    return np.linalg.norm(reached.pose6[:, :3] - poses[:, :3], axis=1)


def test_compensate_commands_poses_at_a_temperature_past_the_logs(warm, tmp_path, capsys):
    """Fresh poses at 20 and at 35 °C (past the log's 17.5–32.5 °C): the error at 35 °C within 1.5× its own at
    20 °C + 3 µm and under a quarter of the rigid model's there (measured with ls: 0.8 / 1.3 µm, the rigid
    model 146 µm at 35 °C)."""
    root, platform, truth, _ = warm
    poses = random_poses(platform, 50, np.random.default_rng(9), fraction=0.8)
    write_poses(tmp_path / "poses.csv", poses)
    errors = {}
    for temperature in (20.0, 35.0):
        out = tmp_path / f"q{temperature:g}.csv"
        argv = ["compensate", "--platform", root / "c_p.toml", "--poses", tmp_path / "poses.csv", "--out", out]
        code, _, err = run(capsys, *argv, "--temperature-C", temperature)
        assert code == 0, err
        errors[temperature] = float(np.mean(_reached_error_mm(truth, poses, read_strokes(out), temperature)))
    rigid = tmp_path / "rigid.csv"
    assert (
        run(
            capsys, "compensate", "--platform", root / "c_rigid.toml", "--poses", tmp_path / "poses.csv", "--out", rigid
        )[0]
        == 0
    )
    rigid_35 = float(np.mean(_reached_error_mm(truth, poses, read_strokes(rigid), 35.0)))
    assert errors[35.0] <= 1.5 * errors[20.0] + 0.003, errors
    assert errors[35.0] <= 0.25 * rigid_35, (errors, rigid_35)
    assert errors[35.0] < 0.005 and rigid_35 > 0.05  # µm where the rigid model leaves tenths of a millimetre


def test_compensate_defaults_to_the_reference_temperature(warm, tmp_path, capsys):
    """Without ``--temperature-C`` the legs are at ``[thermal] reference_temperature_C`` (22 °C): the same
    strokes bit for bit as ``--temperature-C 22``, and others than at 20 °C (each leg ~0.025 mm longer there)."""
    root, platform, _, _ = warm
    write_poses(tmp_path / "poses.csv", random_poses(platform, 10, np.random.default_rng(3), fraction=0.5))
    base = ["compensate", "--platform", root / "c_p.toml", "--poses", tmp_path / "poses.csv", "--out"]
    for name, extra in (("default", []), ("ref", ["--temperature-C", "22"]), ("cold", ["--temperature-C", "20"])):
        assert run(capsys, *base, tmp_path / f"{name}.csv", *extra)[0] == 0
    default, ref, cold = (read_strokes(tmp_path / f"{name}.csv") for name in ("default", "ref", "cold"))
    np.testing.assert_array_equal(default, ref)
    # 2 K colder: each leg shorter by α_i · 2 K · L_i, its stroke longer by that (L ≈ 1.05–1.35 m)
    np.testing.assert_array_less(0.015, cold - ref)
    np.testing.assert_array_less(cold - ref, 0.04)


@pytest.mark.parametrize(
    ("platform_name", "value", "expected"),
    [
        (
            "rigid",
            "25",
            "--temperature-C: {rigid} has no [thermal] (spec §17): a model without the legs' expansion has no "
            "temperature to compensate",
        ),
        ("p", "150.5", "--temperature-C: expected a temperature within [-50, 150] °C, got 150.5"),
        ("p", "-51", "--temperature-C: expected a temperature within [-50, 150] °C, got -51.0"),
        ("p", "nan", "--temperature-C: expected a temperature within [-50, 150] °C, got nan"),
    ],
)
def test_compensate_refuses_a_temperature_in_one_line(warm, tmp_path, capsys, platform_name, value, expected):
    root, platform, _, _ = warm
    write_poses(tmp_path / "poses.csv", random_poses(platform, 3, np.random.default_rng(3), fraction=0.5))
    out = tmp_path / "q.csv"
    platform_path = root / f"c_{platform_name}.toml"
    code, _, err = run(
        capsys,
        "compensate",
        "--platform",
        platform_path,
        "--poses",
        tmp_path / "poses.csv",
        "--out",
        out,
        "--temperature-C",
        value,
    )
    assert code == 2 and "\n" not in err
    assert err == "stewart-calib compensate: error: " + expected.format(rigid=platform_path)
    assert not out.exists()


def test_the_online_calibrator_compensates_at_the_channels_it_is_given(warm):
    """``OnlineCalibrator.compensated_strokes(pose, {"temperature_C": …})``: the strokes of the calibrated
    model at those temperatures, as ``compensate`` gives them."""
    from stewart_calib.analysis.compensation import compensate
    from stewart_calib.workflows.online import OnlineCalibrator

    _, platform, _, log = warm
    calibrator = OnlineCalibrator(platform, "ekf")
    calibrator.update_block(log)
    pose = np.r_[platform.workspace.home[:3], np.degrees(platform.workspace.home[3:])]
    warm_legs = {TEMPERATURE_C: np.full(6, 30.0)}
    strokes = calibrator.compensated_strokes(pose, warm_legs)
    drive = drive_model(platform).calibrated_by(calibrator.estimate())
    np.testing.assert_allclose(strokes, compensate(drive, platform.workspace.home, inputs=warm_legs), rtol=0, atol=1e-9)
    cold = calibrator.compensated_strokes(pose, {TEMPERATURE_C: np.full(6, REFERENCE_C)})
    assert np.all(strokes < cold - 0.05)  # 8 K warmer: ~0.1 mm longer legs, shorter strokes


# ----------------------------------------------------------------------------- validate


def _validate_rms_mm(capsys, root: Path, result: Path, out: Path) -> float:
    code, text, _ = run(
        capsys, "validate", "--platform", root / "p.toml", "--result", result, "--log", root / "held.csv", "--out", out
    )
    assert code == 0
    return float(re.search(r"position RMS ([0-9.e-]+) mm", text).group(1))


def test_validate_predicts_each_row_at_its_own_temperatures(warm, tmp_path, capsys):
    """The calibrated thermal model on a held-out warm-up: µm (the tracker's reading noise); the same model
    with α zeroed, each leg's growth at the rows' 17.5–32.5 °C left out: ten times that and more (measured
    5.0 µm against 71 µm)."""
    root, _, _, _ = warm
    rms = _validate_rms_mm(capsys, root, root / "r_p.json", tmp_path / "V.csv")
    zeroed = json.loads((root / "r_p.json").read_text())
    zeroed[THERMAL]["estimate"] = [0.0] * 6
    (tmp_path / "zeroed.json").write_text(json.dumps(zeroed))
    rms_zeroed = _validate_rms_mm(capsys, root, tmp_path / "zeroed.json", tmp_path / "V0.csv")
    assert rms < 0.008 and rms_zeroed > 10 * rms, (rms, rms_zeroed)


# ----------------------------------------------------------------------------- track and checkpoints


#: how far a resumed run may be from one run over the whole log [mm, ppm/K]: ekf's state is its checkpoint's
#: bit for bit; isam2's fixed-lag smoother is rebuilt from its replay buffer on loading, which
#: relinearises (the package's tolerance for it, tests/test_online.py)
RESUME_TOLERANCE = {"ekf": 0.0, "isam2": 1e-6}


@pytest.mark.parametrize("method", ["ekf", "isam2"])
def test_track_resumes_a_warm_log_from_its_checkpoint(warm, tmp_path, capsys, method):
    """``track`` reads the temperature columns like any other; a checkpoint after 80 rows, resumed on the
    whole log, gives the estimate of one run over it — ekf's bit for bit, α among it (isam2: 2.6e-7 mm,
    2.9e-7 ppm/K)."""
    root, _, _, _ = warm
    text = (root / "log.csv").read_text().splitlines(keepends=True)
    part = tmp_path / "part.csv"
    part.write_text("".join(text[: 1 + 80]))
    common = ["track", "--platform", root / "p.toml", "--method", method]
    assert run(capsys, *common, "--log", root / "log.csv", "--out", tmp_path / "whole.json")[0] == 0
    checkpoint = tmp_path / "c.npz"
    assert run(capsys, *common, "--log", part, "--out", tmp_path / "r.json", "--checkpoint", checkpoint)[0] == 0
    assert read_result(tmp_path / "r.json")["samples_used"] == 80
    assert (
        run(capsys, *common, "--log", root / "log.csv", "--out", tmp_path / "r.json", "--checkpoint", checkpoint)[0]
        == 0
    )
    whole, resumed = read_result(tmp_path / "whole.json"), read_result(tmp_path / "r.json")
    assert resumed["samples_used"] == whole["samples_used"] == N
    tolerance = RESUME_TOLERANCE[method]
    np.testing.assert_allclose(resumed["error"], whole["error"], rtol=0, atol=tolerance)
    np.testing.assert_allclose(resumed[THERMAL]["estimate"], whole[THERMAL]["estimate"], rtol=0, atol=tolerance)
    np.testing.assert_allclose(whole[THERMAL]["estimate"], TRUE_ALPHA, atol=2.0)  # within 2 ppm/K of the truth


def test_an_online_checkpoint_keeps_each_held_samples_temperatures(warm, tmp_path):
    """Saved mid-log and loaded, ``OnlineCalibrator`` goes on as if never stopped, bit for bit (ekf): the
    temperatures of the samples it holds are in the checkpoint."""
    from stewart_calib.workflows.online import OnlineCalibrator

    _, platform, _, log = warm
    never = OnlineCalibrator(platform, "ekf")
    never.update_block(log)
    first = OnlineCalibrator(platform, "ekf")
    first.update_block(log.select(slice(0, 37)))
    first.save(tmp_path / "c.npz")
    resumed = OnlineCalibrator.load(tmp_path / "c.npz", platform)
    resumed.update_block(log.select(slice(37, None)))
    np.testing.assert_array_equal(resumed.estimate().error, never.estimate().error)
    np.testing.assert_array_equal(resumed.estimate().block_values(THERMAL), never.estimate().block_values(THERMAL))


# ----------------------------------------------------------------------------- import


def test_import_maps_the_controllers_temperature_columns_like_the_strokes(tmp_path, capsys):
    """A Motive export and a controller log of counts with one temperature column in K: the log gets
    ``temp1_C … temp6_C`` after the measured columns, interpolated to each measurement's time like the
    strokes; six columns in °C give each leg its own."""
    from scipy.spatial.transform import Rotation

    from . import vendor_files as vendor

    t = np.arange(100) / 50.0
    rotation = Rotation.from_euler("xyz", np.radians(5.0) * np.sin(np.outer(t, [0.3, 0.5, 0.7])))
    position = 100.0 + 20.0 * np.sin(np.outer(t, [0.2, 0.4, 0.6]))
    vendor.motive_csv(tmp_path / "m.csv", t, rotation.as_quat(), position * 1e-3)
    t_c = np.arange(-0.1, 2.2, 0.004)
    q = 40.0 + 10.0 * np.sin(np.outer(t_c, [0.31, 0.47, 0.23, 0.59, 0.37, 0.41]))
    legs_C = 20.0 + 3.0 * t_c[:, None] + np.arange(6) * 0.5  # warming by 3 K/s, each leg its own
    header = ["stamp_ms", *(f"leg{i}" for i in range(1, 7)), "T_K", *(f"T{i}" for i in range(1, 7))]
    with open(tmp_path / "c.csv", "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        for k in range(len(t_c)):
            writer.writerow(
                [
                    repr(float(t_c[k] * 1e3)),
                    *map(repr, (q[k] * 100.0).tolist()),
                    repr(float(legs_C[k, 0] + 273.15)),
                    *map(repr, legs_C[k].tolist()),
                ]
            )
    base = (
        '[strokes]\ntime = "stamp_ms"\ntime_unit = "ms"\n'
        'columns = ["leg1", "leg2", "leg3", "leg4", "leg5", "leg6"]\nunit = "counts"\ncounts_per_mm = 100.0\n'
    )
    platform = dataclasses.replace(load_platform("hobby-hexapod"), thermal=Thermal())
    for name, mapping, expected in (
        (
            "one",
            base + 'temperatures = ["T_K"]\ntemperature_unit = "K"\n',
            np.repeat(20.0 + 3.0 * t[:, None], 6, axis=1),
        ),
        (
            "six",
            base + f"temperatures = {[f'T{i}' for i in range(1, 7)]!r}\n".replace("'", '"'),
            20.0 + 3.0 * t[:, None] + np.arange(6) * 0.5,
        ),
    ):
        (tmp_path / f"{name}.toml").write_text(mapping)
        out = tmp_path / f"{name}.csv"
        code, _, err = run(
            capsys,
            "import",
            "--motive",
            tmp_path / "m.csv",
            "--rigid-body",
            "platform",
            "--strokes",
            tmp_path / "c.csv",
            "--mapping",
            tmp_path / f"{name}.toml",
            "--up",
            "z",
            "--out",
            out,
        )
        assert code == 0, err
        assert ("temperatures in K (one for all legs)" if name == "one" else "temperatures in °C (one per leg)") in err
        columns = out.read_text().splitlines()[0].split(",")
        assert columns[-6:] == [f"temp{i}_C" for i in range(1, 7)] and columns[7:13] == [
            "mx_mm",
            "my_mm",
            "mz_mm",
            "mroll_deg",
            "mpitch_deg",
            "myaw_deg",
        ]
        log = read_log(out, platform)
        np.testing.assert_allclose(log.inputs[TEMPERATURE_C], expected, rtol=0, atol=1e-9)  # linear in time: exact
        np.testing.assert_allclose(
            log.strokes, 40.0 + 10.0 * np.sin(np.outer(t, [0.31, 0.47, 0.23, 0.59, 0.37, 0.41])), atol=2e-4
        )


# ----------------------------------------------------------------------------- export


def test_export_warns_what_a_controller_without_thermal_compensation_leaves_out(warm, tmp_path, capsys):
    """The largest |α_i| · 10 K · L_i at the workspace's home (136 µm here: α4 ≈ 13 ppm/K on a leg of
    1.05 m); the json carries the calibrated expansion, genhexkins has no place for it."""
    root, platform, _, _ = warm
    calibrated = load_platform(root / "c_p.toml")
    alpha = np.asarray(calibrated.thermal.expansion_ppm_per_K)
    legs = calibrated.drive
    R, t = kin.pose_to_rt(platform.workspace.home)
    lengths = np.linalg.norm(t + legs.platform_joints @ R.T - legs.base_joints, axis=-1)  # joint to joint at home
    growth_um = np.abs(alpha) * 10.0 * lengths * 1e-3
    leg = int(np.argmax(growth_um))
    for fmt, words in (
        ("linuxcnc", "has no thermal expansion"),
        ("json", 'carries the expansion ("thermal") that a controller must apply'),
    ):
        code, _, err = run(
            capsys, "export", "--platform", root / "c_p.toml", "--format", fmt, "--out", tmp_path / f"e.{fmt}"
        )
        assert code == 0
        line = err.splitlines()[-1]
        assert line == (
            f"stewart-calib export: warning: {fmt} {words}: a controller without thermal compensation leaves out the "
            f"legs' growth α_i ΔT_i L_i, up to {growth_um[leg]:.3g} µm (leg {leg + 1}) at ±10 K from the reference "
            "22 °C; stewart-calib compensate --temperature-C gives strokes with it"
        )
        assert 100 < growth_um[leg] < 200
    exported = json.loads((tmp_path / "e.json").read_text())
    assert exported["thermal"] == {"reference_temperature_C": REFERENCE_C, "expansion_ppm_per_K": alpha.tolist()}
    code, _, err = run(
        capsys, "export", "--platform", root / "c_rigid.toml", "--format", "json", "--out", tmp_path / "r.json"
    )
    assert code == 0 and "thermal" not in err and "thermal" not in json.loads((tmp_path / "r.json").read_text())


def test_export_gives_the_compliance_not_the_expansion_with_both_tables(tmp_path, capsys):
    """With ``[elastic]`` and ``[thermal]`` the give warning takes the compliance term by its key: the same
    numbers as the elastic platform alone."""
    elastic = Elastic(60.0, np.array([0.0, 0.0, -50.0]), compliance_mm_per_kN=np.full(6, 1.0))
    base = dataclasses.replace(nim_stewart(), elastic=elastic)
    lines = {}
    for name, platform in (
        ("elastic", base),
        ("both", dataclasses.replace(base, thermal=Thermal(20.0, np.full(6, 11.5), 0.0))),
    ):
        (tmp_path / f"{name}.toml").write_text(platform_to_toml(platform))
        code, _, err = run(
            capsys,
            "export",
            "--platform",
            tmp_path / f"{name}.toml",
            "--format",
            "json",
            "--out",
            tmp_path / f"{name}.json",
        )
        assert code == 0
        lines[name] = [line for line in err.splitlines() if "leg compliance" in line]
    assert len(lines["elastic"]) == 1 and lines["both"] == lines["elastic"]


# ----------------------------------------------------------------------------- identifiability and calibrate


def _at_one_temperature(log: Log, spread_K: float) -> Log:
    """``log`` with every leg at 25 °C, rising by ``spread_K`` over the rows."""
    n = len(log)
    temperatures = np.repeat(25.0 + spread_K * np.arange(n)[:, None] / max(n - 1, 1), 6, axis=1)
    return dataclasses.replace(log, inputs={TEMPERATURE_C: temperatures})


def test_identifiability_names_the_expansion_and_its_trade_off_at_one_temperature(warm, tmp_path, capsys):
    """The warm-up identifies α1…α6 (σ 0.05 ppm/K, no trade-off line); at one temperature α_i ΔT (l_i + q_i)
    is a combination of l_i and k_i — the σ of α with them free is unbounded — and one line says so."""
    root, platform, _, log = warm
    code, text, _ = run(capsys, "identifiability", "--platform", root / "p.toml", "--log", root / "log.csv")
    assert code == 0
    assert "drive parameters and alpha1…alpha6" in text and "thermal [ppm/K]: alpha1" in text
    assert "not separable" not in text
    (tmp_path / "one.csv").write_text(log_text(_at_one_temperature(log, 0.0), platform))
    code, text, _ = run(
        capsys,
        "identifiability",
        "--platform",
        root / "p.toml",
        "--log",
        tmp_path / "one.csv",
        "--json",
        tmp_path / "i.json",
    )
    assert code == 0
    expected = (
        "warning: alpha1…alpha6 not separable from l_i and k_i: the log spans 0 K (at one temperature α_i ΔT "
        "(l_i + q_i) is a combination of l_i and k_i; not identified by the data, above the prior σ 20 ppm/K): "
        "the calibration keeps them near [thermal] expansion_ppm_per_K; a log over a warm-up separates them"
    )
    assert f"stewart-calib identifiability: {expected}" in text.splitlines()  # the JSON's field is the line itself
    assert json.loads((tmp_path / "i.json").read_text())["thermal_trade_off"] == expected


def test_the_trade_off_threshold_is_the_data_against_the_prior(warm, tmp_path, capsys):
    """A log spanning 0.3 K tells α to ~2 ppm/K with l_i and k_i free (Cramér–Rao): within a prior σ of 20
    ppm/K no line, past a prior σ of 1 ppm/K the line, in ``calibrate`` as in ``identifiability``."""
    root, platform, _, log = warm
    (tmp_path / "narrow.csv").write_text(log_text(_at_one_temperature(log, 0.3), platform))
    (tmp_path / "tight.toml").write_text(platform_to_toml(thermal_platform(1.0)))
    found = {}
    for name in ("p", "tight"):
        platform_path = root / "p.toml" if name == "p" else tmp_path / "tight.toml"
        _, text, _ = run(capsys, "identifiability", "--platform", platform_path, "--log", tmp_path / "narrow.csv")
        argv = [
            "calibrate",
            "--platform",
            platform_path,
            "--log",
            tmp_path / "narrow.csv",
            "--method",
            "ls",
            "--out",
            tmp_path / f"{name}.json",
        ]
        code, _, err = run(capsys, *argv)
        assert code == 0
        found[name] = (
            [line for line in text.splitlines() if "not separable" in line],
            [line for line in err.splitlines() if "not separable" in line],
        )
    assert found["p"] == ([], [])
    (identifiability_line,), (calibrate_line,) = found["tight"]
    assert identifiability_line.startswith(
        "stewart-calib identifiability: warning: alpha1…alpha6 not separable from l_i and k_i: the log spans 0.3 K"
    )
    sigma = [float(v) for v in re.search(r"Cramér–Rao σ ([0-9.]+)–([0-9.]+) ppm/K", identifiability_line).groups()]
    assert 1.0 < sigma[0] <= sigma[1] < 10.0 and "above the prior σ 1 ppm/K" in identifiability_line
    assert calibrate_line.startswith(
        "stewart-calib calibrate: warning: alpha1…alpha6 not separable from l_i and k_i: the log spans 0.3 K"
    )


# ----------------------------------------------------------------------------- report and recording


def test_the_report_and_the_recording_show_each_legs_temperature_and_growth(warm, tmp_path, capsys):
    """The HTML report's leg temperatures (the log's own range per leg) and growth α_i ΔT_i L_i (up to ~0.14
    mm at 10 K above the reference); the rerun recording's one line per leg of each."""
    from tests.readback import read_blueprint_names, read_scalars

    root, _, _, log = warm
    argv = [
        "calibrate",
        "--platform",
        root / "p.toml",
        "--log",
        root / "log.csv",
        "--method",
        "ekf",
        "--out",
        tmp_path / "r.json",
    ]
    assert run(capsys, *argv, "--report", tmp_path / "rep", "--rerun", tmp_path / "r.rrd")[0] == 0
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "<h2>Leg expansion α ± σ</h2>" in page
    section = page[page.index("<h2>Leg temperatures</h2>") :]
    rows = re.findall(r"<tr><td>leg (\d)</td>((?:<td>[^<]*</td>){5})</tr>", section)
    assert [int(leg) for leg, _ in rows] == [1, 2, 3, 4, 5, 6]
    values = np.array([[float(v) for v in re.findall(r"<td>([^<]*)</td>", cells)] for _, cells in rows])
    temperatures = log.inputs[TEMPERATURE_C]
    np.testing.assert_allclose(values[:, 0], temperatures.min(axis=0), rtol=1e-3)
    np.testing.assert_allclose(values[:, 2], temperatures.max(axis=0), rtol=1e-3)
    alpha = np.array(read_result(tmp_path / "r.json")[THERMAL]["estimate"])
    lengths = load_platform(root / "p.toml").drive.initial_lengths + log.strokes  # joint to joint, within 1e-3
    growth_um = alpha * (temperatures - REFERENCE_C) * lengths * 1e-3
    np.testing.assert_allclose(values[:, 3], growth_um.min(axis=0), rtol=0.01)
    np.testing.assert_allclose(values[:, 4], growth_um.max(axis=0), rtol=0.01)
    assert 100 < values[:, 4].max() < 200  # µm: 10.5 K above the reference on a 1.1 m leg
    assert "data:image/png;base64," in section
    _, recorded = read_scalars(tmp_path / "r.rrd", "temperature/leg3")
    np.testing.assert_allclose(recorded, temperatures[:, 2], rtol=0, atol=1e-12)
    _, grown = read_scalars(tmp_path / "r.rrd", "growth/leg3/ekf")
    np.testing.assert_allclose(grown, growth_um[:, 2], rtol=0.01, atol=0.05)
    assert "inputs" in read_blueprint_names(tmp_path / "r.rrd")


def test_import_reads_a_loggers_own_temperature_column_from_the_same_rows(tmp_path, capsys):
    """A logger that writes counts, the pose and one temperature per row (``--csv``): the temperature is read
    with the strokes, every leg's the same, after the measured columns."""
    rows = (EXAMPLE / "fit_raw.csv").read_text().splitlines()
    warm_C = [20.0 + 0.25 * k for k in range(len(rows) - 1)]
    (tmp_path / "raw.csv").write_text(
        "\n".join([rows[0] + ",leg_C", *(f"{row},{c!r}" for row, c in zip(rows[1:], warm_C, strict=True))]) + "\n"
    )
    mapping = (EXAMPLE / "raw.toml").read_text() + 'temperatures = ["leg_C"]\n'
    (tmp_path / "raw.toml").write_text(mapping)
    out = tmp_path / "log.csv"
    code, _, err = run(
        capsys, "import", "--csv", tmp_path / "raw.csv", "--mapping", tmp_path / "raw.toml", "--out", out
    )
    assert code == 0, err
    assert out.read_text().splitlines()[0].split(",")[-6:] == [f"temp{i}_C" for i in range(1, 7)]
    log = read_log(out, dataclasses.replace(load_platform("hobby-hexapod"), thermal=Thermal()))
    np.testing.assert_array_equal(log.inputs[TEMPERATURE_C], np.repeat(np.array(warm_C)[:, None], 6, axis=1))
    plain = tmp_path / "plain.csv"
    assert (
        run(capsys, "import", "--csv", EXAMPLE / "fit_raw.csv", "--mapping", EXAMPLE / "raw.toml", "--out", plain)[0]
        == 0
    )
    np.testing.assert_array_equal(log.strokes, read_log(plain, load_platform("hobby-hexapod")).strokes)
