"""Write a recording in the layout of :mod:`groundstation.acquisition.layout`.

:class:`Recorder` wraps ``mcap.writer.Writer`` with the three things a flight recorder needs:

- **Bounded loss on a crash.** Chunks are closed when they reach ``chunk_bytes`` (uncompressed)
  or span ``max_chunk_span_ns`` of log time, whichever comes first, and every chunk goes straight
  to the operating system (no user-space buffer), so a SIGKILL loses at most the open chunk:
  about one second of data by default. :func:`groundstation.acquisition.reader.open_recording`
  reads such a file up to its last complete chunk.
- **Reported, not crashed.** An unwritable path, a full disk or any other OS error raises
  :class:`RecordingError` naming the path and the OS error; after that the recorder refuses
  further writes and ``close()`` only releases the file. The process shell puts the error on the
  bus.
- **Never erases.** A recorder creates its file and refuses an existing one
  (:class:`RecordingExistsError`); ``replace=True`` (a command's ``--force``) removes it first.
  A restarted or standby recorder writes a new segment beside the first
  (:mod:`~groundstation.acquisition.segments`) instead of truncating anything.
- **Determinism.** No clock is read here: identical calls give byte-identical files.
"""

from __future__ import annotations

import os
import stat
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from groundstation.acquisition import layout
from groundstation.errors import GroundstationError

# Uncompressed bytes per chunk. A live session writes ~25 kB/s of MAVLink, ~20-60 kB/s of NatNet
# and a few 10 kB/s of decoded envelopes, so 256 KiB is about one second or less.
DEFAULT_CHUNK_BYTES = 256 * 1024
# A chunk also closes when it spans this much log time, so a quiet session loses <= 1 s too.
DEFAULT_MAX_CHUNK_SPAN_NS = 1_000_000_000


class RecordingError(GroundstationError, OSError):
    """Writing or reading a recording failed; the message names the path and the cause."""


class RecordingExistsError(RecordingError, FileExistsError):
    """The output recording exists; a recorder never overwrites one (``--force`` removes it)."""


class _Passthrough:
    """Minimal file-like object (write/tell/flush/close) over an unbuffered file descriptor.

    Creates the file exclusively: an existing regular file raises ``FileExistsError`` (never
    truncated); an existing device or FIFO (``/dev/full``, a pipe) is opened for writing.
    """

    def __init__(self, path: Path):
        self.path = path
        try:
            self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            if stat.S_ISREG(os.stat(path).st_mode):
                raise
            self._fd = os.open(path, os.O_WRONLY)
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data)
        total = len(view)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        self._pos += total
        return total

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:  # nothing is buffered in user space
        return None

    def fsync(self) -> None:
        os.fsync(self._fd)

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)


@dataclass
class RecorderStats:
    """What a recorder has written so far.

    Attributes
    ----------
    messages : int
        Messages handed to :meth:`Recorder.write`.
    durable_messages : int
        Messages inside chunks already handed to the OS (they survive a SIGKILL).
    bytes_written : int
        Bytes of file handed to the OS.
    chunks : int
        Chunks closed.
    per_topic : Counter
        Messages per topic.
    start_ns, end_ns : int or None
        Smallest and largest log time written, ns.
    """

    messages: int = 0
    durable_messages: int = 0
    bytes_written: int = 0
    chunks: int = 0
    per_topic: Counter = field(default_factory=Counter)
    start_ns: int | None = None
    end_ns: int | None = None


class Recorder:
    """Write messages, metadata and ground truth to an MCAP recording.

    Parameters
    ----------
    path : str or Path
        Output file, created; an existing file is refused (never truncated). Its directory
        must exist.
    metadata : mapping of str to str, optional
        The ``groundstation`` metadata record (see :func:`layout.station_metadata`); written at
        once, so even a file cut short after one chunk says what wrote it.
    chunk_bytes : int
        Maximum uncompressed chunk size, bytes.
    max_chunk_span_ns : int
        Maximum log-time span of one chunk, ns.
    compression : {"zstd", "none"}
        Chunk compression.
    replace : bool
        Remove an existing file at ``path`` first (what ``--force`` asks for).

    Raises
    ------
    RecordingExistsError
        If ``path`` exists and ``replace`` is False.
    RecordingError
        If the file cannot be created or written (the message names path and OS error).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        metadata: Mapping[str, str] | None = None,
        chunk_bytes: int = DEFAULT_CHUNK_BYTES,
        max_chunk_span_ns: int = DEFAULT_MAX_CHUNK_SPAN_NS,
        compression: str = "zstd",
        replace: bool = False,
    ):
        if chunk_bytes <= 0 or max_chunk_span_ns <= 0:
            raise layout.LayoutError(
                f"chunk_bytes={chunk_bytes} and max_chunk_span_ns={max_chunk_span_ns} "
                "must be positive"
            )
        comp = {"zstd": CompressionType.ZSTD, "none": CompressionType.NONE}.get(compression)
        if comp is None:
            raise layout.LayoutError(f"compression {compression!r} is not 'zstd' or 'none'")
        self.path = Path(path)
        self.stats = RecorderStats()
        self._channels: dict[layout.ChannelSpec, int] = {}
        self._typed: dict[tuple[str, str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: Counter = Counter()
        self._max_span = int(max_chunk_span_ns)
        self._chunk_start_ns: int | None = None
        self._open_in_chunk = 0
        self._failed: RecordingError | None = None
        self._closed = False
        self._stream: _Passthrough | None = None
        try:
            if replace and self.path.is_file():
                self.path.unlink()
            self._stream = _Passthrough(self.path)
            self._writer = Writer(
                self._stream,  # type: ignore[arg-type]
                chunk_size=int(chunk_bytes),
                compression=comp,
            )
            self._writer.start(profile=layout.PROFILE, library=self._library())
            if metadata is not None:
                self._writer.add_metadata(layout.METADATA_NAME, dict(metadata))
        except FileExistsError:
            err = RecordingExistsError(
                f"recording {str(self.path)!r} already exists; not overwriting it",
                hint="choose another file, or pass --force to replace it",
            )
            err.errno, err.filename = 17, str(self.path)
            self._failed = err
            raise err from None
        except OSError as exc:
            self._fail(exc, "create")
        self._sync_stats()

    @staticmethod
    def _library() -> str:
        from mcap import __version__ as mcap_version

        return f"groundstation-recorder layout/{layout.LAYOUT_VERSION}; mcap-python {mcap_version}"

    # -- errors ----------------------------------------------------------------------------
    def _fail(self, exc: OSError, action: str) -> None:
        err = RecordingError(
            f"cannot {action} recording {str(self.path)!r}: {exc.strerror or exc} "
            f"(errno {exc.errno})",
            hint="check that the directory exists, is writable and has free space",
        )
        err.errno = exc.errno
        err.filename = str(self.path)
        self._failed = err
        if self._stream is not None:
            try:
                self._stream.close()
            except OSError:
                pass
        raise err from exc

    def _check_usable(self) -> None:
        if self._failed is not None:
            raise RecordingError(
                f"recording {str(self.path)!r} failed earlier: {self._failed.message}"
            )
        if self._closed:
            raise RecordingError(f"recording {str(self.path)!r} is closed")

    def _sync_stats(self) -> None:
        if self._stream is not None:
            self.stats.bytes_written = self._stream.tell()

    # -- writing ---------------------------------------------------------------------------
    def _channel_id(self, spec: layout.ChannelSpec) -> int:
        cid = self._channels.get(spec)
        if cid is None:
            cid = self._writer.register_channel(
                spec.topic, spec.message_encoding, 0, spec.metadata_dict()
            )
            self._channels[spec] = cid
        return cid

    def write(
        self,
        data: Any,
        topic: str,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        *,
        source: str | None = None,
        channel_metadata: Mapping[str, str] | None = None,
    ) -> None:
        """Append one message.

        Parameters
        ----------
        data : bytes or Envelope
            Wire bytes for raw topics, the envelope blob (or an envelope, serialised here with
            ``groundstation.bus.envelope.to_bytes``) for the others.
        topic : str
            Bus topic; one channel per (topic, source, channel_metadata).
        log_time_ns : int
            Station receive time, ns.
        publish_time_ns : int, optional
            Source time, ns; defaults to ``log_time_ns``.
        source : str, optional
            Source URI stored in the channel metadata.
        channel_metadata : mapping, optional
            Extra channel metadata (e.g. ``{"natnet_version": "4.1"}``).

        Raises
        ------
        RecordingError
            On an OS error (disk full, I/O error) or after an earlier failure.
        LayoutError
            On a bad topic, a non-integer time or data of the wrong type.
        """
        self._check_usable()
        blob, source, publish_time_ns = self._unwrap(data, topic, source, publish_time_ns)
        spec = layout.channel_spec(topic, source=source, extra=channel_metadata)
        log_time = _as_ns(log_time_ns, "log_time_ns")
        pub_time = log_time if publish_time_ns is None else _as_ns(publish_time_ns, "publish")
        try:
            cid = self._channel_id(spec)
            before = self._stream.tell()
            self._writer.add_message(
                channel_id=cid,
                log_time=log_time,
                data=blob,
                publish_time=pub_time,
                sequence=self._sequence[cid] & 0xFFFFFFFF,
            )
            self._sequence[cid] += 1
            self._account(topic, log_time)
            if self._stream.tell() != before:  # the writer just closed a chunk
                self._chunk_closed()
            elif self._chunk_start_ns is not None and (
                log_time - self._chunk_start_ns >= self._max_span
            ):
                self._writer.flush()
                self._chunk_closed()
        except OSError as exc:
            self._fail(exc, "write")
        self._sync_stats()

    @staticmethod
    def _unwrap(
        data: Any, topic: str, source: str | None, publish_time_ns: int | None
    ) -> tuple[bytes, str | None, int | None]:
        """Bytes to store, the source and the publish time for ``data`` on ``topic``."""
        if isinstance(data, bytes | bytearray | memoryview):
            return bytes(data), source, publish_time_ns
        header = getattr(data, "header", None)
        if header is None or not hasattr(data, "arrays"):
            raise layout.LayoutError(
                f"cannot record a {type(data).__name__} on {topic!r}",
                hint="pass bytes or a groundstation.bus.envelope.Envelope",
            )
        if publish_time_ns is None:
            publish_time_ns = header.source_ns
        if layout.is_raw_topic(topic):
            # Raw topics store the wire bytes only (layout.py): unwrap the envelope's data array.
            raw = data.arrays.get(layout.RAW_DATA_ARRAY)
            if raw is None:
                raise layout.LayoutError(
                    f"envelope on raw topic {topic!r} has no {layout.RAW_DATA_ARRAY!r} array"
                )
            if source is None:
                field_name = layout.RAW_SOURCE_FIELDS.get(topic, "")
                value = data.payload.get(field_name)
                source = None if value is None else str(value)
            return np.asarray(raw).tobytes(), source, publish_time_ns
        from groundstation.bus.envelope import to_bytes  # lazy: keep the writer core light

        return to_bytes(data), source, publish_time_ns

    def _account(self, topic: str, log_time: int) -> None:
        st = self.stats
        st.messages += 1
        st.per_topic[topic] += 1
        st.start_ns = log_time if st.start_ns is None else min(st.start_ns, log_time)
        st.end_ns = log_time if st.end_ns is None else max(st.end_ns, log_time)
        self._open_in_chunk += 1
        if self._chunk_start_ns is None:
            self._chunk_start_ns = log_time

    def _chunk_closed(self) -> None:
        self.stats.chunks += 1
        self.stats.durable_messages += self._open_in_chunk
        self._open_in_chunk = 0
        self._chunk_start_ns = None

    def write_typed(
        self,
        data: bytes,
        topic: str,
        log_time_ns: int,
        publish_time_ns: int | None = None,
        *,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
    ) -> None:
        """Append one message on a channel with an MCAP schema (e.g. a Foxglove protobuf
        channel, ``groundstation.openformats.channels``): one schema per name, one channel per
        topic; same durability, statistics and errors as :meth:`write`."""
        self._check_usable()
        topic = layout.validate_topic(topic)
        log_time = _as_ns(log_time_ns, "log_time_ns")
        pub_time = log_time if publish_time_ns is None else _as_ns(publish_time_ns, "publish")
        try:
            key = (topic, message_encoding, schema_name)
            cid = self._typed.get(key)
            if cid is None:
                sid = self._schemas.get(schema_name)
                if sid is None:
                    sid = self._writer.register_schema(schema_name, schema_encoding, schema_data)
                    self._schemas[schema_name] = sid
                meta = {layout.KEY_LAYOUT: layout.LAYOUT_VERSION}
                cid = self._writer.register_channel(topic, message_encoding, sid, meta)
                self._typed[key] = cid
            before = self._stream.tell()
            self._writer.add_message(
                channel_id=cid,
                log_time=log_time,
                data=bytes(data),
                publish_time=pub_time,
                sequence=self._sequence[cid] & 0xFFFFFFFF,
            )
            self._sequence[cid] += 1
            self._account(topic, log_time)
            if self._stream.tell() != before:
                self._chunk_closed()
            elif self._chunk_start_ns is not None and (
                log_time - self._chunk_start_ns >= self._max_span
            ):
                self._writer.flush()
                self._chunk_closed()
        except OSError as exc:
            self._fail(exc, "write")
        self._sync_stats()

    def add_truth(self, truth: Mapping[str, Any], log_time_ns: int = 0) -> None:
        """Attach ground truth as ``truth.json`` (see :func:`layout.encode_truth`)."""
        self._check_usable()
        data = layout.encode_truth(truth)
        try:
            self._writer.add_attachment(
                create_time=0,
                log_time=_as_ns(log_time_ns, "log_time_ns"),
                name=layout.TRUTH_ATTACHMENT,
                media_type=layout.TRUTH_MEDIA_TYPE,
                data=data,
            )
        except OSError as exc:
            self._fail(exc, "write")
        self._sync_stats()

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """Add a metadata record (all values strings)."""
        self._check_usable()
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
            raise layout.LayoutError(f"metadata {name!r} must map str to str")
        try:
            self._writer.add_metadata(name, dict(data))
        except OSError as exc:
            self._fail(exc, "write")
        self._sync_stats()

    def flush(self) -> None:
        """Close the open chunk and hand it to the OS (call on a timer when data is sparse)."""
        self._check_usable()
        try:
            if self._open_in_chunk:
                self._writer.flush()
                self._chunk_closed()
        except OSError as exc:
            self._fail(exc, "write")
        self._sync_stats()

    def close(self, *, fsync: bool = False) -> RecorderStats:
        """Write the summary and footer and close the file. Safe to call twice.

        After a failure this only releases the file descriptor (the file then reads as a
        truncated recording) and returns the stats.
        """
        if self._closed:
            return self.stats
        self._closed = True
        if self._failed is not None:
            return self.stats
        try:
            if self._open_in_chunk:
                self._chunk_closed()
            self._writer.finish()
            if fsync:
                self._stream.fsync()
        except OSError as exc:
            self._fail(exc, "finish")
        finally:
            self._sync_stats()
            self._stream.close()
        return self.stats

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _as_ns(value: Any, name: str) -> int:
    try:
        ns = int(value)
    except (TypeError, ValueError):
        raise layout.LayoutError(f"{name}={value!r} is not an integer number of ns") from None
    if ns != value or ns < 0 or ns >= 2**64:
        raise layout.LayoutError(f"{name}={value!r} must be an integer in [0, 2**64) ns")
    return ns
