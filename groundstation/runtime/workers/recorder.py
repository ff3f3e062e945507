"""The recorder process: every topic of the session into one MCAP file.

``python -m groundstation.runtime.workers.recorder --session ID --out LOG.mcap
[--source URI ...] [--created-by TEXT]``

Subscribes to every topic of every publisher of the session with ``recv_with_frames`` and writes
through :class:`~groundstation.acquisition.recorder.Recorder` in the layout of
:mod:`~groundstation.acquisition.layout`: raw topics unwrapped to their wire bytes (NatNet
version / Motive up axis from the payload become channel metadata), every other topic as the
frames exactly as received (``pack_frames``), log time = the header's receive time (stamped on
receipt when the publisher left it 0), publish time = the header's source time.

Chunks are closed at least once a second of log time (and by a 1 s timer when the session is
quiet), so a SIGKILL loses at most about a second. SIGINT/SIGTERM drain what is queued, close the
file and exit 0. An unwritable path or a full disk is a :class:`RecordingError`: it is published
on ``log`` (and ``status`` shows ``state = "failed"``), the process keeps running and counts the
messages it drops instead of crashing (a crash would only be restarted into the same error).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from typing import Any

import zmq

from groundstation.acquisition import layout
from groundstation.acquisition.recorder import Recorder, RecordingError
from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.bus.envelope import Envelope, pack_frames
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.openformats.export import foxglove_hook
from groundstation.runtime.session import (
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    load_settings,
    publish_log,
    session_from_args,
)

_IDLE_FLUSH_NS = 1_000_000_000
_DRAIN_IDLE_MS = 300
_REMIND_NS = 5_000_000_000


def _station_version() -> str:
    try:
        from importlib.metadata import version

        return version("groundstation")
    except Exception:  # noqa: BLE001 - not installed: still record
        return "unknown"


class RecorderProcess:
    """The loop of the recorder process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        out: str,
        settings: AcquisitionSettings,
        *,
        name: str = "recorder",
        sources: Sequence[str] = (),
        created_by: str = "groundstation record",
        context: zmq.Context | None = None,
        foxglove: Any = None,
    ) -> None:
        self.name, self.out = name, out
        self.ctx = context or zmq.Context()
        self.pub = Publisher(
            topics=("status", "log"), context=self.ctx, **session.publisher_kwargs(name)
        )
        self.sub = Subscriber(session.subscribe_endpoints(), context=self.ctx)
        self.rates = RateCounter()
        self.dropped = 0
        self.bad = 0
        self.state = "starting"
        self.recorder: Recorder | None = None
        self.error: RecordingError | None = None
        self._reminded_ns: int | None = None
        from groundstation.config import to_toml

        meta = layout.station_metadata(
            station_version=_station_version(),
            created_by=created_by,
            config="[acquisition]\n" + to_toml(settings),
            sources=sources,
            extra={
                "session": session.session_id,
                layout.KEY_UTC_OFFSET: str(time.time_ns() - time.monotonic_ns()),
            },
        )
        try:
            self.recorder = Recorder(out, metadata=meta)
            self.state = "recording"
        except RecordingError as exc:
            self._failed(exc)
        # Foxglove channels beside ours (issue 15): groundstation.openformats.export
        self.foxglove = foxglove(self.recorder) if self.recorder and foxglove else None

    def _failed(self, exc: RecordingError) -> None:
        self.state = "failed"
        self.error = exc
        if self.recorder is not None:
            self.recorder.close()
        self.recorder = None
        publish_log(self.pub, self.name, "error", exc.message, exc.hint)

    def write(self, env: Envelope, frames: list) -> None:
        """Record one received message (or count it as dropped after a failure)."""
        self.rates.add(env.topic)
        rec = self.recorder
        if rec is None:
            self.dropped += 1
            self._remind(env.topic not in ("status", "log"))
            return
        try:
            if layout.is_raw_topic(env.topic):
                extra = {
                    key: str(env.payload[field])
                    for key, field in (
                        (layout.KEY_NATNET_VERSION, "natnet_version"),
                        (layout.KEY_MOTIVE_UP, "motive_up"),
                    )
                    if field in env.payload
                }
                rec.write(env, env.topic, env.header.recv_ns, channel_metadata=extra or None)
            else:
                rec.write(pack_frames(frames), env.topic, env.header.recv_ns, env.header.source_ns)
            if self.foxglove is not None:
                self.foxglove.add(env, env.header.recv_ns)
        except RecordingError as exc:
            self.dropped += 1
            self._failed(exc)
        except layout.LayoutError as exc:  # e.g. a negative time: skip the message, go on
            self.bad += 1
            publish_log(self.pub, self.name, "warning", f"not recorded: {exc.message}")

    def _remind(self, data_topic: bool) -> None:
        """Repeat the failure on ``log`` at the first dropped data message (its publishers are
        connected by then, unlike at start-up) and every ``_REMIND_NS`` while dropping."""
        now = time.monotonic_ns()
        due = self._reminded_ns is None if data_topic else False
        due = due or (self._reminded_ns is not None and now - self._reminded_ns >= _REMIND_NS)
        if due and self.error is not None:
            self._reminded_ns = now
            text = f"{self.error.message}; {self.dropped} message(s) dropped so far"
            publish_log(self.pub, self.name, "error", text, self.error.hint)

    def _status(self, now_ns: int) -> None:
        topics = self.rates.snapshot(now_ns)
        for topic, st in self.sub.stats.items():
            topics.setdefault(topic, {}).update(gaps=st.gaps, bad=st.bad)
        rec = self.recorder
        written = rec.stats.bytes_written if rec is not None else 0
        topics["recording"] = {"bytes_written": written, "dropped": self.dropped, "bad": self.bad}
        if self.foxglove is not None:  # translations written / messages it could not translate
            topics["foxglove"] = {
                "written": self.foxglove.written,
                "bad": self.foxglove.translator.bad,
            }
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": self.state,
                "topics": topics,
                "text": f"{self.out}: {written} bytes written, {self.dropped} dropped"
                + (f"; {self.error.message}" if self.error is not None else ""),
            },
        )

    def run(self, stop: StopSignals | None = None, max_s: float | None = None) -> int:
        """Record until SIGINT/SIGTERM (or ``max_s`` s), then drain, close and return 0."""
        stop = stop if stop is not None else StopSignals()
        now = time.monotonic_ns()
        end = None if max_s is None else now + int(max_s * 1e9)
        next_status, last_msg = now, now
        try:
            while not stop and (end is None or now < end):
                got = self.sub.recv_with_frames(100)
                now = time.monotonic_ns()
                if got is not None:
                    self.write(*got)
                    last_msg = now
                elif self.recorder is not None and now - last_msg >= _IDLE_FLUSH_NS:
                    self._flush()
                    last_msg = now
                if now >= next_status:
                    self._status(now)
                    next_status = max(next_status + 1_000_000_000, now)
            while (got := self.sub.recv_with_frames(_DRAIN_IDLE_MS)) is not None:
                self.write(*got)  # what the sources sent before they stopped
            return 0
        finally:
            self.close()

    def _flush(self) -> None:
        try:
            self.recorder.flush()
        except RecordingError as exc:
            self._failed(exc)

    def close(self) -> None:
        if self.recorder is not None:
            try:
                if self.foxglove is not None:
                    self.foxglove.finish()
                self.recorder.close(fsync=True)
            except RecordingError as exc:
                self._failed(exc)
        self.state = "stopped" if self.state != "failed" else "failed"
        try:
            self._status(time.monotonic_ns())
        except Exception:  # noqa: BLE001 - best effort at shutdown
            pass
        self.sub.close()
        self.pub.close()
        self.ctx.term()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.recorder")
    add_session_arguments(p)
    p.add_argument("--out", required=True, help="MCAP file to write")
    p.add_argument("--name", default="recorder", help="process name (its endpoint)")
    p.add_argument("--source", action="append", default=[], help="source URI (metadata)")
    p.add_argument("--created-by", default="groundstation record", help="metadata text")
    p.add_argument("--max-s", type=float, default=None, help="stop after this many seconds")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    args = _parser().parse_args(argv)
    stop = StopSignals()
    proc = RecorderProcess(
        session_from_args(args),
        args.out,
        load_settings(args.config, args.set),
        name=args.name,
        sources=args.source,
        created_by=args.created_by,
        foxglove=foxglove_hook(args.config, args.set),
    )
    return proc.run(stop, args.max_s)


if __name__ == "__main__":
    sys.exit(main())
