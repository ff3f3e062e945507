"""PeerLock and NatNetPeerPolicy: who a UDP link listens to (pure; issue 14, point 8)."""

from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"

import pytest

from firmware_bridge.errors import UriError
from firmware_bridge.link.peer import PeerLock, PeerRule, parse_peer
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import Heartbeat, ImuSample
from firmware_bridge.natnet import (
    FrameOfData,
    RigidBody,
    ServerInfo,
    encode_frame_of_data,
    encode_server_info,
)
from firmware_bridge.natnet.peers import NatNetPeerPolicy

VEHICLE = ("127.0.0.1", 14551)
ATTACKER = ("127.0.0.1", 40000)


def frame(sysid: int = 1, rec=None) -> bytes:
    return MavlinkCodec(sysid, 1).encode(rec or Heartbeat(2, 12, 0, 0, 4))


def test_locks_to_the_first_vehicle_and_rejects_everyone_else():
    lock = PeerLock()
    assert not lock.admit(ATTACKER, b"no mavlink here")  # nothing valid: no lock
    assert lock.peer is None
    assert lock.admit(VEHICLE, frame(1))
    assert lock.peer == VEHICLE and lock.locked_system_id == 1
    imu = frame(1, ImuSample((0, 0, -9.8), (0, 0, 0)))
    assert not lock.admit(ATTACKER, imu)  # forged telemetry from a foreign port
    assert not lock.admit(("10.0.0.5", 14551), imu)  # same port, other host
    assert not lock.admit(VEHICLE, frame(7))  # the locked address, another system id
    assert lock.admit(VEHICLE, imu)
    assert lock.rejected == 4 and lock.accepted == 2
    assert lock.rejected_from["127.0.0.1:40000"] == 2
    assert "system id 7" in lock.last_rejected
    c = lock.counters()
    assert c["peer"] == "127.0.0.1:14551" and c["rejected_peers"] == 4


def test_system_id_setting_skips_other_vehicles_before_the_lock():
    lock = PeerLock(system_id=3)
    assert not lock.admit(ATTACKER, frame(1))
    assert lock.peer is None
    assert lock.admit(VEHICLE, frame(3))
    assert lock.locked_system_id == 3


def test_allow_list_accepts_only_listed_senders():
    lock = PeerLock(allow=["127.0.0.1:14551"])
    assert not lock.admit(ATTACKER, frame(1))  # valid frame, not allowed: never locks
    assert lock.peer is None
    assert lock.admit(VEHICLE, frame(1))
    any_port = PeerLock(allow=["10.1.2.3"])
    assert any_port.admit(("10.1.2.3", 5), frame(1))
    assert not any_port.admit(("10.1.2.4", 5), frame(1))


def test_pre_locked_target_accepts_only_it():
    lock = PeerLock(lock_to=VEHICLE)
    assert not lock.admit(ATTACKER, frame(1))
    assert lock.admit(VEHICLE, frame(1))
    assert lock.locked_system_id == 1


def test_rejected_senders_kept_are_bounded():
    lock = PeerLock()
    lock.admit(VEHICLE, frame(1))
    for port in range(100):
        lock.admit(("127.0.0.1", 20000 + port), frame(1))
    assert lock.rejected == 100 and len(lock.rejected_from) == 33  # 32 + "other"
    assert lock.rejected_from["other"] == 68


@pytest.mark.parametrize(
    ("text", "rule"),
    [
        ("127.0.0.1", PeerRule("127.0.0.1")),
        ("127.0.0.1:14551", PeerRule("127.0.0.1", 14551)),
        ("[::1]:14551", PeerRule("::1", 14551)),
        ("localhost:5", PeerRule("127.0.0.1", 5)),
    ],
)
def test_parse_peer(text, rule):
    assert parse_peer(text) == rule


@pytest.mark.parametrize("text", ["127.0.0.1:0", "127.0.0.1:x", "999.1.1.1", "127.0.0.1:70000"])
def test_parse_peer_errors(text):
    with pytest.raises(UriError, match="allowed peer"):
        parse_peer(text)


def _natnet_frame() -> bytes:
    body = RigidBody(1, (0, 1, 0), (0, 0, 0, 1), 0.0, True)
    return encode_frame_of_data(FrameOfData(1, (body,), 1.0), (4, 1))


SPOOF = encode_server_info(ServerInfo("Motive", (2, 0, 0, 0), (2, 0, 0, 0)))


def test_natnet_server_info_only_from_the_server_command_port():
    policy = NatNetPeerPolicy("127.0.0.1", 1510)
    assert policy.admit(("127.0.0.1", 50000), _natnet_frame())
    assert not policy.admit(("127.0.0.1", 50001), SPOOF)  # right host, wrong port
    assert not policy.admit(("10.0.0.9", 1510), SPOOF)  # right port, wrong host
    assert not policy.admit(("10.0.0.9", 50000), _natnet_frame())  # forged frame
    assert policy.admit(("127.0.0.1", 1510), SPOOF)  # the real server's reply
    assert policy.rejected_server_info == 1 and policy.rejected_peers == 2


def test_natnet_multicast_without_server_locks_to_the_first_frame_host():
    policy = NatNetPeerPolicy(None, 1510)
    assert not policy.admit(("10.0.0.9", 1510), SPOOF)  # before any frame: nobody is trusted
    assert policy.admit(("10.0.0.1", 40000), _natnet_frame())
    assert policy.server == "10.0.0.1"
    assert not policy.admit(("10.0.0.2", 40000), _natnet_frame())
    assert policy.counters()["rejected_peers"] == 2
