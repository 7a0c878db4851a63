"""``[elastic]`` values and payloads no platform could have are refused in one line (spec §10).

The bound is physical: six legs hold the weight ``m g`` along z, so the most loaded leg carries at
least a sixth of it axially, whatever the pose; at the declared compliance plus one prior σ that
leg shortens by at least ``(c + σ_c) m g / 6``, and no leg gives more than its stroke range.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.errors import CalibError
from stewart_calib.io import read_log, write_log
from stewart_calib.io.platform_file import parse_platform, platform_to_toml
from stewart_calib.model.platform import G_N_PER_KG, Elastic, payload_limit
from stewart_calib.resources import read_toml
from stewart_calib.samples import LOAD_KG
from tests.synthetic import NIM_STEWART, make_log, nim_stewart, random_poses

MASS_KG, SIGMA = 60.0, 20.0  # nim-stewart's 60 kg platform, legs' compliance σ 20 mm/kN
STROKE_RANGE_MM = 940.0  # nim-stewart's [-420, 520] mm


def _doc(**elastic) -> dict:
    _, doc = read_toml(NIM_STEWART, "platforms", "platform")
    table = {"platform_mass_kg": MASS_KG, "platform_com_mm": [0.0, 0.0, -50.0], "compliance_sigma_mm_per_kN": SIGMA}
    return doc | {"elastic": table | elastic}


def test_the_payload_limit_is_the_load_under_which_a_leg_would_give_its_stroke_range():
    platform = parse_platform(_doc())
    limit = payload_limit(platform)
    # (c + σ) (m + M) g / 6 / 1000 = stroke range, c = 0
    assert limit == pytest.approx(STROKE_RANGE_MM / (SIGMA * G_N_PER_KG / 6 / 1000) - MASS_KG, rel=1e-12)
    assert 28_000 < limit < 29_000  # tonnes: far beyond any payload of this robot, far below 1e9 kg
    rigid = dataclasses.replace(platform, elastic=Elastic(MASS_KG, np.zeros(3), compliance_sigma_mm_per_kN=0.0))
    assert payload_limit(rigid) == np.inf  # legs declared rigid give nothing under any payload


@pytest.mark.parametrize(
    "elastic, key, expected",
    [
        ({"platform_mass_kg": 1e-9}, "elastic.platform_mass_kg", "a mass in kg of at least 0.001 (a gram)"),
        ({"compliance_mm_per_kN": [1e9] * 6}, "elastic.compliance_mm_per_kN", "legs that can hold the platform"),
        ({"compliance_sigma_mm_per_kN": 1e12}, "elastic.compliance_sigma_mm_per_kN", "beyond 940 mm of the stroke"),
        ({"payload_sigma_kg": 1e12}, "elastic.payload_sigma_kg", "a payload σ the platform could carry: at most"),
    ],
)
def test_elastic_values_no_platform_has_are_refused_naming_the_key(elastic, key, expected):
    """A tiny mass, a huge compliance or prior σ, a huge payload σ: accepted before, and then a
    singular matrix (payload σ), a traceback or most rows dropped (prior σ) in the estimators."""
    with pytest.raises(CalibError) as err:
        parse_platform(_doc(**elastic), "p.toml")
    message = str(err.value)
    assert message.startswith(f"p.toml: key '{key}': expected ") and expected in message and "\n" not in message


def test_the_limit_is_just_past_what_the_legs_can_hold():
    """σ at its bound passes, 1 % over it is refused: the message's 'at most' is the bound itself."""
    at_most = STROKE_RANGE_MM / (MASS_KG * G_N_PER_KG / 6 / 1000)
    parse_platform(_doc(compliance_sigma_mm_per_kN=at_most * (1 - 1e-9)))
    with pytest.raises(CalibError, match=f"expected at most {at_most:.4g} mm/kN"):
        parse_platform(_doc(compliance_sigma_mm_per_kN=at_most * 1.01))


@pytest.fixture()
def elastic_files(tmp_path):
    platform = parse_platform(_doc())
    rng = np.random.default_rng(2)
    log, _ = make_log(nim_stewart(), np.zeros(42), random_poses(platform, 30, rng), rng)
    load = np.repeat([0.0, 20.0, 40.0], 10)
    (tmp_path / "p.toml").write_text(platform_to_toml(platform))
    return platform, dataclasses.replace(log, inputs={LOAD_KG: load}), tmp_path


def test_a_payload_the_platform_could_not_carry_is_refused_naming_row_and_column(elastic_files):
    """One row of 1e9 kg was used and set all six compliances to 0 ± 0 (truth 2.33 mm/kN)."""
    platform, log, tmp_path = elastic_files
    load = log.inputs[LOAD_KG].copy()
    load[4] = 1e9
    write_log(tmp_path / "log.csv", dataclasses.replace(log, inputs={LOAD_KG: load}), platform)
    with pytest.raises(CalibError) as err:
        read_log(tmp_path / "log.csv", platform)
    message = str(err.value)
    assert message.startswith(f"{tmp_path / 'log.csv'}: row 6: column 'load_kg': expected a payload the platform")
    assert "grams" not in message and "\n" not in message
    skipped = read_log(tmp_path / "log.csv", platform, skip_bad_rows=True)  # gated like any impossible reading
    assert len(skipped) == 29 and skipped.skipped[0][0] == 6


def test_a_payload_in_grams_is_named_as_such(elastic_files, capsys):
    platform, log, tmp_path = elastic_files
    write_log(tmp_path / "log.csv", dataclasses.replace(log, inputs={LOAD_KG: log.inputs[LOAD_KG] * 1000.0}), platform)
    argv = ["calibrate", "--platform", str(tmp_path / "p.toml"), "--log", str(tmp_path / "log.csv")]
    assert cli.main([*argv, "--method", "ekf", "--out", str(tmp_path / "r.json")]) == 2
    err = capsys.readouterr().err
    # 20 000 "kg" is within the tonnes the legs could hold; 40 000 is not, and is 40 kg in grams
    assert err.count("\n") == 1 and "row 22: column 'load_kg'" in err and "it looks like grams (40 kg)" in err
    assert not (tmp_path / "r.json").exists()


def test_compensate_refuses_a_payload_the_platform_could_not_carry(elastic_files, capsys):
    platform, _, tmp_path = elastic_files
    home = platform.workspace.home
    pose = ",".join(map(repr, [*home[:3], *np.degrees(home[3:])]))
    (tmp_path / "poses.csv").write_text(f"x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n{pose}\n")
    argv = ["compensate", "--platform", str(tmp_path / "p.toml"), "--poses", str(tmp_path / "poses.csv")]
    assert cli.main([*argv, "--out", str(tmp_path / "q.csv"), "--payload-kg", "1e9"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--payload-kg: expected a payload the platform can carry, at most" in err
