"""Estimator settings: the documented defaults file, overrides and refusals (one line naming the key)."""

import dataclasses

import pytest

from stewart_calib.config import EstimatorConfig, load_estimator_config
from stewart_calib.errors import CalibError
from stewart_calib.resources import CONFIGS


def test_default_toml_documents_exactly_the_built_in_defaults():
    assert load_estimator_config(CONFIGS / "estimators" / "default.toml") == EstimatorConfig()


def test_paper_toml_changes_only_what_it_explains():
    paper = load_estimator_config(CONFIGS / "estimators" / "paper.toml")
    assert (paper.noise.reading_sigma_mm, paper.noise.random_walk_mm_per_sqrt_s) == (0.02, 0.1)
    assert paper.paper_ekf.angle_unit == "deg"
    assert paper.ls == dataclasses.replace(EstimatorConfig().ls, weighting="paper")  # the paper's own LS
    assert (paper.ekf, paper.isam2) == (EstimatorConfig().ekf, EstimatorConfig().isam2)


def test_set_overrides_parse_toml_values():
    config = load_estimator_config(None, ["isam2.lag_s=5", "isam2.robust=cauchy", "paper_ekf.adaptive=true"])
    assert (config.isam2.lag_s, config.isam2.robust, config.paper_ekf.adaptive) == (5.0, "cauchy", True)


@pytest.mark.parametrize(
    "override, expected",
    [
        ("noise.reading_sigma_mm=0", "key 'noise.reading_sigma_mm': expected a positive σ, got 0.0"),
        ("noise.prior_sigma_mm=-1", "key 'noise.prior_sigma_mm': expected a finite non-negative number"),
        ("paper_ekf.adaptive_window=5", "key 'paper_ekf.adaptive_window': expected at least 6 innovations"),
        ("paper_ekf.adaptive_window=6.5", "key 'paper_ekf.adaptive_window': expected a whole number"),
        ("isam2.lag_s=0", "key 'isam2.lag_s': expected a positive lag"),
        ("isam2.robust=tukey", "key 'isam2.robust': expected one of none, huber, cauchy"),
        ("isam2.lags=3", "unknown key 'isam2.lags'"),
        ("kalman.q=3", "unknown section 'kalman'"),
        ("lag_s=3", "expected section.key=value"),
        ("noise.reading_sigma_mm=nan", "expected a finite non-negative number, got nan"),
        ("noise.reading_sigma_mm=abc", "expected a number"),
        # a gate passing every sample has no finite χ² threshold: refused here, not as chdtri's ValueError
        ("ekf.gate_probability=1", "key 'ekf.gate_probability': expected a probability in (0, 1) (0: the gate off)"),
        ("isam2.gate_probability=1.5", "key 'isam2.gate_probability': expected a probability in (0, 1)"),
        ("paper_ekf.gate_probability=1.0", "key 'paper_ekf.gate_probability': expected a probability in (0, 1)"),
    ],
)
def test_bad_overrides_are_refused_in_one_line_naming_the_key(override, expected):
    with pytest.raises(CalibError) as err:
        load_estimator_config(None, [override])
    assert expected in str(err.value) and "\n" not in str(err.value)


def test_a_bad_file_is_refused_naming_it(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[noise]\nstroke_sigma_mm = 0.0\n")
    with pytest.raises(CalibError, match=rf"{path}: key 'noise.stroke_sigma_mm': expected a positive σ"):
        load_estimator_config(path)
