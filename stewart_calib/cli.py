"""The ``stewart-calib`` command (also ``python -m stewart_calib``).

Each subcommand lives in its own module under :mod:`stewart_calib.pipelines` and exposes
``add_parser(subparsers)`` (registering its arguments and ``func``) and a ``main(argv)``
for scripts. A :class:`~stewart_calib.errors.CalibError` becomes one line on stderr and
exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import sys

from . import __version__
from .pipelines import Parser, add_subcommands, dispatch

#: subcommands, each the module of the same name in stewart_calib.pipelines.
SUBCOMMANDS = ("calibrate", "simulate", "reproduce", "track", "identifiability", "plan", "compensate", "import_bag", "validate", "sweep")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(
        prog="stewart-calib",
        description="Online kinematic calibration of a Stewart platform from an in-situ tracker.",
    )
    parser.add_argument("--version", action="version", version=f"stewart-calib {__version__}")
    add_subcommands(parser, SUBCOMMANDS)
    return parser


def main(argv: list[str] | None = None) -> int:
    return dispatch(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
