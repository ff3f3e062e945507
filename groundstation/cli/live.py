"""``groundstation live --link URI [--mocap URI] [--joystick DEV] [--record FILE] [...]``

Starts every process of a live session under the supervisor, on one session bus
(:mod:`groundstation.runtime.session`), in this order::

    recorder (--record)  link  mocap (--mocap)  pilot (--joystick)  mapper  detector  viewer

(the detector and mapper when their modules are installed and ``--no-mapping`` is not given; the
viewer unless ``--no-viewer``: a window by default, ``--headless --out DIR`` for PNG/PLY files).
This process is only the operator's terminal: a monitor subscriber feeds
:class:`~groundstation.runtime.status.StatusBoard`, which prints one status line per second (rates
per stream, gaps, contacts, observations, refit time, mesh age, the pilot path -- a failsafe in
upper case with its reason) and, at once, warnings, errors and pilot faults.

Ctrl-C (or SIGTERM, or ``--duration``) stops the workers in reverse start order -- viewer,
detector, mapper, pilot (MANUAL_CONTROL stops: the vehicle's failsafe acts), sources -- and the
recorder last, which drains its queue and closes the file; the recording is then opened to check
that it is complete (exit 0) and its contents are summarised. ``--summary FILE`` writes the
session's measured numbers (refit time, mesh interval, contact-to-mesh latency, gaps) as JSON.

Ready handshake: the link and mocap processes wait for the monitor and the recorder on their
data topics, the pilot for the link, the monitor and the recorder on ``pilot.command``, so the
recording starts with sequence 0 of every source stream.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import signal
import sys
import time
from pathlib import Path

from groundstation.bus.pubsub import Subscriber
from groundstation.errors import ConfigError, GroundstationError
from groundstation.runtime.session import Session, load_settings, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.status import StatusBoard
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module

#: What the monitor subscribes to (every data topic of the sources, so that it is one of the
#: subscribers the sources wait for; large latest-value state such as meshes is decoded once).
MONITOR_TOPICS = (
    "raw.mavlink", "raw.natnet", "samples.imu", "samples.attitude", "samples.pose",
    "link.health", "status", "log", "pilot.command", "pilot.event", "contact.event",
    "observations", "mapper.fit", "mesh",
)  # fmt: skip
DETECTOR_MODULE = "groundstation.runtime.workers.detector"
MAPPER_MODULE = "groundstation.runtime.workers.mapper"
PILOT_MODULE = "groundstation.runtime.workers.pilot"
_DRAIN_MS = 300


def add_live_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation live``."""
    parser.add_argument("--link", required=True, help="firmware link: serial://... or udp://...")
    parser.add_argument("--mocap", default=None, help="mocap: natnet://239.255.42.99:1511")
    parser.add_argument("--joystick", default=None, metavar="DEV", help="/dev/input/js0 (or FIFO)")
    parser.add_argument("--record", default=None, metavar="FILE", help="MCAP file to write")
    view = parser.add_mutually_exclusive_group()
    view.add_argument("--no-viewer", action="store_true", help="do not start the viewer")
    view.add_argument("--headless", action="store_true", help="viewer writes PNG/PLY to --out")
    parser.add_argument("--out", default="live_view", help="--headless output folder")
    parser.add_argument(
        "--viewer",
        choices=("open3d", "rerun"),
        default="open3d",
        help="open3d: window or --headless files (default); rerun: Rerun's web viewer, served "
        "on --web-bind (127.0.0.1 by default) at the address printed",
    )
    from groundstation.cli.replay import add_viewer_arguments

    add_viewer_arguments(parser)
    parser.add_argument(
        "--no-mapping", action="store_true", help="do not start the detector and mapper"
    )
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    parser.add_argument("--summary", default=None, metavar="FILE", help="write numbers as JSON")
    parser.add_argument("--config", default=None, help="TOML configuration file")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )
    parser.add_argument("--session-root", default="/tmp", help="parent of the session directory")


def _available(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _check_config(args: argparse.Namespace) -> None:
    """Load the configuration once here, so a bad setting fails before any worker starts."""
    load_settings(args.config, args.set)


def plan(args: argparse.Namespace, session_id: str) -> tuple[Session, list[WorkerSpec]]:
    """The session and the worker specs of a live run, in start order (no side effects)."""
    cfg_file = ["--config", args.config] if args.config else []
    cfg = (*cfg_file, *[a for s in args.set for a in ("--set", s)])
    mapping = not args.no_mapping and _available(DETECTOR_MODULE) and _available(MAPPER_MODULE)
    names = ["recorder"] if args.record else []
    names += ["link"] + (["mocap"] if args.mocap else []) + (["pilot"] if args.joystick else [])
    names += ["mapper", "detector"] if mapping else []
    session = Session(session_id, tuple(names), args.session_root)
    rec = 1 if args.record else 0
    wait_sources = ("--wait-subscribers", str(1 + rec))  # the monitor (+ the recorder)
    specs: list[WorkerSpec] = []
    if args.record:
        sources = [args.link] + ([args.mocap] if args.mocap else [])
        specs.append(
            WorkerSpec(
                "recorder",
                python_module(
                    "groundstation.runtime.workers.recorder",
                    *session.as_args(),
                    "--out",
                    str(args.record),
                    "--created-by",
                    "groundstation live " + " ".join(sys.argv[1:]),
                    *[a for s in sources for a in ("--source", s)],
                    *cfg,
                ),
            )
        )
    specs.append(source_worker(args.link, session, "link", (*wait_sources, *cfg)))
    if args.mocap:
        specs.append(source_worker(args.mocap, session, "mocap", (*wait_sources, *cfg)))
    if args.joystick:
        specs.append(
            WorkerSpec(
                "pilot",
                python_module(
                    PILOT_MODULE,
                    *session.as_args(),
                    "--device",
                    args.joystick,
                    "--wait-subscribers",
                    str(2 + rec),
                    *cfg,
                ),
            )
        )
    if mapping:
        # The mapper starts first (it restores from the recording, then subscribes); the
        # detector's ready handshake covers observations and contact.event, which the mapper
        # does not hold, so it waits for the monitor (and the recorder).
        mapper_args = ["--recording", str(args.record)] if args.record else []
        specs.append(
            WorkerSpec(
                "mapper",
                python_module(MAPPER_MODULE, *session.as_args(), *mapper_args, *cfg),
                env=(("OPENBLAS_NUM_THREADS", "1"), ("OMP_NUM_THREADS", "1")),
            )
        )
        # --first-id auto: a detector restarted by the supervisor numbers on from the clock
        detector = ("--wait-subscribers", str(1 + rec), "--first-id", "auto", *cfg)
        specs.append(
            WorkerSpec("detector", python_module(DETECTOR_MODULE, *session.as_args(), *detector))
        )
    if not args.no_viewer:
        view = ["--headless", "--out", str(args.out)] if args.headless else []
        if args.viewer == "rerun":
            view = ["--viewer", "rerun", "--web-bind", args.web_bind, "--web-port",
                    str(args.web_port), "--grpc-port", str(args.grpc_port), *cfg]  # fmt: skip
            view += ["--rrd", str(args.rrd)] if args.rrd else []
        specs.append(
            WorkerSpec(
                "viewer",
                python_module(
                    "groundstation.cli",
                    "view",
                    "--session",
                    session.session_id,
                    "--session-root",
                    session.root,
                    "--publishers",
                    ",".join(session.publishers),
                    *view,
                ),
                max_restarts=3,
            )
        )
    return session, specs


def _err(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_live(args: argparse.Namespace) -> int:
    """Run the live session until Ctrl-C / SIGTERM / ``--duration``; 0 when it ended cleanly
    and the recording (if any) is complete."""
    _check_config(args)
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration {args.duration} must be > 0")
    session, specs = plan(args, new_session_id())
    if not args.no_mapping and "detector" not in [s.name for s in specs]:
        _err("live: detector/mapper not installed: running acquisition only")
    root = "" if session.root == "/tmp" else f" --session-root {session.root}"
    _err(
        f"live: session {session.session_id}; another viewer: groundstation view --session "
        f"{session.session_id}{root} --publishers {','.join(session.publishers)}"
    )
    stopping: list[int] = []
    old = {
        s: signal.signal(s, lambda n, f: stopping.append(n))
        for s in (signal.SIGINT, signal.SIGTERM)
    }
    sub = Subscriber(session.subscribe_endpoints(), MONITOR_TOPICS)
    sup = Supervisor(specs)
    t0 = time.monotonic_ns()
    board = StatusBoard(t0)
    end = math.inf if args.duration is None else t0 + args.duration * 1e9
    clean = True
    try:
        for ev in sup.start():
            _err(f"started {ev.name} ({ev.detail})")
        next_line = t0 + 1_000_000_000
        while not stopping and time.monotonic_ns() < end:
            env = sub.recv(50)
            now = time.monotonic_ns()
            if env is not None:
                for msg in board.ingest(env, now):
                    _err(msg)
            for ev in sup.poll():
                if ev.kind == "started":  # a restart: same line as at start-up
                    _err(f"started {ev.name} ({ev.detail})")
                else:
                    rc = "" if ev.returncode is None else f" {ev.returncode}"
                    _err(f"{ev.name} {ev.kind}{rc} {ev.detail}".rstrip())
                clean = clean and ev.kind not in ("gave_up",)
            if now >= next_line:
                board.set_gaps(sub.gaps)
                print(board.line(now, sup.alive()), flush=True)
                next_line = max(next_line + 1_000_000_000, now)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        _err("live: stopping (recorder last)")
        for ev in sup.stop():
            _err(f"stopped {ev.name} ({ev.detail})")
            clean = clean and ev.returncode == 0
        while (env := sub.recv(_DRAIN_MS)) is not None:  # the workers' final status
            board.ingest(env, time.monotonic_ns())
        board.set_gaps(sub.gaps)
        print("final: " + board.line(time.monotonic_ns(), {}), flush=True)
        sub.close()
        session.cleanup()
    summary = board.summary()
    ok = clean
    if args.record:
        summary["recording"] = _check_recording(args.record)
        ok = ok and summary["recording"].get("complete", False)
    _err("live summary: " + json.dumps(summary, default=str))
    if args.summary:
        Path(args.summary).write_text(json.dumps(summary, indent=1, default=str) + "\n")
    return 0 if ok else 1


def _check_recording(path: str) -> dict:
    """Open the recording without recovery: complete?, duration and per-topic counts."""
    from groundstation.acquisition.reader import open_recording

    try:
        with open_recording(path) as rec:
            s = rec.summary
            out = {"complete": not rec.truncated, "duration_s": s.duration_s,
                   "topic_counts": dict(s.topic_counts)}  # fmt: skip
    except GroundstationError as exc:
        _err(f"error: recording {path}: {exc.message}")
        return {"complete": False, "error": exc.message}
    counts = ", ".join(f"{k} {v}" for k, v in sorted(out["topic_counts"].items()))
    _err(f"recorded {path}: {out['duration_s']:.1f} s, {counts}")
    return out
