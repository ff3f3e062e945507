"""The Foxglove channels of a recording (a file-format contract, beside ``acquisition/layout``).

Every channel below uses MCAP ``message_encoding = "protobuf"`` with a schema of encoding
``"protobuf"`` whose name is the Foxglove well-known schema (``foxglove.SceneUpdate``, ...) and
whose data is the serialized ``FileDescriptorSet`` of that message (with its dependencies), so
any MCAP reader decodes them with the ``foxglove_schemas_protobuf`` classes or the schema alone.
Topics start with ``/`` and so never collide with the station's own channels.

Frames (``frame_id``): ``world`` is the station's world frame (right-handed, z up, metres: the
mocap frame after the axis conversion of ``firmware_bridge.frames``); ``body`` is the vehicle,
placed in ``world`` by ``/tf`` (from the mocap pose); ``ned`` is the firmware's local NED frame,
which has no known transform to ``world`` (its attitude is recorded for plots only).

Times: ``log_time`` is the message's time on the recording's log axis (the receive time of the
bus message it came from; for derived data, the data time it refers to) and every ``timestamp``
field holds the data time on that same axis (station monotonic ns), so plots and the 3D view
line up with the raw channels.
"""

from __future__ import annotations

import dataclasses
from functools import cache
from types import MappingProxyType

PROTOBUF = "protobuf"


@dataclasses.dataclass(frozen=True)
class FoxgloveChannel:
    """One Foxglove channel: topic, schema full name, what it holds (units and frame)."""

    topic: str
    schema: str
    doc: str


_TABLE = (
    FoxgloveChannel(
        "/map/mesh", "foxglove.SceneUpdate",
        "the mapped surface: entity 'mesh' (one per mesh id, replaced on every update) with one "
        "TriangleListPrimitive in frame world, vertex colours = predictive std (viridis, range in "
        "the entity metadata std_min/std_max), metadata fit_index, vertices, triangles",
    ),
    FoxgloveChannel(
        "/map/contacts", "foxglove.PointCloud",
        "every contact point (label 0 observation) in frame world, float32 x y z, uint8 red "
        "green blue alpha (green trusted, magenta flagged, grey pending), uint8 state (0 "
        "trusted, 1 flagged, 2 pending), float32 p_false (NaN when the detector gave none), "
        "float32 u (the fit's per-datum uncertainty, NaN before a fit), int32 event_id; "
        "republished whenever a contact arrives or a fit changes the flags",
    ),
    FoxgloveChannel(
        "/vehicle/trajectory", "foxglove.SceneUpdate",
        "entity 'trajectory': the flown path as one LINE_STRIP in frame world (mocap positions "
        "at least 5 cm apart, coarsened beyond 2000 points), replaced once a second of data",
    ),
    FoxgloveChannel(
        "/vehicle/pose", "foxglove.PoseInFrame",
        "mocap pose of the vehicle in frame world (metres, quaternion body -> world), up to "
        "50 Hz of data time",
    ),
    FoxgloveChannel(
        "/tf", "foxglove.FrameTransform",
        "world -> body, from the valid mocap poses, up to 50 Hz (the frame tree: world, body)",
    ),
    FoxgloveChannel(
        "/vehicle/attitude", "foxglove.PoseInFrame",
        "firmware attitude: orientation body FRD -> local NED in frame ned (position zero), "
        "up to 50 Hz",
    ),
    FoxgloveChannel(
        "/imu/accel", "foxglove.Vector3",
        "IMU specific force, body FRD, m/s^2 (x, y, z), up to 50 Hz (the raw channel has all)",
    ),
    FoxgloveChannel(
        "/imu/gyro", "foxglove.Vector3", "IMU angular rate, body FRD, rad/s (x, y, z), up to 50 Hz"
    ),
    FoxgloveChannel(
        "/detector/signal", "foxglove.Vector3",
        "the contact detector's signal, one per IMU sample: x = filtered |a| (gravity removed, "
        "world frame) in G, y = contact threshold a0 in G (contact.threshold_g), z = release "
        "level in G (release_ratio * a0). Plot .x against .y",
    ),
    FoxgloveChannel(
        "/detector/event_peak", "foxglove.Vector3",
        "one per contact event message: x = peak filtered |a| in G, y = event id, z = 1 at the "
        "begin and 0 at the end of the event (plot .x as dots on the signal plot)",
    ),
    FoxgloveChannel(
        "/detector/events", "foxglove.Event",
        "one per ended contact event: start and end time, metadata id, peak_g, position, "
        "normal, p_false when given",
    ),
    FoxgloveChannel(
        "/log", "foxglove.Log",
        "warnings and errors of every process (log topic), status text of every process "
        "(status topic, level INFO), contact events and fits (name detector / mapper)",
    ),
)  # fmt: skip

#: Topic -> channel, in the order above.
CHANNELS = MappingProxyType({c.topic: c for c in _TABLE})


def message_class(schema: str):
    """The ``foxglove_schemas_protobuf`` class of a schema full name (``foxglove.Log``)."""
    import importlib

    if not schema.startswith("foxglove."):
        raise KeyError(schema)
    name = schema.split(".", 1)[1]
    module = importlib.import_module(f"foxglove_schemas_protobuf.{name}_pb2")
    return getattr(module, name)


@cache
def schema_data(schema: str) -> bytes:
    """Serialized ``FileDescriptorSet`` of a Foxglove schema and its dependencies."""
    from mcap_protobuf.schema import build_file_descriptor_set

    return build_file_descriptor_set(message_class(schema)).SerializeToString()
