"""A recorded session is its ordered segments; read them as one recording.

A recorder never truncates a file. A session recorded to ``flight.mcap`` writes segment 0 there;
every later segment goes beside it as ``flight.001.mcap``, ``flight.002.mcap``, ... because the
active recorder rotates to a new segment every ``segment_s`` seconds of log time (so a file
being written stays small enough to scan quickly) and because a standby recorder that takes over
from a killed one starts a new segment instead of touching the killed one's file. Each segment's
``groundstation`` metadata names its ``session`` and its ``segment`` index
(:mod:`~groundstation.acquisition.layout`).

:func:`open_session` opens a session given its first file (or any of its segments, or the folder
holding one session) and returns a :class:`SessionRecording` that reads like one
:class:`~groundstation.acquisition.reader.Recording`: messages of every segment in log-time order,
one summary, the first segment's metadata and truth. Segments cut short (a killed recorder) are
recovered up to their last complete chunk by the reader; :attr:`SessionRecording.truncated` says
so. :func:`claim_output` is the one check every writer's ``--out`` goes through: an existing
recording is never replaced without ``force``.

Built on top of :mod:`~groundstation.acquisition.reader` (no MCAP parsing here).
"""

from __future__ import annotations

import heapq
import os
import re
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from groundstation.acquisition import layout
from groundstation.acquisition.reader import (
    ChannelInfo,
    RecordedMessage,
    Recording,
    RecordingSummary,
    RecoveryReport,
    open_recording,
)
from groundstation.errors import GroundstationError

SUFFIX = ".mcap"
_MAX_INDEX = 9999


class OutputExistsError(GroundstationError, FileExistsError):
    """An output file exists and ``--force`` was not given; the message names the file(s)."""


class SegmentError(GroundstationError, ValueError):
    """A path does not hold one recorded session (no file, mixed sessions, unreadable folder)."""


# -- names ---------------------------------------------------------------------------------------


def segment_path(first: str | os.PathLike[str], index: int) -> Path:
    """Path of segment ``index`` of the session whose segment 0 is ``first``.

    ``flight.mcap`` -> ``flight.mcap`` (0), ``flight.001.mcap`` (1), ...; a name without the
    ``.mcap`` suffix gets ``.001`` appended.
    """
    first = Path(first)
    if not 0 <= index <= _MAX_INDEX:
        raise SegmentError(f"segment index {index} out of range 0..{_MAX_INDEX}")
    if index == 0:
        return first
    if first.suffix == SUFFIX:
        return first.with_name(f"{first.stem}.{index:03d}{SUFFIX}")
    return first.with_name(f"{first.name}.{index:03d}")


def _sibling_pattern(first: Path) -> re.Pattern[str]:
    if first.suffix == SUFFIX:
        return re.compile(re.escape(first.stem) + r"\.(\d{3,4})" + re.escape(SUFFIX) + "$")
    return re.compile(re.escape(first.name) + r"\.(\d{3,4})$")


def sibling_segments(first: str | os.PathLike[str]) -> list[tuple[int, Path]]:
    """Existing later segments of ``first`` as (index, path), by index (names only)."""
    first = Path(first)
    folder = first.parent if str(first.parent) else Path(".")
    pattern = _sibling_pattern(first)
    out = []
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    for name in names:
        m = pattern.fullmatch(name)
        if m and int(m.group(1)) > 0:
            out.append((int(m.group(1)), folder / name))
    return sorted(out)


def output_paths(first: str | os.PathLike[str]) -> list[Path]:
    """The files a session written to ``first`` would occupy that exist now."""
    first = Path(first)
    found = [first] if first.exists() or first.is_symlink() else []
    return found + [p for _, p in sibling_segments(first)]


def next_segment(first: str | os.PathLike[str]) -> tuple[int, Path]:
    """The first free segment (index, path) of ``first`` (never an existing file)."""
    taken = {0} if Path(first).exists() else set()
    taken |= {i for i, _ in sibling_segments(first)}
    index = 0
    while index in taken:
        index += 1
    return index, segment_path(first, index)


def claim_output(path: str | os.PathLike[str], force: bool = False, what: str = "--out") -> Path:
    """Make sure writing a new recording (or any output file) at ``path`` erases nothing.

    Without ``force`` an existing file (or an existing later segment of it) is an error naming
    it; with ``force`` those files are removed first. Returns ``path``.

    Raises
    ------
    OutputExistsError
        ``path`` or one of its segments exists and ``force`` is False.
    SegmentError
        ``path`` is a folder, or a file cannot be removed.
    """
    path = Path(path)
    if path.is_dir():
        raise SegmentError(f"{what} {str(path)!r} is a folder, not a file", hint="name a file")
    existing = output_paths(path)
    if not existing:
        return path
    if not force:
        more = f" and {len(existing) - 1} more segment(s)" if len(existing) > 1 else ""
        raise OutputExistsError(
            f"{what} {str(existing[0])!r} already exists{more}; not overwriting it",
            hint="choose another file, or pass --force to replace it",
        )
    for p in existing:
        try:
            p.unlink()
        except OSError as exc:
            raise SegmentError(f"cannot remove {str(p)!r} for --force: {exc.strerror}") from None
    return path


# -- finding a session's segments ----------------------------------------------------------------


def candidate_paths(path: str | os.PathLike[str]) -> list[Path]:
    """Files that may be segments of the session at ``path`` (by name only, not opened).

    ``path`` is a session's first file (its later segments are looked for beside it), a later
    segment (``flight.002.mcap``: the session's first file is looked for first), or a folder
    (every ``*.mcap`` in it).

    Raises
    ------
    SegmentError
        No such file or folder, or an empty folder.
    """
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix == SUFFIX and p.is_file())
        if not files:
            raise SegmentError(f"folder {str(path)!r} holds no {SUFFIX} recording")
        return files
    if not path.exists():
        raise SegmentError(
            f"recording {str(path)!r} does not exist", hint="give a recording file or its folder"
        )
    m = re.fullmatch(r"(.*)\.(\d{3,4})(" + re.escape(SUFFIX) + ")?", path.name)
    if m and int(m.group(2)) > 0:
        first = path.with_name(m.group(1) + (m.group(3) or ""))
        if first.is_file():
            path = first
    return [path] + [p for _, p in sibling_segments(path)]


def _session_of(rec: Recording) -> tuple[str | None, int]:
    meta = rec.metadata() or {}
    return meta.get(layout.KEY_SESSION), layout.segment_index(meta) or 0


def _select(path: Path, recs: list[Recording]) -> list[Recording]:
    """The recordings of one session, in segment order; closes the others."""
    if path.is_dir():
        sessions = {_session_of(r)[0] for r in recs}
        if len(recs) > 1 and (len(sessions) > 1 or None in sessions):
            for r in recs:
                r.close()
            raise SegmentError(
                f"folder {str(path)!r} holds {len(recs)} recordings of {len(sessions)} session(s)",
                hint="give one recording file instead",
            )
        return sorted(recs, key=lambda r: (_session_of(r)[1], r.path.name))
    session = _session_of(recs[0])[0]
    keep, drop = [recs[0]], []
    for r in recs[1:]:
        (keep if session is not None and _session_of(r)[0] == session else drop).append(r)
    for r in drop:
        r.close()
    return sorted(keep, key=lambda r: _session_of(r)[1])


def _select_keep(path: Path, recs: list[Recording]) -> list[Recording]:
    """:func:`_select` without closing the recordings it leaves out (a cache owns them)."""
    if path.is_dir():
        sessions = {_session_of(r)[0] for r in recs}
        if len(recs) > 1 and (len(sessions) > 1 or None in sessions):
            raise SegmentError(f"folder {str(path)!r} holds recordings of {len(sessions)} sessions")
        return sorted(recs, key=lambda r: (_session_of(r)[1], r.path.name))
    session = _session_of(recs[0])[0]
    keep = [recs[0]] + [r for r in recs[1:] if session is not None and _session_of(r)[0] == session]
    return sorted(keep, key=lambda r: _session_of(r)[1])


def find_segments(path: str | os.PathLike[str]) -> list[Path]:
    """The segment files of the session at ``path`` in segment order (see :func:`open_session`)."""
    with open_session(path) as session:
        return list(session.paths)


# -- reading them as one -------------------------------------------------------------------------


def _channel_key(ch: ChannelInfo) -> tuple[str, str, tuple[tuple[str, str], ...]]:
    return ch.topic, ch.message_encoding, tuple(sorted(ch.metadata.items()))


class SessionRecording:
    """The segments of one session read as one recording (use :func:`open_session`).

    Channels of every segment are merged by (topic, encoding, metadata) and numbered once, so
    a channel keeps one id across segments (a decoder keyed by channel id continues over a
    segment boundary).

    Attributes
    ----------
    path : Path
        The first segment.
    paths : list of Path
        Every segment, in order.
    segments : list of Recording
    truncated : bool
        True when any segment was cut short (recovered up to its last complete chunk).
    recovery : RecoveryReport or None
        The first cut segment's report (see :attr:`recoveries` for all).
    summary : RecordingSummary
        Counts and span over every segment.
    """

    def __init__(self, segments: Iterable[Recording]):
        self.segments: list[Recording] = list(segments)
        if not self.segments:
            raise SegmentError("a session needs at least one segment")
        self.paths = [Path(r.path) for r in self.segments]
        self.path = self.paths[0]
        self._global: dict[tuple, ChannelInfo] = {}
        self._local: list[dict[int, ChannelInfo]] = []
        for rec in self.segments:
            local = {}
            for ch in rec.summary.channels:
                key = _channel_key(ch)
                g = self._global.get(key)
                if g is None:
                    g = ChannelInfo(len(self._global) + 1, ch.topic, ch.message_encoding,
                                    dict(ch.metadata))  # fmt: skip
                    self._global[key] = g
                local[ch.id] = g
            self._local.append(local)
        self.truncated = any(r.truncated for r in self.segments)
        self.recoveries: list[tuple[Path, RecoveryReport]] = [
            (r.path, r.recovery) for r in self.segments if r.recovery is not None
        ]
        self.recovery = self.recoveries[0][1] if self.recoveries else None
        counts: Counter = Counter()
        starts = [r.summary.start_ns for r in self.segments if r.summary.start_ns is not None]
        ends = [r.summary.end_ns for r in self.segments if r.summary.end_ns is not None]
        for r in self.segments:
            counts.update(r.summary.topic_counts)
        self.summary = RecordingSummary(
            message_count=sum(r.summary.message_count for r in self.segments),
            topic_counts=dict(counts),
            start_ns=min(starts) if starts else None,
            end_ns=max(ends) if ends else None,
            channels=tuple(self._global.values()),
        )

    def _remapped(self, k: int, it: Iterator[RecordedMessage]) -> Iterator[RecordedMessage]:
        local = self._local[k]
        same: dict[int, ChannelInfo] = {}  # channel id -> the segment's channel equal to g
        for msg in it:
            ch = msg.channel
            if same.get(ch.id) is ch:  # compared once per channel, not per message
                yield msg
                continue
            g = local.get(ch.id)
            if g is None or g == ch:
                if g is not None:
                    same[ch.id] = ch
                yield msg
            else:
                yield RecordedMessage(
                    msg.topic, msg.log_time_ns, msg.publish_time_ns, msg.data, msg.sequence, g
                )

    def messages(
        self,
        topics: Iterable[str] | str | None = None,
        start_ns: int | None = None,
        end_ns: int | None = None,
    ) -> Iterator[RecordedMessage]:
        """Messages of every segment in log-time order (ties: earlier segment first).

        Same parameters as :meth:`Recording.messages`.
        """
        if isinstance(topics, str):
            topics = [topics]
        topics = None if topics is None else list(topics)
        its = []
        for k, rec in enumerate(self.segments):
            s = rec.summary
            if s.start_ns is None:
                continue
            if end_ns is not None and s.start_ns >= end_ns:
                continue
            if start_ns is not None and s.end_ns is not None and s.end_ns < start_ns:
                continue
            its.append(self._remapped(k, rec.messages(topics, start_ns, end_ns)))
        if len(its) == 1:
            yield from its[0]
        else:
            yield from heapq.merge(*its, key=lambda m: m.log_time_ns)

    def topics(self) -> dict[str, int]:
        """Message count per topic over every segment."""
        return dict(self.summary.topic_counts)

    def metadata(self, name: str = layout.METADATA_NAME) -> dict[str, str] | None:
        """The first segment's metadata record ``name`` (default: the station record)."""
        for rec in self.segments:
            meta = rec.metadata(name)
            if meta is not None:
                return meta
        return None

    def attachment(self, name: str) -> bytes | None:
        """The first attachment called ``name`` in any segment, or None."""
        for rec in self.segments:
            data = rec.attachment(name)
            if data is not None:
                return data
        return None

    def truth(self) -> dict[str, Any] | None:
        """The ``truth.json`` attachment of the session, parsed, or None."""
        data = self.attachment(layout.TRUTH_ATTACHMENT)
        return None if data is None else layout.decode_truth(data)

    def describe(self) -> str:
        """One line: segments, span, and what was cut short."""
        cut = ", ".join(f"{p.name}: {r.describe()}" for p, r in self.recoveries)
        return (
            f"{len(self.segments)} segment(s), {self.summary.duration_s:.1f} s, "
            f"{self.summary.message_count} messages" + (f"; cut short: {cut}" if cut else "")
        )

    def close(self) -> None:
        for rec in self.segments:
            rec.close()

    def __enter__(self) -> SessionRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class GrowingSession:
    """A session that is still being written, read again and again (a restarted worker catching
    up): finished segments are opened once and kept, only the newest one is opened again, and
    only when it has grown.

    Parameters
    ----------
    path : path
        The session's first segment or folder.
    """

    def __init__(self, path: str | os.PathLike[str], **open_kwargs: Any):
        self.path = Path(path)
        self._kw = open_kwargs
        self._open: dict[Path, tuple[int, Recording]] = {}

    def _recording(self, p: Path, newest: bool) -> Recording:
        size = p.stat().st_size
        got = self._open.get(p)
        if got is not None and (not newest or got[0] == size):
            return got[1]
        if got is not None:
            got[1].close()
        rec = open_recording(p, **self._kw)
        self._open[p] = (size, rec)
        return rec

    def session(self) -> SessionRecording:
        """The session as it is on disk now (do not close it: :meth:`close` does)."""
        paths = candidate_paths(self.path)
        recs = [self._recording(p, k == len(paths) - 1) for k, p in enumerate(paths)]
        return SessionRecording(_select_keep(self.path, recs))

    def messages(
        self, topics: Iterable[str] | str | None = None, start_ns: int | None = None
    ) -> list[RecordedMessage]:
        """Messages of ``topics`` from log time ``start_ns`` on, in log-time order."""
        return list(self.session().messages(topics, start_ns))

    def close(self) -> None:
        for _, rec in self._open.values():
            rec.close()
        self._open = {}

    def __enter__(self) -> GrowingSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_session(path: str | os.PathLike[str], **open_kwargs: Any) -> SessionRecording:
    """Open a recorded session (its first file, a later segment, or its folder) as one.

    Extra keyword arguments go to :func:`~groundstation.acquisition.reader.open_recording` for
    each segment.

    Raises
    ------
    SegmentError
        No such recording, or a folder of several sessions.
    RecordingError, LayoutError
        As :func:`~groundstation.acquisition.reader.open_recording`.
    """
    path = Path(path)
    recs: list[Recording] = []
    try:
        for p in candidate_paths(path):
            recs.append(open_recording(p, **open_kwargs))
    except BaseException:
        for r in recs:
            r.close()
        raise
    return SessionRecording(_select(path, recs))
