"""Where a command's writes land: never over one of its inputs (by identity, siblings included),
through links to the file they name, into a device or descriptor rather than over it, and all
of a command's files or none."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from stewart_calib import cli
from stewart_calib.io.platform_file import load_platform, platform_to_toml
from tests.synthetic import NIM_STEWART, ROOT


@pytest.fixture
def platform_path(tmp_path) -> Path:
    path = tmp_path / "P.toml"
    path.write_text(platform_to_toml(load_platform(NIM_STEWART)))
    return path


def _run(capsys, *argv) -> tuple[int, list[str]]:
    capsys.readouterr()
    code = cli.main([str(arg) for arg in argv])
    return code, capsys.readouterr().err.strip().splitlines()


def _export(platform: Path, out: Path, fmt: str = "linuxcnc") -> list[str]:
    return ["export", "--platform", platform, "--format", fmt, "--out", out]


@pytest.mark.parametrize("input_name", ["P", "link"])
def test_export_refuses_an_ini_sibling_that_is_its_input(tmp_path, platform_path, capsys, input_name):
    """``--out P.hal`` writes ``P.ini`` beside it: the platform ``P.ini`` (or a link to it) is an input."""
    before = platform_path.read_bytes()
    platform = tmp_path / "P.ini"
    platform_path.rename(platform)
    given = platform
    if input_name == "link":
        given = tmp_path / "elsewhere.toml"
        given.symlink_to(platform)
    code, err = _run(capsys, *_export(given, tmp_path / "P.hal"))
    assert code == 2 and err == [
        f"stewart-calib export: error: --out {tmp_path / 'P.ini'}: is the --platform input; writing it would "
        "destroy it — expected another path"
    ]
    assert platform.read_bytes() == before and not (tmp_path / "P.hal").exists()


def test_export_refuses_an_ini_sibling_that_is_a_directory_and_writes_nothing(tmp_path, platform_path, capsys):
    (tmp_path / "k.ini").mkdir()
    code, err = _run(capsys, *_export(platform_path, tmp_path / "k.hal"))
    assert code == 2 and err == [
        f"stewart-calib export: error: --out {tmp_path / 'k.ini'}: is a directory; expected a file path"
    ]
    assert not (tmp_path / "k.hal").exists() and list((tmp_path / "k.ini").iterdir()) == []


def test_export_writes_both_files_or_neither(tmp_path, platform_path, capsys):
    """``k.ini`` cannot be written (a FIFO no process reads, found only when it is written): no ``k.hal``."""
    os.mkfifo(tmp_path / "k.ini")
    code, err = _run(capsys, *_export(platform_path, tmp_path / "k.hal"))
    assert code == 2 and err == [
        f"stewart-calib export: error: {tmp_path / 'k.ini'}: cannot write (a FIFO no process reads)"
    ]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["P.toml", "k.ini"]


def test_an_output_through_a_link_writes_the_file_it_names(tmp_path, platform_path, capsys):
    target, link = tmp_path / "real.json", tmp_path / "link.json"
    target.write_text("old")
    link.symlink_to(target)
    assert _run(capsys, *_export(platform_path, link, "json"))[0] == 0
    assert link.is_symlink() and json.loads(target.read_text())["platform"] == "nim-stewart"


def test_an_output_naming_a_descriptor_is_written_into_it_not_replaced(tmp_path, platform_path):
    """``--out /dev/stdout`` (here a link of our own to ``/proc/self/fd/1``, the same name of the
    same descriptor, so that no failure touches the system's): the JSON reaches the command's
    standard output, redirected to a file, and the link stays a link."""
    link, captured = tmp_path / "stdout.json", tmp_path / "captured.json"
    link.symlink_to("/proc/self/fd/1")
    with open(captured, "wb") as stdout:
        done = subprocess.run(
            [sys.executable, "-m", "stewart_calib", *map(str, _export(platform_path, link, "json"))],
            stdout=stdout,
            stderr=subprocess.PIPE,
            cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            timeout=120,
        )
    assert done.returncode == 0, done.stderr
    assert link.is_symlink() and os.readlink(link) == "/proc/self/fd/1"
    assert json.loads(captured.read_text())["platform"] == "nim-stewart"


def test_an_output_fifo_with_a_reader_is_written_through(tmp_path, platform_path, capsys):
    fifo = tmp_path / "out.json"
    os.mkfifo(fifo)
    reader = os.open(fifo, os.O_RDONLY | os.O_NONBLOCK)  # a reader there before the write (the JSON fits the pipe)
    try:
        code, err = _run(capsys, *_export(platform_path, fifo, "json"))
        os.set_blocking(reader, True)
        received = b"".join(iter(lambda: os.read(reader, 1 << 16), b""))
    finally:
        os.close(reader)
    assert code == 0, err
    assert fifo.is_fifo() and json.loads(received)["platform"] == "nim-stewart"


def test_sweep_refuses_a_spec_inside_its_output_that_it_would_write(tmp_path, capsys):
    out = tmp_path / "study"
    out.mkdir()
    spec = out / "summary.md"  # a spec of any name: sweep writes DIR/summary.md
    shutil.copy(ROOT / "configs" / "sweeps" / "smoke.toml", spec)
    before = spec.read_bytes()
    code, err = _run(capsys, "sweep", "--spec", spec, "--out", out)
    assert code == 2 and err == [
        f"stewart-calib sweep: error: --out {spec}: is the --spec input; writing it would destroy it — "
        "expected another path"
    ]
    assert spec.read_bytes() == before and sorted(path.name for path in out.iterdir()) == ["summary.md"]


def test_every_write_refuses_an_input_of_the_command_by_identity(tmp_path):
    """The last line of defence, in the writer itself: a file the command reads, under another
    name (a hard link), is not replaced, whatever pipeline writes it."""
    from stewart_calib.errors import CalibError
    from stewart_calib.io import atomic_write_text, protected_inputs

    spec, other_name = tmp_path / "spec.toml", tmp_path / "plots.png"
    spec.write_text("keep")
    os.link(spec, other_name)
    with protected_inputs({str(spec): "--spec"}), pytest.raises(CalibError, match="is the --spec input"):
        atomic_write_text(other_name, "overwritten")
    assert spec.read_text() == "keep"
    atomic_write_text(other_name, "fine once the command is done")
    assert spec.read_text() == "keep"  # the name now holds a new file; the input's stays
