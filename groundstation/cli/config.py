"""``groundstation config show``: print the effective configuration."""

from __future__ import annotations

import argparse

from groundstation.config import load_config, to_toml


def add_config_show_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML file with settings (tables as in the output)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override one setting"
    )


def run_config_show(args: argparse.Namespace) -> int:
    print(to_toml(load_config(args.config, args.set)), end="")
    return 0
