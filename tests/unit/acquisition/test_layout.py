"""The MCAP layout contract: encodings, channel metadata, station metadata, ground truth."""

from __future__ import annotations

import math

import pytest

from groundstation.acquisition import layout
from groundstation.errors import GroundstationError


def test_raw_topics_hold_wire_bytes_and_others_envelopes():
    assert layout.message_encoding("raw.mavlink") == "mavlink2"
    assert layout.message_encoding("raw.natnet") == "natnet"
    assert layout.message_encoding("raw.pilot") == "linux-js"
    assert layout.message_encoding("samples.imu") == "gs-envelope/1"
    assert layout.is_raw_topic("raw.natnet") and not layout.is_raw_topic("observations")


def test_raw_topics_match_the_bus_topic_table():
    from groundstation.bus.topics import TOPICS

    for topic, field in layout.RAW_SOURCE_FIELDS.items():
        spec = TOPICS[topic]
        assert field in spec.fields, (topic, field)
        assert layout.RAW_DATA_ARRAY in spec.arrays
    assert {t for t in TOPICS if t.startswith("raw.")} == set(layout.RAW_ENCODINGS)


def test_channel_spec_is_hashable_and_keyed_by_source():
    a = layout.channel_spec("raw.mavlink", source="serial:///dev/ttyUSB0")
    b = layout.channel_spec("raw.mavlink", source="udp://:14550")
    assert a != b and len({a, b, layout.channel_spec("raw.mavlink", source="udp://:14550")}) == 2
    assert a.metadata_dict() == {"layout": layout.LAYOUT_VERSION, "source": "serial:///dev/ttyUSB0"}


@pytest.mark.parametrize("bad", ["", " imu", None, 3])
def test_bad_topic_names_are_refused(bad):
    with pytest.raises(layout.LayoutError, match="topic"):
        layout.channel_spec(bad)


def test_station_metadata_round_trip_and_reserved_keys():
    meta = layout.station_metadata(
        station_version="0.1.0",
        created_by="pytest",
        config="[contact]\nthreshold_g = 0.6\n",
        sources=["serial:///dev/ttyUSB0", "natnet://239.255.42.99:1511"],
        extra={"pilot": "anna"},
    )
    assert all(isinstance(v, str) for v in meta.values())
    assert layout.parse_sources(meta) == ["serial:///dev/ttyUSB0", "natnet://239.255.42.99:1511"]
    with pytest.raises(layout.LayoutError, match="reserved"):
        layout.station_metadata(station_version="1", created_by="x", extra={"layout": "9"})


def test_truth_round_trip_is_canonical_and_rejects_nan():
    truth = {"scene": {"walls": [[0.0, 1.0, 2.0]]}, "contacts": [{"t_ns": 5, "id": 1}]}
    data = layout.encode_truth(truth)
    assert layout.decode_truth(data) == truth
    assert layout.encode_truth(dict(reversed(list(truth.items())))) == data
    with pytest.raises(layout.LayoutError, match=r"truth\.scene\.x"):
        layout.encode_truth({"scene": {"x": math.nan}})
    with pytest.raises(layout.LayoutError, match="JSON"):
        layout.decode_truth(b"\xff not json")


def test_unknown_layout_version_is_refused_with_a_hint():
    layout.check_layout_version(layout.LAYOUT_VERSION, "f.mcap")
    with pytest.raises(GroundstationError, match="version '99'") as info:
        layout.check_layout_version("99", "f.mcap")
    assert info.value.hint


def test_seconds_to_ns_rounds_and_refuses_non_finite():
    assert layout.seconds_to_ns(0.008332999999993262) == 8_333_000
    with pytest.raises(layout.LayoutError):
        layout.seconds_to_ns(math.inf)
