"""The SITL as a pure generator of timestamped wire bytes, plus the real-time pacing shell.

:meth:`Simulation.outputs` advances the vehicle one physics step at a time on a simulated clock
and yields :class:`Outgoing` (sim time ns, channel ``"mavlink"`` or ``"mocap"``, bytes) whenever a
stream is due: HIGHRES_IMU and ATTITUDE_QUATERNION (200 Hz by default, changeable with
SET_MESSAGE_INTERVAL), HEARTBEAT (1 Hz), NatNet 4.1 frames of rigid body 1 (200 Hz), plus
replies (COMMAND_ACK, TIMESYNC). :meth:`Simulation.receive` feeds the station's bytes in. Same
seed and same inputs -> identical bytes. :func:`run_paced` is the thin outer layer that sends
each item to its sink when its deadline (start + t / speed) comes, against absolute deadlines so
late wake-ups never accumulate drift; a recorder is just another sink. With
``wait_for_station`` it first holds the vehicle on the ground, sending only a standby HEARTBEAT
once a second, until the station's first message arrives (its heartbeat or a command): the
simulated clock starts then, so nothing is flown or sent before anyone listens.
"""

from __future__ import annotations

import math
import selectors
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    MAV_CMD_SET_MESSAGE_INTERVAL,
    AttitudeSample,
    CommandAck,
    Heartbeat,
    ImuSample,
    ManualControl,
    SetMessageInterval,
    Timesync,
)
from firmware_bridge.natnet import FrameOfData, RigidBody, encode_frame_of_data
from firmware_bridge.sitl.imu_model import quat_mul
from firmware_bridge.sitl.pilots import make_pilot
from firmware_bridge.sitl.scene import Scene
from firmware_bridge.sitl.truth import truth_document
from firmware_bridge.sitl.vehicle import LANDED, Vehicle, VehicleSettings, planning_cylinder

HIGHRES_IMU_ID, ATTITUDE_QUATERNION_ID, HEARTBEAT_ID = 105, 31, 0
DEFAULT_INTERVALS_NS = {
    HIGHRES_IMU_ID: 5_000_000,
    ATTITUDE_QUATERNION_ID: 5_000_000,
    HEARTBEAT_ID: 1_000_000_000,
}
MAV_RESULT_ACCEPTED, MAV_RESULT_UNSUPPORTED = 0, 3
# PX4 custom_mode: main mode << 16 | sub mode << 24 (px4_custom_mode.h).
_PX4_MODE = {
    "MANUAL": 3 << 16,
    "HOLD": (4 << 16) | (3 << 24),
    "LAND": (4 << 16) | (6 << 24),
    "LANDED": (4 << 16) | (3 << 24),
    "SCRIPT": (4 << 16) | (4 << 24),
    "SCRIPT_DONE": (4 << 16) | (3 << 24),
}


@dataclass(frozen=True)
class MocapSettings:
    """NatNet output: rate (Hz), Motive up axis, noise (m, rad, 1 sigma), frame drop probability."""

    rate: float = 200.0
    up: str = "y"
    position_noise: float = 0.0005
    rotation_noise: float = 0.002
    drop_probability: float = 0.005
    rigid_body_id: int = 1


@dataclass(frozen=True)
class Outgoing:
    """Bytes due at sim time ``t_ns`` on ``channel`` ("mavlink" or "mocap")."""

    t_ns: int
    channel: str
    data: bytes


@dataclass
class SimStats:
    mavlink_frames: int = 0
    mocap_frames: int = 0
    mocap_dropped: int = 0  # simulated tracking drop-outs (not sent on purpose)
    commands: int = 0
    manual_controls: int = 0
    timesyncs: int = 0
    station_records: int = 0  # every record decoded from the station's uplink
    per_message: dict[int, int] = field(default_factory=dict)


class Simulation:
    """Pure, deterministic SITL core (no sockets, no clock reads).

    Parameters
    ----------
    scene : Scene
    pilot : "manual" or "script:NAME" (:data:`~firmware_bridge.sitl.pilots.PILOTS`)
    seed : int
    duration : s of simulated time, or None for no end (``outputs`` then never stops)
    signing_key : 32 bytes, optional
        MAVLink 2 signing key: commands (MANUAL_CONTROL, COMMAND_LONG, ATT_POS_MOCAP) must then
        be signed with it; unsigned or wrongly signed ones are rejected and counted
        (``codec.stats.rejected_signature``), like a PX4 with signing enabled.
    """

    def __init__(
        self,
        scene: Scene,
        pilot: str = "manual",
        seed: int = 0,
        duration: float | None = None,
        vehicle: VehicleSettings | None = None,
        mocap: MocapSettings | None = None,
        system_id: int = 1,
        signing_key: bytes | None = None,
    ):
        self.scene, self.seed, self.duration, self.pilot_name = scene, seed, duration, pilot
        vs = vehicle or VehicleSettings()
        script = None
        if pilot != "manual":
            name = pilot.split(":", 1)[1] if pilot.startswith("script:") else pilot
            radius, height = planning_cylinder(vs)
            script = make_pilot(name, scene, radius, height, seed=seed)
        self.vehicle = Vehicle(scene, script, seed, vs)
        self.mocap = mocap or MocapSettings()
        self.mocap_rng = np.random.default_rng([seed, 1])
        self.codec = MavlinkCodec(
            system_id=system_id,
            component_id=1,
            signing_key=signing_key,
            require_signed=signing_key is not None,
        )
        self.system_id = system_id
        self.intervals = dict(DEFAULT_INTERVALS_NS)
        self.next_due = dict(self.intervals)  # first samples one interval after t = 0
        self.mocap_interval = int(round(1e9 / self.mocap.rate)) if self.mocap.rate > 0 else 0
        self.mocap_next = self.mocap_interval
        self.mocap_frame_id = 0
        self.replies: list[object] = []
        self.stats = SimStats()
        self.finished = False

    # -- inbound -------------------------------------------------------------------------------
    def receive(self, data: bytes) -> None:
        """Station -> vehicle bytes (any split; corrupt bytes are skipped and counted)."""
        for rec in self.codec.decode(data, self.vehicle.t_ns):
            self.stats.station_records += 1
            if isinstance(rec, ManualControl):
                if rec.target_system in (0, self.system_id):
                    self.stats.manual_controls += 1
                    self.vehicle.manual_control(rec.x, rec.y, rec.z, rec.r)
            elif isinstance(rec, SetMessageInterval):
                self.stats.commands += 1
                self.replies.append(self._set_interval(rec))
            elif isinstance(rec, Timesync) and rec.tc1 == 0:
                self.stats.timesyncs += 1
                self.replies.append(Timesync(tc1=self.vehicle.t_ns, ts1=rec.ts1))

    def _set_interval(self, rec: SetMessageInterval) -> CommandAck:
        mid = rec.message_id
        if mid not in self.intervals:
            return CommandAck(MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_UNSUPPORTED)
        if rec.interval_us == 0:
            self.intervals[mid] = DEFAULT_INTERVALS_NS[mid]
        elif rec.interval_us < 0:
            self.intervals[mid] = 0  # disabled
        else:
            self.intervals[mid] = max(self.vehicle.step_ns, rec.interval_us * 1000)
        self.next_due[mid] = self.vehicle.t_ns + self.vehicle.step_ns
        return CommandAck(MAV_CMD_SET_MESSAGE_INTERVAL, MAV_RESULT_ACCEPTED)

    # -- outbound ------------------------------------------------------------------------------
    def _mav(self, rec: object, mid: int) -> bytes:
        self.stats.mavlink_frames += 1
        self.stats.per_message[mid] = self.stats.per_message.get(mid, 0) + 1
        return self.codec.encode(rec)  # type: ignore[arg-type]

    def standby_heartbeat(self) -> bytes:
        """A HEARTBEAT of the vehicle on the ground (standby), for before the clock starts."""
        return self._mav(Heartbeat(2, 12, 1 | 16 | 8 | 64, _PX4_MODE["LANDED"], 3), HEARTBEAT_ID)

    def _heartbeat(self) -> Heartbeat:
        v = self.vehicle
        mode = v.mode
        armed = mode != LANDED
        # MAV_MODE_FLAG: custom mode enabled 1, stabilize 16, guided 8, manual input 64, armed 128
        base = 1 | 16 | 8 | 64 | (128 if armed else 0)
        status = 4 if armed else 3  # MAV_STATE_ACTIVE / STANDBY
        return Heartbeat(2, 12, base, _PX4_MODE.get(mode, 0), status)  # QUADROTOR, PX4

    def _mocap_frame(self, t_ns: int) -> bytes | None:
        m, rng, b = self.mocap, self.mocap_rng, self.vehicle.body
        self.mocap_frame_id += 1
        noise = rng.standard_normal(6).tolist()
        if rng.random() < m.drop_probability:
            self.stats.mocap_dropped += 1
            return None
        x, y, z = (b.position[i] + m.position_noise * noise[i] for i in range(3))
        h = 0.5 * m.rotation_noise
        dq = (1.0, h * noise[3], h * noise[4], h * noise[5])  # small-angle noise, world frame
        qw, qx, qy, qz = quat_mul(dq, b.quaternion)
        s = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qw, qx, qy, qz = qw * s, qx * s, qy * s, qz * s
        # firmware_bridge.frames.world_to_motive in plain floats (Y-up: x_m = x, y_m = z,
        # z_m = -y, same permutation for the quaternion axes; Z-up: identity), (x, y, z, w).
        if m.up == "y":
            pm, qm = (x, z, -y), (qx, qz, -qy, qw)
        else:
            pm, qm = (x, y, z), (qx, qy, qz, qw)
        body = RigidBody(m.rigid_body_id, pm, qm, 0.0003, True)
        frame = FrameOfData(self.mocap_frame_id, (body,), t_ns / 1e9)
        self.stats.mocap_frames += 1
        return encode_frame_of_data(frame, version=(4, 1))

    def outputs(self) -> Iterator[Outgoing]:
        """Advance the simulation and yield every outgoing item in time order."""
        v = self.vehicle
        end = None if self.duration is None else int(round(self.duration * 1e9))
        intervals, due = self.intervals, self.next_due
        while end is None or v.t_ns < end:
            v.step()
            t = v.t_ns
            while self.replies:
                rec = self.replies.pop(0)
                mid = 77 if isinstance(rec, CommandAck) else 111
                yield Outgoing(t, "mavlink", self._mav(rec, mid))
            if intervals[HEARTBEAT_ID] and t >= due[HEARTBEAT_ID]:
                due[HEARTBEAT_ID] = _advance(due[HEARTBEAT_ID], intervals[HEARTBEAT_ID], t)
                yield Outgoing(t, "mavlink", self._mav(self._heartbeat(), HEARTBEAT_ID))
            if intervals[HIGHRES_IMU_ID] and t >= due[HIGHRES_IMU_ID]:
                due[HIGHRES_IMU_ID] = _advance(due[HIGHRES_IMU_ID], intervals[HIGHRES_IMU_ID], t)
                accel, gyro = v.imu_sample()
                rec = ImuSample(accel, gyro, time_source_ns=t)
                yield Outgoing(t, "mavlink", self._mav(rec, HIGHRES_IMU_ID))
            a_id = ATTITUDE_QUATERNION_ID
            if intervals[a_id] and t >= due[a_id]:
                due[a_id] = _advance(due[a_id], intervals[a_id], t)
                q, rates = v.attitude()
                rec = AttitudeSample(q, rates, time_source_ns=t)
                yield Outgoing(t, "mavlink", self._mav(rec, a_id))
            if self.mocap_interval and t >= self.mocap_next:
                self.mocap_next = _advance(self.mocap_next, self.mocap_interval, t)
                data = self._mocap_frame(t)
                if data is not None:
                    yield Outgoing(t, "mocap", data)
        self.finished = True

    # -- ground truth --------------------------------------------------------------------------
    def truth(self) -> dict:
        """The truth sidecar document for everything simulated so far."""
        v = self.vehicle
        s = v.settings
        q = s.quad
        b = v.body
        gusts = v.gusts.history
        g = s.gusts
        if b.name == "simple":
            vehicle = {
                "radius": q.radius,
                "height": q.height,
                "mass": q.mass,
                "contact_stiffness": q.contact_stiffness,
                "contact_restitution": q.contact_restitution,
            }
            physics = {"engine": "simple", "rate": s.physics_rate}
        else:
            vehicle = {
                "radius": b.airframe.reach_max,  # the cylinder circumscribing the body
                "height": b.airframe.planning_height,
                "mass": b.mass,
                "contact_stiffness": None,
                "contact_restitution": s.mujoco.nominal_restitution,
            }
            physics = {"engine": b.name, "rate": s.physics_rate, **b.describe()}
        log = getattr(v.pilot, "maneuvers", None)
        return truth_document(
            scene=self.scene.to_dict(),
            vehicle=vehicle,
            seed=self.seed,
            events=v.tracker.all_events(gusts),
            gusts=gusts,
            settings={
                "pilot": self.pilot_name,
                "physics_rate": s.physics_rate,
                "gust_rate_per_min": g.rate_per_min,
                "mocap_up": self.mocap.up,
                "mocap_drop_probability": self.mocap.drop_probability,
                "physics": b.name,
                "gust_force_n": [g.peak_min * b.mass, g.peak_max * b.mass],
                "gust_duration_s": [g.duration_min, g.duration_max],
                "gust_cluster_probability": g.cluster_probability,
                "gust_cluster_size": list(g.cluster_size),
            },
            duration=v.t,
            physics=physics,
            airframe=b.airframe.to_dict(),
            maneuvers=[m.to_dict() for m in log.records] if log is not None else [],
        )


def _advance(due: int, interval: int, now: int) -> int:
    due += interval
    return due if due > now else now + interval


# -- pacing shell --------------------------------------------------------------------------------


class Sink(Protocol):
    def send(self, data: bytes) -> None: ...


class Source(Protocol):
    def fileno(self) -> int: ...
    def recv(self) -> bytes: ...
    def flush(self) -> None: ...


def wait_for_station(
    sim: Simulation,
    sinks: Mapping[str, Sink],
    sel: selectors.BaseSelector,
    stop: Callable[[], bool],
    on_wait: Callable[[float], None] | None = None,
) -> bool:
    """Hold the vehicle until the station sends anything (see the module docstring): a standby
    HEARTBEAT every second meanwhile (a listening UDP station learns the address from it).
    Returns False when ``stop`` ended the wait."""
    t0 = next_beat = time.monotonic()
    heard = sim.stats.station_records
    mav = sinks.get("mavlink")
    while sim.stats.station_records == heard:
        if stop():
            return False
        now = time.monotonic()
        if now >= next_beat:
            if mav is not None:
                mav.send(sim.standby_heartbeat())
            if on_wait is not None:
                on_wait(now - t0)
            next_beat += 1.0
        for key, _ in sel.select(min(0.1, max(0.0, next_beat - time.monotonic()))):
            data = key.data.recv()
            if data:
                sim.receive(data)
            key.data.flush()
    return True


def run_paced(
    sim: Simulation,
    sinks: Mapping[str, Sink],
    sources: list[Source],
    speed: float = 1.0,
    stop: Callable[[], bool] = lambda: False,
    on_second: Callable[[float], None] | None = None,
    wait: bool = False,
    on_wait: Callable[[float], None] | None = None,
) -> None:
    """Send ``sim.outputs()`` to ``sinks[channel]`` at ``speed`` x real time (inf = no pacing).

    Deadlines are absolute (start + t_sim / speed), so a late wake-up sends everything that is
    due at once and never shifts later deadlines. While waiting, the ``sources`` (the station's
    command uplink) are read and fed to ``sim.receive``. ``on_second`` is called with the sim
    time at most once per wall second (status line). ``wait``: hold the vehicle until the
    station is heard first (:func:`wait_for_station`; ``on_wait`` gets the seconds waited).
    """
    sel = selectors.DefaultSelector()
    for src in sources:
        sel.register(src.fileno(), selectors.EVENT_READ, src)
    if wait and not wait_for_station(sim, sinks, sel, stop, on_wait):
        sel.close()
        return
    pace = math.isfinite(speed)
    start = time.monotonic_ns()
    last_status = start
    next_poll = 0
    scale = 1.0 / speed if pace else 0.0

    def pump(timeout: float) -> None:
        for key, _ in sel.select(timeout):
            data = key.data.recv()
            if data:
                sim.receive(data)

    try:
        for item in sim.outputs():
            if stop():
                break
            deadline = start + int(item.t_ns * scale)
            now = time.monotonic_ns()
            while pace and now < deadline:
                pump((deadline - now) / 1e9)
                for src in sources:
                    src.flush()
                if stop():
                    return
                now = time.monotonic_ns()
            if item.t_ns >= next_poll:  # also read commands when running behind / unpaced
                next_poll = item.t_ns + 5_000_000
                pump(0.0)
            sink = sinks.get(item.channel)
            if sink is not None:
                sink.send(item.data)
            if on_second is not None and now - last_status >= 1_000_000_000:
                last_status = now
                on_second(item.t_ns / 1e9)
    finally:
        sel.close()
