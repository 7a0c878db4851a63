"""The kernels compiled ahead of time at installation (setup.py; stewart_calib._jit, issue 31).

Every entry point is caught at its first call from Python while the README's commands run (so one
that no command reaches fails here too), then called again on copies of those arguments through
the AOT module and through numba's JIT: the same numbers to rounding (:func:`_rounding`). Arguments
that are not what an entry point declares, a missing module and a stale one all take the JIT path.
"""

from __future__ import annotations

import copy
import importlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from stewart_calib import _jit, cli
from stewart_calib.io.platform_file import load_platform
from tests.synthetic import ROOT

# every kernel module, so that ENTRY_POINTS (filled as they are imported) is whole when the tests below
# are parametrised over it
for _module in _jit.KERNEL_MODULES:
    importlib.import_module(_module)

pytestmark = pytest.mark.skipif(
    not _jit.aot_functions(),
    reason="no AOT module built from these kernel sources for this processor (pip install -e . builds it)",
)


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """A directory with the quick experiment's simulation in ``sim``."""
    root = tmp_path_factory.mktemp("aot")
    assert cli.main(["simulate", "--experiment", "quick", "--out", str(root / "sim")]) in (0, None)
    return root


def _log(root) -> list[str]:
    return ["--platform", str(root / "sim" / "platform.toml"), "--log", str(root / "sim" / "log.csv")]


@pytest.fixture(scope="module")
def first_calls(quick) -> dict[str, tuple]:
    """``{entry point: copies of its first call's arguments}`` over calibrate with ekf, isam2 (also with the
    tracker's geometry unknown) and ls, track, validate and simulate of the quick experiment, and
    :func:`_python_paths`."""
    calls = {}
    call = _jit.Kernel.__call__

    def record(kernel, *args, **kwargs):
        if kernel.entry is not None and kernel.name not in calls:
            calls[kernel.name] = _copy(args)
        return call(kernel, *args, **kwargs)

    commands = [
        *(
            ["calibrate", *_log(quick), "--method", m, "--config", "paper", "--out", str(quick / f"{m}.json")]
            for m in ("ekf", "isam2", "ls")
        ),
        ["track", *_log(quick), "--method", "ekf", "--config", "paper", "--out", str(quick / "track.json")],
        ["validate", *_log(quick), "--result", str(quick / "ekf.json"), "--out", str(quick / "V.csv")],
        ["simulate", "--experiment", "quick", "--out", str(quick / "again")],
        # the tracker's geometry identified: its rulers' compiled rows in the graph
        ["calibrate", *_log(quick), "--method", "isam2", "--config", "paper-tracker", "--out", str(quick / "t.json")],
    ]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(_jit.Kernel, "__call__", record)
        for argv in commands:
            assert cli.main(argv) in (0, None), argv
        _python_paths(load_platform(quick / "sim" / "platform.toml"))
    return calls


def _python_paths(platform) -> None:
    """What the quick commands leave to the Python paths that reproduce takes (the paper's EKF, an unknown
    tracker geometry, a filter without a compiled recursion, the true drive under load): one call each, at the
    home pose; and the robust filter's walk test, which needs two noise windows (the quick log has one)."""
    from stewart_calib.estimators import kalman, robust
    from stewart_calib.model import kinematics as kin
    from stewart_calib.model.unknowns import UnknownLayout
    from stewart_calib.resources import CONFIGS
    from stewart_calib.simulation import load_experiment
    from stewart_calib.simulation.load import Settling

    drive, R, t = platform.drive, np.eye(3), np.array([0.0, 0.0, platform.workspace.home[2]])
    strokes = kin.inverse_kinematics(drive, R[None], t[None])[0]
    rows = np.hstack([drive.base_joints, drive.platform_joints, drive.initial_lengths[:, None]])
    kin.leg_residual(R, t, rows, strokes)
    r, H, R_meas, _ = kin.leg_ekf_observation(drive, np.zeros(42), R, t, strokes, 1e-4 * np.eye(6), 0.01)
    state = kalman.FilterState("ekf", 1.0, 0.0, len(r), UnknownLayout(n_params=drive.n_params))
    kalman.fill_walk(state.Q, np.eye(42), 1e-4)
    state.update(H, -r, R_meas, 0.0)
    eigenvalues = np.full(84, 1e-3)
    robust._walk_rate_in_use(eigenvalues, 2.0 * eigenvalues, 1e-6, 0.7, 2.7)
    robust._contrast_terms(np.arange(3.0), np.ones((3, 2)), np.eye(3, 2), np.empty((2, 2)), np.empty((2, 2)))
    load = load_experiment(CONFIGS / "experiments" / "quick.toml").load
    Settling.of(load, drive.as_vector()).loaded_params(R[None], t[None], 0.0)


def test_a_calibration_imports_no_numba(quick, tmp_path):
    """Every kernel it runs is compiled already: numba (~0.2 s of CPU to import) is not loaded."""
    argv = ["calibrate", *_log(quick), "--method", "ekf", "--config", "paper", "--out", str(tmp_path / "r.json")]
    script = f"import sys\nfrom stewart_calib import cli\ncli.main({argv!r})\nprint('numba' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True)
    assert (done.returncode, done.stdout.split()[-1:]) == (0, ["False"]), done.stderr


def test_the_aot_calls_release_the_gil_as_the_kernels_declare():
    """Every entry point is ``nogil`` (the read-ahead thread's kernels run beside the filter's): pycc's
    wrappers release the GIL only when built so (setup.py), and then call ``PyEval_SaveThread``."""
    assert all(kernel.options.get("nogil") for kernel in _jit.ENTRY_POINTS.values())
    module = importlib.import_module(_jit.AOT_MODULE)
    assert b"PyEval_SaveThread" in Path(module.__file__).read_bytes()


def test_every_entry_point_is_reached(first_calls):
    assert set(first_calls) == set(_jit.ENTRY_POINTS)


@pytest.mark.parametrize("name", sorted(_jit.ENTRY_POINTS))
def test_the_aot_code_computes_what_the_jit_computes(first_calls, name):
    kernel, arguments = _jit.ENTRY_POINTS[name], first_calls[name]
    assert _jit.argument_check(kernel.entry)(*arguments)  # so the commands ran it through the AOT module
    by_jit, by_aot = _copy(arguments), _copy(arguments)
    returned_jit, returned_aot = kernel.dispatcher(*by_jit), _jit.aot_functions()[name](by_aot)
    outputs = [[np.asarray(x) for x in _leaves(run)] for run in ((returned_jit, by_jit), (returned_aot, by_aot))]
    for expected, actual in zip(*outputs, strict=True):
        assert actual.dtype == expected.dtype and actual.shape == expected.shape
        if expected.dtype.kind != "f":
            np.testing.assert_array_equal(actual, expected)
        else:
            finite = np.isfinite(expected)  # NaN and ±inf (a stiffness of inf: a rigid plate) where the JIT has them
            np.testing.assert_array_equal(actual[~finite], expected[~finite])
            scale = max(1.0, np.max(np.abs(expected[finite]), initial=0.0))
            np.testing.assert_allclose(actual[finite], expected[finite], rtol=0, atol=_rounding(kernel) * scale)


def _rounding(kernel) -> float:
    """How far two compiles of one kernel may round apart, relative to the larger of 1 and its output's
    magnitude (mm near 10³, unit vectors, innovations): ``fastmath`` reorders the filter's sums (1e-9, as the
    compiled and the Python recursion, tests/test_robust.py); otherwise 2⁻⁴⁰, a few ulps carried through a
    Newton solve (measured: 1 ulp on rotations, 1e-13 mm on a 1e-10 mm FK residual; bit for bit in a plain
    process, not always under pytest, for a reason not found)."""
    return 1e-9 if kernel.options.get("fastmath") else 2.0**-40


def _copy(value):
    """A deep copy that keeps each array's writability: numba compiles a read-only argument apart,
    and that other compile need not round alike."""
    if isinstance(value, tuple):
        return tuple(_copy(item) for item in value)
    if isinstance(value, np.ndarray):
        copied = value.copy(order="K")
        copied.setflags(write=value.flags.writeable)
        return copied
    return copy.copy(value)


def _leaves(value):
    if isinstance(value, tuple):
        for item in value:
            yield from _leaves(item)
    else:
        yield value


def test_arguments_other_than_declared_take_the_jit():
    from stewart_calib.model import _kernels

    values = np.array([0.0, -0.5, 2.0])
    aot = _jit.aot_functions()["stewart_calib.model._kernels.all_within"]
    assert aot((values, -1.0, 1.0)) is False
    for other in (values.astype(np.float32), np.repeat(values, 2)[::2], values.astype(int)):
        assert not _jit.F8_1.accepts(other)
        assert _kernels.all_within(other, -1.0, 1.0) is False  # the JIT's answer: nothing was misread
    frozen = values.copy()
    frozen.setflags(write=False)
    assert not _jit.F8_1.accepts(frozen) and _jit.RO_1.accepts(frozen) and _jit.RO_1.accepts(values)
    assert not _jit.F8_2.accepts(values) and not _jit.F8_2F.accepts(np.zeros((3, 3)))
    assert _jit.F8_2F.accepts(np.zeros((3, 2), order="F"))
    assert not _jit.INT.accepts(True) and not _jit.FLOAT.accepts(1) and _jit.FLOAT.accepts(np.float64(1.0))
    assert not _jit.LEGS.accepts((frozen, frozen, frozen))  # a 1-d array where a 2-d one is declared


#: a kernel called with the AOT module hidden or stale: prints its answer and whether numba compiled it
WITHOUT_AOT = """
import sys
import numpy as np
from stewart_calib import _jit
from stewart_calib.model import _kernels
{hide}
print(_kernels.all_within(np.array([0.5, -0.5]), -1.0, 1.0), len(_kernels.all_within.signatures))
"""
HIDDEN = """
class Hide:
    def find_spec(self, name, path, target=None):
        if name == _jit.AOT_MODULE:
            raise ImportError(name)
sys.meta_path.insert(0, Hide())
"""
STALE = "_jit.source_digests = lambda: {}"


@pytest.mark.parametrize("hide", [HIDDEN, STALE], ids=["missing", "stale"])
def test_without_a_usable_aot_module_kernels_compile_as_before(tmp_path, hide):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run(
        [sys.executable, "-c", WITHOUT_AOT.format(hide=hide)], env=env, cwd=tmp_path, capture_output=True, text=True
    )
    assert (done.returncode, done.stdout.split()) == (0, ["True", "1"]), done.stderr
