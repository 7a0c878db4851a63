"""Platform files the adversarial pass got through (issue 14): degenerate joints, metres,
misspelt keys, numbers written as text — each refused at load in one line naming the key."""

from __future__ import annotations

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.errors import CalibError
from stewart_calib.platform import parse_platform
from tests.test_platform import _doc, _refusal, _to_toml


def _edited(edit) -> str:
    doc = _doc()
    edit(doc)
    return _to_toml(doc)


def _set(section, key, value):
    return lambda d: d[section].__setitem__(key, value)


@pytest.mark.parametrize(
    ("edit", "expected"),
    [
        (
            _set("drive", "base_joints_mm", [[100.0, 50.0, 10.0]] * 6),
            "key 'drive.base_joints_mm': expected 6 joints spread in a plane; joints 1–6 all coincide at [100.0, "
            "50.0, 10.0]",
        ),
        (
            _set("tracker", "platform_joints_mm", [[10.0 * k, 20.0 * k, -127.21] for k in range(6)]),
            "key 'tracker.platform_joints_mm': expected 6 joints spread in a plane; joints 1–6 lie on one line",
        ),
        (
            _set("drive", "stroke_rnage_mm", [-420.0, 520.0]),
            "unknown key 'drive.stroke_rnage_mm' (did you mean 'stroke_range_mm'?); expected one of base_joints_mm, "
            "initial_lengths_mm, kind, platform_joints_mm, stroke_range_mm",
        ),
        (lambda d: d.__setitem__("nmae", "x"), "unknown key 'nmae' (did you mean 'name'?)"),
        (
            lambda d: d["drive"]["initial_lengths_mm"].__setitem__(0, "1048.5"),
            "key 'drive.initial_lengths_mm': expected a list of 6 numbers of numbers (not quoted text)",
        ),
        (
            lambda d: d["tracker"]["base_joints_mm"][2].__setitem__(1, "-651.41"),
            "key 'tracker.base_joints_mm': expected 6 rows of [x, y, z] in mm of numbers (not quoted text)",
        ),
    ],
)
def test_bad_platforms_are_refused_at_load_naming_the_key(tmp_path, edit, expected):
    assert expected in _refusal(tmp_path, _edited(edit))


def test_a_key_with_a_newline_is_named_on_one_line():
    """A quoted TOML key may hold a newline (found by test_fuzz): the refusal stays one line."""
    doc = _doc()
    doc["drive"]["bad\nkey"] = 1.0
    with pytest.raises(CalibError) as info:
        parse_platform(doc, "p.toml")
    assert str(info.value).startswith("p.toml: unknown key 'drive.bad\\nkey'") and "\n" not in str(info.value)


def test_a_platform_in_metres_is_called_metres(tmp_path):
    def to_metres(doc):
        for section in ("drive", "tracker"):
            for key in ("base_joints_mm", "platform_joints_mm"):
                doc[section][key] = (np.array(doc[section][key]) / 1000).tolist()
            doc[section]["initial_lengths_mm"] = (np.array(doc[section]["initial_lengths_mm"]) / 1000).tolist()
            doc[section].pop("stroke_range_mm", None)
            doc[section].pop("reading_range_mm", None)
        doc.pop("workspace")

    message = _refusal(tmp_path, _edited(to_metres))
    assert message.endswith(
        "[drive]: the geometry looks like metres (largest coordinate or length 1.049); expected millimetres (spec §2)"
    )


def test_a_degenerate_platform_is_refused_by_every_command_in_one_line(tmp_path, capsys):
    path = tmp_path / "p.toml"
    path.write_text(_edited(_set("drive", "platform_joints_mm", [[0.0, 0.0, -127.21]] * 6)))
    poses = tmp_path / "poses.csv"
    poses.write_text("x_mm,y_mm,z_mm,roll_deg,pitch_deg,yaw_deg\n0,0,1125.8,0,0,0\n")
    for argv in (
        ["identifiability", "--platform", str(path), "--poses", str(poses)],
        ["plan", "--platform", str(path), "--n", "20", "--out", str(tmp_path / "planned.csv")],
    ):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "drive.platform_joints_mm" in err[0] and "coincide" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "poses.csv"]
