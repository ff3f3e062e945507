"""``groundstation replay LOG [--speed max|X] [--out DIR] [--processes] [--set key=value ...]``

Runs the mapping pipeline on a recording. ``--speed max`` (default) uses the in-process
pipeline (``pipeline.offline``: fast, deterministic); ``--processes`` forces the multi-process
one (replay source, detector and mapper processes on a session bus; also used for any finite
``--speed X``). Both write the same outputs to ``--out`` (``pipeline.outputs``: mesh.ply,
observations.csv, report.json, snapshots/) and print a progress line on stderr and the report
summary on stdout. Settings: the configuration recorded with the log is the base (so a replay
reproduces the live detector and mapper; keys this version does not know are reported and
skipped), ``--config FILE`` and ``--set section.key=value`` apply on top (every section of
``groundstation config show``). ``LOG`` may be a session's first file or its folder: every
segment is replayed.

A damaged recording (corrupt chunks, a truncated file that lost data) is first checked chunk by
chunk; the replay then runs on what can be read, says what was dropped, and exits with status
:data:`EXIT_DAMAGED` unless ``--allow-damaged`` is given (then 0).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from groundstation.errors import ConfigError, InputDataError

#: Exit status of a replay that ran on a damaged recording without ``--allow-damaged``.
EXIT_DAMAGED = 3
#: Report keys printed on stdout (those present in the report).
REPORT_SUMMARY_KEYS = (
    "duration_s", "contacts", "contacts_per_min", "observations", "refits", "refit_s_median",
    "chamfer_m", "shape_error_m", "fp_precision", "fp_recall",
)  # fmt: skip


def _speed(text: str) -> float:
    if text == "max":
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--speed {text!r}: use 'max' or a number > 0") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"--speed {text!r}: use 'max' or a number > 0")
    return v


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log", help="recording (.mcap; SITL, live or imported), or a recorded session's folder"
    )
    parser.add_argument("--speed", type=_speed, default=math.inf, help="max (default) or X")
    parser.add_argument("--out", default=None, help="output folder (default: no files)")
    parser.add_argument(
        "--processes", action="store_true", help="run as processes on a bus (default: in process)"
    )
    parser.add_argument("--config", default=None, help="TOML configuration file")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )
    parser.add_argument("--snapshots", type=int, default=3, help="PNG snapshots of the last N fits")
    parser.add_argument("--timeout", type=float, default=1800.0, help="multi-process time limit, s")
    parser.add_argument("--quiet", action="store_true", help="no progress line")
    parser.add_argument(
        "--map",
        choices=("live", "final"),
        default="live",
        help="live: refit on the live cadence (default); final: detect over the whole log, then "
        "fit once on everything (fastest when only the final map matters)",
    )
    parser.add_argument(
        "--checkpoints",
        type=int,
        default=0,
        metavar="N",
        help="with --map final: also fit N times at evenly spaced log times",
    )
    parser.add_argument(
        "--allow-damaged",
        action="store_true",
        help=f"exit 0 even if the recording is damaged (default: exit {EXIT_DAMAGED})",
    )


def check_damage(log: Path) -> str | None:
    """Decode every chunk of ``log`` (every segment of a session) once; what was lost, or None
    for an intact recording.

    Raises
    ------
    RecordingError
        Not a recording at all (or unreadable).
    """
    import warnings

    from groundstation.acquisition.reader import TruncatedRecordingWarning, open_recording
    from groundstation.acquisition.segments import find_segments

    lost = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", TruncatedRecordingWarning)  # reported below instead
        segments = find_segments(log)
        for path in segments:
            with open_recording(path) as rec:
                rec.verify()
                if rec.damaged:
                    name = f"{path.name}: " if len(segments) > 1 else ""
                    lost.append(name + rec.damage_text())
    return "; ".join(lost) or None


def _progress_offline(quiet: bool):
    if quiet:
        return None

    def show(done: float, total: float, refits: int, contacts: int) -> None:
        end = "\n" if done >= total else "\r"
        print(
            f"replay: {done:6.1f}/{total:.1f} s of log, {contacts} contacts, {refits} refits",
            end=end,
            file=sys.stderr,
            flush=True,
        )

    return show


def _resolve(log: Path, args: argparse.Namespace):
    """The recorded configuration as the base, ``--config``/``--set`` on top (said on stderr)."""
    import warnings

    from groundstation.acquisition.segments import open_session
    from groundstation.runtime.configuration import recorded_base, resolve

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with open_session(log) as rec:
            tree, what = recorded_base(rec.metadata())
    resolved = resolve(args.config, args.set, base=tree, base_name=f"{log.name}: {what}")
    if not args.quiet:
        on_top = " with --config/--set on top" if (args.config or args.set) else ""
        base = f"{what}{on_top}" if what else f"defaults{on_top} (the log holds no configuration)"
        print(f"replay: settings: {base}", file=sys.stderr, flush=True)
        if resolved.skipped:
            print(
                "replay: recorded settings this version does not use, skipped: "
                + ", ".join(resolved.skipped),
                file=sys.stderr,
                flush=True,
            )
    return resolved


def run_replay(args: argparse.Namespace) -> int:
    log = Path(args.log)
    if not log.exists():
        raise InputDataError(f"recording {str(log)!r} does not exist")
    if args.snapshots < 0:
        raise ConfigError(f"--snapshots must be >= 0, got {args.snapshots}")
    config = _resolve(log, args).config  # once, here
    if args.checkpoints < 0:
        raise ConfigError(f"--checkpoints must be >= 0, got {args.checkpoints}")
    if args.map == "final" and (args.processes or math.isfinite(args.speed)):
        raise ConfigError(
            "--map final runs in process at full speed",
            hint="drop --processes and --speed, or use --map live",
        )
    damage = check_damage(log)
    if damage is not None:
        print(f"warning: recording {log.name} is damaged: {damage}", file=sys.stderr)
    if args.processes or math.isfinite(args.speed):
        from groundstation.pipeline.multiprocess import run_multiprocess

        def show(text: str) -> None:
            if not args.quiet:
                print(f"replay: {text}", file=sys.stderr, flush=True)

        result = run_multiprocess(
            str(log.resolve()),
            speed=args.speed,
            timeout_s=args.timeout,
            progress=show,
            config=config,
        )
    else:
        from groundstation.pipeline.offline import run_offline

        result = run_offline(
            str(log),
            config,
            progress=_progress_offline(args.quiet),
            map_mode=args.map,
            checkpoints=args.checkpoints,
        )
    from groundstation.pipeline.outputs import build_report, write_outputs

    report = (
        write_outputs(result, args.out, snapshots=args.snapshots)
        if args.out
        else build_report(result)
    )
    keys = REPORT_SUMMARY_KEYS
    parts = []
    for k in keys:
        if k in report:
            v = report[k]
            parts.append(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}")
    print(f"{result.mode} replay of {log.name}: " + ", ".join(parts))
    gaps = sum(v for v in result.gaps.values())
    if gaps:
        print(f"warning: {gaps} sequence gaps on the bus: {result.gaps}", file=sys.stderr)
    if damage is not None and not getattr(args, "allow_damaged", False):
        print(f"error: replayed a damaged recording: {damage}", file=sys.stderr)
        print(
            "hint: the outputs cover only what could be read; pass --allow-damaged to accept "
            "that (exit 0)",
            file=sys.stderr,
        )
        return EXIT_DAMAGED
    return 0
