"""Numbers in written files: 15 significant digits (``errors.without_noise``), so that no file holds the
binary noise of arithmetic (``12.000000000000002``, ``0.7000000000000001``) and every writer rounds alike."""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib

import numpy as np
import pytest

from stewart_calib.errors import number, without_noise
from stewart_calib.estimate import Estimate
from stewart_calib.io import result_dict, write_log, write_pose_list, write_result
from stewart_calib.io.controllers import controller_json_text
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.samples import Log
from tests.synthetic import nim_stewart


def _significant_digits(value: float) -> int:
    """The significant digits of a float's ``repr`` (``1.25e-05`` → 3)."""
    mantissa = repr(value).lower().split("e")[0].lstrip("-").replace(".", "")
    return len(mantissa.strip("0")) or 1


def _python_rounding(values: np.ndarray) -> np.ndarray:
    return np.array([float(f"{v:.15g}") if math.isfinite(v) else v for v in values.tolist()])


def test_an_array_rounds_to_the_doubles_python_formats_to_15_digits():
    rng = np.random.default_rng(0)
    powers = 10.0 ** np.arange(-12, 18)
    values = np.concatenate(
        [
            rng.normal(0, 30, 50_000),  # a few thousand products land on a half: the exact remainder decides
            np.arange(10_000) * 0.1,
            10.0 ** rng.uniform(-12, 18, 20_000) * rng.choice([-1.0, 1.0], 20_000),  # outside 1e-8 … 1e15 too
            powers,
            np.nextafter(powers, 0.0),
            np.nextafter(powers, np.inf),
            [0.0, -0.0, 5e-324, 1.7e308, np.nan, np.inf, -np.inf],
        ]
    )
    rounded = without_noise(values)
    expected = _python_rounding(values)
    assert np.array_equal(rounded, expected, equal_nan=True)
    assert np.signbit(without_noise(np.array([-0.0])))[0]
    # each holds at most 15 significant digits, and is what a message shows of it
    finite = rounded[np.isfinite(rounded)].tolist()
    assert max(map(_significant_digits, finite)) == 15
    assert all(float(number(x)) == x for x in finite)


def test_documents_round_their_floats_and_leave_everything_else():
    document = {"t": [0.1 * 7, 3, True, "0.1", None], "nested": ({"deg": math.degrees(math.radians(12.0))},)}
    assert without_noise(document) == {"t": [0.7, 3, True, "0.1", None], "nested": ({"deg": 12.0},)}
    assert type(without_noise(np.float64(1 / 3))) is float and without_noise(np.arange(3)).dtype.kind == "i"


def test_a_platform_file_holds_no_binary_noise_and_writes_again_the_same():
    platform = nim_stewart()
    twelve = dataclasses.replace(platform.workspace, rotation_limit=math.radians(12.0))
    text = platform_to_toml(dataclasses.replace(platform, workspace=twelve))
    assert "rotation_limit_deg = 12.0\n" in text  # not 12.000000000000002
    again = parse_platform(tomllib.loads(text), "again.toml")
    assert platform_to_toml(again) == text
    assert again.workspace.rotation_limit == math.radians(12.0)


@pytest.mark.parametrize("rows", [10, 5000])  # by repr and by pyarrow (from 4096 rows)
def test_a_log_and_a_pose_list_write_times_without_binary_noise(tmp_path, rows):
    t_s = np.arange(rows) * 0.1
    log = Log(t_s=t_s, strokes=np.zeros((rows, 6)), readings=np.full((rows, 6), 1 / 3))
    write_log(tmp_path / "log.csv", log)
    lines = (tmp_path / "log.csv").read_text().splitlines()
    assert lines[8].split(",")[0] == "0.7" and lines[8].split(",")[7] == "0.333333333333333"
    write_pose_list(tmp_path / "poses.csv", np.zeros((rows, 6)), dwell_s=0.1)
    assert (tmp_path / "poses.csv").read_text().splitlines()[8].split(",")[0] == "0.7"


def test_json_files_write_15_digits(tmp_path):
    platform = nim_stewart()
    rng = np.random.default_rng(5)
    estimate = Estimate(rng.normal(0, 1, 42), np.diag(rng.uniform(0.01, 1, 42)), "ekf", 12)
    write_result(tmp_path / "r.json", result_dict(estimate, platform, extra={"elapsed_s": 0.1 * 7}))
    text = (tmp_path / "r.json").read_text()
    assert '"elapsed_s": 0.7' in text
    numbers = [float(v) for v in json.loads(text)["estimate"]]
    assert numbers == without_noise(platform.drive.as_vector() + estimate.error).tolist()
    controller = json.loads(controller_json_text(platform.drive, np.full(6, 0.1 * 7 - 0.7), "inch", {}))
    inches = [v for leg in controller["legs"] for v in [*leg["base_joint"], leg["stroke_per_logged_unit"]]]
    assert max(map(_significant_digits, inches)) <= 15 and controller["legs"][0]["stroke_per_logged_unit"] == 1.0


def test_a_platforms_identity_keeps_every_bit():
    """A sweep's cell id hashes its platform's values to the bit (``exact``): the 15 digits of the file would
    give every cell, and so every task's random draws, another id."""
    platform = nim_stewart()
    turned = dataclasses.replace(platform, drive=platform.drive.perturbed(np.full(42, 1 / 3)))
    exact = platform_to_toml(turned, exact=True)
    assert exact != platform_to_toml(turned)
    back = parse_platform(tomllib.loads(exact), "exact.toml")
    np.testing.assert_array_equal(back.drive.as_vector(), turned.drive.as_vector())


def test_a_checkpoint_keeps_its_platform_to_the_bit(tmp_path):
    """A checkpoint is state, not a file for people: its platform is read back as it was, to the last bit."""
    from stewart_calib.workflows.online import OnlineCalibrator

    platform = nim_stewart()
    turned = dataclasses.replace(platform, drive=platform.drive.perturbed(np.full(42, 1 / 3)))
    OnlineCalibrator(turned, "ekf").save(tmp_path / "c.npz")
    resumed = OnlineCalibrator.load(tmp_path / "c.npz", None)
    np.testing.assert_array_equal(resumed.platform.drive.as_vector(), turned.drive.as_vector())
    assert OnlineCalibrator.load(tmp_path / "c.npz", turned).platform.drive.as_vector().tolist() == (
        turned.drive.as_vector().tolist()
    )
