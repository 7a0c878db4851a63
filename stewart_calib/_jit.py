"""``njit``: numba's decorator with an on-disk cache wherever one can be written.

numba looks for a cache directory when a ``cache=True`` function is *decorated*, i.e. when
its module is imported, and raises ``RuntimeError: cannot cache function …`` when neither
``NUMBA_CACHE_DIR``, the ``__pycache__`` beside the source (read-only site-packages) nor the
user-wide cache (read-only home) can be written — so every command, ``--version``
included, would crash at import. :func:`njit` then points numba at a private directory in
the system's temporary directory, and when that cannot be made either, compiles without a
cache (each process pays the compile, a few seconds, instead of failing).

The first run after an installation compiles the kernels it uses (20–35 s of CPU for
``calibrate``, measured on 2 cores) before the cache makes every later run start in about a
second. On a terminal, :class:`CompileNotice` says so once, so the wait is not taken for a hang.
"""

from __future__ import annotations

import os
import stat
import sys
import tempfile
from pathlib import Path

import numba
from numba.core import config as numba_config
from numba.core import event as numba_event


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


def njit(**options):
    """``numba.njit(cache=True, **options)``, falling back to a private temporary cache
    directory and then to no cache when numba finds nowhere to write one (see the module)."""

    def decorate(func):
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

    return decorate


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
                "up to ~30 s; later runs load them from the cache)",
                file=sys.stderr,
                flush=True,
            )

    def on_end(self, event) -> None:
        pass


COMPILE_NOTICE = CompileNotice()
numba_event.register("numba:compile", COMPILE_NOTICE)
