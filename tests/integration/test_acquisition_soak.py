"""Soak measurements for the closing note (opt-in: ``pytest -m soak -s``): 10 minutes of 200 Hz
IMU + attitude + 200 Hz mocap recorded and replayed at speed=max (in process and over the bus),
and the bus latency and gaps of a live SITL session at real-time speed. Numbers are printed; the
assertions are on counts and gaps only."""

from __future__ import annotations

import math
import os
import select
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.sitl.runner import Simulation
from firmware_bridge.sitl.scene import load_scene
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import FINISHED, iter_replay
from groundstation.acquisition.sim_recording import write_simulation
from groundstation.bus.pubsub import Subscriber
from groundstation.runtime.session import REPLAY_PUBLISHER, Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor, WorkerSpec, python_module

ROOT = Path(__file__).resolve().parents[2]
SAMPLES = ("samples.imu", "samples.attitude", "samples.pose")
pytestmark = [pytest.mark.soak, pytest.mark.timeout(1800)]


def _record(path: Path, seconds: float, samples: bool) -> float:
    sim = Simulation(load_scene("wall"), "script:hover", 5, seconds)
    t0 = time.monotonic()
    write_simulation(sim, str(path), seed=5, created_by="soak", record_samples=samples)
    return time.monotonic() - t0


def _bus_replay(path: Path) -> tuple[Counter, dict, float]:
    session = Session(new_session_id(), (REPLAY_PUBLISHER,))
    sub = Subscriber(
        session.subscribe_endpoints(),
        [*SAMPLES, "raw.mavlink", "raw.natnet", "log"],
        flow_endpoint=session.flow_endpoint(REPLAY_PUBLISHER),
    )
    sup = Supervisor([source_worker(f"replay://{path}?speed=max", session, REPLAY_PUBLISHER)])
    counts: Counter = Counter()
    text = ""
    try:
        sup.start()
        while not text:
            env = sub.recv(5000)
            assert env is not None or sup.alive()[REPLAY_PUBLISHER]
            if env is None:
                continue
            if env.topic == "log" and env.payload["message"].startswith(FINISHED):
                text = env.payload["message"]
            counts[env.topic] += 1
        gaps = {t: s.gaps for t, s in sub.stats.items()}
    finally:
        sub.close()
        sup.stop(timeout_s=10)
    wall = float(text.split(" in ")[1].split(" s")[0])  # the source's own wall time
    return counts, gaps, wall


def test_ten_minutes_recording_size_and_replay_time(tmp_path):
    minutes = float(os.environ.get("GS_SOAK_MINUTES", "10"))
    full, raw = tmp_path / "full.mcap", tmp_path / "raw.mcap"
    gen_full = _record(full, 60 * minutes, samples=True)
    gen_raw = _record(raw, 60 * minutes, samples=False)
    with open_recording(full) as rec:
        counts = rec.summary.topic_counts
    t0 = time.monotonic()
    offline = Counter(e.topic for e in iter_replay(str(raw)))
    t_offline = time.monotonic() - t0
    bus, gaps, t_bus = _bus_replay(raw)
    for topic in SAMPLES:
        assert offline[topic] == counts[topic] == bus[topic] and gaps[topic] == 0, topic
    print(
        f"\n{minutes:g} min: {dict(counts)}\n"
        f"size raw+samples {full.stat().st_size / 1e6:.1f} MB (written in {gen_full:.1f} s), "
        f"raw only {raw.stat().st_size / 1e6:.1f} MB (written in {gen_raw:.1f} s)\n"
        f"replay speed=max: in process {t_offline:.1f} s, bus {t_bus:.1f} s "
        f"({sum(bus.values())} messages, gaps {sum(gaps.values())})"
    )


def test_live_bus_latency_and_gaps_at_real_time(tmp_path):
    seconds = float(os.environ.get("GS_SOAK_LIVE_S", "60"))
    session = Session(new_session_id())
    topics = [*SAMPLES, "raw.mavlink", "raw.natnet"]  # the link/mocap wait for their data topics
    with Subscriber(session.subscribe_endpoints(), topics) as sub:
        sitl = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "sitl", "--link", "pty", "--mocap",
             "udp://127.0.0.1:15733", "--pilot", "script:hover", "--duration", str(seconds + 5)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        select.select([sitl.stdout], [], [], 30)
        device = sitl.stdout.readline().strip().rsplit(" ", 1)[1]
        wait = ("--wait-subscribers", "2")
        sup = Supervisor([
            WorkerSpec("recorder", python_module(
                "groundstation.runtime.workers.recorder", *session.as_args(),
                "--out", str(tmp_path / "live.mcap"))),
            source_worker(f"serial://{device}", session, "link", wait),
            source_worker("natnet://127.0.0.1:15733", session, "mocap", wait),
        ])  # fmt: skip
        lat: dict[str, list[int]] = {t: [] for t in SAMPLES}
        sup.start()
        try:
            end = None
            while end is None or time.monotonic() < end:
                env = sub.recv(30_000 if end is None else 5000)
                assert env is not None, "no samples"
                end = end or time.monotonic() + seconds
                if env.topic in lat:
                    lat[env.topic].append(time.monotonic_ns() - env.header.recv_ns)
            gaps = {t: s.gaps for t, s in sub.stats.items()}
        finally:
            sup.stop(timeout_s=10)
            sitl.terminate()
            sitl.wait(10)
            sitl.stdout.close()
    for topic in SAMPLES:
        a = np.asarray(lat[topic], float) / 1e3
        p50, p99 = np.percentile(a, [50, 99])
        print(f"\n{topic}: n {a.size} over {seconds:g} s, read->subscriber latency "
              f"p50 {p50:.0f} us p99 {p99:.0f} us, gaps {gaps[topic]}")  # fmt: skip
        assert gaps[topic] == 0 and a.size > 150 * seconds and math.isfinite(p99)
