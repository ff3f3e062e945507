"""MavlinkCodec: round trips, golden frames, unit conversions, chunking, damage accounting."""

from __future__ import annotations

import math
import os
import random
import struct

os.environ["MAVLINK20"] = "1"

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from firmware_bridge.errors import ProtocolError
from firmware_bridge.mavlink import DecodeStats, MavlinkCodec
from firmware_bridge.mavlink.messages import (
    STANDARD_GRAVITY,
    AttitudeSample,
    CommandAck,
    Heartbeat,
    ImuSample,
    ManualControl,
    MocapPose,
    SetMessageInterval,
    Timesync,
    euler_to_quaternion,
    quaternion_to_euler,
)

# Frames generated once with pymavlink directly (MAVLink(None, 1, 1), message class .pack()).
GOLDEN_HEARTBEAT = "fd09000000010100000000000100020c510403a4f5"  # seq 0
GOLDEN_HIGHRES_IMU = (  # seq 7
    "fd3d000007010169000087d61200000000000000003f000080be00001cc10000003e000080bd0000003d0000"
    "00000000000000000000000000000000000000000000000000003f1e47"
)

f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
u8 = st.integers(0, 255)
usec_ns = st.integers(0, 2**53).map(lambda u: u * 1000)
msec_ns = st.integers(0, 2**32 - 1).map(lambda m: m * 1_000_000)
meta = {"system_id": 1, "component_id": 1}
smeta = {"system_id": st.just(1), "component_id": st.just(1)}


def vec(n: int) -> st.SearchStrategy[tuple[float, ...]]:
    return st.tuples(*[f32] * n)


RECORDS = st.one_of(
    st.builds(Heartbeat, u8, u8, u8, st.integers(0, 2**32 - 1), u8, u8, **smeta),
    st.builds(
        ImuSample, vec(3), vec(3), st.just("HIGHRES_IMU"), u8, time_source_ns=usec_ns, **smeta
    ),
    st.builds(AttitudeSample, vec(4), vec(3), time_source_ns=msec_ns, **smeta),
    st.builds(
        Timesync, st.integers(-(2**63), 2**63 - 1), st.integers(-(2**63), 2**63 - 1), **smeta
    ),
    st.builds(
        ManualControl,
        st.integers(-1000, 1000),
        st.integers(-1000, 1000),
        st.integers(0, 1000),
        st.integers(-1000, 1000),
        st.integers(0, 2**32 - 1),
        u8,
        **smeta,
    ),
    st.builds(MocapPose, vec(4), vec(3), time_source_ns=usec_ns, **smeta),
    st.builds(SetMessageInterval, st.integers(0, 2**24), st.integers(-1, 2**24), u8, u8, **smeta),
    st.builds(CommandAck, st.integers(0, 65535), u8, u8, u8, **smeta),
)


@settings(max_examples=300, deadline=None)
@given(records=st.lists(RECORDS, min_size=1, max_size=8), recv_ns=st.integers(0, 2**62))
def test_round_trip_every_record_type(records, recv_ns):
    tx, rx = MavlinkCodec(1, 1), MavlinkCodec()
    data = b"".join(tx.encode(r) for r in records)
    out = rx.decode(data, recv_ns)
    assert out == [_replace(r, time_recv_ns=recv_ns) for r in records]
    assert rx.stats.frames == len(records)
    assert rx.stats.crc_errors == rx.stats.garbage_bytes == rx.stats.lost == 0


def _replace(record, **kw):
    import dataclasses

    return dataclasses.replace(record, **kw)


def test_golden_heartbeat_and_highres_imu_frames():
    tx = MavlinkCodec(1, 1)
    hb = Heartbeat(2, 12, 81, 65536, 4, 3)
    assert tx.encode(hb).hex() == GOLDEN_HEARTBEAT
    tx._tx.seq = 7
    imu = ImuSample((0.5, -0.25, -9.75), (0.125, -0.0625, 0.03125), time_source_ns=1_234_567_000)
    assert tx.encode(imu).hex() == GOLDEN_HIGHRES_IMU
    out = MavlinkCodec().decode(bytes.fromhex(GOLDEN_HEARTBEAT + GOLDEN_HIGHRES_IMU), 5)
    assert out == [
        _replace(hb, time_recv_ns=5, **meta),
        _replace(imu, time_recv_ns=5, **meta),
    ]


def _pymavlink_frame(msg, seq=0, sysid=1, compid=1) -> bytes:
    m = mavlink.MAVLink(None, sysid, compid)
    m.seq = seq
    return msg.pack(m)


def test_scaled_imu_converts_milli_g_and_milli_rad_per_s():
    frame = _pymavlink_frame(
        mavlink.MAVLink_scaled_imu_message(1500, 1000, -500, -1000, 1000, -250, 3, 0, 0, 0, 0)
    )
    (s,) = MavlinkCodec().decode(frame, 0)
    assert s.msg_type == "SCALED_IMU"
    assert s.accel == pytest.approx((9.80665, -4.903325, -9.80665), abs=1e-12)
    assert s.gyro == pytest.approx((1.0, -0.25, 0.003), abs=1e-12)
    assert s.time_source_ns == 1500 * 1_000_000
    # and back: 1 g in m/s^2 encodes as exactly 1000 mG
    tx = MavlinkCodec(1, 1)
    rec = ImuSample(
        (STANDARD_GRAVITY, 0.0, -2 * STANDARD_GRAVITY), (0.5, 0, 0), "SCALED_IMU", 0,
        time_source_ns=2_000_000,
    )  # fmt: skip
    msg = mavlink.MAVLink(None).decode(bytearray(tx.encode(rec)))
    assert (msg.xacc, msg.yacc, msg.zacc, msg.xgyro, msg.time_boot_ms) == (1000, 0, -2000, 500, 2)


@pytest.mark.parametrize(
    "rpy", [(0.0, 0.0, 0.0), (0.3, -0.2, 1.0), (-1.2, 0.7, -2.9), (0.1, 1.2, 3.1), (2.5, -0.4, 0.2)]
)
def test_attitude_euler_becomes_the_zyx_quaternion(rpy):
    roll, pitch, yaw = rpy
    frame = _pymavlink_frame(mavlink.MAVLink_attitude_message(40, roll, pitch, yaw, 0.1, 0.2, 0.3))
    (a,) = MavlinkCodec().decode(frame, 0)
    # Independent oracle: scipy's intrinsic Z-Y-X rotation (scalar-last quaternion).
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    ref = (w, x, y, z)
    sign = 1.0 if sum(p * q for p, q in zip(a.quaternion, ref, strict=True)) >= 0 else -1.0
    assert [sign * q for q in a.quaternion] == pytest.approx(ref, abs=1e-6)
    assert a.msg_type == "ATTITUDE" and a.time_source_ns == 40_000_000
    back = quaternion_to_euler(euler_to_quaternion(roll, pitch, yaw))
    assert back == pytest.approx(rpy, abs=1e-9)


def _stream(n: int = 40) -> tuple[list, bytes, list[bytes]]:
    tx = MavlinkCodec(1, 1)
    recs, frames = [], []
    for i in range(n):
        # values chosen so no frame contains 0xFD/0xFE except its start byte (exact counts)
        r = (
            ImuSample((0.5, 0.25, -9.75), (0.125, 0.0625, 0.5), time_source_ns=(i + 1) * 5_000_000)
            if i % 2 == 0
            else AttitudeSample((1.0, 0.0, 0.0, 0.0), (0.25, 0.5, 0.125), time_source_ns=i * 10**6)
        )
        f = tx.encode(r)
        if 0xFD in f[1:] or 0xFE in f[1:]:
            tx._tx.seq = (tx._tx.seq - 1) & 0xFF  # keep sequence numbers contiguous
            continue
        recs.append(_replace(r, **meta))
        frames.append(f)
    return recs, b"".join(frames), frames


def test_any_chunking_gives_the_same_records():
    recs, data, _ = _stream()
    rng = random.Random(1)
    for trial in range(20):
        rx = MavlinkCodec()
        out, pos = [], 0
        while pos < len(data):
            k = 1 if trial == 0 else rng.randint(1, 150)
            out += rx.decode(data[pos : pos + k], 7)
            pos += k
        assert out == [_replace(r, time_recv_ns=7) for r in recs]
        assert rx.pending_bytes == 0 and rx.stats.garbage_bytes == 0


def test_partial_frame_is_buffered_until_complete():
    _, _, frames = _stream(2)
    rx = MavlinkCodec()
    assert rx.decode(frames[0][:-1], 1) == []
    assert rx.pending_bytes == len(frames[0]) - 1
    assert len(rx.decode(frames[0][-1:], 2)) == 1


def test_garbage_between_frames_is_skipped_and_counted():
    recs, _, frames = _stream()
    noise = bytes([0x00, 0x11, 0x55, 0xAA, 0x42]) * 7  # 35 bytes, no start byte
    rx = MavlinkCodec()
    out = rx.decode(noise + b"".join(f + noise for f in frames), 0)
    assert len(out) == len(recs)
    assert rx.stats.garbage_bytes == len(noise) * (len(frames) + 1)
    assert rx.stats.crc_errors == 0 and rx.stats.lost == 0


def test_flipped_byte_is_one_crc_error_and_one_lost_frame():
    recs, _, frames = _stream()
    damaged = set(range(3, len(frames), 7))
    data = b""
    for i, f in enumerate(frames):
        if i in damaged:
            f = bytearray(f)
            f[14] ^= 0x01  # payload bit flip
        data += bytes(f)
    rx = MavlinkCodec()
    out = rx.decode(data, 0)
    assert len(out) == len(frames) - len(damaged)
    assert rx.stats.crc_errors == len(damaged)
    assert rx.stats.garbage_bytes == sum(len(frames[i]) for i in damaged)
    assert rx.stats.lost == len(damaged)  # seen as sequence gaps


def test_truncated_frame_loses_only_itself():
    recs, _, frames = _stream()
    data = b"".join(f[: len(f) // 2] if i in (5, 20) else f for i, f in enumerate(frames))
    rx = MavlinkCodec()
    out = rx.decode(data, 0)
    # pymavlink's parse_buffer would also drop the frame after each truncated one
    assert len(out) == len(frames) - 2
    assert rx.stats.crc_errors == 2
    assert rx.stats.lost == 2


def test_unknown_message_id_is_skipped_and_counted():
    recs, _, frames = _stream(6)
    payload = bytes(range(1, 21))
    header = struct.pack("<BBBBBBB", 0xFD, len(payload), 0, 0, 99, 1, 1) + (54321).to_bytes(
        3, "little"
    )
    crc = mavlink.x25crc(header[1:] + payload)
    crc.accumulate(bytes([77]))  # some CRC-extra we do not know
    unknown = header + payload + struct.pack("<H", crc.crc)
    tx = mavlink.MAVLink(None, 1, 1)
    sys_status = mavlink.MAVLink_sys_status_message(*([1] * 13)).pack(tx)  # valid, unmapped
    rx = MavlinkCodec()
    out = rx.decode(frames[0] + unknown + frames[1] + sys_status + b"".join(frames[2:]), 0)
    assert len(out) == len(frames)
    assert rx.stats.unknown == 1 and rx.stats.per_type["UNKNOWN_54321"] == 1
    assert rx.stats.unhandled == 1 and rx.stats.per_type["SYS_STATUS"] == 1
    assert rx.stats.crc_errors == 0 and rx.stats.garbage_bytes == 0


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
@example(seed=79996)  # regression: a noise "unknown id" candidate hid 4 intact frames
@example(seed=339)
@example(seed=2499)
def test_random_damage_never_raises_and_intact_frames_survive(seed):
    recs, _, frames = _stream()
    rng = random.Random(seed)
    data = bytearray()
    intact = 0
    for f in frames:
        kind = rng.random()
        if kind < 0.15:
            data += bytes(rng.randrange(256) for _ in range(rng.randint(1, 60)))
        if kind > 0.85:
            f = bytearray(f)
            f[rng.randrange(len(f))] ^= 1 << rng.randrange(8)
            data += f[: rng.randint(1, len(f))]
        else:
            data += f
            intact += 1
    data += bytes(300)  # later traffic: resolves a false frame start still waiting for bytes
    rx = MavlinkCodec()
    out, pos = [], 0
    while pos < len(data):
        k = rng.randint(1, 200)
        out += rx.decode(bytes(data[pos : pos + k]), 0)
        pos += k
    # A false frame start in noise hides a good frame only if its checksum matches by chance
    # (p ~ 2^-16 per false start, 2^-8 for unknown ids): allow one.
    assert intact - 1 <= len(out) <= intact
    assert rx.pending_bytes < 3
    assert isinstance(rx.stats, DecodeStats)


def test_sequence_gaps_per_sender():
    a, b = MavlinkCodec(1, 1), MavlinkCodec(2, 1)
    hb = Heartbeat(2, 12, 0, 0, 4)
    fa = [a.encode(hb) for _ in range(10)]
    fb = [b.encode(hb) for _ in range(10)]
    rx = MavlinkCodec()
    rx.decode(b"".join(fa[i] for i in range(10) if i not in (2, 3, 7)), 0)
    rx.decode(b"".join(fb), 0)
    assert rx.stats.seq_gaps == {(1, 1): 3, (2, 1): 0}


@pytest.mark.parametrize(
    "record",
    [
        ManualControl(1001, 0, 0, 0),
        ManualControl(0, 0, -1, 0),
        ManualControl(0, 0, 0, 0, buttons=2**32),
        ImuSample((400.0, 0, 0), (0, 0, 0), "SCALED_IMU"),
        ImuSample((0, 0, 0), (0, 0, 0), time_source_ns=-1),
        Heartbeat(256, 0, 0, 0, 0),
        SetMessageInterval(105, -2),
    ],
)
def test_out_of_range_values_raise_protocol_error(record):
    with pytest.raises(ProtocolError):
        MavlinkCodec().encode(record)


def test_bad_vector_length_names_the_field():
    with pytest.raises(ProtocolError, match="ImuSample.accel"):
        ImuSample((1.0, 2.0), (0, 0, 0))
    with pytest.raises(ProtocolError, match="zero or NaN norm"):
        quaternion_to_euler((0.0, 0.0, 0.0, 0.0))
    assert math.isfinite(quaternion_to_euler((2.0, 0.0, 0.0, 0.0))[0])


def test_unknown_id_noise_cannot_hide_the_intact_frames_after_it():
    """Seed 79996's failure built by hand: a false start byte right before intact frames whose
    unknown-id "frame" spans them and passes the weak check (some CRC-extra matches, p = 1/256
    for noise) must not swallow them."""
    from firmware_bridge.mavlink.codec import MavlinkCodec as Codec

    _, _, frames = _stream(6)
    good = b"".join(frames)
    payload_len = 60
    plausible = (
        header
        for seq in range(256)  # vary header bytes until the weak check passes
        for sysid in range(256)
        if Codec._plausible_unknown(
            bytearray(
                (header := bytes([0xFD, payload_len, 0, 0, seq, sysid, 197, 154, 0, 0]))
                + good[: payload_len + 2]
            ),
            False,
        )
    )
    header = next(plausible)
    rx = MavlinkCodec()
    out = rx.decode(header + good + bytes(300), 0)
    assert len(out) == len(frames)
    assert rx.stats.unknown == 0 and rx.stats.lost == 0


def test_plausible_unknown_lookup_equals_trying_every_crc_extra():
    from firmware_bridge.mavlink.codec import _LAST_STEP_TERMS, _crc_accumulate

    rng = random.Random(3)
    for _ in range(5000):
        crc, wire = rng.randrange(65536), rng.randrange(65536)
        brute = any(_crc_accumulate(crc, e) == wire for e in range(256))
        assert brute == ((wire ^ (crc >> 8)) in _LAST_STEP_TERMS)
