"""The small pcapng reader: both byte orders, block kinds, link layers, and malformed files."""

from __future__ import annotations

import struct

import pytest

from tests.support.pcapng import (
    EPB,
    IDB,
    SHB,
    SPB,
    PcapngError,
    PcapngStats,
    UdpDatagram,
    encode_pcapng,
    iter_udp,
    read_pcapng_file,
)

DGRAMS = [
    UdpDatagram(1509244022.606067, "192.168.0.106", "239.255.42.99", 1511, 1511, b"\x07\x00ab"),
    UdpDatagram(1509244022.614400, "10.0.0.1", "10.0.0.2", 49467, 1510, b""),
    UdpDatagram(1509244023.0, "127.0.0.1", "127.0.0.1", 1, 65535, bytes(range(256)) * 5),
]


def _block(e: str, btype: int, body: bytes) -> bytes:
    body += b"\0" * (-len(body) % 4)
    n = len(body) + 12
    return struct.pack(e + "II", btype, n) + body + struct.pack(e + "I", n)


def _ipv4_udp(src: bytes, dst: bytes, sport: int, dport: int, payload: bytes, frag=0) -> bytes:
    udp = struct.pack("!HHHH", sport, dport, 8 + len(payload), 0) + payload
    return struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + len(udp), 0, frag, 64, 17, 0, src, dst) + udp


@pytest.mark.parametrize("big_endian", [False, True])
def test_round_trip_both_byte_orders(big_endian):
    data = encode_pcapng(DGRAMS, big_endian=big_endian)
    assert data[:4] == b"\x0a\x0d\x0d\x0a"
    assert data[8:12] == (b"\x1a\x2b\x3c\x4d" if big_endian else b"\x4d\x3c\x2b\x1a")
    got = list(iter_udp(data))
    assert [g[1:] for g in got] == [d[1:] for d in DGRAMS]
    for g, d in zip(got, DGRAMS, strict=True):
        assert g.timestamp_s == pytest.approx(d.timestamp_s, abs=1e-6)


def test_nanosecond_resolution_option():
    data = encode_pcapng(DGRAMS[:1], ts_per_s=1_000_000_000)
    (got,) = iter_udp(data)
    assert got.timestamp_s == pytest.approx(DGRAMS[0].timestamp_s, abs=1e-9)


@pytest.mark.parametrize("e", ["<", ">"])
def test_simple_packet_block_vlan_sll_raw_and_skips(e, tmp_path):
    ip = _ipv4_udp(b"\x01\x02\x03\x04", b"\x05\x06\x07\x08", 10, 20, b"hello")
    eth_vlan = b"\0" * 12 + b"\x81\x00\x00\x05" + b"\x08\x00" + ip
    sll = b"\0" * 14 + b"\x08\x00" + ip
    arp = b"\0" * 12 + b"\x08\x06" + b"\0" * 28
    frag = b"\0" * 12 + b"\x08\x00" + _ipv4_udp(b"\1" * 4, b"\2" * 4, 1, 2, b"x", frag=0x2000)
    tcp = bytearray(b"\0" * 12 + b"\x08\x00" + ip)
    tcp[14 + 9] = 6
    data = _block(e, SHB, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1))
    data += _block(e, IDB, struct.pack(e + "HHI", 1, 0, 0))  # 0: Ethernet
    data += _block(e, IDB, struct.pack(e + "HHI", 113, 0, 0))  # 1: Linux cooked
    data += _block(e, IDB, struct.pack(e + "HHI", 101, 0, 0))  # 2: raw IP
    data += _block(e, IDB, struct.pack(e + "HHI", 147, 0, 0))  # 3: user link type
    data += _block(e, SPB, struct.pack(e + "I", len(eth_vlan)) + eth_vlan)
    data += _block(e, 0x0BAD, b"custom block is skipped")
    for if_id, frame in [(1, sll), (2, ip), (0, arp), (0, frag), (0, bytes(tcp)), (3, ip)]:
        head = struct.pack(e + "IIIII", if_id, 0, 2_000_000, len(frame), len(frame))
        data += _block(e, EPB, head + frame)
    stats = PcapngStats()
    path = tmp_path / "x.pcapng"
    path.write_bytes(data)
    got = read_pcapng_file(path, stats)
    assert [g.payload for g in got] == [b"hello"] * 3
    assert got[0] == UdpDatagram(0.0, "1.2.3.4", "5.6.7.8", 10, 20, b"hello")
    assert got[1].timestamp_s == pytest.approx(2.0)
    assert (stats.packets, stats.udp) == (7, 3)
    assert (stats.skipped_non_udp, stats.skipped_fragments, stats.skipped_link_types) == (2, 1, 1)


def test_malformed_files_name_block_and_offset():
    good = encode_pcapng(DGRAMS[:1])
    with pytest.raises(PcapngError, match="offset 0"):
        list(iter_udp(b"\x01\x00\x00\x00" + good[4:]))  # no section header first
    bad_magic = bytearray(good)
    bad_magic[8:12] = b"\0\0\0\0"
    with pytest.raises(PcapngError, match="byte-order magic"):
        list(iter_udp(bytes(bad_magic)))
    with pytest.raises(PcapngError, match=r"block type 0x6 at offset \d+ has bad length"):
        list(iter_udp(good[:-8]))
    bad_trailer = bytearray(good)
    bad_trailer[-1] = 0x7F
    with pytest.raises(PcapngError, match="trailing length"):
        list(iter_udp(bytes(bad_trailer)))
    with pytest.raises(PcapngError, match="truncated block header"):
        list(iter_udp(good + b"\0" * 5))


def test_packet_for_undescribed_interface_is_an_error():
    e = "<"
    data = _block(e, SHB, struct.pack(e + "IHHq", 0x1A2B3C4D, 1, 0, -1))
    data += _block(e, EPB, struct.pack(e + "IIIII", 0, 0, 0, 0, 0))
    with pytest.raises(PcapngError, match="interface 0"):
        list(iter_udp(data))


def test_every_truncation_gives_pcapng_error_or_fewer_packets():
    good = encode_pcapng(DGRAMS)
    for cut in range(0, len(good), 7):
        try:
            got = list(iter_udp(good[:cut]))
        except PcapngError:
            continue
        assert len(got) <= len(DGRAMS)
