"""``groundstation live --link URI [--mocap URI] [--joystick DEV] [--record FILE] [...]``

Starts every process of a live session under the supervisor, on one session bus
(:mod:`groundstation.runtime.session`), in this order::

    recorder, recorder2 (--record)  link  mocap (--mocap)  pilot (--joystick)  mapper  detector
    viewer

(the detector and mapper when their modules are installed and ``--no-mapping`` is not given; the
viewer unless ``--no-viewer``: a window by default, ``--headless --out DIR`` for PNG/PLY files).
The configuration is resolved once here (``--config``, ``--set``) and written to the session
directory, where every worker reads it; the recorders store it whole in the recording. The two
recorders are an active/standby pair (:mod:`groundstation.runtime.workers.recorder`): a killed
recorder is replaced at once by the other, in a new segment, nothing erased. An existing
recording is never replaced without ``--force``.

This process is only the operator's terminal: a monitor subscriber feeds
:class:`~groundstation.runtime.status.StatusBoard`, which prints one status line per second
(rates per stream, gaps, contacts, observations, refit time, mesh age, the pilot path) and, in
upper case, everything that is wrong (:mod:`groundstation.runtime.alerts`: a worker restarting,
a silent stream, MAVLink frame loss, a missing device, a stale map, a recorder behind, ...);
warnings, errors and pilot faults are printed at once.

Ctrl-C (or SIGTERM, or ``--duration``) stops the workers in reverse start order -- viewer,
detector, mapper, pilot (MANUAL_CONTROL stops: the vehicle's failsafe acts), sources -- and the
recorders last, which drain their queue and close the file; the recording is then opened to
check it and its contents are summarised. The closing summary lists every condition the status
line showed and what data was lost; the exit code is 0 only when the session ended cleanly and
lost nothing (1 otherwise). ``--summary FILE`` writes the summary as JSON.

Workers run in one process group owned by this process and die with it (parent-death signal):
a SIGKILLed ``live`` leaves no worker behind.

``--signing-key FILE`` (32 raw bytes or 64 hex characters) signs every frame the link process
sends to the vehicle with MAVLink 2 signing (``acquisition.signing_key_file``); a vehicle (or
``groundstation sitl --signing-key FILE``) holding the same key then rejects unsigned commands.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import queue
import signal
import sys
import threading
import time
from pathlib import Path

from groundstation.bus.pubsub import Subscriber
from groundstation.errors import ConfigError, GroundstationError
from groundstation.runtime.alerts import Alerts, AlertSettings
from groundstation.runtime.configuration import (
    CONFIG_FILE,
    Resolved,
    resolve,
    write_session_config,
)
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.status import StatusBoard
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module

#: Priority changes (nice) asked for: the acquisition and pilot path get more CPU share than the
#: rest of a loaded machine, the recorders and the detector a little (a privilege; without it
#: they say so). The detector must keep up with 200 Hz samples or every contact is late (the
#: 10-minute load soak at nice 0: 170 s behind at the end); the mapper and the viewer degrade
#: by skipping refits and frames instead.
NICE = {"link": -5, "mocap": -5, "pilot": -5, "recorder": -3, "recorder2": -3, "detector": -3}
#: What the monitor subscribes to: the samples (so that it is one of the subscribers the sources
#: wait for) and the state and events it shows; not the raw wire bytes, which only the recorders
#: need (decoding them here would cost the terminal a third of its CPU for nothing).
MONITOR_TOPICS = (
    "samples.imu", "samples.attitude", "samples.pose",
    "link.health", "status", "log", "pilot.command", "pilot.event", "contact.event",
    "observations", "mapper.fit", "mesh",
)  # fmt: skip
DETECTOR_MODULE = "groundstation.runtime.workers.detector"
MAPPER_MODULE = "groundstation.runtime.workers.mapper"
PILOT_MODULE = "groundstation.runtime.workers.pilot"
RECORDER_MODULE = "groundstation.runtime.workers.recorder"
VIEWER_MODULE = "groundstation.runtime.workers.viewer"
RECORDERS = ("recorder", "recorder2")
_DRAIN_MS = 300
_POLL_NS = 50_000_000
_BATCH = 1000


def add_live_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation live``."""
    parser.add_argument("--link", required=True, help="firmware link: serial://... or udp://...")
    parser.add_argument("--mocap", default=None, help="mocap: natnet://239.255.42.99:1511")
    parser.add_argument("--joystick", default=None, metavar="DEV", help="/dev/input/js0 (or FIFO)")
    parser.add_argument("--record", default=None, metavar="FILE", help="MCAP file to write")
    parser.add_argument(
        "--force", action="store_true", help="replace an existing --record file (and segments)"
    )
    parser.add_argument(
        "--segment-s", type=float, default=60.0, metavar="S",
        help="the recording starts a new segment file every S seconds (default 60)",
    )  # fmt: skip
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
    parser.add_argument(
        "--signing-key",
        default=None,
        metavar="FILE",
        help="MAVLink 2 signing key (32 raw bytes or 64 hex characters): sign every command "
        "sent to the vehicle (sets acquisition.signing_key_file)",
    )


def _available(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def _signing_sets(args: argparse.Namespace) -> list[str]:
    """``--signing-key FILE`` as the setting the link process reads (absolute path)."""
    key = getattr(args, "signing_key", None)
    return [] if key is None else [f"acquisition.signing_key_file={Path(key).resolve()}"]


def _check_signing(resolved: Resolved) -> None:
    """A signing key that cannot be read fails here, before any worker starts."""
    settings = resolved.config.acquisition
    if settings.signing_key_file:
        from firmware_bridge.mavlink.signing import SigningKeyError, load_signing_key

        try:
            load_signing_key(settings.signing_key_file)
        except SigningKeyError as exc:
            raise ConfigError(exc.message, exc.hint) from None


def plan(args: argparse.Namespace, session_id: str) -> tuple[Session, list[WorkerSpec]]:
    """The session and the worker specs of a live run, in start order (no side effects)."""
    mapping = not args.no_mapping and _available(DETECTOR_MODULE) and _available(MAPPER_MODULE)
    recorders = list(RECORDERS) if args.record else []
    names = recorders + ["link"] + (["mocap"] if args.mocap else [])
    names += (["pilot"] if args.joystick else []) + (["mapper", "detector"] if mapping else [])
    session = Session(session_id, tuple(names), args.session_root)
    rec = len(recorders)
    # Ready handshake: the sources wait for both recorders on every data topic, and for the
    # monitor and the detector too on the sample topics.
    wait_sources = ("--wait-subscribers", str(rec),
                    "--wait-samples", str(1 + rec + (1 if mapping else 0)))  # fmt: skip
    specs: list[WorkerSpec] = []
    sources = [args.link] + ([args.mocap] if args.mocap else [])
    for name in recorders:
        argv = python_module(
            RECORDER_MODULE, *session.as_args(), "--name", name, "--out", str(args.record),
            "--created-by", "groundstation live " + " ".join(sys.argv[1:]),
            "--segment-s", str(getattr(args, "segment_s", 60.0)),
            *[a for s in sources for a in ("--source", s)],
        )  # fmt: skip
        specs.append(WorkerSpec(name, argv, warm=True, max_restarts=20, group="recorders",
                                stop_timeout_s=30.0, nice=NICE[name]))  # fmt: skip
    for spec in (
        source_worker(args.link, session, "link", wait_sources),
        *([source_worker(args.mocap, session, "mocap", wait_sources)] if args.mocap else []),
    ):
        specs.append(WorkerSpec(spec.name, spec.argv, warm=True, max_restarts=20,
                                nice=NICE[spec.name]))  # fmt: skip
    if args.joystick:
        argv = python_module(PILOT_MODULE, *session.as_args(), "--device", args.joystick,
                             "--wait-subscribers", str(2 + rec))  # fmt: skip
        specs.append(WorkerSpec("pilot", argv, warm=True, max_restarts=20, nice=NICE["pilot"]))
    if mapping:
        recording = ["--recording", str(args.record)] if args.record else []
        specs.append(
            WorkerSpec(
                "mapper",
                python_module(MAPPER_MODULE, *session.as_args(), *recording),
                env=(("OPENBLAS_NUM_THREADS", "1"), ("OMP_NUM_THREADS", "1")),
                warm=True,
                max_restarts=20,
            )
        )
        # ids from 0 as in a replay; a restarted detector resumes from its checkpoint and the
        # recording and publishes each observation once (runtime/workers/detector.py)
        detector = ("--wait-subscribers", str(2 + rec), "--first-id", "0", *recording)
        specs.append(
            WorkerSpec(
                "detector",
                python_module(DETECTOR_MODULE, *session.as_args(), *detector),
                warm=True,
                max_restarts=20,
                nice=NICE["detector"],
            )  # fmt: skip
        )
    if not args.no_viewer:
        view = ["--headless", "--out", str(args.out)] if args.headless else []
        if args.viewer == "rerun":
            # the rerun sink reads the session's resolved configuration (written before start)
            config_file = str(Path(session.directory) / CONFIG_FILE)
            view = ["--viewer", "rerun", "--web-bind", args.web_bind, "--web-port",
                    str(args.web_port), "--grpc-port", str(args.grpc_port),
                    "--config", config_file]  # fmt: skip
            view += ["--rrd", str(args.rrd)] if args.rrd else []
        argv = python_module(VIEWER_MODULE, "--session", session.session_id,
                             "--session-root", session.root,
                             "--publishers", ",".join(session.publishers), *view)  # fmt: skip
        specs.append(WorkerSpec("viewer", argv, max_restarts=3))
    return session, specs


def _err(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class _Watch(threading.Thread):
    """Polls the supervisor every ``_POLL_NS`` in its own thread, so that a dead worker is
    restarted at once even when the monitor is behind (a loaded machine); events go to
    ``events`` with their time. It must outlive the workers it restarts: Linux sends a
    worker's parent-death signal when the *thread* that started it ends."""

    def __init__(self, sup: Supervisor) -> None:
        super().__init__(name="supervisor", daemon=True)
        self.sup, self.events = sup, queue.Queue()
        self.halt = threading.Event()

    def run(self) -> None:
        while not self.halt.wait(_POLL_NS / 1e9):
            for ev in self.sup.poll():
                self.events.put((ev, time.monotonic_ns()))


def _board(t0: int, resolved: Resolved, args: argparse.Namespace) -> StatusBoard:
    cfg = resolved.config
    expect = ["samples.imu", "samples.attitude"] + (["samples.pose"] if args.mocap else [])
    settings = AlertSettings(
        refit_period_s=cfg.mapper.refit_period_s, min_contacts=cfg.mapper.min_contacts
    )
    return StatusBoard(t0, Alerts(t0, settings, expect))


def run_live(args: argparse.Namespace) -> int:
    """Run the live session until Ctrl-C / SIGTERM / ``--duration``; 0 when it ended cleanly
    and lost no data."""
    resolved = resolve(args.config, [*args.set, *_signing_sets(args)])
    _check_signing(resolved)
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration {args.duration} must be > 0")
    if not args.segment_s > 0:
        raise ConfigError(f"--segment-s {args.segment_s} must be > 0")
    if args.record:
        from groundstation.acquisition.segments import claim_output

        claim_output(args.record, args.force, "--record")
    session, specs = plan(args, new_session_id())
    if not args.no_mapping and "detector" not in [s.name for s in specs]:
        _err("live: detector/mapper not installed: running acquisition only")
    if not args.record and "detector" in [s.name for s in specs]:
        _err("live: no --record: a restarted detector or mapper cannot catch up on what it missed")
    session.write_info(command="live")
    write_session_config(session.directory, resolved)
    root = "" if session.root == "/tmp" else f" --session-root {session.root}"
    _err(
        f"live: session {session.session_id}; another viewer: groundstation view --session "
        f"{session.session_id}{root}"
    )
    stopping: list[int] = []
    old = {
        s: signal.signal(s, lambda n, f: stopping.append(n))
        for s in (signal.SIGINT, signal.SIGTERM)
    }
    sub = Subscriber(session.subscribe_endpoints(), MONITOR_TOPICS)
    sup = Supervisor(specs)
    t0 = time.monotonic_ns()
    board = _board(t0, resolved, args)
    end = math.inf if args.duration is None else t0 + args.duration * 1e9
    clean = True
    watch = _Watch(sup)
    try:
        for ev in sup.start():
            _err(f"started {ev.name} ({ev.detail})")
        watch.start()
        next_line = t0 + 1_000_000_000
        while not stopping and time.monotonic_ns() < end:
            env = sub.recv(50)
            now = time.monotonic_ns()
            n = 0
            while env is not None:
                for msg in board.ingest(env, now):
                    _err(msg)
                n += 1
                env = sub.recv(0) if n < _BATCH else None
                now = time.monotonic_ns()
            while not watch.events.empty():
                ev, t_ev = watch.events.get()
                board.on_worker(ev.name, ev.kind, ev.restarts, ev.detail, t_ev)
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
        # only now: a worker's parent-death signal fires when the thread that started it ends
        watch.halt.set()
        if watch.is_alive():
            watch.join(5)
        while (env := sub.recv(_DRAIN_MS)) is not None:  # the workers' final status
            board.ingest(env, time.monotonic_ns())
        board.set_gaps(sub.gaps)
        print("final: " + board.line(time.monotonic_ns(), {}, final=True), flush=True)
        board.alerts.close(time.monotonic_ns())
        sub.close()
        session.cleanup()
    summary = board.summary()
    loss = list(summary["data_loss"])
    if summary["gaps_monitor"] or summary["gaps_recorder"]:
        loss.append(
            f"bus sequence gaps: {summary['gaps_monitor']} (monitor), "
            f"{summary['gaps_recorder']} (recorder)"
        )
    if args.record:
        summary["recording"] = check_recording(args.record)
        if not summary["recording"].get("complete", False):
            why = summary["recording"].get("error", "its last segment was cut")
            loss.append(f"recording {args.record} incomplete: {why}")
    summary["data_loss"] = loss
    summary["clean_stop"] = clean
    for ev in summary["events"]:
        dur = f" for {ev['duration_s']} s" if ev.get("duration_s") is not None else ""
        _err(f"live event: t={ev['t_s']} s {ev['text']}{dur}")
    for text in loss:
        _err(f"live: DATA LOST: {text}")
    _err("live summary: " + json.dumps(summary, default=str))
    if args.summary:
        Path(args.summary).write_text(json.dumps(summary, indent=1, default=str) + "\n")
    return 0 if clean and not loss else 1


def check_recording(path: str) -> dict:
    """Open the recorded session: its segments, whether the last one closed properly (a cut
    earlier segment belongs to a recorder that was replaced by its standby), duration and
    per-topic counts."""
    import warnings

    from groundstation.acquisition.segments import open_session

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with open_session(path) as rec:
                s = rec.summary
                last_cut = rec.segments[-1].truncated
                out = {
                    "complete": not last_cut,
                    "segments": len(rec.segments),
                    "segments_cut": [p.name for p, _ in rec.recoveries],
                    "duration_s": s.duration_s,
                    "topic_counts": dict(s.topic_counts),
                }
    except GroundstationError as exc:
        _err(f"error: recording {path}: {exc.message}")
        return {"complete": False, "error": exc.message}
    counts = ", ".join(f"{k} {v}" for k, v in sorted(out["topic_counts"].items()))
    cut = f", {len(out['segments_cut'])} cut by a recorder restart" if out["segments_cut"] else ""
    _err(f"recorded {path}: {out['segments']} segment(s){cut}, {out['duration_s']:.1f} s, {counts}")
    return out
