"""Locked and signed links against an attacker on loopback (issue 14, point 8).

Real processes (the link and mocap workers under the supervisor, ``groundstation sitl``) and real
UDP sockets. Each attack is rejected and counted:

- peer hijack: one datagram from another port used to redirect every MANUAL_CONTROL to it;
- forged telemetry: HIGHRES_IMU from a foreign port used to be recorded as vehicle data;
- spoofed server info: one datagram from anyone used to switch NatNet to 2.0 and stop all mocap;
- unsigned commands: with a signing key set, the SITL rejects unsigned MANUAL_CONTROL and accepts
  the station's signed ones.
"""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    Heartbeat,
    ImuSample,
    ManualControl,
    SetMessageInterval,
)
from firmware_bridge.natnet import (
    FrameOfData,
    RigidBody,
    ServerInfo,
    encode_frame_of_data,
    encode_server_info,
)
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.session import Session, new_session_id
from groundstation.runtime.sources import source_worker
from groundstation.runtime.supervisor import Supervisor

ROOT = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.timeout(180)
DATA = ["raw.mavlink", "samples.imu", "samples.attitude", "samples.pose"]


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.1)
    return s


def _free_port() -> int:
    with _udp() as s:
        return s.getsockname()[1]


def _drain(sock: socket.socket, codec: MavlinkCodec, seconds: float, until=None) -> list:
    out: list = []
    end = time.monotonic() + seconds
    while time.monotonic() < end and not (until and until(out)):
        try:
            data, _ = sock.recvfrom(65536)
        except TimeoutError:
            continue
        out += codec.decode(data, 0)
    return out


def _last_status(sub: Subscriber, process: str, seconds: float, until) -> tuple[dict, list]:
    """Latest ``status`` payload of ``process`` once ``until(payload)`` holds; every message."""
    seen: list = []
    status: dict = {}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        env = sub.recv(200)
        if env is None:
            continue
        seen.append(env)
        if env.topic == "status" and env.payload["process"] == process:
            status = env.payload
            if until(status):
                break
    while (env := sub.recv(300)) is not None:  # what was queued on the other sockets
        seen.append(env)
    return status, seen


def test_peer_hijack_and_forged_telemetry_are_rejected_and_counted(zctx):
    port = _free_port()
    vehicle, attacker = _udp(), _udp()
    session = Session(new_session_id(), ("link", "pilot"))
    pilot = Publisher(topics=["pilot.command"], context=zctx, **session.publisher_kwargs("pilot"))
    sub = Subscriber(session.subscribe_endpoints(), [*DATA, "status", "log"], context=zctx)
    sup = Supervisor([source_worker(f"udp://127.0.0.1:{port}?mode=listen", session, "link", ())])
    vtx, atx = MavlinkCodec(1, 1), MavlinkCodec(1, 1)  # the attacker even claims system 1
    station = ("127.0.0.1", port)
    try:
        sup.start()
        pilot.wait_for_subscribers(1, timeout_s=30)
        got_vehicle: list = []
        end = time.monotonic() + 30
        while not any(isinstance(r, SetMessageInterval) for r in got_vehicle):
            assert time.monotonic() < end, "the link never answered the vehicle"
            vehicle.sendto(vtx.encode(Heartbeat(2, 12, 0, 0, 4)), station)
            got_vehicle += _drain(vehicle, MavlinkCodec(), 0.5)
        # the attack: one datagram from another port, then forged telemetry
        attacker.sendto(atx.encode(Heartbeat(2, 12, 0, 0, 4)), station)
        for i in range(5):
            forged = ImuSample((66.0, 66.0, 66.0), (0, 0, 0), time_source_ns=(i + 1) * 10**6)
            attacker.sendto(atx.encode(forged), station)
        real = ImuSample((0.0, 0.0, -9.8), (0.0, 0.0, 0.0), time_source_ns=10**9)
        vehicle.sendto(vtx.encode(real), station)
        time.sleep(0.3)
        for i in range(5):
            cmd = {"x": 10 + i, "y": 0, "z": 500, "r": 0, "buttons": 0, "enabled": True}
            pilot.publish("pilot.command", cmd)
            time.sleep(0.03)
        manual_vehicle = [
            r for r in _drain(vehicle, MavlinkCodec(), 3.0) if isinstance(r, ManualControl)
        ]
        manual_attacker = [
            r for r in _drain(attacker, MavlinkCodec(), 0.5) if isinstance(r, ManualControl)
        ]
        status, seen = _last_status(
            sub, "link", 10, lambda s: s["topics"].get("security", {}).get("rejected_peers", 0) >= 6
        )
    finally:
        sup.stop(timeout_s=10)
        sub.close()
        pilot.close(linger_ms=0)
        vehicle.close()
        attacker.close()
    assert [m.x for m in manual_vehicle] == [10, 11, 12, 13, 14]
    assert manual_attacker == []  # nothing redirected
    sec = status["topics"]["security"]
    assert sec["rejected_peers"] == 6 and sec["peer"] == f"127.0.0.1:{vehicle_port(sec)}"
    assert sec["system_id"] == 1
    imu = [e for e in seen if e.topic == "samples.imu"]
    assert imu and all(list(e.arrays["accel_mps2"]) != [66.0, 66.0, 66.0] for e in imu)
    raw = b"".join(bytes(e.arrays["data"]) for e in seen if e.topic == "raw.mavlink")
    assert struct_float(66.0) not in raw  # the forged bytes were not even published/recorded
    logs = [e.payload.get("message", "") for e in seen if e.topic == "log"]
    assert any("peer_rejected" in t and "not the locked peer" in t for t in logs), logs


def vehicle_port(sec: dict) -> str:
    return sec["peer"].rsplit(":", 1)[1]


def struct_float(x: float) -> bytes:
    import struct

    return struct.pack("<fff", x, x, x)


def _natnet_frame(i: int) -> bytes:
    body = RigidBody(1, (0.1, 1.0, -0.2), (0.0, 0.0, 0.0, 1.0), 0.0002, True)
    return encode_frame_of_data(FrameOfData(i, (body,), i / 200), (4, 1))


def test_spoofed_server_info_is_rejected_and_mocap_goes_on(zctx):
    port = _free_port()
    server_data, server_cmd, attacker = _udp(), _udp(), _udp()
    cmd_port = server_cmd.getsockname()[1]
    session = Session(new_session_id(), ("mocap",))
    sub = Subscriber(
        session.subscribe_endpoints(), ["raw.natnet", "samples.pose", "status", "log"],
        context=zctx,
    )  # fmt: skip
    uri = f"natnet://127.0.0.1:{port}?cmd_port={cmd_port}"
    sup = Supervisor([source_worker(uri, session, "mocap", ())])
    spoof = encode_server_info(ServerInfo("Motive", (2, 0, 0, 0), (2, 0, 0, 0)))
    legit = encode_server_info(ServerInfo("Motive", (3, 1, 0, 0), (4, 0, 0, 0)))
    dest = ("127.0.0.1", port)
    poses: list = []
    try:
        sup.start()
        end = time.monotonic() + 30
        i = 0
        while not poses:
            assert time.monotonic() < end, "no pose from the mocap process"
            server_data.sendto(_natnet_frame(i), dest)
            i += 1
            env = sub.recv(100)
            if env is not None and env.topic == "samples.pose":
                poses.append(env)
        for _ in range(3):
            attacker.sendto(spoof, dest)  # any sender
        server_data.sendto(spoof, dest)  # the server's host, but not its command port
        time.sleep(0.2)
        before = i
        for _ in range(40):
            server_data.sendto(_natnet_frame(i), dest)
            i += 1
            time.sleep(0.005)
        status, seen = _last_status(
            sub, "mocap", 10,
            lambda s: s["topics"].get("security", {}).get("rejected_server_info", 0) >= 4,
        )  # fmt: skip
        # the real server's command port may change the version: an event, not silence
        server_cmd.sendto(legit, dest)
        status2, seen2 = _last_status(
            sub, "mocap", 10, lambda s: s["topics"]["decoder"]["version_changes"] >= 1
        )
    finally:
        sup.stop(timeout_s=10)
        sub.close()
        for s in (server_data, server_cmd, attacker):
            s.close()
    after = [e for e in seen if e.topic == "samples.pose"]
    assert len(after) >= 40 - 2 and after[-1].payload["valid"]  # mocap did not stop
    assert i - before == 40
    sec, dec = status["topics"]["security"], status["topics"]["decoder"]
    # on loopback every sender is the server's host: all four are server info from a port
    # that is not the server's command port
    assert sec["rejected_server_info"] == 4 and sec["rejected_peers"] == 0
    assert dec["version"] == "4.1" and dec["refused_versions"] == 0  # never reached the decoder
    raw = [bytes(e.arrays["data"]) for e in seen if e.topic == "raw.natnet"]
    assert spoof not in raw  # neither decoded nor recorded
    assert status2["topics"]["decoder"]["version"] == "4.0"
    logs = [e.payload.get("message", "") for e in seen + seen2 if e.topic == "log"]
    assert any("NATNET VERSION CHANGED 4.1 -> 4.0" in t for t in logs), logs
    assert any("rejected" in t and "command port" in t for t in logs), logs


def _sitl(*args: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen(
        [sys.executable, "-m", "groundstation.cli", "sitl", *args], cwd=ROOT, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip


def _sitl_local_port(proc: subprocess.Popen) -> int:
    end = time.monotonic() + 30
    while time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            line = proc.stdout.readline()
            if "local port" in line:
                return int(line.rsplit("local port", 1)[1].strip(" )\n"))
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"SITL printed no port: {proc.stderr.read()[-2000:]}")


def test_sitl_with_a_key_rejects_unsigned_commands_and_accepts_the_station(zctx, tmp_path):
    key = tmp_path / "key.hex"
    key.write_text(os.urandom(32).hex() + "\n")
    port = _free_port()
    session = Session(new_session_id(), ("link", "pilot"))
    pilot = Publisher(topics=["pilot.command"], context=zctx, **session.publisher_kwargs("pilot"))
    sub = Subscriber(session.subscribe_endpoints(), [*DATA, "status"], context=zctx)
    sets = ("--set", f"acquisition.signing_key_file={key}")
    sup = Supervisor([source_worker(f"udp://127.0.0.1:{port}?mode=listen", session, "link", sets)])
    proc = _sitl(
        "--link", f"udp://127.0.0.1:{port}", "--pilot", "manual", "--duration", "12",
        "--gust-rate", "0", "--signing-key", str(key),
    )  # fmt: skip
    attacker = _udp()
    try:
        sitl_port = _sitl_local_port(proc)
        sup.start()
        pilot.wait_for_subscribers(1, timeout_s=30)
        # the link is up once samples flow
        end = time.monotonic() + 30
        while (env := sub.recv(200)) is None or env.topic != "samples.imu":
            assert time.monotonic() < end, "no samples from the SITL"
        unsigned = MavlinkCodec(255, 190)
        for _ in range(7):  # an attacker (or an unkeyed station) on the vehicle's port
            attacker.sendto(unsigned.encode(ManualControl(0, 0, 1000, 0)), ("127.0.0.1", sitl_port))
            time.sleep(0.02)
        for i in range(10):
            cmd = {"x": 0, "y": 0, "z": 600 + i, "r": 0, "buttons": 0, "enabled": True}
            pilot.publish("pilot.command", cmd)
            time.sleep(0.03)
        time.sleep(0.5)
        status, _ = _last_status(sub, "link", 5, lambda s: s["topics"].get("security"))
    finally:
        sup.stop(timeout_s=10)
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, err = proc.communicate(timeout=5)
        sub.close()
        pilot.close(linger_ms=0)
        attacker.close()
    assert status["topics"]["security"]["signing"] is True
    final = [ln for ln in err.splitlines() if ln.startswith("sitl t=")][-1]
    assert "manual 10" in final and "unsigned rejected 7" in final, err[-2000:]
    assert "rx cmds 2" in final  # the station's signed SET_MESSAGE_INTERVAL pair was accepted
