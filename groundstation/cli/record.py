"""``groundstation record --link URI [--mocap URI] --out LOG.mcap [--duration S]``

Runs the link process, the mocap process and the recorder process under the supervisor (one
session, :mod:`groundstation.runtime.session`), prints one status line per second (rate per
stream and bus gaps as the recorder sees them, bytes written, process states; warnings and
errors from ``log`` as they come), and stops after ``--duration`` seconds or on Ctrl-C: sources
first, then the recorder, which drains its queue and closes the file, so the file is complete.
A worker that dies is restarted by the supervisor (and said so); the recorder runs as an
active/standby pair, so a killed recorder is replaced at once in a new segment. The configuration
is resolved once here and read by every worker from the session directory; an existing ``--out``
is never replaced without ``--force``.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time

from groundstation.acquisition.segments import claim_output, open_session
from groundstation.bus.pubsub import Subscriber
from groundstation.errors import GroundstationError
from groundstation.runtime.configuration import resolve, write_session_config
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module

_SHORT = {
    "samples.imu": "imu",
    "samples.attitude": "att",
    "samples.pose": "pose",
    "raw.mavlink": "raw.mav",
    "raw.natnet": "raw.nat",
}


def add_record_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation record``."""
    parser.add_argument("--link", required=True, help="firmware link: serial://... or udp://...")
    parser.add_argument("--mocap", default=None, help="mocap: natnet://239.255.42.99:1511")
    parser.add_argument("--out", required=True, help="MCAP file to write")
    parser.add_argument(
        "--force", action="store_true", help="replace an existing --out file (and segments)"
    )
    parser.add_argument(
        "--duration", type=float, default=None, metavar="S", help="stop after S seconds"
    )
    parser.add_argument("--config", default=None, help="TOML configuration file")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )
    parser.add_argument("--session-root", default="/tmp", help="parent of the session directory")


def status_line(t_s: float, status: dict[str, dict], alive: dict[str, bool]) -> str:
    """One status line from the latest ``status`` payload of each process (pure)."""
    active = [
        n
        for n, st in status.items()
        if n.startswith("recorder")
        and st.get("topics", {}).get("recording", {}).get("role") == "active"
    ]
    rec = status.get(active[0] if active else "recorder", {}).get("topics", {})
    parts = [f"t={t_s:6.1f} s"]
    for topic, short in _SHORT.items():
        if topic in rec:
            parts.append(f"{short} {rec[topic].get('rate_hz', 0.0):6.1f} Hz")
    gaps = sum(
        int(v.get("gaps", 0)) for k, v in rec.items() if isinstance(v, dict) and k != "recording"
    )
    info = rec.get("recording", {})
    parts.append(f"gaps {gaps}")
    parts.append(f"written {info.get('bytes_written', 0) / 1e6:.2f} MB")
    if info.get("dropped"):
        parts.append(f"DROPPED {info['dropped']}")
    states = [
        f"{name} {status.get(name, {}).get('state', '?') if up else 'DOWN'}"
        for name, up in alive.items()
    ]
    parts.append("[" + ", ".join(states) + "]")
    return "  ".join(parts)


def run_record(args: argparse.Namespace) -> int:
    """Record until ``--duration`` or Ctrl-C; returns 0 when the file is complete."""
    resolved = resolve(args.config, args.set)  # once, here; the workers read the result
    claim_output(args.out, args.force)
    recorders = ("recorder", "recorder2")
    names = (*recorders, "link", "mocap") if args.mocap else (*recorders, "link")
    session = Session(new_session_id(), names, args.session_root)
    session.write_info(command="record")
    write_session_config(session.directory, resolved)
    sources = [args.link] + ([args.mocap] if args.mocap else [])
    specs = []
    for name in recorders:
        recorder_argv = python_module(
            "groundstation.runtime.workers.recorder", *session.as_args(), "--name", name,
            "--out", args.out, "--created-by", "groundstation record " + " ".join(sys.argv[1:]),
            *[a for s in sources for a in ("--source", s)],
        )  # fmt: skip
        specs.append(
            WorkerSpec(name, recorder_argv, warm=True, group="recorders", stop_timeout_s=30.0)
        )
    wait = ("--wait-subscribers", str(len(recorders)))
    specs.append(source_worker(args.link, session, "link", wait))
    if args.mocap:
        specs.append(source_worker(args.mocap, session, "mocap", wait))

    stopping: list[int] = []
    old = signal.signal(signal.SIGINT, lambda s, f: stopping.append(s))
    sub = Subscriber(session.subscribe_endpoints(), ["status", "log"])
    sup = Supervisor(specs)
    status: dict[str, dict] = {}
    t0 = time.monotonic()
    end = math.inf if args.duration is None else t0 + args.duration
    try:
        for ev in sup.start():
            print(f"started {ev.name} ({ev.detail})", file=sys.stderr)
        next_line = t0 + 1.0
        while not stopping and time.monotonic() < end:
            env = sub.recv(100)
            if env is not None:
                if env.topic == "status":
                    status[env.payload["process"]] = env.payload
                elif env.payload.get("level") in ("warning", "error"):
                    p = env.payload
                    hint = f" (hint: {p['hint']})" if p.get("hint") else ""
                    print(f"{p['process']}: {p['level']}: {p['message']}{hint}", file=sys.stderr)
            for ev in sup.poll():
                print(f"{ev.name} {ev.kind} {ev.returncode} {ev.detail}", file=sys.stderr)
            if time.monotonic() >= next_line:
                print(status_line(time.monotonic() - t0, status, sup.alive()), flush=True)
                next_line += 1.0
    finally:
        signal.signal(signal.SIGINT, old)
        for ev in sup.stop():
            print(f"stopped {ev.name} ({ev.detail})", file=sys.stderr)
        sub.close()
        session.cleanup()
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with open_session(args.out) as rec:
                summary = rec.summary
                complete = not rec.segments[-1].truncated
                n_seg = len(rec.segments)
    except GroundstationError as exc:
        print(f"error: {exc.message}", file=sys.stderr)
        return 1
    counts = ", ".join(f"{k} {v}" for k, v in sorted(summary.topic_counts.items()))
    print(f"recorded {args.out}: {n_seg} segment(s), {summary.duration_s:.1f} s, {counts}",
          flush=True)  # fmt: skip
    return 0 if complete else 1
