"""The rerun recording: written with every building block, read back from the .rrd file."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
from rerun.chunk import RrdReader

from stewart_calib import kinematics as kin
from stewart_calib.platform import N_PARAMS_PER_LEG, PARAMETER_FIELDS
from stewart_calib.viz import geometry, recording
from stewart_calib.viz.recording import (
    SAMPLE_TIMELINE,
    TIME_TIMELINE,
    TRUTH,
    circle_angles_rad,
    log_parameters,
    log_platform_geometry,
    log_platform_pose,
    log_pose_errors,
    log_trajectory,
    open_recording,
    parameter_path,
    send_blueprint,
)
from tests.instrument_data import hobby
from tests.readback import read_blueprint_names, read_entity_rows, read_scalars, read_static
from tests.synthetic import nim_stewart, numpy_legs, random_error, random_poses

METHODS = ("ls", "isam2")
STAGES = ("no-load", "20kg")
N_SAMPLES = 40
N_CIRCLE = 90
DT_S = 0.1
POLAR_BASE_RADIUS_MM = 2.0
POLAR_GAIN = 5.0
CIRCLE_RADIUS_MM = 100.0


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """One recording with all building blocks; returns the path and everything that was logged."""
    rng = np.random.default_rng(5)
    platform = nim_stewart()
    poses = random_poses(platform, N_SAMPLES, rng, fraction=0.5)
    R, t = kin.pose_to_rt(poses)
    R_desired, t_desired = kin.pose_to_rt(poses + rng.normal(0.0, 0.01, poses.shape))
    true_drive = platform.drive.perturbed(random_error(rng))
    times_s = np.arange(N_SAMPLES) * DT_S
    truth = random_error(rng)
    params = {method: truth + rng.normal(0.0, 0.1, (N_SAMPLES, 42)) for method in METHODS}
    errors = {method: (rng.random(N_SAMPLES), rng.random(N_SAMPLES) * 0.01) for method in METHODS}
    # Half a step off ±180°, so no point sits on the branch cut of the angle read back.
    angles_rad = np.linspace(-np.pi, np.pi, N_CIRCLE, endpoint=False) + np.pi / N_CIRCLE
    centre_mm = np.array([10.0, -20.0, 1125.8])
    unit_circle = np.c_[np.cos(angles_rad), np.sin(angles_rad), np.zeros(N_CIRCLE)]
    desired_xyz = centre_mm + CIRCLE_RADIUS_MM * unit_circle
    actual_xyz = {
        (stage, method): desired_xyz + rng.normal(0.0, 0.05, desired_xyz.shape)
        for stage in STAGES
        for method in METHODS
    }

    path = tmp_path_factory.mktemp("viz") / "run.rrd"
    with open_recording(path) as rec:
        log_platform_geometry(rec, platform)
        log_platform_pose(rec, platform, R, t, times_s, drive_legs=true_drive, desired=(R_desired, t_desired))
        log_parameters(rec, TRUTH, truth, times_s[0], samples=[0])
        for method in METHODS:
            log_parameters(rec, method, params[method], times_s)
            log_pose_errors(rec, method, times_s, *errors[method])
            for stage in STAGES:
                log_trajectory(
                    rec, stage, method, desired_xyz, actual_xyz[stage, method], POLAR_BASE_RADIUS_MM, POLAR_GAIN
                )
        send_blueprint(rec, platform.drive.n_legs, METHODS, STAGES)
    return dict(
        path=path,
        platform=platform,
        R=R,
        t=t,
        true_drive=true_drive,
        times_s=times_s,
        truth=truth,
        params=params,
        errors=errors,
        angles_rad=angles_rad,
        desired_xyz=desired_xyz,
        actual_xyz=actual_xyz,
    )


def _series_paths() -> list[str]:
    paths = ["/world/platform", "/world/platform_desired", "/world/legs/drive", "/world/legs/tracker"]
    for method in METHODS:
        paths += [f"/errors/position_mm/{method}", f"/errors/orientation_deg/{method}"]
        paths += ["/" + parameter_path(leg, field, method) for leg in range(1, 7) for field in PARAMETER_FIELDS]
    return paths


def test_every_series_has_one_row_per_sample(written):
    rows = read_entity_rows(written["path"])
    assert rows["/params/leg3/d_y/isam2"] == N_SAMPLES
    for path in _series_paths():
        assert rows.get(path) == N_SAMPLES, path
    assert rows["/params/leg6/l/truth"] == 1


def test_static_entities_present(written):
    static = read_entity_rows(written["path"], static=True)
    expected = [
        "/conventions",
        "/world",
        "/world/base/outline",
        "/world/base/drive_joints",
        "/world/base/tracker_joints",
        "/world/platform/outline",
        "/world/platform/drive_joints",
        "/world/platform/tracker_joints",
        "/world/platform_desired/outline",
    ]
    for stage in STAGES:
        expected.append(f"/polar/{stage}/reference")
        for method in METHODS:
            expected += [f"/trajectories/{stage}/{method}/desired", f"/trajectories/{stage}/{method}/actual"]
            expected += [f"/polar/{stage}/{method}", f"/polar/{stage}/{method}/raw"]
    for path in expected:
        assert path in static, path
    # Series styling is logged once per entity, not once per call or per row.
    assert static["/params/leg3/d_y/isam2"] == 1


def test_series_carry_both_timelines(written):
    series = [chunk for chunk in RrdReader(written["path"]).stream().to_chunks() if not chunk.is_static]
    assert series
    for chunk in series:
        assert set(chunk.timeline_names) == {SAMPLE_TIMELINE, TIME_TIMELINE}, chunk.entity_path


def test_scalars_read_back_as_logged(written):
    leg, k = 3, PARAMETER_FIELDS.index("d_y")
    samples, values = read_scalars(written["path"], "params/leg3/d_y/isam2")
    np.testing.assert_array_equal(samples, np.arange(N_SAMPLES))
    np.testing.assert_array_equal(values, written["params"]["isam2"][:, (leg - 1) * N_PARAMS_PER_LEG + k])

    times, values = read_scalars(written["path"], "errors/orientation_deg/ls", timeline=TIME_TIMELINE)
    np.testing.assert_allclose(times.astype("timedelta64[ns]").astype(np.int64) * 1e-9, written["times_s"], atol=1e-9)
    np.testing.assert_array_equal(values, written["errors"]["ls"][1])

    _, truth = read_scalars(written["path"], "params/leg6/l/truth")
    assert truth[0] == written["truth"][41]


def _series_row(path: Path, entity_path: str, column: str, sample: int):
    chunks = RrdReader(path).stream().to_chunks()
    (chunk,) = [c for c in chunks if c.entity_path == entity_path and not c.is_static]
    batch = chunk.to_record_batch()
    row = int(np.flatnonzero(batch.column(SAMPLE_TIMELINE).to_numpy() == sample)[0])
    return batch.column(column)[row].as_py()


def test_platform_transform_is_the_pose(written):
    k = 11
    # rerun stores a 3×3 matrix column-major, as float32.
    column_major = _series_row(written["path"], "/world/platform", "Transform3D:mat3x3", k)
    mat3x3 = np.array(column_major).reshape(3, 3, order="F")
    (translation,) = _series_row(written["path"], "/world/platform", "Transform3D:translation", k)
    np.testing.assert_allclose(mat3x3, written["R"][k], atol=1e-6)
    np.testing.assert_allclose(translation, written["t"][k], atol=1e-3)


def test_leg_strips_join_the_joints_at_the_pose(written):
    k = 7
    strips = np.array(_series_row(written["path"], "/world/legs/drive", "LineStrips3D:strips", k))
    legs = written["true_drive"]  # drawn with the drive it was given, not the nominal one
    expected_platform_joints = kin.transform_points(written["R"][k], written["t"][k], legs.platform_joints)
    # Positions are stored as float32: ~1e-4 mm at 1 m.
    np.testing.assert_allclose(strips[:, 0], legs.base_joints, atol=1e-3)
    np.testing.assert_allclose(strips[:, 1], expected_platform_joints, atol=1e-3)
    assert not np.allclose(legs.base_joints, written["platform"].drive.base_joints, atol=1e-2)


def test_a_rotary_leg_is_drawn_crank_horn_rod():
    from tests.test_rotary_legs import LEGS, reachable_poses

    R, t, _ = reachable_poses(LEGS, 4, 11)
    strips = geometry.leg_polylines(LEGS, R, t).reshape(4, 6, 3, 3)
    crank, horn, joint = strips[..., 0, :], strips[..., 1, :], strips[..., 2, :]
    np.testing.assert_allclose(crank, np.broadcast_to(LEGS.crank_centres, crank.shape))
    np.testing.assert_allclose(np.linalg.norm(horn - crank, axis=-1), np.broadcast_to(LEGS.horn_lengths, (4, 6)))
    np.testing.assert_allclose(np.linalg.norm(joint - horn, axis=-1), np.broadcast_to(LEGS.rod_lengths, (4, 6)))
    np.testing.assert_allclose(joint, kin.transform_points(R, t, LEGS.platform_joints), atol=1e-9)


def test_any_prismatic_leg_model_is_drawn_straight():
    platform = nim_stewart()
    R, t = kin.pose_to_rt(random_poses(platform, 5, np.random.default_rng(8)))
    np.testing.assert_array_equal(  # as the compiled leg set
        geometry.leg_polylines(numpy_legs(platform.drive), R, t), geometry.leg_polylines(platform.drive, R, t)
    )


def test_polar_plot_encodes_the_deviation(written):
    stage, method = "20kg", "ls"
    deviation_mm = np.linalg.norm(written["actual_xyz"][stage, method] - written["desired_xyz"], axis=1)
    raw = read_static(written["path"], f"polar/{stage}/{method}/raw")
    np.testing.assert_allclose(raw["deviation_mm"], deviation_mm, rtol=1e-12)
    np.testing.assert_allclose(raw["angle_deg"], np.degrees(written["angles_rad"]), atol=1e-9)

    (strip,) = read_static(written["path"], f"polar/{stage}/{method}")["LineStrips2D:strips"]
    strip = np.array(strip)
    assert len(strip) == N_CIRCLE + 1  # closed
    radius = np.hypot(strip[:-1, 0], strip[:-1, 1])
    order = np.argsort(written["angles_rad"])
    np.testing.assert_allclose(radius, POLAR_BASE_RADIUS_MM + POLAR_GAIN * deviation_mm[order], rtol=1e-5)


def test_circle_angles_in_a_tilted_plane():
    angles_rad = np.linspace(-3.0, 3.0, 50)
    tilt = kin.rpy_to_rotation(np.array([np.radians(30.0), 0.0, 0.0]))  # about x: x stays in the plane
    circle = np.c_[np.cos(angles_rad), np.sin(angles_rad), np.zeros_like(angles_rad)] * 80.0
    points = circle @ tilt.T + np.array([5.0, 5.0, 1000.0])
    np.testing.assert_allclose(circle_angles_rad(points), angles_rad, atol=1e-9)


def test_blueprint_lays_out_the_tabs(written):
    names = read_blueprint_names(written["path"])
    for name in ["scene", "pose errors", "trajectories", "parameters ls", "parameters isam2", "leg 6 [mm]", "20kg"]:
        assert name in names, name


def test_names_and_shapes_are_checked(tmp_path):
    with open_recording(tmp_path / "bad.rrd") as rec:
        with pytest.raises(ValueError, match="method"):
            log_pose_errors(rec, "bad name", [0.0], [1.0], [1.0])
        with pytest.raises(ValueError, match="params_mm"):
            log_parameters(rec, "ekf", np.zeros((3, 42)), [0.0, 0.1])
        with pytest.raises(ValueError, match="samples"):
            log_parameters(rec, "ekf", np.zeros((2, 42)), [0.0, 0.1], samples=[0])


def test_a_platform_without_a_tracker_draws_the_drive_alone(tmp_path):
    """calibrate --rerun on a platform measured by another instrument (no [tracker], like the
    hobby hexapod's) drew tracker legs from None: an AttributeError and no recording."""
    platform = hobby()
    assert platform.tracker is None
    R, t = kin.pose_to_rt(np.tile(platform.workspace.home, (3, 1)))
    path = tmp_path / "no-tracker.rrd"
    with open_recording(path) as rec:
        log_platform_geometry(rec, platform)
        log_platform_pose(rec, platform, R, t, np.arange(3) * DT_S, desired=(R, t))
    static, rows = read_entity_rows(path, static=True), read_entity_rows(path)
    assert "/world/base/drive_joints" in static and "/world/platform_desired/outline" in static
    assert not [p for p in (*static, *rows) if "tracker" in p]
    assert rows["/world/legs/drive"] == 3


def test_batches_append_and_the_global_stream_is_untouched(tmp_path):
    before = rr.get_global_data_recording()
    path = tmp_path / "batches.rrd"
    with open_recording(path) as rec:
        for start in (0, 10):
            samples = np.arange(start, start + 10)
            log_parameters(rec, "ekf", np.full((10, 42), float(start)), samples * DT_S, samples=samples)
    assert rr.get_global_data_recording() is before
    samples, values = read_scalars(path, "params/leg1/j_x/ekf")
    np.testing.assert_array_equal(samples, np.arange(20))
    np.testing.assert_array_equal(values, np.repeat([0.0, 10.0], 10))
    assert read_entity_rows(path, static=True)["/params/leg1/j_x/ekf"] == 1


def test_columnar_logging_sends_each_series_once(tmp_path, monkeypatch):
    # One send per series whatever the row count: one log call per row would take minutes on
    # long logs (speed itself is measured in benchmarks/, not asserted here).
    n = 5000
    rng = np.random.default_rng(0)
    params = {method: rng.normal(size=(n, 42)) for method in ("ls", "paper_ekf", "ekf", "isam2")}
    times_s = np.arange(n) * 0.001
    sends = []
    send = recording._send_scalars
    monkeypatch.setattr(
        recording, "_send_scalars", lambda rec, path, *rest: (sends.append(path), send(rec, path, *rest))
    )
    with open_recording(tmp_path / "fast.rrd") as rec:
        for method, values in params.items():
            log_parameters(rec, method, values, times_s)
    assert len(sends) == len(set(sends)) == 42 * len(params)
    assert read_entity_rows(tmp_path / "fast.rrd")["/params/leg6/l/isam2"] == n


def test_rerun_cli_verifies_the_file(written):
    cli = Path(sys.executable).with_name("rerun")
    cli = str(cli) if cli.exists() else shutil.which("rerun")
    if cli is None:
        pytest.skip("rerun CLI not installed")
    result = subprocess.run([cli, "rrd", "verify", str(written["path"])], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def test_parameter_fields_are_read_off_the_leg_models_names():
    platform = nim_stewart()
    assert recording.parameter_fields(platform.drive.parameter_names, 6) == PARAMETER_FIELDS
    assert recording.parameter_fields(("a1x", "d1z", "h1", "tu1", "tw1", "a2x", "d2z", "h2", "tu2", "tw2"), 2) == (
        "a_x",
        "d_z",
        "h",
        "tu",
        "tw",
    )
