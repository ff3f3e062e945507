"""OptiTrack NatNet: our own decoder and encoder for bitstreams 3.0, 3.1, 4.0 and 4.1.

Why our own: no well-kept Python NatNet package on PyPI handles 3.0-4.1 with skip-correctness
(every unused section skipped exactly, the 4.1 per-section byte counts honoured). OptiTrack's
``NatNetClient.py`` is a sample, not a package (and its 4.1 suffix branch is unreachable);
``python_natnet`` (mje-nz) stops at 3.x and is unmaintained. Layouts follow the NatNet SDK's
``PacketClient.cpp``/``NatNetClient.py`` and are checked against real Motive traffic.

Layers: bytes -> :func:`parse_packet` -> typed records (:mod:`.records`);
:func:`encode_frame_of_data` / :func:`encode_server_info` go the other way;
:class:`firmware_bridge.natnet.link.NatNetLink` is the UDP shell (import it from its module so
that decoding never imports sockets).
"""

from firmware_bridge.natnet.encoder import (
    encode_connect_request,
    encode_frame_of_data,
    encode_message,
    encode_server_info,
)
from firmware_bridge.natnet.parser import parse_packet
from firmware_bridge.natnet.records import (
    NAT_CONNECT,
    NAT_FRAMEOFDATA,
    NAT_MODELDEF,
    NAT_REQUEST_MODELDEF,
    NAT_SERVERINFO,
    SUPPORTED_VERSIONS,
    AnalogDevice,
    Asset,
    AssetMarker,
    FrameExtras,
    FrameOfData,
    LabeledMarker,
    MarkerSet,
    NatNetParseError,
    RigidBody,
    ServerInfo,
    Skeleton,
    UnknownMessage,
)

__all__ = [
    "NAT_CONNECT",
    "NAT_FRAMEOFDATA",
    "NAT_MODELDEF",
    "NAT_REQUEST_MODELDEF",
    "NAT_SERVERINFO",
    "SUPPORTED_VERSIONS",
    "AnalogDevice",
    "Asset",
    "AssetMarker",
    "FrameExtras",
    "FrameOfData",
    "LabeledMarker",
    "MarkerSet",
    "NatNetParseError",
    "RigidBody",
    "ServerInfo",
    "Skeleton",
    "UnknownMessage",
    "encode_connect_request",
    "encode_frame_of_data",
    "encode_message",
    "encode_server_info",
    "parse_packet",
]
