"""The ``stewart-calib`` command (also ``python -m stewart_calib``).

Each subcommand lives in its own module under :mod:`stewart_calib.pipelines` (listed in
:data:`~stewart_calib.pipelines.COMMANDS`) and exposes ``add_parser(subparsers)`` (registering
its arguments and ``func``) and a ``main(argv)`` for scripts; only the module of the command
run is imported. A :class:`~stewart_calib.errors.CalibError` becomes one line on stderr and
exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import os
import sys

# Before numpy loads (a user's own setting wins): the commands' linear algebra is on matrices of
# at most ~50 × 50, where OpenBLAS's threads only add synchronisation: on a shared machine numpy's
# eigh of 48 × 48 is an order of magnitude slower with two threads than with one.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from . import __version__
from .pipelines import COMMANDS, Parser, add_subcommands, dispatch


def build_parser(load=None) -> argparse.ArgumentParser:
    """The command line; ``load``: the commands whose arguments it knows (default all; see
    :func:`~stewart_calib.pipelines.add_subcommands`)."""
    parser = Parser(
        prog="stewart-calib",
        description="Online kinematic calibration of a Stewart platform from an in-situ tracker.",
    )
    parser.add_argument("--version", action="version", version=f"stewart-calib {__version__}")
    add_subcommands(parser, load)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    # The top level takes no option with a value, so the first word is the command: only its
    # module is imported (start-up: stewart-calib --help imports no pipeline at all).
    command = next((word for word in argv if not word.startswith("-")), None)
    return dispatch(build_parser(load=[command] if command in COMMANDS else []).parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
