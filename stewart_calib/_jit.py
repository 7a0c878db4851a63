"""``njit``: numba's decorator with an on-disk cache wherever one can be written.

numba looks for a cache directory when a ``cache=True`` function is *decorated*, i.e. when
its module is imported, and raises ``RuntimeError: cannot cache function …`` when neither
``NUMBA_CACHE_DIR``, the ``__pycache__`` beside the source (read-only site-packages) nor the
user-wide cache (read-only home) can be written — so every command, ``--version``
included, would crash at import. :func:`njit` then points numba at a private directory in
the system's temporary directory, and when that cannot be made either, compiles without a
cache (each process pays the compile, a few seconds, instead of failing).

The first run after an installation compiles the kernels it uses before the cache makes every
later run start in under a second; on a terminal, :class:`CompileNotice` says so once, so the wait
is not taken for a hang. What that compile costs, and the rules every kernel follows to keep it
small (issue 31; ``calibrate --method ekf`` on 120 samples, empty cache: 26.4–27.3 s of CPU before
them, 13.3–13.8 s after, same machine and load; peak 466 → 328 MB):

* every kernel goes through :func:`njit` (never ``numba.njit``): the cache fallbacks above, the
  notice, and LLVM level ``opt`` (:data:`OPT_LEVEL` = 1; :class:`OptimisationLevel`), which
  compiles in ~3/4 of level 3's time and ran as fast (ekf, track, validate, identifiability,
  compensate at 10⁵ samples, isam2 at 10⁴: equal CPU time). Ask for ``opt=3`` only where a
  measurement shows the kernel faster;
* no array-to-array slice assignment (``a[:] = b``, ``a[k, :] = b[j]``) in a kernel: numba compiles
  a formatted shape-mismatch message into each (string joins, ``str`` of ints: ~40 % of the compile
  before this rule). Copy element by element (``_kernels.copy_pose`` for a pose); filling with a
  scalar (``a[:] = 0.0``) is free. Likewise ``@``, ``np.dot`` and ``np.sum`` on the small arrays
  of a kernel compile BLAS glue (~1 s each): write the loop;
* one specialisation per kernel: numba compiles a kernel, and every kernel it calls, once per
  distinct argument type — C or A layout, int32 or int64, a writable or a read-only array, a
  literal or a variable. Python wrappers pass C-contiguous float64 arrays, Python floats and ints,
  and drive or tracker geometry read-only, as :class:`~stewart_calib.platform.LegGeometry` holds it;
  inside a kernel, a constant ``True``/``False`` or integer handed to another kernel is a
  ``Literal`` type of its own (``np.bool_(False)`` is not);
* every kernel called from Python is a compile of its own of its whole call tree (numba links and
  optimises the callees' code into each): add an entry point only where the Python side needs one.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
import weakref
from pathlib import Path
from typing import Any

import numba
from numba.core import config as _numba_config
from numba.core import event as numba_event

#: numba's options (CACHE_DIR, OPT) are set from the environment when it loads: its stubs list none
numba_config: Any = _numba_config

#: LLVM optimisation level of the kernels (:class:`OptimisationLevel`): level 1 instead of numba's 3
#: compiles in ~3/4 of the time, and the kernels ran as fast (measured: the module docstring).
OPT_LEVEL = 1


def _private_temporary_dir() -> str | None:
    """``<tmp>/stewart-calib-numba-<uid>``, made if needed; None unless it is a directory that
    this user owns and no one else can write (another user's cache would be code we run)."""
    path = Path(tempfile.gettempdir()) / f"stewart-calib-numba-{os.getuid()}"
    try:
        path.mkdir(mode=0o700, exist_ok=True)
        info = path.lstat()
        tempfile.TemporaryFile(dir=path).close()
    except OSError:
        return None
    if not stat.S_ISDIR(info.st_mode) or info.st_uid != os.getuid() or info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return None
    return str(path)


def njit(opt: int = OPT_LEVEL, **options):
    """``numba.njit(cache=True, **options)`` compiled at LLVM optimisation level ``opt``
    (:data:`OPT_LEVEL`; :class:`OptimisationLevel`), falling back to a private temporary cache
    directory and then to no cache when numba finds nowhere to write one (see the module)."""

    def decorate(func):
        dispatcher = _cached_njit(func, options)
        OPTIMISATION_LEVEL.levels[dispatcher] = opt
        return dispatcher

    return decorate


def _cached_njit(func, options: dict):
    try:
        return numba.njit(cache=True, **options)(func)
    except RuntimeError as err:
        if "cannot cache" not in str(err):
            raise
    fallback = _private_temporary_dir()
    if fallback is not None and numba_config.CACHE_DIR != fallback:
        numba_config.CACHE_DIR = fallback  # numba reads it for every later function too
        try:
            return numba.njit(cache=True, **options)(func)
        except RuntimeError as err:
            if "cannot cache" not in str(err):
                raise
    return numba.njit(cache=False, **options)(func)


class OptimisationLevel(numba_event.Listener):
    """numba optimises every function at ``NUMBA_OPT`` (default 3), one setting for the process. Our
    kernels' compiles (numba's ``numba:compile`` event, a cache miss, inside numba's compiler lock)
    run at their own level, with the numba functions they pull in; the level numba reads
    (``numba.core.config.OPT``, read at each pass manager it builds) is restored after. An explicit
    ``NUMBA_OPT`` in the environment wins."""

    def __init__(self):
        self.levels: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self._saved: list = []

    def on_start(self, event) -> None:
        self._saved.append(numba_config.OPT)
        level = self.levels.get(event.data["dispatcher"])
        if level is not None and "NUMBA_OPT" not in os.environ:
            numba_config.OPT = numba_config._OptLevel(level)

    def on_end(self, event) -> None:
        numba_config.OPT = self._saved.pop()


class CompileNotice(numba_event.Listener):
    """numba's ``numba:compile`` event fires only for a kernel not found in the cache: the first
    one a process compiles prints one line on standard error when that is a terminal (piped
    output stays quiet, as progress bars do)."""

    def __init__(self):
        self.told = False

    def on_start(self, event) -> None:
        if not self.told and sys.stderr.isatty():
            self.told = True
            print(
                "stewart-calib: compiling the numeric kernels for this machine (once after an installation, "
                "10–30 s; later runs load them from the cache)",
                file=sys.stderr,
                flush=True,
            )

    def on_end(self, event) -> None:
        pass


COMPILE_NOTICE = CompileNotice()
numba_event.register("numba:compile", COMPILE_NOTICE)
OPTIMISATION_LEVEL = OptimisationLevel()
numba_event.register("numba:compile", OPTIMISATION_LEVEL)
