"""The link process against a vehicle on real loopback UDP: it asks for 200 Hz IMU/attitude, pings
TIMESYNC, forwards ``pilot.command`` as MANUAL_CONTROL only while enabled, publishes what the
vehicle sends, and survives garbage bytes (counted in ``link.health``)."""

from __future__ import annotations

import socket
import time

import pytest

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    Heartbeat,
    ImuSample,
    ManualControl,
    SetMessageInterval,
    Timesync,
)
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor

pytestmark = pytest.mark.timeout(90)


def test_link_process_commands_pilot_forwarding_samples_and_bad_bytes(zctx):
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(0.2)
    port = vehicle.getsockname()[1]
    session = Session(new_session_id(), ("link", "pilot"))
    pilot = Publisher(topics=["pilot.command"], context=zctx, **session.publisher_kwargs("pilot"))
    # the link process waits for a subscriber of its data topics before it opens the link
    data = ["raw.mavlink", "samples.imu", "samples.attitude", "samples.pose"]
    sub = Subscriber(session.subscribe_endpoints(), [*data, "link.health"], context=zctx)
    sup = Supervisor([source_worker(f"udp://127.0.0.1:{port}", session, "link")])
    rx = MavlinkCodec(system_id=1, component_id=1)
    tx = MavlinkCodec(system_id=1, component_id=1)
    got: list = []
    station = None

    def receive(until_s: float, stop=lambda: False) -> None:
        nonlocal station
        end = time.monotonic() + until_s
        while time.monotonic() < end and not stop():
            try:
                data, station = vehicle.recvfrom(65536)
            except TimeoutError:
                continue
            got.extend(rx.decode(data, 0))

    try:
        sup.start()
        pilot.wait_for_subscribers(1, timeout_s=30)  # the link process subscribed
        receive(20, lambda: sum(isinstance(r, SetMessageInterval) for r in got) >= 2)
        assert station is not None, "nothing sent by the link process"
        for i in range(5):  # enabled: forwarded; disabled: nothing goes out
            cmd = {"x": 100 + i, "y": 0, "z": 500, "r": 0, "buttons": 0}
            pilot.publish("pilot.command", {**cmd, "enabled": True})
            time.sleep(0.05)
            pilot.publish("pilot.command", {**cmd, "x": -7, "enabled": False})
            time.sleep(0.05)
        # the vehicle streams: garbage first, then an IMU sample
        vehicle.sendto((b"\xfd\x05" + b"garbage!" * 3) * 5, station)
        vehicle.sendto(tx.encode(ImuSample((1, 2, 3), (0, 0, 0), time_source_ns=7000)), station)
        receive(1.0)
        imu, health = None, None
        end = time.monotonic() + 10
        while (imu is None or health is None) and time.monotonic() < end:
            env = sub.recv(500)
            if env is None:
                continue
            if env.topic == "samples.imu":
                imu = env
            elif env.topic == "link.health" and env.payload["rx_messages"] >= 1:
                health = env.payload
        assert sup.alive()["link"], "bad bytes must not kill the link process"
    finally:
        events = sup.stop(timeout_s=10)
        sub.close()
        pilot.close(linger_ms=0)
        vehicle.close()
    intervals = {r.message_id: r.interval_us for r in got if isinstance(r, SetMessageInterval)}
    assert intervals == {105: 5000, 31: 5000}  # 200 Hz HIGHRES_IMU and ATTITUDE_QUATERNION
    assert any(isinstance(r, Timesync) and r.tc1 == 0 for r in got)
    assert any(isinstance(r, Heartbeat) and r.type == 6 for r in got)  # GCS heartbeat
    manual = [r for r in got if isinstance(r, ManualControl)]
    assert [m.x for m in manual] == [100, 101, 102, 103, 104]
    assert all(m.z == 500 and m.target_system == 1 for m in manual)
    assert imu is not None and list(imu.arrays["accel_mps2"]) == [1.0, 2.0, 3.0]
    assert imu.header.source_ns == 7000
    assert health["garbage_bytes"] > 0 and health["connected"] is True
    assert [e.returncode for e in events] == [0]
