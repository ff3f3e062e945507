"""MAVLink telemetry logs (``.tlog``): read, import, and the frame splitter shared with export.

A tlog (QGroundControl, Mission Planner, MAVProxy) is a sequence of records::

    uint64 big-endian timestamp, us since the Unix epoch | one MAVLink 1 or 2 frame

The frames in a tlog already are wire bytes, so the importer copies each valid frame unchanged
onto ``raw.mavlink`` (log time = publish time = the record's timestamp in ns); replay runs the
live decoders on them. The reader here is our own (no ``mavutil`` global state): frame lengths
follow the MAVLink serialization spec (v2: 10-byte header + payload + 2-byte CRC + 13-byte
signature when incompat flag 0x01 is set; v1: 6 + payload + 2), and each frame's CRC is checked
by ``MavlinkCodec``. Damaged records are skipped and counted; after damage the reader resyncs on
the next position that holds a plausible timestamp followed by a valid frame.
"""

from __future__ import annotations

import os
import re
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

from groundstation.acquisition import layout
from groundstation.acquisition.importers import (
    ImportDataError,
    ImportReport,
    atomic_output,
    check_source,
    import_metadata,
)
from groundstation.acquisition.recorder import Recorder

_TS = struct.Struct(">Q")
_STX_V2, _STX_V1 = 0xFD, 0xFE
_STX = re.compile(b"[\xfd\xfe]")
_SIGNATURE_LEN = 13
#: Log times are int64 ns downstream (bus headers): later timestamps are dropped and counted.
MAX_TIME_NS = 2**63 - 1


def frame_length(buf: bytes | bytearray, pos: int) -> int | None:
    """Length of the MAVLink frame starting at ``buf[pos]`` (None: not a start byte or too short).

    MAVLink 2: STX, len, incompat, compat, seq, sys, comp, msgid(3), payload, crc(2),
    [signature(13) if incompat & 0x01]; MAVLink 1: STX, len, seq, sys, comp, msgid, payload,
    crc(2).
    """
    if len(buf) - pos < 3:
        return None
    if buf[pos] == _STX_V2:
        return buf[pos + 1] + 12 + (_SIGNATURE_LEN if buf[pos + 2] & 0x01 else 0)
    if buf[pos] == _STX_V1:
        return buf[pos + 1] + 8
    return None


def message_id(frame: bytes) -> int:
    """Message id of a MAVLink 1 or 2 frame."""
    if frame[0] == _STX_V2:
        return frame[7] | (frame[8] << 8) | (frame[9] << 16)
    return frame[5]


def message_name(msgid: int) -> str:
    """Name of a ``common`` message id, or ``"MSG_<id>"``."""
    from pymavlink.dialects.v20 import common

    cls = common.mavlink_map.get(msgid)
    return cls.msgname if cls is not None else f"MSG_{msgid}"


class FrameValidator:
    """Checks single frames with ``MavlinkCodec`` (CRC, CRC-extra, known layout)."""

    def __init__(self) -> None:
        from firmware_bridge.mavlink.codec import MavlinkCodec

        self._codec = MavlinkCodec()

    def is_valid(self, frame: bytes) -> bool:
        before = self._codec.stats.frames
        self._codec.decode(bytes(frame), 0)
        ok = self._codec.stats.frames == before + 1 and self._codec.pending_bytes == 0
        if self._codec.pending_bytes:  # never carry a partial frame into the next check
            self._codec = type(self._codec)()
        return ok


@dataclass(frozen=True)
class TlogRecord:
    """One tlog record: timestamp (us since the Unix epoch) and the frame bytes."""

    time_us: int
    frame: bytes


def read_tlog(data: bytes, skipped: Counter) -> Iterator[TlogRecord]:
    """Parse tlog bytes into records; damaged records are skipped and counted in ``skipped``.

    A record whose frame fails the check starts a resync: the reader moves on byte by byte
    until a timestamp followed by a valid frame appears (one damaged record counts once).
    """
    check = FrameValidator()
    pos, n = 0, len(data)
    resyncing = False
    while pos + _TS.size < n:
        flen = frame_length(data, pos + _TS.size)
        if flen is not None:
            end = pos + _TS.size + flen
            if end > n and not resyncing:
                skipped["truncated record at end of file"] += 1
                return
            (ts,) = _TS.unpack_from(data, pos)
            if end <= n:
                frame = data[pos + _TS.size : end]
                if check.is_valid(frame):
                    resyncing = False
                    yield TlogRecord(ts, bytes(frame))
                    pos = end
                    continue
        if not resyncing:
            skipped["damaged record (bad frame), resynced"] += 1
            resyncing = True
        # next position whose frame would start with a start byte (the byte-by-byte scan of
        # the resync, without visiting the positions that cannot hold a record)
        m = _STX.search(data, pos + 1 + _TS.size)
        if m is None:
            return
        pos = m.start() - _TS.size


def import_tlog(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    created_by: str = "groundstation import tlog",
) -> ImportReport:
    """Import a ``.tlog`` into a recording at ``out`` (frames copied unchanged)."""
    p = check_source(src)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise ImportDataError(f"cannot read {str(p)!r}: {exc.strerror or exc}") from None
    skipped: Counter = Counter()
    counts: Counter = Counter()
    last_ns = -1
    with (
        atomic_output(out) as tmp,
        Recorder(tmp, metadata=import_metadata(created_by, [str(src)])) as rec,
    ):
        for r in read_tlog(data, skipped):
            t_ns = r.time_us * 1000
            if t_ns > MAX_TIME_NS:
                skipped["timestamp beyond 2**63 ns (dropped)"] += 1
                continue
            if t_ns < last_ns:
                skipped["timestamp went backwards (kept, reader sorts by time)"] += 1
            last_ns = max(last_ns, t_ns)
            rec.write(r.frame, layout.RAW_MAVLINK_TOPIC, t_ns, t_ns, source=f"import:tlog:{p.name}")
            counts[message_name(message_id(r.frame))] += 1
        if not counts:
            raise ImportDataError(
                f"{str(p)!r} holds no valid MAVLink frames ({dict(skipped)})",
                hint="a tlog is 8-byte big-endian us timestamps each followed by a MAVLink frame",
            )
    return ImportReport(
        source=str(src),
        out=str(out),
        counts=dict(counts),
        skipped={k: v for k, v in skipped.items() if v},
        start_ns=rec.stats.start_ns,
        end_ns=rec.stats.end_ns,
        notes=["frames copied unchanged onto raw.mavlink; log time = tlog timestamp"],
    )
