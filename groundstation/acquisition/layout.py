"""The MCAP layout of a ground-station recording (a file-format contract; pure).

A recording is an MCAP file (https://mcap.dev/spec), profile ``""`` (no ROS profile), written in
zstd-compressed chunks. Everything below is version ``LAYOUT_VERSION``; a reader that meets a
newer version refuses rather than guesses.

Channels
--------
One channel per bus topic (``groundstation.bus.topics``), registered on first use. The station's
own channels use no MCAP schema (``schema_id = 0``): the message encoding names the format.

===================  ==================  =========================================================
topic                message_encoding    message data
===================  ==================  =========================================================
``raw.mavlink``      ``mavlink2``        exactly the bytes read from the firmware link in one read
                                         (one or more MAVLink 2 frames, possibly partial: the
                                         stream is the concatenation of the messages)
``raw.natnet``       ``natnet``          exactly one NatNet UDP datagram; channel metadata
                                         ``natnet_version`` (e.g. ``"4.1"``) and ``motive_up``
                                         (``"y"`` or ``"z"``) when known
``raw.pilot``        ``linux-js``        joystick events as read (8-byte ``js_event`` records)
any other topic      ``gs-envelope/1``   one bus envelope in its single-blob form
                                         (``groundstation.bus.envelope.to_bytes``)
===================  ==================  =========================================================

Beside them, Foxglove channels (topics starting with ``/``, ``message_encoding = "protobuf"``,
an MCAP schema of encoding ``protobuf`` named after the Foxglove well-known schema, e.g.
``foxglove.SceneUpdate``) carry the same data in a form outside tools decode; their table is
``groundstation.openformats.channels``. Readers of this layout select channels by topic and
leave the others alone.

Raw channels hold the wire bytes and nothing else, so replay re-runs the same decoders on them and
outside tools can extract them. Channel metadata always carries ``layout`` (the layout version)
and, when known, ``source`` (the URI the bytes came from, e.g. ``serial:///dev/ttyUSB0``). Two
sources publishing on one topic get two channels with the same topic and different ``source``.

Times
-----
``log_time`` is the station's monotonic receive time in integer nanoseconds; ``publish_time`` is
the source's own timestamp in integer nanoseconds (for raw channels, where the bytes carry their
own timestamps inside, ``publish_time = log_time``). Importers, which have no receive time, use
the source time for both. ``sequence`` is the per-channel message counter starting at 0.

File-level records
------------------
- Metadata record ``groundstation`` (all values strings): ``layout``, ``station_version``,
  ``created_by`` (the program and command that wrote the file), ``config`` (the effective
  configuration as TOML, every section as ``groundstation config show`` prints it, so a replay
  can start from exactly the settings the session ran with; may be empty; recordings written
  before this layout note hold only the ``[acquisition]`` table), ``sources`` (JSON list of
  source URIs), plus free keys. A live session's recording adds ``session`` (the session id) and
  ``segment`` (``"0"``, ``"1"``, ...): a session is its ordered segments, ``flight.mcap``,
  ``flight.001.mcap``, ... (:mod:`~groundstation.acquisition.segments`), each a complete MCAP
  file of its own with the same metadata apart from ``segment``.
  ``utc_offset_ns`` (optional, written by live recorders): UTC time minus the log-time clock
  when the recording started, integer ns as text, so ``log_time + utc_offset_ns`` is the wall
  clock (``export tlog`` dates its records with it).
- Attachment ``truth.json`` (media type ``application/json``): ground truth when it exists (the
  scene, contact events, reference trajectories), one JSON object.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from groundstation.errors import GroundstationError

LAYOUT_VERSION = "1"
PROFILE = ""
ENVELOPE_ENCODING = "gs-envelope/1"
MAVLINK_ENCODING = "mavlink2"
NATNET_ENCODING = "natnet"
RAW_MAVLINK_TOPIC = "raw.mavlink"
RAW_NATNET_TOPIC = "raw.natnet"
RAW_PILOT_TOPIC = "raw.pilot"
JOYSTICK_ENCODING = "linux-js"
RAW_ENCODINGS: dict[str, str] = {
    RAW_MAVLINK_TOPIC: MAVLINK_ENCODING,
    RAW_NATNET_TOPIC: NATNET_ENCODING,
    RAW_PILOT_TOPIC: JOYSTICK_ENCODING,
}
#: Payload field of the bus envelope that names the source of a raw topic (bus/topics.py).
RAW_SOURCE_FIELDS: dict[str, str] = {
    RAW_MAVLINK_TOPIC: "link",
    RAW_NATNET_TOPIC: "sender",
    RAW_PILOT_TOPIC: "device",
}
#: Array of the bus envelope that holds the wire bytes of a raw topic (uint8, shape (n,)).
RAW_DATA_ARRAY = "data"
KNOWN_ENCODINGS = frozenset({ENVELOPE_ENCODING, *RAW_ENCODINGS.values()})
METADATA_NAME = "groundstation"
TRUTH_ATTACHMENT = "truth.json"
TRUTH_MEDIA_TYPE = "application/json"
KEY_LAYOUT = "layout"
KEY_SOURCE = "source"
KEY_NATNET_VERSION = "natnet_version"
KEY_MOTIVE_UP = "motive_up"
KEY_CONFIG = "config"
KEY_SESSION = "session"
KEY_SEGMENT = "segment"
KEY_UTC_OFFSET = "utc_offset_ns"


class LayoutError(GroundstationError, ValueError):
    """A value does not fit the recording layout (topic name, metadata, truth, version)."""


@dataclass(frozen=True)
class ChannelSpec:
    """What identifies one MCAP channel of a recording.

    Attributes
    ----------
    topic : str
        Bus topic, e.g. ``"raw.mavlink"`` or ``"samples.imu"``.
    message_encoding : str
        ``"mavlink2"``, ``"natnet"`` or ``"gs-envelope/1"``.
    metadata : tuple of (str, str)
        Sorted channel metadata items (hashable, so a spec can key a dict).
    """

    topic: str
    message_encoding: str
    metadata: tuple[tuple[str, str], ...]

    def metadata_dict(self) -> dict[str, str]:
        return dict(self.metadata)


def validate_topic(topic: object) -> str:
    """Return ``topic`` if it is a usable topic name, else raise :class:`LayoutError`."""
    if not isinstance(topic, str) or not topic or topic.strip() != topic:
        raise LayoutError(
            f"bad topic name {topic!r}", hint="use a non-empty name like 'samples.imu'"
        )
    return topic


def is_raw_topic(topic: str) -> bool:
    """True for channels that hold wire bytes rather than bus envelopes."""
    return topic in RAW_ENCODINGS


def message_encoding(topic: str) -> str:
    """The MCAP message encoding used for ``topic``."""
    return RAW_ENCODINGS.get(validate_topic(topic), ENVELOPE_ENCODING)


def channel_spec(
    topic: str, *, source: str | None = None, extra: Mapping[str, str] | None = None
) -> ChannelSpec:
    """Build the channel spec for ``topic`` from ``source`` and extra metadata.

    Parameters
    ----------
    topic : str
        Bus topic.
    source : str, optional
        URI the data came from; distinguishes two channels on one topic.
    extra : mapping of str to str, optional
        More channel metadata, e.g. ``{"natnet_version": "4.1"}``.
    """
    meta = {KEY_LAYOUT: LAYOUT_VERSION}
    if source is not None:
        meta[KEY_SOURCE] = str(source)
    for key, value in (extra or {}).items():
        if not isinstance(key, str) or not isinstance(value, str):
            raise LayoutError(f"channel metadata must map str to str, got {key!r}: {value!r}")
        meta[key] = value
    return ChannelSpec(topic, message_encoding(topic), tuple(sorted(meta.items())))


def check_layout_version(version: str | None, where: str) -> None:
    """Refuse a recording written with a layout this code does not know."""
    if version is not None and version != LAYOUT_VERSION:
        raise LayoutError(
            f"{where}: recording layout version {version!r} is not supported "
            f"(this station reads version {LAYOUT_VERSION!r})",
            hint="read it with the station version that wrote it",
        )


def station_metadata(
    *,
    station_version: str,
    created_by: str,
    config: str = "",
    sources: Iterable[str] = (),
    extra: Mapping[str, str] | None = None,
    session: str | None = None,
    segment: int | None = None,
) -> dict[str, str]:
    """The ``groundstation`` metadata record (all values are strings).

    Parameters
    ----------
    station_version : str
        ``groundstation.__version__`` or similar.
    created_by : str
        Program and command that wrote the file, e.g. ``"groundstation import csv IMU_1.csv"``.
    config : str
        Effective configuration as text (TOML), may be empty.
    sources : iterable of str
        Source URIs.
    extra : mapping of str to str, optional
        Free keys; they may not shadow the fixed ones.
    session : str, optional
        Session id of a live recording (its segments share it).
    segment : int, optional
        Index of this file among the session's segments (0 = the first).
    """
    meta = {
        KEY_LAYOUT: LAYOUT_VERSION,
        "station_version": str(station_version),
        "created_by": str(created_by),
        KEY_CONFIG: str(config),
        "sources": json.dumps([str(s) for s in sources]),
    }
    if session is not None:
        meta[KEY_SESSION] = str(session)
    if segment is not None:
        if int(segment) < 0:
            raise LayoutError(f"segment index {segment} must be >= 0")
        meta[KEY_SEGMENT] = str(int(segment))
    for key, value in (extra or {}).items():
        if key in meta:
            raise LayoutError(f"metadata key {key!r} is reserved by the layout")
        if not isinstance(key, str) or not isinstance(value, str):
            raise LayoutError(f"metadata must map str to str, got {key!r}: {value!r}")
        meta[key] = value
    return meta


def segment_index(meta: Mapping[str, str]) -> int | None:
    """The ``segment`` index of a metadata record (None when absent or not a number >= 0)."""
    raw = meta.get(KEY_SEGMENT)
    try:
        value = int(raw) if raw is not None else None
    except ValueError:
        return None
    return value if value is not None and value >= 0 else None


def parse_utc_offset(meta: Mapping[str, str] | None) -> int | None:
    """The ``utc_offset_ns`` of a metadata record, or None when absent or unreadable."""
    try:
        return int((meta or {})[KEY_UTC_OFFSET])
    except (KeyError, ValueError):
        return None


def parse_sources(meta: Mapping[str, str]) -> list[str]:
    """The source URIs stored in a ``groundstation`` metadata record."""
    raw = meta.get("sources", "[]")
    try:
        sources = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise LayoutError(f"metadata 'sources' is not JSON: {raw[:80]!r} ({exc})") from None
    if not isinstance(sources, list) or not all(isinstance(s, str) for s in sources):
        raise LayoutError(f"metadata 'sources' must be a JSON list of strings, got {raw[:80]!r}")
    return sources


def _check_finite(obj: Any, path: str = "truth") -> None:
    if isinstance(obj, float) and not math.isfinite(obj):
        raise LayoutError(f"{path} is {obj!r}; ground truth must be finite")
    if isinstance(obj, Mapping):
        for key, value in obj.items():
            if not isinstance(key, str):
                raise LayoutError(f"{path} has a non-string key {key!r}")
            _check_finite(value, f"{path}.{key}")
    elif isinstance(obj, list | tuple):
        for i, value in enumerate(obj):
            _check_finite(value, f"{path}[{i}]")


def encode_truth(truth: Mapping[str, Any]) -> bytes:
    """Serialise ground truth for the ``truth.json`` attachment (sorted keys, UTF-8).

    Raises
    ------
    LayoutError
        If ``truth`` is not a JSON object of finite values.
    """
    if not isinstance(truth, Mapping):
        raise LayoutError(f"ground truth must be a mapping, got {type(truth).__name__}")
    _check_finite(truth)
    try:
        text = json.dumps(truth, sort_keys=True, separators=(",", ":"), allow_nan=False)
    except TypeError as exc:
        raise LayoutError(f"ground truth is not JSON-serialisable: {exc}") from None
    return text.encode("utf-8")


def decode_truth(data: bytes) -> dict[str, Any]:
    """Parse a ``truth.json`` attachment."""
    try:
        truth = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise LayoutError(f"truth.json attachment is not UTF-8 JSON: {exc}") from None
    if not isinstance(truth, dict):
        raise LayoutError(f"truth.json must hold a JSON object, got {type(truth).__name__}")
    return truth


def seconds_to_ns(t_s: float) -> int:
    """Seconds (float) to integer nanoseconds, rounded to nearest."""
    if not math.isfinite(t_s):
        raise LayoutError(f"time {t_s!r} s is not finite")
    return int(round(t_s * 1e9))
