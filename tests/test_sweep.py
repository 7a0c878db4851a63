"""The sweep without a cluster: spec validation, the simulated data, the scores, the store.

Dask itself (a real scheduler and workers, resume, a dying worker) is tests/test_sweep_dask.py.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from stewart_calib.cli import main
from stewart_calib.sweep import store
from stewart_calib.sweep.spec import load_spec, parse_spec
from stewart_calib.sweep.task import run_task, simulate, task_rng

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "configs" / "sweeps" / "smoke.toml"

#: Columns that measure the run rather than the data.
TIMES = ("seconds", "cpu_seconds")

#: χ²(42) central 99.9 %: a single run of a consistent, efficient estimator falls outside once in 1000.
CHI2_42 = chi2.ppf([0.0005, 0.9995], 42)


def spec_of(doc: dict, tmp_path: Path):
    return parse_spec(doc, tmp_path / "spec.toml")


def test_smoke_spec_grid_and_matched_noise():
    spec = load_spec(SMOKE)
    doc = tomllib.loads(SMOKE.read_text(encoding="utf-8"))
    lists = {k: v for k, v in doc["grid"].items() if isinstance(v, list)}
    assert spec.swept == list(lists)
    assert len(spec.cells) == np.prod([len(v) for v in lists.values()])
    assert len({c.id for c in spec.cells}) == len(spec.cells)
    for cell in spec.cells:
        noise = cell.estimator_config.noise
        assert (noise.reading_sigma_mm, noise.stroke_sigma_mm, noise.random_walk_mm_per_sqrt_s) == (
            cell.settings["reading_sigma_mm"],
            cell.settings["stroke_sigma_mm"],
            cell.settings["drift_mm_per_sqrt_s"],
        )


def test_cell_ids_follow_content_not_seeds(tmp_path):
    doc = {"methods": ["ekf"], "seeds": 2, "grid": {"reading_sigma_mm": [0.002, 0.01]}}
    ids = [c.id for c in spec_of(doc, tmp_path).cells]
    assert [c.id for c in spec_of(doc | {"seeds": 50}, tmp_path).cells] == ids  # more seeds: same cells
    grown = spec_of(doc | {"grid": {"reading_sigma_mm": [0.002, 0.01, 0.05]}}, tmp_path)
    assert [c.id for c in grown.cells][:2] == ids  # a new value adds cells, keeps the others
    assert not {c.id for c in spec_of(doc | {"methods": ["ekf", "ls"]}, tmp_path).cells} & set(ids)


def test_estimator_setting_axis_reaches_the_config(tmp_path):
    spec = spec_of({"methods": ["ekf"], "seeds": 1, "grid": {"ekf": {"gate_probability": [0.0, 0.999]}}}, tmp_path)
    assert spec.swept == ["ekf.gate_probability"]
    assert [c.estimator_config.ekf.gate_probability for c in spec.cells] == [0.0, 0.999]


@pytest.mark.parametrize(
    "doc, named",
    [
        ({"seeds": 1, "colour": "red"}, "'colour'"),
        ({"seeds": 1, "methods": ["ekf", "kalman"]}, "'kalman'"),
        ({"seeds": 1, "grid": {"noise_level": [1, 2]}}, "'grid.noise_level'"),
        ({"seeds": 1, "grid": {"instrument": ["tracker", "pose"]}}, "'pose'"),
        ({"seeds": 1, "grid": {"ekf": {"gate": 0.9}}}, "'ekf.gate'"),
        ({"seeds": 1, "grid": {"platform": "nowhere"}}, "'nowhere'"),
        ({"seeds": 1, "families": {"f": {"base_radius_mm": 1.0}}}, "'families.f.platform_radius_mm'"),
        ({"methods": ["ekf"]}, "'seeds'"),
    ],
)
def test_bad_spec_is_one_line_naming_it(tmp_path, capsys, doc, named):
    spec_path = tmp_path / "bad.toml"
    spec_path.write_text("\n".join(_toml_lines(doc)), encoding="utf-8")
    out = tmp_path / "out"
    assert main(["sweep", "--spec", str(spec_path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and named in err and str(spec_path) in err
    assert not out.exists()


def _toml_lines(doc: dict, prefix: str = "") -> list[str]:
    """A small TOML writer for the test specs (scalars, lists of scalars, nested tables)."""
    scalars = [f"{k} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    tables = []
    for key, value in doc.items():
        if isinstance(value, dict):
            name = f"{prefix}{key}"
            tables += [f"[{name}]", *_toml_lines(value, f"{name}.")]
    return scalars + tables


def _toml_value(value) -> str:
    if isinstance(value, list):
        return "[" + ", ".join(map(_toml_value, value)) + "]"
    return f'"{value}"' if isinstance(value, str) else repr(value)


def _cell(tmp_path, methods=("ekf",), **grid):
    spec = spec_of({"methods": list(methods), "seeds": 1, "grid": grid}, tmp_path)
    return spec, spec.cells[0]


def test_glitches_move_one_reading_by_the_glitch_size(tmp_path):
    _, clean_cell = _cell(tmp_path, samples=200, glitch_size_mm=0.7)
    _, dirty_cell = _cell(tmp_path, samples=200, glitch_size_mm=0.7, glitch_rate=0.2)
    clean = simulate(clean_cell.settings, clean_cell.platform, np.random.default_rng(5))
    dirty = simulate(dirty_cell.settings, dirty_cell.platform, np.random.default_rng(5))
    np.testing.assert_array_equal(clean.log.strokes, dirty.log.strokes)  # glitches are drawn last: the rest is the same
    jump = dirty.log.readings - clean.log.readings
    assert 0 < dirty.glitched.sum() < 200
    np.testing.assert_array_equal(np.count_nonzero(jump, axis=1), dirty.glitched.astype(int))
    np.testing.assert_allclose(np.abs(jump.sum(axis=1))[dirty.glitched], 0.7, rtol=1e-12)


def test_drift_is_a_random_walk_of_the_given_rate(tmp_path):
    _, cell = _cell(tmp_path, samples=400, drift_mm_per_sqrt_s=0.01, rate_hz=20.0)
    data = simulate(cell.settings, cell.platform, np.random.default_rng(3))
    steps = np.diff(data.true_params, axis=0)
    m = steps.size
    expected = 0.01**2 / 20.0
    # sample variance of m normal draws: relative standard error sqrt(2 / m); 4σ
    assert abs(np.mean(steps**2) / expected - 1.0) < 4.0 * np.sqrt(2.0 / m)


@pytest.mark.parametrize("drift", [0.0, 0.01])
def test_efficient_filter_scores_at_its_bound(tmp_path, drift):
    """On data of exactly its model, the EKF is efficient and consistent: 42·(RMS/CRB)² and the
    NEES each follow χ²(42) (the bound is Cramér–Rao without drift, the posterior bound with it)."""
    _, cell = _cell(tmp_path, samples=150, drift_mm_per_sqrt_s=drift)
    (row,) = run_task(cell, 11, ("ekf",))
    assert row["failure"] == "" and row["samples_rejected"] == 0
    assert CHI2_42[0] < 42 * row["rms_over_crb"] ** 2 < CHI2_42[1]
    assert CHI2_42[0] < row["nees"] < CHI2_42[1]
    assert row["closed_loop_mm"] < row["closed_loop_nominal_mm"] / 10  # calibrated: far better than nominal


def test_task_is_a_function_of_cell_and_seed(tmp_path):
    doc = {
        "methods": ["ls", "ekf"],
        "seeds": 1,
        "grid": {"samples": 30, "platform": "f", "glitch_rate": 0.1},
        "families": {
            "f": {
                "base_radius_mm": [600.0, 800.0],
                "platform_radius_mm": 280.0,
                "base_half_angle_deg": 12.0,
                "platform_half_angle_deg": [40.0, 50.0],
            }
        },
    }
    cell = spec_of(doc, tmp_path).cells[0]
    first, again = run_task(cell, 4, ("ls", "ekf")), run_task(cell, 4, ("ls", "ekf"))
    other_seed = run_task(cell, 5, ("ls", "ekf"))
    strip = lambda rows: [{k: v for k, v in r.items() if k not in TIMES} for r in rows]  # noqa: E731
    assert strip(first) == strip(again)
    assert strip(first) != strip(other_seed)
    # a family draws its geometry per run: two seeds, two drives
    a = simulate(cell.settings, cell.platform, task_rng(cell.id, 4)).platform.drive.as_vector()
    b = simulate(cell.settings, cell.platform, task_rng(cell.id, 5)).platform.drive.as_vector()
    assert not np.allclose(a, b)


def test_results_are_in_grid_order_whatever_the_finishing_order(tmp_path):
    spec = spec_of(
        {"methods": ["ekf", "ls"], "seeds": 3, "grid": {"samples": 20, "reading_sigma_mm": [0.002, 0.01]}}, tmp_path
    )
    schema = store.schema(spec)
    store.prepare(tmp_path)
    tasks = spec.tasks()
    for k in np.random.default_rng(0).permutation(len(tasks)):
        cell, seed = tasks[k]
        rows = [
            {"cell": cell.id, "seed": seed, "method": m, **cell.settings, "failure": ""} for m in reversed(spec.methods)
        ]
        store.write_part(tmp_path, rows, schema)
    assert store.finished(spec, tmp_path) == {(c.id, s) for c, s in tasks}
    table = store.consolidate(spec, tmp_path, schema)
    expected = [(c.id, s, m) for c, s in tasks for m in spec.methods]
    assert list(zip(*(table[n].to_pylist() for n in ("cell", "seed", "method")), strict=True)) == expected
