"""Stream decoders on hostile input: never raise, and whatever they yield can be published.

Reproducers (issue 14): a 164-byte NatNet 4.1 frame whose timestamp overflows int64 ns (1e300 s
raised OverflowError inside the decoder; 1e291 s made a source time the bus header cannot carry,
so the mocap process died on publish), and such a datagram inside a recording (``replay``
crashed with the same traceback). A spoofed server info announcing NatNet 2.0 switched the
decoder to a version it cannot read and stopped all mocap silently.
"""

from __future__ import annotations

import math
import os
import random
import struct

os.environ["MAVLINK20"] = "1"

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    AttitudeSample,
    Heartbeat,
    ImuSample,
    MocapPose,
    Timesync,
)
from firmware_bridge.natnet import (
    FrameOfData,
    RigidBody,
    ServerInfo,
    encode_frame_of_data,
    encode_server_info,
)
from groundstation.acquisition import layout
from groundstation.acquisition.decoders import (
    INT64_MAX,
    Decoded,
    MavlinkStreamDecoder,
    NatNetStreamDecoder,
)
from groundstation.acquisition.recorder import Recorder
from groundstation.acquisition.replay import iter_replay
from groundstation.bus.envelope import decode, encode
from groundstation.bus.topics import TOPICS

BODY = RigidBody(1, (0.5, 1.0, -0.25), (0.0, 0.0, 0.0, 1.0), 0.0002, True)


def natnet_frame(timestamp_s: float, frame_id: int = 7, version=(4, 1)) -> bytes:
    return encode_frame_of_data(FrameOfData(frame_id, (BODY,), timestamp_s), version)


def publishable(d: Decoded) -> None:
    """What a worker does with a decoded sample: number it, encode it, and a reader decodes it."""
    back = decode(encode(d.envelope(seq=0, origin=1)), TOPICS)
    assert back.header.source_ns == d.source_ns


@pytest.mark.parametrize("timestamp_s", [1e291, 1e300, math.inf, math.nan, -1.0, 9.3e9])
def test_natnet_frame_with_an_impossible_timestamp_keeps_the_pose(timestamp_s):
    data = natnet_frame(timestamp_s)
    assert len(data) == 164
    dec = NatNetStreamDecoder()
    (pose,) = dec.feed(data, 1_000_000)
    assert pose.source_ns == 0 and pose.payload["valid"]
    assert pose.payload["t_station_ns"] == 1_000_000  # detector time from the receive time
    assert dec.counters.out_of_range == 1 and "out of range" in dec.last_error
    publishable(pose)


def test_a_recording_holding_the_overflow_datagram_replays(tmp_path):
    path = tmp_path / "overflow.mcap"
    meta = {layout.KEY_NATNET_VERSION: "4.1", layout.KEY_MOTIVE_UP: "y"}
    with Recorder(path) as rec:
        for i in range(20):
            t = 10**9 + i * 5_000_000
            ts = 1e300 if i == 10 else (1e291 if i == 11 else t / 1e9)
            data = natnet_frame(ts, i)
            rec.write(data, layout.RAW_NATNET_TOPIC, t, t, source="x", channel_metadata=meta)
    poses = list(iter_replay(str(path)))
    assert len(poses) == 20
    assert [p.header.source_ns for p in poses[10:12]] == [0, 0]
    for env in poses:
        decode(encode(env), TOPICS)


def test_spoofed_server_info_cannot_switch_to_an_unreadable_version():
    dec = NatNetStreamDecoder((4, 1))
    assert len(dec.feed(natnet_frame(1.0), 1)) == 1
    spoof = encode_server_info(ServerInfo("Motive", (2, 0, 0, 0), (2, 0, 0, 0)))
    assert dec.feed(spoof, 2) == []
    assert dec.version == (4, 1) and dec.counters.refused_versions == 1
    assert "unsupported version 2.0" in dec.events[-1]
    assert len(dec.feed(natnet_frame(1.005), 3)) == 1  # mocap goes on


def test_a_version_change_mid_session_is_an_event():
    dec = NatNetStreamDecoder((4, 1))
    info = encode_server_info(ServerInfo("Motive", (3, 1, 0, 0), (3, 0, 0, 0)))
    assert dec.feed(info, 1) == [] and dec.version == (3, 0)  # before any frame: configures
    assert dec.events == [] and dec.counters.version_changes == 0
    assert len(dec.feed(natnet_frame(1.0, version=(3, 0)), 2)) == 1
    dec.feed(encode_server_info(ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0))), 3)
    assert dec.version == (4, 1) and dec.counters.version_changes == 1
    assert dec.events == ["NATNET VERSION CHANGED 3.0 -> 4.1 after 1 frames (server info from "
                          "'Motive')"]  # fmt: skip


def _highres_imu(time_usec: int) -> bytes:
    msg = mavlink.MAVLink_highres_imu_message(time_usec, 0, 0, -9.8, *[0] * 10, 0)
    return msg.pack(mavlink.MAVLink(None, 1, 1))


def test_mavlink_sample_times_beyond_int64_are_dropped_and_counted():
    dec = MavlinkStreamDecoder()
    assert dec.feed(_highres_imu(2**64 - 1), 5) == []  # 1.8e22 ns: no bus header can carry it
    assert dec.counters.out_of_range == 1
    (ok,) = dec.feed(_highres_imu(INT64_MAX // 1000), 6)
    publishable(ok)


def test_forged_timesync_reply_cannot_make_unpublishable_times():
    dec = MavlinkStreamDecoder()
    tx = MavlinkCodec(1, 1)
    dec.feed(tx.encode(Timesync(tc1=-(2**63), ts1=2**62)), 10**9)  # absurd round trip
    for d in dec.feed(tx.encode(ImuSample((0, 0, -9.8), (0, 0, 0), time_source_ns=10**15)), 10**9):
        publishable(d)


def _mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 6)):
        op = rng.randrange(5)
        if op == 0 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 1 and len(b) >= 8:
            at = rng.randrange(len(b) - 7)
            b[at : at + 8] = struct.pack("<d", rng.choice((1e291, -1e300, math.inf, math.nan)))
        elif op == 2 and len(b) >= 4:
            at = rng.randrange(len(b) - 3)
            b[at : at + 4] = struct.pack("<i", rng.choice((-1, 2**31 - 1, 0, 1 << 20)))
        elif op == 3:
            del b[rng.randrange(len(b) + 1) :]
        else:
            at = rng.randrange(len(b) + 1)
            b[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 16)))
    return bytes(b)


NATNET_SEEDS = [
    natnet_frame(1.25),
    natnet_frame(2.5, version=(3, 0)),
    encode_server_info(
        ServerInfo("Motive", (3, 1, 0, 0), (3, 1, 0, 0), 10**7, 1511, True, "239.255.42.99")
    ),
]


@settings(max_examples=400, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), which=st.integers(0, len(NATNET_SEEDS) - 1))
def test_natnet_decoder_never_raises_and_yields_publishable_poses(seed, which):
    rng = random.Random(seed)
    dec = NatNetStreamDecoder(rng.choice([(3, 0), (4, 0), (4, 1)]))
    for _ in range(3):
        for d in dec.feed(_mutate(NATNET_SEEDS[which], rng), rng.randrange(2**63)):
            publishable(d)


def _telemetry() -> bytes:
    tx = MavlinkCodec(1, 1)
    recs = [
        Heartbeat(2, 12, 0, 0, 4),
        ImuSample((0.1, 0.2, -9.8), (0.01, 0.0, 0.02), time_source_ns=5_000_000),
        AttitudeSample((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), time_source_ns=5_000_000),
        Timesync(tc1=4_000_000, ts1=1_000_000),
    ]
    return b"".join(tx.encode(r) for r in recs)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_mavlink_decoder_never_raises_and_yields_publishable_samples(seed):
    rng = random.Random(seed)
    dec = MavlinkStreamDecoder()
    data = _mutate(_telemetry(), rng)
    pos = 0
    while pos < len(data):
        k = rng.randint(1, 64)
        for d in dec.feed(data[pos : pos + k], rng.randrange(2**63)):
            publishable(d)
        pos += k
    dec.health_payload(True)


@pytest.mark.parametrize(
    ("q", "kept"),
    [((1e-300, 0.0, 0.0, 0.0), 0), ((1e-40, 1e-40, 0.0, 0.0), 0), ((3e38, 3e38, 3e38, 3e38), 2)],
)
def test_mavlink_quaternions_with_a_useless_norm_are_counted_not_raised(q, kept):
    """Found by ``bench fuzz --target mavlink``: an ATT_POS_MOCAP quaternion with a tiny but
    nonzero norm passed the "any nonzero" check and raised AxisError out of the decoder."""
    tx = MavlinkCodec(1, 197)
    dec = MavlinkStreamDecoder()
    frames = tx.encode(MocapPose(q, (1.0, 2.0, 3.0), time_source_ns=1000))
    frames += tx.encode(AttitudeSample(q, (0.0, 0.0, 0.0), time_source_ns=1000))
    out = dec.feed(frames, 5)
    for d in out:
        publishable(d)
    assert len(out) == kept and dec.counters.nonfinite == 2 - kept
