"""Where the shipped configs live: ``configs/`` at the repository root, installed inside the
package as ``stewart_calib/configs`` (a link in the source tree), so that a wheel finds them too.

A command's ``--platform``, ``--experiment`` or ``--config`` (and :func:`~stewart_calib.io.platform_file.load_platform`
and friends) take either a path or the name of a shipped file (spec §8): ``nim-stewart``,
``quick``, ``paper``. A path that exists always wins.
"""

import os
from importlib import resources
from pathlib import Path

from .errors import CalibError, shown
from .inputs import parse_toml, read_input_text

#: ``platforms/``, ``experiments/`` and ``estimators/`` TOML files.
CONFIGS = Path(str(resources.files("stewart_calib") / "configs"))


def shipped_names(kind: str) -> list[str]:
    """Names of the shipped files of ``kind`` (``"platforms"``, ``"experiments"``, ``"estimators"``)."""
    return sorted(path.stem for path in (CONFIGS / kind).glob("*.toml"))


def resolve(value: str | Path, kind: str) -> Path:
    """``value`` as a path when it is a file or names a directory; else the shipped file of that
    name (with or without ``.toml``) in ``configs/<kind>/`` when there is one — also where a bare
    name is a directory here (``simulate --experiment servo --out servo`` run a second time: the
    first run's output directory does not hide the shipped experiment); else ``value`` unchanged, for
    the caller's "not found" or "is a directory" message (see :func:`not_found_hint`)."""
    path = Path(value)
    if (path.exists() and not path.is_dir()) or len(path.parts) != 1:
        return path
    packaged = CONFIGS / kind / f"{path.name.removesuffix('.toml')}.toml"
    return packaged if packaged.is_file() else path


def not_found_hint(value: str | Path, kind: str) -> str:
    """For a bare name that is neither a file nor shipped, ``" (nor the name of a shipped file: a, b)"``:
    what the user may have meant; nothing for a path with a directory."""
    names = shipped_names(kind)
    return f" (nor the name of a shipped file: {', '.join(names)})" if names and len(Path(value).parts) == 1 else ""


def read_toml(value: str | Path, kind: str, what: str) -> tuple[Path, dict]:
    """The TOML document at ``value`` — a path or the name of a shipped file of ``kind`` — and its path.

    Raises:
        CalibError: one line naming the file: not found (with :func:`not_found_hint`), unreadable,
            or not valid TOML; ``what`` names the file's role (``"platform file"``).
    """
    path = resolve(value, kind)
    if not os.path.lexists(path):
        raise CalibError(f"{shown(path)}: {what} not found{not_found_hint(path, kind)}")
    return path, parse_toml(read_input_text(path, what), path)
