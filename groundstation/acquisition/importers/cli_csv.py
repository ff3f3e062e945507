"""``groundstation import csv SRC --out LOG.mcap``: IMU CSV (aggressive_flight layout) -> MCAP."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="IMU CSV file (time, Euler_X/Y/Z, Acc_X/Y/Z, Gyr_X/Y/Z)")
    parser.add_argument("--out", required=True, help="output recording (.mcap)")
    parser.add_argument(
        "--gt", default=None, help="ground-truth CSV (default: GT.csv beside SRC, if present)"
    )
    parser.add_argument(
        "--pose",
        choices=("natnet", "mavlink"),
        default="natnet",
        help="encode positions as NatNet 4.1 frames (default) or MAVLink ATT_POS_MOCAP",
    )


def run(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.csv_imu import import_csv

    report = import_csv(
        args.src,
        args.out,
        gt_path=args.gt,
        pose_transport=args.pose,
        created_by=f"groundstation import csv {args.src} --out {args.out}",
    )
    print(report.describe())
    return 0
