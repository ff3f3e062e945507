"""A small pcapng reader (and writer) for UDP traffic, used only by the tests.

It lives under ``tests/`` (it was ``firmware_bridge/pcapng.py``): the station never reads
captures; the contract test replays the real NatNet capture in ``external_data`` through it.

Reads section header, interface description, enhanced and simple packet blocks in either
byte order (pcapng spec, draft-ietf-opsawg-pcapng: SHB 0x0A0D0D0A with byte-order magic
0x1A2B3C4D, IDB 0x00000001, SPB 0x00000003, EPB 0x00000006; other blocks are skipped by their
length). Link layers: Ethernet (with 802.1Q tags), Linux cooked (SLL), raw IPv4. IPv4/UDP
decapsulation yields :class:`UdpDatagram`; non-UDP packets and IP fragments are counted in
:attr:`PcapngStats` and skipped. Errors name the block type and byte offset.

Pure functions over bytes; :func:`read_pcapng_file` is the only I/O.
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

from firmware_bridge.errors import ProtocolError

SHB = 0x0A0D0D0A
IDB = 0x00000001
SPB = 0x00000003
EPB = 0x00000006
BYTE_ORDER_MAGIC = 0x1A2B3C4D

LINKTYPE_ETHERNET = 1
LINKTYPE_RAW = 101
LINKTYPE_LINUX_SLL = 113
LINKTYPE_IPV4 = 228

_OPT_IF_TSRESOL = 9
_ETH_IPV4 = 0x0800
_ETH_VLAN = (0x8100, 0x88A8)
_IPPROTO_UDP = 17


class PcapngError(ProtocolError):
    """A pcapng file is malformed; the message names the block and byte offset."""


class UdpDatagram(NamedTuple):
    """One UDP datagram: capture time (s since the epoch), addresses, ports, payload."""

    timestamp_s: float
    src: str
    dst: str
    sport: int
    dport: int
    payload: bytes


@dataclass
class PcapngStats:
    """Counts of what :func:`iter_udp` saw and skipped."""

    blocks: int = 0
    packets: int = 0
    udp: int = 0
    skipped_non_udp: int = 0
    skipped_fragments: int = 0
    skipped_link_types: int = 0


@dataclass
class _Interface:
    link_type: int
    snap_len: int
    ts_per_s: float = 1e6


def _ts_resolution(options: bytes, endian: str) -> float:
    """Ticks per second from an IDB's options (if_tsresol, spec 4.2; default 10^-6 s)."""
    o = 0
    while o + 4 <= len(options):
        code, length = struct.unpack_from(endian + "HH", options, o)
        o += 4
        if code == 0:
            break
        if code == _OPT_IF_TSRESOL and length >= 1:
            v = options[o]
            return float(2 ** (v & 0x7F)) if v & 0x80 else float(10**v)
        o += (length + 3) & ~3
    return 1e6


def iter_udp(data: bytes, stats: PcapngStats | None = None) -> Iterator[UdpDatagram]:
    """Yield the UDP datagrams of a pcapng capture held in ``data``.

    Parameters
    ----------
    data : bytes
        Whole pcapng file.
    stats : PcapngStats, optional
        Filled with counts of blocks, packets and what was skipped.

    Raises
    ------
    PcapngError
        Bad magic, a block length that is not a multiple of 4 or runs past the end, a
        packet before any section header or for an unknown interface.
    """
    st = stats if stats is not None else PcapngStats()
    o = 0
    endian = ""
    interfaces: list[_Interface] = []
    while o < len(data):
        if len(data) - o < 12:
            raise PcapngError(f"pcapng: truncated block header at offset {o}")
        if struct.unpack_from("<I", data, o)[0] == SHB:
            (magic,) = struct.unpack_from("<I", data, o + 8)
            if magic == BYTE_ORDER_MAGIC:
                endian = "<"
            elif magic == 0x4D3C2B1A:
                endian = ">"
            else:
                raise PcapngError(
                    f"pcapng: section header at offset {o} has bad byte-order magic {magic:#x}"
                )
            interfaces = []
        elif not endian:
            raise PcapngError(
                f"pcapng: block at offset {o} precedes any section header (not a pcapng file?)"
            )
        btype, blen = struct.unpack_from(endian + "II", data, o)
        if blen < 12 or blen % 4 or o + blen > len(data):
            raise PcapngError(
                f"pcapng: block type {btype:#x} at offset {o} has bad length {blen} "
                f"(file has {len(data) - o} bytes left)"
            )
        (trailer,) = struct.unpack_from(endian + "I", data, o + blen - 4)
        if trailer != blen:
            raise PcapngError(
                f"pcapng: block type {btype:#x} at offset {o}: trailing length {trailer} "
                f"!= leading length {blen}"
            )
        body = data[o + 8 : o + blen - 4]
        st.blocks += 1
        if btype == IDB:
            if len(body) < 8:
                raise PcapngError(f"pcapng: interface description at offset {o} is too short")
            link, _res, snap = struct.unpack_from(endian + "HHI", body, 0)
            interfaces.append(_Interface(link, snap, _ts_resolution(body[8:], endian)))
        elif btype in (EPB, SPB):
            if btype == EPB:
                if len(body) < 20:
                    raise PcapngError(f"pcapng: enhanced packet block at offset {o} too short")
                if_id, ts_hi, ts_lo, cap_len, _orig = struct.unpack_from(endian + "IIIII", body)
                frame = body[20 : 20 + cap_len]
                if len(frame) != cap_len:
                    raise PcapngError(
                        f"pcapng: enhanced packet block at offset {o} captured length "
                        f"{cap_len} exceeds the block"
                    )
            else:
                if len(body) < 4:
                    raise PcapngError(f"pcapng: simple packet block at offset {o} too short")
                if_id, ts_hi, ts_lo = 0, 0, 0
                (orig,) = struct.unpack_from(endian + "I", body)
                frame = body[4 : 4 + orig]
            if if_id >= len(interfaces):
                raise PcapngError(
                    f"pcapng: packet block at offset {o} names interface {if_id} but only "
                    f"{len(interfaces)} are described"
                )
            st.packets += 1
            iface = interfaces[if_id]
            ts = ((ts_hi << 32) | ts_lo) / iface.ts_per_s
            dgram = _decapsulate(frame, iface.link_type, ts, st)
            if dgram is not None:
                st.udp += 1
                yield dgram
        o += blen


def _decapsulate(frame: bytes, link: int, ts: float, st: PcapngStats) -> UdpDatagram | None:
    """Strip link, IPv4 and UDP headers (network byte order); None when not IPv4/UDP."""
    if link == LINKTYPE_ETHERNET:
        o, ethertype = 12, None
        while len(frame) >= o + 2:
            (ethertype,) = struct.unpack_from("!H", frame, o)
            o += 2
            if ethertype in _ETH_VLAN:
                o += 2
                continue
            break
    elif link == LINKTYPE_LINUX_SLL:
        o = 16
        ethertype = struct.unpack_from("!H", frame, 14)[0] if len(frame) >= 16 else None
    elif link in (LINKTYPE_RAW, LINKTYPE_IPV4):
        o, ethertype = 0, _ETH_IPV4
    else:
        st.skipped_link_types += 1
        return None
    if ethertype != _ETH_IPV4 or len(frame) < o + 20 or frame[o] >> 4 != 4:
        st.skipped_non_udp += 1
        return None
    ihl = (frame[o] & 0x0F) * 4
    total_len, frag, proto = struct.unpack_from("!H2xHxB", frame, o + 2)
    if proto != _IPPROTO_UDP or ihl < 20:
        st.skipped_non_udp += 1
        return None
    if frag & 0x3FFF:  # more-fragments flag or a fragment offset
        st.skipped_fragments += 1
        return None
    src = str(ipaddress.IPv4Address(frame[o + 12 : o + 16]))
    dst = str(ipaddress.IPv4Address(frame[o + 16 : o + 20]))
    u = o + ihl
    if len(frame) < u + 8 or total_len < ihl + 8:
        st.skipped_non_udp += 1
        return None
    sport, dport, ulen = struct.unpack_from("!HHH", frame, u)
    payload = frame[u + 8 : u + ulen]
    if ulen < 8 or len(payload) != ulen - 8:
        st.skipped_non_udp += 1  # truncated by the snap length
        return None
    return UdpDatagram(ts, src, dst, sport, dport, bytes(payload))


def read_pcapng_file(path: str | Path, stats: PcapngStats | None = None) -> list[UdpDatagram]:
    """Read a pcapng file and return its UDP datagrams (see :func:`iter_udp`)."""
    return list(iter_udp(Path(path).read_bytes(), stats))


def encode_pcapng(
    datagrams: Iterable[UdpDatagram], big_endian: bool = False, ts_per_s: int = 1_000_000
) -> bytes:
    """Write datagrams as a pcapng capture (one Ethernet interface, enhanced packet blocks).

    For tests and exports. ``ts_per_s`` must be a power of ten (if_tsresol).
    """
    e = ">" if big_endian else "<"

    def block(btype: int, body: bytes) -> bytes:
        body += b"\0" * (-len(body) % 4)
        n = len(body) + 12
        return struct.pack(e + "II", btype, n) + body + struct.pack(e + "I", n)

    exp = len(str(ts_per_s)) - 1
    if 10**exp != ts_per_s:
        raise PcapngError(f"ts_per_s={ts_per_s} is not a power of ten")
    out = bytearray(block(SHB, struct.pack(e + "IHHq", BYTE_ORDER_MAGIC, 1, 0, -1)))
    opts = struct.pack(e + "HH", _OPT_IF_TSRESOL, 1) + bytes([exp, 0, 0, 0])
    opts += struct.pack(e + "HH", 0, 0)
    out += block(IDB, struct.pack(e + "HHI", LINKTYPE_ETHERNET, 0, 0xFFFF) + opts)
    for d in datagrams:
        udp = struct.pack("!HHHH", d.sport, d.dport, 8 + len(d.payload), 0) + d.payload
        ip = struct.pack(
            "!BBHHHBBH4s4s",
            0x45,
            0,
            20 + len(udp),
            0,
            0,
            64,
            _IPPROTO_UDP,
            0,
            ipaddress.IPv4Address(d.src).packed,
            ipaddress.IPv4Address(d.dst).packed,
        )
        eth = b"\x01\x00\x5e\x00\x00\x01" + b"\x02\x00\x00\x00\x00\x01" + b"\x08\x00"
        frame = eth + ip + udp
        ticks = round(d.timestamp_s * ts_per_s)
        head = struct.pack(e + "IIIII", 0, ticks >> 32, ticks & 0xFFFFFFFF, len(frame), len(frame))
        out += block(EPB, head + frame)
    return bytes(out)
