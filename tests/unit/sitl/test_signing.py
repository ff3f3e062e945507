"""The SITL with a signing key: unsigned or wrongly signed commands are rejected and counted."""

from __future__ import annotations

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import ManualControl, SetMessageInterval, Timesync
from firmware_bridge.sitl.runner import Simulation
from firmware_bridge.sitl.scene import load_scene

KEY = bytes(range(32))


def _station(key: bytes | None) -> MavlinkCodec:
    if key is None:
        return MavlinkCodec(255, 190)
    return MavlinkCodec(255, 190, signing_key=key, sign_outgoing=True, signing_timestamp=10**9)


def _commands(codec: MavlinkCodec) -> bytes:
    return b"".join(
        codec.encode(r)
        for r in (
            ManualControl(0, 0, 700, 0),
            SetMessageInterval(105, 10_000),
            ManualControl(0, 0, 710, 0),
            Timesync(0, 5),  # telemetry-class message: need not be signed
        )
    )


def test_with_a_key_only_signed_commands_are_obeyed():
    sim = Simulation(load_scene("wall"), "manual", 0, 1.0, signing_key=KEY)
    sim.receive(_commands(_station(None)))
    sim.receive(_commands(_station(bytes(range(1, 33)))))  # wrong key
    assert sim.stats.manual_controls == 0 and sim.stats.commands == 0
    assert sim.codec.stats.rejected_signature == 6
    assert sim.stats.timesyncs == 2
    sim.receive(_commands(_station(KEY)))
    assert sim.stats.manual_controls == 2 and sim.stats.commands == 1
    assert sim.codec.stats.rejected_signature == 6


def test_without_a_key_everything_is_obeyed_as_before():
    sim = Simulation(load_scene("wall"), "manual", 0, 1.0)
    sim.receive(_commands(_station(None)) + _commands(_station(KEY)))
    assert sim.stats.manual_controls == 4 and sim.codec.stats.rejected_signature == 0
