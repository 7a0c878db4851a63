"""The elastic robot's files (spec §10): ``[elastic]`` in the platform file, ``load_kg`` as an input,
``simulate``'s platform with the masses and the compliance's truth."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from stewart_calib.cli import main
from stewart_calib.errors import CalibError
from stewart_calib.io import read_log
from stewart_calib.io.logs import LogRowParser
from stewart_calib.platform import load_platform, parse_platform, platform_to_toml
from stewart_calib.simulation.experiment import load_experiment
from tests.test_platform import _doc, _refusal, _to_toml

QUICK = Path(__file__).resolve().parents[1] / "configs" / "experiments" / "quick.toml"
ELASTIC = {"platform_mass_kg": 60.0, "platform_com_mm": [0.0, 0.0, -50.0]}


def _with_elastic(**keys) -> dict:
    doc = _doc()
    doc["elastic"] = {**ELASTIC, **keys}
    return doc


def test_elastic_reads_with_its_defaults_and_round_trips():
    platform = parse_platform(_with_elastic(), "p.toml")
    elastic = platform.elastic
    assert elastic.platform_mass_kg == 60.0
    np.testing.assert_array_equal(elastic.platform_com_mm, [0.0, 0.0, -50.0])
    np.testing.assert_array_equal(elastic.payload_com_mm, np.zeros(3))
    np.testing.assert_array_equal(elastic.compliance_mm_per_kN, np.zeros(6))
    # the default σ: the compliance at which a sixth of the platform's weight shortens a leg by 2 mm
    assert elastic.compliance_sigma_mm_per_kN == pytest.approx(2.0 / (60.0 * 9.80665 / 6 / 1000.0), rel=1e-12)
    assert elastic.true_compliance_mm_per_kN is None
    text = platform_to_toml(platform)
    again = parse_platform(tomllib.loads(text), "again.toml")
    assert platform_to_toml(again) == text
    assert parse_platform(_doc(), "rigid.toml").elastic is None


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        ({"platform_mass_kg": -1.0}, "key 'elastic.platform_mass_kg': expected a positive mass in kg, got -1.0"),
        ({"platform_mass_kg": 0.0}, "key 'elastic.platform_mass_kg': expected a positive mass in kg, got 0.0"),
        ({"platform_mass_kg": float("nan")}, "key 'elastic.platform_mass_kg': expected a finite number"),
        ({"platform_mass_kg": float("inf")}, "key 'elastic.platform_mass_kg': expected a finite number"),
        (
            {"platform_com_mm": [0.0, 0.0, -50000.0]},
            "key 'elastic.platform_com_mm': expected [x, y, z] in mm within 10",
        ),
        ({"payload_com_mm": [9000.0, 0.0, 0.0]}, "key 'elastic.payload_com_mm': expected [x, y, z] in mm within 10"),
        ({"compliance_sigma_mm_per_kN": -0.5}, "key 'elastic.compliance_sigma_mm_per_kN': expected a σ ≥ 0"),
        ({"compliance_mm_per_kN": [1.0] * 5}, "key 'elastic.compliance_mm_per_kN': expected a list of 6 numbers"),
        ({"payload_mass": 3.0}, "unknown key 'elastic.payload_mass'"),
    ],
)
def test_bad_elastic_tables_are_refused_in_one_line(tmp_path, keys, expected):
    assert expected in _refusal(tmp_path, _to_toml(_with_elastic(**keys)))


def test_a_missing_platform_mass_is_named(tmp_path):
    doc = _with_elastic()
    del doc["elastic"]["platform_mass_kg"]
    assert "key 'elastic.platform_mass_kg': expected the platform's mass in kg (missing)" in _refusal(
        tmp_path, _to_toml(doc)
    )


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "quick"
    assert main(["simulate", "--experiment", str(QUICK), "--out", str(out)]) == 0
    return out


def test_simulate_writes_the_masses_and_the_compliance_truth(simulated):
    load = load_experiment(QUICK).load
    elastic = load_platform(simulated / "platform.toml").elastic
    assert elastic.platform_mass_kg == load.platform_mass_kg
    np.testing.assert_array_equal(elastic.platform_com_mm, load.platform_com_mm)
    np.testing.assert_array_equal(elastic.payload_com_mm, load.payload_com_mm)
    np.testing.assert_array_equal(elastic.compliance_mm_per_kN, np.zeros(6))  # nominal: not yet calibrated
    series = 1e3 / load.leg_N_per_mm + 1e3 / load.base_joint_N_per_mm + 1e3 / load.platform_joint_N_per_mm
    np.testing.assert_allclose(elastic.true_compliance_mm_per_kN, series, rtol=1e-15)


@pytest.mark.parametrize(("value", "shown"), [("-2.0", "-2.0"), ("nan", "nan"), ("inf", "inf"), ("", "nan")])
def test_load_kg_is_an_input_with_elastic_refused_naming_the_row(simulated, tmp_path, value, shown):
    platform = load_platform(simulated / "platform.toml")
    lines = (simulated / "log.csv").read_text().splitlines()
    column = lines[0].split(",").index("load_kg")
    fields = lines[3].split(",")
    fields[column] = value
    lines[3] = ",".join(fields)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    expected = f"{path}: row 4: column 'load_kg': expected a finite payload ≥ 0 kg"
    with pytest.raises(CalibError, match=r"^[^\n]*$") as caught:
        read_log(path, platform)
    assert str(caught.value).startswith(expected) and str(caught.value).endswith(f"got {shown}")
    parser = LogRowParser(str(path), lines[0], platform)
    with pytest.raises(CalibError) as streamed:
        parser.parse(lines[3], 4)
    assert str(streamed.value) == str(caught.value)
    assert parser.parse_block([line.encode() for line in lines[1:5]]) is None
    # a rigid platform reads the payload for reports only: a blank or negative one is not its business
    rigid = load_platform("nim-stewart")
    assert len(read_log(path, rigid)) == len(lines) - 1
