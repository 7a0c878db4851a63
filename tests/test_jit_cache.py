"""numba cannot write its cache (read-only site-packages and home): every command still works (issue 14).

The kernels compiled ahead of time at installation need no cache at all; these tests are about the
JIT path they fall back on, so they turn them off (``STEWART_CALIB_AOT=0``, stewart_calib._jit).

The test cannot make directories read-only for root, so it takes away numba's places instead:
``NUMBA_CACHE_LOCATOR_CLASSES`` leaves out the ``__pycache__`` beside the source (a read-only
site-packages) and the user-wide cache lives under a regular file (a home that cannot be
written), which fails for root too.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from stewart_calib import __version__
from tests.synthetic import ROOT

#: a small kernel is enough: the cache location is decided when each function is decorated.
CALL_A_KERNEL = (
    "import numpy as np; from stewart_calib.model import _kernels; print(_kernels.all_within(np.zeros(6), -1.0, 1.0))"
)


def _run(tmp_path, locators: str, *argv: str) -> subprocess.CompletedProcess:
    not_a_dir = tmp_path / "home-file"
    not_a_dir.write_text("")
    env = {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "NUMBA_CACHE_LOCATOR_CLASSES": locators,
        "XDG_CACHE_HOME": str(not_a_dir / "cache"),
        "HOME": str(not_a_dir),
        "TMPDIR": str(tmp_path / "tmp"),
        "STEWART_CALIB_AOT": "0",
    }
    env.pop("NUMBA_CACHE_DIR", None)
    (tmp_path / "tmp").mkdir(exist_ok=True)
    return subprocess.run([sys.executable, *argv], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("locators", ["UserWideCacheLocator", "UserProvidedCacheLocator,UserWideCacheLocator"])
def test_version_works_when_numba_cannot_write_its_cache(tmp_path, locators):
    done = _run(tmp_path, locators, "-m", "stewart_calib", "--version")
    assert (done.returncode, done.stdout.strip(), done.stderr) == (0, f"stewart-calib {__version__}", "")


def test_the_cache_falls_back_to_a_private_temporary_directory(tmp_path):
    done = _run(tmp_path, "UserProvidedCacheLocator,UserWideCacheLocator", "-c", CALL_A_KERNEL)
    assert (done.returncode, done.stdout.strip()) == (0, "True"), done.stderr
    cache = tmp_path / "tmp" / f"stewart-calib-numba-{os.getuid()}"
    assert oct(cache.stat().st_mode & 0o777) == "0o700"
    assert any(cache.rglob("*all_within*.nbi"))  # the compiled kernel was cached there


def test_without_any_writable_place_kernels_run_uncached(tmp_path):
    # only the user-wide locator, which cannot be written: not even the temporary directory helps
    done = _run(tmp_path, "UserWideCacheLocator", "-c", CALL_A_KERNEL)
    assert (done.returncode, done.stdout.strip()) == (0, "True"), done.stderr


class _Terminal:
    """Standard error as a terminal (or a pipe) that keeps what is written."""

    def __init__(self, tty: bool):
        self.tty, self.text = tty, ""

    def isatty(self) -> bool:
        return self.tty

    def write(self, text: str) -> None:
        self.text += text

    def flush(self) -> None:
        pass


@pytest.mark.parametrize("tty", [True, False])
def test_compiling_says_so_once_on_a_terminal_and_nothing_when_piped(monkeypatch, tty):
    from stewart_calib import _jit

    numba, _ = _jit.load_numba()  # what the first kernel to compile does: numba, with our listeners
    monkeypatch.setattr(_jit.COMPILE_NOTICE, "told", False)
    stderr = _Terminal(tty)
    monkeypatch.setattr(sys, "stderr", stderr)
    fresh = [numba.njit(lambda x, k=k: x + k) for k in range(2)]  # never cached: two compiles
    for kernel in fresh:
        kernel(1.0)
    assert stderr.text.count("compiling numeric kernels") == (1 if tty else 0)


#: compiles a kernel at level 0 (an empty cache: numba's compile event fires) and prints the level
#: numba's passes read as its compile starts (a listener registered after stewart_calib's) and after it
COMPILE_AT_LEVEL_0 = """
import numpy as np
from numba.core import config, event
from stewart_calib._jit import load_numba, njit

load_numba()  # stewart_calib's listeners first, as when a kernel compiles before this one

seen = []


class Watch(event.Listener):
    def on_start(self, e):
        seen.append(int(config.OPT))

    def on_end(self, e):
        pass


event.register("numba:compile", Watch())


@njit(opt=0)
def total(values):
    return values.sum()


total(np.ones(3))
print(seen[0], int(config.OPT))
"""


@pytest.mark.parametrize(("numba_opt", "expected"), [(None, "0 3"), ("2", "2 2")])
def test_a_kernel_compiles_at_its_own_optimisation_level(tmp_path, numba_opt, expected):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "STEWART_CALIB_AOT": "0"}
    env.pop("NUMBA_OPT", None)
    if numba_opt is not None:  # the user's explicit level wins
        env["NUMBA_OPT"] = numba_opt
    done = subprocess.run(
        [sys.executable, "-c", COMPILE_AT_LEVEL_0], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert (done.returncode, done.stdout.strip()) == (0, expected), done.stderr


def test_the_fk_kernels_compile_once_for_every_caller(tmp_path):
    """The tracker's FK runs inside the EKF's observation and inside the residual check of a log; the
    drives' geometry reaches both read-only and the cold start is no literal, so numba compiles the
    Newton solve and the single-pose FK once, not once per caller (issue 31: each costs seconds)."""
    script = (
        "import numpy as np\n"
        "from stewart_calib.model import _kernels, kinematics as kin\n"
        "from tests.synthetic import ROOT\n"
        "from stewart_calib.io.platform_file import load_platform\n"
        "p = load_platform(ROOT / 'configs' / 'platforms' / 'nim-stewart.toml')\n"
        "R, t = np.eye(3)[None], np.array([[0.0, 0.0, p.workspace.home[2]]])\n"
        "readings = kin.inverse_kinematics(p.tracker, R, t)\n"
        "strokes = kin.inverse_kinematics(p.drive, R, t)\n"
        "kin.tracker_reading_residuals(p.tracker, readings, [p.drive], [strokes])\n"
        "from stewart_calib.model.drive import drive_model\n"
        "from stewart_calib.estimators.measurement import LegSetPose\n"
        "from stewart_calib.instruments.tracker import TrackerModel\n"
        "pose = LegSetPose(TrackerModel(p.tracker, 1e-3), drive_model(p), 1e-3)\n"
        "pose.observe(np.zeros(42), np.concatenate((strokes[0], readings[0])))\n"
        "print(len(_kernels._newton.signatures), len(_kernels._fk_single.signatures))\n"
    )
    # an empty cache: a kernel loaded from the cache holds its callees' code, which then never compile
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "STEWART_CALIB_AOT": "0"}
    done = subprocess.run(
        [sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert (done.returncode, done.stdout.strip()) == (0, "1 1"), done.stderr


#: a kernel called once, its cache hits and misses printed; "changed": as after an edit of another kernel module
CACHE_HIT_OR_MISS = """
import sys
import numpy as np
from stewart_calib import _jit
if sys.argv[1:] == ["changed"]:
    digests = _jit.source_digests()
    digests["stewart_calib.estimators.kalman"] = "0" * 64
    _jit.source_digests = lambda: digests
from stewart_calib.model import _kernels
_kernels.all_within(np.zeros(6), -1.0, 1.0)
stats = _kernels.all_within.stats
print(sum(stats.cache_hits.values()), sum(stats.cache_misses.values()))
"""


def test_a_change_to_another_kernel_module_compiles_every_kernel_again(tmp_path):
    """numba keys a cached kernel on its own module's file alone, while its machine code holds the kernels
    it calls from other modules (robust.py's hold kalman.py's): after a change to one module only, its
    callers in others would run its old code from the cache. The key holds every kernel module's source."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path / "cache"), "STEWART_CALIB_AOT": "0"}

    def hits_and_misses(*argv: str) -> str:
        done = subprocess.run(
            [sys.executable, "-c", CACHE_HIT_OR_MISS, *argv], env=env, cwd=tmp_path, capture_output=True, text=True,
            timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    assert hits_and_misses() == "0 1"  # an empty cache: compiled
    assert hits_and_misses() == "1 0"  # the same sources: loaded
    assert hits_and_misses("changed") == "0 1"  # another module's source changed: compiled again
