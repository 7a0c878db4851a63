"""Shipped files by name (spec §8): ``--platform nim-stewart``, ``--experiment quick``,
``--config paper`` — from the checkout, and from a wheel installed in a fresh venv."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from stewart_calib.config import load_estimator_config
from stewart_calib.errors import CalibError
from stewart_calib.io.platform_file import load_platform
from stewart_calib.resources import CONFIGS, resolve
from stewart_calib.simulation.experiment import load_experiment

ROOT = Path(__file__).resolve().parents[1]


def test_names_load_the_shipped_files():
    by_name, by_path = load_platform("nim-stewart"), load_platform(ROOT / "configs" / "platforms" / "nim-stewart.toml")
    assert by_name.source.endswith("nim-stewart.toml")
    assert (by_name.drive.as_vector() == by_path.drive.as_vector()).all()
    assert load_platform("nim-stewart.toml").name == "nim-stewart"  # the README's spelling works too
    assert load_experiment("quick").name == load_experiment(ROOT / "configs" / "experiments" / "quick.toml").name
    assert load_estimator_config("paper") == load_estimator_config(CONFIGS / "estimators" / "paper.toml")


def test_an_existing_path_wins_over_a_shipped_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "paper").write_text("[ekf]\nprocess_noise_mm = 0.5\n")  # a local file of the same name
    assert resolve("paper", "estimators") == Path("paper")
    assert resolve("sub/paper", "estimators") == Path("sub/paper")  # a path with a directory is never a name


def test_an_unknown_name_lists_the_shipped_ones():
    with pytest.raises(
        CalibError,
        match=r"nim-stewrat: platform file not found "
        r"\(nor the name of a shipped file: hobby-hexapod, nim-stewart, servo-hexapod\)",
    ):
        load_platform("nim-stewrat")


def _build_wheel(tmp_path: Path) -> Path:
    """Build from a copy of the sources: setuptools writes build/ and *.egg-info beside them."""
    source = tmp_path / "source"
    source.mkdir()
    shutil.copy(ROOT / "README.md", source / "README.md")
    # No setup.py in the copy, so no AOT kernels to compile: the isolated build environment needs
    # setuptools and wheel alone, not numpy, numba, scipy and gtsam (installing those was most of
    # the build's time; the checkout's own install builds with the full list)
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    build_requires = re.search(r"^requires = \[.*\]$", pyproject, flags=re.MULTILINE)
    assert build_requires is not None and '"setuptools>=68", "wheel"' in build_requires[0]
    pure_requires = 'requires = ["setuptools>=68", "wheel"]'
    (source / "pyproject.toml").write_text(pyproject.replace(build_requires[0], pure_requires), encoding="utf-8")
    for name in ("stewart_calib", "configs"):
        shutil.copytree(ROOT / name, source / name, symlinks=True, ignore=shutil.ignore_patterns("__pycache__"))
    dest = tmp_path / "dist"
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", str(source), "-w", str(dest)],
        capture_output=True,
        text=True,
    )
    if build.returncode != 0 and "No matching distribution" in build.stderr:
        pytest.skip("building a wheel needs setuptools from a package index, which is not reachable")
    assert build.returncode == 0, build.stderr
    return next(dest.glob("stewart_calib-*.whl"))


def test_names_work_from_an_installed_wheel(tmp_path):
    """A fresh venv holding only the wheel (its dependencies come from this interpreter's
    site-packages through a .pth line, so nothing is downloaded), run outside the checkout."""
    wheel = _build_wheel(tmp_path)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # no checkout on the path
    subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps", str(wheel)],
        check=True,
        capture_output=True,
        env=env,
    )
    site = Path(
        subprocess.run(
            [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    (site / "shared-dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    work = tmp_path / "elsewhere"
    work.mkdir()

    def run(*argv):
        return subprocess.run(
            [str(venv / "bin" / "stewart-calib"), *argv],
            cwd=work,
            env=env,
            capture_output=True,
            text=True,
        )

    loaded = subprocess.run(
        [
            str(python),
            "-c",
            """
import stewart_calib
from stewart_calib.config import load_estimator_config
from stewart_calib.simulation.experiment import load_experiment
print(stewart_calib.__file__)
print(load_experiment("quick").platform.source)
print(load_estimator_config("paper").noise)
""",
        ],
        cwd=work,
        env=env,
        check=True,
        capture_output=True,
        text=True,
    ).stdout.splitlines()
    assert loaded[0].startswith(str(site)) and loaded[1].startswith(str(site))
    assert loaded[2] == str(load_estimator_config(CONFIGS / "estimators" / "paper.toml").noise)
    # the command line resolves names by the same function; one cheap command shows it
    planned = run("plan", "--platform", "nim-stewart", "--n", "7", "--out", "poses.csv")
    assert planned.returncode == 0, planned.stderr
    assert len((work / "poses.csv").read_text().splitlines()) == 1 + 7
    missing = run("simulate", "--experiment", "quik", "--out", "sim")
    assert missing.returncode == 2
    assert (
        "quik: experiment file not found (nor the name of a shipped file: "
        "paper, quick, servo, servo-points, tilted, warmup)" in missing.stderr
    )
