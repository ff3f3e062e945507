"""``groundstation view``: show the live mesh, flagged contacts and the vehicle.

Examples::

    groundstation view --connect tcp://127.0.0.1:5601,tcp://127.0.0.1:5602
    groundstation view --session 1a2b3c4d --headless --out results/view --every 5

    groundstation view --session 1a2b3c4d --viewer rerun --web-port 9090

A window (Open3D legacy Visualizer) by default; ``--headless`` writes ``snapshot_<fit>.png``
(the three-view renderer with metre axes that replay snapshots use; ``--renderer open3d`` for
an offscreen perspective render instead), ``mesh_<fit>.ply`` and ``points_<fit>.ply`` into
``--out`` for every ``--every``-th mesh. ``--viewer rerun`` serves Rerun's web viewer instead
(``viewer.rerun_sink``; bound to 127.0.0.1 unless ``--web-bind`` says otherwise) and prints the
address to open. Ctrl-C (SIGINT) or SIGTERM exits cleanly (status 0).
"""

from __future__ import annotations

import argparse
import os
import sys

from groundstation.errors import ConfigError
from groundstation.viewer.scene import ViewSettings


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_argument_group("where to listen (one of)")
    src.add_argument(
        "--connect",
        metavar="ENDPOINT[,ENDPOINT...]",
        help="publisher endpoints, comma-separated (e.g. tcp://127.0.0.1:5601)",
    )
    src.add_argument("--session", help="session id: connect to every publisher of that session")
    src.add_argument("--session-root", default="/tmp", help="parent of the session directory")
    src.add_argument(
        "--publishers", default=None, help="publishing processes of the session (comma-separated)"
    )
    src.add_argument("--server-key", metavar="FILE", help="CURVE public key file of the publishers")
    out = parser.add_argument_group("sink")
    out.add_argument(
        "--viewer",
        choices=("open3d", "rerun"),
        default="open3d",
        help="open3d: window or --headless files (default); rerun: Rerun's web viewer",
    )
    out.add_argument("--headless", action="store_true", help="write PNG/PLY files, no window")
    out.add_argument("--out", default="view_out", help="output folder for --headless")
    out.add_argument("--every", type=int, default=1, help="--headless: every N-th mesh")
    out.add_argument(
        "--renderer",
        choices=("auto", "open3d", "matplotlib"),
        default="matplotlib",
        help="--headless PNG renderer: matplotlib (default) three views with metre axes, as "
        "replay snapshots; open3d an offscreen perspective render; auto open3d, else matplotlib",
    )
    out.add_argument("--max-snapshots", type=int, default=0, help="--headless: stop after N")
    out.add_argument("--width", type=int, default=None, help="pixels (960 headless, 1280 window)")
    out.add_argument("--height", type=int, default=None, help="pixels (720 headless, 800 window)")
    out.add_argument("--fps", type=float, default=25.0, help="window frame rate")
    what = parser.add_argument_group("what to show")
    what.add_argument("--trajectory-s", type=float, default=10.0, help="trajectory length (s)")
    what.add_argument("--max-observations", type=int, default=20000, help="points kept")
    what.add_argument("--show-internal", action="store_true", help="draw internal points")
    what.add_argument("--show-external", action="store_true", help="draw external points")
    what.add_argument("--std-range", metavar="LO,HI", help="fixed std colour range")
    what.add_argument("--config", default=None, help="TOML configuration (--viewer rerun: the "
                      "detector threshold and filter of the signal plot)")  # fmt: skip
    what.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )
    from groundstation.cli.replay import add_viewer_arguments

    add_viewer_arguments(parser)


def _endpoints(args: argparse.Namespace) -> list[str]:
    if bool(args.connect) == bool(args.session):
        raise ConfigError(
            "give exactly one of --connect ENDPOINT[,...] or --session ID",
            hint="e.g. groundstation view --connect tcp://127.0.0.1:5601",
        )
    if args.connect:
        eps = [e.strip() for e in args.connect.split(",") if e.strip()]
        if not eps:
            raise ConfigError(f"--connect {args.connect!r} names no endpoint")
        return eps
    from groundstation.runtime.session import Session

    # Fail fast on a session that does not exist (a typo would otherwise wait forever); its
    # session.json also lists every publisher (the mapper's meshes among them).
    session = Session.find(args.session, args.session_root)
    if args.publishers:
        pubs = tuple(p for p in args.publishers.split(",") if p)
        session = Session(session.session_id, pubs, session.root)
    return session.subscribe_endpoints()


def _settings(args: argparse.Namespace) -> ViewSettings:
    std_range = None
    if args.std_range:
        try:
            lo, hi = (float(x) for x in args.std_range.split(","))
        except ValueError:
            raise ConfigError(
                f"--std-range {args.std_range!r} must be LO,HI (two numbers)"
            ) from None
        std_range = (lo, hi)
    if args.every < 1:
        raise ConfigError(f"--every {args.every} must be >= 1")
    return ViewSettings(
        trajectory_window_s=args.trajectory_s,
        max_observations=args.max_observations,
        show_internal=args.show_internal,
        show_external=args.show_external,
        std_range=std_range,
    )


def _make_sink(args: argparse.Namespace):
    if args.headless:
        from groundstation.viewer.headless import HeadlessSink

        return HeadlessSink(
            args.out,
            width=args.width or 960,
            height=args.height or 720,
            backend=args.renderer,
            warn=_stderr,
        )
    from groundstation.viewer.window import WindowSink

    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        _stderr("viewer: no display; the window is drawn offscreen (use --headless for files)")
    return WindowSink(
        width=args.width or 1280, height=args.height or 800, echo=lambda s: print(s, flush=True)
    )


def _run_rerun(args: argparse.Namespace, endpoints: list[str], key: bytes | None) -> int:
    """``--viewer rerun``: Rerun's server + the bus -> Rerun loop until Ctrl-C / SIGTERM."""
    import signal

    from groundstation.cli.replay import rerun_settings
    from groundstation.config import load_config
    from groundstation.runtime.session import StopSignals
    from groundstation.runtime.workers.rerun_viewer import RerunViewerProcess
    from groundstation.viewer.rerun_sink import RerunLogger, RerunServer, open_stream

    cfg = load_config(args.config, args.set)
    settings = rerun_settings(args)
    server = RerunServer(settings)
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        stream = open_stream(settings, server)
        logger = RerunLogger(stream, cfg.contact, cfg.alignment, settings=settings)
        proc = RerunViewerProcess(endpoints, logger, stop=StopSignals(), server_public_key=key)
        _stderr(f"viewer: Rerun web viewer at {server.web_url}")
        if server.exposure_warning:
            _stderr(f"viewer: {server.exposure_warning}")
        _stderr(f"viewer: listening on {', '.join(endpoints)}")
        status = proc.run()
        stream.flush()
        stream.disconnect()
        _stderr(proc.summary())
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        server.close()
    return status


def run_view(args: argparse.Namespace) -> int:
    import signal

    from groundstation.bus.security import check_endpoint
    from groundstation.runtime.session import StopSignals
    from groundstation.runtime.workers.viewer import ViewerProcess

    endpoints = _endpoints(args)
    for ep in endpoints:
        check_endpoint(ep)
    settings = _settings(args)
    key = None
    if args.server_key:
        from groundstation.bus.security import CurveKeys

        key = CurveKeys.load(args.server_key).public
    if args.viewer == "rerun":
        return _run_rerun(args, endpoints, key)
    sink = _make_sink(args)
    try:
        proc = ViewerProcess(
            endpoints,
            sink,
            settings=settings,
            every=args.every,
            fps=args.fps,
            max_snapshots=args.max_snapshots or None,
            server_public_key=key,
        )
    except BaseException:
        sink.close()
        raise
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    proc.stop = StopSignals()  # Ctrl-C / SIGTERM end the loop cleanly
    try:
        _stderr(f"viewer: listening on {', '.join(endpoints)}")
        status = proc.run()
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    _stderr(proc.summary())
    return status
