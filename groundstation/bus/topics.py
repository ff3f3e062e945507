"""The one table of bus topics: name, message type, schema version, publisher, drop policy.

Drop policies (enforced by the socket shells in :mod:`groundstation.bus.pubsub`):

- ``"lossless"``: raw bytes, samples, observations and events. Never dropped by the bus
  (unbounded high-water mark); sequence gaps on these topics are faults.
- ``"latest"``: state that a newer message supersedes (mesh, fit, status, health).
  A small high-water mark bounds memory; a slow subscriber loses intermediate values and the
  gap counter shows how many.

Times: every header carries ``source_ns`` (the data's own clock: firmware time for samples,
mocap time for poses, the station monotonic read time for raw chunks, the sample time that
triggered a derived message) and ``recv_ns`` (station monotonic receive time).

No topic name is a prefix of another, so a ZeroMQ prefix subscription to a name is exact.
Payload checks are cheap (types, required/unknown keys, dtype and shape) and run on publish and
on decode, so schema drift fails loudly in tests.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, Literal

import numpy as np

from groundstation.bus.errors import SchemaError

Policy = Literal["lossless", "latest"]
Kind = Literal["data", "event", "state"]

_F8 = ("<f8",)
_FLOAT = ("<f4", "<f8")
_INT = ("<i4", "<i8")


@dataclass(frozen=True)
class Field:
    """One JSON payload field: ``kind`` in str/int/float/bool/list/dict/any."""

    kind: str
    optional: bool = False
    nullable: bool = False
    choices: tuple[Any, ...] | None = None


@dataclass(frozen=True)
class Array:
    """One array: allowed dtype strings and a shape of ints (fixed) or names (bound per message)."""

    dtypes: tuple[str, ...]
    shape: tuple[int | str, ...]
    optional: bool = False


@dataclass(frozen=True)
class Topic:
    """Declaration of one topic.

    Parameters
    ----------
    name : str
        Topic name (also the ZeroMQ topic frame).
    type : str
        Message type name carried in the header.
    schema_version : int
        Payload schema version carried in the header; bump on any payload change.
    publisher_role : str
        The process that owns the topic ("any" for status/log, which every process publishes).
    policy : {"lossless", "latest"}
        Drop policy, see the module docstring.
    kind : {"data", "event", "state"}
        Data and events are lossless; state is latest-value.
    fields, arrays : mapping
        Payload fields and arrays.
    doc : str
        Meaning and units.
    """

    name: str
    type: str
    schema_version: int
    publisher_role: str
    policy: Policy
    kind: Kind
    fields: Mapping[str, Field] = field(default_factory=dict)
    arrays: Mapping[str, Array] = field(default_factory=dict)
    doc: str = ""

    def validate(self, payload: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> None:
        """Cheap schema check; raises :class:`SchemaError` naming the offending key."""
        _check_keys(self.name, "payload field", payload, self.fields)
        for key, spec in self.fields.items():
            if key in payload:
                _check_field(self.name, key, payload[key], spec)
        _check_keys(self.name, "array", arrays, self.arrays)
        dims: dict[str, int] = {}
        for key, spec in self.arrays.items():
            if key in arrays:
                _check_array(self.name, key, np.asarray(arrays[key]), spec, dims)


def _check_keys(topic: str, what: str, got: Mapping[str, Any], spec: Mapping[str, Any]) -> None:
    unknown = sorted(set(got) - set(spec))
    missing = sorted(k for k, s in spec.items() if not s.optional and k not in got)
    if unknown or missing:
        raise SchemaError(
            f"topic {topic!r}: {what}s do not match the table (unknown {unknown}, "
            f"missing {missing})",
            hint="update groundstation/bus/topics.py and bump schema_version",
        )


_KIND_CHECK = {
    "str": lambda v: isinstance(v, str),
    "int": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "float": lambda v: isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v),
    "bool": lambda v: isinstance(v, bool),
    "list": lambda v: isinstance(v, list | tuple),
    "dict": lambda v: isinstance(v, dict),
    "any": lambda v: True,
}


def _check_field(topic: str, key: str, value: Any, spec: Field) -> None:
    if value is None and spec.nullable:
        return
    if not _KIND_CHECK[spec.kind](value):
        raise SchemaError(
            f"topic {topic!r}: field {key!r} = {value!r} is not a (finite) {spec.kind}"
        )
    if spec.choices is not None and value not in spec.choices:
        raise SchemaError(f"topic {topic!r}: field {key!r} = {value!r} not in {spec.choices}")


def _check_array(topic: str, key: str, a: np.ndarray, spec: Array, dims: dict[str, int]) -> None:
    dtype = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
    if dtype.str not in spec.dtypes:
        raise SchemaError(
            f"topic {topic!r}: array {key!r} has dtype {a.dtype}, allowed {spec.dtypes}"
        )
    if a.ndim != len(spec.shape):
        raise SchemaError(
            f"topic {topic!r}: array {key!r} has shape {a.shape}, expected {spec.shape}"
        )
    for n, want in zip(a.shape, spec.shape, strict=True):
        if isinstance(want, str):
            want = dims.setdefault(want, n)
        if n != want:
            raise SchemaError(
                f"topic {topic!r}: array {key!r} has shape {a.shape}, expected {spec.shape} "
                f"with {dims}"
            )


def _t(*args: Any, **kw: Any) -> Topic:
    return Topic(*args, **kw)


_U8 = Array(("|u1",), ("n",))
_VEC3 = Array(_F8, (3,))
_QUAT = Array(_F8, (4,))

_TABLE = [
    _t("raw.mavlink", "raw_mavlink", 1, "link", "lossless", "data",
       {"link": Field("str")}, {"data": _U8},
       "Bytes chunk exactly as read from the firmware link (MAVLink 2, unparsed). "
       "source_ns: station monotonic time of the read; link: the link URI."),
    _t("raw.natnet", "raw_natnet", 2, "mocap", "lossless", "data",
       {"sender": Field("str"), "natnet_version": Field("str", optional=True),
        "motive_up": Field("str", optional=True, choices=("y", "z"))}, {"data": _U8},
       "One NatNet UDP datagram as received; sender: 'host:port'; natnet_version ('4.1') and "
       "motive_up ('y'/'z') as configured, stored by the recorder as channel metadata."),
    _t("raw.pilot", "raw_pilot", 1, "pilot", "lossless", "data",
       {"device": Field("str")}, {"data": _U8},
       "Linux joystick events as read (concatenated 8-byte js_event records)."),
    # Detector time axis (t_station_ns, station monotonic ns): see acquisition/decoders.py.
    # t_station_ns is optional only because older tests publish these topics with an empty
    # payload (and pin Header("imu_sample", 1, ...)); the station's decoders always set it.
    _t("samples.imu", "imu_sample", 1, "link", "lossless", "data",
       {"t_station_ns": Field("int", optional=True)},
       {"accel_mps2": _VEC3, "gyro_radps": _VEC3},
       "One IMU sample in the body frame (FRD): specific force m/s^2, angular rate rad/s. "
       "source_ns: firmware time of the sample; recv_ns: station receive time of its bytes; "
       "t_station_ns: firmware time mapped to the station clock by TIMESYNC (receive time "
       "before the first round trip)."),
    _t("samples.attitude", "attitude_sample", 2, "link", "lossless", "data",
       {"t_station_ns": Field("int", optional=True)},
       {"q_wxyz": _QUAT, "rates_radps": Array(_F8, (3,), optional=True)},
       "Attitude: unit quaternion (w, x, y, z) rotating body FRD to earth NED; times as for "
       "samples.imu."),
    _t("samples.pose", "pose_sample", 2, "mocap", "lossless", "data",
       {"body_id": Field("int"), "valid": Field("bool"),
        "t_station_ns": Field("int", optional=True)},
       {"position_m": _VEC3, "q_wxyz": _QUAT},
       "Mocap rigid-body pose in the world frame (m, quaternion w-first; NaN when not valid). "
       "source_ns: mocap time; recv_ns: station receive time; t_station_ns: receive time minus "
       "the configured mocap latency (already compensated: align with latency 0)."),
    _t("link.health", "link_health", 2, "link", "latest", "state",
       {"connected": Field("bool"), "rx_bytes": Field("int"), "rx_messages": Field("int"),
        "bad_frames": Field("int"), "last_heartbeat_ns": Field("int", nullable=True),
        "lost_frames": Field("int", optional=True),
        "garbage_bytes": Field("int", optional=True),
        "timesync_offset_ns": Field("int", optional=True, nullable=True),
        "timesync_rtt_ns": Field("int", optional=True, nullable=True),
        "rates_hz": Field("dict", optional=True)}, {},
       "Firmware link counters (cumulative) and the station time of the last HEARTBEAT; "
       "lost_frames (MAVLink sequence gaps), garbage_bytes, the TIMESYNC offset "
       "(vehicle - station, ns) and RTT, and message rates (Hz) over the last window."),
    _t("contact.event", "contact_event", 1, "detector", "lossless", "event",
       {"id": Field("int"), "state": Field("str", choices=("begin", "end", "rejected")),
        "peak_g": Field("float"), "p_false": Field("float", optional=True),
        "p_false_impulse": Field("float", optional=True),
        "dv_mps": Field("float", optional=True), "rebound": Field("bool", optional=True),
        "features": Field("dict", optional=True),
        "floor_clearance_m": Field("float", optional=True),
        "at_floor": Field("bool", optional=True),
        "tilt_deg": Field("float", optional=True), "upset": Field("bool", optional=True)},
       {"position_m": _VEC3, "normal": _VEC3},
       "A contact began or ended: drone position (m, world) at its onset, outward unit normal, "
       "peak in G. The impulse detector sends begin and end together once it has decided, "
       "with p_false (probability from the physics that the event is not a contact; "
       "p_false_impulse: from its own impulse, without the burst context), dv_mps "
       "(impulse per unit mass along the normal), rebound and the named evidence features; "
       "state 'rejected': a candidate too likely false to make observations, or one begun "
       "with the body at the floor (at_floor; floor_clearance_m: the body's lowest point "
       "above the configured floor at the onset, m) or tilted past contact.reject_tilt_deg "
       "(upset; tilt_deg: the thrust axis from the vertical at the onset)."),
    _t("observations", "observation", 2, "detector", "lossless", "data",
       {"id": Field("int"), "label": Field("int", choices=(-1, 0, 1)),
        "event_id": Field("int", optional=True), "accel_g": Field("float", optional=True),
        "p_false": Field("float", optional=True),
        "dv_mps": Field("float", optional=True, nullable=True),
        "rebound": Field("bool", optional=True),
        "sigma_m": Field("float", optional=True, nullable=True)},
       {"x_m": _VEC3, "normal": _VEC3},
       "One GPIS observation: point x (m, world), label y (0 surface, -1 inside, +1 outside), "
       "outward unit normal (zeros for external points); source_ns: the data time it refers to "
       "(station axis, ns); event_id: the contact event of a contact/internal point (-1 for "
       "external points); accel_g: filtered |a| in G when it was emitted; p_false, dv_mps, "
       "rebound: its event's evidence (impulse detector); sigma_m: placement uncertainty (m)."),
    _t("mapper.fit", "mapper_fit", 2, "mapper", "latest", "state",
       {"fit_index": Field("int"), "reliable": Field("bool", optional=True),
        "reasons": Field("list", optional=True), "data_ns": Field("int", optional=True),
        "lag_s": Field("float", optional=True), "fit_s": Field("float", optional=True),
        "timings": Field("dict", optional=True),
        "hyperparameters": Field("dict", optional=True),
        "flagged_events": Field("list", optional=True),
        "awaiting_events": Field("list", optional=True)},
       {"ids": Array(_INT, ("n",)), "u": Array(_FLOAT, ("n",)), "flags": Array(("|u1",), ("n",))},
       "Per-observation uncertainty u_i = beta~_i/alpha~_i and flag bits after a refit "
       "(bit 0 = flagged false-positive contact; bit 1, with bit 0 = flagged only because no "
       "other touch corroborates it). reliable/reasons: the fit diagnosis "
       "(mapping.diagnostics; an unreliable fit keeps the last good mesh); data_ns: data time "
       "of the newest observation in the fit; lag_s: data time received minus data_ns when "
       "published; fit_s: wall seconds of the refit; timings: where they went (rows_s, fit_s, "
       "mesh_s and of it mesh_gp_s, mesh_offset_s; total_s); hyperparameters: lengthscale, ...; "
       "flagged_events: contact event ids flagged as false positives; awaiting_events: those "
       "of them a second touch beside them would keep (mapper.lone_flag_p)."),
    _t("mesh", "mesh", 1, "mapper", "latest", "state",
       {"fit_index": Field("int")},
       {"vertices": Array(_FLOAT, ("v", 3)), "triangles": Array(_INT, ("t", 3)),
        "vertex_std": Array(_FLOAT, ("v",))},
       "Surface mesh {mu = 0}: vertices (m, world), triangles (vertex indices), predictive std."),
    _t("status", "status", 1, "any", "latest", "state",
       {"process": Field("str"), "state": Field("str"), "topics": Field("dict"),
        "text": Field("str", optional=True)}, {},
       "Per-process status: state and per-topic counters (rate_hz, received, gaps, ...)."),
    # Lossless, not latest-value: every command is recorded with the session (issue 6) and the
    # link turns each one into exactly one MANUAL_CONTROL. A stalled link cannot replay a stale
    # backlog: it drops commands older than its max command age (source_ns = the pilot's tick
    # time, same monotonic clock), so "commands stop -> MANUAL_CONTROL stops" still holds.
    _t("pilot.command", "pilot_command", 1, "pilot", "lossless", "data",
       {"x": Field("int"), "y": Field("int"), "z": Field("int"), "r": Field("int"),
        "buttons": Field("int"), "enabled": Field("bool")}, {},
       "Shaped MANUAL_CONTROL setpoint (-1000..1000; z 0..1000), one per pilot tick while armed; "
       "source_ns: the pilot's tick time (station monotonic)."),
    _t("pilot.event", "pilot_event", 1, "pilot", "lossless", "event",
       {"event": Field("str"), "text": Field("str", optional=True)}, {},
       "Pilot path events: device lost/found, failsafe engaged/cleared, e-stop."),
    _t("log", "log", 1, "any", "lossless", "event",
       {"process": Field("str"), "level": Field("str", choices=("info", "warning", "error")),
        "message": Field("str"), "hint": Field("str", optional=True, nullable=True)}, {},
       "Warnings and errors from worker processes (shown in the status line)."),
]  # fmt: skip

TOPICS: Mapping[str, Topic] = MappingProxyType({t.name: t for t in _TABLE})


def get_topic(name: str, table: Mapping[str, Topic] = TOPICS) -> Topic:
    """Look up a topic; raises :class:`SchemaError` listing the known names."""
    try:
        return table[name]
    except KeyError:
        raise SchemaError(f"unknown topic {name!r}; known: {sorted(table)}") from None
