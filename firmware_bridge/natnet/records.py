"""Typed NatNet records: what the parser returns and what the encoder accepts.

Values are kept exactly as they travel on the wire (Motive's axes, metres, quaternion in
x, y, z, w order); axis conversion is :mod:`firmware_bridge.frames`' job.

The records for sections the station does not use (marker sets, skeletons, assets, labeled
markers, force plates, devices) exist so that the encoder can emit realistic frames (SITL,
skip-correctness tests). The parser only counts them.
"""

from __future__ import annotations

from dataclasses import dataclass

from firmware_bridge.errors import ProtocolError

#: Message ids (NatNet SDK ``NatNetTypes.h``: NAT_CONNECT ... NAT_KEEPALIVE).
NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10

#: Bitstream versions whose frame-of-data layout this package decodes and encodes.
SUPPORTED_VERSIONS: tuple[tuple[int, int], ...] = ((3, 0), (3, 1), (4, 0), (4, 1))

Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


class NatNetParseError(ProtocolError):
    """A NatNet packet is truncated, inconsistent or of an unsupported version.

    Parameters
    ----------
    message : str
        What is wrong; names the message id, byte offset and bitstream version.
    hint : str, optional
        How to fix it.
    message_id, offset : int, optional
        Where decoding stopped.
    version : tuple of int, optional
        Bitstream version that was assumed.
    """

    def __init__(
        self,
        message: str,
        hint: str | None = None,
        *,
        message_id: int | None = None,
        offset: int | None = None,
        version: tuple[int, int] | None = None,
    ):
        super().__init__(message, hint)
        self.message_id = message_id
        self.offset = offset
        self.version = version


@dataclass(frozen=True, slots=True)
class RigidBody:
    """One rigid body of a frame of data.

    Attributes
    ----------
    id : int
        Streaming id set in Motive.
    position : (3,) tuple of float
        Metres, Motive's frame (Y-up or Z-up as configured in Motive).
    orientation : (4,) tuple of float
        Unit quaternion (x, y, z, w) exactly as on the wire.
    mean_error : float
        Mean marker error, metres.
    tracking_valid : bool
        Rigid-body params bit 0x01: tracked in this frame.
    """

    id: int
    position: Vec3
    orientation: Quat
    mean_error: float
    tracking_valid: bool


@dataclass(frozen=True, slots=True)
class FrameOfData:
    """A decoded NatNet frame of data (message 7).

    Attributes
    ----------
    frame_id : int
        Motive's frame counter.
    rigid_bodies : tuple of RigidBody
    timestamp_s : float
        Motive's software timestamp, seconds since its clock started.
    camera_mid_exposure_ts, data_received_ts, transmit_ts : int
        High-resolution clock ticks (divide by ``ServerInfo.clock_frequency`` for seconds).
    params : int
        Frame params: 0x01 recording, 0x02 tracked models changed, 0x04 bitstream changed.
    timecode, timecode_subframe : int
        SMPTE timecode (packed as in the SDK) and subframe.
    precision_timestamp_s, precision_timestamp_frac : int
        NatNet 4.1 precision (PTP) timestamp: whole seconds and fractional part (0 if absent).
    marker_set_count, other_marker_count, skeleton_count, asset_count, labeled_marker_count,
    force_plate_count, device_count : int
        Sizes of the sections that were skipped (assets exist from 4.1 on).
    """

    frame_id: int
    rigid_bodies: tuple[RigidBody, ...]
    timestamp_s: float
    camera_mid_exposure_ts: int = 0
    data_received_ts: int = 0
    transmit_ts: int = 0
    params: int = 0
    timecode: int = 0
    timecode_subframe: int = 0
    precision_timestamp_s: int = 0
    precision_timestamp_frac: int = 0
    marker_set_count: int = 0
    other_marker_count: int = 0
    skeleton_count: int = 0
    asset_count: int = 0
    labeled_marker_count: int = 0
    force_plate_count: int = 0
    device_count: int = 0

    def rigid_body(self, body_id: int) -> RigidBody | None:
        """Return the rigid body with streaming id ``body_id``, or None if absent."""
        for body in self.rigid_bodies:
            if body.id == body_id:
                return body
        return None


@dataclass(frozen=True, slots=True)
class ServerInfo:
    """Server description (message 1, reply to a connect request).

    Attributes
    ----------
    app_name : str
        Streaming application, e.g. ``"Motive"``.
    app_version, natnet_version : (4,) tuple of int
        Application and NatNet bitstream versions (major, minor, build, revision).
    clock_frequency : int
        High-resolution clock frequency, ticks per second (0 when the server did not send it,
        i.e. before NatNet 3.0).
    data_port : int or None
        UDP port frames are sent to.
    multicast : bool or None
        Whether frames are multicast.
    multicast_address : str or None
        Dotted multicast group, e.g. ``"239.255.42.99"``.
    """

    app_name: str
    app_version: tuple[int, int, int, int]
    natnet_version: tuple[int, int, int, int]
    clock_frequency: int = 0
    data_port: int | None = None
    multicast: bool | None = None
    multicast_address: str | None = None

    @property
    def bitstream_version(self) -> tuple[int, int]:
        """(major, minor) to pass to :func:`parse_packet` for this server's frames."""
        return (self.natnet_version[0], self.natnet_version[1])


@dataclass(frozen=True, slots=True)
class UnknownMessage:
    """A message this package does not decode (model definitions, echo, commands...)."""

    message_id: int
    payload: bytes


# --- Sections the station skips; encoder input only -----------------------------------------


@dataclass(frozen=True, slots=True)
class MarkerSet:
    """Named marker set: ``name`` (ASCII, no NUL) and marker positions (m)."""

    name: str
    markers: tuple[Vec3, ...] = ()


@dataclass(frozen=True, slots=True)
class Skeleton:
    """Skeleton: id and bones (rigid-body layout of the frame's version)."""

    id: int
    bones: tuple[RigidBody, ...] = ()


@dataclass(frozen=True, slots=True)
class LabeledMarker:
    """Labeled marker: packed id (model << 16 | marker), position, size (m), params, residual."""

    id: int
    position: Vec3
    size: float = 0.02
    params: int = 0
    residual: float = 0.0


@dataclass(frozen=True, slots=True)
class AssetMarker:
    """Marker of a NatNet 4.1 asset (same fields as a labeled marker)."""

    id: int
    position: Vec3
    size: float = 0.02
    params: int = 0
    residual: float = 0.0


@dataclass(frozen=True, slots=True)
class Asset:
    """NatNet 4.1 asset (trained markerset): rigid bodies and markers."""

    id: int
    rigid_bodies: tuple[RigidBody, ...] = ()
    markers: tuple[AssetMarker, ...] = ()


@dataclass(frozen=True, slots=True)
class AnalogDevice:
    """Force plate or peripheral device: id and per-channel sample lists."""

    id: int
    channels: tuple[tuple[float, ...], ...] = ()


@dataclass(frozen=True, slots=True)
class FrameExtras:
    """Content of the skipped sections, for the encoder (SITL realism, skip tests)."""

    marker_sets: tuple[MarkerSet, ...] = ()
    other_markers: tuple[Vec3, ...] = ()
    skeletons: tuple[Skeleton, ...] = ()
    assets: tuple[Asset, ...] = ()
    labeled_markers: tuple[LabeledMarker, ...] = ()
    force_plates: tuple[AnalogDevice, ...] = ()
    devices: tuple[AnalogDevice, ...] = ()


def check_version(version: tuple[int, int], message_id: int | None = None) -> tuple[int, int]:
    """Validate a bitstream version and return it as ``(major, minor)``.

    Raises
    ------
    NatNetParseError
        If the version is not one of :data:`SUPPORTED_VERSIONS`.
    """
    try:
        key = (int(version[0]), int(version[1]))
    except (TypeError, ValueError, IndexError) as exc:
        raise NatNetParseError(
            f"NatNet version {version!r} is not a (major, minor) pair",
            hint="pass e.g. (4, 1) or ServerInfo.bitstream_version",
            message_id=message_id,
        ) from exc
    if key not in SUPPORTED_VERSIONS:
        raise NatNetParseError(
            f"NatNet bitstream version {key[0]}.{key[1]} is not supported "
            f"(supported: {', '.join(f'{a}.{b}' for a, b in SUPPORTED_VERSIONS)})",
            hint="set Motive's streaming bitstream version to 3.x or 4.0/4.1",
            message_id=message_id,
            version=key,
        )
    return key
