"""OnlineCalibrator: rejected samples leave the state alone, checkpoints resume, bad checkpoints are refused."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from stewart_calib.analysis.compensation import compensate
from stewart_calib.config import config_from_dict
from stewart_calib.errors import CalibError, SampleRejected, number
from stewart_calib.samples import Sample
from stewart_calib.workflows.online import CHECKPOINT_VERSION, ONLINE_METHODS, OnlineCalibrator, Rejections, npz_bytes
from tests.faults import INDETERMINANT, degenerate_sample
from tests.synthetic import make_log, nim_stewart, random_error, random_poses

METHODS = ONLINE_METHODS  # every online method of the registry
#: isam2 is rebuilt from a Gaussian prior on the window variable plus a replay (its export_state),
#: so it agrees with the uninterrupted run to the linearisation error its relinearisation
#: threshold (1e-2 mm) leaves, δ²/L ≈ 1e-7 mm; measured 2.2e-7 mm. The EKFs are bit-exact.
RESUME_TOLERANCE_MM = {"paper-ekf": 1e-12, "ekf": 1e-12, "isam2": 1e-6}


@pytest.fixture(scope="module")
def platform():
    return nim_stewart()


@pytest.fixture(scope="module")
def config():
    return config_from_dict({"isam2": {"window_samples": 5, "lag_s": 1.0}})


@pytest.fixture(scope="module")
def log(platform):
    rng = np.random.default_rng(3)
    error = random_error(rng, 1.0)
    log, _ = make_log(
        platform, error, random_poses(platform, 150, rng), rng, reading_sigma_mm=0.002, stroke_sigma_mm=0.001
    )
    return log


def _feed(calib, samples):
    for sample in samples:
        calib.update(sample)
    return calib


def _assert_states_equal(a: dict, b: dict):
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], dict):
            _assert_states_equal(a[key], b[key])
        else:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)


@pytest.mark.parametrize("method", METHODS)
def test_resume_from_checkpoint_matches_an_uninterrupted_run(platform, config, log, method, tmp_path):
    full = _feed(OnlineCalibrator(platform, method, config), log).estimate()
    for cut in (3, 97):  # before the first window closes, and deep into the run (isam2 trimmed its buffer)
        first = _feed(OnlineCalibrator(platform, method, config), log.select(slice(0, cut)))
        first.save(tmp_path / "c.npz")
        resumed = OnlineCalibrator.load(tmp_path / "c.npz", None)
        if method != "isam2":  # the EKF state is restored bit for bit
            _assert_states_equal(first.export_state(), resumed.export_state())
        estimate = _feed(resumed, log.select(slice(cut, len(log)))).estimate()
        assert estimate.samples_used == full.samples_used == len(log)
        assert np.max(np.abs(estimate.error - full.error)) <= RESUME_TOLERANCE_MM[method]
        # covariance in mm²: the isam2 bound squared against the ~1e-4 mm stddev scale
        assert np.max(np.abs(estimate.covariance - full.covariance)) <= RESUME_TOLERANCE_MM[method] * 1e-2


def test_a_gtsam_failure_rejects_the_sample_and_the_smoother_is_rebuilt_without_it(
    platform, config, log, monkeypatch, tmp_path
):
    bad = 97  # deep into the run: the replay buffer starts at a snapshot, so the rebuild is not a replay from the start
    degenerate_sample(monkeypatch, float(log.t_s[bad]))
    never = _feed(OnlineCalibrator(platform, "isam2", config), log.select(np.arange(len(log)) != bad)).estimate()
    calib = _feed(OnlineCalibrator(platform, "isam2", config), log.select(slice(0, bad)))
    calib.save(tmp_path / "c.npz")
    with pytest.raises(
        SampleRejected,
        match=rf"^sample at t = {number(log.t_s[bad])} s: gtsam failed in the iSAM2 update \({INDETERMINANT} .*\)$",
    ):
        calib.update(log[bad])
    assert calib.rejections.by_reason == {"solver failed": 1}
    # The failed update rebuilt the smoother from the state a checkpoint holds, as a resume does: bit for bit.
    resumed = OnlineCalibrator.load(tmp_path / "c.npz", None)
    _assert_states_equal(calib.export_state(), resumed.export_state())
    np.testing.assert_array_equal(calib.estimate().error, resumed.estimate().error)
    np.testing.assert_array_equal(calib.estimate().covariance, resumed.estimate().covariance)
    # So it goes on as a resumed run does, and ends where a run that never saw the sample ends
    # to the resume tolerance (the snapshot linearises the older samples once, see above).
    estimate = _feed(calib, log.select(slice(bad + 1, len(log)))).estimate()
    assert estimate.samples_used == never.samples_used == len(log) - 1
    assert np.max(np.abs(estimate.error - never.error)) <= RESUME_TOLERANCE_MM["isam2"]
    assert np.max(np.abs(estimate.covariance - never.covariance)) <= RESUME_TOLERANCE_MM["isam2"] * 1e-2


def test_an_isam2_checkpoint_of_the_graph_in_the_configured_noise_resumes_as_one_of_now(platform, config, tmp_path):
    """A checkpoint written while isam2's graph kept the configured noise ``R0`` holds its snapshot's
    covariance as ``covariance``: the marginal of then, over the front end's ``s²``. It resumes as the
    checkpoint of the same state written now (``covariance_mm2``). Readings at 0.3× the told noise
    (``s²`` ≈ 0.08), so that the units show: a checkpoint written by the code of before and taken in
    mm² ended 2.1σ from the uninterrupted run, its σ 13–38 % wide (0.48σ and 0.99–1.05, the two codes'
    own difference, once converted)."""
    rng = np.random.default_rng(5)
    error = random_error(rng, 1.0)
    log, _ = make_log(platform, error, random_poses(platform, 150, rng), rng, 0.002 * 0.3, 0.001 * 0.3)
    cut = 97  # deep into the run: the replay buffer starts at a snapshot
    _feed(OnlineCalibrator(platform, "isam2", config), log.select(slice(0, cut))).save(tmp_path / "now.npz")
    with np.load(tmp_path / "now.npz") as npz:
        arrays = {name: npz[name] for name in npz.files}
    noise_scale2 = float(arrays["state/front/robust/noise"][0])
    assert noise_scale2 < 0.2
    arrays["state/snapshot/covariance"] = arrays.pop("state/snapshot/covariance_mm2") / noise_scale2
    _rewrite(tmp_path / "before.npz", arrays)
    now, before = (
        _feed(OnlineCalibrator.load(tmp_path / name, None), log.select(slice(cut, len(log)))).estimate()
        for name in ("now.npz", "before.npz")
    )
    assert np.max(np.abs(before.error - now.error)) <= 1e-9
    assert np.max(np.abs(before.covariance - now.covariance)) <= 1e-9 * np.max(np.abs(now.covariance))


def test_a_checkpoint_without_the_walk_of_the_scales_memory_takes_the_walk_in_use(platform, config, log, tmp_path):
    """The noise scale's remembered sums carry the walk their windows were measured at (``scale_walk``,
    which decides whether a moved walk drops them); a checkpoint of before holds none and resumes with
    them as measured at the walk in use."""
    _feed(OnlineCalibrator(platform, "ekf", config), log.select(slice(0, 97))).save(tmp_path / "c.npz")
    with np.load(tmp_path / "c.npz") as npz:
        arrays = {name: npz[name] for name in npz.files if name != "state/robust/scale_walk"}
    _rewrite(tmp_path / "c.npz", arrays)
    robust = OnlineCalibrator.load(tmp_path / "c.npz", None).export_state()["robust"]
    assert robust["scale_sums"][1] > 0.0
    assert robust["scale_walk"] == robust["scale_sums"][1] * np.log(robust["noise"][1])


def _unusable(platform, t_s):
    readings_at_home = np.zeros(6)
    return {
        "NaN stroke": Sample(t_s, np.r_[np.nan, np.zeros(5)], readings_at_home),
        "reading out of range": Sample(t_s, np.zeros(6), np.r_[platform.reading_range[1] + 1.0, np.zeros(5)]),
        # in range, but no pose has these tracker lengths
        "FK fails": Sample(t_s, np.zeros(6), np.array([318.0, -276.0, 318.0, -276.0, 318.0, -276.0])),
        "time goes back": Sample(t_s - 10.0, np.zeros(6), readings_at_home),
    }


@pytest.mark.parametrize("method", METHODS)
def test_an_unusable_sample_is_rejected_and_leaves_the_state_untouched(platform, config, log, method):
    calib = _feed(OnlineCalibrator(platform, method, config), log.select(slice(0, 12)))
    before, estimate = calib.export_state(), calib.estimate()
    cases = _unusable(platform, float(log.t_s[11]) + 0.1)
    if method == "paper-ekf":
        del cases["time goes back"]  # the paper's filter has a constant Q per update: time does not enter
    for name, sample in cases.items():
        with pytest.raises(SampleRejected):
            calib.update(sample)
        _assert_states_equal(before, calib.export_state())
        np.testing.assert_array_equal(calib.estimate().error, estimate.error, err_msg=name)
    assert calib.rejections.count == len(cases)
    assert set(calib.rejections.by_reason) <= {"non-finite value", "out of range", "FK failed", "time went back"}
    _feed(calib, log.select(slice(12, 14)))  # and it goes on
    assert calib.estimate().samples_used == 14


def test_rejections_are_summarised_by_reason():
    rejections = Rejections.of(
        [
            SampleRejected("ekf: sample at t = 1 s gated: NIS 9e4 > χ² bound 27.9", SampleRejected.GATED),
            SampleRejected("tracker forward kinematics did not converge", SampleRejected.FK_FAILED),
            SampleRejected("ekf: sample at t = 2 s gated: NIS 1e5 > χ² bound 27.9", SampleRejected.GATED),
            SampleRejected("sample at t = 3 s is older than the last one (4 s)", SampleRejected.TIME_BACK),
        ]
    )
    assert rejections.summary() == {
        "count": 4,
        "by_reason": {"FK failed": 1, "gated outlier": 2, "time went back": 1},
        "first": "ekf: sample at t = 1 s gated: NIS 9e4 > χ² bound 27.9",
    }


def test_result_and_compensation(platform, config, log):
    calib = _feed(OnlineCalibrator(platform, "ekf", config), log.select(slice(0, 20)))
    with pytest.raises(SampleRejected):
        calib.update(_unusable(platform, 99.0)["NaN stroke"])
    result = calib.result()
    assert (result["samples_used"], result["samples_skipped"], result["samples_rejected"]["count"]) == (20, 1, 1)
    poses = log.desired_poses[:3]
    np.testing.assert_array_equal(calib.compensated_strokes_rad(poses), compensate(calib.estimate(), poses, platform))
    # the same poses in the files' degrees
    in_degrees = np.column_stack([poses[:, :3], np.degrees(poses[:, 3:])])
    np.testing.assert_allclose(calib.compensated_strokes(in_degrees), calib.compensated_strokes_rad(poses), atol=1e-9)
    assert np.abs(in_degrees[:, 3:] - poses[:, 3:]).max() > 1.0  # the test tells degrees from radians


def _saved(platform, config, log, tmp_path):
    path = tmp_path / "c.npz"
    _feed(OnlineCalibrator(platform, "ekf", config), log.select(slice(0, 5))).save(path)
    with np.load(path) as npz:
        return path, {name: npz[name] for name in npz.files}


def _rewrite(path, arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p, a: p.unlink(), "checkpoint not found"),
        (lambda p, a: p.write_bytes(p.read_bytes()[:200]), "not a readable checkpoint"),
        (lambda p, a: p.write_bytes(b"\x80\x04garbage" * 10), "not a readable checkpoint (not an .npz archive"),
        (
            lambda p, a: p.write_bytes(np.random.default_rng(0).bytes(4096)),
            "not a readable checkpoint (not an .npz archive",
        ),
        (
            lambda p, a: np.save(p.open("wb"), np.array([{"x": 1}], dtype=object), allow_pickle=True),
            "not a readable checkpoint",
        ),
        (lambda p, a: _rewrite(p, {**a, "version": np.array(CHECKPOINT_VERSION + 1)}), "version"),
        (lambda p, a: _rewrite(p, {**a, "format": np.array("stewart-calib/result@1")}), "not a checkpoint"),
        (lambda p, a: _rewrite(p, {**a, "method": np.array("ls")}), "unknown online method"),
        (lambda p, a: _rewrite(p, {k: v for k, v in a.items() if k != "state/robust/filter/P"}), "'P' missing"),
        (lambda p, a: _rewrite(p, {**a, "state/robust/filter/x": np.zeros(41)}), "key 'x': expected shape (42,)"),
        (lambda p, a: _rewrite(p, {**a, "state/robust/filter/x": np.full(42, np.nan)}), "not finite"),
        (lambda p, a: _rewrite(p, {**a, "platform_toml": np.array("name = 3")}), "key 'name'"),
        (lambda p, a: _rewrite(p, {**a, "config_json": np.array("{")}), "JSONDecodeError"),
        (lambda p, a: _rewrite(p, {**a, "rows_read": np.array(-1)}), "rows_read"),
    ],
)
def test_bad_checkpoints_are_refused_in_one_line(platform, config, log, tmp_path, damage, message):
    path, arrays = _saved(platform, config, log, tmp_path)
    damage(path, arrays)
    with pytest.raises(CalibError) as err:
        OnlineCalibrator.load(path, None)
    assert message in str(err.value) and "\n" not in str(err.value)
    assert str(path) in str(err.value) and "allow_pickle" not in str(err.value)  # never advise loading unsafely


def test_checkpoint_is_a_zip_of_plain_arrays_and_holds_no_pickle(platform, config, log, tmp_path):
    path, arrays = _saved(platform, config, log, tmp_path)
    assert zipfile.is_zipfile(path)
    assert all(a.dtype.kind in "fiuU" for a in arrays.values())  # nothing that needs allow_pickle


def test_checkpoint_archive_is_what_np_load_and_zipfile_read(tmp_path):
    rng = np.random.default_rng(5)
    arrays = {
        "format": np.array("stewart-calib/checkpoint"),
        "version": np.array(1),
        "state/a/P": rng.random((42, 42)),
        "flags": np.array([True, False]),
        "none": np.zeros((0, 6)),
        "ints": np.arange(-3, 3),
    }
    path = tmp_path / "c.npz"
    path.write_bytes(npz_bytes(arrays))
    with zipfile.ZipFile(path) as archive:
        assert archive.testzip() is None  # every member's CRC-32 checks
        assert archive.namelist() == [f"{name}.npy" for name in arrays]
    with np.load(path, allow_pickle=False) as npz:
        for name, array in arrays.items():
            assert npz[name].dtype == array.dtype and npz[name].shape == array.shape
            np.testing.assert_array_equal(npz[name], array)
