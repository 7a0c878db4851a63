"""What a user runs: one module per ``stewart-calib`` subcommand (``add_parser``, ``main``)."""

import argparse
import sys


def add_config_arguments(parser: argparse.ArgumentParser, example: str = "isam2.lag_s=5") -> None:
    """``--config C.toml`` and repeatable ``--set section.key=value`` (see ``load_estimator_config``)."""
    parser.add_argument("--config", metavar="C.toml", help="estimator config (default: configs/estimators/default.toml values)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help=f"override a config value, e.g. {example}"
    )


def run_command(name: str, argv: list[str] | None = None) -> int:
    """Run ``stewart-calib NAME ARGV…`` (``argv`` None: this process's arguments): each pipeline's ``main``."""
    from ..cli import main  # cli imports the pipelines

    return main([name, *(sys.argv[1:] if argv is None else argv)])
