"""``stewart-calib import-bag``: real bags written with rosbags' own writers (ROS 2 sqlite3 and
MCAP, ROS 1), read back into a measurement log; bad bags refused in one line."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from stewart_calib.cli import main
from stewart_calib.pipelines.import_bag import TopicSeries, interpolate_to_stamps
from tests.ros_messages import JOINT_STATE, POSE_STAMPED, T0_S, bag_writer, joint_state, pose_stamped, stamp_ns

STROKE_HZ, MEASUREMENT_HZ = 100.0, 30.0
DURATION_S = 2.0
AMPLITUDE_M, OMEGA_RAD_S = 0.05, 2 * np.pi * 0.7
JOINTS = [f"leg{i}" for i in range(1, 7)]


def strokes_m(t_s: np.ndarray) -> np.ndarray:
    """Smooth test strokes [m]: a sine per leg with its own phase."""
    return AMPLITUDE_M * np.sin(OMEGA_RAD_S * t_s[:, None] + np.arange(6) * 0.9)


def interpolation_bound_mm() -> float:
    """Linear interpolation error of a sine over one stroke period h: ≤ h²/8 · max|f''| (+ float noise)."""
    h = 1.0 / STROKE_HZ
    return h * h / 8 * AMPLITUDE_M * OMEGA_RAD_S**2 * 1000.0 + 1e-9


def stamps(hz: float, offset_s: float = 0.0) -> np.ndarray:
    return np.arange(0.0, DURATION_S, 1.0 / hz) + offset_s


def poses(t_s: np.ndarray) -> np.ndarray:
    """``(N, 6)`` [m, rad]: a pose moving in all six axes."""
    s = np.sin(t_s)[:, None]
    return np.array([0.01, -0.02, 0.7, 0.05, -0.1, 0.3]) * (1.0 + s)


def write_bag(
    path: Path,
    kind: str,
    measurement: str = "readings",
    extra_topic: tuple[str, str] | None = None,
    without_a_joint: tuple[set[int], set[int]] = (set(), set()),
) -> None:
    """A bag with ``/drive/joint_states`` (strokes, joints in a shuffled order) and the measurement
    (``/tracker/joint_states`` readings or ``/mocap/pose``), in ``kind`` = ros2-sqlite3 | ros2-mcap | ros1.
    ``without_a_joint``: the indices of the stroke and of the reading messages that lack one joint
    (and carry a seventh, unrelated one)."""
    writer, typestore, serialize = bag_writer(path, kind)
    with writer:
        drive = writer.add_connection("/drive/joint_states", JOINT_STATE, typestore=typestore)
        topic, msgtype = (
            ("/tracker/joint_states", JOINT_STATE) if measurement == "readings" else ("/mocap/pose", POSE_STAMPED)
        )
        meas = writer.add_connection(topic, msgtype, typestore=typestore)
        messages = []
        order = [3, 0, 5, 1, 4, 2]  # drivers need not publish the joints in leg order
        for k, (t, q) in enumerate(zip(stamps(STROKE_HZ), strokes_m(stamps(STROKE_HZ)), strict=True)):
            names = [JOINTS[i] for i in order]
            if k in without_a_joint[0]:
                names[2] = "gripper"
            messages.append((t, drive, joint_state(typestore, t, names, q[order])))
        t_meas = stamps(MEASUREMENT_HZ, offset_s=0.0037)
        for k, (t, value) in enumerate(
            zip(t_meas, strokes_m(t_meas) * 2.0 if measurement == "readings" else poses(t_meas), strict=True)
        ):
            names = [("spare" if i == 1 and k in without_a_joint[1] else name) for i, name in enumerate(JOINTS)]
            msg = (
                joint_state(typestore, t, names, value)
                if measurement == "readings"
                else pose_stamped(typestore, t, value)
            )
            messages.append((t, meas, msg))
        if extra_topic is not None:
            conn = writer.add_connection(extra_topic[0], extra_topic[1], typestore=typestore)
            messages.append((0.5, conn, typestore.types[extra_topic[1]](data="hello")))
        for t, connection, msg in sorted(messages, key=lambda m: m[0]):
            writer.write(connection, stamp_ns(t), serialize(msg, connection.msgtype))


def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], np.array(rows[1:], dtype=float)


@pytest.mark.parametrize("kind", ["ros2-sqlite3", "ros2-mcap", "ros1"])
def test_strokes_are_interpolated_to_the_reading_stamps(tmp_path, kind):
    bag = tmp_path / ("run.bag" if kind == "ros1" else "run")
    write_bag(bag, kind)
    out = tmp_path / "log.csv"
    code = main(
        [
            "import-bag",
            str(bag),
            "--strokes",
            "/drive/joint_states",
            "--readings",
            "/tracker/joint_states",
            "--stroke-joints",
            ",".join(JOINTS),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    header, rows = read_csv(out)
    assert header == ["t_s", *(f"q{i}_mm" for i in range(1, 7)), *(f"s{i}_mm" for i in range(1, 7))]
    t_meas = stamps(MEASUREMENT_HZ, offset_s=0.0037)
    # the last reading comes after the last stroke message: no stroke on its right, no row
    inside = t_meas <= stamps(STROKE_HZ)[-1]
    assert len(rows) == inside.sum()
    np.testing.assert_allclose(rows[:, 0], t_meas[inside] - t_meas[0], atol=1e-6)  # ns stamps → s
    np.testing.assert_allclose(rows[:, 7:], 2000.0 * strokes_m(t_meas[inside]), atol=1e-9)  # m → mm
    err = np.abs(rows[:, 1:7] - 1000.0 * strokes_m(t_meas[inside]))
    assert err.max() <= interpolation_bound_mm()
    assert err.max() > 0  # the strokes really were interpolated, not copied from a neighbour


@pytest.mark.parametrize("kind", ["ros2-sqlite3", "ros1"])
def test_pose_topic_writes_the_measured_pose_columns(tmp_path, kind):
    bag = tmp_path / ("run.bag" if kind == "ros1" else "run")
    write_bag(bag, kind, measurement="pose")
    out = tmp_path / "log.csv"
    assert (
        main(
            [
                "import-bag",
                str(bag),
                "--strokes",
                "/drive/joint_states",
                "--pose",
                "/mocap/pose",
                "--stroke-joints",
                ",".join(JOINTS),
                "--stroke-unit",
                "m",
                "--pose-unit",
                "m",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    header, rows = read_csv(out)
    assert header[7:] == ["mx_mm", "my_mm", "mz_mm", "mroll_deg", "mpitch_deg", "myaw_deg"]
    t_meas = stamps(MEASUREMENT_HZ, offset_s=0.0037)
    expected = poses(t_meas[t_meas <= stamps(STROKE_HZ)[-1]])
    np.testing.assert_allclose(rows[:, 7:10], 1000.0 * expected[:, :3], atol=1e-9)
    np.testing.assert_allclose(rows[:, 10:], np.degrees(expected[:, 3:]), atol=1e-9)


def test_units_by_flag(tmp_path):
    bag = tmp_path / "run"
    write_bag(bag, "ros2-sqlite3")
    out_m, out_mm = tmp_path / "m.csv", tmp_path / "mm.csv"
    base = [
        "import-bag",
        str(bag),
        "--strokes",
        "/drive/joint_states",
        "--readings",
        "/tracker/joint_states",
        "--stroke-joints",
        ",".join(JOINTS),
    ]
    assert main([*base, "--out", str(out_m)]) == 0
    assert main([*base, "--stroke-unit", "mm", "--reading-unit", "um", "--out", str(out_mm)]) == 0
    _, m = read_csv(out_m)
    _, mm = read_csv(out_mm)
    np.testing.assert_allclose(mm[:, 1:7] * 1000.0, m[:, 1:7], rtol=1e-12)
    np.testing.assert_allclose(mm[:, 7:] * 1e6, m[:, 7:], rtol=1e-12)


def test_interpolation_respects_the_maximum_gap():
    source = TopicSeries(np.array([0.0, 1.0, 1.1, 3.0]), np.arange(4.0)[:, None] * np.ones((1, 6)))
    values, kept = interpolate_to_stamps(source, np.array([-0.5, 0.5, 1.05, 1.1, 2.0, 3.5]), max_gap_s=1.0)
    # -0.5 and 3.5: outside; 2.0: its neighbours are 1.9 s apart; 1.1: an exact stamp needs no gap
    np.testing.assert_array_equal(kept, [False, True, True, True, False, False])
    np.testing.assert_allclose(values[:, 0], [0.5, 1.5, 2.0])


def _refusal(capsys, argv) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    return err


def test_missing_topic_lists_the_bags_topics(tmp_path, capsys):
    bag = tmp_path / "run"
    write_bag(bag, "ros2-mcap")
    out = tmp_path / "log.csv"
    err = _refusal(
        capsys,
        [
            "import-bag",
            str(bag),
            "--strokes",
            "/joint_states",
            "--readings",
            "/tracker/joint_states",
            "--out",
            str(out),
        ],
    )
    assert "/joint_states: no such topic" in err
    assert "/drive/joint_states (sensor_msgs/msg/JointState)" in err and "/tracker/joint_states" in err
    assert not out.exists()


def test_wrong_message_type_is_named(tmp_path, capsys):
    bag = tmp_path / "run.bag"
    write_bag(bag, "ros1", extra_topic=("/status", "std_msgs/msg/String"))
    err = _refusal(
        capsys,
        [
            "import-bag",
            str(bag),
            "--strokes",
            "/drive/joint_states",
            "--pose",
            "/status",
            "--out",
            str(tmp_path / "log.csv"),
        ],
    )
    assert "--pose /status: the topic carries std_msgs/msg/String; expected geometry_msgs/msg/PoseStamped" in err


def test_joint_names_in_no_message_are_refused(tmp_path, capsys):
    bag = tmp_path / "run"
    write_bag(bag, "ros2-sqlite3")
    out = tmp_path / "log.csv"
    err = _refusal(
        capsys,
        [
            "import-bag",
            str(bag),
            "--strokes",
            "/drive/joint_states",
            "--readings",
            "/tracker/joint_states",
            "--stroke-joints",
            "a,b,c,d,e,f",
            "--out",
            str(out),
        ],
    )
    assert "message 1: joint(s) a, b, c, d, e, f not in the message; it has leg4, leg1" in err
    assert f"(every one of its {len(stamps(STROKE_HZ))} messages refused)" in err  # not a row's fault: the topic's
    assert not out.exists()


def test_a_file_that_is_not_a_bag(tmp_path, capsys):
    not_a_bag = tmp_path / "log.bag"
    not_a_bag.write_text("t_s,q1_mm\n")
    err = _refusal(
        capsys,
        ["import-bag", str(not_a_bag), "--strokes", "/a", "--readings", "/b", "--out", str(tmp_path / "log.csv")],
    )
    assert "cannot read as a ROS bag" in err


def test_a_message_without_one_of_the_joints_refuses_only_its_row(tmp_path, capsys):
    """The legs are matched by name in every message; one that lacks a leg's joint gives no row
    (a reading) or no stroke sample (the strokes are interpolated across it), and is counted."""
    bag = tmp_path / "run"
    refused_strokes, refused_readings = {10, 11}, {5}
    write_bag(bag, "ros2-sqlite3", without_a_joint=(refused_strokes, refused_readings))
    out = tmp_path / "log.csv"
    argv = ["import-bag", str(bag), "--strokes", "/drive/joint_states", "--readings", "/tracker/joint_states"]
    # the readings' legs named by their first message, the strokes' (in another order) by the option
    assert main([*argv, "--stroke-joints", ",".join(JOINTS), "--out", str(out)]) == 0
    err = capsys.readouterr().err
    t_meas = stamps(MEASUREMENT_HZ, offset_s=0.0037)
    inside = t_meas <= stamps(STROKE_HZ)[-1]
    kept = inside & ~np.isin(np.arange(len(t_meas)), list(refused_readings))
    assert f"wrote {out} ({kept.sum()} rows" in err and f"of {len(t_meas)} --readings message(s)" in err
    assert f"{(~inside).sum()} without stroke messages" in err
    assert "1 --readings /tracker/joint_states message(s) refused (first: message 6: joint(s) leg2 not in" in err
    assert "2 --strokes /drive/joint_states message(s) refused (first: message 11: joint(s) leg6 not in" in err
    _, rows = read_csv(out)
    assert len(rows) == kept.sum()
    np.testing.assert_allclose(rows[:, 0], t_meas[kept] - t_meas[0], atol=1e-6)
    np.testing.assert_allclose(rows[:, 7:], 2000.0 * strokes_m(t_meas[kept]), atol=1e-9)
    # across the two refused stroke messages the interpolation spans 30 ms: h²/8 · max|f''| with h 3×
    err_mm = np.abs(rows[:, 1:7] - 1000.0 * strokes_m(t_meas[kept]))
    assert err_mm.max() <= 9 * interpolation_bound_mm()


def test_the_shipped_sample_bag_is_the_simulators_quick_run(tmp_path):
    """examples/ros-bag/run.bag imports to the log ``simulate --experiment quick`` writes, and its
    platform.toml is that simulation's: strokes and readings to float rounding of metres, stamps to
    float seconds since the epoch. Where the simulator changed, ``python examples/ros-bag/make_bag.py``
    writes both again."""
    shipped = Path(__file__).resolve().parents[1] / "examples" / "ros-bag"
    assert main(["simulate", "--experiment", "quick", "--out", str(tmp_path / "sim")]) == 0
    out = tmp_path / "bag-log.csv"
    argv = ["import-bag", str(shipped / "run.bag"), "--strokes", "/drive/joint_states"]
    assert main([*argv, "--readings", "/tracker/joint_states", "--out", str(out)]) == 0
    header, imported = read_csv(out)
    simulated_header, simulated = read_csv_columns(tmp_path / "sim" / "log.csv", header)
    assert header == simulated_header
    # import-bag takes stamps as float seconds since the epoch: steps of 2.4e-7 s at T0_S
    np.testing.assert_allclose(imported[:, 0], simulated[:, 0], rtol=0, atol=np.spacing(float(T0_S)))
    # mm → m → mm: a float64 round trip through the division and the product, ~1e-13 mm at 300 mm
    np.testing.assert_allclose(imported[:, 1:], simulated[:, 1:], rtol=1e-14, atol=1e-12)
    assert (shipped / "platform.toml").read_text() == (tmp_path / "sim" / "platform.toml").read_text(), (
        "examples/ros-bag/platform.toml is not the simulation's: python examples/ros-bag/make_bag.py"
    )


def read_csv_columns(path: Path, names: list[str]) -> tuple[list[str], np.ndarray]:
    """The columns ``names`` of a CSV whose other columns may hold text (the log's ``stage``)."""
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    columns = [rows[0].index(name) for name in names]
    return names, np.array([[float(row[k]) for k in columns] for row in rows[1:]])


def test_load_kg_is_written_in_every_row_and_a_bad_one_refused(tmp_path, capsys):
    """A bag of a session at 20 kg: ``--load-kg 20`` gives every row ``load_kg`` 20 (spec §10); −1 kg is refused."""
    bag = tmp_path / "run"
    write_bag(bag, "ros2-sqlite3")
    out = tmp_path / "log.csv"
    base = ["import-bag", str(bag), "--strokes", "/drive/joint_states", "--readings", "/tracker/joint_states"]
    assert main([*base, "--load-kg", "20", "--out", str(out)]) == 0
    assert "payload 20 kg in every row" in capsys.readouterr().err
    header, rows = read_csv(out)
    assert header[-1] == "load_kg" and header[7:13] == [f"s{i}_mm" for i in range(1, 7)]
    np.testing.assert_array_equal(rows[:, -1], np.full(len(rows), 20.0))
    err = _refusal(capsys, [*base, "--load-kg", "-1", "--out", str(tmp_path / "bad.csv")])
    assert "--load-kg: expected a finite payload ≥ 0 kg" in err and not (tmp_path / "bad.csv").exists()
