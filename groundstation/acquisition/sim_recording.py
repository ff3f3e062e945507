"""SITL straight to a recording: the bytes a station would have received, with simulated receive
times, written in exactly the layout the recorder process writes (``groundstation sitl --speed max
--record LOG.mcap``).

Model of the station side (pure and deterministic from the seed; :class:`StationWireModel`):

- **Clocks.** Firmware time = simulation time. The station's monotonic clock runs at the same
  rate from ``station_offset_ns`` (station = sim + offset), so TIMESYNC has a real offset to find.
- **MAVLink serial link.** Each frame enters the line ``latency`` after the vehicle emits it and
  occupies it for ``10 bits / baud`` per byte (frames queue back to back). The link process's
  reader wakes ``U(wake)`` after the first pending byte arrives, takes every byte that has
  arrived by then (frames may be cut: the decoder must reassemble them), and is busy
  ``U(busy)`` (1-5 ms: publishing, decoding) before it can read again. One read = one
  ``raw.mavlink`` message, log time = read time.
- **Station uplink.** At start the station asks for HIGHRES_IMU and ATTITUDE_QUATERNION at
  200 Hz (SET_MESSAGE_INTERVAL) and pings TIMESYNC every ``ping_period`` of station time
  (``ts1`` = station send time); the bytes reach the vehicle ``latency`` later, so its replies
  (COMMAND_ACK, TIMESYNC) appear in the received stream like live ones.
- **NatNet UDP.** Each datagram is received ``latency + U(jitter)`` after it was sent; one
  datagram = one ``raw.natnet`` message.

The live decoders (:mod:`groundstation.acquisition.decoders`) run on these chunks at their
receive times, and their samples are recorded too (as the link/mocap processes would have
published them), plus ``truth.json`` and the ``groundstation`` metadata, whose ``config`` holds
the simulated airframe as the station's ``[vehicle]`` table (:func:`station_vehicle`) and the
floor's height (:func:`station_config`): a replay,
``batch`` or ``bench sessions --logs`` of the recording starts from the body that was flown, as
it does from a live session's recorded configuration.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from firmware_bridge.frames import AxisConvention
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import SetMessageInterval, Timesync
from firmware_bridge.sitl.airframe import Airframe
from groundstation.acquisition import layout
from groundstation.acquisition.decoders import MavlinkStreamDecoder, NatNetStreamDecoder
from groundstation.acquisition.recorder import Recorder, RecorderStats
from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.config import to_toml
from groundstation.contact.vehicle import VehicleSettings

LINK_SOURCE = "sitl://pty"
MOCAP_SOURCE = "sitl://natnet"
NATNET_SENDER = "127.0.0.1:1511"


@dataclass(frozen=True)
class WireSettings:
    """Station-side link model (times in ns).

    Attributes
    ----------
    station_offset_ns : int
        Station monotonic clock minus simulation (firmware) clock.
    baud : int
        Serial line rate (10 bits per byte).
    latency_ns : int
        Fixed one-way latency of the serial link (USB/driver), both directions.
    wake_ns : (int, int)
        Range of the reader's wake-up delay after the first pending byte.
    busy_ns : (int, int)
        Range of the time a read keeps the reader busy (1-5 ms).
    natnet_latency_ns : int
        Fixed NatNet latency (Motive processing + network).
    natnet_jitter_ns : int
        Uniform extra NatNet delay, 0..jitter.
    ping_period_ns : int
        Station TIMESYNC ping period.
    """

    station_offset_ns: int = 1_000_000_000_000
    baud: int = 921_600
    latency_ns: int = 500_000
    wake_ns: tuple[int, int] = (50_000, 300_000)
    busy_ns: tuple[int, int] = (1_000_000, 5_000_000)
    natnet_latency_ns: int = 3_000_000
    natnet_jitter_ns: int = 500_000
    ping_period_ns: int = 1_000_000_000


@dataclass(frozen=True)
class WireChunk:
    """Bytes as the station received them: raw topic, station receive time (ns), data."""

    topic: str
    recv_ns: int
    data: bytes


class StationWireModel:
    """Pure model of the station's receive side (see the module docstring)."""

    def __init__(self, settings: WireSettings, seed: int):
        self.s = settings
        self.rng = np.random.default_rng([seed, 7])
        self.byte_ns = 10 * 1_000_000_000 / settings.baud
        self._line: list[tuple[float, bytes]] = []  # (arrival of first byte, bytes), queued
        self._line_free = 0.0
        self._reader_free = 0
        self._natnet_last = -1

    def mavlink(self, sim_ns: int, frame: bytes) -> None:
        """The vehicle put ``frame`` on the serial line at sim time ``sim_ns``."""
        start = max(sim_ns + self.s.station_offset_ns + self.s.latency_ns, self._line_free)
        self._line.append((start, frame))
        self._line_free = start + len(frame) * self.byte_ns

    def reads_until(self, station_ns: int) -> Iterator[WireChunk]:
        """Every read the station completes up to ``station_ns``."""
        while self._line:
            first = self._line[0][0]
            lo, hi = self.s.wake_ns
            read_at = int(max(first, self._reader_free) + self.rng.integers(lo, hi + 1))
            if read_at > station_ns:
                return
            out = bytearray()
            while self._line:
                t, data = self._line[0]
                n = min(len(data), int((read_at - t) // self.byte_ns) + 1) if read_at >= t else 0
                if n <= 0:
                    break
                out += data[:n]
                if n == len(data):
                    self._line.pop(0)
                else:
                    self._line[0] = (t + n * self.byte_ns, data[n:])
                    break
            lo, hi = self.s.busy_ns
            self._reader_free = read_at + int(self.rng.integers(lo, hi + 1))
            yield WireChunk(layout.RAW_MAVLINK_TOPIC, read_at, bytes(out))

    def natnet(self, sim_ns: int, datagram: bytes) -> WireChunk:
        """The mocap sent ``datagram`` at sim time ``sim_ns``: when the station got it."""
        jitter = int(self.rng.integers(0, self.s.natnet_jitter_ns + 1))
        t = sim_ns + self.s.station_offset_ns + self.s.natnet_latency_ns + jitter
        t = max(t, self._natnet_last + 1)  # one socket: datagrams arrive in order
        self._natnet_last = t
        return WireChunk(layout.RAW_NATNET_TOPIC, t, datagram)


def simulated_chunks(
    sim: Any, wire: StationWireModel, stop: Callable[[], bool] = lambda: False
) -> Iterator[WireChunk]:
    """Run ``sim`` (a ``firmware_bridge.sitl.runner.Simulation``) and yield what the station
    receives, with the station's SET_MESSAGE_INTERVAL and TIMESYNC pings fed back in."""
    s = wire.s
    codec = MavlinkCodec()  # the station's address (255/190)
    uplink: list[tuple[int, bytes]] = []  # (sim time it reaches the vehicle, bytes)
    for mid in (105, 31):
        uplink.append((s.latency_ns, codec.encode(SetMessageInterval(mid, 5000, 1, 1))))
    next_ping = 0
    for item in sim.outputs():
        if stop():
            break
        t = item.t_ns
        while next_ping <= t:  # station pings on its own clock
            ts1 = next_ping + s.station_offset_ns
            uplink.append((next_ping + s.latency_ns, codec.encode(Timesync(0, ts1))))
            next_ping += s.ping_period_ns
        while uplink and uplink[0][0] <= t:
            sim.receive(uplink.pop(0)[1])
        if item.channel == "mavlink":
            wire.mavlink(t, item.data)
            yield from wire.reads_until(t + s.station_offset_ns)
        elif item.channel == "mocap":
            yield wire.natnet(t, item.data)
    yield from wire.reads_until(2**62)


def station_vehicle(airframe: Airframe) -> VehicleSettings:
    """The station's ``[vehicle]`` for a simulated airframe, measured off its geometry.

    - The ``cylinder`` layout (the simple engine's body): the cylinder's radius and height.
    - A guarded quadrotor: its layout, arm length and guard plane; each guard to the rim's outer
      face (centreline radius + tube); the central box; legs down to the feet's outer surface.
      The station's legs are vertical rods on the arm diagonals while the simulated ones splay
      outwards, so the station's rods stand where the feet are (their horizontal distance from
      the centre plus the leg's radius): a side contact low on the body meets the feet.
    """
    if airframe.layout == "cylinder":
        return VehicleSettings(
            shape="cylinder", radius_m=airframe.cylinder_radius, height_m=airframe.cylinder_height
        )
    feet = max(float(np.hypot(foot[0], foot[1])) for _, foot in airframe.legs())
    return VehicleSettings(
        shape="guards",
        layout=airframe.layout,  # type: ignore[arg-type]
        arm_length_m=airframe.arm_length,
        guard_radius_m=airframe.guard_radius + airframe.guard_tube,
        guard_z_m=airframe.guard_z,
        body_half_m=tuple(airframe.body_half),  # type: ignore[arg-type]
        leg_length_m=round(airframe.bottom - airframe.body_half[2], 4),
        leg_offset_m=round(feet + airframe.leg_radius, 4),  # 0.1 mm: a readable table
    )


def vehicle_config(airframe: Airframe) -> str:
    """:func:`station_vehicle` as the ``[vehicle]`` TOML table stored in the recording."""
    return "[vehicle]\n" + to_toml(station_vehicle(airframe))


def station_config(sim: Any) -> str:
    """What the station knows of a simulated session: the airframe's ``[vehicle]`` and the
    height of the floor both physics engines put at the scene region's bottom
    (``contact.floor_z_m``: a candidate begun with the body at the floor is rejected)."""
    floor = float(sim.scene.region_min[2])
    return f"{vehicle_config(sim.vehicle.body.airframe)}\n[contact]\nfloor_z_m = {floor!r}\n"


def write_simulation(
    sim: Any,
    path: str,
    *,
    seed: int,
    created_by: str,
    motive_up: str = "y",
    wire: WireSettings | None = None,
    settings: AcquisitionSettings | None = None,
    stop: Callable[[], bool] = lambda: False,
    record_samples: bool = False,
) -> RecorderStats:
    """Record a SITL run: raw chunks, decoded samples, ``truth.json`` and metadata.

    Raises
    ------
    RecordingError
        The file cannot be written (message names the path and the OS error).
    """
    wire = wire or WireSettings()
    settings = settings or AcquisitionSettings(motive_up=motive_up)  # type: ignore[arg-type]
    model = StationWireModel(wire, seed)
    mav = MavlinkStreamDecoder(settings.timesync_window, int(settings.timesync_max_rtt_ms * 1e6))
    nat = NatNetStreamDecoder((4, 1), AxisConvention(motive_up))  # type: ignore[arg-type]
    seqs: dict[str, int] = {}
    meta = layout.station_metadata(
        station_version="sitl",
        created_by=created_by,
        config=station_config(sim),
        sources=[LINK_SOURCE, MOCAP_SOURCE],
        extra={"sitl_seed": str(seed), "wire_model": json.dumps(asdict(wire), sort_keys=True)},
    )
    natnet_meta = {layout.KEY_NATNET_VERSION: "4.1", layout.KEY_MOTIVE_UP: motive_up}
    with Recorder(path, metadata=meta) as rec:
        for chunk in simulated_chunks(sim, model, stop):
            if chunk.topic == layout.RAW_MAVLINK_TOPIC:
                rec.write(chunk.data, chunk.topic, chunk.recv_ns, source=LINK_SOURCE)
                decoded = mav.feed(chunk.data, chunk.recv_ns)
            else:
                rec.write(
                    chunk.data, chunk.topic, chunk.recv_ns,
                    source=MOCAP_SOURCE, channel_metadata=natnet_meta,
                )  # fmt: skip
                decoded = nat.feed(chunk.data, chunk.recv_ns)
            if record_samples:
                for d in decoded:
                    seq = seqs.get(d.topic, 0)
                    seqs[d.topic] = seq + 1
                    rec.write(d.envelope(seq), d.topic, d.recv_ns)
        truth = sim.truth()
        truth["clock"] = {
            "firmware_ns": "simulation time",
            "station_ns": "simulation time + station_offset_ns (log time axis)",
            "station_offset_ns": wire.station_offset_ns,
        }
        rec.add_truth(truth)
        return rec.close()
