"""The pure SITL generator: rates, determinism, commands, NatNet frames, truth."""

from __future__ import annotations

import hashlib
import json
from collections import Counter

import numpy as np
import pytest

from firmware_bridge.frames import motive_to_world, quat_ned_frd_to_enu_flu
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    MAV_CMD_SET_MESSAGE_INTERVAL,
    AttitudeSample,
    CommandAck,
    Heartbeat,
    ImuSample,
    SetMessageInterval,
    Timesync,
)
from firmware_bridge.natnet import FrameOfData, parse_packet
from firmware_bridge.sitl.runner import MocapSettings, Simulation
from firmware_bridge.sitl.scene import load_scene


def _records(sim, station=None):
    station = station or MavlinkCodec()
    recs, mocap = [], []
    for item in sim.outputs():
        if item.channel == "mavlink":
            recs.extend(station.decode(item.data, item.t_ns))
        else:
            mocap.append(item)
    return recs, mocap, station


def test_rates_and_time_continuity():
    sim = Simulation(load_scene("paper"), "script:hover", seed=1, duration=3.0)
    recs, mocap, station = _records(sim)
    kinds = Counter(type(r).__name__ for r in recs)
    assert kinds["ImuSample"] == 600 and kinds["AttitudeSample"] == 600
    assert kinds["Heartbeat"] == 3
    imu_t = np.array([r.time_source_ns for r in recs if isinstance(r, ImuSample)])
    assert np.all(np.diff(imu_t) == 5_000_000)
    assert station.stats.crc_errors == 0 and station.stats.lost == 0
    # Mocap: 200 Hz minus the configured 0.5 % drop-outs, frame ids count the dropped ones too.
    assert 580 <= len(mocap) <= 600
    frames = [parse_packet(m.data, (4, 1)) for m in mocap]
    assert all(isinstance(f, FrameOfData) for f in frames)
    ids = [f.frame_id for f in frames]
    assert ids == sorted(ids) and ids[-1] == 600
    assert 600 - len(ids) == sim.stats.mocap_dropped


def test_same_seed_same_bytes_different_seed_differs():
    def digest(seed):
        sim = Simulation(load_scene("wall"), "script:survey", seed=seed, duration=4.0)
        h = hashlib.sha256()
        for item in sim.outputs():
            h.update(item.t_ns.to_bytes(8, "little") + item.channel.encode() + item.data)
        return h.hexdigest()

    assert digest(7) == digest(7)
    assert digest(7) != digest(8)


def test_attitude_and_mocap_agree_with_the_body():
    sim = Simulation(load_scene("wall"), "script:survey", seed=2, duration=3.0,
                     mocap=MocapSettings(position_noise=0.0, rotation_noise=0.0))  # fmt: skip
    station = MavlinkCodec()
    body = sim.vehicle.body
    checked = 0
    for item in sim.outputs():
        if item.channel == "mavlink":
            for r in station.decode(item.data, 0):
                if isinstance(r, AttitudeSample):
                    q = quat_ned_frd_to_enu_flu(r.quaternion)  # the station's conversion
                    q_true = np.array(body.quaternion)
                    assert abs(q @ q_true) == pytest.approx(1.0, abs=1e-6)
        else:
            f = parse_packet(item.data, (4, 1))
            rb = f.rigid_body(1)
            p, q = motive_to_world(rb.position, rb.orientation, up="y")
            assert p == pytest.approx(body.position, abs=1e-5)
            assert abs(q @ np.array(body.quaternion)) == pytest.approx(1.0, abs=1e-5)
            checked += 1
    assert checked > 500


def test_set_message_interval_timesync_and_corrupt_uplink():
    sim = Simulation(load_scene("paper"), "manual", seed=0, duration=2.0)
    gcs = MavlinkCodec(system_id=255, component_id=190)
    station = MavlinkCodec()
    recs = []
    sent = False
    for item in sim.outputs():
        recs.extend(station.decode(item.data, item.t_ns) if item.channel == "mavlink" else [])
        if not sent and item.t_ns >= 1_000_000_000:
            sent = True
            noise = bytes(range(0x10, 0x40)) + b"\xfd\x09\x00\x00"  # garbage + a bad header
            sim.receive(noise + gcs.encode(SetMessageInterval(105, 20_000)))  # IMU -> 50 Hz
            sim.receive(gcs.encode(SetMessageInterval(33, 10_000)))  # not streamed -> refused
            sim.receive(gcs.encode(Timesync(tc1=0, ts1=123456789)))
    acks = [r for r in recs if isinstance(r, CommandAck)]
    assert [(a.command, a.result) for a in acks] == [
        (MAV_CMD_SET_MESSAGE_INTERVAL, 0), (MAV_CMD_SET_MESSAGE_INTERVAL, 3)
    ]  # fmt: skip
    ts = [r for r in recs if isinstance(r, Timesync)]
    assert len(ts) == 1 and ts[0].ts1 == 123456789 and ts[0].tc1 == pytest.approx(1e9, abs=1e7)
    imu = [r.time_source_ns for r in recs if isinstance(r, ImuSample)]
    first, second = [t for t in imu if t <= 1e9], [t for t in imu if t > 1.01e9]
    assert len(first) in (199, 200)  # the change applies from the next physics step
    assert 45 <= len(second) <= 50 and set(np.diff(second)) == {20_000_000}
    assert sim.codec.stats.garbage_bytes >= 30  # corrupt uplink bytes skipped and counted
    assert sim.stats.commands == 2 and sim.stats.timesyncs == 1


def test_manual_control_moves_the_vehicle_and_heartbeat_reports_mode():
    from firmware_bridge.mavlink.messages import ManualControl

    sim = Simulation(load_scene("paper"), "manual", seed=0, duration=3.0)
    gcs, station = MavlinkCodec(255, 190), MavlinkCodec()
    modes = []
    for item in sim.outputs():
        if item.channel == "mavlink":
            modes += [
                r.custom_mode for r in station.decode(item.data, 0) if isinstance(r, Heartbeat)
            ]
        if item.t_ns % 50_000_000 == 0 and item.t_ns < 2_000_000_000:
            sim.receive(gcs.encode(ManualControl(0, 0, 800, 0)))  # climb
    assert sim.stats.manual_controls >= 30
    assert sim.vehicle.body.z > sim.scene.start[2] + 0.5
    # PX4 custom modes at 1, 2, 3 s: POSCTL, POSCTL, then AUTO.LOITER (input stale at 2.5 s)
    assert modes == [3 << 16, 3 << 16, (4 << 16) | (3 << 24)]


def test_truth_document_is_json_with_contacts_and_gusts():
    sim = Simulation(load_scene("pillar"), "script:touch", seed=3, duration=12.0)
    for _ in sim.outputs():
        pass
    doc = json.loads(json.dumps(sim.truth()))
    assert doc["seed"] == 3 and doc["vehicle"]["radius"] == 0.2 and doc["vehicle"]["height"] == 0.1
    assert doc["scene"]["objects"][0]["type"] == "cylinder"
    kinds = [c["kind"] for c in doc["contacts"]]
    assert "touch" in kinds
    touch = next(c for c in doc["contacts"] if c["kind"] == "touch")
    assert touch["peak_accel_g"] > 2 and touch["end"] > touch["start"]
    assert len([k for k in kinds if k == "gust"]) == len(doc["gusts"])
