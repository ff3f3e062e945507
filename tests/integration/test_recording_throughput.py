"""Throughput of the recorder on a synthetic live session (opt-in: pytest -m soak -s).

10 minutes of 200 Hz HIGHRES_IMU + 200 Hz ATTITUDE_QUATERNION MAVLink 2 frames (one read per
frame pair) and 200 Hz NatNet 4.1 frames of data, through :class:`Recorder`, then a full
time-ordered read. Prints file size, write time and read time; asserts only on counts.
"""

from __future__ import annotations

import math
import time

import pytest

from firmware_bridge.mavlink.codec import MavlinkCodec
from firmware_bridge.mavlink.messages import AttitudeSample, ImuSample
from firmware_bridge.natnet import FrameOfData, RigidBody, encode_frame_of_data
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.recorder import Recorder


def synthesize(seconds: float, rate_hz: int = 200):
    codec = MavlinkCodec(1, 1)
    n = int(seconds * rate_hz)
    period = 1_000_000_000 // rate_hz
    for i in range(n):
        t = 1_000_000_000 + i * period
        s = i / rate_hz
        imu = ImuSample(
            (0.3 * math.sin(s), 0.2 * math.cos(s), -9.81 + 0.1 * math.sin(7 * s)),
            (0.01 * math.sin(3 * s), 0.0, 0.02),
            time_source_ns=t,
        )
        half = 0.5 * 0.1 * math.sin(0.2 * s)
        att = AttitudeSample(
            (math.cos(half), 0.0, 0.0, math.sin(half)), (0.0, 0.0, 0.02), time_source_ns=t
        )
        link = codec.encode(imu) + codec.encode(att)
        body = RigidBody(1, (math.sin(s), 1.0, math.cos(s)), (0.0, 0.0, 0.0, 1.0), 0.0005, True)
        natnet = encode_frame_of_data(FrameOfData(i, (body,), s), version=(4, 1))
        yield t, link, natnet


@pytest.mark.soak
@pytest.mark.timeout(900)
def test_ten_minutes_at_200_hz(tmp_path):
    seconds = 600.0
    data = list(synthesize(seconds))
    path = tmp_path / "ten_minutes.mcap"
    raw_bytes = sum(len(a) + len(b) for _, a, b in data)
    t0 = time.perf_counter()
    with Recorder(path) as rec:
        for t, link, natnet in data:
            rec.write(link, "raw.mavlink", t + 200_000, t, source="serial:///dev/ttyUSB0")
            rec.write(natnet, "raw.natnet", t + 300_000, t, source="127.0.0.1:1511")
    write_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open_recording(path) as r:
        n = sum(1 for _ in r.messages())
        chunks = rec.stats.chunks
    read_s = time.perf_counter() - t0
    size = path.stat().st_size
    print(
        f"\n10 min @ 200 Hz: {len(data) * 2} messages, {raw_bytes / 1e6:.1f} MB of wire bytes -> "
        f"{size / 1e6:.2f} MB file ({chunks} chunks, {raw_bytes / size:.1f}x); "
        f"write {write_s:.1f} s, full read {read_s:.1f} s"
    )
    assert n == len(data) * 2
