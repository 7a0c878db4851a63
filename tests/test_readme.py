"""Every fenced ``bash`` and ``python`` snippet of README.md and of the how-to pages runs as written.

A page's snippets run in order in one directory (later ones use the files earlier ones write), as in
a fresh clone: it holds links to the checkout's ``configs/`` and ``examples/`` and nothing else. They
run in this process (an interpreter start per command would double the time):

* ``source .venv/bin/activate`` is not run (this interpreter is that venv);
* ``stewart-calib ARGS`` runs as ``stewart_calib.cli.main(ARGS)`` — ``.venv/bin/`` prefixes
  refer to the venv the set-up lines make, which is this one;
* ``python3 -m venv …`` and ``pip install -e …`` are not run (this interpreter is that venv),
  but the extras they name must exist in pyproject.toml;
* ``python -m pytest`` is not run (this is that run), but must name no missing path;
* ``reproduce`` is parsed by the real parser, not run: tests/test_reproduce.py runs it (its
  ``--quick`` form; the full one takes ~20 s alone); so is ``sweep`` (the smoke study starts a
  Dask cluster and takes about a minute; tests/test_sweep_dask.py runs small sweeps);
* ``track --follow --idle-timeout S`` is parsed as written and runs with :data:`IDLE_TIMEOUT_S`:
  the snippets' logs are whole before it starts, so the timeout only waits for rows that never
  come (5 s of nothing per page); every row is read and every file written as with S.

Every file a snippet reads is shipped (``examples/``, ``configs/``) or written by a snippet before it.

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
#: the site's pages whose commands run here (each in a directory of its own, as a reader starting on it)
HOWTOS = [ROOT / "docs" / "index.md"] + [
    ROOT / "docs" / "howto" / f"{name}.md"
    for name in (
        "motion-capture",
        "laser-tracker",
        "in-situ-tracker",
        "under-load",
        "cluster",
        "servo-platform",
        "temperature",
    )
]
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.S | re.M)
#: ``track --follow``'s idle timeout here [s]: the log is complete, so it only ends the wait at its end
IDLE_TIMEOUT_S = 0.2


def snippets(page: Path = README) -> list[tuple[str, str]]:
    """``(language, text)`` of every fenced bash / python block of ``page``, in order."""
    return [
        (m.group(1), m.group(2))
        for m in FENCE.finditer(page.read_text(encoding="utf-8"))
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


def _run(words: list[str]) -> None:
    program = words[0].removeprefix(".venv/bin/")
    args = words[1:]
    if words == ["source", ".venv/bin/activate"]:
        return
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
    if args[:1] == ["track"] and "--follow" in args and "--idle-timeout" in args:
        build_parser().parse_args(args)
        at = args.index("--idle-timeout") + 1
        args = [*args[:at], str(IDLE_TIMEOUT_S), *args[at + 1 :]]
    assert main(args) == 0, f"stewart-calib {' '.join(args)} failed (its message is in the captured stderr)"


def _run_page(page: Path, work: Path, monkeypatch) -> None:
    """Every snippet of ``page`` in order, in ``work``, which holds links to configs/ and examples/."""
    for shipped in ("configs", "examples"):
        if (ROOT / shipped).is_dir():
            (work / shipped).symlink_to(ROOT / shipped, target_is_directory=True)
    monkeypatch.chdir(work)
    for language, text in snippets(page):
        if language == "bash":
            for words in bash_commands(text):
                _run(words)
        else:
            exec(compile(text, f"{page.name} python snippet", "exec"), {"__name__": "__main__"})


def test_every_readme_snippet_runs_as_written(tmp_path, monkeypatch):
    found = snippets()
    assert any(language == "python" for language, _ in found) and any(language == "bash" for language, _ in found)
    _run_page(README, tmp_path, monkeypatch)


@pytest.mark.parametrize("page", HOWTOS, ids=lambda page: page.stem)
def test_every_howto_snippet_runs_as_written(page, tmp_path, monkeypatch):
    assert snippets(page), f"{page.name} has no bash or python snippet"
    _run_page(page, tmp_path, monkeypatch)


@pytest.mark.parametrize(
    "text, expected",
    [
        ("a b \\\n    c  # note\nd && e f", [["a", "b", "c"], ["d"], ["e", "f"]]),
        ("# only a comment\n", []),
    ],
)
def test_bash_commands_are_split_as_a_shell_would(text, expected):
    assert bash_commands(text) == expected


def _api_snippet() -> str:
    (text,) = [text for language, text in snippets() if language == "python" and "OnlineCalibrator" in text]
    return text


@pytest.mark.parametrize("instrument", ["tracker", "pose"])
def test_the_api_example_runs_for_the_tracker_and_a_pose_instrument(tmp_path, monkeypatch, instrument):
    """The README's Python API example on an in-situ tracker's log and, with the platform and log
    names changed, on a motion-capture log: it runs, and the checkpoint it saves resumes to the
    same compensated strokes."""
    import numpy as np

    from stewart_calib.io import write_log
    from stewart_calib.workflows.online import OnlineCalibrator
    from tests import synthetic

    text = _api_snippet()
    (tmp_path / "sim").mkdir()
    if instrument == "tracker":
        rng = np.random.default_rng(5)
        platform = synthetic.nim_stewart()
        log, _ = synthetic.make_log(
            platform, synthetic.random_error(rng), synthetic.random_poses(platform, 40, rng), rng, 0.002, 0.001
        )
    else:
        from stewart_calib.simulation.instrument import InstrumentTruth
        from tests import instrument_data

        case = instrument_data.make_case(
            instrument_data.hobby(), 60, 2, InstrumentTruth(np.r_[40.0, -25, 15, 5, -3, 30], np.zeros(6))
        )
        platform, log = case.platform, case.log
        assert 'load_platform("nim-stewart")' in text
        text = text.replace('load_platform("nim-stewart")', 'load_platform("hobby-hexapod")')
    write_log(tmp_path / "sim" / "log.csv", log, platform)
    monkeypatch.chdir(tmp_path)
    namespace = {"__name__": "__main__"}
    exec(compile(text, "README.md API snippet", "exec"), namespace)
    strokes = namespace["strokes_mm"]
    assert strokes.shape == (6,) and np.all(np.isfinite(strokes))
    resumed = OnlineCalibrator.load("state.npz", platform)
    np.testing.assert_array_equal(resumed.compensated_strokes(namespace["next_pose"]), strokes)


SECTION = re.compile(r"(?<![Pp]aper )(?<!paper's )§\s?(\d+)")


def _help_texts() -> str:
    """Every description and option help of ``stewart-calib`` and its commands."""
    import argparse

    parser = build_parser()
    texts = [parser.description or ""]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                texts.append(sub.description or "")
                texts += [a.help or "" for a in sub._actions]
            texts += [choice.help or "" for choice in action._choices_actions]
    return "\n".join(texts)


def test_every_section_reference_resolves():
    """§ references of the README, the commands' help and docs/formats.md itself name a section of
    docs/formats.md (the paper's sections, 'paper §4.1', are the paper's)."""
    formats = (ROOT / "docs" / "formats.md").read_text(encoding="utf-8")
    sections = {int(n) for n in re.findall(r"^## (\d+)\.", formats, re.M)}
    assert sections == set(range(1, max(sections) + 1))
    for name, text in {
        "README.md": README.read_text(encoding="utf-8"),
        "--help": _help_texts(),
        "formats": formats,
    }.items():
        cited = {int(n) for n in SECTION.findall(text)}
        assert cited, name
        assert cited <= sections, f"{name} cites § {sorted(cited - sections)}, which docs/formats.md does not have"
