"""Read a recording: messages in log-time order, seeking, topics, ground truth, metadata.

A complete file is read through its summary (chunk indexes): a time window costs only the chunks
that overlap it. A file without a footer (the recorder was killed, the disk filled, the machine
lost power) is *recovered*: its records are scanned from the start up to the last complete one,
every complete chunk with a valid CRC is kept, and a :class:`RecoveryReport` says what was lost
(bytes, records, and the log-time span of a cut chunk when its header survived). A warning
(:class:`TruncatedRecordingWarning`) is issued once per opened file.

Damage is never silent and never a library exception. Every chunk is decoded here with bounded
sizes (:mod:`groundstation.acquisition.chunks`: at most 256 MiB, zstd/lz4 output capped at the
declared size) and its CRC checked; a chunk that fails is skipped and added to
:attr:`Recording.damage` (:class:`DamageReport`: which chunks, their log-time spans and, from the
message indexes, how many messages of which topics were lost). Before, mcap/zstd exceptions of 5
kinds escaped, and two flipped bytes in a chunk made ``replay`` drop 478 of 11,386 messages
silently. Opening raises only :class:`RecordingError` (or ``LayoutError`` for a newer layout).
"""

from __future__ import annotations

import bisect
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
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Attachment, Channel, Metadata

from groundstation.acquisition import layout
from groundstation.acquisition.chunks import (
    ChunkDamage,
    ChunkMessage,
    decode_chunk,
    message_index_count,
)
from groundstation.acquisition.recorder import RecordingError

_MAGIC = b"\x89MCAP0\r\n"
MAGIC_SIZE = len(_MAGIC)
_RECORD_PREFIX = struct.Struct("<BQ")  # opcode u8, length u64 (MCAP spec "Records")
_FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, length, summary_start, summary_offset_start, crc
_MAX_PROBLEMS = 20


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
class DamageReport:
    """What could not be read from a recording (accumulates while it is read).

    Attributes
    ----------
    corrupt_chunks : int
        Chunks skipped: bad CRC, undecodable compression, impossible sizes or records.
    lost_messages : int
        Messages in those chunks, counted from the message indexes (0 when no index survived).
    lost_by_topic : Counter
        ``lost_messages`` per topic.
    lost_spans_ns : list of (int, int)
        Log-time span of each corrupt chunk, ns.
    problems : list of str
        What went wrong, first :data:`_MAX_PROBLEMS` problems (chunks, metadata, attachments).
    unreadable_records : int
        Metadata/attachment/channel records that could not be decoded (skipped).
    """

    corrupt_chunks: int = 0
    lost_messages: int = 0
    lost_by_topic: Counter = field(default_factory=Counter)
    lost_spans_ns: list[tuple[int, int]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    unreadable_records: int = 0

    def __bool__(self) -> bool:
        return bool(self.corrupt_chunks or self.unreadable_records)

    def note(self, problem: str) -> None:
        if len(self.problems) < _MAX_PROBLEMS:
            self.problems.append(problem)

    def describe(self) -> str:
        if not self:
            return "no damage"
        topics = ", ".join(f"{k} {v}" for k, v in sorted(self.lost_by_topic.items()))
        spans = ", ".join(f"{a / 1e9:.3f}-{b / 1e9:.3f} s" for a, b in self.lost_spans_ns[:5])
        more = "" if len(self.lost_spans_ns) <= 5 else f" (+{len(self.lost_spans_ns) - 5} more)"
        text = (
            f"{self.corrupt_chunks} corrupt chunk(s) skipped, {self.lost_messages} message(s) "
            f"lost"
            + (f" ({topics})" if topics else "")
            + (f", log time {spans}{more}" if spans else "")
        )
        if self.unreadable_records:
            text += f"; {self.unreadable_records} unreadable metadata/attachment record(s)"
        return text + (f"; first problem: {self.problems[0]}" if self.problems else "")


@dataclass
class _ChunkRef:
    offset: int  # file offset of the chunk record's body
    length: int
    start_ns: int
    end_ns: int
    #: channel id -> file offset of its MessageIndex record for this chunk (when known)
    index_offsets: dict[int, int] = field(default_factory=dict)
    #: channel id -> message count, when counted while scanning
    index_counts: dict[int, int] | None = None


class Recording:
    """An open recording; use :func:`open_recording`.

    Parameters
    ----------
    path : str, Path or bytes-like
        The file, or its bytes (read in memory, e.g. by ``groundstation bench fuzz``).

    Attributes
    ----------
    path : Path
    truncated : bool
        True when the file had no valid footer and was recovered by scanning.
    recovery : RecoveryReport or None
        Set when ``truncated``.
    damage : DamageReport
        Chunks and records skipped so far (grows as chunks are read; :meth:`verify` reads all).
    summary : RecordingSummary
    """

    def __init__(self, path: str | os.PathLike[str] | bytes | bytearray | memoryview):
        self._file: Any
        if isinstance(path, bytes | bytearray | memoryview):
            self.path = Path("<memory>")
            self._file = io.BytesIO(bytes(path))
        else:
            self.path = Path(path)
            try:
                self._file = open(self.path, "rb")  # noqa: SIM115 - closed by close()
            except OSError as exc:
                raise RecordingError(
                    f"cannot open recording {str(self.path)!r}: {exc.strerror or exc}"
                ) from exc
        self.truncated = False
        self.recovery: RecoveryReport | None = None
        self.damage = DamageReport()
        self._size = self._file.seek(0, io.SEEK_END)
        self._channels: dict[int, ChannelInfo] = {}
        self._metadata: list[Metadata] = []
        self._attachments: list[Attachment] = []
        self._chunks: list[_ChunkRef] = []
        self._damaged_chunks: set[int] = set()
        try:
            self._open()
        except BaseException:
            self._file.close()
            raise

    # -- opening ---------------------------------------------------------------------------
    def _open(self) -> None:
        self._file.seek(0)
        head = self._file.read(MAGIC_SIZE)
        if head != _MAGIC:
            raise RecordingError(
                f"{str(self.path)!r} is not an MCAP recording (starts with {head[:8]!r})"
            )
        reason = self._footer_problem()
        if reason is None:
            reason = self._open_summary()
            if reason is None:
                self._check_versions()
                return
        self._scan(reason)
        self._check_versions()

    def _open_summary(self) -> str | None:
        """Read channels, chunk indexes, statistics, metadata and attachments from the summary;
        the reason when the summary cannot be used (then the file is scanned)."""
        self._file.seek(0)
        try:
            summary = SeekingReader(self._file).get_summary()
        except Exception as exc:  # noqa: BLE001 - the mcap library raises assorted errors
            return f"unreadable summary ({type(exc).__name__}: {str(exc)[:100]})"
        if summary is None or summary.statistics is None:
            return "no summary section"
        stats = summary.statistics
        try:
            channels = {cid: _info(ch) for cid, ch in summary.channels.items()}
            chunks = [self._chunk_ref_from_index(ci) for ci in summary.chunk_indexes]
            counts: Counter = Counter()
            for cid, n in stats.channel_message_counts.items():
                counts[channels[cid].topic] += n
        except (ChunkDamage, KeyError) as exc:
            return f"inconsistent summary ({exc})"
        if stats.message_count and not chunks:
            return "summary without chunk indexes"
        self._channels, self._chunks = channels, chunks
        for index in summary.metadata_indexes:
            rec = self._read_indexed(index.offset, index.length, Opcode.METADATA, Metadata)
            if rec is not None:
                self._metadata.append(rec)
        for index in summary.attachment_indexes:
            rec = self._read_indexed(index.offset, index.length, Opcode.ATTACHMENT, Attachment)
            if rec is not None:
                self._attachments.append(rec)
        self.summary = RecordingSummary(
            message_count=stats.message_count,
            topic_counts=dict(counts),
            start_ns=stats.message_start_time if stats.message_count else None,
            end_ns=stats.message_end_time if stats.message_count else None,
            channels=tuple(self._channels.values()),
        )
        return None

    def _chunk_ref_from_index(self, ci: Any) -> _ChunkRef:
        start, length = int(ci.chunk_start_offset), int(ci.chunk_length)
        if start < MAGIC_SIZE or length < _RECORD_PREFIX.size or start + length > self._size:
            raise ChunkDamage(f"chunk index points outside the file ({start}+{length})")
        offsets = {int(c): int(o) for c, o in ci.message_index_offsets.items()}
        return _ChunkRef(
            start + _RECORD_PREFIX.size,
            length - _RECORD_PREFIX.size,
            int(ci.message_start_time),
            int(ci.message_end_time),
            offsets,
        )

    def _read_indexed(self, offset: int, length: int, opcode: int, cls: Any) -> Any:
        """One summary-indexed record (metadata, attachment), or None (counted as damage)."""
        what = cls.__name__.lower()
        try:
            if offset < MAGIC_SIZE or length < _RECORD_PREFIX.size or offset + length > self._size:
                raise ChunkDamage(f"index points outside the file ({offset}+{length})")
            self._file.seek(offset)
            op, body_len = _RECORD_PREFIX.unpack(self._file.read(_RECORD_PREFIX.size))
            if op != opcode or body_len != length - _RECORD_PREFIX.size:
                raise ChunkDamage(f"opcode {op:#x} / length {body_len} do not match the index")
            body = self._file.read(body_len)
            return cls.read(ReadDataStream(io.BytesIO(body)))
        except Exception as exc:  # noqa: BLE001 - a corrupt record is skipped and counted
            self.damage.unreadable_records += 1
            self.damage.note(f"{what} at {offset}: {type(exc).__name__}: {str(exc)[:100]}")
            return None

    def _footer_problem(self) -> str | None:
        size = self._size
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
        size = self._size
        pos = MAGIC_SIZE
        f.seek(pos)
        counts: Counter = Counter()
        complete = corrupt = lost_records = 0
        lost_span: tuple[int, int] | None = None
        start_ns = end_ns = None
        recovered = 0
        last_ref: _ChunkRef | None = None
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
            if opcode == Opcode.CHUNK:
                ref = _ChunkRef(body_at, length, 0, 0, index_counts={})
                last_ref = ref
                try:
                    records = decode_chunk(body)
                except ChunkDamage as exc:
                    corrupt += 1
                    self._chunk_damaged(ref, body, str(exc))
                else:
                    complete += 1
                    cstart = cend = None
                    for rec in records:
                        if isinstance(rec, Channel):
                            self._channels[rec.id] = _info(rec)
                        elif isinstance(rec, ChunkMessage) and rec.channel_id in self._channels:
                            counts[self._channels[rec.channel_id].topic] += 1
                            recovered += 1
                            t = rec.log_time
                            cstart = t if cstart is None else min(cstart, t)
                            cend = t if cend is None else max(cend, t)
                    if cstart is not None:
                        ref.start_ns, ref.end_ns = cstart, cend
                        self._chunks.append(ref)
                        start_ns = cstart if start_ns is None else min(start_ns, cstart)
                        end_ns = cend if end_ns is None else max(end_ns, cend)
            elif opcode == Opcode.MESSAGE_INDEX and last_ref is not None:
                counted = message_index_count(body)
                if counted is not None and last_ref.index_counts is not None:
                    cid, n = counted
                    last_ref.index_counts[cid] = n
                    if last_ref.offset in self._damaged_chunks:
                        self._count_lost({cid: n})
            elif opcode in (Opcode.CHANNEL, Opcode.METADATA, Opcode.ATTACHMENT):
                try:
                    stream = ReadDataStream(io.BytesIO(body))
                    if opcode == Opcode.CHANNEL:
                        ch = Channel.read(stream)
                        self._channels[ch.id] = _info(ch)
                    elif opcode == Opcode.METADATA:
                        self._metadata.append(Metadata.read(stream))
                    else:
                        self._attachments.append(Attachment.read(stream))
                except Exception as exc:  # noqa: BLE001 - a corrupt record is skipped, counted
                    self.damage.unreadable_records += 1
                    self.damage.note(f"record {opcode:#x} at {pos}: {type(exc).__name__}")
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

    # -- damage ----------------------------------------------------------------------------
    def _count_lost(self, counts: dict[int, int]) -> None:
        for cid, n in counts.items():
            ch = self._channels.get(cid)
            self.damage.lost_messages += n
            self.damage.lost_by_topic[ch.topic if ch else f"channel {cid}"] += n

    def _chunk_damaged(self, ref: _ChunkRef, body: bytes | None, why: str) -> None:
        """Record a corrupt chunk once: its span and, from the message indexes, its messages."""
        if ref.offset in self._damaged_chunks:
            return
        self._damaged_chunks.add(ref.offset)
        d = self.damage
        d.corrupt_chunks += 1
        span = (ref.start_ns, ref.end_ns)
        if body is not None and len(body) >= 16 and ref.start_ns == ref.end_ns == 0:
            span = struct.unpack_from("<QQ", body)
        d.lost_spans_ns.append((int(span[0]), int(span[1])))
        d.note(f"chunk at byte {ref.offset - _RECORD_PREFIX.size}: {why}")
        if ref.index_counts:
            self._count_lost(ref.index_counts)
        elif ref.index_offsets:
            counts = {}
            for cid, offset in ref.index_offsets.items():
                got = self._message_index_at(offset)
                if got is not None:
                    counts[cid] = got[1]
            self._count_lost(counts)

    def _message_index_at(self, offset: int) -> tuple[int, int] | None:
        if offset < MAGIC_SIZE or offset + _RECORD_PREFIX.size > self._size:
            return None
        self._file.seek(offset)
        op, length = _RECORD_PREFIX.unpack(self._file.read(_RECORD_PREFIX.size))
        if op != Opcode.MESSAGE_INDEX or offset + _RECORD_PREFIX.size + length > self._size:
            return None
        return message_index_count(self._file.read(length))

    def _load_chunk(self, ref: _ChunkRef) -> list[Any] | None:
        """The records of one chunk, or None after recording it as damaged."""
        self._file.seek(ref.offset - _RECORD_PREFIX.size)
        prefix = self._file.read(_RECORD_PREFIX.size)
        body = None
        try:
            if len(prefix) != _RECORD_PREFIX.size:
                raise ChunkDamage("chunk record cut short")
            op, length = _RECORD_PREFIX.unpack(prefix)
            if op != Opcode.CHUNK or length != ref.length:
                raise ChunkDamage(
                    f"record at the indexed offset is opcode {op:#x}, length {length}"
                )
            body = self._file.read(ref.length)
            return decode_chunk(body)
        except ChunkDamage as exc:
            self._chunk_damaged(ref, body, str(exc))
            return None

    def verify(self) -> DamageReport:
        """Decode every chunk once (CRC, decompression, records) and return :attr:`damage`."""
        for ref in self._chunks:
            self._load_chunk(ref)
        return self.damage

    @property
    def damaged(self) -> bool:
        """True if anything recorded is known to be lost (corrupt chunks or records, or a
        truncated file that lost bytes or chunks)."""
        rec = self.recovery
        lost = rec is not None and (rec.lost_bytes > 0 or rec.corrupt_chunks > 0)
        return bool(self.damage) or lost

    def damage_text(self) -> str:
        """One line: what was lost (truncation and corrupt chunks)."""
        parts = []
        if self.recovery is not None and (self.recovery.lost_bytes or self.recovery.corrupt_chunks):
            parts.append(self.recovery.describe())
        if self.damage:
            parts.append(self.damage.describe())
        return "; ".join(parts) or "no damage"

    # -- reading ---------------------------------------------------------------------------
    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """Messages in log-time order (ties keep file order); corrupt chunks are skipped and
        recorded in :attr:`damage`.

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
        yield from self._merge_chunks(wanted, start_ns, end_ns)

    def _merge_chunks(
        self, wanted: set[str] | None, start_ns: int | None, end_ns: int | None
    ) -> Iterator[RecordedMessage]:
        # Merge over chunks sorted by start time: a queued message is safe to emit once no
        # chunk still unread can start before it (same order as mcap's message queue: log
        # time, then chunk offset, then position in the chunk). The queue is a sorted list
        # extended by whole chunks (Timsort merges the two sorted runs in linear time) rather
        # than a heap pushed and popped per message: with the recorder's chunks, which do not
        # overlap, every chunk's messages leave in one slice.
        refs = sorted(
            (
                r
                for r in self._chunks
                if (start_ns is None or r.end_ns >= start_ns)
                and (end_ns is None or r.start_ns < end_ns)
            ),
            key=lambda r: (r.start_ns, r.offset),
        )
        channels = self._channels
        queue: list[tuple[int, int, int, RecordedMessage]] = []
        for ref in refs:
            if queue and queue[0][0] < ref.start_ns:
                k = bisect.bisect_left(queue, (ref.start_ns,))
                for item in queue[:k]:
                    yield item[3]
                del queue[:k]
            records = self._load_chunk(ref)
            off = ref.offset
            added = []
            for i, rec in enumerate(records or ()):
                if isinstance(rec, Channel):
                    channels.setdefault(rec.id, _info(rec))
                    continue
                ch = channels.get(rec.channel_id)
                if ch is None or (wanted is not None and ch.topic not in wanted):
                    continue
                t = rec.log_time
                if start_ns is not None and t < start_ns:
                    continue
                if end_ns is not None and t >= end_ns:
                    continue
                msg = RecordedMessage(ch.topic, t, rec.publish_time, rec.data, rec.sequence, ch)
                added.append((t, off, i, msg))
            if added:
                queue += added
                queue.sort()  # (log time, chunk offset, index) is unique: no msg compared
        for item in queue:
            yield item[3]

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
        if data is None:
            return None
        try:
            return layout.decode_truth(data)
        except (RecursionError, ValueError) as exc:  # too deep, or a 5,000-digit number
            if isinstance(exc, layout.LayoutError):
                raise
            raise layout.LayoutError(
                f"truth.json attachment cannot be parsed: {type(exc).__name__}: {str(exc)[:80]}"
            ) from None

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
