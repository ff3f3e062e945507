"""NatNet parser: golden packets built field by field from the SDK layout, and bad input."""

from __future__ import annotations

import struct

import pytest

from firmware_bridge.errors import ProtocolError
from firmware_bridge.natnet import (
    FrameOfData,
    NatNetParseError,
    RigidBody,
    ServerInfo,
    UnknownMessage,
    encode_connect_request,
    encode_frame_of_data,
    encode_server_info,
    parse_packet,
)


def _le(fmt: str, *values) -> bytes:
    return struct.pack("<" + fmt, *values)


def _golden_41() -> bytes:
    """A NatNet 4.1 frame written field by field (PacketClient.cpp order), one of each section."""
    rb = _le("i", 3) + _le("3f", 1.0, 2.0, 3.0) + _le("4f", 0.0, 0.0, 0.0, 1.0)
    rb += _le("f", 0.25) + _le("h", 1)  # mean error, params: tracking valid
    rb_lost = _le("i", 9) + _le("7f", 0, 0, 0, 0, 0, 0, 1) + _le("f", 0.0) + _le("h", 0)
    marker_set = b"Quad\0" + _le("i", 1) + _le("3f", 0.5, 0.5, 0.5)
    other = _le("3f", 4.0, 5.0, 6.0)
    skeleton = _le("ii", 77, 1) + rb
    asset = _le("ii", 5, 1) + rb + _le("i", 1) + _le("i3ffhf", 8, 1, 1, 1, 0.01, 2, 0.001)
    labeled = _le("i3ffhf", (2 << 16) | 1, 0.1, 0.2, 0.3, 0.02, 10, 0.0002)
    plate = _le("ii", 1, 2) + _le("i", 2) + _le("2f", 1.0, 2.0) + _le("i", 0)
    device = _le("ii", 4, 1) + _le("i", 3) + _le("3f", 7.0, 8.0, 9.0)

    def sec(count, body):
        return _le("ii", count, len(body)) + body

    payload = _le("i", 1234)
    payload += sec(1, marker_set) + sec(1, other) + sec(2, rb + rb_lost) + sec(1, skeleton)
    payload += sec(1, asset) + sec(1, labeled) + sec(1, plate) + sec(1, device)
    payload += _le("II", 0x01020304, 5) + _le("d", 12.5) + _le("QQQ", 100, 200, 300)
    payload += _le("II", 1700000000, 123456) + _le("h", 0x03) + _le("i", 0)
    return _le("HH", 7, len(payload)) + payload


EXPECTED_41 = FrameOfData(
    frame_id=1234,
    rigid_bodies=(
        RigidBody(3, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), 0.25, True),
        RigidBody(9, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0, False),
    ),
    timestamp_s=12.5,
    camera_mid_exposure_ts=100,
    data_received_ts=200,
    transmit_ts=300,
    params=3,
    timecode=0x01020304,
    timecode_subframe=5,
    precision_timestamp_s=1700000000,
    precision_timestamp_frac=123456,
    marker_set_count=1,
    other_marker_count=1,
    skeleton_count=1,
    asset_count=1,
    labeled_marker_count=1,
    force_plate_count=1,
    device_count=1,
)


def test_golden_41_frame_decodes_every_field():
    assert parse_packet(_golden_41(), (4, 1)) == EXPECTED_41


def test_41_section_byte_counts_are_honoured_over_item_layouts():
    """A 4.1 section whose items are longer than known layouts is skipped by its byte count."""
    data = bytearray(_golden_41())
    # Rebuild the labeled-marker section with 6 unknown trailing bytes: only the count moves.
    body = _le("i3ffhf", 1, 0, 0, 0, 0.02, 0, 0.0) + b"future"
    start = data.index(_le("ii", 1, 26))
    old_len = 8 + 26
    new = _le("ii", 1, len(body)) + body
    data[start : start + old_len] = new
    struct.pack_into("<H", data, 2, len(data) - 4)
    frame = parse_packet(bytes(data), (4, 1))
    assert frame.labeled_marker_count == 1
    assert frame.rigid_bodies == EXPECTED_41.rigid_bodies
    assert frame.precision_timestamp_frac == 123456


def test_41_rigid_body_section_with_extra_bytes_is_read_then_skipped():
    data = bytearray(_golden_41())
    start = data.index(_le("ii", 2, 76))
    data[start : start + 8] = _le("ii", 2, 80)
    data[start + 8 + 76 : start + 8 + 76] = b"\xaa" * 4  # fields a later 4.x might add
    struct.pack_into("<H", data, 2, len(data) - 4)
    assert parse_packet(bytes(data), (4, 1)) == EXPECTED_41


def test_41_rigid_body_section_longer_than_declared_is_an_error():
    data = bytearray(_golden_41())
    start = data.index(_le("ii", 2, 76))
    struct.pack_into("<ii", data, start, 2, 40)  # 2 bodies need 76 bytes
    with pytest.raises(NatNetParseError, match="rigid bodies"):
        parse_packet(bytes(data), (4, 1))


def test_30_frame_same_content_without_section_sizes():
    frame = parse_packet(encode_frame_of_data(EXPECTED_41, (3, 0)), (3, 0))
    assert frame.rigid_bodies == EXPECTED_41.rigid_bodies
    assert frame.precision_timestamp_s == 0  # no precision timestamp before 4.1


def test_encoder_reproduces_the_golden_41_bytes():
    from firmware_bridge.natnet import (
        AnalogDevice,
        Asset,
        AssetMarker,
        FrameExtras,
        LabeledMarker,
        MarkerSet,
        Skeleton,
    )

    rb = EXPECTED_41.rigid_bodies[0]
    extras = FrameExtras(
        marker_sets=(MarkerSet("Quad", ((0.5, 0.5, 0.5),)),),
        other_markers=((4.0, 5.0, 6.0),),
        skeletons=(Skeleton(77, (rb,)),),
        assets=(Asset(5, (rb,), (AssetMarker(8, (1, 1, 1), 0.01, 2, 0.001),)),),
        labeled_markers=(LabeledMarker((2 << 16) | 1, (0.1, 0.2, 0.3), 0.02, 10, 0.0002),),
        force_plates=(AnalogDevice(1, ((1.0, 2.0), ())),),
        devices=(AnalogDevice(4, ((7.0, 8.0, 9.0),)),),
    )
    assert encode_frame_of_data(EXPECTED_41, (4, 1), extras) == _golden_41()


@pytest.mark.parametrize("version", [(3, 0), (3, 1), (4, 0), (4, 1)])
def test_every_truncation_raises_parse_error(version):
    """Cutting the datagram anywhere (and fixing the header) gives NatNetParseError only."""
    full = encode_frame_of_data(EXPECTED_41, version)
    for cut in range(len(full)):
        data = bytearray(full[:cut])
        if cut >= 4:
            struct.pack_into("<H", data, 2, cut - 4)
        with pytest.raises(NatNetParseError):
            parse_packet(bytes(data), version)


def test_error_names_message_offset_and_version():
    full = bytearray(encode_frame_of_data(EXPECTED_41, (4, 0)))
    data = full[:30]
    struct.pack_into("<H", data, 2, 26)
    with pytest.raises(NatNetParseError) as info:
        parse_packet(bytes(data), (4, 0))
    err = info.value
    assert isinstance(err, ProtocolError)
    assert err.message_id == 7 and err.version == (4, 0) and err.offset is not None
    assert "message 7" in str(err) and "4.0" in str(err) and "offset" in str(err)


def test_header_length_mismatch_is_reported():
    data = encode_frame_of_data(EXPECTED_41, (4, 1))
    with pytest.raises(NatNetParseError, match="declares"):
        parse_packet(data + b"\0", (4, 1))
    with pytest.raises(NatNetParseError, match="header"):
        parse_packet(b"\x07", (4, 1))


def test_wrong_version_is_detected_not_misread():
    """A 4.1 frame read as 3.0 (and vice versa) fails loudly instead of returning garbage."""
    with pytest.raises(NatNetParseError):
        parse_packet(_golden_41(), (3, 0))
    with pytest.raises(NatNetParseError):
        parse_packet(encode_frame_of_data(EXPECTED_41, (3, 0)), (4, 1))


def test_impossible_counts_are_rejected_quickly():
    data = bytearray(encode_frame_of_data(EXPECTED_41, (3, 0)))
    struct.pack_into("<i", data, 8, 2**30)  # marker-set count
    with pytest.raises(NatNetParseError, match="marker sets count"):
        parse_packet(bytes(data), (3, 0))
    struct.pack_into("<i", data, 8, -1)
    with pytest.raises(NatNetParseError):
        parse_packet(bytes(data), (3, 0))


@pytest.mark.parametrize("version", [(2, 9), (4, 2), (5, 0), "4.1", None])
def test_unsupported_versions_are_refused(version):
    with pytest.raises(NatNetParseError, match="version"):
        parse_packet(_golden_41(), version)


def test_server_info_round_trip_and_short_form():
    info = ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0), 10_000_000, 1511, True, "239.255.42.99")
    data = encode_server_info(info)
    assert len(data) == 4 + 279
    assert parse_packet(data) == info
    assert parse_packet(data).bitstream_version == (4, 1)
    short = bytearray(data[: 4 + 264])
    struct.pack_into("<H", short, 2, 264)
    assert parse_packet(bytes(short)) == ServerInfo("Motive", (3, 1, 0, 0), (4, 1, 0, 0))
    with pytest.raises(NatNetParseError, match="server info"):
        parse_packet(_le("HH", 1, 100) + bytes(100))
    with pytest.raises(NatNetParseError, match="trailing"):
        parse_packet(_le("HH", 1, 269) + bytes(short[4:]) + bytes(5))


def test_other_messages_are_returned_unknown():
    data = encode_connect_request((4, 1, 0, 0))
    msg = parse_packet(data)
    assert isinstance(msg, UnknownMessage) and msg.message_id == 0
    assert msg.payload[:9] == b"NatNetLib" and len(msg.payload) == 264


def test_parse_accepts_bytearray_and_memoryview():
    data = _golden_41()
    assert parse_packet(bytearray(data)) == parse_packet(memoryview(data)) == EXPECTED_41


def test_encoder_rejects_out_of_range_values():
    bad = FrameOfData(2**40, (), 0.0)
    with pytest.raises(ProtocolError, match="cannot be encoded"):
        encode_frame_of_data(bad, (4, 1))
    from firmware_bridge.natnet import Asset, FrameExtras

    with pytest.raises(ProtocolError, match="assets"):
        encode_frame_of_data(EXPECTED_41, (4, 0), FrameExtras(assets=(Asset(1),)))


def test_bodies_only_fast_path_equals_the_general_parser(monkeypatch):
    # oracle: the section-by-section parser (fast path disabled) on frames of 0-3 bodies, the
    # golden frame with every section, and every single-byte corruption and truncation
    import random

    from firmware_bridge.natnet import parser

    rng = random.Random(0)
    packets = [_golden_41()]
    for k in range(40):
        bodies = tuple(
            RigidBody(rng.randrange(1, 9), (rng.gauss(0, 2), 1.0, -0.5),
                      (0.0, 0.6, 0.0, 0.8), 0.001, rng.random() < 0.8)
            for _ in range(k % 4)
        )  # fmt: skip
        frame = FrameOfData(frame_id=k, rigid_bodies=bodies, timestamp_s=k / 200, params=k % 3)
        packets.append(encode_frame_of_data(frame, (4, 1)))
    damaged = []
    for p in packets[:6]:
        for i in range(len(p)):
            b = bytearray(p)
            b[i] ^= 1 << rng.randrange(8)
            damaged.append(bytes(b))
        damaged += [p[:n] for n in range(len(p))]

    def parse_all() -> list[str]:
        out = []
        for p in packets + damaged:
            try:
                out.append(repr(parse_packet(p, (4, 1))))
            except NatNetParseError as exc:
                out.append(f"error {exc.message}")
        return out

    fast = parse_all()
    monkeypatch.setattr(parser, "_parse_bodies_only", lambda buf, end: None)
    assert fast == parse_all()
    assert sum(r.startswith("FrameOfData") for r in fast) > 40
