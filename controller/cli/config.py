"""`touchshape config show`: the effective configuration."""

from __future__ import annotations

import argparse
from pathlib import Path

from controller.config import config_to_toml, load_config


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `config show`."""
    config = groups.add_parser("config", help="show the effective configuration")
    commands = config.add_subparsers(dest="command", required=True)
    show = commands.add_parser("show", help="print the effective config as TOML")
    show.add_argument(
        "--config", type=Path, default=None, help="TOML config file (default: the sim bench)"
    )
    show.set_defaults(handler=_show)


def _show(args: argparse.Namespace) -> int:
    print(config_to_toml(load_config(args.config)), end="")
    return 0
