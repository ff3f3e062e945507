"""Contract: our NatNet decoder on real Motive 2.1 / NatNet 3.0 traffic (python_natnet test data).

Oracles: the values listed in external_data/SOURCES.md and OptiTrack's own SampleClient's
decoding of the same session (``SampleClient_output.txt``).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.natnet import (
    FrameExtras,
    FrameOfData,
    LabeledMarker,
    ServerInfo,
    UnknownMessage,
    encode_frame_of_data,
    encode_server_info,
    parse_packet,
)
from tests.support.pcapng import PcapngStats, read_pcapng_file

pytestmark = pytest.mark.external

FIRST_ID, LAST_ID = 162734, 163251


@pytest.fixture(scope="module")
def capture_dir(external_data: Path) -> Path:
    folder = external_data / "natnet_capture" / "test_data"
    if not folder.is_dir():
        pytest.skip(f"NatNet capture not found at {folder}")
    return folder


@pytest.fixture(scope="module")
def datagrams(capture_dir: Path):
    stats = PcapngStats()
    dgrams = read_pcapng_file(capture_dir / "raw" / "traffic.pcapng", stats)
    return dgrams, stats


@pytest.fixture(scope="module")
def server_info(datagrams) -> ServerInfo:
    dgrams, _ = datagrams
    infos = [
        parse_packet(d.payload) for d in dgrams if d.sport == 1510 and d.payload[:2] == b"\x01\0"
    ]
    assert infos, "no server-info reply in the capture"
    assert len(set(infos)) == 1
    return infos[0]


@pytest.fixture(scope="module")
def frames(datagrams, server_info) -> list[FrameOfData]:
    dgrams, _ = datagrams
    version = server_info.bitstream_version  # the version comes from the capture itself
    return [parse_packet(d.payload, version) for d in dgrams if d.dport == 1511]


def test_capture_reads_completely(datagrams):
    dgrams, stats = datagrams
    assert (stats.packets, stats.udp, len(dgrams)) == (550, 550, 550)
    assert stats.skipped_non_udp == stats.skipped_fragments == 0
    data = [d for d in dgrams if d.dport == 1511]
    assert len(data) == 518
    assert {(d.src, d.dst) for d in data} == {("192.168.0.106", "239.255.42.99")}


def test_server_info_in_capture(server_info):
    assert server_info.app_name == "Motive"
    assert server_info.app_version == (2, 1, 0, 0)
    assert server_info.natnet_version == (3, 0, 0, 0)
    assert server_info.clock_frequency == 3_312_787
    assert (server_info.data_port, server_info.multicast) == (1511, True)
    assert server_info.multicast_address == "239.255.42.99"
    assert parse_packet(encode_server_info(server_info)) == server_info


def test_all_518_frames_decode_with_contiguous_ids(frames):
    assert len(frames) == 518
    assert all(isinstance(f, FrameOfData) for f in frames)
    ids = [f.frame_id for f in frames]
    assert ids == list(range(FIRST_ID, LAST_ID + 1))
    # 120 Hz: software timestamps step by 1/120 s, high-res clock ticks agree.
    assert np.allclose(np.diff([f.timestamp_s for f in frames]), 1 / 120, atol=1e-9)
    mid = np.array([f.camera_mid_exposure_ts for f in frames], dtype=np.float64)
    assert np.allclose(np.diff(mid) / 3_312_787, 1 / 120, atol=2e-4)
    for f in frames:
        assert [b.id for b in f.rigid_bodies] == [2]
        assert (f.other_marker_count, f.labeled_marker_count, f.skeleton_count) == (5, 6, 0)
        assert f.data_received_ts >= f.camera_mid_exposure_ts


def test_single_packet_values(capture_dir):
    data = (capture_dir / "mocapframe_packet_v3.bin").read_bytes()
    frame = parse_packet(data, (3, 0))
    assert frame.frame_id == 162734
    (body,) = frame.rigid_bodies
    assert body.id == 2 and body.tracking_valid
    assert body.position == pytest.approx((0.1744, 1.4471, -0.7343), abs=5e-5)
    assert body.orientation == pytest.approx((-0.0546, 0.5099, 0.0437, -0.8574), abs=5e-5)
    assert body.mean_error == pytest.approx(0.0005152203)
    assert frame.timestamp_s == pytest.approx(1356.117, abs=5e-4)
    assert frame.camera_mid_exposure_ts == 1416497730518
    assert frame.transmit_ts == 1416497748722


def test_encoder_reproduces_the_motive_packet_byte_for_byte(capture_dir):
    """Other/labeled markers read independently at their offsets; the rest from our decode."""
    import struct

    data = (capture_dir / "mocapframe_packet_v3.bin").read_bytes()
    others = tuple(struct.unpack_from("<3f", data, 16 + 12 * i) for i in range(5))
    labeled = tuple(
        LabeledMarker(*(lambda v: (v[0], v[1:4], v[4], v[5], v[6]))(m))
        for m in struct.iter_unpack("<i3ffhf", data[0x7E : 0x7E + 6 * 26])
    )
    extras = FrameExtras(other_markers=others, labeled_markers=labeled)
    assert encode_frame_of_data(parse_packet(data, (3, 0)), (3, 0), extras) == data


def test_occluded_packet_is_what_it_really_contains(capture_dir):
    """Despite its name the rigid body in this packet is tracked (params 0x01); what is
    occluded is a labeled marker (its params 0x0B has the occluded bit 0x01 set)."""
    data = (capture_dir / "mocapframe_packet_occluded_v3.bin").read_bytes()
    frame = parse_packet(data, (3, 0))
    assert frame.frame_id == 269007
    (body,) = frame.rigid_bodies
    assert body.id == 7
    assert body.tracking_valid is True
    assert body.position == pytest.approx((-0.15413, 0.28294, 0.47066), abs=1e-5)
    assert (frame.marker_set_count, frame.other_marker_count, frame.labeled_marker_count) == (
        2,
        0,
        4,
    )
    lm_start = data.index(b"\x02\x00\x07\x00")  # packed id (model 7 << 16 | marker 2)
    params = int.from_bytes(data[lm_start + 20 : lm_start + 22], "little", signed=True)
    assert params & 0x01  # that marker is occluded


def test_other_single_packets(capture_dir):
    info = parse_packet((capture_dir / "serverinfo_packet_v3.bin").read_bytes())
    assert isinstance(info, ServerInfo) and info.natnet_version == (3, 0, 0, 0)
    for name, message_id in [
        ("connect_packet_v3.bin", 0),
        ("modeldef_packet_v3.bin", 5),
        ("requestmodeldef_packet_v3.bin", 4),
        ("echorequest_packet_v3.bin", 12),
        ("echoresponse_packet_v3.bin", 13),
    ]:
        msg = parse_packet((capture_dir / name).read_bytes(), (3, 0))
        assert isinstance(msg, UnknownMessage) and msg.message_id == message_id


_NUM = r"-?\d+\.\d+"


def _sample_client_frames(text: str) -> dict[int, dict]:
    """Parse SampleClient's printout: frame id -> timestamp, counts and rigid bodies."""
    out: dict[int, dict] = {}
    cur: dict | None = None
    pending: dict | None = None
    for line in text.splitlines():
        line = line.strip()
        if m := re.fullmatch(r"FrameID : (\d+)", line):
            cur = {"bodies": [], "counts": {}}
            out[int(m.group(1))] = cur
            pending = None
        elif cur is None:
            continue
        elif m := re.fullmatch(r"Timestamp : (" + _NUM + ")", line):
            cur["timestamp"] = float(m.group(1))
        elif m := re.fullmatch(
            r"(Other Markers|Rigid Bodies|Labeled Markers) \[Count=(\d+)\]", line
        ):
            cur["counts"][m.group(1)] = int(m.group(2))
        elif m := re.fullmatch(
            r"Rigid Body \[ID=(\d+)\s+Error=(" + _NUM + r")\s+Valid=(\d)\]", line
        ):
            pending = {
                "id": int(m.group(1)),
                "error": float(m.group(2)),
                "valid": m.group(3) == "1",
            }
        elif pending is not None and re.fullmatch(r"(" + _NUM + r"\s+){6}" + _NUM, line):
            pending["values"] = [float(x) for x in line.split()]
            cur["bodies"].append(pending)
            pending = None
    return out


def test_cross_check_against_optitrack_sample_client(capture_dir, frames):
    text = (capture_dir / "raw" / "SampleClient_output.txt").read_text(errors="replace")
    oracle = _sample_client_frames(text)
    assert len(oracle) >= 200
    ours = {f.frame_id: f for f in frames}
    common = sorted(set(oracle) & set(ours))
    assert len(common) >= 200
    sample = [common[i] for i in np.linspace(0, len(common) - 1, 20).astype(int)]
    assert len(set(sample)) == 20
    tol = 0.005 + 1e-6  # printed with %.2f
    for fid in sample:
        want, got = oracle[fid], ours[fid]
        assert abs(got.timestamp_s - want["timestamp"]) <= tol, fid
        assert want["counts"] == {
            "Other Markers": got.other_marker_count,
            "Rigid Bodies": len(got.rigid_bodies),
            "Labeled Markers": got.labeled_marker_count,
        }
        assert len(want["bodies"]) == len(got.rigid_bodies)
        for wb, gb in zip(want["bodies"], got.rigid_bodies, strict=True):
            assert (wb["id"], wb["valid"]) == (gb.id, gb.tracking_valid)
            assert abs(wb["error"] - gb.mean_error) <= tol
            values = np.array([*gb.position, *gb.orientation])
            assert np.all(np.abs(values - wb["values"]) <= tol), (fid, values, wb["values"])
