"""``stewart-calib simulate``: files per the spec, read back by io and by a plain csv reader."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.io import read_log, read_truth
from stewart_calib.platform import PARAMETER_NAMES, load_platform
from stewart_calib.simulation.closed_loop import run_experiment
from stewart_calib.simulation.experiment import load_experiment

QUICK = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "quick.toml"


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "quick"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(out)]) == 0
    return out


def test_output_reads_back_with_the_projects_reader(simulated):
    expected = run_experiment(load_experiment(QUICK))
    platform = load_platform(simulated / "platform.toml")
    nominal = load_experiment(QUICK).platform  # the nominal platform, round-tripped exactly
    np.testing.assert_array_equal(platform.drive.as_vector(), nominal.drive.as_vector())
    np.testing.assert_array_equal(platform.tracker.as_vector(), nominal.tracker.as_vector())
    log = read_log(simulated / "log.csv", platform=platform)  # strict: every row in range
    truth = read_truth(simulated / "truth.csv")
    assert len(log) == len(truth.t_s) == len(expected.log)
    # CSV round-trips floats via repr; degrees ↔ radians may cost an ulp
    np.testing.assert_array_equal(log.strokes, expected.log.strokes)
    np.testing.assert_array_equal(log.readings, expected.log.readings)
    np.testing.assert_allclose(log.desired_poses, expected.desired_poses, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(truth.params, expected.truth.params)
    np.testing.assert_allclose(truth.true_poses, expected.actual_poses, rtol=0, atol=1e-12)
    assert log.stages == list(expected.stages)
    np.testing.assert_array_equal(log.load_kg, expected.payload_kg)


def test_output_reads_back_with_a_plain_csv_reader(simulated):
    with open(simulated / "log.csv", newline="", encoding="utf-8") as handle:
        rows = list(csv.DictReader(handle))
    with open(simulated / "truth.csv", newline="", encoding="utf-8") as handle:
        truth_rows = list(csv.DictReader(handle))
    required = ["t_s", *(f"q{i}_mm" for i in range(1, 7)), *(f"s{i}_mm" for i in range(1, 7))]
    assert set(required) <= set(rows[0])
    assert {"x_mm", "roll_deg", "stage", "load_kg"} <= set(rows[0])
    assert {"t_s", *PARAMETER_NAMES, "true_x_mm", "true_yaw_deg"} <= set(truth_rows[0])
    assert len(rows) == len(truth_rows)
    t = [float(r["t_s"]) for r in rows]
    assert t == [float(r["t_s"]) for r in truth_rows] and all(b >= a for a, b in zip(t, t[1:]))
    assert {r["stage"] for r in rows} == {"no-load", "40kg"}
    # a pose in degrees: within the ±20° workspace
    assert max(abs(float(r["roll_deg"])) for r in rows) <= 20.0


def test_same_experiment_same_files(simulated, tmp_path):
    again = tmp_path / "again"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(again)]) == 0
    for name in ("platform.toml", "log.csv", "truth.csv"):
        assert (again / name).read_bytes() == (simulated / name).read_bytes(), name


def test_bad_key_exits_with_one_line_naming_file_and_key(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text(QUICK.read_text().replace("[poses]", "[poses]\nsamples_per_poze = 3"))
    assert main(["simulate", "--experiment", str(bad), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(bad) in err and "'poses.samples_per_poze'" in err
    assert not (tmp_path / "out" / "log.csv").exists()
