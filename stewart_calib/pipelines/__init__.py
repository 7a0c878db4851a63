"""What a user runs: one module per ``stewart-calib`` subcommand (``add_parser``, ``main``).

The command line itself (:mod:`stewart_calib.cli`) sits on top and lists the subcommands; the
pieces it shares with each pipeline's ``main(argv)`` live here, so nothing points back up.
"""

import argparse
import importlib
import sys

from ..errors import CalibError


class Parser(argparse.ArgumentParser):
    """``argparse`` whose usage errors are one line and exit 2, as every other refusal."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


def add_subcommands(parser: argparse.ArgumentParser, names) -> None:
    """Register the subcommands ``names``, each the module of that name in this package."""
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    for name in names:
        importlib.import_module(f".{name}", __name__).add_parser(sub)


def dispatch(args: argparse.Namespace) -> int:
    """Run the parsed subcommand: a :class:`CalibError` becomes one line on stderr and exit 2."""
    try:
        return int(args.func(args) or 0)
    except CalibError as err:
        print(f"stewart-calib {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stewart-calib {args.command}: interrupted", file=sys.stderr)
        return 130


def add_config_arguments(parser: argparse.ArgumentParser, example: str = "isam2.lag_s=5") -> None:
    """``--config C.toml`` and repeatable ``--set section.key=value`` (see ``load_estimator_config``)."""
    parser.add_argument("--config", metavar="C.toml", help="estimator config: a file or a shipped name (default, paper); default: default.toml values")
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help=f"override a config value, e.g. {example}"
    )


def run_command(name: str, argv: list[str] | None = None) -> int:
    """Run ``stewart-calib NAME ARGV…`` (``argv`` None: this process's arguments): each pipeline's ``main``."""
    parser = Parser(prog="stewart-calib")
    add_subcommands(parser, [name])
    return dispatch(parser.parse_args([name, *(sys.argv[1:] if argv is None else argv)]))
