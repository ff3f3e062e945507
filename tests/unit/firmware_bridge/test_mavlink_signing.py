"""MAVLink 2 signing on the command uplink: accepted, rejected and counted."""

from __future__ import annotations

import pytest

from firmware_bridge.errors import ProtocolError
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    Heartbeat,
    ImuSample,
    ManualControl,
    MocapPose,
    SetMessageInterval,
)
from firmware_bridge.mavlink.signing import (
    SigningKeyError,
    load_signing_key,
    signing_timestamp,
)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
COMMANDS = [
    ManualControl(10, -20, 500, 0, 3),
    SetMessageInterval(105, 5000),
    MocapPose((1, 0, 0, 0), (1, 2, -3), time_source_ns=1000),
]


def vehicle() -> MavlinkCodec:
    return MavlinkCodec(1, 1, signing_key=KEY, require_signed=True)


def station(key: bytes | None = KEY, sign: bool = True) -> MavlinkCodec:
    return MavlinkCodec(255, 190, signing_key=key, sign_outgoing=sign, signing_timestamp=10**9)


def test_signed_commands_are_accepted():
    veh, gcs = vehicle(), station()
    out = veh.decode(b"".join(gcs.encode(c) for c in COMMANDS), 1)
    assert [type(r) for r in out] == [type(c) for c in COMMANDS]
    assert veh.stats.rejected_signature == 0


def test_unsigned_commands_are_rejected_and_counted():
    veh, gcs = vehicle(), station(key=None, sign=False)
    out = veh.decode(b"".join(gcs.encode(c) for c in COMMANDS), 1)
    assert out == []
    assert veh.stats.rejected_signature == len(COMMANDS)
    assert veh.stats.crc_errors == 0 and veh.stats.garbage_bytes == 0


def test_wrong_key_is_rejected_and_counted():
    veh, gcs = vehicle(), station(key=OTHER_KEY)
    assert veh.decode(b"".join(gcs.encode(c) for c in COMMANDS), 1) == []
    assert veh.stats.rejected_signature == len(COMMANDS)


def test_wrong_key_is_rejected_even_when_unsigned_is_allowed():
    veh = MavlinkCodec(1, 1, signing_key=KEY, require_signed=False)
    assert len(veh.decode(station(key=None, sign=False).encode(COMMANDS[0]), 1)) == 1
    assert veh.decode(station(key=OTHER_KEY).encode(COMMANDS[0]), 1) == []
    assert veh.stats.rejected_signature == 1


def test_replayed_signed_frame_is_rejected():
    veh, gcs = vehicle(), station()
    frame = gcs.encode(COMMANDS[0])
    assert len(veh.decode(frame, 1)) == 1
    assert veh.decode(frame, 2) == []  # same timestamp again
    assert veh.stats.rejected_signature == 1


def test_unsigned_telemetry_is_accepted_by_a_signing_station():
    gcs = MavlinkCodec(255, 190, signing_key=KEY, require_signed=True)
    tx = MavlinkCodec(1, 1)
    data = tx.encode(Heartbeat(2, 12, 0, 0, 4)) + tx.encode(ImuSample((0, 0, -9.8), (0, 0, 0)))
    assert len(gcs.decode(data, 1)) == 2
    assert gcs.stats.rejected_signature == 0


def test_receiver_without_key_accepts_signed_frames():
    assert len(MavlinkCodec(1, 1).decode(station().encode(COMMANDS[0]), 1)) == 1


def test_signing_needs_a_key():
    with pytest.raises(ProtocolError, match="signing_key"):
        MavlinkCodec(require_signed=True)


def test_key_file_raw_hex_and_bad(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    assert load_signing_key(raw) == KEY == load_signing_key(hexed)
    bad = tmp_path / "bad.key"
    bad.write_text("not a key")
    with pytest.raises(SigningKeyError, match="bad.key"):
        load_signing_key(bad)
    with pytest.raises(SigningKeyError, match="missing.key"):
        load_signing_key(tmp_path / "missing.key")
    with pytest.raises(SigningKeyError):
        MavlinkCodec(signing_key=b"short")


def test_signing_timestamp_epoch():
    assert signing_timestamp(1420070400.0) == 0
    assert signing_timestamp(1420070401.5) == 150_000


def test_a_forged_signature_cannot_lock_out_the_genuine_station():
    """pymavlink stores a stream's signing timestamp before checking the signature; a forged
    frame with timestamp 2**48-1 on the station's stream would turn every genuine frame after
    it into a "replay" (a denial of service on the pilot's commands)."""
    veh = vehicle()
    forger = MavlinkCodec(
        255, 190, signing_key=OTHER_KEY, sign_outgoing=True, signing_timestamp=2**48 - 100
    )
    assert veh.decode(forger.encode(COMMANDS[0]), 1) == []
    gcs = station()  # genuine key, timestamps from 10**9
    out = veh.decode(b"".join(gcs.encode(c) for c in COMMANDS), 2)
    assert [type(r) for r in out] == [type(c) for c in COMMANDS]
    assert veh.stats.rejected_signature == 1
    assert veh.decode(gcs.encode(COMMANDS[0])[:0] + station().encode(COMMANDS[0]), 3) == []
    assert veh.stats.rejected_signature == 2  # a genuine replay is still refused
