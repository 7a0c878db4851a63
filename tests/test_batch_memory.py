"""The batch methods on long logs: ``ls`` folds its Jacobian in chunk by chunk (memory of one
chunk, whatever the log's length), and a method that holds every sample (``lm``) says what it
will need before it starts and refuses a log that would not fit."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from stewart_calib import cli, memory
from stewart_calib.config import EstimatorConfig
from stewart_calib.estimators import ls
from stewart_calib.io import write_log
from stewart_calib.model import kinematics as kin
from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_error, random_poses, tracked_log


def _poses_and_strokes(n: int, seed: int):
    platform = nim_stewart()
    rng = np.random.default_rng(seed)
    log, _ = make_log(platform, random_error(rng), random_poses(platform, n, rng), rng, 0.002, 0.001)
    R_v, t_v = kin.pose_to_rt(log.desired_poses)
    return platform, log.strokes, R_v + 0.0, t_v + 0.0


def _noise(platform) -> ls.PoseNoise:
    return ls.PoseNoise(platform.tracker, 0.002, 0.001)  # the σ's of _poses_and_strokes' log


def test_ls_never_forms_the_stacked_jacobian_of_the_whole_log(monkeypatch):
    """The stacked ``6N × 42`` Jacobian alone is 6 MB at N = 3 000 (and its SVD as much again):
    the fit's peak stays below that one array (what is left is a chunk's work, ~0.5 MB in chunks
    of 256 samples, and the poses' 0.3 MB)."""
    n = 3_000
    monkeypatch.setattr(ls, "CHUNK_SAMPLES", 256)
    platform, strokes, R_v, t_v = _poses_and_strokes(n, 5)
    stacked_bytes = 6 * n * platform.drive.n_params * 8
    ls.gauss_newton(
        platform.drive, strokes[:50], R_v[:50], t_v[:50], EstimatorConfig().ls, _noise(platform)
    )  # compiled untraced
    tracemalloc.start()
    try:
        solution = ls.gauss_newton(platform.drive, strokes, R_v, t_v, EstimatorConfig().ls, _noise(platform))
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert solution.covariance is not None and peak < stacked_bytes, f"peak {peak / 1e6:.1f} MB"


def test_ls_in_chunks_is_the_fit_in_one(monkeypatch):
    """Chunks of 7 samples against one chunk of all: the QR update keeps the SVD's accuracy (agreement
    to 1e-6 σ, where the noise puts σ ~ 1e-3 mm and the solve's rounding ~1e-12 mm)."""
    platform, strokes, R_v, t_v = _poses_and_strokes(300, 6)
    config = EstimatorConfig().ls
    whole = ls.gauss_newton(platform.drive, strokes, R_v, t_v, config, _noise(platform))
    monkeypatch.setattr(ls, "CHUNK_SAMPLES", 7)
    chunked = ls.gauss_newton(platform.drive, strokes, R_v, t_v, config, _noise(platform))
    sigma = np.sqrt(np.diag(whole.covariance))
    assert np.all(np.abs(chunked.error - whole.error) <= 1e-6 * sigma)
    np.testing.assert_allclose(chunked.singular_values, whole.singular_values, rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.diag(chunked.covariance)), sigma, rtol=1e-9)
    assert chunked.residual_rms == pytest.approx(whole.residual_rms, rel=1e-9)


def test_lm_on_a_log_beyond_the_memory_available_is_refused_before_it_starts(tmp_path, capsys, monkeypatch):
    log = tmp_path / "log.csv"
    write_log(log, tracked_log(11, 40))
    rows = memory.estimated_rows(log)
    assert rows is not None and abs(rows - 40) <= 2  # rows of nearly one length
    need = memory.BASE_BYTES + rows * 15_000
    monkeypatch.setattr(memory, "available_bytes", lambda: need - 1)
    out = tmp_path / "r.json"
    capsys.readouterr()
    argv = ["calibrate", "--platform", str(NIM_STEWART), "--log", str(log), "--method", "lm", "--out", str(out)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"stewart-calib calibrate: error: --log {log}: lm holds every sample")
    assert "more than the" in err[0] and "(ekf, isam2)" in err[0] and not out.exists()


def test_a_large_need_is_said_before_the_run(tmp_path, monkeypatch):
    log = tmp_path / "log.csv"
    write_log(log, tracked_log(11, 40))
    rows = memory.estimated_rows(log)
    monkeypatch.setattr(memory, "available_bytes", lambda: 10**15)
    assert memory.check_memory("lm", None, log) is None  # streams: nothing to say
    assert memory.check_memory("lm", 1000, log) is None  # ~300 MB: not worth a line
    need_gb = (memory.BASE_BYTES + rows * 10**9) / 1e9
    assert memory.check_memory("lm", 10**9, log) == (
        f"lm holds every sample (~1 GB each): ~{need_gb:.3g} GB for the ~{rows} rows of {log} (1e+06 GB available)"
    )
