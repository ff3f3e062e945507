"""Encode NatNet frames of data and server info in the layouts :mod:`.parser` reads.

Used by the SITL (which plays Motive) and by round-trip tests. The sections the station skips
can be filled from :class:`FrameExtras` so that a parser's skipping is exercised for real.
Layout reference: see :mod:`firmware_bridge.natnet.parser`.
"""

from __future__ import annotations

import ipaddress
import struct
from collections.abc import Iterable

from firmware_bridge.errors import ProtocolError
from firmware_bridge.natnet.records import (
    NAT_CONNECT,
    NAT_FRAMEOFDATA,
    NAT_SERVERINFO,
    AnalogDevice,
    FrameExtras,
    FrameOfData,
    RigidBody,
    ServerInfo,
    check_version,
)

_HEADER = struct.Struct("<HH")
_I32 = struct.Struct("<i")
_I32X2 = struct.Struct("<ii")
_VEC3 = struct.Struct("<3f")
_RIGID_BODY = struct.Struct("<i3f4ffh")
_MARKER = struct.Struct("<i3ffhf")  # labeled / asset marker: id, position, size, params, residual
_SUFFIX_3 = struct.Struct("<IIdQQQ")
_PRECISION = struct.Struct("<II")
_TAIL = struct.Struct("<hi")
_SERVER_COMMON = struct.Struct("<256s4B4B")
_SERVER_3 = struct.Struct("<QH?4s")

_EMPTY_EXTRAS = FrameExtras()


def encode_message(message_id: int, payload: bytes) -> bytes:
    """Prefix ``payload`` with the NatNet header (u16 message id, u16 byte count).

    Raises
    ------
    ProtocolError
        If the payload exceeds the 65535 bytes a NatNet header can declare.
    """
    if len(payload) > 0xFFFF:
        raise ProtocolError(
            f"NatNet message {message_id} payload of {len(payload)} bytes exceeds 65535",
            hint="stream fewer markers or rigid bodies per frame",
        )
    return _HEADER.pack(message_id, len(payload)) + payload


def encode_connect_request(client_version: tuple[int, int, int, int] = (4, 1, 0, 0)) -> bytes:
    """Encode a connect request (message 0), which servers answer with server info.

    The payload mirrors NatNetLib's: a 256-byte name, the client's app and NatNet versions.
    """
    payload = _SERVER_COMMON.pack(b"NatNetLib", *client_version, *client_version)
    return encode_message(NAT_CONNECT, payload)


def _rigid_body(body: RigidBody) -> bytes:
    return _RIGID_BODY.pack(
        body.id, *body.position, *body.orientation, body.mean_error, 1 if body.tracking_valid else 0
    )


def _section(count: int, body: bytes, sized: bool) -> bytes:
    """Section = i32 count, [i32 byte count (4.1+)], items."""
    if sized:
        return _I32X2.pack(count, len(body)) + body
    return _I32.pack(count) + body


def _analog(devices: Iterable[AnalogDevice]) -> bytes:
    out = bytearray()
    for dev in devices:
        out += _I32X2.pack(dev.id, len(dev.channels))
        for samples in dev.channels:
            out += _I32.pack(len(samples)) + struct.pack(f"<{len(samples)}f", *samples)
    return bytes(out)


def encode_frame_of_data(
    frame: FrameOfData, version: tuple[int, int] = (4, 1), extras: FrameExtras | None = None
) -> bytes:
    """Encode a frame of data (message 7), header included.

    Parameters
    ----------
    frame : FrameOfData
        Rigid bodies and timing to send. Its ``*_count`` fields are ignored: the skipped
        sections are written from ``extras`` (empty by default).
    version : (int, int)
        Bitstream version (3.0, 3.1, 4.0 or 4.1).
    extras : FrameExtras, optional
        Marker sets, other markers, skeletons, assets (4.1 only), labeled markers, force
        plates and devices to include.

    Returns
    -------
    bytes
        One datagram.

    Raises
    ------
    ProtocolError
        Unsupported version, value out of the wire's range (e.g. an id beyond int32), or
        assets for a version before 4.1.
    """
    version = check_version(version, NAT_FRAMEOFDATA)
    sized = version >= (4, 1)
    ex = extras or _EMPTY_EXTRAS
    if ex.assets and not sized:
        raise ProtocolError(
            f"assets cannot be encoded in NatNet {version[0]}.{version[1]} (4.1+ only)",
            hint="drop FrameExtras.assets or encode version (4, 1)",
        )
    try:
        out = bytearray(_I32.pack(frame.frame_id))
        sets = bytearray()
        for mset in ex.marker_sets:
            sets += mset.name.encode("ascii") + b"\0" + _I32.pack(len(mset.markers))
            for m in mset.markers:
                sets += _VEC3.pack(*m)
        out += _section(len(ex.marker_sets), bytes(sets), sized)
        others = b"".join(_VEC3.pack(*m) for m in ex.other_markers)
        out += _section(len(ex.other_markers), others, sized)
        bodies = b"".join(_rigid_body(b) for b in frame.rigid_bodies)
        out += _section(len(frame.rigid_bodies), bodies, sized)
        skels = bytearray()
        for sk in ex.skeletons:
            skels += _I32X2.pack(sk.id, len(sk.bones))
            skels += b"".join(_rigid_body(b) for b in sk.bones)
        out += _section(len(ex.skeletons), bytes(skels), sized)
        if sized:
            assets = bytearray()
            for asset in ex.assets:
                assets += _I32X2.pack(asset.id, len(asset.rigid_bodies))
                assets += b"".join(_rigid_body(b) for b in asset.rigid_bodies)
                assets += _I32.pack(len(asset.markers))
                for m in asset.markers:
                    assets += _MARKER.pack(m.id, *m.position, m.size, m.params, m.residual)
            out += _section(len(ex.assets), bytes(assets), sized)
        labeled = b"".join(
            _MARKER.pack(m.id, *m.position, m.size, m.params, m.residual)
            for m in ex.labeled_markers
        )
        out += _section(len(ex.labeled_markers), labeled, sized)
        out += _section(len(ex.force_plates), _analog(ex.force_plates), sized)
        out += _section(len(ex.devices), _analog(ex.devices), sized)
        out += _SUFFIX_3.pack(
            frame.timecode,
            frame.timecode_subframe,
            frame.timestamp_s,
            frame.camera_mid_exposure_ts,
            frame.data_received_ts,
            frame.transmit_ts,
        )
        if sized:
            out += _PRECISION.pack(frame.precision_timestamp_s, frame.precision_timestamp_frac)
        params = frame.params - 0x10000 if frame.params >= 0x8000 else frame.params
        out += _TAIL.pack(params, 0)
    except (struct.error, UnicodeEncodeError) as exc:
        raise ProtocolError(
            f"frame {frame.frame_id} cannot be encoded as NatNet {version[0]}.{version[1]}: {exc}",
            hint="ids are int32, ticks uint64, params 16 bits, names ASCII",
        ) from None
    return encode_message(NAT_FRAMEOFDATA, bytes(out))


def encode_server_info(info: ServerInfo) -> bytes:
    """Encode a server-info message (message 1) in the NatNet 3.0+ form.

    ``data_port``/``multicast``/``multicast_address`` of None are sent as 0, False, 0.0.0.0.

    Raises
    ------
    ProtocolError
        Name longer than 255 bytes, a version part outside 0-255, or a bad address.
    """
    name = info.app_name.encode("latin-1", errors="replace")
    if len(name) > 255:
        raise ProtocolError(f"server app name of {len(name)} bytes exceeds 255")
    try:
        addr = ipaddress.IPv4Address(info.multicast_address or "0.0.0.0").packed
        payload = _SERVER_COMMON.pack(name, *info.app_version, *info.natnet_version)
        payload += _SERVER_3.pack(
            info.clock_frequency, info.data_port or 0, bool(info.multicast), addr
        )
    except (struct.error, ValueError) as exc:
        raise ProtocolError(f"server info {info!r} cannot be encoded: {exc}") from None
    return encode_message(NAT_SERVERINFO, payload)
