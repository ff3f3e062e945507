"""UdpLink over loopback: listen/send modes, replies to the peer, and pymavlink as an
independent client in both directions."""

from __future__ import annotations

import os
import socket

os.environ["MAVLINK20"] = "1"

import pytest

from firmware_bridge.link import open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import Heartbeat, ImuSample

pytestmark = pytest.mark.timeout(60)


def read_records(link, codec, n, idle_timeout_s=5.0):
    """Decode datagrams until ``n`` records arrived or nothing came for ``idle_timeout_s``."""
    out = []
    while len(out) < n:
        data = link.read(idle_timeout_s)
        if not data:
            break
        out += codec.decode(data, 0)
    return out


def test_listen_and_send_modes_reply_to_the_peer():
    with open_link("udp://127.0.0.1:0?mode=listen") as station:
        port = station.local_address[1]
        assert station.write(b"nobody to send to yet") is False
        assert station.dropped_writes == 1
        with open_link(f"udp://127.0.0.1:{port}") as vehicle:
            assert vehicle.mode == "send" and station.mode == "listen"
            vtx = MavlinkCodec(1, 1)
            imu = [
                ImuSample((0.1 * i, 0, -9.8), (0, 0, 0.01 * i), time_source_ns=i * 5_000_000)
                for i in range(200)
            ]
            for r in imu:
                vehicle.write(vtx.encode(r))
            rx = MavlinkCodec()
            got = read_records(station, rx, 200)
            assert [r.time_source_ns for r in got] == [r.time_source_ns for r in imu]
            assert rx.stats.lost == 0
            assert station.peer == ("127.0.0.1", vehicle.local_address[1])
            # the station's reply goes back to the vehicle's ephemeral port
            assert station.write(MavlinkCodec().encode(Heartbeat(6, 8, 0, 0, 4))) is True
            (hb,) = read_records(vehicle, MavlinkCodec(1, 1), 1)
            assert isinstance(hb, Heartbeat) and hb.system_id == 255
        assert [e.kind for e in station.events][:2] == ["opened", "connected"]


def test_read_times_out_with_empty_bytes_and_close_is_idempotent():
    link = open_link("udp://127.0.0.1:0?mode=listen")
    assert link.read(0.05) == b""
    link.close()
    link.close()
    assert link.read(0.05) == b""


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_pymavlink_mavutil_decodes_what_we_send():
    from pymavlink import mavutil

    port = _free_udp_port()
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=200)
    try:
        with open_link(f"udp://127.0.0.1:{port}") as link:
            tx = MavlinkCodec(1, 1)
            link.write(tx.encode(Heartbeat(2, 12, 81, 65536, 4)))
            link.write(
                tx.encode(ImuSample((0.5, -0.25, -9.75), (0.125, 0, 0.5), time_source_ns=1_234_000))
            )
            hb = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
            imu = conn.recv_match(type="HIGHRES_IMU", blocking=True, timeout=5)
    finally:
        conn.close()
    assert hb is not None and (hb.type, hb.autopilot, hb.base_mode) == (2, 12, 81)
    assert hb.custom_mode == 65536 and hb.get_srcSystem() == 1
    assert imu is not None and imu.time_usec == 1234
    assert (imu.xacc, imu.yacc, imu.zacc, imu.zgyro) == (0.5, -0.25, -9.75, 0.5)
    assert hb._header.incompat_flags == 0 and hb.get_msgbuf()[0] == 0xFD  # MAVLink 2


def test_we_decode_what_pymavlink_mavutil_sends():
    from pymavlink import mavutil

    with open_link("udp://127.0.0.1:0?mode=listen") as link:
        port = link.local_address[1]
        conn = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=1, source_component=1
        )
        try:
            conn.mav.heartbeat_send(2, 3, 0, 7, 4)
            conn.mav.highres_imu_send(
                5_000, 1.0, 2.0, 3.0, 0.5, 0.25, 0.125, 0, 0, 0, 0, 0, 0, 0, 63
            )
            got = read_records(link, MavlinkCodec(), 2)
        finally:
            conn.close()
    assert isinstance(got[0], Heartbeat) and got[0].custom_mode == 7
    assert got[1].accel == (1.0, 2.0, 3.0) and got[1].time_source_ns == 5_000_000
