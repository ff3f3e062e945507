"""Pure stream decoders: chunking independence, TIMESYNC mapping from the byte stream, bad bytes,
NatNet poses in the world frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_bridge.frames import AxisConvention
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import AttitudeSample, Heartbeat, ImuSample, Timesync
from firmware_bridge.natnet import FrameOfData, RigidBody, encode_frame_of_data
from groundstation.acquisition.decoders import (
    MavlinkStreamDecoder,
    NatNetStreamDecoder,
    content_key,
)
from groundstation.bus.envelope import decode, encode, to_bytes
from groundstation.bus.topics import TOPICS


def _vehicle_stream(n: int = 50, t0_ns: int = 1_000_000_000) -> bytes:
    codec = MavlinkCodec(system_id=1, component_id=1)
    out = [codec.encode(Heartbeat(2, 12, 0, 0, 4))]
    for i in range(n):
        t = t0_ns + i * 5_000_000
        out.append(
            codec.encode(ImuSample((0.1 * i, 0.0, -9.81), (0.0, 0.01 * i, 0.0), time_source_ns=t))
        )
        out.append(
            codec.encode(AttitudeSample((1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.1), time_source_ns=t))
        )
    return b"".join(out)


def _blobs(decoder: MavlinkStreamDecoder, chunks: list[bytes], recv_ns: int) -> list[bytes]:
    out = []
    for c in chunks:
        out += [to_bytes(d.envelope(seq=0)) for d in decoder.feed(c, recv_ns)]
    return out


@pytest.mark.parametrize("size", [1, 7, 64, 1000])
def test_same_bytes_give_byte_identical_envelopes_regardless_of_chunking(size):
    stream = _vehicle_stream()
    whole = _blobs(MavlinkStreamDecoder(), [stream], 123)
    split = _blobs(
        MavlinkStreamDecoder(), [stream[i : i + size] for i in range(0, len(stream), size)], 123
    )
    assert len(whole) == 100
    assert split == whole


def test_envelopes_match_the_topic_table_and_carry_both_clocks():
    dec = MavlinkStreamDecoder()
    samples = dec.feed(_vehicle_stream(3), 777)
    assert [s.topic for s in samples] == ["samples.imu", "samples.attitude"] * 3
    for i, s in enumerate(samples):
        env = decode(encode(s.envelope(seq=i)), TOPICS)  # validates type, schema and payload
        assert (
            env.header.recv_ns == 777
            and env.header.source_ns == 1_000_000_000 + (i // 2) * 5_000_000
        )
        assert content_key(env) == content_key(s)
        assert s.payload["t_station_ns"] == 777  # not synced yet: receive time
    assert dec.last_heartbeat_ns == 777 and dec.vehicle == (1, 1)


def test_timesync_mapping_is_recomputed_from_replies_in_the_stream():
    vehicle = MavlinkCodec(system_id=1, component_id=1)
    dec = MavlinkStreamDecoder(max_rtt_ns=50_000_000)
    t_v = 2_000_000_000
    imu = vehicle.encode(ImuSample((0, 0, -9.8), (0, 0, 0), time_source_ns=t_v))
    assert dec.feed(imu, 10_000_000_000)[0].payload["t_station_ns"] == 10_000_000_000
    # a reply too slow to trust (rtt 80 ms > 50 ms) is rejected: still unsynced
    dec.feed(vehicle.encode(Timesync(tc1=t_v + 1, ts1=9_920_000_000)), 10_000_000_000)
    assert not dec.timesync.synced and dec.timesync.rejected == 1
    # ping sent at station 10.000 s, vehicle stamped 2.010 s, reply read at station 10.004 s
    reply = vehicle.encode(Timesync(tc1=2_010_000_000, ts1=10_000_000_000))
    assert dec.feed(reply, 10_004_000_000) == []
    offset = 2_010_000_000 - (10_000_000_000 + 10_004_000_000) // 2
    assert dec.timesync.offset_ns == offset
    later = vehicle.encode(ImuSample((0, 0, -9.8), (0, 0, 0), time_source_ns=2_020_000_000))
    (s,) = dec.feed(later, 10_016_000_000)
    assert s.payload["t_station_ns"] == 2_020_000_000 - offset == 10_012_000_000
    assert s.source_ns == 2_020_000_000 and s.recv_ns == 10_016_000_000
    health = dec.health_payload(True)
    assert health["timesync_offset_ns"] == offset and health["timesync_rtt_ns"] == 4_000_000
    TOPICS["link.health"].validate(health, {})


def test_bad_bytes_are_skipped_and_counted_and_later_frames_survive():
    stream = _vehicle_stream(10)
    damaged = bytearray(stream)
    damaged[40] ^= 0xFF  # corrupt a frame near the start
    noisy = b"\xfd\x09garbage\xfe" + bytes(damaged) + b"\x00\xff" * 20
    dec = MavlinkStreamDecoder()
    samples = dec.feed(noisy, 1)
    assert 17 <= len(samples) < 20  # the damaged frame is lost, everything after survives
    st = dec.codec.stats
    assert st.crc_errors >= 1 and st.garbage_bytes > 0
    assert dec.health_payload(True)["bad_frames"] >= 1


def test_non_finite_imu_values_are_dropped_and_counted():
    vehicle = MavlinkCodec(system_id=1, component_id=1)
    data = vehicle.encode(ImuSample((math.nan, 0, 0), (0, 0, 0), time_source_ns=5000))
    data += vehicle.encode(ImuSample((1, 2, 3), (0, 0, 0), time_source_ns=6000))
    dec = MavlinkStreamDecoder()
    out = dec.feed(data, 9)
    assert [s.source_ns for s in out] == [6000] and dec.counters.nonfinite == 1


def _natnet(bodies, t_s=12.5, frame_id=3):
    return encode_frame_of_data(FrameOfData(frame_id, tuple(bodies), t_s), version=(4, 1))


def test_natnet_pose_in_world_frame_with_latency_and_validity():
    h = math.sqrt(0.5)
    good = RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 0.0003, True)
    turned = RigidBody(
        2, (0.0, 0.0, 0.0), (0.0, h, 0.0, h), 0.0003, True
    )  # 90 deg about Motive y (up)
    lost = RigidBody(3, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), 0.0, False)
    dec = NatNetStreamDecoder((4, 1), AxisConvention("y"), mocap_latency_ns=4_000_000)
    out = dec.feed(_natnet([good, turned, lost]), 50_000_000)
    assert [s.payload["body_id"] for s in out] == [1, 2, 3]
    p0 = out[0]
    np.testing.assert_allclose(p0.arrays["position_m"], [1.0, -3.0, 2.0])  # Y-up -> z-up world
    np.testing.assert_allclose(p0.arrays["q_wxyz"], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(out[1].arrays["q_wxyz"], [h, 0.0, 0.0, h], atol=1e-12)  # yaw about z
    assert p0.payload == {"body_id": 1, "valid": True, "t_station_ns": 46_000_000}
    assert p0.source_ns == 12_500_000_000 and p0.recv_ns == 50_000_000
    assert out[2].payload["valid"] is False and np.isnan(out[2].arrays["position_m"]).all()
    for s in out:
        decode(encode(s.envelope()), TOPICS)


def test_natnet_bad_datagrams_are_counted_not_raised():
    dec = NatNetStreamDecoder()
    frame = _natnet([RigidBody(1, (0, 0, 0), (0, 0, 0, 1), 0.0, True)])
    assert dec.feed(frame[:-3], 1) == [] and dec.feed(b"\x07", 2) == []
    assert dec.counters.bad == 2 and "NatNet" in dec.last_error
    assert len(dec.feed(frame, 3)) == 1
