"""Done-when test of acquisition: the SITL over a real pseudo-terminal (MAVLink) and loopback UDP
(NatNet) into the link and mocap processes, started by the supervisor with the recorder, over real
ZeroMQ ipc sockets; a test subscriber collects every published sample; then the recording is
replayed at speed=max over the bus and in process, and both give exactly the samples that were
published live, with zero gaps.

Frames are counted, never timed.
"""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest

from groundstation.acquisition.decoders import content_key
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import FINISHED, iter_replay
from groundstation.bus.pubsub import Subscriber
from groundstation.runtime.session import REPLAY_PUBLISHER, Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ("samples.imu", "samples.attitude", "samples.pose")
SIM_S = 6.0

pytestmark = pytest.mark.timeout(180)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _first_line(proc: subprocess.Popen, prefix: str, timeout_s: float = 30.0) -> str:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            line = proc.stdout.readline()
            if line.startswith(prefix):
                return line.strip()
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"SITL did not print {prefix!r}")


def _collect(sub: Subscriber, until, idle_s: float, limit_s: float) -> dict[str, list]:
    """Samples per topic until ``until()`` is true and no sample arrived for ``idle_s``."""
    got: dict[str, list] = defaultdict(list)
    end = time.monotonic() + limit_s
    last = time.monotonic()
    while time.monotonic() < end:
        env = sub.recv(200)
        if env is not None and env.topic in SAMPLES:
            got[env.topic].append(content_key(env))
            last = time.monotonic()
        elif until() and time.monotonic() - last > idle_s:
            break
    return got


def _replay_over_bus(path: Path, zctx) -> tuple[dict[str, list], dict[str, int], str]:
    session = Session(new_session_id(), (REPLAY_PUBLISHER,))
    spec = source_worker(f"replay://{path}?speed=max", session, REPLAY_PUBLISHER)
    sub = Subscriber(
        session.subscribe_endpoints(),
        [*SAMPLES, "log"],
        flow_endpoint=session.flow_endpoint(REPLAY_PUBLISHER),
        context=zctx,
    )
    sup = Supervisor([spec])
    finished: list[str] = []
    got: dict[str, list] = defaultdict(list)
    try:
        sup.start()
        end = time.monotonic() + 120
        while not finished and time.monotonic() < end:
            env = sub.recv(1000)
            if env is None:
                assert sup.alive()[REPLAY_PUBLISHER] or finished, "replay process died"
                continue
            if env.topic == "log" and env.payload["message"].startswith(FINISHED):
                finished.append(env.payload["message"])
            elif env.topic in SAMPLES:
                got[env.topic].append(content_key(env))
        gaps = {t: s.gaps for t, s in sub.stats.items()}
    finally:
        sub.close()
        sup.stop(timeout_s=10)
    assert finished, "replay did not finish"
    return got, gaps, finished[0]


def test_sitl_session_recorded_and_replayed_gives_the_same_samples(tmp_path, zctx):
    session = Session(new_session_id())
    out = tmp_path / "live.mcap"
    mport = _free_udp_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    sitl = subprocess.Popen(
        [sys.executable, "-m", "groundstation.cli", "sitl", "--link", "pty",
         "--mocap", f"udp://127.0.0.1:{mport}", "--pilot", "script:survey", "--scene", "wall",
         "--duration", str(SIM_S), "--mocap-drop", "0"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    sub = Subscriber(session.subscribe_endpoints(), context=zctx)  # every topic, like a recorder
    wait = ("--wait-subscribers", "2")  # the recorder and this test
    sup = None
    try:
        device = _first_line(sitl, "SITL MAVLink on ").rsplit(" ", 1)[1]
        sup = Supervisor(
            [
                WorkerSpec(
                    "recorder",
                    python_module(
                        "groundstation.runtime.workers.recorder",
                        *session.as_args(),
                        "--out",
                        str(out),
                        "--source",
                        f"serial://{device}",
                    ),  # fmt: skip
                ),
                source_worker(f"serial://{device}", session, "link", wait),
                source_worker(f"natnet://127.0.0.1:{mport}", session, "mocap", wait),
            ]
        )
        sup.start()
        live = _collect(sub, lambda: sitl.poll() is not None, 1.5, 90)
        assert sitl.wait(30) == 0
        assert all(sup.alive().values()), sup.alive()
        live_gaps = {t: s.gaps for t, s in sub.stats.items()}
        first = {t: s.first_seq for t, s in sub.stats.items()}
    finally:
        if sitl.poll() is None:
            sitl.send_signal(signal.SIGTERM)
            sitl.wait(10)
        sitl.stdout.close()
        sub.close()
        stopped = sup.stop(timeout_s=10) if sup is not None else []
    assert [e.returncode for e in stopped] == [0, 0, 0], stopped  # SIGINT -> clean exit

    # the live stream: ~200 Hz of each sample topic over most of the session, nothing lost
    for topic in SAMPLES:
        assert len(live[topic]) > 0.5 * 200 * SIM_S, (topic, len(live[topic]))
        assert live_gaps[topic] == 0 and first[topic] == 0, topic
    synced = [k for k in live["samples.imu"] if k[3] != f'{{"t_station_ns": {k[2]}}}']
    assert len(synced) > 0.5 * len(live["samples.imu"]), "TIMESYNC never mapped firmware time"

    with open_recording(out) as rec:
        assert not rec.truncated
        counts = rec.summary.topic_counts
        assert rec.metadata()["sources"] == f'["serial://{device}"]'
    for topic in SAMPLES:  # the recorder holds what was published, the test saw the same
        assert counts[topic] == len(live[topic]), topic
    assert counts["raw.mavlink"] > 0 and counts["raw.natnet"] == len(live["samples.pose"])

    # in-process replay: the same decoders on the recorded bytes
    offline: dict[str, list] = defaultdict(list)
    for e in iter_replay(str(out)):
        offline[e.topic].append(content_key(e))
    for topic in SAMPLES:
        assert offline[topic] == live[topic], topic

    # bus replay at speed=max with credit flow control
    replayed, gaps, text = _replay_over_bus(out, zctx)
    for topic in SAMPLES:
        assert replayed[topic] == live[topic], topic
        assert gaps[topic] == 0
    print(f"\nlive {sum(len(v) for v in live.values())} samples; {text}")
