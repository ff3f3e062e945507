"""The bus envelope: pure, deterministic serialization (no sockets, no clock, no pickle).

One message travels as ZeroMQ multipart frames::

    [topic, header, meta, buffer0, buffer1, ...]

- ``topic``: the topic name, UTF-8 (ZeroMQ subscriptions match it as a prefix; the topic table
  guarantees no name is a prefix of another, so subscribing to a name is an exact match).
- ``header``: fixed little-endian layout :data:`HEADER_STRUCT`, then the type name::

      offset size field
      0      3    magic b"GSB" (a foreign message is detected here)
      3      1    envelope format version (:data:`FORMAT_VERSION`)
      4      2    schema version of the payload (uint16)
      6      1    length L of the type name (uint8)
      7      1    padding (0)
      8      4    origin: id of the publishing instance (uint32; sequences are per origin)
      12     8    sequence number, per topic and origin (uint64)
      20     8    source time, ns (int64; the clock of the data's source)
      28     8    receive time, ns (int64; station monotonic clock, 0 = not stamped yet)
      36     L    type name, UTF-8

- ``meta``: compact JSON ``{"a": [[name, dtype, shape], ...], "p": payload}`` with sorted keys,
  so encoding is deterministic (``encode(decode(frames)) == frames``).
- ``buffer_i``: the raw C-order bytes of array ``i``; decoding wraps them with ``np.frombuffer``
  (zero-copy, read-only). Only little-endian numeric/bool dtypes are allowed (no object dtype).

Decoding takes bytes from other processes and from recordings, so it is bounded and raises only
:class:`EnvelopeError` (fuzzed: ``groundstation bench fuzz --target envelope``): topic frame
<= :data:`MAX_TOPIC_LEN` bytes, meta frame <= :data:`MAX_META_BYTES`, JSON nesting <=
:data:`MAX_JSON_DEPTH`, integers within int64/uint64 (at most 20 digits: a 5,000-digit integer
would otherwise cost seconds or raise ``ValueError``), floats finite (``1e999`` parses to inf and
``NaN`` is not JSON), at most :data:`MAX_ARRAYS` arrays of at most :data:`MAX_NDIM` dimensions,
each at most :data:`MAX_DIM` long, spanning at most :data:`MAX_ARRAY_BYTES` even when another
dimension is 0 (a zero-size array with a dimension of 2**70 made numpy raise ``ValueError``).

The single-blob form (:func:`to_bytes` / :func:`from_bytes`) length-prefixes the frames so a
recorder can store a message as one MCAP record and a replay can republish it byte-for-byte::

    uint32 frame count N, then N times: uint64 length, bytes        (little-endian)

Model: jupyter_client ``session.py`` (header + content + buffers) and pyzmq
``examples/serialization`` (arrays as dtype/shape + raw buffer).
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from groundstation.bus.errors import EnvelopeError

if TYPE_CHECKING:
    from groundstation.bus.topics import Topic

MAGIC = b"GSB"
FORMAT_VERSION = 1
HEADER_STRUCT = struct.Struct("<3sBHBxIQqq")  # see the module docstring for the layout
MAX_TYPE_LEN = 255
ALLOWED_DTYPES = frozenset(
    ["|b1", "|i1", "|u1", "<i2", "<u2", "<i4", "<u4", "<i8", "<u8"]
    + ["<f2", "<f4", "<f8", "<c8", "<c16"]
)
MAX_TOPIC_LEN = 255
MAX_META_BYTES = 1 << 20
MAX_JSON_DEPTH = 32
MAX_ARRAYS = 256
MAX_NDIM = 8
MAX_DIM = 1 << 40
MAX_ARRAY_BYTES = 1 << 40
_MAX_INT_DIGITS = 20  # uint64 max has 20 digits
_INT_MIN, _INT_MAX = -(2**63), 2**64 - 1
_BLOB_COUNT = struct.Struct("<I")
_BLOB_LEN = struct.Struct("<Q")
_MAX_FRAMES = 1 << 16

Buffer = bytes | bytearray | memoryview


@dataclass(frozen=True)
class Header:
    """Versioned message header.

    Parameters
    ----------
    type : str
        Message type name (declared per topic in :mod:`groundstation.bus.topics`).
    schema : int
        Payload schema version, 0..65535.
    seq : int
        Per-topic sequence number assigned by the publisher, starting at 0.
    source_ns : int
        Source timestamp, ns (the clock of the data's origin).
    recv_ns : int
        Station monotonic receive time, ns; 0 means "not stamped yet".
    origin : int
        Id of the publishing instance (uint32). Sequence numbers count per (topic, origin), so
        a restarted publisher (new origin) starts a new stream instead of showing a gap.
    """

    type: str
    schema: int
    seq: int
    source_ns: int
    recv_ns: int = 0
    origin: int = 0


@dataclass(frozen=True, eq=False)
class Envelope:
    """One bus message: topic + header + JSON payload + named arrays.

    Parameters
    ----------
    topic : str
        Topic name.
    header : Header
        Versioned header.
    payload : dict
        JSON-compatible values (str, int, float (finite), bool, None, lists, dicts).
    arrays : dict of str to numpy.ndarray
        Named numeric arrays; any shape (0-d and empty included).
    """

    topic: str
    header: Header
    payload: dict[str, Any] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)

    def with_recv_ns(self, recv_ns: int) -> Envelope:
        """Return a copy whose header carries ``recv_ns``."""
        return replace(self, header=replace(self.header, recv_ns=int(recv_ns)))


def pack_header(header: Header) -> bytes:
    """Pack a :class:`Header` into its fixed little-endian layout."""
    type_b = header.type.encode("utf-8")
    if not 0 < len(type_b) <= MAX_TYPE_LEN:
        raise EnvelopeError(f"type name {header.type!r} must be 1..{MAX_TYPE_LEN} UTF-8 bytes")
    try:
        fixed = HEADER_STRUCT.pack(
            MAGIC,
            FORMAT_VERSION,
            header.schema,
            len(type_b),
            header.origin,
            header.seq,
            header.source_ns,
            header.recv_ns,
        )
    except struct.error as exc:
        raise EnvelopeError(
            f"header field out of range in {header} ({exc})",
            hint="schema is uint16, origin uint32, seq uint64, source_ns/recv_ns int64",
        ) from None
    return fixed + type_b


def unpack_header(frame: Buffer) -> Header:
    """Parse a header frame; raises :class:`EnvelopeError` on a foreign or truncated frame."""
    mv = memoryview(frame)
    if mv.nbytes < HEADER_STRUCT.size:
        raise EnvelopeError(f"header frame too short: {mv.nbytes} < {HEADER_STRUCT.size} bytes")
    magic, version, schema, type_len, origin, seq, source_ns, recv_ns = HEADER_STRUCT.unpack_from(
        mv
    )
    if magic != MAGIC:
        raise EnvelopeError(f"bad magic {bytes(magic)!r} (expected {MAGIC!r}): not a bus message")
    if version != FORMAT_VERSION:
        raise EnvelopeError(
            f"unsupported envelope format version {version} (this build reads {FORMAT_VERSION})"
        )
    if mv.nbytes != HEADER_STRUCT.size + type_len:
        raise EnvelopeError(
            f"header frame is {mv.nbytes} bytes, expected {HEADER_STRUCT.size + type_len}"
        )
    try:
        type_name = bytes(mv[HEADER_STRUCT.size :]).decode("utf-8")
    except UnicodeDecodeError:
        raise EnvelopeError("type name in header is not valid UTF-8") from None
    return Header(type_name, schema, seq, source_ns, recv_ns, origin)


def _as_wire_array(name: str, value: Any) -> np.ndarray:
    a = np.asarray(value)
    if a.dtype.kind not in "biufc":
        raise EnvelopeError(
            f"array {name!r} has dtype {a.dtype} which is not allowed on the bus",
            hint="use bool, integer, float or complex arrays (no object/str/structured dtypes)",
        )
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    if not a.flags.c_contiguous:
        a = a.copy(order="C")  # np.ascontiguousarray would turn 0-d into 1-d
    return a


def encode(env: Envelope) -> list[bytes | memoryview]:
    """Serialize an envelope into multipart frames.

    Array frames are zero-copy ``memoryview`` objects over the (contiguous) arrays: do not
    modify the arrays until the frames are sent.

    Parameters
    ----------
    env : Envelope
        The message.

    Returns
    -------
    list of bytes or memoryview
        ``[topic, header, meta, buffer0, ...]``.

    Raises
    ------
    EnvelopeError
        Non-JSON payload (including NaN/inf floats), disallowed dtype, bad header field.
    """
    if not isinstance(env.payload, Mapping):
        raise EnvelopeError(f"payload must be a dict, got {type(env.payload).__name__}")
    arrays = [(str(n), _as_wire_array(str(n), v)) for n, v in env.arrays.items()]
    meta = {"a": [[n, a.dtype.str, list(a.shape)] for n, a in arrays], "p": dict(env.payload)}
    try:
        meta_b = json.dumps(
            meta, sort_keys=True, separators=(",", ":"), allow_nan=False, ensure_ascii=True
        ).encode("ascii")
    except (TypeError, ValueError) as exc:
        raise EnvelopeError(
            f"payload of topic {env.topic!r} is not JSON-serializable: {exc}",
            hint="payload values must be str/int/finite float/bool/None/list/dict; "
            "put numbers that may be NaN into arrays",
        ) from None
    frames: list[bytes | memoryview] = [env.topic.encode("utf-8"), pack_header(env.header), meta_b]
    frames += [memoryview(a.reshape(-1).view(np.uint8)) for _, a in arrays]
    return frames


def _json_int(text: str) -> int:
    if len(text.lstrip("-")) > _MAX_INT_DIGITS:
        raise EnvelopeError(f"integer with {len(text)} digits in meta (limit {_MAX_INT_DIGITS})")
    value = int(text)
    if not _INT_MIN <= value <= _INT_MAX:
        raise EnvelopeError(f"integer {value} in meta is outside int64/uint64")
    return value


def _json_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise EnvelopeError(f"number {text[:40]!r} in meta overflows to {value}")
    return value


def _json_constant(text: str) -> float:
    raise EnvelopeError(f"{text} is not allowed in meta (JSON has no NaN/Infinity)")


def _check_depth(value: Any, depth: int = 0) -> None:
    if depth > MAX_JSON_DEPTH:
        raise EnvelopeError(f"meta nests deeper than {MAX_JSON_DEPTH} levels")
    if isinstance(value, dict):
        for v in value.values():
            _check_depth(v, depth + 1)
    elif isinstance(value, list):
        for v in value:
            _check_depth(v, depth + 1)


def _parse_meta(frame: Buffer) -> tuple[dict[str, Any], list[tuple[str, str, tuple[int, ...]]]]:
    raw = bytes(frame)
    if len(raw) > MAX_META_BYTES:
        raise EnvelopeError(f"meta frame of {len(raw)} bytes exceeds {MAX_META_BYTES}")
    try:
        meta = json.loads(
            raw, parse_int=_json_int, parse_float=_json_float, parse_constant=_json_constant
        )
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise EnvelopeError(f"meta frame is not valid JSON: {exc}") from None
    except RecursionError:
        raise EnvelopeError(f"meta nests deeper than {MAX_JSON_DEPTH} levels") from None
    _check_depth(meta)
    if not isinstance(meta, dict) or set(meta) != {"a", "p"}:
        raise EnvelopeError("meta frame must be a JSON object with exactly the keys 'a' and 'p'")
    payload, descs = meta["p"], meta["a"]
    if not isinstance(payload, dict):
        raise EnvelopeError(f"payload must be a JSON object, got {type(payload).__name__}")
    if not isinstance(descs, list):
        raise EnvelopeError("array descriptors ('a') must be a JSON list")
    if len(descs) > MAX_ARRAYS:
        raise EnvelopeError(f"meta declares {len(descs)} arrays (limit {MAX_ARRAYS})")
    out: list[tuple[str, str, tuple[int, ...]]] = []
    for d in descs:
        ok = isinstance(d, list) and len(d) == 3 and isinstance(d[0], str)
        ok = ok and isinstance(d[1], str) and isinstance(d[2], list)
        ok = ok and all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in d[2])
        if not ok:
            raise EnvelopeError(f"bad array descriptor {_short(d)} (expected [name, dtype, shape])")
        if d[1] not in ALLOWED_DTYPES:
            raise EnvelopeError(
                f"array {_short(d[0])}: dtype {_short(d[1])} not allowed "
                f"(allowed: {sorted(ALLOWED_DTYPES)})"
            )
        if len(d[2]) > MAX_NDIM or any(s > MAX_DIM for s in d[2]):
            raise EnvelopeError(
                f"array {_short(d[0])}: shape {_short(d[2])} exceeds the limits "
                f"({MAX_NDIM} dimensions of at most {MAX_DIM})"
            )
        out.append((d[0], d[1], tuple(d[2])))
    names = [d[0] for d in out]
    if len(set(names)) != len(names):
        raise EnvelopeError(f"duplicate array names in {_short(names)}")
    return payload, out


def _short(value: Any, limit: int = 80) -> str:
    """``repr`` cut to ``limit`` characters (error messages never echo megabytes)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def decode(frames: Sequence[Buffer], table: Mapping[str, Topic] | None = None) -> Envelope:
    """Parse multipart frames into an :class:`Envelope` (arrays are read-only views).

    Parameters
    ----------
    frames : sequence of bytes-like
        ``[topic, header, meta, buffer0, ...]`` as produced by :func:`encode`.
    table : mapping of str to Topic, optional
        Topic table; when given, the topic must be known, type and schema version must match,
        and the payload/arrays are validated against the topic's declaration.

    Raises
    ------
    EnvelopeError
        Bad magic, unknown type/schema for the topic, disallowed dtype, shape/size mismatch,
        JSON error, frame count mismatch (:class:`SchemaError` for declaration mismatches).
    """
    if len(frames) < 3:
        raise EnvelopeError(f"frame count mismatch: {len(frames)} frames, need at least 3")
    topic_b = bytes(memoryview(frames[0])[: MAX_TOPIC_LEN + 1])
    if len(topic_b) > MAX_TOPIC_LEN:
        raise EnvelopeError(f"topic frame longer than {MAX_TOPIC_LEN} bytes")
    try:
        topic = topic_b.decode("utf-8")
    except UnicodeDecodeError:
        raise EnvelopeError("topic frame is not valid UTF-8") from None
    header = unpack_header(frames[1])
    payload, descs = _parse_meta(frames[2])
    if len(frames) != 3 + len(descs):
        raise EnvelopeError(
            f"frame count mismatch on {topic!r}: {len(frames)} frames, "
            f"meta declares {len(descs)} arrays (expected {3 + len(descs)})"
        )
    arrays: dict[str, np.ndarray] = {}
    for (name, dtype_s, shape), buf in zip(descs, frames[3:], strict=True):
        dtype = np.dtype(dtype_s)
        if math.prod(max(d, 1) for d in shape) * dtype.itemsize > MAX_ARRAY_BYTES:
            # numpy refuses such shapes even when another dimension is 0
            raise EnvelopeError(
                f"array {_short(name)}: shape {shape} of {dtype_s} spans more than "
                f"{MAX_ARRAY_BYTES} bytes (even as a zero-size array)"
            )
        mv = memoryview(buf).cast("B")
        expected = math.prod(shape) * dtype.itemsize
        if mv.nbytes != expected:
            raise EnvelopeError(
                f"array {_short(name)}: buffer holds {mv.nbytes} bytes but shape {shape} "
                f"of {dtype_s} needs {expected}"
            )
        arrays[name] = np.frombuffer(mv, dtype=dtype).reshape(shape)
    env = Envelope(topic, header, payload, arrays)
    if table is not None:
        check_against_table(env, table)
    return env


def check_against_table(env: Envelope, table: Mapping[str, Topic]) -> None:
    """Check topic, type, schema version and payload of ``env`` against the topic table."""
    from groundstation.bus.errors import SchemaError

    topic = table.get(env.topic)
    if topic is None:
        raise SchemaError(f"unknown topic {env.topic!r}", hint="declare it in bus/topics.py")
    if env.header.type != topic.type or env.header.schema != topic.schema_version:
        raise SchemaError(
            f"unknown type/schema {env.header.type!r} v{env.header.schema} for topic "
            f"{env.topic!r} (expected {topic.type!r} v{topic.schema_version})"
        )
    topic.validate(env.payload, env.arrays)


def pack_frames(frames: Sequence[Buffer]) -> bytes:
    """Join frames into one length-prefixed blob (see the module docstring)."""
    parts = [_BLOB_COUNT.pack(len(frames))]
    for f in frames:
        mv = memoryview(f)
        parts += [_BLOB_LEN.pack(mv.nbytes), mv]
    return b"".join(parts)


def unpack_frames(blob: Buffer) -> list[memoryview]:
    """Split a blob made by :func:`pack_frames` into frames (zero-copy views)."""
    mv = memoryview(blob).cast("B")
    if mv.nbytes < _BLOB_COUNT.size:
        raise EnvelopeError(f"blob too short ({mv.nbytes} bytes) for a frame count")
    (n,) = _BLOB_COUNT.unpack_from(mv)
    if n > _MAX_FRAMES:
        raise EnvelopeError(f"blob declares {n} frames (> {_MAX_FRAMES}): corrupt blob")
    pos, frames = _BLOB_COUNT.size, []
    for i in range(n):
        if pos + _BLOB_LEN.size > mv.nbytes:
            raise EnvelopeError(f"blob truncated in the length of frame {i} of {n}")
        (length,) = _BLOB_LEN.unpack_from(mv, pos)
        pos += _BLOB_LEN.size
        if pos + length > mv.nbytes:
            raise EnvelopeError(
                f"blob truncated in frame {i} of {n}: needs {length} bytes, has {mv.nbytes - pos}"
            )
        frames.append(mv[pos : pos + length])
        pos += length
    if pos != mv.nbytes:
        raise EnvelopeError(f"blob has {mv.nbytes - pos} trailing bytes after {n} frames")
    return frames


def to_bytes(env: Envelope) -> bytes:
    """Serialize an envelope into one blob (for MCAP recording)."""
    return pack_frames(encode(env))


def from_bytes(blob: Buffer, table: Mapping[str, Topic] | None = None) -> Envelope:
    """Parse a blob made by :func:`to_bytes` (or :func:`pack_frames` of received frames)."""
    return decode(unpack_frames(blob), table)
