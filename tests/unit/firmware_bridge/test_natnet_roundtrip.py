"""Encoder/parser round trips (hypothesis) for NatNet 3.0, 3.1, 4.0 and 4.1.

Every skipped section (marker sets, other markers, skeletons, assets, labeled markers, force
plates, devices) is filled with random content so that the parser's skipping is exercised;
random corruption must give NatNetParseError or a frame, never IndexError/struct.error.
"""

from __future__ import annotations

import dataclasses
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_bridge.natnet import (
    AnalogDevice,
    Asset,
    AssetMarker,
    FrameExtras,
    FrameOfData,
    LabeledMarker,
    MarkerSet,
    NatNetParseError,
    RigidBody,
    Skeleton,
    encode_frame_of_data,
    parse_packet,
)

VERSIONS = [(3, 0), (3, 1), (4, 0), (4, 1)]

f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
i32 = st.integers(-(2**31), 2**31 - 1)
u32 = st.integers(0, 2**32 - 1)
u64 = st.integers(0, 2**64 - 1)
vec3 = st.tuples(f32, f32, f32)

rigid_bodies = st.builds(RigidBody, i32, vec3, st.tuples(f32, f32, f32, f32), f32, st.booleans())
markers = st.tuples(i32, vec3, f32, st.integers(-(2**15), 2**15 - 1), f32)
labeled = markers.map(lambda m: LabeledMarker(*m))
asset_markers = markers.map(lambda m: AssetMarker(*m))
analog = st.builds(
    AnalogDevice, i32, st.lists(st.lists(f32, max_size=4).map(tuple), max_size=3).map(tuple)
)
names = st.text(alphabet=st.characters(min_codepoint=1, max_codepoint=127), min_size=0, max_size=12)


def _tuple(strategy, max_size=3):
    return st.lists(strategy, max_size=max_size).map(tuple)


@st.composite
def frames_and_extras(draw, version):
    frame = FrameOfData(
        frame_id=draw(i32),
        rigid_bodies=draw(_tuple(rigid_bodies, 4)),
        timestamp_s=draw(st.floats(allow_nan=False)),
        camera_mid_exposure_ts=draw(u64),
        data_received_ts=draw(u64),
        transmit_ts=draw(u64),
        params=draw(st.integers(0, 0xFFFF)),
        timecode=draw(u32),
        timecode_subframe=draw(u32),
        precision_timestamp_s=draw(u32) if version >= (4, 1) else 0,
        precision_timestamp_frac=draw(u32) if version >= (4, 1) else 0,
    )
    extras = FrameExtras(
        marker_sets=draw(_tuple(st.builds(MarkerSet, names, _tuple(vec3)))),
        other_markers=draw(_tuple(vec3)),
        skeletons=draw(_tuple(st.builds(Skeleton, i32, _tuple(rigid_bodies)))),
        assets=draw(_tuple(st.builds(Asset, i32, _tuple(rigid_bodies), _tuple(asset_markers))))
        if version >= (4, 1)
        else (),
        labeled_markers=draw(_tuple(labeled)),
        force_plates=draw(_tuple(analog)),
        devices=draw(_tuple(analog)),
    )
    return frame, extras


def _expected(frame: FrameOfData, ex: FrameExtras) -> FrameOfData:
    return dataclasses.replace(
        frame,
        marker_set_count=len(ex.marker_sets),
        other_marker_count=len(ex.other_markers),
        skeleton_count=len(ex.skeletons),
        asset_count=len(ex.assets),
        labeled_marker_count=len(ex.labeled_markers),
        force_plate_count=len(ex.force_plates),
        device_count=len(ex.devices),
    )


@pytest.mark.parametrize("version", VERSIONS)
@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_round_trip_with_every_section(version, data):
    frame, extras = data.draw(frames_and_extras(version))
    wire = encode_frame_of_data(frame, version, extras)
    assert parse_packet(wire, version) == _expected(frame, extras)


@pytest.mark.parametrize("version", VERSIONS)
@settings(max_examples=50, deadline=None)
@given(data=st.data())
def test_corruption_never_escapes_as_a_crash(version, data):
    """Flip bytes / cut the tail of a valid frame: a frame or NatNetParseError, nothing else."""
    frame, extras = data.draw(frames_and_extras(version))
    wire = bytearray(encode_frame_of_data(frame, version, extras))
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(4, len(wire) - 1))
        wire[pos] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(4, len(wire)))
    wire = wire[:cut]
    struct.pack_into("<H", wire, 2, cut - 4)
    try:
        result = parse_packet(bytes(wire), version)
    except NatNetParseError:
        return
    assert isinstance(result, FrameOfData)


@pytest.mark.parametrize("version", VERSIONS)
def test_sections_really_are_skipped_not_ignored(version):
    """The rigid body after large skipped sections decodes right (offsets were followed)."""
    body = RigidBody(42, (1.5, -2.5, 3.25), (0.5, 0.5, 0.5, 0.5), 0.125, True)
    extras = FrameExtras(
        marker_sets=(MarkerSet("a", ((1, 2, 3),) * 7), MarkerSet("longer name", ())),
        other_markers=((9, 9, 9),) * 11,
        skeletons=(Skeleton(1, (body,) * 3),),
        labeled_markers=(LabeledMarker(1, (0, 0, 0)),) * 5,
        force_plates=(AnalogDevice(1, ((1.0,) * 9, (2.0,) * 2)),),
        devices=(AnalogDevice(2, ((3.0,) * 4,)),),
        assets=(Asset(1, (body,), (AssetMarker(1, (0, 0, 0)),)),) if version >= (4, 1) else (),
    )
    frame = FrameOfData(7, (body,), 99.0, 1, 2, 3)
    parsed = parse_packet(encode_frame_of_data(frame, version, extras), version)
    assert parsed.rigid_bodies == (body,)
    assert (parsed.transmit_ts, parsed.timestamp_s) == (3, 99.0)
    assert parsed.marker_set_count == 2 and parsed.other_marker_count == 11
