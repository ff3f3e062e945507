"""Export a recording's MAVLink traffic to a ``.tlog`` (for QGroundControl, MAVExplorer, ...).

Every valid frame on the ``raw.mavlink`` channels is written unchanged, in log-time order, as
``uint64 big-endian (UTC microseconds) | frame``, the tlog format. Log times are the station's
monotonic clock, so they are dated by the first wall-clock reference found (the report says
which): the recording's ``utc_offset_ns`` metadata (live recorders write it), else the vehicle's
own clock (the first MAVLink SYSTEM_TIME with a non-zero ``time_unix_usec``), else the file's
modification time taken as the end of the recording; ``utc_start`` overrides all three. Raw
chunks may hold several frames or split a frame across reads: a per-channel splitter reassembles
them (the same length rules and CRC check as :mod:`.tlog`); damaged bytes are skipped and
counted. With ``natnet_as_mocap`` (default), each NatNet frame's rigid body becomes an
ATT_POS_MOCAP frame (Motive -> world (ENU) -> NED, quaternion FLU/ENU -> FRD/NED, via
``firmware_bridge.frames``) from system 1, component 197, so the mocap track appears in the tlog
too.
"""

from __future__ import annotations

import os
import struct
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from groundstation.acquisition import layout
from groundstation.acquisition.importers import (
    AUTOPILOT_SYSTEM_ID,
    MOCAP_COMPONENT_ID,
    RIGID_BODY_ID,
)
from groundstation.acquisition.importers.tlog import (
    _TS,
    FrameValidator,
    frame_length,
    message_id,
    message_name,
)
from groundstation.acquisition.recorder import RecordingError
from groundstation.acquisition.segments import open_session as open_recording  # segments as one


class FrameSplitter:
    """Reassemble MAVLink frames from a byte stream cut at arbitrary points (pure)."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._check = FrameValidator()
        self.garbage_bytes = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the complete valid frames found."""
        buf = self._buf
        buf += data
        out: list[bytes] = []
        pos = 0
        while pos < len(buf):
            if buf[pos] not in (0xFD, 0xFE):
                pos += 1
                self.garbage_bytes += 1
                continue
            flen = frame_length(buf, pos)
            if flen is None or pos + flen > len(buf):
                break  # wait for more bytes
            frame = bytes(buf[pos : pos + flen])
            if self._check.is_valid(frame):
                out.append(frame)
                pos += flen
            else:
                pos += 1
                self.garbage_bytes += 1
        del buf[:pos]
        return out


@dataclass
class ExportReport:
    """What an export wrote."""

    source: str
    out: str
    counts: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    records: int = 0
    clock: str = ""
    first_utc_us: int | None = None

    def describe(self) -> str:
        lines = [f"exported {self.source} -> {self.out}: {self.records} tlog records"]
        if self.first_utc_us is not None:
            import datetime

            first = datetime.datetime.fromtimestamp(self.first_utc_us / 1e6, datetime.UTC)
            lines.append(f"  dated from {self.clock}: first record {first.isoformat()}")
        for name, n in sorted(self.counts.items()):
            lines.append(f"  {name:<20} {n:>8}")
        for reason, n in sorted(self.skipped.items()):
            lines.append(f"  skipped {n} ({reason})")
        return "\n".join(lines)


_SYSTEM_TIME_ID = 2
_UNIX_US = struct.Struct("<Q")


def system_time_unix_us(frame: bytes) -> int | None:
    """``time_unix_usec`` of a MAVLink 1/2 SYSTEM_TIME frame (0 or None when absent/not one)."""
    if message_id(frame) != _SYSTEM_TIME_ID:
        return None
    head = 10 if frame[0] == 0xFD else 6
    payload = frame[head : head + frame[1]] + bytes(8)  # MAVLink 2 trims trailing zeros
    return _UNIX_US.unpack_from(payload)[0]


def _wall_clock(
    meta: dict | None,
    first_system_time: tuple[int, int] | None,
    src: Path,
    end_ns: int | None,
    utc_start: float | None,
    start_ns: int | None,
    utc_offset_ns: int | None = None,
) -> tuple[int, str]:
    """(UTC ns - log ns, which reference) for :func:`export_tlog` (module docstring order)."""
    if utc_offset_ns is not None:
        return int(utc_offset_ns), "the offset given"
    if utc_start is not None:
        return int(utc_start * 1e9) - int(start_ns or 0), "--utc-start"
    offset = layout.parse_utc_offset(meta)
    if offset is not None:
        return offset, "the recording's utc_offset_ns metadata"
    if first_system_time is not None:
        log_ns, unix_us = first_system_time
        return unix_us * 1000 - log_ns, "the vehicle's SYSTEM_TIME"
    mtime_ns = src.stat().st_mtime_ns
    return mtime_ns - int(end_ns or 0), "the file's modification time (no clock in the recording)"


def export_tlog(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    natnet_as_mocap: bool = True,
    utc_start: float | None = None,
    utc_offset_ns: int | None = None,
) -> ExportReport:
    """Write the MAVLink frames of recording ``src`` (and optionally its mocap poses) to ``out``.

    Parameters
    ----------
    utc_start : float, optional
        UTC time of the recording's first message, seconds since the epoch (overrides the
        clock found in the recording).
    utc_offset_ns : int, optional
        UTC minus log time, ns, exactly (overrides everything; 0 writes the log times as they
        are, for a lossless MCAP -> tlog -> MCAP round trip).

    Raises
    ------
    RecordingError
        If ``out`` cannot be written (path and OS error named).
    """
    from firmware_bridge.frames import enu_to_ned, motive_to_world, quat_enu_flu_to_ned_frd
    from firmware_bridge.mavlink.codec import MavlinkCodec
    from firmware_bridge.mavlink.messages import MocapPose
    from firmware_bridge.natnet import FrameOfData, parse_packet

    report = ExportReport(str(src), str(out))
    counts: Counter = Counter()
    skipped: Counter = Counter()
    splitters: dict[int, FrameSplitter] = {}
    mocap = MavlinkCodec(AUTOPILOT_SYSTEM_ID, MOCAP_COMPONENT_ID)
    topics = [layout.RAW_MAVLINK_TOPIC] + ([layout.RAW_NATNET_TOPIC] if natnet_as_mocap else [])
    chunks: list[tuple[int, bytes]] = []  # (log time ns, frame)
    system_time: tuple[int, int] | None = None
    with open_recording(src) as rec:
        meta = rec.metadata()
        start_ns, end_ns = rec.summary.start_ns, rec.summary.end_ns
        for msg in rec.messages(topics=topics):
            ts = msg.log_time_ns
            if msg.topic == layout.RAW_MAVLINK_TOPIC:
                splitter = splitters.setdefault(msg.channel.id, FrameSplitter())
                for frame in splitter.feed(msg.data):
                    chunks.append((ts, frame))
                    counts[message_name(message_id(frame))] += 1
                    if system_time is None and (unix_us := system_time_unix_us(frame)):
                        system_time = (ts, unix_us)
                continue
            meta = msg.channel.metadata
            version = tuple(int(v) for v in meta.get(layout.KEY_NATNET_VERSION, "4.1").split("."))
            try:
                frame_of_data = parse_packet(msg.data, version)  # type: ignore[arg-type]
            except Exception:  # noqa: BLE001 - a bad datagram is counted, never fatal
                skipped["NatNet datagram that does not parse"] += 1
                continue
            if not isinstance(frame_of_data, FrameOfData):
                continue
            body = frame_of_data.rigid_body(RIGID_BODY_ID) or (
                frame_of_data.rigid_bodies[0] if frame_of_data.rigid_bodies else None
            )
            if body is None or not body.tracking_valid:
                skipped["NatNet frame without a tracked rigid body"] += 1
                continue
            p_w, q_w = motive_to_world(body.position, body.orientation, meta.get("motive_up", "y"))
            pose = MocapPose(
                tuple(quat_enu_flu_to_ned_frd(q_w)),
                tuple(enu_to_ned(p_w)),
                time_source_ns=msg.publish_time_ns,
            )
            chunks.append((ts, mocap.encode(pose)))
            counts["ATT_POS_MOCAP (from NatNet)"] += 1
    garbage = sum(s.garbage_bytes for s in splitters.values())
    if garbage:
        skipped["damaged MAVLink bytes"] = garbage
    offset, report.clock = _wall_clock(
        meta, system_time, Path(src), end_ns, utc_start, start_ns, utc_offset_ns
    )
    if chunks:
        report.first_utc_us = (chunks[0][0] + offset) // 1000
    try:
        Path(out).write_bytes(b"".join(_TS.pack((t + offset) // 1000) + f for t, f in chunks))
    except OSError as exc:
        raise RecordingError(
            f"cannot write tlog {str(out)!r}: {exc.strerror or exc} (errno {exc.errno})"
        ) from exc
    report.counts = dict(counts)
    report.skipped = dict(skipped)
    report.records = len(chunks)
    return report
