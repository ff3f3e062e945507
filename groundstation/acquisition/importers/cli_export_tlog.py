"""``groundstation export tlog LOG.mcap --out FILE.tlog``: a recording's MAVLink -> tlog."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="recording (.mcap)")
    parser.add_argument("--out", required=True, help="output telemetry log (.tlog)")
    parser.add_argument(
        "--no-mocap",
        action="store_true",
        help="do not convert NatNet poses to ATT_POS_MOCAP frames",
    )


def run(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.export_tlog import export_tlog

    report = export_tlog(args.src, args.out, natnet_as_mocap=not args.no_mocap)
    print(report.describe())
    return 0
