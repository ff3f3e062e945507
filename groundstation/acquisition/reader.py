"""Read a recording: messages in log-time order, seeking, topics, ground truth, metadata.

A complete file is read through its index (``mcap.reader.SeekingReader``): a time window costs
only the chunks that overlap it. A file without a footer (the recorder was killed, the disk
filled, the machine lost power) is *recovered*: its records are scanned from the start up to the
last complete one, every complete chunk with a valid CRC is kept, and a :class:`RecoveryReport`
says what was lost (bytes, records, and the log-time span of a cut chunk when its header
survived). A warning (:class:`TruncatedRecordingWarning`) is issued once per opened file.
"""

from __future__ import annotations

import heapq
import io
import os
import struct
import warnings
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Chunk, Message, Metadata
from mcap.stream_reader import MAGIC_SIZE, breakup_chunk

from groundstation.acquisition import layout
from groundstation.acquisition.recorder import RecordingError

_MAGIC = b"\x89MCAP0\r\n"
_RECORD_PREFIX = struct.Struct("<BQ")  # opcode u8, length u64 (MCAP spec "Records")
_FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc


class TruncatedRecordingWarning(UserWarning):
    """A recording had no footer and was read only up to its last complete chunk."""


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a recording."""

    id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass(frozen=True)
class RecordedMessage:
    """One recorded message.

    Attributes
    ----------
    topic : str
        Bus topic.
    log_time_ns : int
        Station receive time, ns.
    publish_time_ns : int
        Source time, ns.
    data : bytes
        Wire bytes (raw channels) or envelope blob.
    sequence : int
        Per-channel counter written by the recorder.
    channel : ChannelInfo
        The channel (encoding, source).
    """

    topic: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes
    sequence: int
    channel: ChannelInfo


@dataclass(frozen=True)
class RecoveryReport:
    """What reading a truncated recording kept and lost.

    Attributes
    ----------
    complete_chunks : int
        Chunks read intact.
    recovered_messages : int
        Messages in them.
    corrupt_chunks : int
        Complete chunks whose CRC or compression failed (skipped).
    lost_bytes : int
        Trailing bytes that did not form a complete record.
    lost_records : int
        Incomplete trailing records (0 or 1).
    lost_time_range_ns : (int, int) or None
        Log-time span of the cut chunk when its header survived.
    reason : str
        Why the file counts as truncated.
    """

    complete_chunks: int
    recovered_messages: int
    corrupt_chunks: int
    lost_bytes: int
    lost_records: int
    lost_time_range_ns: tuple[int, int] | None
    reason: str

    def describe(self) -> str:
        span = ""
        if self.lost_time_range_ns is not None:
            a, b = self.lost_time_range_ns
            span = f", cut chunk spanned log time {a / 1e9:.3f}-{b / 1e9:.3f} s"
        return (
            f"{self.reason}: recovered {self.recovered_messages} messages in "
            f"{self.complete_chunks} complete chunks; lost {self.lost_bytes} trailing bytes "
            f"({self.lost_records} incomplete record(s)), {self.corrupt_chunks} corrupt chunk(s)"
            f"{span}"
        )


@dataclass(frozen=True)
class RecordingSummary:
    """Topics, counts and time span of a recording (times in ns of log time)."""

    message_count: int
    topic_counts: dict[str, int]
    start_ns: int | None
    end_ns: int | None
    channels: tuple[ChannelInfo, ...] = field(default=())

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9


@dataclass
class _ChunkRef:
    offset: int  # file offset of the chunk record's body
    length: int
    start_ns: int
    end_ns: int


class Recording:
    """An open recording; use :func:`open_recording`.

    Attributes
    ----------
    path : Path
    truncated : bool
        True when the file had no valid footer and was recovered by scanning.
    recovery : RecoveryReport or None
        Set when ``truncated``.
    summary : RecordingSummary
    """

    def __init__(self, path: str | os.PathLike[str]):
        self.path = Path(path)
        try:
            self._file = open(self.path, "rb")
        except OSError as exc:
            raise RecordingError(
                f"cannot open recording {str(self.path)!r}: {exc.strerror or exc}"
            ) from exc
        self.truncated = False
        self.recovery: RecoveryReport | None = None
        self._channels: dict[int, ChannelInfo] = {}
        self._metadata: list[Metadata] = []
        self._attachments: list[Attachment] = []
        self._chunks: list[_ChunkRef] = []
        self._seeking: SeekingReader | None = None
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    # -- opening ---------------------------------------------------------------------------
    def _open(self) -> None:
        head = self._file.read(MAGIC_SIZE)
        if head != _MAGIC:
            raise RecordingError(
                f"{str(self.path)!r} is not an MCAP recording (starts with {head[:8]!r})"
            )
        reason = self._footer_problem()
        if reason is None:
            self._file.seek(0)
            reader = SeekingReader(self._file)
            try:
                summary = reader.get_summary()
            except (McapError, EOFError, struct.error, ValueError) as exc:
                summary, reason = None, f"unreadable summary ({exc})"
            if summary is not None and summary.statistics is not None:
                self._seeking = reader
                self._channels = {cid: _info(ch) for cid, ch in summary.channels.items()}
                self._metadata = list(reader.iter_metadata())
                self._attachments = list(reader.iter_attachments())
                stats = summary.statistics
                counts: Counter = Counter()
                for cid, n in stats.channel_message_counts.items():
                    counts[self._channels[cid].topic] += n
                self.summary = RecordingSummary(
                    message_count=stats.message_count,
                    topic_counts=dict(counts),
                    start_ns=stats.message_start_time if stats.message_count else None,
                    end_ns=stats.message_end_time if stats.message_count else None,
                    channels=tuple(self._channels.values()),
                )
                self._check_versions()
                return
            reason = reason or "no summary section"
        self._scan(reason)
        self._check_versions()

    def _footer_problem(self) -> str | None:
        size = self._file.seek(0, io.SEEK_END)
        if size < MAGIC_SIZE * 2 + _FOOTER_LEN:
            return f"file too short for a footer ({size} bytes)"
        self._file.seek(size - MAGIC_SIZE)
        if self._file.read(MAGIC_SIZE) != _MAGIC:
            return "no closing magic (the writer did not finish)"
        self._file.seek(size - MAGIC_SIZE - _FOOTER_LEN)
        if self._file.read(1) != bytes([Opcode.FOOTER]):
            return "no footer record before the closing magic"
        return None

    def _check_versions(self) -> None:
        where = str(self.path)
        meta = self.metadata()
        if meta is not None:
            layout.check_layout_version(meta.get(layout.KEY_LAYOUT), where)
        for ch in self._channels.values():
            layout.check_layout_version(ch.metadata.get(layout.KEY_LAYOUT), where)

    def _scan(self, reason: str) -> None:
        """Read records sequentially up to the last complete one (MCAP spec, "Records")."""
        self.truncated = True
        f = self._file
        size = f.seek(0, io.SEEK_END)
        pos = MAGIC_SIZE
        f.seek(pos)
        counts: Counter = Counter()
        complete = corrupt = lost_records = 0
        lost_span: tuple[int, int] | None = None
        start_ns = end_ns = None
        recovered = 0
        while True:
            prefix = f.read(_RECORD_PREFIX.size)
            if len(prefix) < _RECORD_PREFIX.size:
                if prefix:
                    lost_records = 1
                break
            opcode, length = _RECORD_PREFIX.unpack(prefix)
            body_at = pos + _RECORD_PREFIX.size
            if body_at + length > size:
                lost_records = 1
                if opcode == Opcode.CHUNK:
                    times = f.read(16)
                    if len(times) == 16:
                        lost_span = struct.unpack("<QQ", times)
                break
            if opcode == Opcode.FOOTER:
                pos = size  # a footer without a summary: nothing lost
                break
            body = f.read(length)
            stream = ReadDataStream(io.BytesIO(body))
            if opcode == Opcode.CHUNK:
                try:
                    records = breakup_chunk(Chunk.read(stream), validate_crc=True)
                except Exception:  # noqa: BLE001 - any corruption: count it and go on
                    corrupt += 1
                else:
                    complete += 1
                    cstart = cend = None
                    for rec in records:
                        if isinstance(rec, Channel):
                            self._channels[rec.id] = _info(rec)
                        elif isinstance(rec, Message) and rec.channel_id in self._channels:
                            counts[self._channels[rec.channel_id].topic] += 1
                            recovered += 1
                            t = rec.log_time
                            cstart = t if cstart is None else min(cstart, t)
                            cend = t if cend is None else max(cend, t)
                    if cstart is not None:
                        self._chunks.append(_ChunkRef(body_at, length, cstart, cend))
                        start_ns = cstart if start_ns is None else min(start_ns, cstart)
                        end_ns = cend if end_ns is None else max(end_ns, cend)
            elif opcode == Opcode.CHANNEL:
                ch = Channel.read(stream)
                self._channels[ch.id] = _info(ch)
            elif opcode == Opcode.METADATA:
                self._metadata.append(Metadata.read(stream))
            elif opcode == Opcode.ATTACHMENT:
                self._attachments.append(Attachment.read(stream))
            pos = body_at + length
        self.summary = RecordingSummary(
            message_count=recovered,
            topic_counts=dict(counts),
            start_ns=start_ns,
            end_ns=end_ns,
            channels=tuple(self._channels.values()),
        )
        self.recovery = RecoveryReport(
            complete_chunks=complete,
            recovered_messages=recovered,
            corrupt_chunks=corrupt,
            lost_bytes=max(0, size - pos),
            lost_records=lost_records,
            lost_time_range_ns=lost_span,
            reason=reason,
        )
        warnings.warn(
            f"recording {str(self.path)!r} is truncated; {self.recovery.describe()}",
            TruncatedRecordingWarning,
            stacklevel=5,
        )

    # -- reading ---------------------------------------------------------------------------
    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """Messages in log-time order (ties keep file order).

        Parameters
        ----------
        topics : str or iterable of str, optional
            Only these topics.
        start_ns : int, optional
            First log time included, ns (inclusive).
        end_ns : int, optional
            Log time excluded from here on, ns (exclusive).
        """
        if isinstance(topics, str):
            topics = [topics]
        wanted = None if topics is None else set(topics)
        if start_ns is not None and end_ns is not None and end_ns < start_ns:
            raise layout.LayoutError(f"end_ns={end_ns} comes before start_ns={start_ns}")
        if self._seeking is not None:
            for _, channel, msg in self._seeking.iter_messages(
                topics=None if wanted is None else sorted(wanted),
                starting_at=start_ns,
                ending_before=end_ns,
                log_time_order=True,
            ):
                yield self._message(self._channels[channel.id], msg)
            return
        yield from self._scan_messages(wanted, start_ns, end_ns)

    def _scan_messages(
        self, wanted: set[str] | None, start_ns: int | None, end_ns: int | None
    ) -> Iterator[RecordedMessage]:
        # k-way merge over chunks sorted by start time: a queued message is safe to emit once
        # no chunk still unread can start before it (same rule as mcap's message queue).
        refs = sorted(
            (
                r
                for r in self._chunks
                if (start_ns is None or r.end_ns >= start_ns)
                and (end_ns is None or r.start_ns < end_ns)
            ),
            key=lambda r: (r.start_ns, r.offset),
        )
        heap: list[tuple[int, int, int, Message]] = []
        for ref in refs:
            while heap and heap[0][0] < ref.start_ns:
                yield self._message_from_heap(heapq.heappop(heap))
            self._file.seek(ref.offset)
            chunk = Chunk.read(ReadDataStream(io.BytesIO(self._file.read(ref.length))))
            for i, rec in enumerate(breakup_chunk(chunk)):
                if not isinstance(rec, Message):
                    continue
                ch = self._channels.get(rec.channel_id)
                if ch is None or (wanted is not None and ch.topic not in wanted):
                    continue
                if start_ns is not None and rec.log_time < start_ns:
                    continue
                if end_ns is not None and rec.log_time >= end_ns:
                    continue
                heapq.heappush(heap, (rec.log_time, ref.offset, i, rec))
        while heap:
            yield self._message_from_heap(heapq.heappop(heap))

    def _message_from_heap(self, item: tuple[int, int, int, Message]) -> RecordedMessage:
        msg = item[3]
        return self._message(self._channels[msg.channel_id], msg)

    @staticmethod
    def _message(ch: ChannelInfo, msg: Message) -> RecordedMessage:
        return RecordedMessage(
            topic=ch.topic,
            log_time_ns=msg.log_time,
            publish_time_ns=msg.publish_time,
            data=bytes(msg.data),
            sequence=msg.sequence,
            channel=ch,
        )

    def topics(self) -> dict[str, int]:
        """Message count per topic."""
        return dict(self.summary.topic_counts)

    def metadata(self, name: str = layout.METADATA_NAME) -> dict[str, str] | None:
        """The first metadata record called ``name`` (default: the station record), or None."""
        for rec in self._metadata:
            if rec.name == name:
                return dict(rec.metadata)
        return None

    def attachment(self, name: str) -> bytes | None:
        """The data of the first attachment called ``name``, or None."""
        for rec in self._attachments:
            if rec.name == name:
                return bytes(rec.data)
        return None

    def truth(self) -> dict[str, Any] | None:
        """The ``truth.json`` attachment, parsed, or None."""
        data = self.attachment(layout.TRUTH_ATTACHMENT)
        return None if data is None else layout.decode_truth(data)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> Recording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _info(ch: Channel) -> ChannelInfo:
    return ChannelInfo(ch.id, ch.topic, ch.message_encoding, dict(ch.metadata))


def open_recording(path: str | os.PathLike[str]) -> Recording:
    """Open a recording for reading (recovering it when truncated).

    Raises
    ------
    RecordingError
        If the file cannot be opened or is not MCAP.
    LayoutError
        If it was written with an unknown layout version.
    """
    return Recording(path)
