"""The ``stewart-calib`` command (also ``python -m stewart_calib``).

Each subcommand lives in its own module under :mod:`stewart_calib.pipelines` and exposes
``add_parser(subparsers)`` (registering its arguments and ``func``) and a ``main(argv)``
for scripts. A :class:`~stewart_calib.errors.CalibError` becomes one line on stderr and
exit status 2 — never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import __version__
from .errors import CalibError

#: subcommands, each the module of the same name in stewart_calib.pipelines.
SUBCOMMANDS = ("calibrate", "simulate", "reproduce", "track", "identifiability", "plan", "compensate", "import_bag")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit 2, as for every other refusal
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="stewart-calib",
        description="Online kinematic calibration of a Stewart platform from an in-situ tracker.",
    )
    parser.add_argument("--version", action="version", version=f"stewart-calib {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for module_name in SUBCOMMANDS:
        importlib.import_module(f".pipelines.{module_name}", __package__).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except CalibError as err:
        print(f"stewart-calib {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stewart-calib {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
