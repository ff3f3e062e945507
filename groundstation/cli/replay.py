"""``groundstation replay LOG [--speed max|X] [--start S] [--end S] [--out DIR] [--processes]
[--viewer rerun] [--set key=value ...]``

Runs the mapping pipeline on a recording. ``--speed max`` (default) uses the in-process
pipeline (``pipeline.offline``: fast, deterministic); ``--processes`` forces the multi-process
one (replay source, detector and mapper processes on a session bus; also used for any finite
``--speed X``). ``LOG`` may be a session's first file or its folder: every segment is
replayed. ``--start`` / ``--end`` replay only that window (seconds of log time from the start of
the recording; the decoders start cold at ``--start``). Both modes write the same outputs to
``--out`` (``pipeline.outputs``: mesh.ply, observations.csv, report.json, report.html,
replay.mcap, snapshots/) and print a progress line on stderr and the report summary on stdout.
``--viewer rerun`` streams the replay to Rerun's web viewer (``viewer.rerun_sink``) and keeps
serving it after the replay until Ctrl-C (or ``--serve-s``). Settings: the configuration
recorded with the log is the base (so a replay reproduces the live detector and mapper; keys
this version does not know are reported and skipped), ``--config FILE`` and ``--set
section.key=value`` apply on top (every section of ``groundstation config show``).

An MCAP file that is not a groundstation recording (no ``groundstation`` metadata and none of
its channels), or one without raw bytes to replay, is an error (exit 2), not an empty result.
A damaged recording (corrupt chunks, a truncated file that lost data) is first checked chunk by
chunk; the replay then runs on what can be read, says what was dropped, and exits with status
:data:`EXIT_DAMAGED` unless ``--allow-damaged`` is given (then 0).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import signal
import sys
import time
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


def _seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a time >= 0 s from the log start")
    return v


def add_viewer_arguments(parser: argparse.ArgumentParser) -> None:
    """``--web-bind``, ``--web-port``, ``--grpc-port``, ``--rrd`` of ``--viewer rerun``."""
    g = parser.add_argument_group("--viewer rerun (Rerun web view)")
    g.add_argument(
        "--web-bind",
        default="127.0.0.1",
        metavar="ADDR",
        help="address the web viewer and its stream listen on (default 127.0.0.1: this "
        "machine only; see the README to reach it from another machine)",
    )
    g.add_argument("--web-port", type=int, default=9090, help="web viewer HTTP port (0: any)")
    g.add_argument("--grpc-port", type=int, default=9876, help="Rerun stream port (0: any)")
    g.add_argument("--rrd", default=None, metavar="FILE", help="also save the stream to FILE.rrd")


def rerun_settings(args: argparse.Namespace):
    from groundstation.viewer.rerun_sink import RerunSettings

    return RerunSettings(
        bind=args.web_bind, web_port=args.web_port, grpc_port=args.grpc_port, rrd=args.rrd
    )


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "log", help="recording (.mcap; SITL, live or imported), or a recorded session's folder"
    )
    parser.add_argument("--speed", type=_speed, default=math.inf, help="max (default) or X")
    parser.add_argument(
        "--start",
        type=_seconds,
        default=None,
        metavar="S",
        help="replay from S seconds of log time after the start of the recording",
    )
    parser.add_argument(
        "--end",
        type=_seconds,
        default=None,
        metavar="S",
        help="replay up to S seconds of log time after the start of the recording",
    )
    parser.add_argument(
        "--out",
        default=None,
        help="output folder (default: no files): mesh.ply, observations.csv, report.json, "
        "report.html, replay.mcap, snapshots/",
    )
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
        help="live: refit on the live cadence (default); final: detect over the whole log, fit "
        "where the live mapper learns its kernel (each time the data grew by "
        "mapping.theta_refit_growth), then on everything (when only the final map matters)",
    )
    parser.add_argument(
        "--checkpoints",
        type=int,
        default=None,
        metavar="N",
        help="with --map final: fit N times at evenly spaced log times instead (0: only the "
        "final fit)",
    )
    parser.add_argument(
        "--allow-damaged",
        action="store_true",
        help=f"exit 0 even if the recording is damaged (default: exit {EXIT_DAMAGED})",
    )
    parser.add_argument(
        "--viewer",
        choices=("none", "rerun"),
        default="none",
        help="rerun: stream the replay to Rerun's web viewer and keep serving it afterwards",
    )
    parser.add_argument(
        "--serve-s",
        type=float,
        default=None,
        metavar="S",
        help="--viewer rerun: stop serving S seconds after the replay (default: at Ctrl-C)",
    )
    add_viewer_arguments(parser)


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
    from groundstation.runtime.configuration import resolve_for_log

    return resolve_for_log(log, args.config, args.set, "replay", quiet=args.quiet)


def _check_log(log: Path, start: float | None, end: float | None) -> tuple[int, float]:
    """Refuse a file that is not a station recording; (log start ns, window duration s)."""
    from groundstation.acquisition.reader import open_recording
    from groundstation.acquisition.segments import find_segments, open_session
    from groundstation.openformats.export import check_groundstation_recording

    if not log.exists():
        raise InputDataError(f"recording {str(log)!r} does not exist")
    if start is not None and end is not None and end <= start:
        raise ConfigError(f"--end {end} s must come after --start {start} s")
    with open_recording(find_segments(log)[0]) as rec:
        check_groundstation_recording(rec, need_raw=True)
    with open_session(log) as session:
        t0, duration = int(session.summary.start_ns or 0), session.summary.duration_s
    if start is not None and start >= duration:
        raise ConfigError(
            f"--start {start} s is past the end of {log.name} ({duration:.1f} s of log)"
        )
    window = min(duration, end if end is not None else duration) - (start or 0.0)
    return t0, window


class _WebView:
    """The Rerun server, stream and logger of ``--viewer rerun``."""

    def __init__(self, args: argparse.Namespace, config, t0_ns: int) -> None:
        from groundstation.viewer.rerun_sink import RerunLogger, RerunServer, open_stream

        settings = rerun_settings(args)
        self.server = RerunServer(settings)
        print(f"replay: Rerun web viewer at {self.server.web_url}", file=sys.stderr, flush=True)
        if self.server.exposure_warning:
            print(f"replay: {self.server.exposure_warning}", file=sys.stderr, flush=True)
        self.stream = open_stream(settings, self.server)
        self.logger = RerunLogger(
            self.stream, config.contact, config.alignment, t0_ns=t0_ns, settings=settings
        )

    def results(self, result) -> None:
        from groundstation.openformats.export import result_envelopes

        for env in result_envelopes(result):
            self.logger.ingest_envelope(env)
        self.logger.finish()
        self.stream.flush()

    def serve(self, seconds: float | None) -> None:
        """Serve until ``seconds`` pass, the server exits, or SIGINT / SIGTERM arrives. Both
        signals get this process's own handler for the while, whatever it inherited: a replay
        started as a shell's background job ignores SIGINT from birth and would otherwise serve
        on, and the default SIGTERM would end it without closing the stream and the .rrd."""
        how = "Ctrl-C to stop" if seconds is None else f"for {seconds:g} s"
        print(f"replay: serving {self.server.web_url} ({how})", file=sys.stderr, flush=True)
        end = math.inf if seconds is None else time.monotonic() + seconds
        stopped: list[int] = []
        previous = {
            sig: signal.signal(sig, lambda signum, _frame: stopped.append(signum))
            for sig in (signal.SIGINT, signal.SIGTERM)
        }
        try:
            while not stopped and time.monotonic() < end and self.server.proc.poll() is None:
                time.sleep(0.2)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if stopped:
            name = signal.Signals(stopped[0]).name
            print(f"replay: stopped serving ({name})", file=sys.stderr, flush=True)

    def close(self) -> None:
        try:
            self.stream.flush()
            self.stream.disconnect()
        finally:
            self.server.close()


def run_replay(args: argparse.Namespace) -> int:
    log = Path(args.log)
    if args.snapshots < 0:
        raise ConfigError(f"--snapshots must be >= 0, got {args.snapshots}")
    if args.checkpoints is not None and args.checkpoints < 0:
        raise ConfigError(f"--checkpoints must be >= 0, got {args.checkpoints}")
    if args.map == "final" and (args.processes or math.isfinite(args.speed)):
        raise ConfigError(
            "--map final runs in process at full speed",
            hint="drop --processes and --speed, or use --map live",
        )
    t0_ns, window_s = _check_log(log, args.start, args.end)
    config = _resolve(log, args).config  # once, here
    damage = check_damage(log)
    if damage is not None:
        print(f"warning: recording {log.name} is damaged: {damage}", file=sys.stderr)
    window = (args.start, args.end)
    command = "groundstation replay " + " ".join(sys.argv[2:] if sys.argv[1:2] == ["replay"]
                                                 else sys.argv[1:])  # fmt: skip
    web = _WebView(args, config, t0_ns) if args.viewer == "rerun" else None
    output = None
    try:
        if args.out:
            from groundstation.acquisition.segments import find_segments
            from groundstation.openformats.replay_output import ReplayOutput

            out = Path(args.out)
            out.mkdir(parents=True, exist_ok=True)
            window_ns = tuple(None if s is None else t0_ns + int(round(s * 1e9)) for s in window)
            first = find_segments(log)[0]
            output = ReplayOutput(out / "replay.mcap", first, config, window_ns, command)
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
                start=args.start,
                end=args.end,
            )
            if output is not None:
                output.samples_from_log(config.acquisition)
        else:
            from groundstation.pipeline.offline import run_offline
            from groundstation.pipeline.outputs import KEEP_MESHES

            taps = [t for t in (output and output.sample, web and web.logger.ingest_envelope) if t]

            def tap(env) -> None:
                for f in taps:
                    f(env)

            result = run_offline(
                str(log),
                config,
                progress=_progress_offline(args.quiet),
                keep_meshes=KEEP_MESHES if output is not None else 3,
                map_mode=args.map,
                checkpoints=args.checkpoints,
                start=args.start,
                end=args.end,
                tap=tap if taps else None,
            )
        result = dataclasses.replace(result, duration_s=window_s)
        if web is not None and (args.processes or math.isfinite(args.speed)):
            from groundstation.acquisition.replay import iter_replay

            for env in iter_replay(str(log), args.start, args.end, config.acquisition):
                web.logger.ingest_envelope(env)  # no in-process tap in this mode
        from groundstation.pipeline.outputs import build_report, write_outputs

        if args.out:
            report = write_outputs(
                result,
                args.out,
                snapshots=args.snapshots,
                replay_output=output,
                config=config,
                command=command,
                window_s=window,
            )
        else:
            report = build_report(result)
        parts = []
        for k in REPORT_SUMMARY_KEYS:
            if k in report:
                v = report[k]
                parts.append(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}")
        print(f"{result.mode} replay of {log.name}: " + ", ".join(parts), flush=True)
        if args.out:
            print(f"wrote {Path(args.out) / 'report.html'} and {Path(args.out) / 'replay.mcap'}")
        gaps = sum(v for v in result.gaps.values())
        if gaps:
            print(f"warning: {gaps} sequence gaps on the bus: {result.gaps}", file=sys.stderr)
        if web is not None:
            web.results(result)
            web.serve(args.serve_s)
    finally:
        if output is not None:
            output.close()  # no-op when write_outputs closed it
        if web is not None:
            web.close()
    if damage is not None and not getattr(args, "allow_damaged", False):
        print(f"error: replayed a damaged recording: {damage}", file=sys.stderr)
        print(
            "hint: the outputs cover only what could be read; pass --allow-damaged to accept "
            "that (exit 0)",
            file=sys.stderr,
        )
        return EXIT_DAMAGED
    return 0
