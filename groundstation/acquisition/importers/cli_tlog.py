"""``groundstation import tlog SRC --out LOG.mcap``: MAVLink telemetry log -> MCAP."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="MAVLink telemetry log (.tlog)")
    parser.add_argument("--out", required=True, help="output recording (.mcap)")


def run(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.tlog import import_tlog

    report = import_tlog(
        args.src, args.out, created_by=f"groundstation import tlog {args.src} --out {args.out}"
    )
    print(report.describe())
    return 0
