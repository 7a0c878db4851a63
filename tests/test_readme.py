"""Every fenced ``bash`` and ``python`` snippet of README.md runs as written.

The snippets run in order in one directory (later ones use the files earlier ones write), as in
a fresh clone: it holds links to the checkout's ``configs/`` and ``examples/`` and nothing else. They
run in this process (an interpreter start per command would double the time):

* ``stewart-calib ARGS`` runs as ``stewart_calib.cli.main(ARGS)`` — ``.venv/bin/`` prefixes
  refer to the venv the set-up lines make, which is this one;
* ``python3 -m venv …`` and ``pip install -e …`` are not run (this interpreter is that venv),
  but the extras they name must exist in pyproject.toml;
* ``python -m pytest`` is not run (this is that run), but must name no missing path;
* ``reproduce`` is parsed by the real parser, not run: tests/test_reproduce.py runs it (its
  ``--quick`` form; the full one takes ~20 s alone); so is ``sweep`` (the smoke study starts a
  Dask cluster and takes about a minute; tests/test_sweep_dask.py runs small sweeps);
* a ROS bag a snippet reads is written beforehand with rosbags' writer (tests/test_import_bag.py).

A ``python`` block runs as a script (``runpy``-like ``exec``) in the same directory.
"""

from __future__ import annotations

import re
import shlex
import tomllib
from pathlib import Path

import pytest

from stewart_calib.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)


def snippets() -> list[tuple[str, str]]:
    """``(language, text)`` of every fenced bash / python block, in order."""
    return [
        (m.group(1), m.group(2))
        for m in FENCE.finditer(README.read_text(encoding="utf-8"))
        if m.group(1) in ("bash", "python")
    ]


def bash_commands(text: str) -> list[list[str]]:
    """The commands of a bash block: continuation lines joined, comments dropped, ``&&`` split."""
    joined = re.sub(r"\\\n\s*", " ", text)
    commands = []
    for line in joined.splitlines():
        words = shlex.split(line, comments=True)
        while words:
            cut = words.index("&&") if "&&" in words else len(words)
            commands.append(words[:cut])
            words = words[cut + 1 :]
    return commands


def _extras() -> set[str]:
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"])


def _check_pip_install(words: list[str]) -> None:
    assert words[:3] == ["pip", "install", "-e"] or words[:2] == ["pip", "install"], words
    for target in words[2:]:
        match = re.fullmatch(r"\.(?:\[([\w,-]+)\])?", target)
        if match and match.group(1):
            assert set(match.group(1).split(",")) <= _extras(), f"README installs unknown extras: {target}"


def _prepare_inputs(work: Path, words: list[str]) -> None:
    """Inputs a snippet assumes the user has: a ROS bag for import-bag."""
    if words[:1] == ["import-bag"]:
        from tests.test_import_bag import write_bag

        bag = work / words[1]
        if not bag.exists():
            write_bag(bag, "ros1" if bag.suffix == ".bag" else "ros2-sqlite3")


def _run(words: list[str], work: Path) -> None:
    program = words[0].removeprefix(".venv/bin/")
    args = words[1:]
    if program in ("python3", "python") and args[:2] == ["-m", "venv"]:
        return
    if program == "pip" or (program in ("python3", "python") and args[:2] == ["-m", "pip"]):
        _check_pip_install(["pip", *(args[2:] if program != "pip" else args)])
        return
    if program in ("python3", "python") and args[:2] == ["-m", "pytest"]:
        assert all((ROOT / a).exists() for a in args[2:] if not a.startswith("-")), args
        return
    if program == "python" and args[:1] == ["-m"] and args[1] == "benchmarks":
        return  # minutes long; tests/test_benchmarks_quick.py runs its --quick form
    assert program == "stewart-calib", f"README runs an unexpected program: {' '.join(words)}"
    if args[:1] in (["reproduce"], ["sweep"]):
        build_parser().parse_args(args)  # exits (SystemExit) on an option the command does not have
        return
    _prepare_inputs(work, args)
    assert main(args) == 0, f"stewart-calib {' '.join(args)} failed (its message is in the captured stderr)"


def test_every_readme_snippet_runs_as_written(tmp_path, monkeypatch):
    found = snippets()
    assert any(language == "python" for language, _ in found) and any(language == "bash" for language, _ in found)
    for shipped in ("configs", "examples"):
        if (ROOT / shipped).is_dir():
            (tmp_path / shipped).symlink_to(ROOT / shipped, target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    for language, text in found:
        if language == "bash":
            for words in bash_commands(text):
                _run(words, tmp_path)
        else:
            exec(compile(text, "README.md python snippet", "exec"), {"__name__": "__main__"})


@pytest.mark.parametrize(
    "text, expected",
    [
        ("a b \\\n    c  # note\nd && e f", [["a", "b", "c"], ["d"], ["e", "f"]]),
        ("# only a comment\n", []),
    ],
)
def test_bash_commands_are_split_as_a_shell_would(text, expected):
    assert bash_commands(text) == expected
