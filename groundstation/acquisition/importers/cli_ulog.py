"""``groundstation import ulog SRC --out LOG.mcap``: PX4 ULog -> MCAP."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="PX4 ULog file (.ulg)")
    parser.add_argument("--out", required=True, help="output recording (.mcap)")
    parser.add_argument(
        "--pose",
        choices=("natnet", "mavlink"),
        default="natnet",
        help="encode positions as NatNet 4.1 frames (default) or MAVLink ATT_POS_MOCAP",
    )


def run(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.ulog import import_ulog

    report = import_ulog(
        args.src,
        args.out,
        pose_transport=args.pose,
        created_by=f"groundstation import ulog {args.src} --out {args.out}",
    )
    print(report.describe())
    return 0
