"""The link process's command path: each fresh ``pilot.command`` becomes exactly one
MANUAL_CONTROL; a command older than the max command age (a stalled bus or link) is dropped and
counted, never sent late; when commands stop, MANUAL_CONTROL stops (no repeats of its own)."""

from __future__ import annotations

import socket
import time

import pytest

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import ManualControl, SetMessageInterval
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor

pytestmark = pytest.mark.timeout(120)


def test_fresh_commands_once_each_stale_ones_dropped_and_none_repeated(zctx):
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(0.2)
    session = Session(new_session_id(), ("link", "pilot"))
    pilot = Publisher(topics=["pilot.command"], context=zctx, **session.publisher_kwargs("pilot"))
    data = ["raw.mavlink", "samples.imu", "samples.attitude", "samples.pose"]  # the link waits
    status = Subscriber(session.subscribe_endpoints(), ["status", *data], context=zctx)
    spec = source_worker(
        f"udp://127.0.0.1:{vehicle.getsockname()[1]}", session, "link",
        ("--max-command-age-ms", "100"),
    )  # fmt: skip
    sup = Supervisor([spec])
    rx = MavlinkCodec(system_id=1, component_id=1)
    got: list = []

    def receive(seconds: float, until=lambda: False) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not until():
            try:
                data, _ = vehicle.recvfrom(65536)
            except TimeoutError:
                continue
            got.extend(rx.decode(data, time.monotonic_ns()))

    try:
        sup.start()
        pilot.wait_for_subscribers(1, timeout_s=30)
        receive(20, lambda: any(isinstance(r, SetMessageInterval) for r in got))  # link is open
        now = time.monotonic_ns()
        for i in range(10):
            fresh = i % 2 == 0  # odd ones were "ticked" 0.5 s ago: a stale backlog
            src = time.monotonic_ns() if fresh else now - 500_000_000
            cmd = {"x": i, "y": 0, "z": 500, "r": 0, "buttons": 0, "enabled": True}
            pilot.publish("pilot.command", cmd, source_ns=src)
            time.sleep(0.02)
        receive(1.5)  # commands have stopped: nothing more may arrive
        link_status = None
        end = time.monotonic() + 10
        while time.monotonic() < end:
            env = status.recv(500)
            if env is not None and env.topic == "status":
                pc = env.payload["topics"].get("pilot.command", {})
                if pc.get("received", 0) >= 10:
                    link_status = pc
                    break
    finally:
        events = sup.stop(timeout_s=10)
        status.close()
        pilot.close(linger_ms=0)
        vehicle.close()
    manual = [r for r in got if isinstance(r, ManualControl)]
    assert [m.x for m in manual] == [0, 2, 4, 6, 8]
    assert link_status is not None
    assert link_status["manual_control_sent"] == 5 and link_status["stale_dropped"] == 5
    assert [e.returncode for e in events] == [0]
