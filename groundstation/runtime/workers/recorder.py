"""The recorder process: every topic of the session into MCAP segments that are never erased.

``python -m groundstation.runtime.workers.recorder --session ID --out LOG.mcap
[--source URI ...] [--created-by TEXT] [--segment-s S] [--name NAME]``

Subscribes to every topic of every publisher of the session through a
:class:`~groundstation.runtime.tap.Tap` (frames as received, header parsed only) and writes
through :class:`~groundstation.acquisition.recorder.Recorder` in the layout of
:mod:`~groundstation.acquisition.layout`: raw topics unwrapped to their wire bytes (NatNet
version / Motive up axis from the payload become channel metadata), every other topic as the
frames exactly as received (``pack_frames``), log time = the header's receive time (stamped on
receipt when the publisher left it 0), publish time = the header's source time. The write path
is one method, :meth:`RecorderProcess.write_message`.

Active and standby
------------------
A session runs two recorder processes. The one that holds the session's ``recorder.lock``
(``flock``, released by the kernel the instant its holder dies) is *active* and writes; the
other is a *standby*: subscribed to the same topics, it keeps the last ``--ring-s`` seconds of
messages in memory and blocks on the lock. When the active recorder dies, the standby gets the
lock, reads what the dead one made durable (the tail of its segment, recovered up to the last
complete chunk), writes from its ring every message that is not in the file, and carries on
in a **new segment**: nothing is truncated, and what the dead recorder had received but not yet
written is not lost. Messages neither held (the standby had not yet subscribed) are counted as
``takeover_lost``. The supervisor restarts the dead process, which becomes the new standby.

Segments
--------
Segment 0 is ``--out``; later ones are written beside it (``LOG.001.mcap``, ...) by a takeover
and every ``--segment-s`` seconds of recording (default 60), so that a file being written is
always small enough for a restarted detector or mapper to read back quickly
(:mod:`~groundstation.acquisition.segments`; every reader reads a session's segments as one).
Every segment's metadata holds the session's whole configuration, its session id and index.
An existing file is never overwritten: a segment path that exists is skipped.

Chunks are closed at least once a second of log time (and by a 1 s timer when the session is
quiet), so a SIGKILL of a lone recorder loses at most about a second. SIGINT/SIGTERM drain what
is queued, close the file and exit 0. An unwritable path or a full disk is a
:class:`RecordingError`: it is published on ``log`` (and ``status`` shows ``state = "failed"``),
the process keeps running and counts the messages it drops instead of crashing (a crash would
only be restarted into the same error). Its status also says how far behind it writes
(``lag_s``: now minus the receive time of the newest message written).

Detector outputs are recorded once: an observation or contact event whose id an earlier
incarnation of the detector already published (a SIGKILL between sending an output and
counting it as sent makes the resumed detector send that one again) is dropped and counted
(``duplicates``).
"""

from __future__ import annotations

import argparse
import collections
import fcntl
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import zmq

from groundstation.acquisition import layout, segments
from groundstation.acquisition.recorder import Recorder, RecordingError
from groundstation.bus.envelope import EnvelopeError, pack_frames, unpack_frames, unpack_header
from groundstation.config import Config, to_toml
from groundstation.openformats.export import foxglove_hook
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.tap import Tap, Tapped
from groundstation.runtime.worker import Worker, worker_main

_IDLE_FLUSH_NS = 1_000_000_000
_DRAIN_IDLE_MS = 300
_REMIND_NS = 5_000_000_000
DEFAULT_SEGMENT_S = 60.0
DEFAULT_RING_S = 10.0
LOCK_FILE = "recorder.lock"
#: Topics whose messages are the detector's outputs, each published once under its id.
_KEYED_OUTPUTS = frozenset({"observations", "contact.event"})
#: How many of them the recorder remembers to drop a repeat (a repeat follows its first within
#: the seconds of a restart; 65,536 is hours of contacts).
_KEYED_MEMORY = 65_536


def _station_version() -> str:
    try:
        from importlib.metadata import version

        return version("groundstation")
    except Exception:  # noqa: BLE001 - not installed: still record
        return "unknown"


def message_key(msg: Tapped) -> tuple:
    """What identifies a received message in a recording: raw topics by (topic, receive time),
    the only header field their stored bytes keep (as log time); envelopes by (topic, origin)
    and sequence number."""
    if layout.is_raw_topic(msg.topic):
        return ("raw", msg.topic), msg.header.recv_ns
    return ("env", msg.topic, msg.header.origin), msg.header.seq


def _durable_positions(first: Path, since_ns: int) -> dict[tuple, int]:
    """Per message stream, the newest position recorded at or after log time ``since_ns`` in
    the session written to ``first`` (every segment, cut ones recovered)."""
    out: dict[tuple, int] = {}
    if not first.exists():
        return out
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a cut segment is what we expect here
        with segments.open_session(first) as rec:
            for m in rec.messages(start_ns=max(0, since_ns)):
                if layout.is_raw_topic(m.topic):
                    key, pos = ("raw", m.topic), m.log_time_ns
                else:
                    try:
                        h = unpack_header(unpack_frames(m.data)[1])
                    except (EnvelopeError, IndexError):
                        continue  # a damaged message: not a position
                    key, pos = ("env", m.topic, h.origin), h.seq
                if pos > out.get(key, -1):
                    out[key] = pos
    return out


class RecorderProcess(Worker):
    """The loop of the recorder process (see the module docstring).

    Parameters
    ----------
    session : Session
    out : str
        Segment 0 of the recording.
    config : Config
        The session's configuration (stored whole in every segment's metadata).
    standby : bool
        Take part in the active/standby lock (False: always active, e.g. a lone recorder
        started by hand).
    segment_s : float
        Rotate to a new segment after this many seconds of recording (the recorder's clock:
        log times of different publishers interleave out of order).
    ring_s : float
        Seconds of messages a standby keeps for a takeover.
    """

    def __init__(
        self,
        session: Session,
        out: str,
        config: Config,
        *,
        name: str = "recorder",
        sources: Sequence[str] = (),
        created_by: str = "groundstation record",
        context: zmq.Context | None = None,
        standby: bool = True,
        segment_s: float = DEFAULT_SEGMENT_S,
        ring_s: float = DEFAULT_RING_S,
        foxglove: Any = None,
    ) -> None:
        super().__init__(session, config, name=name, context=context)
        self.parent_death_signal = signal.SIGTERM  # close the segment when orphaned
        self.out = Path(out)
        self.sub = Tap(session.subscribe_endpoints(), self.ctx)
        self.dropped = 0
        self.bad = 0
        self.duplicates = 0  # detector outputs a restarted detector published again
        self._outputs: collections.OrderedDict[tuple, int] = collections.OrderedDict()
        self.recorder: Recorder | None = None
        self.error: RecordingError | None = None
        self.segment_index: int | None = None
        self.segments_written = 0
        self.segment_s = float(segment_s)
        self.ring_s = float(ring_s)
        self.role = "starting"
        self.takeover_lost = 0
        self.takeover_written = 0
        self.lag_s = 0.0
        self._lag_max = 0.0
        self._segment_t0: int | None = None
        self._last_msg = time.monotonic_ns()
        self._reminded_ns: int | None = None
        self._ring: collections.deque[tuple[int, Tapped]] = collections.deque()
        self._lock_fd: int | None = None
        self._promote = threading.Event()
        self._use_lock = standby
        self._foxglove_make = foxglove
        self.foxglove: Any = None  # the current segment's Foxglove writer (issue 15)
        self._meta = dict(
            station_version=_station_version(),
            created_by=created_by,
            config=to_toml(config),
            sources=list(sources),
            session=session.session_id,
            # UTC minus the log-time (monotonic) clock: export tlog dates its records with it
            extra={layout.KEY_UTC_OFFSET: str(time.time_ns() - time.monotonic_ns())},
        )

    # -- roles ---------------------------------------------------------------------------------
    def setup(self) -> int | None:
        if not self._use_lock:
            self._become_active()
            return None
        path = os.path.join(self.session.ensure_directory(), LOCK_FILE)
        self._lock_fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self.role = self.state = "standby"
            threading.Thread(target=self._wait_for_lock, name="standby-lock", daemon=True).start()
            return None
        self._become_active()
        return None

    def _wait_for_lock(self) -> None:
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX)  # returns when the active one dies
        except OSError:
            return
        self._promote.set()

    def _become_active(self, lazy: bool = False) -> None:
        """Write from now on; ``lazy``: create the segment at the first message to write (a
        standby promoted while the session stops writes no empty segment)."""
        self.role = "active"
        self.state = "recording"
        if not lazy:
            self._open_segment()

    def _take_over(self) -> None:
        """The active recorder died: write what it had not made durable, then go on."""
        ring, self._ring = self._ring, collections.deque()
        since = min((m.recv_ns for _, m in ring), default=0)
        try:
            durable = _durable_positions(self.out, since - 5_000_000_000)
        except Exception as exc:  # noqa: BLE001 - an unreadable file: write the whole ring
            self.log("warning", f"takeover: cannot read {self.out}: {exc}")
            durable = {}
        first_in_ring: dict[tuple, int] = {}
        for _, msg in ring:
            key, pos = message_key(msg)
            first_in_ring.setdefault(key, pos)
        self._become_active(lazy=True)
        written = 0
        for _, msg in ring:
            key, pos = message_key(msg)
            if pos <= durable.get(key, -1):
                continue
            self.write_message(msg)
            written += 1
        lost = sum(
            max(0, first_in_ring[k] - durable[k] - 1)
            for k in first_in_ring
            if k[0] == "env" and k in durable
        )
        self.takeover_written, self.takeover_lost = written, lost
        self.log(
            "warning" if lost else "info",
            f"took over the recording in segment {self.segment_index}: wrote {written} "
            f"message(s) the stopped recorder had not made durable; {lost} lost",
        )

    # -- writing -------------------------------------------------------------------------------
    def _open_segment(self) -> None:
        while True:
            index, path = segments.next_segment(self.out)
            meta = layout.station_metadata(**self._meta, segment=index)
            try:
                self.recorder = Recorder(path, metadata=meta)
            except RecordingError as exc:
                if isinstance(exc, FileExistsError):
                    continue  # taken meanwhile: never overwrite, take the next one
                self._failed(exc)
                return
            break
        self.segment_index = index
        self.segments_written += 1
        self._segment_t0 = None
        self.state = "recording"
        # Foxglove channels beside ours (issue 15): groundstation.openformats.export
        make = self._foxglove_make
        self.foxglove = make(self.recorder) if make is not None else None

    def _failed(self, exc: RecordingError) -> None:
        self.state = "failed"
        self.error = exc
        if self.recorder is not None:
            self.recorder.close()
        self.recorder = self.foxglove = None
        self.log("error", exc.message, exc.hint)

    def take(self, msg: Tapped) -> None:
        """Take one received message: record it (active), keep it for a takeover (standby), or
        count it as dropped after a failure."""
        self.rates.add(msg.topic)
        if self.role == "standby":
            now = time.monotonic_ns()
            self._ring.append((now, msg))
            cut = now - int(self.ring_s * 1e9)
            while self._ring and self._ring[0][0] < cut:
                self._ring.popleft()
            return
        self.write_message(msg)

    def _repeated_output(self, msg: Tapped) -> bool:
        """Whether ``msg`` is a detector output (an observation or a contact event, keyed by its
        id) that an earlier incarnation of its publisher already published. A resumed detector
        publishes again the last outputs the killed one counted as sent, since those may have
        died in its send queue (at least once, never lost); the recording keeps the first."""
        if msg.topic not in _KEYED_OUTPUTS:
            return False
        try:
            p = msg.envelope.payload
            key = (msg.topic, int(p["id"]), p.get("state"))
        except (EnvelopeError, KeyError, TypeError, ValueError):
            return False  # the write path names a malformed message
        origin = msg.header.origin
        first = self._outputs.setdefault(key, origin)
        if first != origin:
            self.duplicates += 1
            return True
        while len(self._outputs) > _KEYED_MEMORY:
            self._outputs.popitem(last=False)
        return False

    def write_message(self, msg: Tapped) -> None:
        """The write path: one received message into the current segment."""
        if self._repeated_output(msg):
            return
        if self.recorder is None and self.error is None:
            self._open_segment()
        rec = self.recorder
        if rec is None:
            self.dropped += 1
            self._remind(msg.topic not in ("status", "log"))
            return
        log_ns = msg.recv_ns
        try:
            if layout.is_raw_topic(msg.topic):
                env = msg.envelope
                extra = {
                    key: str(env.payload[field])
                    for key, field in (
                        (layout.KEY_NATNET_VERSION, "natnet_version"),
                        (layout.KEY_MOTIVE_UP, "motive_up"),
                    )
                    if field in env.payload
                }
                rec.write(env, msg.topic, log_ns, channel_metadata=extra or None)
            else:
                rec.write(pack_frames(msg.frames), msg.topic, log_ns, msg.header.source_ns)
            if self.foxglove is not None:
                self.foxglove.add(msg.envelope, log_ns)
        except RecordingError as exc:
            self.dropped += 1
            self._failed(exc)
            return
        except (layout.LayoutError, EnvelopeError) as exc:  # skip the message, go on
            self.bad += 1
            self.log("warning", f"not recorded: {getattr(exc, 'message', exc)}")
            return
        now = time.monotonic_ns()
        if msg.header.recv_ns:  # stamped by its publisher: how late we write it
            self._lag_max = max(self._lag_max, (now - log_ns) / 1e9 if log_ns <= now else 0.0)
        if self._segment_t0 is None:
            self._segment_t0 = now
        elif now - self._segment_t0 >= self.segment_s * 1e9:
            self._rotate()

    def _rotate(self) -> None:
        try:
            if self.recorder is not None:
                self._finish_foxglove()
                self.recorder.close()
        except RecordingError as exc:
            self._failed(exc)
            return
        self._open_segment()

    def _finish_foxglove(self) -> None:
        """Write the segment's last Foxglove messages before the segment closes."""
        if self.foxglove is not None:
            self.foxglove.finish()
            self.foxglove = None

    def _remind(self, data_topic: bool) -> None:
        """Repeat the failure on ``log`` at the first dropped data message (its publishers are
        connected by then, unlike at start-up) and every ``_REMIND_NS`` while dropping."""
        now = time.monotonic_ns()
        due = self._reminded_ns is None if data_topic else False
        due = due or (self._reminded_ns is not None and now - self._reminded_ns >= _REMIND_NS)
        if due and self.error is not None:
            self._reminded_ns = now
            text = f"{self.error.message}; {self.dropped} message(s) dropped so far"
            self.log("error", text, self.error.hint)

    # -- worker hooks --------------------------------------------------------------------------
    def step(self) -> None:
        if self._promote.is_set() and self.role == "standby":
            self._take_over()
        msg = self.sub.recv(100)
        now = time.monotonic_ns()
        if msg is not None:
            self.take(msg)
            self._last_msg = now
        elif self.recorder is not None and now - self._last_msg >= _IDLE_FLUSH_NS:
            self._flush()
            self._last_msg = now

    def _flush(self) -> None:
        try:
            self.recorder.flush()
        except RecordingError as exc:
            self._failed(exc)

    def status_topics(self, now_ns: int) -> dict:
        topics = self.rates.snapshot(now_ns)
        for topic, st in self.sub.stats.items():
            topics.setdefault(topic, {}).update(gaps=st.gaps, bad=st.bad)
        rec = self.recorder
        self.lag_s, self._lag_max = round(self._lag_max, 3), 0.0
        topics["recording"] = {
            "bytes_written": rec.stats.bytes_written if rec is not None else 0,
            "dropped": self.dropped,
            "bad": self.bad,
            "duplicates": self.duplicates,
            "role": self.role,
            "segment": self.segment_index,
            "segments_written": self.segments_written,
            "path": None if rec is None else str(rec.path),
            "lag_s": self.lag_s,
            "ring": len(self._ring),
            "takeover_written": self.takeover_written,
            "takeover_lost": self.takeover_lost,
        }
        if self.foxglove is not None:  # translations written / messages it could not translate
            topics["foxglove"] = {
                "written": self.foxglove.written,
                "bad": self.foxglove.translator.bad,
            }
        return topics

    def status_text(self) -> str:
        if self.role == "standby":
            return f"standby for {self.out} ({len(self._ring)} messages held)"
        rec = self.recorder
        written = rec.stats.bytes_written if rec is not None else 0
        where = "" if rec is None else f"{rec.path}"
        return f"{where or self.out}: {written} bytes written, {self.dropped} dropped" + (
            f"; {self.error.message}" if self.error is not None else ""
        )

    def teardown(self) -> None:
        if self.role == "active":
            while (msg := self.sub.recv(_DRAIN_IDLE_MS)) is not None:
                self.take(msg)  # what the sources sent before they stopped
            if self.recorder is not None:
                try:
                    self._finish_foxglove()
                    self.recorder.close(fsync=True)
                except RecordingError as exc:
                    self._failed(exc)
        self.sub.close()
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # releases the lock (a standby may take over: it is stopping)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.recorder")
    add_session_arguments(p)
    p.add_argument("--out", required=True, help="MCAP file to write (segment 0)")
    p.add_argument("--name", default="recorder", help="process name (its endpoint)")
    p.add_argument("--source", action="append", default=[], help="source URI (metadata)")
    p.add_argument("--created-by", default="groundstation record", help="metadata text")
    p.add_argument("--max-s", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--segment-s", type=float, default=DEFAULT_SEGMENT_S,
                   help="start a new segment after this many seconds of recording")  # fmt: skip
    p.add_argument("--ring-s", type=float, default=DEFAULT_RING_S,
                   help="standby: seconds of messages kept for a takeover")  # fmt: skip
    p.add_argument("--no-standby", action="store_true",
                   help="always write (no active/standby lock)")  # fmt: skip
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""

    def build(args: argparse.Namespace) -> RecorderProcess:
        if not args.segment_s > 0 or not args.ring_s > 0:
            from groundstation.errors import ConfigError

            raise ConfigError("--segment-s and --ring-s must be > 0")
        config = worker_config(args)
        return RecorderProcess(
            session_from_args(args),
            args.out,
            config,
            name=args.name,
            sources=args.source,
            created_by=args.created_by,
            standby=not args.no_standby,
            segment_s=args.segment_s,
            ring_s=args.ring_s,
            foxglove=foxglove_hook(config),
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
