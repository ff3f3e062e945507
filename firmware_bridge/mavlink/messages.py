"""Typed MAVLink records in SI units, and their mapping to/from pymavlink messages.

Every record is a frozen, slotted dataclass. Besides its payload it carries, keyword-only:

- ``time_source_ns``: the vehicle's own timestamp in integer ns (HIGHRES_IMU / ATT_POS_MOCAP
  ``time_usec`` x 1e3, SCALED_IMU / ATTITUDE / ATTITUDE_QUATERNION ``time_boot_ms`` x 1e6);
  0 for messages without one (HEARTBEAT, MANUAL_CONTROL, TIMESYNC, commands);
- ``time_recv_ns``: the station's monotonic receive time in integer ns (the ``recv_ns`` given to
  :meth:`MavlinkCodec.decode`); 0 when a record is built for encoding;
- ``system_id`` / ``component_id``: the sender's MAVLink address (set on decode).

Conventions (MAVLink common.xml): body frame FRD, local frame NED, quaternions (w, x, y, z)
rotating body FRD into local NED, Euler angles aerospace Z-Y-X (yaw, pitch, roll).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from firmware_bridge.errors import ProtocolError

#: Standard gravity used for the SCALED_IMU milli-g conversion (CGPM 1901), m/s^2.
STANDARD_GRAVITY = 9.80665
#: MAV_CMD_SET_MESSAGE_INTERVAL (common.xml, command id 511).
MAV_CMD_SET_MESSAGE_INTERVAL = 511

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def _meta() -> Any:
    return field(default=0, kw_only=True)


def _as_floats(value: Sequence[float], n: int, name: str) -> tuple[float, ...]:
    try:
        out = tuple(map(float, value))
    except (TypeError, ValueError) as exc:
        raise ProtocolError(f"{name} must be {n} numbers, got {value!r}") from exc
    if len(out) != n:
        raise ProtocolError(f"{name} must have {n} elements, got {len(out)}: {value!r}")
    return out


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """HEARTBEAT (id 0): MAV_TYPE, MAV_AUTOPILOT, MAV_MODE_FLAG bits, custom mode, MAV_STATE."""

    type: int
    autopilot: int
    base_mode: int
    custom_mode: int
    system_status: int
    mavlink_version: int = 3
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()


@dataclass(frozen=True, slots=True)
class ImuSample:
    """One IMU sample, body FRD.

    Attributes
    ----------
    accel : (3,) tuple of float, m/s^2
        Specific force including gravity, as the firmware reports it (about (0, 0, -9.81) at rest).
    gyro : (3,) tuple of float, rad/s
    msg_type : {"HIGHRES_IMU", "SCALED_IMU"}
        Wire message it came from / is encoded as. SCALED_IMU quantizes to 1 mG and 1 mrad/s.
    sensor_id : int
        HIGHRES_IMU ``id`` (IMU instance); 0 for SCALED_IMU.
    """

    accel: Vec3
    gyro: Vec3
    msg_type: str = "HIGHRES_IMU"
    sensor_id: int = 0
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()

    def __post_init__(self) -> None:
        object.__setattr__(self, "accel", _as_floats(self.accel, 3, "ImuSample.accel"))
        object.__setattr__(self, "gyro", _as_floats(self.gyro, 3, "ImuSample.gyro"))
        if self.msg_type not in ("HIGHRES_IMU", "SCALED_IMU"):
            raise ProtocolError(
                f"ImuSample.msg_type must be 'HIGHRES_IMU' or 'SCALED_IMU', got {self.msg_type!r}"
            )


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    """Attitude: quaternion (w, x, y, z) body FRD -> local NED, body rates in rad/s.

    ``msg_type`` is "ATTITUDE_QUATERNION" or "ATTITUDE" (Euler angles on the wire).
    """

    quaternion: Quat
    rates: Vec3
    msg_type: str = "ATTITUDE_QUATERNION"
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()

    def __post_init__(self) -> None:
        q = _as_floats(self.quaternion, 4, "AttitudeSample.quaternion")
        object.__setattr__(self, "quaternion", q)
        object.__setattr__(self, "rates", _as_floats(self.rates, 3, "AttitudeSample.rates"))
        if self.msg_type not in ("ATTITUDE_QUATERNION", "ATTITUDE"):
            raise ProtocolError(
                "AttitudeSample.msg_type must be 'ATTITUDE_QUATERNION' or 'ATTITUDE', "
                f"got {self.msg_type!r}"
            )


@dataclass(frozen=True, slots=True)
class Timesync:
    """TIMESYNC (id 111): ``tc1`` = 0 marks a request; a reply echoes ``ts1``. Both in ns."""

    tc1: int
    ts1: int
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()


@dataclass(frozen=True, slots=True)
class ManualControl:
    """MANUAL_CONTROL (id 69): x/y/r in -1000..1000, z (thrust) 0..1000, 32-bit button mask.

    ``buttons`` bits 0-15 travel in ``buttons``, bits 16-31 in the ``buttons2`` extension.
    """

    x: int
    y: int
    z: int
    r: int
    buttons: int = 0
    target_system: int = 1
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()


@dataclass(frozen=True, slots=True)
class MocapPose:
    """ATT_POS_MOCAP (id 138): quaternion (w, x, y, z) and position (x, y, z) in m, NED."""

    quaternion: Quat
    position: Vec3
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()

    def __post_init__(self) -> None:
        q = _as_floats(self.quaternion, 4, "MocapPose.quaternion")
        object.__setattr__(self, "quaternion", q)
        object.__setattr__(self, "position", _as_floats(self.position, 3, "MocapPose.position"))


@dataclass(frozen=True, slots=True)
class SetMessageInterval:
    """COMMAND_LONG with MAV_CMD_SET_MESSAGE_INTERVAL (511).

    ``interval_us``: period in microseconds; -1 disables the message, 0 restores the default.
    """

    message_id: int
    interval_us: int
    target_system: int = 1
    target_component: int = 1
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()


@dataclass(frozen=True, slots=True)
class CommandAck:
    """COMMAND_ACK (id 77): ``command`` (MAV_CMD) and ``result`` (MAV_RESULT, 0 = accepted)."""

    command: int
    result: int
    target_system: int = 0
    target_component: int = 0
    time_source_ns: int = _meta()
    time_recv_ns: int = _meta()
    system_id: int = _meta()
    component_id: int = _meta()


Record = (
    Heartbeat
    | ImuSample
    | AttitudeSample
    | Timesync
    | ManualControl
    | MocapPose
    | SetMessageInterval
    | CommandAck
)

_NAMES: dict[type, str] = {
    Heartbeat: "HEARTBEAT",
    Timesync: "TIMESYNC",
    ManualControl: "MANUAL_CONTROL",
    MocapPose: "ATT_POS_MOCAP",
    SetMessageInterval: "COMMAND_LONG",
    CommandAck: "COMMAND_ACK",
}


def message_name(record: Record) -> str:
    """MAVLink message name a record travels as (e.g. "HIGHRES_IMU", "COMMAND_LONG")."""
    name = getattr(record, "msg_type", None)
    return name if name is not None else _NAMES[type(record)]


# --- attitude maths -------------------------------------------------------------------------


def euler_to_quaternion(roll: float, pitch: float, yaw: float) -> Quat:
    """Z-Y-X Euler angles (rad) -> quaternion (w, x, y, z): q = q_z(yaw) q_y(pitch) q_x(roll).

    Same convention as MAVLink's ``mavlink_euler_to_quaternion`` (mavlink_conversions.h).
    """
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def quaternion_to_euler(q: Sequence[float]) -> Vec3:
    """Quaternion (w, x, y, z) -> (roll, pitch, yaw) in rad, Z-Y-X (mavlink_quaternion_to_euler)."""
    w, x, y, z = q
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 0.0:
        raise ProtocolError(f"quaternion {tuple(q)!r} has zero or NaN norm")
    w, x, y, z = w / n, x / n, y / n, z / n
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


# --- pymavlink message -> record ------------------------------------------------------------


def from_mavlink(msg: Any, recv_ns: int) -> Record | None:
    """Convert a decoded pymavlink message to a record, or None if we do not map that message.

    Parameters
    ----------
    msg : pymavlink ``MAVLink_message``
        A message decoded by the generated ``common`` dialect (header in ``msg._header``).
    recv_ns : int
        Station monotonic receive time, ns.
    """
    hdr = msg._header
    meta = {"time_recv_ns": recv_ns, "system_id": hdr.srcSystem, "component_id": hdr.srcComponent}
    mid = hdr.msgId
    if mid == 105:  # HIGHRES_IMU: m/s^2, rad/s, time_usec
        return ImuSample(
            (msg.xacc, msg.yacc, msg.zacc),
            (msg.xgyro, msg.ygyro, msg.zgyro),
            "HIGHRES_IMU",
            msg.id,
            time_source_ns=msg.time_usec * 1000,
            **meta,
        )
    if mid == 31:  # ATTITUDE_QUATERNION: q1..q4 = w, x, y, z
        return AttitudeSample(
            (msg.q1, msg.q2, msg.q3, msg.q4),
            (msg.rollspeed, msg.pitchspeed, msg.yawspeed),
            "ATTITUDE_QUATERNION",
            time_source_ns=msg.time_boot_ms * 1_000_000,
            **meta,
        )
    if mid == 26:  # SCALED_IMU: mG -> m/s^2 (x g0 / 1000), mrad/s -> rad/s (/ 1000)
        k = STANDARD_GRAVITY / 1000.0
        return ImuSample(
            (msg.xacc * k, msg.yacc * k, msg.zacc * k),
            (msg.xgyro / 1000.0, msg.ygyro / 1000.0, msg.zgyro / 1000.0),
            "SCALED_IMU",
            0,
            time_source_ns=msg.time_boot_ms * 1_000_000,
            **meta,
        )
    if mid == 30:  # ATTITUDE: roll, pitch, yaw (rad) -> quaternion
        return AttitudeSample(
            euler_to_quaternion(msg.roll, msg.pitch, msg.yaw),
            (msg.rollspeed, msg.pitchspeed, msg.yawspeed),
            "ATTITUDE",
            time_source_ns=msg.time_boot_ms * 1_000_000,
            **meta,
        )
    if mid == 0:
        return Heartbeat(
            msg.type, msg.autopilot, msg.base_mode, msg.custom_mode, msg.system_status,
            msg.mavlink_version, **meta,
        )  # fmt: skip
    if mid == 111:
        return Timesync(msg.tc1, msg.ts1, **meta)
    if mid == 69:
        buttons = (msg.buttons & 0xFFFF) | ((msg.buttons2 & 0xFFFF) << 16)
        return ManualControl(msg.x, msg.y, msg.z, msg.r, buttons, msg.target, **meta)
    if mid == 138:
        return MocapPose(
            tuple(msg.q), (msg.x, msg.y, msg.z), time_source_ns=msg.time_usec * 1000, **meta
        )
    if mid == 76 and msg.command == MAV_CMD_SET_MESSAGE_INTERVAL:
        return SetMessageInterval(
            int(round(msg.param1)),
            int(round(msg.param2)),
            msg.target_system,
            msg.target_component,
            **meta,
        )
    if mid == 77:
        return CommandAck(msg.command, msg.result, msg.target_system, msg.target_component, **meta)
    return None


# --- record -> pymavlink message ------------------------------------------------------------


def _int_in(value: int, lo: int, hi: int, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ProtocolError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return value


def _usec(ns: int, name: str) -> int:
    return _int_in(ns, 0, 2**63 - 1, name) // 1000


def _msec(ns: int, name: str) -> int:
    return _int_in(ns // 1_000_000, 0, 2**32 - 1, f"{name} // 1e6 (time_boot_ms)")


def _mg(a: float, name: str) -> int:
    v = round(a / STANDARD_GRAVITY * 1000.0)
    return _int_in(v, -32768, 32767, f"{name} in mG")


def to_mavlink(record: Record, mav: Any) -> Any:
    """Build the pymavlink message for a record with the generated ``MAVLink`` instance ``mav``.

    Raises
    ------
    ProtocolError
        A value does not fit its wire field (range, integer type, record type).
    """
    if isinstance(record, ImuSample):
        if record.msg_type == "SCALED_IMU":
            g = [_int_in(round(w * 1000.0), -32768, 32767, "gyro in mrad/s") for w in record.gyro]
            a = [_mg(v, "accel") for v in record.accel]
            ms = _msec(record.time_source_ns, "time_source_ns")
            return mav.scaled_imu_encode(ms, *a, *g, 0, 0, 0)
        return mav.highres_imu_encode(
            _usec(record.time_source_ns, "time_source_ns"), *record.accel, *record.gyro,
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0b111111, record.sensor_id,
        )  # fmt: skip
    if isinstance(record, AttitudeSample):
        ms = _msec(record.time_source_ns, "time_source_ns")
        if record.msg_type == "ATTITUDE":
            return mav.attitude_encode(ms, *quaternion_to_euler(record.quaternion), *record.rates)
        return mav.attitude_quaternion_encode(ms, *record.quaternion, *record.rates)
    if isinstance(record, Heartbeat):
        return mav.heartbeat_encode(
            record.type, record.autopilot, record.base_mode, record.custom_mode,
            record.system_status, record.mavlink_version,
        )  # fmt: skip
    if isinstance(record, Timesync):
        lim = 2**63 - 1
        tc1 = _int_in(record.tc1, -lim - 1, lim, "Timesync.tc1")
        return mav.timesync_encode(tc1, _int_in(record.ts1, -lim - 1, lim, "Timesync.ts1"))
    if isinstance(record, ManualControl):
        x = _int_in(record.x, -1000, 1000, "ManualControl.x")
        y = _int_in(record.y, -1000, 1000, "ManualControl.y")
        z = _int_in(record.z, 0, 1000, "ManualControl.z")
        r = _int_in(record.r, -1000, 1000, "ManualControl.r")
        b = _int_in(record.buttons, 0, 2**32 - 1, "ManualControl.buttons")
        tgt = _int_in(record.target_system, 0, 255, "ManualControl.target_system")
        return mav.manual_control_encode(tgt, x, y, z, r, b & 0xFFFF, b >> 16)
    if isinstance(record, MocapPose):
        return mav.att_pos_mocap_encode(
            _usec(record.time_source_ns, "time_source_ns"), record.quaternion, *record.position
        )
    if isinstance(record, SetMessageInterval):
        return mav.command_long_encode(
            _int_in(record.target_system, 0, 255, "target_system"),
            _int_in(record.target_component, 0, 255, "target_component"),
            MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            float(_int_in(record.message_id, 0, 2**24, "message_id")),
            float(_int_in(record.interval_us, -1, 2**31 - 1, "interval_us")),
            0.0, 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip
    if isinstance(record, CommandAck):
        return mav.command_ack_encode(
            _int_in(record.command, 0, 65535, "CommandAck.command"),
            _int_in(record.result, 0, 255, "CommandAck.result"),
            0, 0,
            _int_in(record.target_system, 0, 255, "target_system"),
            _int_in(record.target_component, 0, 255, "target_component"),
        )  # fmt: skip
    raise ProtocolError(
        f"cannot encode {type(record).__name__}: not a firmware_bridge.mavlink.messages record"
    )
