"""Platform files (spec §2): the paper's platform loads, TOML round-trips, every refusal names file and key."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from stewart_calib.errors import CalibError
from stewart_calib.io.platform_file import load_platform, parse_platform, platform_to_toml
from stewart_calib.model.kinematics import leg_lengths, pose_to_rt
from stewart_calib.model.platform import PARAMETER_NAMES
from tests.synthetic import NIM_STEWART, nim_stewart


def test_nim_stewart_loads_with_paper_values():
    platform = nim_stewart()
    assert platform.name == "nim-stewart"
    assert platform.reading_range == (-276.0, 318.0)  # paper §4.1 grating range
    assert platform.stroke_range == (-420.0, 520.0)
    np.testing.assert_array_equal(platform.tracker.base_joints[0], [728.280, 41.410, 108.790])  # Table 2, z_1
    np.testing.assert_array_equal(platform.tracker.platform_joints[5], [25.000, 253.000, -127.210])  # h_6
    ws = platform.workspace
    np.testing.assert_array_equal(ws.home, [0.0, 0.0, 1125.804, 0.0, 0.0, 0.0])
    assert ws.translation_limit == 200.0 and ws.rotation_limit == pytest.approx(math.radians(20.0))
    # at home every tracker reading and every drive stroke is 0 to the file's rounding (its header says so)
    R, t = pose_to_rt(ws.home)
    np.testing.assert_allclose(leg_lengths(platform.tracker, R, t) - platform.tracker.initial_lengths, 0.0, atol=5e-3)
    np.testing.assert_allclose(leg_lengths(platform.drive, R, t) - platform.drive.initial_lengths, 0.0, atol=5e-6)
    assert len(PARAMETER_NAMES) == 42 and PARAMETER_NAMES[:7] == ("j1x", "j1y", "j1z", "d1x", "d1y", "d1z", "l1")


def test_platform_to_toml_round_trips_exactly():
    platform = nim_stewart()
    assert_same_platform(parse_platform(tomllib.loads(platform_to_toml(platform))), platform)


def assert_same_platform(a, b) -> None:
    """Field by field, exactly (the dataclasses hold arrays, so ``==`` cannot compare them)."""
    assert (a.name, a.description, a.stroke_range, a.reading_range) == (
        b.name,
        b.description,
        b.stroke_range,
        b.reading_range,
    )
    for legs_a, legs_b in ((a.drive, b.drive), (a.tracker, b.tracker)):
        np.testing.assert_array_equal(legs_a.params, legs_b.params)
    np.testing.assert_array_equal(a.workspace.home, b.workspace.home)
    assert (a.workspace.translation_limit, a.workspace.rotation_limit) == (
        b.workspace.translation_limit,
        b.workspace.rotation_limit,
    )


def _doc() -> dict:
    return tomllib.loads(NIM_STEWART.read_text())


def _refusal(tmp_path, doc_text: str) -> str:
    path = tmp_path / "p.toml"
    path.write_text(doc_text)
    with pytest.raises(CalibError) as info:
        load_platform(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    return message


def _to_toml(doc: dict) -> str:
    """A minimal TOML writer for the platform document's shapes (strings, numbers, lists, tables)."""

    def value(v) -> str:
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return (
            repr(v)
            if not isinstance(v, float) or math.isfinite(v)
            else ("nan" if v != v else ("inf" if v > 0 else "-inf"))
        )

    top = [f"{k} = {value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    tables = [
        f"[{k}]\n" + "\n".join(f"{kk} = {value(vv)}" for kk, vv in v.items())
        for k, v in doc.items()
        if isinstance(v, dict)
    ]
    return "\n".join(top) + "\n\n" + "\n\n".join(tables) + "\n"


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (
            lambda d: d["drive"]["base_joints_mm"].pop(),
            "key 'drive.base_joints_mm': expected 6 rows of [x, y, z] in mm, got shape (5, 3)",
        ),
        (
            lambda d: d["tracker"].pop("platform_joints_mm"),
            "key 'tracker.platform_joints_mm': expected 6 rows of [x, y, z] in mm (missing)",
        ),
        (lambda d: d.pop("tracker"), "key 'tracker': expected a [tracker] table"),
        (lambda d: d.pop("name"), "key 'name': expected a non-empty string"),
        (
            lambda d: d["drive"]["initial_lengths_mm"].__setitem__(2, float("nan")),
            "key 'drive.initial_lengths_mm': expected a list of 6 numbers of finite numbers",
        ),
        (
            lambda d: d["tracker"]["base_joints_mm"][1].__setitem__(0, float("inf")),
            "key 'tracker.base_joints_mm': expected 6 rows of [x, y, z] in mm of finite numbers",
        ),
        (
            lambda d: d["drive"]["initial_lengths_mm"].__setitem__(0, -1.0),
            "key 'drive.initial_lengths_mm': expected 6 positive lengths in mm",
        ),
        (
            lambda d: d["tracker"].__setitem__("reading_range_mm", [318.0, -276.0]),
            "key 'tracker.reading_range_mm': expected [min, max] with min < max, got [318.0, -276.0]",
        ),
        (
            lambda d: d["drive"].__setitem__("stroke_range_mm", [1.0]),
            "key 'drive.stroke_range_mm': expected a list of 2 numbers, got shape (1,)",
        ),
        (
            lambda d: d["workspace"].__setitem__("rotation_limit_deg", -5.0),
            "key 'workspace.rotation_limit_deg': expected a finite non-negative number",
        ),
        (
            lambda d: d["workspace"]["home"].__setitem__(2, 1800.0),
            "key 'workspace.home': expected a home pose whose drive strokes lie within [-420.0, 520.0] mm",
        ),
        (
            lambda d: d["workspace"]["home"].__setitem__(2, 1500.0),
            "key 'workspace.home': expected a home pose whose tracker readings lie within [-276.0, 318.0] mm; leg 1 "
            "needs 336.455 mm",
        ),
    ],
)
def test_refusals_name_file_and_key(tmp_path, edit, expected):
    doc = _doc()
    edit(doc)
    assert expected in _refusal(tmp_path, _to_toml(doc))


def test_unedited_document_through_the_test_writer_loads(tmp_path):
    """The refusals above come from the edit, not from the test's own TOML writer."""
    path = tmp_path / "p.toml"
    path.write_text(_to_toml(_doc()))
    assert_same_platform(load_platform(path), nim_stewart())


def test_refuses_non_toml_and_missing_file(tmp_path):
    assert "not valid TOML" in _refusal(tmp_path, "name = \n[drive")
    missing = tmp_path / "missing.toml"
    with pytest.raises(CalibError, match=f"^{missing}: platform file not found$"):
        load_platform(missing)


def test_shipped_configs_resolve_inside_the_package():
    # configs/ ships as stewart_calib/configs (a link in the source tree), so installs that are
    # not editable find the same files as the repository.
    from stewart_calib.resources import CONFIGS
    from tests.synthetic import NIM_STEWART

    assert (CONFIGS / "platforms" / "nim-stewart.toml").read_bytes() == NIM_STEWART.read_bytes()
    assert {p.name for p in (CONFIGS / "experiments").glob("*.toml")} >= {"paper.toml", "quick.toml"}
    assert {p.name for p in (CONFIGS / "estimators").glob("*.toml")} >= {"default.toml", "paper.toml"}
