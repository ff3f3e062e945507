"""The Foxglove translator (pure): every message decodes with foxglove_schemas_protobuf and says
what the bus message said; growing state stays bounded; bad input is counted, not raised."""

from __future__ import annotations

import math

import numpy as np
import pytest
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PoseInFrame_pb2 import PoseInFrame
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.descriptor_pb2 import FileDescriptorSet

from groundstation.bus.envelope import Envelope, Header
from groundstation.bus.topics import TOPICS
from groundstation.contact.settings import ContactSettings
from groundstation.openformats.channels import CHANNELS, message_class, schema_data
from groundstation.openformats.foxglove import CLOUD_DTYPE, FoxgloveTranslator
from groundstation.openformats.state import Trajectory


def env(topic: str, t: int, payload: dict, arrays: dict, recv: int | None = None) -> Envelope:
    spec = TOPICS[topic]
    return Envelope(topic, Header(spec.type, spec.schema_version, 0, t, recv or t), payload, arrays)


def by_topic(msgs):
    out: dict[str, list] = {}
    for m in msgs:
        out.setdefault(m.topic, []).append(m)
    return out


def test_every_channel_names_a_foxglove_schema_and_carries_its_descriptor():
    for topic, ch in CHANNELS.items():
        assert topic.startswith("/") and ch.schema.startswith("foxglove."), topic
        cls = message_class(ch.schema)
        assert cls.DESCRIPTOR.full_name == ch.schema
        fds = FileDescriptorSet.FromString(schema_data(ch.schema))
        names = {f"{f.package}.{m.name}" for f in fds.file for m in f.message_type}
        assert ch.schema in names
        assert (
            "google/protobuf/timestamp.proto" in {f.name for f in fds.file}
            or ch.schema == "foxglove.Vector3"
        )


def _mesh_env(t: int = 5_000_000_000) -> Envelope:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    tri = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], dtype=np.int64)
    std = np.array([0.1, 0.2, 0.3, 0.4])
    return env("mesh", t, {"fit_index": 7}, {"vertices": v, "triangles": tri, "vertex_std": std})


def test_mesh_becomes_one_replaceable_entity_with_std_vertex_colours():
    tr = FoxgloveTranslator()
    (m,) = tr.translate(_mesh_env())
    assert m.topic == "/map/mesh" and m.log_time_ns == 5_000_000_000
    up = SceneUpdate.FromString(m.data)
    (ent,) = up.entities
    assert ent.id == "mesh" and ent.frame_id == "world"
    assert ent.timestamp.ToNanoseconds() == 5_000_000_000
    meta = {kv.key: kv.value for kv in ent.metadata}
    assert meta["fit_index"] == "7" and meta["triangles"] == "4"
    (prim,) = ent.triangles
    assert len(prim.points) == 4 and list(prim.indices) == [0, 1, 2, 0, 1, 3, 0, 2, 3, 1, 2, 3]
    assert len(prim.colors) == 4 and prim.pose.orientation.w == 1.0
    # viridis: low std dark purple, high std yellow
    lo, hi = prim.colors[0], prim.colors[3]
    assert lo.b > lo.g and hi.r > hi.b
    # a second mesh replaces the entity (same id)
    (m2,) = tr.translate(_mesh_env(6_000_000_000))
    assert SceneUpdate.FromString(m2.data).entities[0].id == "mesh"


def _obs(i: int, label: int, x, event: int = 0, p_false=None) -> Envelope:
    p = {"id": i, "label": label, "event_id": event if label != 1 else -1, "accel_g": 2.0}
    if p_false is not None:
        p["p_false"] = p_false
    return env("observations", 1_000_000_000 + i * 10_000_000, p,
               {"x_m": np.asarray(x, float), "normal": np.zeros(3)})  # fmt: skip


def _cloud(msg) -> tuple[PointCloud, np.ndarray]:
    pc = PointCloud.FromString(msg.data)
    assert pc.point_stride == CLOUD_DTYPE.itemsize
    assert [f.name for f in pc.fields] == list(CLOUD_DTYPE.names)
    return pc, np.frombuffer(pc.data, dtype=CLOUD_DTYPE)


def test_contacts_are_points_coloured_by_state_and_p_false_is_carried():
    tr = FoxgloveTranslator()
    out = []
    for i in range(4):
        out += tr.translate(_obs(i, 0, [4.0, i, 1.0], event=i // 2, p_false=0.1 * i))
    out += tr.translate(_obs(10, 1, [1.0, 1.0, 1.0]))  # free space: not a contact
    clouds = by_topic(out)["/map/contacts"]
    _, rec = _cloud(clouds[-1] if len(clouds) else None)
    assert set(rec["state"]) == {2}  # pending: no fit yet
    fit = env("mapper.fit", 2_000_000_000, {"fit_index": 0, "flagged_events": [1]},
              {"ids": np.array([0, 1, 2, 3, 10]), "u": np.array([0.1, 0.1, 5.0, 5.0, 0.1]),
               "flags": np.array([0, 0, 1, 1, 0], dtype=np.uint8)})  # fmt: skip
    got = by_topic(tr.translate(fit))
    pc, rec = _cloud(got["/map/contacts"][-1])
    assert len(rec) == 4 and pc.frame_id == "world"
    assert rec["state"].tolist() == [0, 0, 1, 1]  # trusted, trusted, flagged, flagged
    assert rec["green"][0] > rec["red"][0] and rec["red"][2] > rec["green"][2]
    np.testing.assert_allclose(rec["p_false"], [0.0, 0.1, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(rec["u"], [0.1, 0.1, 5.0, 5.0], atol=1e-6)
    assert rec["event_id"].tolist() == [0, 0, 1, 1]
    log = Log.FromString(got["/log"][0].data)
    assert log.name == "mapper" and "2 contacts (1 flagged)" not in log.message  # no begins yet
    assert "fit 0" in log.message
    # the next fit flags event 1 only for want of a second touch (bits 0 and 1): awaiting
    wait = env("mapper.fit", 3_000_000_000,
               {"fit_index": 1, "flagged_events": [1], "awaiting_events": [1]},
               {"ids": np.array([0, 1, 2, 3, 10]), "u": np.array([0.1, 0.1, 5.0, 5.0, 0.1]),
                "flags": np.array([0, 0, 3, 3, 0], dtype=np.uint8)})  # fmt: skip
    got = by_topic(tr.translate(wait))
    _, rec = _cloud(got["/map/contacts"][-1])
    assert rec["state"].tolist() == [0, 0, 3, 3]  # trusted, trusted, awaiting, awaiting
    assert rec["red"][2] > rec["green"][2] > rec["blue"][2]  # amber
    assert "awaiting a second touch: 1" in Log.FromString(got["/log"][0].data).message


def test_pose_gives_pose_transform_and_a_thinned_trajectory():
    tr = FoxgloveTranslator()
    out = []
    for k in range(400):  # 4 s at 100 Hz along x at 0.5 m/s
        t = k * 10_000_000
        out += tr.translate(env("samples.pose", t, {"body_id": 1, "valid": True, "t_station_ns": t},
                                {"position_m": np.array([0.005 * k, 0, 1.0]),
                                 "q_wxyz": np.array([1.0, 0, 0, 0])}))  # fmt: skip
    nan3, nan4 = np.full(3, np.nan), np.full(4, np.nan)
    invalid = {"position_m": nan3, "q_wxyz": nan4}
    out += tr.translate(env("samples.pose", 5, {"body_id": 1, "valid": False}, invalid))
    out += tr.finish()
    got = by_topic(out)
    assert len(got["/vehicle/pose"]) == len(got["/tf"]) == 200  # 50 Hz; the invalid one skipped
    tf = FrameTransform.FromString(got["/tf"][-1].data)
    assert (tf.parent_frame_id, tf.child_frame_id) == ("world", "body")
    assert tf.translation.x == pytest.approx(0.005 * 398) and tf.rotation.w == 1.0
    pose = PoseInFrame.FromString(got["/vehicle/pose"][0].data)
    assert pose.frame_id == "world" and pose.pose.position.z == 1.0
    trajs = got["/vehicle/trajectory"]
    assert 3 <= len(trajs) <= 6  # about once a second of data, plus the last one
    line = SceneUpdate.FromString(trajs[-1].data).entities[0].lines[0]
    xs = [p.x for p in line.points]
    assert xs[0] == 0.0 and xs[-1] == pytest.approx(0.005 * 399, abs=0.05)
    assert all(b - a >= 0.05 - 1e-9 for a, b in zip(xs, xs[1:], strict=False))


def test_trajectory_stays_bounded_on_a_long_flight():
    tr = Trajectory(spacing_m=0.05, max_points=100)
    for k in range(20_000):
        tr.add(k, [0.01 * k, 0.0, 0.0])  # 200 m
    pts = tr.points()
    assert len(pts) <= 100 and pts[-1][0] > 190 and tr.spacing_m > 0.05
    assert len(tr) == len(pts)


def test_signal_threshold_and_events_are_plottable_and_logs_keep_their_level():
    # the threshold detector's signal (filtered |a| in G); the impulse detector's score is
    # checked against its events in tests/integration/test_open_formats.py
    s = ContactSettings(detector="threshold", threshold_g=1.5, release_ratio=0.8)
    tr = FoxgloveTranslator(s)
    out = []
    q = np.array([1.0, 0, 0, 0])  # FRD aligned with NED
    for k in range(50):
        t = k * 5_000_000
        out += tr.translate(env("samples.attitude", t, {"t_station_ns": t}, {"q_wxyz": q}))
        f = np.array([0.0, 0.0, -9.80665]) + (np.array([20.0, 0, 0]) if 20 <= k < 30 else 0)
        out += tr.translate(env("samples.imu", t, {"t_station_ns": t},
                                {"accel_mps2": f, "gyro_radps": np.zeros(3)}))  # fmt: skip
    where = {"position_m": np.ones(3), "normal": np.array([1.0, 0, 0])}
    for t, state, peak in ((100_000_000, "begin", 1.6), (150_000_000, "end", 2.04)):
        payload = {"id": 3, "state": state, "peak_g": peak}
        out += tr.translate(env("contact.event", t, payload, where))
    # a candidate rejected at the source (p_false above 0.98): one instant, told apart
    rejected = {"id": 4, "state": "rejected", "peak_g": 1.3, "p_false": 0.995}
    out += tr.translate(env("contact.event", 200_000_000, rejected, where))
    out += tr.translate(env("log", 7, {"process": "link", "level": "error", "message": "LINK LOST",
                                       "hint": "check the cable"}, {}))  # fmt: skip
    out += tr.finish()
    got = by_topic(out)
    sig = [Vector3.FromString(m.data) for m in got["/detector/signal"]]
    assert len(sig) == 50 and all(v.y == 1.5 and v.z == pytest.approx(1.2) for v in sig)
    assert len(got["/imu/accel"]) == len(got["/vehicle/attitude"]) == 13  # 200 Hz -> 50 Hz
    g = np.array([v.x for v in sig])
    assert g[:19].max() < 1e-9 and g.max() == pytest.approx(20.0 / 9.80665, rel=1e-6)
    peaks = [Vector3.FromString(m.data) for m in got["/detector/event_peak"]]
    assert [(p.x, p.y, p.z) for p in peaks][:2] == [(1.6, 3.0, 1.0), (2.04, 3.0, 0.0)]
    from foxglove_schemas_protobuf.Event_pb2 import Event

    ev, rej = [Event.FromString(m.data) for m in got["/detector/events"]]
    assert (
        ev.start_time.ToNanoseconds() == 100_000_000 and ev.end_time.ToNanoseconds() == 150_000_000
    )
    meta = {kv.key: kv.value for kv in ev.metadata}
    assert meta["peak_g"] == "2.040" and meta["state"] == "contact"
    assert rej.start_time.ToNanoseconds() == rej.end_time.ToNanoseconds() == 200_000_000
    meta = {kv.key: kv.value for kv in rej.metadata}
    assert (meta["state"], meta["id"], meta["p_false"]) == ("rejected", "4", "0.9950")
    logs = [Log.FromString(m.data) for m in got["/log"]]
    err = [x for x in logs if x.name == "link"][0]
    assert (
        err.level == Log.ERROR and "LINK LOST" in err.message and "check the cable" in err.message
    )


def test_malformed_messages_are_counted_not_raised():
    tr = FoxgloveTranslator()
    bad_mesh = env("mesh", 1, {"fit_index": 0}, {"vertices": np.zeros((3, 3)),
                   "triangles": np.array([[0, 1, 5]]), "vertex_std": np.zeros(3)})  # fmt: skip
    assert tr.translate(bad_mesh) == []
    assert tr.translate(env("observations", 1, {"label": 0}, {})) == []
    assert tr.translate(env("status", 1, {"process": "x", "state": "up", "topics": {}}, {}))
    assert tr.bad == 2
    assert math.isfinite(tr.signal.threshold_g)
