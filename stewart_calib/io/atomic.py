"""Atomic writes: a reader sees the old file or the whole new one, never a partial one."""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from ..errors import CalibError


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path in ``path``'s directory for the block to write; renamed onto ``path``
    (``os.replace``) when the block succeeds and removed when it fails, so readers see the old
    file or the whole new one, never a partial one.

    Raises:
        CalibError: the file cannot be written (nothing is left behind).
    """
    path = Path(path)
    fd, tmp = _temporary(path)
    os.close(fd)
    with _replaced_on_success(path, tmp):
        yield tmp


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`), through the temporary's own
    descriptor: ``track`` replaces its result and checkpoint every ``--every`` rows."""
    path = Path(path)
    fd, tmp = _temporary(path)
    with _replaced_on_success(path, tmp):
        try:
            rest = memoryview(data)
            while rest:
                rest = rest[os.write(fd, rest) :]
        finally:
            os.close(fd)


def _temporary(path: Path) -> tuple[int, Path]:
    """A new private file beside ``path`` (``.<name>.<random>.tmp``), open for writing."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        raise CalibError(f"{path}: cannot write ({err.strerror or err.__class__.__name__})") from None
    return fd, Path(tmp)


@contextmanager
def _replaced_on_success(path: Path, tmp: Path) -> Iterator[None]:
    """Rename ``tmp`` onto ``path`` when the block succeeds, remove it when it fails."""
    try:
        yield
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; an output file should not be
        os.replace(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise CalibError(f"{path}: cannot write ({err.strerror or err.__class__.__name__})") from None
        raise
