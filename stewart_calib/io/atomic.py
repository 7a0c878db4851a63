"""Atomic writes: a reader sees the old file or the whole new one, never a partial one."""

from __future__ import annotations

import fcntl
import os
import queue
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import CalibError, shown


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


@contextmanager
def atomic_paths(paths: list[str | Path]) -> Iterator[list[Path]]:
    """Temporaries (as :func:`atomic_path`) for files written together: every one is renamed onto
    its path once the block succeeds (its files closed), every one removed when it fails — the
    files appear all or none (a disk that fills mid-run leaves none).

    Raises:
        CalibError: a file cannot be written (nothing is left behind).
    """
    targets = [Path(path) for path in paths]
    temporaries: list[Path] = []
    try:
        for path in targets:
            fd, tmp = _temporary(path)
            os.close(fd)
            temporaries.append(tmp)
        yield temporaries
        for tmp, path in zip(temporaries, targets, strict=True):
            os.chmod(tmp, 0o666 & ~_umask())
            os.replace(tmp, path)
    except BaseException as err:
        for tmp in temporaries:
            tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            where = err.filename or (targets[0].parent if targets else "")
            raise CalibError(f"{shown(where)}: cannot write ({err.strerror or err.__class__.__name__})") from None
        raise


@contextmanager
def output_directory(path: str | Path, option: str = "--out") -> Iterator[Path]:
    """``path`` as the directory of the block's outputs: made (with missing parents) if it does not
    exist, and those made removed again when the block fails (empty then: its writes are atomic).

    Raises:
        CalibError: it cannot be made or written into (checked before the block's work).
    """
    path = Path(path)
    made, parent = [], path
    while not parent.exists() and parent != parent.parent:
        made.append(parent)
        parent = parent.parent
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CalibError(
            f"{option} {shown(path)}: cannot create the output directory ({err.strerror or err.__class__.__name__})"
        ) from None
    try:
        check_writable_directory(path, option)
        yield path
    except BaseException:
        for directory in made:
            try:
                directory.rmdir()
            except OSError:
                break
        raise


def check_writable_directory(directory: str | Path, option: str) -> None:
    """Refuse, before the work, a directory that is missing, not a directory, or not writable.

    Writable means a file can be made there: a private empty one is made and removed again. The
    permission bits (``os.access``) say yes to root wherever the file system, a mount, a network
    share's root squash or a security module would still refuse the write at the end.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise CalibError(f"{option}: directory {shown(directory)} does not exist")
    try:
        fd, probe = tempfile.mkstemp(dir=directory, prefix=".stewart-calib-probe.", suffix=".tmp")
    except OSError as err:
        reason = err.strerror or err.__class__.__name__
        raise CalibError(f"{option}: directory {shown(directory)} is not writable ({reason})") from None
    os.close(fd)
    os.unlink(probe)


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


@contextmanager
def exclusive_lock(path: str | Path, option: str, holder: str) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` for the block: a hidden ``.<name>.lock`` beside it
    (``flock``; ``path`` itself is replaced by each atomic write, so it cannot carry the lock),
    removed when the block ends.

    Raises:
        CalibError: another process holds it (``holder`` says who, ``option`` names the argument),
            or the lock cannot be made.
    """
    path = Path(path)
    lock = path.parent / f".{path.name}.lock"
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as err:
            raise CalibError(
                f"{option} {shown(path)}: cannot lock ({err.strerror or err.__class__.__name__})"
            ) from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise CalibError(f"{option} {shown(path)}: in use ({holder}; its lock {shown(lock)} is held)") from None
        try:  # the holder before may have removed the file between our open and lock: lock the one there now
            same = os.path.samestat(os.fstat(fd), os.stat(lock))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)  # while still held: a waiting run then locks a new file
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


class BackgroundWriter:
    """Atomic writes (:func:`atomic_write_bytes`) done in order on one thread of their own.

    ``track`` replaces its result and checkpoint every ``--every`` rows: encoding the result and
    the file system's create/write/rename took ~0.5–1 ms a write (more on a busy disk) that the
    rows waited for. Here they overlap with the estimator's compiled work, which releases the GIL.
    At most ``depth`` writes wait; a caller that gets ahead blocks until one is done.

    A write that fails (:class:`CalibError`, or any error of ``make_bytes``) is raised by the
    next :meth:`submit` or by :meth:`close`; the writes after it are not made. Use as a context
    manager: leaving it waits for every write (on an error too, so nothing is written after).
    """

    def __init__(self, depth: int = 2):
        self._jobs: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="stewart-calib writer", daemon=True)
        self._thread.start()

    def submit(self, path: str | Path, make_bytes: Callable[[], bytes]) -> None:
        """Write ``make_bytes()`` to ``path`` atomically after the writes submitted before.

        ``make_bytes`` runs on the writer's thread: it must not read state the caller goes on
        changing (build what is mutable first and close over the result).
        """
        self._raise_failure()
        self._jobs.put((path, make_bytes))

    def close(self) -> None:
        """Wait for the submitted writes; raise the first failure."""
        self._finish()
        self._raise_failure()

    def __enter__(self) -> BackgroundWriter:
        return self

    def __exit__(self, kind, value, traceback) -> None:
        if kind is None:
            self.close()
        else:  # the caller's error comes first; a write's failure would hide it
            self._finish()

    def _finish(self) -> None:
        if self._thread.is_alive():
            self._jobs.put(None)
            self._thread.join()

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            if self._error is None:
                path, make_bytes = job
                try:
                    atomic_write_bytes(path, make_bytes())
                except BaseException as err:  # handed to the caller's thread
                    self._error = err

    def _raise_failure(self) -> None:
        if self._error is not None:
            raise self._error
