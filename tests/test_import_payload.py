"""``import --load-kg`` and the mapping's ``[strokes] load_kg``: the payload of an imported log (spec §10,
§12), which an elastic platform's estimators read; bad payloads refused in one line, nothing written."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import cli
from stewart_calib.io import read_log
from stewart_calib.io.platform_file import load_platform, platform_to_toml
from stewart_calib.model.platform import Elastic, payload_limit
from stewart_calib.samples import LOAD_KG

from . import vendor_files as vendor
from .test_import import COUNTS_MAPPING, EXAMPLE, OFFSETS, _motion, _strokes_of

#: a compliance prior that lets the hobby hexapod carry some 30 kg (spec §10's payload limit)
LOOSE_SIGMA_MM_PER_KN = 1700.0


def _run(capsys, *argv) -> tuple[int, str]:
    code = cli.main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip()


@pytest.fixture()
def files(tmp_path):
    """A Motive export at 100 Hz (Z-up, 2 s) and the controller's counts every 3 ms, with its payload in
    grams: 0 until 1 s, then 20 kg (the first 20 kg row at 1.002 s: the frame at 1.00 s lies between a 0
    and a 20 kg row); an elastic hobby hexapod whose payload limit lies between 20 and 40 kg."""
    t, rotation, position = _motion(200, 100.0)
    vendor.motive_csv(tmp_path / "m.csv", t, rotation.as_quat(), position, unit="Millimeters")
    t_c = np.arange(0, 2.5, 0.003)
    q = _strokes_of(t_c)
    payload_g = np.where(t_c >= 1.0, 20000.0, 0.0)
    with open(tmp_path / "c.csv", "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(["stamp_ms", *(f"leg{i}" for i in range(1, 7)), "payload"])
        for t_ms, counts, grams in zip(t_c * 1000.0, q * 100.0, payload_g, strict=True):
            writer.writerow([repr(float(t_ms)), *map(repr, counts.tolist()), repr(float(grams))])
    (tmp_path / "c.toml").write_text(COUNTS_MAPPING)
    (tmp_path / "held.toml").write_text(COUNTS_MAPPING + 'load_kg = "payload"\nload_unit = "g"\n')
    elastic = Elastic(2.0, np.zeros(3), compliance_sigma_mm_per_kN=LOOSE_SIGMA_MM_PER_KN)
    platform = dataclasses.replace(load_platform("hobby-hexapod"), elastic=elastic)
    assert 20.0 < payload_limit(platform) < 40.0
    (tmp_path / "elastic.toml").write_text(platform_to_toml(platform))
    return tmp_path, platform


def _import(capsys, root: Path, mapping: str, *extra) -> tuple[int, str, Path]:
    out = root / "log.csv"
    code, err = _run(
        capsys, "import", "--motive", root / "m.csv", "--rigid-body", "platform", "--up", "z",
        "--strokes", root / "c.csv", "--mapping", root / mapping, "--out", out, *extra,
    )  # fmt: skip
    return code, err, out


def test_load_kg_is_written_in_every_row_and_read_back_as_the_payload(capsys, files):
    root, platform = files
    code, err, out = _import(capsys, root, "c.toml", "--load-kg", "20")
    assert code == 0, err
    assert "payload 20 kg in every row" in err and err.count("\n") == 0
    assert out.read_text().splitlines()[0].split(",")[-1] == "load_kg"
    log = read_log(out, platform)
    assert len(log) == 200
    np.testing.assert_array_equal(log.inputs[LOAD_KG], np.full(200, 20.0))


def test_the_example_imports_at_20_kg_checked_against_the_elastic_platform(capsys, files):
    """``--platform`` with ``[elastic]``: 20 kg is within its limit, the log passes the diagnosis and reads back."""
    root, platform = files
    out = root / "fit.csv"
    code, err = _run(
        capsys, "import", "--motive", EXAMPLE / "fit_motive.csv", "--rigid-body", "platform",
        "--strokes", EXAMPLE / "fit_counts.csv", "--mapping", EXAMPLE / "controller.toml",
        "--clock-offset-s", OFFSETS["fit"], "--platform", root / "elastic.toml", "--load-kg", "20", "--out", out,
    )  # fmt: skip
    assert code == 0, err
    log = read_log(out, platform)
    assert len(log) == 108
    np.testing.assert_array_equal(log.inputs[LOAD_KG], np.full(108, 20.0))


def test_a_mapped_payload_is_held_from_the_controller_row_at_or_before_each_frame(capsys, files):
    """The frame at 1.00 s lies between the controller's rows at 0.999 s (0 kg) and 1.002 s (20 kg): it
    carries 0 kg (linear interpolation would give 6.7 kg), the frame at 1.01 s 20 kg; grams read as kg/1000."""
    root, platform = files
    code, err, out = _import(capsys, root, "held.toml")
    assert code == 0, err
    assert "payload 'payload' in g (held from the row at or before each measurement)" in err
    log = read_log(out, platform)
    np.testing.assert_array_equal(log.inputs[LOAD_KG], np.where(log.t_s >= 1.002, 20.0, 0.0))
    assert np.count_nonzero(log.inputs[LOAD_KG]) == 99  # frames 1.01 … 1.99 s
    np.testing.assert_allclose(log.strokes, _strokes_of(np.arange(200) / 100.0), atol=1e-2)  # still interpolated


def test_a_generic_csvs_own_payload_column_is_read_with_its_strokes(capsys, tmp_path):
    rows = (EXAMPLE / "fit_raw.csv").read_text().splitlines()
    loads = [0.0 if k < 50 else 20.0 for k in range(len(rows) - 1)]
    (tmp_path / "raw.csv").write_text(
        "\n".join([rows[0] + ",kg", *(f"{row},{m!r}" for row, m in zip(rows[1:], loads, strict=True))]) + "\n"
    )
    (tmp_path / "raw.toml").write_text((EXAMPLE / "raw.toml").read_text() + 'load_kg = "kg"\n')
    out = tmp_path / "log.csv"
    code, err = _run(capsys, "import", "--csv", tmp_path / "raw.csv", "--mapping", tmp_path / "raw.toml", "--out", out)
    assert code == 0, err
    log = read_log(out, dataclasses.replace(load_platform("hobby-hexapod"), elastic=Elastic(2.0, np.zeros(3))))
    np.testing.assert_array_equal(log.inputs[LOAD_KG], loads)


@pytest.mark.parametrize(
    ("mapping", "extra", "message"),
    [
        ("c.toml", ["--load-kg", "-1"], "--load-kg: expected a finite payload ≥ 0 kg (an input where"),
        ("c.toml", ["--load-kg", "nan"], "--load-kg: expected a finite payload ≥ 0 kg (an input where"),
        ("c.toml", ["--load-kg", "40", "--platform", "{root}/elastic.toml"], "--load-kg: expected a payload the "
         "platform can carry, at most 30.39 kg"),
        ("held.toml", ["--load-kg", "20"], "--load-kg: the mapping's [strokes] load_kg = 'payload' gives the payload "
         "already; expected one of the two"),
        ("negative.toml", [], "c.csv: row 2: column 'payload': expected a finite payload ≥ 0 kg"),
        ("held.toml", ["--platform", "{root}/elastic.toml"], "c.csv: row 336: column 'payload': expected a payload "
         "the platform can carry, at most 30.39 kg: under 40 kg"),
    ],
)  # fmt: skip
def test_a_bad_payload_is_refused_in_one_line_and_nothing_written(capsys, files, mapping, extra, message):
    root, _ = files
    # "negative": the controller's payload column read with the sign of the strokes' counts: −20 kg
    (root / "negative.toml").write_text(COUNTS_MAPPING + 'load_kg = "payload"\nload_unit = "g"\n')
    if mapping == "negative.toml":
        text = (root / "c.csv").read_text().splitlines()
        (root / "c.csv").write_text("\n".join([text[0], text[1].rsplit(",", 1)[0] + ",-1.0", *text[2:]]) + "\n")
    if "at most 30.39 kg: under 40 kg" in message:  # a 40 kg step from row 336 on (t = 1.002 s)
        (root / "c.csv").write_text((root / "c.csv").read_text().replace(",20000.0\n", ",40000.0\n"))
    code, err, out = _import(capsys, root, mapping, *(a.format(root=root) for a in extra))
    assert code == 2 and err.count("\n") == 0 and "Traceback" not in err
    assert message in err, err
    assert not out.exists()
