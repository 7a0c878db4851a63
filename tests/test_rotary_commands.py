"""Every command besides calibrate on a rotary (servo-horn) drive (spec §15): plan, identifiability,
track and its checkpoints, export, the HTML report, the rerun recording, import and import-bag, and
the one-line refusal of a log of the other drive kind."""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stewart_calib import cli, io
from stewart_calib.io import read_log
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin
from stewart_calib.resources import CONFIGS
from stewart_calib.viz.geometry import leg_polylines, robot_at

#: a shorter servo experiment than the shipped one (60 calibration poses, 10 validation), its platform the shipped one
EXPERIMENT = (CONFIGS / "experiments" / "servo.toml").read_text(encoding="utf-8")
EXPERIMENT = EXPERIMENT.replace("calibration = 150", "calibration = 60").replace("validation = 30", "validation = 10")


def _run(capsys, *argv) -> tuple[int, str]:
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip()


@pytest.fixture(scope="module")
def servo(tmp_path_factory):
    """A simulated servo run: ``{"dir", "platform", "log", "truth", "result", "report", "rrd"}``, the
    result of ``calibrate --method ekf --report --rerun``."""
    root = tmp_path_factory.mktemp("servo")
    (root / "servo.toml").write_text(EXPERIMENT, encoding="utf-8")
    assert cli.main(["simulate", "--experiment", str(root / "servo.toml"), "--out", str(root / "sim")]) == 0
    files = {"dir": root, "platform": root / "sim" / "platform.toml", "log": root / "sim" / "log.csv"}
    argv = ["calibrate", "--platform", files["platform"], "--log", files["log"], "--method", "ekf"]
    argv += ["--out", root / "r.json", "--report", root / "report", "--rerun", root / "r.rrd"]
    assert cli.main([str(a) for a in argv]) == 0
    return {**files, "result": root / "r.json", "report": root / "report" / "index.html", "rrd": root / "r.rrd"}


def test_plan_keeps_a_servos_angles_inside_its_range_by_the_margin(capsys, tmp_path):
    out = tmp_path / "plan.csv"
    code, _ = _run(
        capsys, "plan", "--platform", "servo-hexapod", "--n", "20", "--candidates", "200", "--seed", "3", "--out", out
    )
    assert code == 0
    platform = load_platform("servo-hexapod")
    poses = io.read_pose_list(out)
    angles = np.degrees(platform.drive.coordinates(*kin.pose_to_rt(poses)))
    low, high = np.degrees(platform.drive.angle_range)
    margin = 2.0 * 2.0  # STROKE_MARGIN_SIGMAS × noise.angle_prior_sigma_deg
    assert np.all(np.isfinite(angles)) and len(poses) == 20
    assert np.all(angles >= low + margin - 1e-9) and np.all(angles <= high - margin + 1e-9)


def test_plan_says_how_far_inside_the_range_a_servos_angles_stay(capsys, tmp_path):
    code = cli.main(
        [
            "plan",
            "--platform",
            "servo-hexapod",
            "--n",
            "12",
            "--candidates",
            "100",
            "--seed",
            "1",
            "--out",
            str(tmp_path / "p.csv"),
        ]
    )
    assert code == 0
    assert "angles 4 deg inside the range" in capsys.readouterr().out


def test_identifiability_names_the_66_in_file_units_and_the_weak_axis_tilts(servo, capsys, tmp_path):
    out = tmp_path / "i.json"
    code, err = _run(capsys, "identifiability", "--platform", servo["platform"], "--log", servo["log"], "--json", out)
    assert code == 0, err
    report = json.loads(out.read_text())
    legs = load_platform(servo["platform"]).drive
    sd = report["predicted_stddev"]
    assert list(sd)[: legs.n_params] == list(legs.parameter_names)
    # a servo's angles in degrees: 70 poses of motion capture see a zero offset to about a degree
    # (in radians it would read 0.02)
    assert all(0.1 < sd[f"o{i}"] < 10.0 for i in range(1, 7))
    # the axes' tilts about w are what these poses see least: no better than their prior (2°), named
    assert {f"tw{i}" for i in range(1, 7)} <= set(report["weak_against_prior"])
    assert not any(name.startswith(("a", "d")) for name in report["weak_against_prior"])
    assert "crank centres" in report["gauge"]


def test_identifiability_text_says_angle_scale_and_names_the_weak_ones(servo, capsys):
    assert cli.main(["identifiability", "--platform", str(servo["platform"]), "--log", str(servo["log"])]) == 0
    text = capsys.readouterr().out
    assert text.startswith("Identifiability of drive, angle scale and pose instrument from 70 poses")
    prior = "stewart-calib identifiability: seen no better than their prior"
    (line,) = [line for line in text.splitlines() if line.startswith(prior)]
    assert re.search(r"tw\d [\d.]+ \(prior 2\)", line)


def test_track_resumes_a_servo_log_from_its_checkpoint_to_the_uninterrupted_estimate(servo, capsys, tmp_path):
    lines = servo["log"].read_text().splitlines(keepends=True)
    half = tmp_path / "half.csv"
    half.write_text("".join(lines[:36]))
    base = ["track", "--platform", servo["platform"], "--method", "ekf", "--every", "10"]
    checkpoint = tmp_path / "c.npz"
    assert _run(capsys, *base, "--log", half, "--checkpoint", checkpoint, "--out", tmp_path / "a.json")[0] == 0
    assert checkpoint.exists()
    code, err = _run(capsys, *base, "--log", servo["log"], "--checkpoint", checkpoint, "--out", tmp_path / "a.json")
    assert code == 0 and "70 samples used" in err
    assert _run(capsys, *base, "--log", servo["log"], "--out", tmp_path / "b.json")[0] == 0
    resumed, whole = (json.loads((tmp_path / name).read_text()) for name in ("a.json", "b.json"))
    assert resumed["parameter_names"][:11] == ["a1x", "a1y", "a1z", "d1x", "d1y", "d1z", "h1", "r1", "o1", "tu1", "tw1"]
    np.testing.assert_array_equal(resumed["estimate"], whole["estimate"])
    np.testing.assert_array_equal(resumed["stroke_scale"]["estimate"], whole["stroke_scale"]["estimate"])


def test_export_json_is_the_calibrated_servos_and_genhexkins_is_refused(servo, capsys, tmp_path):
    from stewart_calib.pipelines.handover import calibrated_model

    out = tmp_path / "servos.json"
    code, err = _run(
        capsys, "export", "--platform", servo["platform"], "--result", servo["result"], "--format", "json", "--out", out
    )
    assert code == 0, err
    exported = json.loads(out.read_text())
    model = calibrated_model(load_platform(servo["platform"]), str(servo["result"]))
    legs, result = model.legs, json.loads(servo["result"].read_text())
    assert exported["kind"] == "rotary" and exported["angle_range_deg"] == [-75.0, 75.0]
    for n, leg in enumerate(exported["legs"]):
        np.testing.assert_allclose(leg["crank_centre"], legs.crank_centres[n], rtol=0, atol=1e-12)
        np.testing.assert_allclose(leg["crank_axis"], legs.crank_axes[n], rtol=0, atol=1e-12)
        assert math.isclose(leg["zero_trim_deg"], result["estimate"][result["parameter_names"].index(f"o{n + 1}")])
        assert math.isclose(leg["angle_per_commanded_degree"], 1.0 + result["stroke_scale"]["estimate"][n])
    # the servo's angle from the exported geometry closes the calibrated leg: φ = (1 + k) θ + o
    pose = np.array([1.0, -2.0, 146.0, math.radians(2.0), math.radians(-1.0), math.radians(3.0)])
    R, t = kin.pose_to_rt(pose)
    theta = model.inverse_kinematics(R[None], t[None])[0]
    for n, leg in enumerate(exported["legs"]):
        phi = math.radians(leg["angle_per_commanded_degree"] * math.degrees(theta[n]) + leg["zero_trim_deg"])
        u, w = np.array(leg["zero_direction"]), np.cross(leg["crank_axis"], leg["zero_direction"])
        horn = np.array(leg["crank_centre"]) + leg["horn_length"] * (math.cos(phi) * u + math.sin(phi) * w)
        rod = t + R @ np.array(leg["platform_joint"]) - horn
        assert abs(np.linalg.norm(rod) - leg["rod_length"]) < 1e-9
    code, err = _run(
        capsys,
        "export",
        "--platform",
        servo["platform"],
        "--result",
        servo["result"],
        "--format",
        "linuxcnc",
        "--out",
        tmp_path / "k.hal",
    )
    assert code != 0 and err.count("\n") == 0 and "genhexkins models prismatic struts" in err
    assert not (tmp_path / "k.hal").exists()


def test_the_report_draws_the_servos_horns_and_rods_and_gives_angles_in_degrees(servo):
    page = servo["report"].read_text()
    assert "<h2>The robot</h2>" in page and "crank → horn → rod" in page
    table = page[page.index("<h2>Parameter errors") :]
    assert "<td>o1</td><td>deg</td>" in table and "<td>a1x</td><td>mm</td>" in table
    platform = load_platform(servo["platform"])
    from stewart_calib.pipelines.handover import calibrated_model

    legs = calibrated_model(platform, str(servo["result"])).legs
    robot = robot_at(platform, legs)
    crank, horn, joint = np.moveaxis(robot.calibrated, 1, 0)
    np.testing.assert_allclose(np.linalg.norm(horn - crank, axis=-1), legs.horn_lengths)
    np.testing.assert_allclose(np.linalg.norm(joint - horn, axis=-1), legs.rod_lengths)
    assert robot.kind == "rotary" and robot.parameter_degrees.sum() == 18


def test_the_recording_draws_the_calibrated_horns_and_rods_and_its_angles_in_degrees(servo):
    readback = pytest.importorskip("tests.readback")
    from stewart_calib.pipelines.handover import calibrated_model

    rows = readback.read_entity_rows(servo["rrd"])
    assert rows["/world/legs/drive"] == rows["/world/platform"] == 70
    strips = next(
        chunk.to_record_batch().column("LineStrips3D:strips").to_pylist()
        for chunk in readback._chunks(servo["rrd"])
        if chunk.entity_path == "/world/legs/drive" and not chunk.is_static
    )[0]
    legs = calibrated_model(load_platform(servo["platform"]), str(servo["result"])).legs
    crank, horn, joint = np.moveaxis(np.array(strips, dtype=float), 1, 0)
    np.testing.assert_allclose(np.linalg.norm(horn - crank, axis=-1), legs.horn_lengths, atol=1e-3)  # float32
    np.testing.assert_allclose(np.linalg.norm(joint - horn, axis=-1), legs.rod_lengths, atol=1e-3)
    result = json.loads(servo["result"].read_text())
    _, o1 = readback.read_scalars(servo["rrd"], "params/leg1/o/ekf")
    assert math.isclose(o1[-1], result["error"][result["parameter_names"].index("o1")], rel_tol=1e-6)


@pytest.mark.parametrize("command", ["calibrate", "track", "identifiability", "validate"])
def test_a_log_of_the_other_drive_kind_is_refused_in_one_line(servo, capsys, tmp_path, command):
    text = servo["log"].read_text()
    as_strokes = tmp_path / "strokes.csv"
    as_strokes.write_text(re.sub(r"q(\d)_deg", r"q\1_mm", text))
    prismatic = tmp_path / "prismatic.toml"
    prismatic.write_text((CONFIGS / "platforms" / "hobby-hexapod.toml").read_text())
    out = tmp_path / "x.json"
    extra = {
        "calibrate": ["--method", "ekf", "--out", out],
        "track": ["--method", "ekf", "--out", out],
        "identifiability": [],
        "validate": ["--result", servo["result"], "--out", tmp_path / "v.csv"],
    }[command]
    for platform, log, expects in ((servo["platform"], as_strokes, "q1_deg"), (prismatic, servo["log"], "q1_mm")):
        if command == "validate" and platform == prismatic:
            continue  # the servo's result is not the prismatic platform's
        code, err = _run(capsys, command, "--platform", platform, "--log", log, *extra)
        assert code != 0 and err.count("\n") == 0, err
        assert "are another drive's" in err and f"expects {expects}" in err
    assert not out.exists()


def _servo_raw_csv(log_path: Path, out: Path, unit: str) -> None:
    """The servo log as a hobbyist's own logger writes it: servo angles (``unit``), the rigid body's
    position in m and orientation as a quaternion, one row each."""
    log = read_log(log_path, load_platform(log_path.parent / "platform.toml"))
    angles = log.strokes if unit == "rad" else np.degrees(log.strokes)
    quaternion = Rotation.from_euler("ZYX", log.readings[:, [5, 4, 3]]).as_quat()  # x y z w
    with out.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["time_s", *(f"servo{i}" for i in range(1, 7)), "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"])
        for k in range(len(log)):
            writer.writerow(
                [
                    repr(float(log.t_s[k])),
                    *map(repr, angles[k].tolist()),
                    *map(repr, (log.readings[k, :3] / 1000).tolist()),
                    *map(repr, quaternion[k].tolist()),
                ]
            )


MAPPING = """[instrument]
time = "time_s"
position = ["x_m", "y_m", "z_m"]
position_unit = "m"
quaternion = ["qx", "qy", "qz", "qw"]
quaternion_order = "xyzw"

[strokes]
columns = ["servo1", "servo2", "servo3", "servo4", "servo5", "servo6"]
unit = "{unit}"
"""


@pytest.mark.parametrize("unit", ["deg", "rad"])
def test_import_writes_a_servos_angles_as_q_deg(servo, capsys, tmp_path, unit):
    raw, mapping, out = tmp_path / "raw.csv", tmp_path / "m.toml", tmp_path / "log.csv"
    _servo_raw_csv(servo["log"], raw, unit)
    mapping.write_text(MAPPING.format(unit=unit))
    code, err = _run(
        capsys, "import", "--csv", raw, "--mapping", mapping, "--platform", servo["platform"], "--out", out
    )
    assert code == 0, err
    platform = load_platform(servo["platform"])
    imported, original = read_log(out, platform), read_log(servo["log"], platform)
    with out.open() as f:
        assert next(csv.reader(f))[1:7] == [f"q{i}_deg" for i in range(1, 7)]
    np.testing.assert_allclose(imported.strokes, original.strokes, rtol=0, atol=1e-12)
    np.testing.assert_allclose(imported.readings, original.readings, rtol=0, atol=1e-9)


def test_import_of_strokes_in_mm_for_a_servo_platform_is_refused_in_one_line(servo, capsys, tmp_path):
    raw, mapping, out = tmp_path / "raw.csv", tmp_path / "m.toml", tmp_path / "log.csv"
    _servo_raw_csv(servo["log"], raw, "deg")
    mapping.write_text(MAPPING.format(unit="mm"))
    code, err = _run(
        capsys, "import", "--csv", raw, "--mapping", mapping, "--platform", servo["platform"], "--out", out
    )
    assert code != 0 and err.count("\n") == 0
    assert "strokes in mm" in err and "q1_deg" in err and not out.exists()


def test_import_bag_writes_revolute_joint_states_as_q_deg(tmp_path):
    from tests.test_import_bag import JOINTS, read_csv, write_bag

    bag = tmp_path / "run"
    write_bag(bag, "ros2-sqlite3")
    base = ["import-bag", str(bag), "--strokes", "/drive/joint_states", "--readings", "/tracker/joint_states"]
    base += ["--stroke-joints", ",".join(JOINTS)]
    assert cli.main([*base, "--stroke-unit", "rad", "--out", str(tmp_path / "rad.csv")]) == 0
    assert cli.main([*base, "--stroke-unit", "mm", "--out", str(tmp_path / "mm.csv")]) == 0
    header, rad = read_csv(tmp_path / "rad.csv")
    _, mm = read_csv(tmp_path / "mm.csv")
    assert header[1:7] == [f"q{i}_deg" for i in range(1, 7)]
    np.testing.assert_allclose(rad[:, 1:7], np.degrees(mm[:, 1:7]), rtol=1e-12)


def test_the_leg_polylines_of_a_prismatic_drive_are_its_legs():
    platform = load_platform("nim-stewart")
    R, t = kin.pose_to_rt(np.asarray(platform.workspace.home)[None])
    (lines,) = [leg_polylines(platform.drive, R, t)]
    np.testing.assert_allclose(
        np.linalg.norm(lines[:, 1] - lines[:, 0], axis=-1),
        kin.inverse_kinematics(platform.drive, R, t)[0] + platform.drive.initial_lengths,
    )


ANGLES = tuple(f"q{i}_deg" for i in range(1, 7))


def _edited_log(servo, tmp_path: Path, edit, names: tuple[str, ...] = ANGLES) -> Path:
    """The servo log with ``edit(values (N, len(names))) -> values`` applied to its columns ``names``
    (default q1_deg … q6_deg [deg])."""
    with servo["log"].open(newline="") as f:
        rows = list(csv.reader(f))
    columns = [rows[0].index(name) for name in names]
    angles = edit(np.array([[float(row[j]) for j in columns] for row in rows[1:]]))
    for row, values in zip(rows[1:], angles, strict=True):
        for j, value in zip(columns, values, strict=True):
            row[j] = repr(float(value))
    path = tmp_path / "edited.csv"
    with path.open("w", newline="") as f:
        csv.writer(f).writerows(rows)
    return path


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (np.radians, "the angles q1_deg…q6_deg look like radians, not deg"),
        (lambda q: q[:, [1, 0, 2, 3, 4, 5]], "angle columns q1_deg and q2_deg look swapped"),
        (lambda q: q * np.array([1, 1, -1, 1, 1, 1]), "leg 3's angle looks reversed (q3_deg counts the wrong way)"),
    ],
)
def test_the_diagnosis_names_a_servo_logs_mistake_in_its_own_columns_and_degrees(
    servo, capsys, tmp_path, edit, message
):
    log = _edited_log(servo, tmp_path, edit)
    code, err = _run(
        capsys,
        "calibrate",
        "--platform",
        servo["platform"],
        "--log",
        log,
        "--method",
        "ekf",
        "--out",
        tmp_path / "x.json",
    )
    assert code != 0 and err.count("\n") == 0 and message in err, err
    assert "mm" not in err.split(message)[1].replace("deg", "")  # its evidence in degrees


def test_a_servo_log_whose_angles_are_another_robots_is_named(servo, capsys, tmp_path):
    rng = np.random.default_rng(4)
    log = _edited_log(servo, tmp_path, lambda q: rng.permutation(q))  # the rows' angles shuffled
    argv = ["calibrate", "--platform", servo["platform"], "--log", log, "--method", "ekf", "--out", tmp_path / "x.json"]
    code, err = _run(capsys, *argv)
    assert code != 0 and err.count("\n") == 0
    assert "the angles q1_deg…q6_deg do not fit this platform's legs" in err and "expected angles [deg]" in err


def test_a_servo_log_at_rest_is_named_in_degrees_of_the_angle_range(servo, capsys, tmp_path):
    rng = np.random.default_rng(4)
    held = (*ANGLES, "mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg")
    log = _edited_log(servo, tmp_path, lambda v: v[:1] + rng.normal(0.0, 0.01, v.shape), held)
    argv = ["calibrate", "--platform", servo["platform"], "--log", log, "--method", "ekf", "--out", tmp_path / "x.json"]
    code, err = _run(capsys, *argv)
    assert code != 0 and err.count("\n") == 0
    assert "samples' angles span" in err and "deg (0.01 of the angle range)" in err, err


def test_a_sweep_of_a_rotary_platform_in_prismatic_cells_is_refused_in_one_line_before_any_task(capsys, tmp_path):
    """A sweep's cells take a platform of their own drive (``drive = "rotary"`` sweeps servo builds)."""
    spec = tmp_path / "drives.toml"
    spec.write_text(
        'name = "drives"\nmethods = ["ekf"]\nseeds = 1\n'
        '[grid]\nplatform = ["hobby-hexapod", "servo-hexapod"]\ninstrument = "pose"\n'
    )
    code, err = _run(capsys, "sweep", "--spec", spec, "--out", tmp_path / "out")
    assert code != 0 and err.count("\n") == 0
    assert (
        "key 'grid.platform'" in err and "'servo-hexapod' is a rotary platform; the cells of drive = 'prismatic'" in err
    )
    assert not (tmp_path / "out" / "results.parquet").exists()
