"""Topic table integrity and payload validation."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.bus.envelope import ALLOWED_DTYPES
from groundstation.bus.errors import SchemaError
from groundstation.bus.topics import TOPICS, get_topic

REQUIRED = {
    "raw.mavlink", "raw.natnet", "raw.pilot", "samples.imu", "samples.attitude", "samples.pose",
    "link.health", "contact.event", "observations", "mapper.fit", "mesh", "status",
    "pilot.command", "pilot.event", "log",
}  # fmt: skip


def test_table_holds_the_required_topics_keyed_by_name():
    assert REQUIRED <= set(TOPICS)
    assert all(name == t.name for name, t in TOPICS.items())


def test_no_topic_name_is_a_prefix_of_another():
    # ZeroMQ subscriptions are prefix matches; this makes subscribing to a name exact
    for a in TOPICS:
        for b in TOPICS:
            assert a == b or not b.startswith(a), (a, b)


def test_types_unique_and_versions_valid():
    types = [t.type for t in TOPICS.values()]
    assert len(set(types)) == len(types)
    for t in TOPICS.values():
        assert 0 < len(t.type.encode()) <= 255 and 1 <= t.schema_version < 2**16
        assert t.doc and t.publisher_role


def test_policies_follow_kinds():
    for t in TOPICS.values():
        assert t.policy in ("lossless", "latest")
        assert (t.policy == "lossless") == (t.kind in ("data", "event")), t.name
    data = {n for n, t in TOPICS.items() if t.kind == "data"}
    assert {n for n in TOPICS if n.startswith(("raw.", "samples."))} | {"observations"} <= data
    assert all(TOPICS[n].policy == "latest" for n in ("mesh", "status", "mapper.fit"))


def test_array_dtypes_are_wire_dtypes():
    for t in TOPICS.values():
        for spec in t.arrays.values():
            assert set(spec.dtypes) <= ALLOWED_DTYPES, t.name


def test_validate_accepts_good_and_names_bad():
    mesh = get_topic("mesh")
    good = {
        "vertices": np.zeros((4, 3), np.float32),
        "triangles": np.zeros((2, 3), np.int32),
        "vertex_std": np.zeros(4, np.float32),
    }
    mesh.validate({"fit_index": 1}, good)
    with pytest.raises(SchemaError, match="vertex_std"):
        mesh.validate({"fit_index": 1}, {**good, "vertex_std": np.zeros(5, np.float32)})
    with pytest.raises(SchemaError, match="dtype"):
        mesh.validate({"fit_index": 1}, {**good, "triangles": np.zeros((2, 3), np.float64)})
    with pytest.raises(SchemaError, match="fit_index"):
        mesh.validate({"fit_index": 1.5}, good)
    with pytest.raises(SchemaError, match="missing"):
        mesh.validate({}, good)
    obs = get_topic("observations")
    with pytest.raises(SchemaError, match="label"):
        obs.validate({"id": 1, "label": 2}, {"x_m": np.zeros(3), "normal": np.zeros(3)})
    with pytest.raises(SchemaError, match="not a"):
        get_topic("contact.event").validate(
            {"id": 1, "state": "begin", "peak_g": float("nan")},
            {"position_m": np.zeros(3), "normal": np.zeros(3)},
        )
    health = get_topic("link.health")
    fields = dict(connected=True, rx_bytes=1, rx_messages=1, bad_frames=0, last_heartbeat_ns=None)
    health.validate(fields, {})
    with pytest.raises(SchemaError, match="connected"):
        health.validate({**fields, "connected": 1}, {})
    get_topic("samples.attitude").validate({}, {"q_wxyz": np.zeros(4)})  # rates optional


def test_unknown_topic_lists_known_names():
    with pytest.raises(SchemaError, match="samples.imu"):
        get_topic("samples.imux")
