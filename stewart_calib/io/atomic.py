"""Atomic writes: a reader sees the old file or the whole new one, never a partial one.

Every write here goes through one check of where it lands (:func:`written_target`):

* a path through symbolic links writes the file they name (the links are kept), so two names
  of one file are one file — for the write and for :func:`exclusive_lock`;
* a device, FIFO or socket, and a name of an open descriptor (``/dev/stdout``, ``/dev/fd/N``,
  ``/proc/self/fd/N``), is written through, never replaced by a regular file: as root a rename
  onto ``/dev/stdout`` replaced the system's link;
* a directory is refused, and so is a file that is an input of the running command
  (:func:`protected_inputs`), by identity (device and inode), whatever its name.
"""

from __future__ import annotations

import fcntl
import os
import queue
import re
import shutil
import stat
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..errors import CalibError, shown

#: the files the running command reads, by identity ``(st_dev, st_ino)`` → the argument naming
#: them (:func:`protected_inputs`): a plain dict, not a context variable, so the writer thread of
#: :class:`BackgroundWriter` sees it too
_INPUTS: dict[tuple[int, int], str] = {}

#: names of an open descriptor of this process: writing one writes that descriptor
_DESCRIPTOR_NAMES = re.compile(
    r"/dev/(?:(?P<std>stdin|stdout|stderr)|fd/(?P<fd>\d+))|/proc/(?:self|thread-self|(?P<pid>\d+))/fd/(?P<pfd>\d+)"
)
_STANDARD = {"stdin": 0, "stdout": 1, "stderr": 2}


@contextmanager
def protected_inputs(files: dict[str, str]) -> Iterator[None]:
    """For the block, refuse any write here onto one of ``files`` (path → the argument that names
    it, e.g. ``"--platform"``): the regular files among them, by identity (any name or link of them)."""
    added: dict[tuple[int, int], str] = {}
    for path, option in files.items():
        try:
            now = os.stat(path)
        except (OSError, ValueError):
            continue
        if stat.S_ISREG(now.st_mode):
            added.setdefault((now.st_dev, now.st_ino), option)
    added = {key: option for key, option in added.items() if key not in _INPUTS}
    _INPUTS.update(added)
    try:
        yield
    finally:
        for key in added:
            _INPUTS.pop(key, None)


@dataclass(frozen=True)
class Target:
    """Where a write to :attr:`path` lands: :attr:`file`, the path with its links followed, is
    replaced; or, ``through``, a device, FIFO, socket or descriptor (:attr:`descriptor`) is written
    into as it is."""

    path: Path
    file: Path
    through: bool = False
    descriptor: int | None = None


def _followed(path: Path) -> tuple[Path, int | None]:
    """``path`` with its symbolic links followed (the last of a chain that ends nowhere yet
    included), and the descriptor it names when a link on the way is a descriptor's name."""
    here = os.path.abspath(path)
    for _ in range(40):  # the kernel's own limit on links followed
        head, name = os.path.split(here)
        here = os.path.join(os.path.realpath(head), name)
        named = _DESCRIPTOR_NAMES.fullmatch(here)
        if named and (named["pid"] is None or int(named["pid"]) == os.getpid()):
            number = _STANDARD[named["std"]] if named["std"] else int(named["fd"] or named["pfd"])
            return Path(here), number
        if not os.path.islink(here):
            break
        here = os.path.normpath(os.path.join(os.path.dirname(here), os.readlink(here)))
    return Path(here), None


def written_target(path: str | Path, option: str | None = None) -> Target:
    """Where a write to ``path`` lands (see the module), checked.

    Raises:
        CalibError: it is a directory, or an input of the running command (:func:`protected_inputs`);
            ``option`` (the argument naming ``path``) leads the message when given.
    """
    path = Path(path)
    file, descriptor = _followed(path)
    lead = f"{option} {shown(path)}" if option else shown(path)
    if descriptor is not None:
        return Target(path, file, True, descriptor)
    try:
        now = os.stat(file)
    except OSError:  # not there yet: made by the write (or its directory's check says why not)
        return Target(path, file)
    if stat.S_ISDIR(now.st_mode):
        raise CalibError(f"{lead}: is a directory; expected a file path")
    if not stat.S_ISREG(now.st_mode):
        return Target(path, file, True)
    reader = _INPUTS.get((now.st_dev, now.st_ino))
    if reader is not None:
        same = "" if reader == option else f" (as {shown(file)})" if file != path else ""
        raise CalibError(f"{lead}: is the {reader} input{same}; writing it would destroy it — expected another path")
    return Target(path, file)


def _write_through(target: Target, source: Path | bytes) -> None:
    """``source`` (a file's content, or bytes) written into the device, FIFO or descriptor ``target``."""
    try:
        if target.descriptor is not None:
            for stream in (sys.stdout, sys.stderr):
                if stream is not None and not stream.closed:
                    stream.flush()  # what was printed before comes first
            fd = os.dup(target.descriptor)
        else:  # a FIFO without a reader is refused here, not waited on for ever
            fd = os.open(target.file, os.O_WRONLY | os.O_NONBLOCK)
            os.set_blocking(fd, True)
    except OSError as err:
        why = "a FIFO no process reads" if err.errno == 6 else err.strerror or err.__class__.__name__  # ENXIO
        raise CalibError(f"{shown(target.path)}: cannot write ({why})") from None
    try:
        with os.fdopen(fd, "wb", closefd=True) as out:
            if isinstance(source, bytes):
                out.write(source)
            else:
                with open(source, "rb") as data:
                    shutil.copyfileobj(data, out)
    except OSError as err:
        raise CalibError(f"{shown(target.path)}: cannot write ({err.strerror or err.__class__.__name__})") from None


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
    target = written_target(path)
    fd, tmp = _temporary(target)
    os.close(fd)
    with _replaced_on_success(target, tmp):
        yield tmp


@contextmanager
def atomic_paths(paths: list[str | Path]) -> Iterator[list[Path]]:
    """Temporaries (as :func:`atomic_path`) for files written together: every one is renamed onto
    its path once the block succeeds (its files closed), every one removed when it fails — the
    files appear all or none (a disk that fills mid-run leaves none).

    Raises:
        CalibError: a file cannot be written (nothing is left behind).
    """
    targets = [written_target(path) for path in paths]
    temporaries: list[Path] = []
    try:
        for target in targets:
            fd, tmp = _temporary(target)
            os.close(fd)
            temporaries.append(tmp)
        yield temporaries
        for target in targets:  # checked again: the block may have taken long
            written_target(target.path)
        # the writes through (a device, a pipe) first: the one that can fail (a FIFO no process
        # reads) then leaves no file replaced; a rename, checked before, does not fail
        for tmp, target in sorted(zip(temporaries, targets, strict=True), key=lambda pair: not pair[1].through):
            if target.through:
                _write_through(target, tmp)
            else:
                os.chmod(tmp, 0o666 & ~_umask())
                os.replace(tmp, target.file)
    except BaseException as err:
        for tmp in temporaries:
            tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            where = err.filename or (targets[0].path.parent if targets else "")
            raise CalibError(f"{shown(where)}: cannot write ({err.strerror or err.__class__.__name__})") from None
        raise
    for tmp in temporaries:
        tmp.unlink(missing_ok=True)  # those written through


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
    target = written_target(path)
    if target.through:
        _write_through(target, data)
        return
    fd, tmp = _temporary(target)
    with _replaced_on_success(target, tmp):
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
    file = _followed(Path(path))[0]  # a link to the file is the file: one lock
    lock = file.parent / f".{file.name}.lock"
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


def _temporary(target: Target) -> tuple[int, Path]:
    """A new private file beside the file ``target`` replaces (``.<name>.<random>.tmp``), or in
    the temporary directory for one written through; open for writing."""
    file = target.file
    try:
        if target.through:
            fd, tmp = tempfile.mkstemp(prefix=f".{file.name}.", suffix=".tmp")
        else:
            fd, tmp = tempfile.mkstemp(dir=file.parent, prefix=f".{file.name}.", suffix=".tmp")
    except OSError as err:
        raise CalibError(f"{target.path}: cannot write ({err.strerror or err.__class__.__name__})") from None
    return fd, Path(tmp)


@contextmanager
def _replaced_on_success(target: Target, tmp: Path) -> Iterator[None]:
    """Rename ``tmp`` onto the target's file (or write it through) when the block succeeds;
    remove it in any case."""
    try:
        yield
        if target.through:
            _write_through(target, tmp)
        else:
            written_target(target.path)  # checked again: the block may have taken long
            os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it private; an output file should not be
            os.replace(tmp, target.file)
    except BaseException as err:
        if isinstance(err, OSError):
            raise CalibError(f"{target.path}: cannot write ({err.strerror or err.__class__.__name__})") from None
        raise
    finally:
        tmp.unlink(missing_ok=True)


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
