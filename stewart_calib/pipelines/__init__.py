"""What a user runs: one module per ``stewart-calib`` subcommand (``add_parser``, ``main``)."""

import argparse


def add_config_arguments(parser: argparse.ArgumentParser, example: str = "isam2.lag_s=5") -> None:
    """``--config C.toml`` and repeatable ``--set section.key=value`` (see ``load_estimator_config``)."""
    parser.add_argument("--config", metavar="C.toml", help="estimator config (default: configs/estimators/default.toml values)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help=f"override a config value, e.g. {example}"
    )
