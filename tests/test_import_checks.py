"""``stewart-calib import`` on files users get wrong: each refused in one line naming the file, row,
column or key and what was expected (never a traceback, nothing written), and the clock offset
estimated from what a real controller and instrument log."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from stewart_calib import cli
from stewart_calib.io.platform_file import load_platform
from stewart_calib.model import kinematics as kin

from . import vendor_files as vendor
from .test_import import COUNTS_MAPPING, EXAMPLE, _motion, _strokes_of, _write_counts

STROKES_IN_ROWS = COUNTS_MAPPING.replace('time = "stamp_ms"\ntime_unit = "ms"\n', "")


def _run(capsys, *argv) -> tuple[int, str]:
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip()


def _refused(capsys, out: Path, *argv) -> str:
    code, err = _run(capsys, *argv, "--out", out)
    assert code == 2 and err.count("\n") == 0 and "Traceback" not in err, err
    assert not out.exists()
    return err


@pytest.fixture
def controller(tmp_path) -> list:
    (tmp_path / "c.toml").write_text(COUNTS_MAPPING)
    t_c = np.arange(0, 6, 0.01)
    _write_counts(tmp_path / "c.csv", t_c, _strokes_of(t_c))
    return ["--strokes", tmp_path / "c.csv", "--mapping", tmp_path / "c.toml"]


def test_vicon_markers_named_twice_or_a_rate_that_is_no_rate(capsys, tmp_path, controller):
    """One marker named twice raised pyarrow's KeyError; a rate of 0 was blamed on the time column."""
    _, _, position = _motion(50, 10.0)
    markers = {f"m{i}": position + 10.0 * i for i in range(4)}
    vendor.vicon_trajectories_csv(tmp_path / "t.csv", 10.0, markers)
    out = tmp_path / "log.csv"
    err = _refused(capsys, out, "import", "--vicon", tmp_path / "t.csv", "--markers", "m0,m1,m0", *controller)
    assert f"{tmp_path / 't.csv'}: --markers: 'm0' is named twice; expected each marker once" in err
    for rate in (0.0, -10.0):
        vendor.vicon_trajectories_csv(tmp_path / "r.csv", rate, markers)
        err = _refused(capsys, out, "import", "--vicon", tmp_path / "r.csv", "--markers", "m0", *controller)
        assert f"row 2: expected the capture rate [Hz], a positive number, got '{rate:g}'" in err
    err = _refused(capsys, out, "import", "--vicon", tmp_path / "t.csv", "--segment", "m0", *controller)
    assert "row 1: a Trajectories export, read with --markers (not --segment)" in err


def test_four_markers_against_a_platform_of_three_targets(capsys, tmp_path, controller):
    """A Vicon export of 4 markers checked against a platform with 3 targets: an IndexError in the
    diagnosis before; now the count is compared first."""
    _, _, position = _motion(50, 10.0)
    vendor.vicon_trajectories_csv(tmp_path / "t.csv", 10.0, {f"m{i}": position + 10.0 * i for i in range(4)})
    text = (Path("configs/platforms/hobby-hexapod.toml")).read_text()
    text = text.replace(
        'kind = "pose"\nframe = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\ntarget = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]',
        'kind = "points"\nframe = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\n'
        "targets_mm = [[10.0, 0.0, 5.0], [-10.0, 20.0, 5.0], [0.0, -20.0, 5.0]]",
    ).replace("orientation_sigma_deg = 0.05\n", "")
    (tmp_path / "p.toml").write_text(text)
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--vicon", tmp_path / "t.csv", "--markers", "m0,m1,m2,m3",
        *controller, "--platform", tmp_path / "p.toml",
    )  # fmt: skip
    assert "the import gives 4 targets (p1 … p4) where its [instrument] has 3 targets_mm" in err


def test_two_vicon_subjects_with_the_segment_are_named_not_chosen(capsys, tmp_path, controller):
    """Two subjects each with a segment 'platform': the first was read without a word."""
    _, rotation, position = _motion(30, 10.0)
    vendor.vicon_segments_csv(tmp_path / "s.csv", 10.0, np.degrees(rotation.as_rotvec()), position)
    text = (tmp_path / "s.csv").read_text().replace("hexapod:base", "rig:platform", 1)
    (tmp_path / "s.csv").write_text(text)
    err = _refused(capsys, tmp_path / "log.csv", "import", "--vicon", tmp_path / "s.csv", "--segment", "platform",
                   *controller)  # fmt: skip
    assert "row 3: 2 segments are named 'platform': 'rig:platform' (field 3), 'hexapod:platform' (field 9)" in err
    assert "name one as Subject:Name" in err
    code, err = _run(capsys, "import", "--vicon", tmp_path / "s.csv", "--segment", "hexapod:platform", *controller,
                     "--out", tmp_path / "log.csv")  # fmt: skip
    assert code == 0, err
    np.testing.assert_allclose(np.genfromtxt(tmp_path / "log.csv", delimiter=",", names=True)["mx_mm"], position[:, 0])


def test_two_motive_rigid_bodies_of_one_name_are_refused_naming_their_ids(capsys, tmp_path, controller):
    """Motive lets two rigid bodies share a name: the later one's columns were read silently."""
    t, rotation, position = _motion(50, 10.0)
    vendor.motive_csv(tmp_path / "m.csv", t, rotation.as_quat(), position * 1e-3, body="wand")
    err = _refused(capsys, tmp_path / "log.csv", "import", "--motive", tmp_path / "m.csv", "--rigid-body", "wand",
                   *controller)  # fmt: skip
    assert "row 4: two rigid bodies are named 'wand' (IDs 1, 2); rename one in Motive and export again" in err


def _generic(path: Path, header: list[str], rows: int = 50) -> None:
    t, rotation, position = _motion(rows, 10.0)
    q = rotation.as_quat()
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for k in range(rows):
            strokes = (_strokes_of(t[k : k + 1])[0] * 100).tolist()
            writer.writerow([t[k], *position[k], *(position[k] + 50), q[k, 3], *q[k, :3], *strokes])


POSE = (
    '[instrument]\ntime = "t"\nposition = {position}\nquaternion = ["qw", "qx", "qy", "qz"]\n'
    'quaternion_order = "wxyz"\n'
)


@pytest.mark.parametrize(
    "position, strokes_mapping, message",
    [
        ('["x", "x", "z"]', STROKES_IN_ROWS, "column 'x' is named twice; expected a different column for each"),
        (
            '["t", "y", "z"]',
            STROKES_IN_ROWS,
            "column 't' is named as 'instrument.time' and as 'instrument.position'; expected a different column",
        ),
        (
            '["x", "y", "z"]',
            STROKES_IN_ROWS.replace('"leg1"', '"qw"'),
            "column 'qw' is named as 'instrument.quaternion' and as 'strokes.columns'",
        ),
    ],
    ids=["position twice", "time as a position", "a quaternion as a stroke"],
)
def test_a_mapping_that_reads_one_column_twice(capsys, tmp_path, position, strokes_mapping, message):
    """pyarrow raised KeyError 'Field "c1" exists 2 times in schema' for each."""
    header = ["t", "x", "y", "z", "x2", "y2", "z2", "qw", "qx", "qy", "qz", *(f"leg{i}" for i in range(1, 7))]
    _generic(tmp_path / "g.csv", header)
    (tmp_path / "m.toml").write_text(POSE.format(position=position) + strokes_mapping)
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--csv", tmp_path / "g.csv", "--mapping", tmp_path / "m.toml"
    )
    assert f"{tmp_path / 'm.toml'}: {message}" in err


def test_a_csv_of_points_whose_header_repeats_a_name(capsys, tmp_path):
    """Two targets exported as x, y, z twice: which x is which cannot be told (a KeyError before)."""
    header = ["t", "x", "y", "z", "x", "y", "z", "qw", "qx", "qy", "qz", *(f"leg{i}" for i in range(1, 7))]
    _generic(tmp_path / "p.csv", header)
    (tmp_path / "m.toml").write_text(
        '[instrument]\ntime = "t"\npoints = [["x", "y", "z"], ["x", "y", "z"]]\n' + STROKES_IN_ROWS
    )
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--csv", tmp_path / "p.csv", "--mapping", tmp_path / "m.toml"
    )
    assert f"{tmp_path / 'p.csv'}: row 1: column 'x' ('instrument.points') appears 2 times in the header" in err
    assert "(fields 2, 5); expected one column of each name" in err


@pytest.mark.parametrize("offset", [["--clock-offset-s", "0"], ["--estimate-clock-offset"]])
def test_a_controller_log_with_a_header_only(capsys, tmp_path, offset):
    """An IndexError (given offset) or a ValueError from numpy (estimated) before."""
    t, rotation, position = _motion(50, 10.0)
    vendor.motive_csv(tmp_path / "m.csv", t, rotation.as_quat(), position * 1e-3)
    (tmp_path / "c.toml").write_text(COUNTS_MAPPING)
    (tmp_path / "c.csv").write_text("stamp_ms,leg1,leg2,leg3,leg4,leg5,leg6\n")
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--motive", tmp_path / "m.csv", "--rigid-body", "platform",
        "--strokes", tmp_path / "c.csv", "--mapping", tmp_path / "c.toml", *offset,
    )  # fmt: skip
    assert f"{tmp_path / 'c.csv'}: no data rows after the header" in err


# ----------------------------------------------------------------------------- the clock offset


def test_the_shipped_example_estimates_its_clock_offset(capsys, tmp_path):
    """The hobby example's 10 Hz controller holds each pose for 0.2 s after each 2 Hz camera frame:
    its speed point-sampled at the frames was all zero ("correlate at best 0.00"). Every offset in
    the hold joins the same strokes, so the log is the one the true offset (1234.5 s) writes."""
    logs = []
    for offset in (["--estimate-clock-offset"], ["--clock-offset-s", "1234.5"]):
        logs.append(tmp_path / f"log{len(logs)}.csv")
        code, err = _run(
            capsys, "import", "--motive", EXAMPLE / "fit_motive.csv", "--rigid-body", "platform", "--strokes",
            EXAMPLE / "fit_counts.csv", "--mapping", EXAMPLE / "controller.toml", *offset, "--out", logs[-1],
        )  # fmt: skip
        assert code == 0, err
        if len(logs) == 1:
            estimated = float(err.split("clock offset estimated ")[1].split(" s")[0])
            assert 1234.5 <= estimated <= 1234.7  # within the 0.2 s hold after the frame
    assert logs[0].read_bytes() == logs[1].read_bytes()


def _physical_case(path: Path, seed: int, offset_s: float) -> list:
    """A hexapod (hobby-hexapod) moving smoothly, ±20 mm and ±8°: motion capture at 100 Hz with
    10 µm noise, the controller's strokes (inverse kinematics of the same motion) at 250 Hz."""
    platform = load_platform("hobby-hexapod")
    rng = np.random.default_rng(seed)
    phases, freqs = rng.uniform(0, 2 * np.pi, 6), rng.uniform(0.05, 0.4, 6)

    def motion(t):
        wave = np.sin(2 * np.pi * freqs * t[:, None] + phases)
        return Rotation.from_euler("xyz", np.radians(8.0) * wave[:, 3:]), np.array([0, 0, 200.0]) + 20.0 * wave[:, :3]

    t = np.arange(0, 20.0, 0.01)
    rotation, position = motion(t)
    noisy = position + rng.normal(0, 0.01, position.shape)
    vendor.motive_csv(path / "m.csv", t, rotation.as_quat(), noisy * 1e-3)
    t_c = np.arange(offset_s - 1.0, offset_s + 21.0, 0.004)
    rotation_c, position_c = motion(t_c - offset_s)
    _write_counts(path / "c.csv", t_c, kin.inverse_kinematics(platform.drive, rotation_c.as_matrix(), position_c))
    (path / "c.toml").write_text(COUNTS_MAPPING)
    return ["import", "--motive", path / "m.csv", "--rigid-body", "platform", "--strokes", path / "c.csv",
            "--mapping", path / "c.toml", "--up", "z", "--estimate-clock-offset"]  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1])
def test_the_clock_offset_of_a_hexapod_s_strokes_is_found_within_a_camera_frame(capsys, tmp_path, seed):
    """The speeds of strokes and of positions are different functions of one motion (a rotation
    moves the legs, not the position): they matched at 1.686 s (seed 0) and 12.370 s (seed 1) for a
    true 12.345 s. The strokes regressed on the pose find it within one camera period (10 ms;
    measured 0.6 ms and 1.8 ms: the regression's curvature terms leave the rest)."""
    code, err = _run(capsys, *_physical_case(tmp_path, seed, 12.345), "--out", tmp_path / "log.csv")
    assert code == 0, err
    estimated = float(err.split("clock offset estimated ")[1].split(" s")[0])
    assert abs(estimated - 12.345) < 0.01


# ----------------------------------------------------------------------------- silently wrong before


@pytest.mark.parametrize("option", ["--csv", "--strokes"])
def test_a_pipe_is_refused_as_a_pipe_not_for_its_content(capsys, tmp_path, option):
    """``--csv <(cat F.csv)`` was refused as "no column 'time_s' in the file" (its header read
    already by the first pass); ``-`` as "file not found"."""
    import os

    read, write = os.pipe()
    os.close(write)
    fifo = f"/dev/fd/{read}"
    try:
        paths = {"--csv": EXAMPLE / "fit_raw.csv", "--strokes": EXAMPLE / "fit_counts.csv"}
        paths[option] = fifo
        argv = ["--motive", EXAMPLE / "fit_motive.csv", "--rigid-body", "platform", "--strokes", paths["--strokes"]]
        argv += ["--mapping", EXAMPLE / "controller.toml", "--clock-offset-s", "1234.5"]
        if option == "--csv":
            argv = ["--csv", paths["--csv"], "--mapping", EXAMPLE / "raw.toml"]
        err = _refused(capsys, tmp_path / "log.csv", "import", *argv)
        assert f"{fifo}: not a regular file (a pipe, a process substitution or a device: cannot seek)" in err
    finally:
        os.close(read)
    err = _refused(capsys, tmp_path / "log.csv", "import", "--csv", "-", "--mapping", EXAMPLE / "raw.toml")
    assert "--csv -: standard input cannot be read twice" in err


def test_with_the_platform_a_leg_that_counts_backwards_is_named(capsys, tmp_path):
    """``sign = -1`` on leg 3 (its strokes below zero): the wiring test mirrored a reversed leg only
    within the stroke range, so this log was written; calibrate then refused its first row."""
    mapping = (
        (EXAMPLE / "raw.toml")
        .read_text()
        .replace("counts_per_rev = 4096", "counts_per_rev = 4096\nsign = [1, 1, -1, 1, 1, 1]")
    )
    (tmp_path / "m.toml").write_text(mapping)
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--csv", EXAMPLE / "fit_raw.csv", "--mapping", tmp_path / "m.toml",
        "--platform", "hobby-hexapod",
    )  # fmt: skip
    assert "leg 3's stroke looks reversed (q3_mm counts the wrong way)" in err


def test_with_the_platform_a_quaternion_in_the_wrong_order_is_named(capsys, tmp_path):
    """The example's quaternions (w x y z, its frame 30° and its target 90° from nominal) declared
    x y z w: written before. Read so, every turn between two poses is the strokes' turn mirrored."""
    (tmp_path / "m.toml").write_text((EXAMPLE / "raw.toml").read_text().replace('"wxyz"', '"xyzw"'))
    err = _refused(
        capsys, tmp_path / "log.csv", "import", "--csv", EXAMPLE / "fit_raw.csv", "--mapping", tmp_path / "m.toml",
        "--platform", "hobby-hexapod",
    )  # fmt: skip
    assert "the measured orientations mroll_deg…myaw_deg turn as a mirror image of the strokes' poses" in err
    assert "a quaternion read in the wrong order (w x y z against x y z w)" in err


@pytest.mark.parametrize("declared, refused", [("xyzw", True), ("wxyz", False)])
def test_without_a_platform_a_quaternion_order_is_told_by_the_identity(capsys, tmp_path, declared, refused):
    """A pose log within 10° of the identity written w x y z and declared x y z w was accepted:
    read so, every row is a turn of about 180°."""
    header = ["t", "x", "y", "z", "x2", "y2", "z2", "qw", "qx", "qy", "qz", *(f"leg{i}" for i in range(1, 7))]
    _generic(tmp_path / "g.csv", header)
    (tmp_path / "m.toml").write_text(
        POSE.format(position='["x", "y", "z"]').replace("wxyz", declared) + STROKES_IN_ROWS
    )
    argv = ["import", "--csv", tmp_path / "g.csv", "--mapping", tmp_path / "m.toml"]
    if not refused:
        code, err = _run(capsys, *argv, "--out", tmp_path / "log.csv")
        assert code == 0, err
        return
    err = _refused(capsys, tmp_path / "log.csv", *argv)
    assert (
        f"{tmp_path / 'm.toml'}: 'instrument.quaternion_order' = 'xyzw': read so, the quaternions qw, qx, qy, qz" in err
    )
    assert "read as 'wxyz', within 1" in err and "expected quaternion_order = 'wxyz'" in err


def test_a_log_from_standard_input_is_read(tmp_path):
    """``calibrate --log -`` said "-: log file not found" where ``track`` reads ``-`` as standard
    input; a pipe on standard input now calibrates as the file does (read once, spooled)."""
    import subprocess
    import sys

    log = tmp_path / "fit.csv"
    assert cli.main(["import", "--csv", str(EXAMPLE / "fit_raw.csv"), "--mapping", str(EXAMPLE / "raw.toml"),
                     "--out", str(log)]) == 0  # fmt: skip
    config = Path(__file__).resolve().parents[1] / "configs" / "estimators" / "motion-capture.toml"
    results = []
    for source in ("-", str(log)):
        results.append(tmp_path / f"r{len(results)}.json")
        argv = ["calibrate", "--platform", "hobby-hexapod", "--log", source, "--method", "ls", "--config", str(config)]
        done = subprocess.run(
            [sys.executable, "-m", "stewart_calib.cli", *argv, "--out", str(results[-1])],
            input=log.read_bytes(), capture_output=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr.decode()
        assert "108 samples used, 0 skipped, of 108 rows" in done.stderr.decode()
    import json

    first, second = (json.loads(path.read_text()) for path in results)
    assert first["estimate"] == second["estimate"] and first["stddev"] == second["stddev"]


@pytest.mark.parametrize("export", ["motive", "csv"])
def test_an_export_with_its_header_only_is_named_not_the_controller(capsys, tmp_path, export):
    """A Motive export of its 7 header rows was reported as "no measurement falls between two
    controller rows … instrument nan–nan s", blaming the controller's log."""
    if export == "motive":
        lines = (EXAMPLE / "fit_motive.csv").read_text().splitlines(keepends=True)[:7]
        argv = ["--motive", tmp_path / "e.csv", "--rigid-body", "platform", "--strokes", EXAMPLE / "fit_counts.csv"]
        argv += ["--mapping", EXAMPLE / "controller.toml", "--clock-offset-s", "1234.5"]
    else:
        lines = (EXAMPLE / "fit_raw.csv").read_text().splitlines(keepends=True)[:1]
        argv = ["--csv", tmp_path / "e.csv", "--mapping", EXAMPLE / "raw.toml"]
    (tmp_path / "e.csv").write_text("".join(lines))
    err = _refused(capsys, tmp_path / "log.csv", "import", *argv)
    assert f"{tmp_path / 'e.csv'}: no data rows after the header; expected the instrument's measurements" in err


def test_a_motion_that_repeats_itself_is_aligned_on_the_whole_overlap(capsys, tmp_path):
    """The scale benchmark's Lissajous stream (10 Hz, 2000 samples, nim-stewart) exported as Motive
    with 10 µm of position noise and a count log at 100 counts/mm (10 µm), 12.345 s ahead: the speed
    matching said 107.354 s. The motion repeats itself, so an offset a period off fits as well over
    a shorter overlap; of equally good fits the longest overlap is taken. Within a hundredth of
    the 0.1 s sample period (measured 0.13 ms: what the fit's curvature terms leave of a motion
    this large, far above the noise's share, < 1 µs)."""
    from benchmarks.common import nim_stewart, synthetic_stream

    log, _ = synthetic_stream(nim_stewart(), 2000, np.random.default_rng(0), 10.0, smooth=True)
    poses, rng = log.desired_poses, np.random.default_rng(50)
    quaternion = Rotation.from_euler("ZYX", poses[:, [5, 4, 3]]).as_quat()
    vendor.motive_csv(tmp_path / "m.csv", log.t_s, quaternion, (poses[:, :3] + rng.normal(0, 0.01, (2000, 3))) / 1e3)
    rows = np.column_stack([(log.t_s + 12.345) * 1000.0, np.round(log.strokes * 100.0)])
    np.savetxt(tmp_path / "k.csv", rows, delimiter=",", header="t_ms,c1,c2,c3,c4,c5,c6", comments="", fmt="%.17g")
    (tmp_path / "k.toml").write_text(
        '[strokes]\ntime = "t_ms"\ntime_unit = "ms"\ncolumns = ["c1", "c2", "c3", "c4", "c5", "c6"]\n'
        'unit = "counts"\ncounts_per_mm = 100.0\nmax_gap_s = 0.2\n'
    )
    code, err = _run(
        capsys, "import", "--motive", tmp_path / "m.csv", "--rigid-body", "platform", "--strokes", tmp_path / "k.csv",
        "--mapping", tmp_path / "k.toml", "--up", "z", "--estimate-clock-offset", "--out", tmp_path / "log.csv",
    )  # fmt: skip
    assert code == 0, err
    estimated = float(err.split("clock offset estimated ")[1].split(" s")[0])
    assert abs(estimated - 12.345) < 0.01 * 0.1
