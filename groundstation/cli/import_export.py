"""``groundstation import csv|ulog|tlog`` and ``groundstation export tlog``: outside recordings
into the station's MCAP layout, and a recording's MAVLink back out. A failed import leaves no
output file behind (``importers.atomic_output``) and prints ``error:``/``hint:``, exit 2.

- ``groundstation import csv SRC --out LOG.mcap``: IMU CSV (aggressive_flight layout) -> MCAP.
- ``groundstation import ulog SRC --out LOG.mcap [--time-limit S]``: PX4 ULog -> MCAP (pyulog
  runs under a time limit: a corrupted log that makes it loop is reported, not waited for).
- ``groundstation import tlog SRC --out LOG.mcap``: MAVLink telemetry log -> MCAP.
- ``groundstation export tlog LOG.mcap --out FILE.tlog``: a recording's MAVLink -> tlog.
- ``groundstation export foxglove OLD.mcap --out NEW.mcap``: a recording with the Foxglove
  channels (``groundstation.openformats.channels``) added.
"""

from __future__ import annotations

import argparse


def _out_arguments(parser: argparse.ArgumentParser, help_text: str) -> None:
    parser.add_argument("--out", required=True, help=help_text)
    parser.add_argument("--force", action="store_true", help="replace an existing --out file")


def _claim(args: argparse.Namespace) -> None:
    """An existing output is never overwritten without ``--force`` (error naming the file);
    a missing input is reported first, by the importer."""
    from pathlib import Path

    from groundstation.acquisition.segments import claim_output

    if Path(args.src).exists():
        claim_output(args.out, args.force)


def add_import_csv_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="IMU CSV file (time, Euler_X/Y/Z, Acc_X/Y/Z, Gyr_X/Y/Z)")
    _out_arguments(parser, "output recording (.mcap)")
    parser.add_argument(
        "--gt", default=None, help="ground-truth CSV (default: GT.csv beside SRC, if present)"
    )
    parser.add_argument(
        "--pose",
        choices=("natnet", "mavlink"),
        default="natnet",
        help="encode positions as NatNet 4.1 frames (default) or MAVLink ATT_POS_MOCAP",
    )


def run_import_csv(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.csv_imu import import_csv

    _claim(args)

    report = import_csv(
        args.src,
        args.out,
        gt_path=args.gt,
        pose_transport=args.pose,
        created_by=f"groundstation import csv {args.src} --out {args.out}",
    )
    print(report.describe())
    return 0


def add_import_ulog_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="PX4 ULog file (.ulg)")
    _out_arguments(parser, "output recording (.mcap)")
    parser.add_argument(
        "--pose",
        choices=("natnet", "mavlink"),
        default="natnet",
        help="encode positions as NatNet 4.1 frames (default) or MAVLink ATT_POS_MOCAP",
    )
    parser.add_argument(
        "--time-limit",
        type=float,
        default=None,
        metavar="S",
        help="stop pyulog after S seconds and report the file as unreadable "
        "(default: 20 s + 2 s per MB; pyulog can loop for ever on a corrupted log)",
    )


def run_import_ulog(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.ulog import import_ulog

    _claim(args)

    report = import_ulog(
        args.src,
        args.out,
        pose_transport=args.pose,
        created_by=f"groundstation import ulog {args.src} --out {args.out}",
        time_limit_s=getattr(args, "time_limit", None),
    )
    print(report.describe())
    return 0


def add_import_tlog_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="MAVLink telemetry log (.tlog)")
    _out_arguments(parser, "output recording (.mcap)")


def run_import_tlog(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.tlog import import_tlog

    _claim(args)

    report = import_tlog(
        args.src, args.out, created_by=f"groundstation import tlog {args.src} --out {args.out}"
    )
    print(report.describe())
    return 0


def add_export_tlog_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="recording (.mcap), or a recorded session's folder")
    _out_arguments(parser, "output telemetry log (.tlog)")
    parser.add_argument(
        "--no-mocap",
        action="store_true",
        help="do not convert NatNet poses to ATT_POS_MOCAP frames",
    )
    parser.add_argument(
        "--utc-start",
        default=None,
        metavar="ISO",
        help="UTC time of the first message (e.g. 2026-05-01T10:00:00Z); default: the "
        "recording's own clock (utc_offset_ns metadata, else the vehicle's SYSTEM_TIME, else "
        "the file's modification time as its end)",
    )


def _utc_seconds(text: str | None) -> float | None:
    if text is None:
        return None
    import datetime

    from groundstation.errors import ConfigError

    try:
        t = datetime.datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ConfigError(
            f"--utc-start {text!r} is not an ISO time", hint="e.g. 2026-05-01T10:00:00Z"
        ) from None
    if t.tzinfo is None:
        t = t.replace(tzinfo=datetime.UTC)
    return t.timestamp()


def run_export_tlog(args: argparse.Namespace) -> int:
    from groundstation.acquisition.importers.export_tlog import export_tlog

    start = _utc_seconds(args.utc_start)  # a bad option before anything touches the output
    _claim(args)
    report = export_tlog(args.src, args.out, natnet_as_mocap=not args.no_mocap, utc_start=start)
    print(report.describe())
    return 0


def add_export_foxglove_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("src", help="recording (.mcap) made before Foxglove channels existed")
    parser.add_argument("--out", required=True, help="new recording (.mcap) with them added")
    parser.add_argument("--config", default=None, help="TOML configuration file")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )


def run_export_foxglove(args: argparse.Namespace) -> int:
    """Copy a recording and add the Foxglove channels (groundstation.openformats.export)."""
    from groundstation.openformats.export import export_foxglove
    from groundstation.openformats.foxglove import FoxgloveTranslator
    from groundstation.runtime.configuration import resolve_for_log

    cfg = resolve_for_log(args.src, args.config, args.set, "export").config
    summary = export_foxglove(
        args.src,
        args.out,
        FoxgloveTranslator(cfg.contact, cfg.alignment),
        acquisition=cfg.acquisition,
        created_by=f"groundstation export foxglove {args.src} --out {args.out}",
    )
    how = " (samples decoded from the raw bytes)" if summary.decoded_samples else ""
    print(f"exported {args.src} -> {args.out}: {summary.copied} messages copied{how}")
    for topic, n in summary.foxglove.items():
        print(f"  {topic:<22} {n:>8}")
    if summary.skipped:
        print(f"  skipped {summary.skipped} (old Foxglove or unknown channels)")
    if summary.bad:
        print(f"  {summary.bad} malformed message(s) copied but not translated")
    return 0
