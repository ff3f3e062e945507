"""Decode NatNet datagrams: frames of data (message 7) and server info (message 1).

Layout (NatNet SDK ``PacketClient.cpp`` / ``NatNetClient.py``; all little-endian)::

    header      u16 message id, u16 payload byte count
    frame       i32 frame number
    sections    marker sets, legacy "other" markers, rigid bodies, skeletons,
                [assets: 4.1+], labeled markers, force plates, devices
                each section = i32 count, [i32 byte count of the section: 4.1+], items
    suffix      u32 timecode, u32 subframe, f64 timestamp,
                u64 mid-exposure, u64 data received, u64 transmit (3.0+),
                [u32 precision secs, u32 precision fractional secs: 4.1+],
                i16 frame params, i32 end-of-data tag

Rigid body (3.0+): i32 id, 3 f32 position, 4 f32 quaternion (x, y, z, w), f32 mean marker
error, i16 params (bit 0x01 = tracking valid). The per-body marker lists of NatNet 2.x were
dropped in 3.0, so 3.0, 3.1 and 4.0 share one layout; 4.1 adds the section byte counts (which
this parser honours: a section always ends where its count says), the asset section and the
precision timestamp. Bitstream 2.x is refused: the SDK's own samples disagree on its suffix
(PacketClient reads a software-latency float that NatNetClient.py does not).

Pure functions of bytes; no sockets, no clocks.
"""

from __future__ import annotations

import struct

from firmware_bridge.natnet.records import (
    NAT_FRAMEOFDATA,
    NAT_SERVERINFO,
    FrameOfData,
    NatNetParseError,
    RigidBody,
    ServerInfo,
    UnknownMessage,
    check_version,
)

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32X2 = struct.Struct("<ii")
_RIGID_BODY = struct.Struct("<i3f4ffh")  # id, position, quaternion xyzw, error, params
_SUFFIX_3 = struct.Struct("<IIdQQQ")  # timecode, subframe, timestamp, 3 x high-res ticks
_PRECISION = struct.Struct("<II")  # 4.1+: precision timestamp secs, fractional secs
_TAIL = struct.Struct("<hi")  # frame params, end-of-data tag
_SERVER_COMMON = struct.Struct("<256s4B4B")
_SERVER_3 = struct.Struct("<QH?4B")  # clock frequency, data port, multicast, group address

#: Fixed item sizes (bytes) of the 3.0+ layouts.
RIGID_BODY_SIZE = _RIGID_BODY.size  # 38
LABELED_MARKER_SIZE = 26  # i32 id, 3 f32 position, f32 size, i16 params, f32 residual
OTHER_MARKER_SIZE = 12
#: Smallest possible item of each section (bytes), to reject impossible counts early.
_MIN_ITEM_SIZE = {
    "marker sets": 5,  # empty name + marker count
    "other markers": OTHER_MARKER_SIZE,
    "rigid bodies": RIGID_BODY_SIZE,
    "skeletons": 8,  # id + bone count
    "assets": 12,  # id + rigid-body count + marker count
    "labeled markers": LABELED_MARKER_SIZE,
    "force plates": 8,  # id + channel count
    "devices": 8,
}


def parse_packet(
    data: bytes | bytearray | memoryview, version: tuple[int, int] = (4, 1)
) -> FrameOfData | ServerInfo | UnknownMessage:
    """Decode one NatNet datagram.

    Parameters
    ----------
    data : bytes
        One UDP payload, header included.
    version : (int, int)
        Bitstream (major, minor) the server streams; frames do not carry it (take it from
        :class:`ServerInfo` or configuration). Only used for frames of data.

    Returns
    -------
    FrameOfData, ServerInfo or UnknownMessage

    Raises
    ------
    NatNetParseError
        Truncated or inconsistent packet, or unsupported version; the message names the
        message id, the byte offset and the version.
    """
    if len(data) < _HEADER.size:
        raise NatNetParseError(
            f"NatNet datagram of {len(data)} bytes is shorter than the 4-byte header", offset=0
        )
    if not isinstance(data, bytes):
        data = bytes(data)
    message_id, n_bytes = _HEADER.unpack_from(data, 0)
    end = _HEADER.size + n_bytes
    if end != len(data):
        raise NatNetParseError(
            f"NatNet message {message_id}: header declares {n_bytes} payload bytes but the "
            f"datagram carries {len(data) - _HEADER.size}",
            hint="the datagram is truncated or two messages were concatenated",
            message_id=message_id,
            offset=2,
        )
    if message_id == NAT_FRAMEOFDATA:
        return _parse_frame(data, check_version(version, message_id), end)
    if message_id == NAT_SERVERINFO:
        return _parse_server_info(data, end)
    return UnknownMessage(message_id, bytes(data[_HEADER.size : end]))


def _error(what: str, offset: int, version: tuple[int, int]) -> NatNetParseError:
    return NatNetParseError(
        f"NatNet frame of data (message {NAT_FRAMEOFDATA}), version {version[0]}.{version[1]}: "
        f"{what} at byte offset {offset}",
        hint="check the bitstream version (ServerInfo.natnet_version) matches the stream",
        message_id=NAT_FRAMEOFDATA,
        offset=offset,
        version=version,
    )


#: 4.1+ frame with rigid bodies only: frame number, (count, bytes) of marker sets, other
#: markers, rigid bodies; after the bodies (count, bytes) of skeletons, assets, labeled markers,
#: force plates, devices, then the suffix, precision timestamp and tail.
_ONLY_BODIES_HEAD = struct.Struct("<i6i")
_ONLY_BODIES_TAIL = struct.Struct("<10iIIdQQQIIhi")


def _parse_bodies_only(buf: bytes, end: int) -> FrameOfData | None:
    """A 4.1+ frame whose only non-empty section is the rigid bodies (what a mocap streaming
    rigid bodies sends every frame), in two unpacks; None for any other frame (the general
    parser then decides). When it returns a frame, the general parser returns the same one:
    every section is empty with a zero byte count, the bodies fill their section exactly and
    the tail ends the datagram."""
    if end < _HEADER.size + _ONLY_BODIES_HEAD.size:
        return None
    frame_id, n_sets, sets_size, n_other, other_size, n_bodies, bodies_size = (
        _ONLY_BODIES_HEAD.unpack_from(buf, _HEADER.size)
    )
    o = _HEADER.size + _ONLY_BODIES_HEAD.size
    if (
        n_sets or sets_size or n_other or other_size or n_bodies < 0
        or bodies_size != n_bodies * RIGID_BODY_SIZE
        or end - o - bodies_size != _ONLY_BODIES_TAIL.size
    ):  # fmt: skip
        return None
    bodies = tuple(
        RigidBody(rid, (x, y, z), (qx, qy, qz, qw), err, bool(params & 0x01))
        for rid, x, y, z, qx, qy, qz, qw, err, params in _RIGID_BODY.iter_unpack(
            buf[o : o + bodies_size]
        )
    )
    (
        *sections, timecode, subframe, timestamp, mid_ts, recv_ts, tx_ts, prec_s, prec_frac,
        params, _eod,
    ) = _ONLY_BODIES_TAIL.unpack_from(buf, o + bodies_size)  # fmt: skip
    if any(sections):
        return None
    return FrameOfData(
        frame_id=frame_id,
        rigid_bodies=bodies,
        timestamp_s=timestamp,
        camera_mid_exposure_ts=mid_ts,
        data_received_ts=recv_ts,
        transmit_ts=tx_ts,
        params=params & 0xFFFF,
        timecode=timecode,
        timecode_subframe=subframe,
        precision_timestamp_s=prec_s,
        precision_timestamp_frac=prec_frac,
        marker_set_count=0,
        other_marker_count=0,
        skeleton_count=0,
        asset_count=0,
        labeled_marker_count=0,
        force_plate_count=0,
        device_count=0,
    )


def _parse_frame(buf: bytes, version: tuple[int, int], end: int) -> FrameOfData:
    """Decode a frame-of-data payload in ``buf[4:end]`` (``len(buf) == end``)."""
    sized = version >= (4, 1)  # 4.1: every section carries its byte count
    if sized:
        frame = _parse_bodies_only(buf, end)
        if frame is not None:
            return frame
    o = _HEADER.size
    section = "frame number"
    counts = {}
    bodies: list[RigidBody] = []
    try:
        (frame_id,) = _I32.unpack_from(buf, o)
        o += 4

        for section in (
            "marker sets",
            "other markers",
            "rigid bodies",
            "skeletons",
            "assets",
            "labeled markers",
            "force plates",
            "devices",
        ):
            if section == "assets" and not sized:
                counts[section] = 0
                continue
            count_at = o
            if sized:
                count, size = _I32X2.unpack_from(buf, o)
                o += 8
                if size < 0 or o + size > end:
                    raise _error(
                        f"{section} byte count {size} runs past the payload end {end}",
                        count_at + 4,
                        version,
                    )
                section_end = o + size
            else:
                (count,) = _I32.unpack_from(buf, o)
                o += 4
                section_end = end
            room = section_end - o
            if count < 0 or count * _MIN_ITEM_SIZE[section] > room:
                raise _error(
                    f"{section} count {count} is impossible in {room} bytes", count_at, version
                )
            counts[section] = count

            if section == "rigid bodies":
                unpack = _RIGID_BODY.unpack_from
                for _ in range(count):
                    rid, x, y, z, qx, qy, qz, qw, err, params = unpack(buf, o)
                    o += RIGID_BODY_SIZE
                    bodies.append(
                        RigidBody(rid, (x, y, z), (qx, qy, qz, qw), err, bool(params & 0x01))
                    )
                if sized:
                    o = section_end  # honour the count: later 4.x may append fields
                continue
            if sized:
                o = section_end  # skip by the declared byte count
                continue
            if count:
                o = _skip_items(buf, o, end, section, count, version)

        section = "frame suffix"
        timecode, subframe, timestamp, mid_ts, recv_ts, tx_ts = _SUFFIX_3.unpack_from(buf, o)
        o += _SUFFIX_3.size
        prec_s = prec_frac = 0
        if sized:
            section = "precision timestamp"
            prec_s, prec_frac = _PRECISION.unpack_from(buf, o)
            o += _PRECISION.size
        section = "frame params"
        params, _eod = _TAIL.unpack_from(buf, o)
        o += _TAIL.size
    except struct.error:
        raise _error(f"packet truncated while reading {section}", o, version) from None
    if o != end:
        raise _error(f"{end - o} unexpected bytes after the end-of-data tag", o, version)
    return FrameOfData(
        frame_id=frame_id,
        rigid_bodies=tuple(bodies),
        timestamp_s=timestamp,
        camera_mid_exposure_ts=mid_ts,
        data_received_ts=recv_ts,
        transmit_ts=tx_ts,
        params=params & 0xFFFF,
        timecode=timecode,
        timecode_subframe=subframe,
        precision_timestamp_s=prec_s,
        precision_timestamp_frac=prec_frac,
        marker_set_count=counts["marker sets"],
        other_marker_count=counts["other markers"],
        skeleton_count=counts["skeletons"],
        asset_count=counts["assets"],
        labeled_marker_count=counts["labeled markers"],
        force_plate_count=counts["force plates"],
        device_count=counts["devices"],
    )


def _skip_items(
    buf: bytes, o: int, end: int, section: str, count: int, version: tuple[int, int]
) -> int:
    """Skip ``count`` items of an unsized (3.0-4.0) section; return the new offset."""
    if section == "other markers":
        o += count * OTHER_MARKER_SIZE
    elif section == "labeled markers":
        o += count * LABELED_MARKER_SIZE
    elif section == "marker sets":
        for _ in range(count):
            nul = buf.find(b"\0", o, end)
            if nul < 0:
                raise _error("marker set name without a terminating NUL", o, version)
            (n,) = _I32.unpack_from(buf, nul + 1)
            if n < 0 or n * OTHER_MARKER_SIZE > end - nul - 5:
                raise _error(f"marker set with impossible marker count {n}", nul + 1, version)
            o = nul + 5 + n * OTHER_MARKER_SIZE
    elif section == "skeletons":
        for _ in range(count):
            _sid, n = _I32X2.unpack_from(buf, o)
            if n < 0 or n * RIGID_BODY_SIZE > end - o - 8:
                raise _error(f"skeleton with impossible bone count {n}", o + 4, version)
            o += 8 + n * RIGID_BODY_SIZE
    else:  # force plates, devices: id, channel count, per channel: frame count + f32 samples
        for _ in range(count):
            _did, n_channels = _I32X2.unpack_from(buf, o)
            o += 8
            if n_channels < 0 or n_channels * 4 > end - o:
                raise _error(f"{section} channel count {n_channels} is impossible", o - 4, version)
            for _ in range(n_channels):
                (n_frames,) = _I32.unpack_from(buf, o)
                o += 4
                if n_frames < 0 or n_frames * 4 > end - o:
                    raise _error(f"{section} frame count {n_frames} is impossible", o - 4, version)
                o += 4 * n_frames
    if o > end:
        raise _error(f"{section} run past the payload end {end}", o, version)
    return o


def _parse_server_info(buf: bytes, end: int) -> ServerInfo:
    """Decode a server-info payload (sSender_Server of the SDK)."""
    o = _HEADER.size
    if end - o < _SERVER_COMMON.size:
        raise NatNetParseError(
            f"NatNet server info (message {NAT_SERVERINFO}): {end - o} payload bytes, "
            f"need at least {_SERVER_COMMON.size}",
            message_id=NAT_SERVERINFO,
            offset=end,
        )
    name_raw, *versions = _SERVER_COMMON.unpack_from(buf, o)
    o += _SERVER_COMMON.size
    app_name = name_raw.split(b"\0", 1)[0].decode("latin-1")
    app_version = tuple(versions[:4])
    natnet_version = tuple(versions[4:])
    if end - o >= _SERVER_3.size:  # NatNet 3.0+ servers append the connection info
        freq, port, multicast, a, b, c, d = _SERVER_3.unpack_from(buf, o)
        return ServerInfo(
            app_name, app_version, natnet_version, freq, port, multicast, f"{a}.{b}.{c}.{d}"
        )
    if end != o:
        raise NatNetParseError(
            f"NatNet server info (message {NAT_SERVERINFO}): {end - o} trailing bytes at "
            f"offset {o} do not form the {_SERVER_3.size}-byte connection info",
            message_id=NAT_SERVERINFO,
            offset=o,
        )
    return ServerInfo(app_name, app_version, natnet_version)
