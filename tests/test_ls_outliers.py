"""The paper's LS takes gross errors in (it has no gate) and says so: the samples no noise explains
are named by time in a warning and in the result's ``"outliers"``, not taken in without a word."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import write_log
from stewart_calib.io.platform_file import platform_to_toml
from tests.synthetic import make_log, nim_stewart, random_error, random_poses

N = 300
GLITCH_RATE = 0.05


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    """``N`` samples of nim-stewart (σ_s 2 µm, σ_q 1 µm), clean and with 5 % of the samples' one
    reading off by 0.5–5 mm (250–2500 σ)."""
    platform = nim_stewart()
    rng = np.random.default_rng(4)
    log, _ = make_log(platform, random_error(rng), random_poses(platform, N, rng), rng, 0.002, 0.001)
    directory = tmp_path_factory.mktemp("glitches")
    (directory / "p.toml").write_text(platform_to_toml(platform))
    write_log(directory / "clean.csv", log)
    glitched = np.flatnonzero(rng.random(N) < GLITCH_RATE)
    readings = log.readings.copy()
    sizes = rng.uniform(0.5, 5.0, len(glitched)) * rng.choice([-1.0, 1.0], len(glitched))
    readings[glitched, rng.integers(0, 6, len(glitched))] += sizes
    write_log(directory / "glitched.csv", log.__class__(log.t_s, log.strokes, readings))
    return directory, set(np.round(log.t_s[glitched], 9))


def _ls(directory, name, capsys, *settings):
    out = directory / f"{name}.json"
    argv = ["calibrate", "--platform", str(directory / "p.toml"), "--log", str(directory / f"{name}.csv")]
    assert cli.main([*argv, "--method", "ls", "--out", str(out), *settings]) == 0
    return json.loads(out.read_text()), capsys.readouterr().err


def test_ls_names_the_gross_errors_it_took_in(logs, capsys):
    directory, glitched_t_s = logs
    result, err = _ls(directory, "glitched", capsys)
    warning = [line for line in err.splitlines() if "no noise explains" in line]
    assert len(warning) == 1 and "ekf, isam2 and lm gate them" in warning[0]
    outliers = result["outliers"]
    # every glitch is beyond the gate; the fit they bend pushes some good samples past it with them
    assert outliers["count"] >= len(glitched_t_s)
    assert set(np.round(outliers["t_s"], 9)) <= glitched_t_s  # the worst named are glitches
    assert min(outliers["noise_multiple"]) > 100  # hundreds of σ: no noise model's tail
    assert result["samples_used"] == N  # the paper's baseline still takes every sample


@pytest.mark.parametrize("settings", [(), ("--set", "noise.reading_sigma_mm=0.0004")])
def test_ls_names_none_of_a_clean_log_even_with_its_noise_five_times_too_small(logs, capsys, settings):
    """A noise σ configured too small scales every sample's χ² alike: the bulk's scale absorbs it."""
    directory, _ = logs
    result, err = _ls(directory, "clean", capsys, *settings)
    assert "outliers" not in result and "no noise explains" not in err
