"""``stewart-calib calibrate`` (spec §6): exit status, one-line refusals, nothing partial written."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.errors import SampleRejected
from stewart_calib.estimate import Estimate
from stewart_calib.estimators.registry import METHODS, MethodSpec
from stewart_calib.io import read_result, write_log
from stewart_calib.model import kinematics as kin
from stewart_calib.pipelines import calibrate as calibrate_pipeline
from stewart_calib.samples import Log
from stewart_calib.workflows import calibration
from stewart_calib.workflows.calibration import run_calibration
from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_error, random_poses

STEP_MM = 0.001


class CountingEstimator:
    """Online test double: δM = (accepted samples) × STEP_MM; refuses samples with s1 < 0."""

    name = "counting"

    def __init__(self, platform, config):
        self.accepted = 0

    def update(self, sample):
        if sample.readings[0] < 0:
            raise SampleRejected(f"s1 = {sample.readings[0]} is negative", SampleRejected.OUT_OF_RANGE)
        self.accepted += 1

    def estimate(self) -> Estimate:
        return Estimate(np.full(42, self.accepted * STEP_MM), np.eye(42) * 0.01, self.name, self.accepted)

    def current_error(self) -> np.ndarray:
        return self.estimate().error


class BatchEstimator(CountingEstimator):
    """Batch test double: ``fit`` gives δM = mean stroke of leg 1 [mm] on every parameter."""

    name = "batch"

    def __init__(self, platform, config):
        super().__init__(platform, config)
        self.rejected = []

    def fit(self, samples) -> Estimate:
        samples = list(samples)
        return Estimate(np.full(42, np.mean([s.strokes[0] for s in samples])), None, self.name, len(samples))


@pytest.fixture
def fakes(monkeypatch):
    for cls, online in ((CountingEstimator, True), (BatchEstimator, False)):
        spec = MethodSpec(cls.name, f"{__name__}:{cls.__name__}", online, False, ("tracker",), "test double")
        monkeypatch.setitem(METHODS, cls.name, spec)
    # the doubles' samples are no robot's: the plausibility check (tests/test_plausibility.py) and the
    # diagnosis of a log's mistakes (tests/test_diagnosis.py) would refuse them
    monkeypatch.setattr(calibrate_pipeline, "check_plausible", lambda *args: None)
    monkeypatch.setattr(calibrate_pipeline, "diagnose_log", lambda *args: None)
    monkeypatch.setattr(calibration, "diagnose_log", lambda *args, **kwargs: None)
    monkeypatch.setattr(calibration.diagnosis, "check_moves", lambda *args: None)
    # nor can a drive fit measure a tracker's geometry on them (tests/test_tracker_geometry_estimate.py)
    monkeypatch.setattr(calibrate_pipeline, "applies", lambda platform, config: False)
    monkeypatch.setattr(
        calibrate_pipeline, "with_estimated_geometry", lambda platform, method, config, log: (config, None)
    )


def _log() -> Log:
    """Ten samples; s1 is negative in three of them (t_s = 2.5, 3.5, 4.5), which the counting double rejects."""
    s1 = np.array([1.0, 1.0, 1.0, 1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0])
    return Log(np.arange(10) * 0.5, np.tile(np.arange(10.0)[:, None], (1, 6)), np.tile(s1[:, None], (1, 6)))


@pytest.fixture
def log_path(tmp_path):
    path = tmp_path / "log.csv"
    write_log(path, _log())
    return path


def _run(capsys, *argv) -> tuple[int, list[str]]:
    code = cli.main(["calibrate", *map(str, argv)])
    return code, capsys.readouterr().err.splitlines()


def _args(log_path, out, method="counting", platform=NIM_STEWART):
    return ["--platform", platform, "--log", log_path, "--method", method, "--out", out]


def test_online_method_writes_result_and_trace(tmp_path, log_path, capsys, fakes):
    out, trace = tmp_path / "r.json", tmp_path / "t.csv"
    code, err = _run(capsys, *_args(log_path, out), "--trace", trace)
    assert code == 0
    result = read_result(out)
    assert result["method"] == "counting" and result["platform"] == "nim-stewart"
    assert (result["samples_used"], result["samples_skipped"]) == (7, 3)
    np.testing.assert_allclose(result["error"], 7 * STEP_MM, rtol=1e-12)
    np.testing.assert_allclose(result["stddev"], 0.1, rtol=1e-12)
    rows = np.loadtxt(trace, delimiter=",", skiprows=1)
    assert rows.shape == (10, 43)
    np.testing.assert_array_equal(rows[:, 0], _log().t_s)
    accepted_so_far = np.array([1, 2, 3, 4, 5, 5, 6, 6, 7, 7])  # a rejected sample leaves the estimate as it was
    np.testing.assert_allclose(
        rows[:, 1:] - nim_stewart().drive.as_vector(), np.tile(accepted_so_far[:, None] * STEP_MM, (1, 42)), atol=1e-9
    )
    assert err[0].startswith(
        "stewart-calib calibrate: counting rejected samples: 3 of 10 (first: t_s=2.5: s1 = -1.0 is negative)"
    )
    assert err[-2].endswith("(counting: 7 samples used, 3 skipped, of 10 rows)")
    assert err[-1].startswith("stewart-calib calibrate: verdict: ")  # the line it ends with


def test_batch_method_fits_whole_log_and_traces_a_constant(tmp_path, log_path, capsys, fakes):
    out, trace = tmp_path / "r.json", tmp_path / "t.csv"
    assert _run(capsys, *_args(log_path, out, "batch"), "--trace", trace)[0] == 0
    result = read_result(out)
    assert result["stddev"] is None and result["samples_used"] == 10
    np.testing.assert_array_equal(result["error"], [4.5] * 42)  # mean of strokes 0..9
    rows = np.loadtxt(trace, delimiter=",", skiprows=1)
    assert rows.shape == (10, 43)
    np.testing.assert_array_equal(rows[:, 1:], np.tile(result["estimate"], (10, 1)))


def test_skip_bad_rows_counts_in_samples_skipped(tmp_path, log_path, capsys, fakes):
    lines = log_path.read_text().splitlines()
    fields = lines[2].split(",")
    lines[2] = ",".join([fields[0], "nan", *fields[2:]])  # second sample: q1 = nan
    log_path.write_text("\n".join(lines) + "\n")
    code, err = _run(capsys, *_args(log_path, tmp_path / "r.json"))
    assert code == 2 and len(err) == 1 and "row 3" in err[0] and "'q1_mm'" in err[0]
    code, err = _run(capsys, *_args(log_path, tmp_path / "r.json"), "--skip-bad-rows")
    assert code == 0
    assert (
        err[0]
        == "stewart-calib calibrate: skipped bad log rows: 1 of 10 (first: row 3: column 'q1_mm': expected a finite "
        "number, got nan)"
    )
    assert read_result(tmp_path / "r.json")["samples_skipped"] == 1 + 3


def test_run_calibration_returns_estimate_trace_and_rejections(fakes):
    run = run_calibration(nim_stewart(), _log(), "counting", trace=True)
    assert (run.estimate.samples_used, len(run.rejected), run.trace.shape) == (7, 3, (10, 42))
    batch = run_calibration(nim_stewart(), _log(), "batch")
    assert (batch.trace, batch.rejected) == (None, [])


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"--platform": "missing.toml"}, "missing.toml: platform file not found"),
        ({"--log": "missing.csv"}, "missing.csv: log file not found"),
        (
            {"--method": "nope"},
            "--method: unknown method 'nope'; expected one of ls, paper-ekf, ekf, isam2, lm, counting, batch",
        ),
        ({"--out": "no/such/dir/r.json"}, "--out no/such/dir/r.json: directory no/such/dir does not exist"),
        ({"--set": "noise.bogus=1"}, "--set: unknown key 'noise.bogus'"),
    ],
)
def test_refusals_are_one_line_exit_2_and_write_nothing(
    tmp_path, log_path, capsys, fakes, monkeypatch, change, expected
):
    monkeypatch.chdir(tmp_path)
    args = dict(
        zip(["--platform", "--log", "--method", "--out"], [NIM_STEWART, log_path, "counting", "r.json"], strict=True)
    )
    code, err = _run(capsys, *[x for k, v in {**args, **change}.items() for x in (k, v)], "--trace", "t.csv")
    assert code == 2
    assert err == [f"stewart-calib calibrate: error: {err[0].split('error: ', 1)[1]}"] and expected in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv"]


def test_all_samples_rejected_is_refused(tmp_path, capsys, fakes):
    log = _log()
    log.readings[:] = -1.0
    write_log(tmp_path / "log.csv", log)
    code, err = _run(capsys, *_args(tmp_path / "log.csv", tmp_path / "r.json"))
    assert (code, len(err)) == (2, 1)
    assert err[0].endswith("counting rejected all 10 samples (first: s1 = -1.0 is negative)")
    assert not (tmp_path / "r.json").exists()


def test_subprocess_bad_log_exits_2_with_one_line(tmp_path):
    bad = tmp_path / "log.csv"
    bad.write_text("t_s,q1_mm\n0,1\n")
    proc = subprocess.run(
        [sys.executable, "-m", "stewart_calib", "calibrate", *map(str, _args(bad, tmp_path / "r.json", "ls"))],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.splitlines() == [
        f"stewart-calib calibrate: error: {bad}: row 1: missing required column(s) "
        "q2_mm, q3_mm, q4_mm, q5_mm, q6_mm, s1_mm, s2_mm, s3_mm, s4_mm, s5_mm, s6_mm"
    ]
    assert not (tmp_path / "r.json").exists()


def test_real_ls_recovers_synthetic_errors_end_to_end(tmp_path, capsys):
    pytest.importorskip("stewart_calib.estimators.ls")
    platform = nim_stewart()
    rng = np.random.default_rng(11)
    true_error = random_error(rng, 0.5)
    log, _ = make_log(platform, true_error, random_poses(platform, 60, rng), rng)  # noise-free
    write_log(tmp_path / "log.csv", log)
    code, err = _run(capsys, *_args(tmp_path / "log.csv", tmp_path / "r.json", "ls"))
    assert code == 0, err
    result = read_result(tmp_path / "r.json")
    assert (result["method"], result["samples_used"], result["samples_skipped"]) == ("ls", 60, 0)
    # exact data: what is left is the log's repr rounding and Gauss–Newton's tolerance
    np.testing.assert_allclose(result["error"], true_error, atol=1e-4)


def test_rerun_recording_holds_the_parameter_errors(tmp_path, log_path, capsys, fakes):
    readback = pytest.importorskip("tests.readback")
    code, _ = _run(capsys, *_args(log_path, tmp_path / "r.json"), "--rerun", tmp_path / "r.rrd")
    assert code == 0
    samples, values = readback.read_scalars(tmp_path / "r.rrd", "params/leg6/l/counting")
    np.testing.assert_array_equal(samples, np.arange(10))
    np.testing.assert_allclose(values.ravel(), np.array([1, 2, 3, 4, 5, 5, 6, 6, 7, 7]) * STEP_MM, atol=1e-9)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["log.csv", "r.json", "r.rrd"]  # no temporary left


def test_result_carries_conditioning_and_rich_poses_raise_no_warning(tmp_path, capsys):
    platform, rng = nim_stewart(), np.random.default_rng(11)
    log, _ = make_log(platform, random_error(rng), random_poses(platform, 40, rng), rng)
    write_log(tmp_path / "log.csv", log)
    code, err = _run(capsys, *_args(tmp_path / "log.csv", tmp_path / "r.json", method="ls"))
    assert code == 0
    conditioning = read_result(tmp_path / "r.json")["conditioning"]
    assert conditioning["rank"] == 42 and conditioning["verdict"] == "identifiable"
    assert 100 < conditioning["condition_number"] < 1e3  # docs/measured-facts.md: ~400 at N = 20, ~250 at N = 200
    assert not any("warning" in line for line in err)


def test_translation_only_log_warns_in_one_line_naming_the_unidentified_directions(tmp_path, capsys):
    # Without rotations, moving d_i and j_i together along an axis changes no leg length:
    # 18 directions (3 per leg) that no estimator can identify.
    platform, rng = nim_stewart(), np.random.default_rng(12)
    poses = random_poses(platform, 40, rng)
    poses[:, 3:] = 0.0
    log, _ = make_log(platform, random_error(rng), poses, rng)
    write_log(tmp_path / "log.csv", log)
    code, err = _run(capsys, *_args(tmp_path / "log.csv", tmp_path / "r.json", method="ekf"))
    assert code == 0
    warnings = [line for line in err if "warning" in line]
    assert len(warnings) == 1 and "18 unidentified directions" in warnings[0] and "j1x" in warnings[0]
    conditioning = read_result(tmp_path / "r.json")["conditioning"]
    assert conditioning["rank"] == 24 and conditioning["null_space_dimension"] == 18
    assert conditioning["verdict"] == "rank-deficient"


@pytest.mark.parametrize("method", ["ls", "ekf"])
def test_samples_a_method_cannot_use_are_counted_and_reported_for_batch_and_online(tmp_path, capsys, method):
    # Readings in range that no pose fits (tracker FK fails): the log reader accepts them, the
    # estimator refuses them — and batch methods must report that just as online ones do.
    platform, rng = nim_stewart(), np.random.default_rng(13)
    log, _ = make_log(platform, random_error(rng, 0.5), random_poses(platform, 40, rng), rng)
    log.readings[[5, 17, 30]] = [318.0, -276.0, 318.0, -276.0, 318.0, -276.0]
    write_log(tmp_path / "log.csv", log)
    code, err = _run(capsys, *_args(tmp_path / "log.csv", tmp_path / "r.json", method=method))
    assert code == 0, err
    result = read_result(tmp_path / "r.json")
    assert (result["samples_used"], result["samples_skipped"]) == (37, 3)
    assert any(f"{method} rejected samples: 3 of 40" in line for line in err)


def test_the_rerun_residuals_of_any_leg_model_are_the_compiled_ones():
    from dataclasses import replace

    from stewart_calib.pipelines.calibrate import _residuals_per_sample
    from tests.synthetic import nim_stewart, numpy_legs, random_error, random_poses

    platform = nim_stewart()
    R, t = kin.pose_to_rt(random_poses(platform, 8, np.random.default_rng(9)))
    params = platform.drive.as_vector() + np.array([random_error(np.random.default_rng(k), 0.3) for k in range(8)])
    strokes = np.random.default_rng(10).normal(0.0, 20.0, (8, 6))
    compiled = _residuals_per_sample(platform, params, R, t, strokes)
    generic = _residuals_per_sample(replace(platform, drive=numpy_legs(platform.drive)), params, R, t, strokes)
    np.testing.assert_allclose(generic, compiled, rtol=0, atol=1e-9)
