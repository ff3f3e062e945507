"""The codec's own decode of plain MAVLink 2 frames equals pymavlink's generated decoder.

``codec._decode_plain_v2`` replaces ``MAVLink.decode`` for unsigned frames without incompat
flags when no signing key is set (the replay path); the oracle is pymavlink itself, on random
payloads of every message type of the dialect (arrays, strings, trimmed payloads) and on damage.
"""

from __future__ import annotations

import os
import random

os.environ["MAVLINK20"] = "1"

import pytest
from pymavlink.dialects.v20 import common as mavlink

from firmware_bridge.mavlink import codec as codec_module
from firmware_bridge.mavlink.codec import MavlinkCodec, _decode_plain_v2


def _frame(msgid: int, payload: bytes, seq: int, crc_ok: bool = True) -> bytearray:
    cls = mavlink.mavlink_map[msgid]
    head = bytes([0xFD, len(payload), 0, 0, seq, 7, 9, msgid & 0xFF, (msgid >> 8) & 0xFF,
                  msgid >> 16])  # fmt: skip
    crc = mavlink.x25crc(head[1:] + payload + bytes([cls.crc_extra])).crc
    if not crc_ok:
        crc ^= 0x0101
    return bytearray(head + payload + bytes([crc & 0xFF, crc >> 8]))


def _fields(msg) -> tuple:
    h = msg._header
    header = (h.msgId, h.incompat_flags, h.compat_flags, h.mlen, h.seq, h.srcSystem,
              h.srcComponent)  # fmt: skip
    values = tuple(repr(getattr(msg, f)) for f in msg.get_fieldnames())  # repr: NaN == NaN
    return type(msg), header, values, msg._crc, bytes(msg._payload), msg._signed


def _pymavlink(frame: bytearray):
    try:
        return mavlink.MAVLink(None).decode(bytearray(frame))
    except Exception:  # noqa: BLE001 - MAVError and friends: the frame is rejected
        return None


@pytest.mark.parametrize("seed", range(3))
def test_every_message_type_decodes_as_pymavlink_does(seed):
    rng = random.Random(seed)
    decoded = 0
    for msgid, cls in sorted(mavlink.mavlink_map.items()):
        size = cls.unpacker.size
        for _ in range(4):
            n = rng.choice([size, rng.randint(1, size), min(255, size + rng.randint(0, 8))])
            payload = bytes(rng.getrandbits(8) for _ in range(n))
            if rng.random() < 0.5:  # MAVLink 2 senders trim trailing zero bytes
                payload = payload[: rng.randint(1, n)].rstrip(b"\0") or b"\1"
            crc_ok = rng.random() < 0.9
            frame = _frame(msgid, payload, rng.getrandbits(8), crc_ok)
            expected = _pymavlink(frame)
            got = _decode_plain_v2(bytearray(frame), msgid)
            assert (got is None) == (expected is None), (cls.msgname, payload.hex(), crc_ok)
            if got is not None:
                assert _fields(got) == _fields(expected), cls.msgname
                decoded += 1
    assert decoded > 2 * len(mavlink.mavlink_map)


def _slow(frame: bytearray, msgid: int):
    return _pymavlink(frame)


def _stream(seed: int) -> bytes:
    """Valid frames of every record type the station decodes, with random damage."""
    from firmware_bridge.mavlink.messages import AttitudeSample, Heartbeat, ImuSample, Timesync

    rng = random.Random(seed)
    tx = MavlinkCodec(system_id=1, component_id=1)
    out = bytearray()
    for k in range(400):
        rec = rng.choice([
            ImuSample((rng.gauss(0, 5), 0.25, -9.8), (0.0, rng.gauss(0, 1), 0.0), sensor_id=k % 3,
                      time_source_ns=k * 5_000_000),
            AttitudeSample((1.0, rng.gauss(0, 0.1), 0.0, 0.0), (0.0, 0.0, 0.0),
                           time_source_ns=k * 5_000_000),
            Heartbeat(2, 3, 0, 0, 4),
            Timesync(rng.getrandbits(40), rng.getrandbits(40)),
        ])  # fmt: skip
        frame = bytearray(tx.encode(rec))
        if rng.random() < 0.05:
            frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        if rng.random() < 0.03:
            frame = frame[: rng.randrange(1, len(frame))]
        out += frame
        if rng.random() < 0.03:
            out += bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 40)))
    return bytes(out)


@pytest.mark.parametrize("seed", range(5))
def test_stream_records_and_counters_equal_the_pymavlink_path(seed, monkeypatch):
    data = _stream(seed)
    rng = random.Random(seed)
    cuts = sorted(rng.sample(range(1, len(data)), 60))
    chunks = [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]
    fast = MavlinkCodec()
    fast_out = [fast.decode(c, i) for i, c in enumerate(chunks)]
    monkeypatch.setattr(codec_module, "_decode_plain_v2", _slow)
    slow = MavlinkCodec()
    slow_out = [slow.decode(c, i) for i, c in enumerate(chunks)]
    assert repr(fast_out) == repr(slow_out)
    assert fast.stats == slow.stats
    assert sum(map(len, fast_out)) > 300 and fast.stats.crc_errors > 0
