"""Replay source: a recording's raw bytes through the live decoders, on the log clock.

``replay://flight.mcap?speed=1|X|max&start=S&end=S`` (times in seconds from the log start; see
:mod:`groundstation.acquisition.sources`).

- :func:`replay_decoded` (pure apart from reading the file): the raw channels (``raw.mavlink``,
  ``raw.natnet``) in log-time order, each channel through its own
  :class:`~groundstation.acquisition.decoders.MavlinkStreamDecoder` /
  :class:`~groundstation.acquisition.decoders.NatNetStreamDecoder` fed with the recorded receive
  time (``log_time``), exactly as the live processes fed them. NatNet version and Motive up axis
  come from the channel metadata when recorded, else from the settings.
- :func:`iter_replay`: the same as bus envelopes, in process, no sockets (the offline pipeline).
- :class:`ReplaySource` / ``python -m groundstation.acquisition.replay``: publishes raw + samples
  on the bus. ``speed=X`` paces against absolute deadlines ``wall0 + (log_time - t0) / X`` (a
  late wake-up never shifts later deadlines); ``speed=max`` runs unpaced under credit flow control
  (``groundstation.bus.flow``), so it never outruns a subscriber that registered for credit. The
  last lossless message is a ``log`` line ``"replay finished ..."``: a subscriber that sees it has
  every sample before it (one socket, ordered).

Seeking with ``start`` starts the decoders cold: MAVLink resynchronises on the next frame and
``t_station_ns`` falls back to the receive time until the next TIMESYNC reply in the log.
Determinism: same file, same window, same settings -> identical samples, at any speed.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import zmq

from firmware_bridge.frames import AxisConvention
from groundstation.acquisition import layout
from groundstation.acquisition.decoders import (
    Decoded,
    MavlinkStreamDecoder,
    NatNetStreamDecoder,
)
from groundstation.acquisition.reader import ChannelInfo, RecordedMessage, Recording, open_recording
from groundstation.acquisition.session import (
    REPLAY_PUBLISHER,
    AcquisitionSettings,
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    load_settings,
    natnet_version_tuple,
    publish_log,
)
from groundstation.bus.envelope import Envelope
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher
from groundstation.errors import GroundstationError

RAW_TOPICS = (layout.RAW_MAVLINK_TOPIC, layout.RAW_NATNET_TOPIC)
SAMPLE_TOPICS = ("samples.imu", "samples.attitude", "samples.pose")
DATA_TOPICS = (*RAW_TOPICS, *SAMPLE_TOPICS)
TOPICS = (*DATA_TOPICS, "status", "log")
FINISHED = "replay finished"


class ReplayError(GroundstationError):
    """A replay cannot start (bad window, no raw channels); the message names the problem."""


@dataclass(frozen=True)
class Window:
    """Log-time window of a replay, ns (``end_ns`` exclusive; None = open)."""

    start_ns: int | None
    end_ns: int | None


def window_ns(rec: Recording, start_s: float | None, end_s: float | None) -> Window:
    """Seconds from the log start -> absolute log-time window (ns)."""
    t0 = rec.summary.start_ns
    if t0 is None:
        return Window(None, None)
    for name, v in (("start", start_s), ("end", end_s)):
        if v is not None and (not math.isfinite(v) or v < 0):
            raise ReplayError(
                f"replay {name}={v!r} s must be a finite time >= 0 from the log start"
            )
    if start_s is not None and end_s is not None and end_s <= start_s:
        raise ReplayError(f"replay end={end_s} s must come after start={start_s} s")
    return Window(
        None if start_s is None else t0 + layout.seconds_to_ns(start_s),
        None if end_s is None else t0 + layout.seconds_to_ns(end_s),
    )


class _Decoders:
    """One decoder per raw channel, configured from its metadata and the settings."""

    def __init__(self, settings: AcquisitionSettings):
        self.settings = settings
        self.by_channel: dict[int, MavlinkStreamDecoder | NatNetStreamDecoder] = {}

    def get(self, ch: ChannelInfo) -> MavlinkStreamDecoder | NatNetStreamDecoder:
        dec = self.by_channel.get(ch.id)
        if dec is None:
            s = self.settings
            latency = int(s.mocap_latency_ms * 1e6)
            if ch.topic == layout.RAW_MAVLINK_TOPIC:
                dec = MavlinkStreamDecoder(
                    s.timesync_window, int(s.timesync_max_rtt_ms * 1e6), latency
                )
            else:
                version = ch.metadata.get(layout.KEY_NATNET_VERSION, s.natnet_version)
                up = ch.metadata.get(layout.KEY_MOTIVE_UP, s.motive_up)
                convention = AxisConvention(up, s.quaternion_order)  # type: ignore[arg-type]
                dec = NatNetStreamDecoder(natnet_version_tuple(version), convention, latency)
            self.by_channel[ch.id] = dec
        return dec


def replay_decoded(
    rec: Recording, window: Window, settings: AcquisitionSettings | None = None
) -> Iterator[tuple[RecordedMessage, list[Decoded]]]:
    """Raw messages of ``rec`` in log-time order within ``window``, each with its samples."""
    decoders = _Decoders(settings or AcquisitionSettings())
    for msg in rec.messages(RAW_TOPICS, window.start_ns, window.end_ns):
        yield msg, decoders.get(msg.channel).feed(msg.data, msg.log_time_ns)


def raw_fields(msg: RecordedMessage) -> tuple[dict, dict]:
    """Payload and arrays of the bus message that carried a recorded raw chunk."""
    source = msg.channel.metadata.get(layout.KEY_SOURCE, "")
    payload: dict = {layout.RAW_SOURCE_FIELDS[msg.topic]: source}
    if msg.topic == layout.RAW_NATNET_TOPIC:
        for key in (layout.KEY_NATNET_VERSION, layout.KEY_MOTIVE_UP):
            if key in msg.channel.metadata:
                payload[key] = msg.channel.metadata[key]
    return payload, {layout.RAW_DATA_ARRAY: np.frombuffer(msg.data, np.uint8)}


def iter_replay(
    path: str,
    start: float | None = None,
    end: float | None = None,
    settings: AcquisitionSettings | None = None,
    *,
    include_raw: bool = False,
) -> Iterator[Envelope]:
    """Decoded samples of a recording as bus envelopes, in process (no sockets).

    Parameters
    ----------
    path : str
        MCAP recording (a truncated one is read up to its last complete chunk).
    start, end : float, optional
        Window in seconds from the log start (``end`` exclusive).
    settings : AcquisitionSettings, optional
        Decoder settings (defaults when None); must match the bus replay's to compare.
    include_raw : bool
        Also yield the raw chunks as ``raw.*`` envelopes, before the samples they produced.

    Yields
    ------
    Envelope
        Sequence numbers count per topic from 0 (origin 0), as a fresh publisher would.
    """
    seqs: dict[str, int] = {}

    def number(d: Decoded) -> Envelope:
        seq = seqs.get(d.topic, 0)
        seqs[d.topic] = seq + 1
        return d.envelope(seq)

    with open_recording(path) as rec:
        for msg, decoded in replay_decoded(rec, window_ns(rec, start, end), settings):
            if include_raw:
                payload, arrays = raw_fields(msg)
                yield number(
                    Decoded(msg.topic, payload, arrays, msg.publish_time_ns, msg.log_time_ns)
                )
            for d in decoded:
                yield number(d)


class ReplaySource:
    """Publish a recording on the bus (see the module docstring).

    Parameters
    ----------
    path : str
        Recording.
    session : Session
        Endpoints; binds as ``name``.
    speed : float
        Times real time; ``math.inf`` = as fast as the flow-controlled subscribers allow.
    start, end : float, optional
        Window, seconds from the log start.
    wait_subscribers : int
        Subscriptions to wait for before the first message (XPUB handshake).
    flow_consumers : int
        With speed=max: subscribers that registered for credit to wait for.
    """

    def __init__(
        self,
        path: str,
        session: Session,
        settings: AcquisitionSettings,
        speed: float = math.inf,
        start: float | None = None,
        end: float | None = None,
        *,
        name: str = REPLAY_PUBLISHER,
        wait_subscribers: int = 1,
        flow_consumers: int = 1,
        context: zmq.Context | None = None,
    ) -> None:
        if not speed > 0:
            raise ReplayError(f"replay speed={speed!r} must be > 0 (or max)")
        self.path, self.settings, self.speed = path, settings, speed
        self.start, self.end, self.name = start, end, name
        self.wait_subscribers, self.flow_consumers = wait_subscribers, flow_consumers
        self.ctx = context or zmq.Context()
        paced = math.isfinite(speed)
        self.pub = Publisher(
            topics=TOPICS,
            context=self.ctx,
            flow_window=None if paced else settings.replay_flow_window,
            flow_endpoint=session.flow_endpoint(name),
            flow_timeout_s=60.0,
            linger_ms=30_000,
            **session.publisher_kwargs(name),
        )
        self.rates = RateCounter()
        self.published = 0

    def _wait(self) -> None:
        timeout = self.settings.subscriber_timeout_s
        deadline = time.monotonic() + timeout
        while True:
            counts = self.pub.subscriber_counts()
            if all(counts[t] >= self.wait_subscribers for t in SAMPLE_TOPICS):
                break
            if time.monotonic() > deadline:
                raise BusTimeoutError(f"replay: subscribers {counts} after {timeout} s")
            time.sleep(0.01)
        if self.pub.flow is not None and self.flow_consumers > 0:
            self.pub.flow.wait_for_consumers(
                self.flow_consumers, max(0.0, deadline - time.monotonic())
            )

    def _status(self, state: str, text: str) -> None:
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": state,
                "topics": self.rates.snapshot(time.monotonic_ns()),
                "text": text,
            },
        )

    def run(self, stop: StopSignals | None = None) -> int:
        """Publish the whole window; returns 0 when done (or stopped by a signal)."""
        try:
            try:
                self._wait()
            except BusTimeoutError as exc:
                publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
            with open_recording(self.path) as rec:
                window = window_ns(rec, self.start, self.end)
                t0 = window.start_ns if window.start_ns is not None else rec.summary.start_ns
                self._publish_all(rec, window, t0 or 0, stop)
            return 0
        finally:
            self.pub.close()
            self.ctx.term()

    def _publish_all(self, rec: Recording, window: Window, t0: int, stop) -> None:
        pub, paced = self.pub, math.isfinite(self.speed)
        wall0 = time.monotonic_ns()
        next_status = wall0
        for msg, decoded in replay_decoded(rec, window, self.settings):
            if stop:
                break
            if paced:  # absolute deadline on the log clock
                deadline = wall0 + int((msg.log_time_ns - t0) / self.speed)
                while (delay := deadline - time.monotonic_ns()) > 0 and not stop:
                    time.sleep(min(delay / 1e9, 0.05))
            payload, arrays = raw_fields(msg)
            pub.publish(
                msg.topic, payload, arrays, source_ns=msg.publish_time_ns, recv_ns=msg.log_time_ns
            )
            self.rates.add(msg.topic)
            for d in decoded:
                pub.publish(d.topic, d.payload, d.arrays, source_ns=d.source_ns, recv_ns=d.recv_ns)
                self.rates.add(d.topic)
            self.published += 1 + len(decoded)
            now = time.monotonic_ns()
            if now >= next_status:
                self._status("running", f"{self.path} at speed {self.speed}")
                next_status = now + 1_000_000_000
        wall = (time.monotonic_ns() - wall0) / 1e9
        text = f"{FINISHED}: {self.published} messages in {wall:.3f} s wall"
        publish_log(pub, self.name, "info", text)
        self._status("finished", text)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.acquisition.replay")
    add_session_arguments(p)
    p.set_defaults(publishers=REPLAY_PUBLISHER)
    p.add_argument("--uri", required=True, help="replay://flight.mcap?speed=1|X|max&start=S&end=S")
    p.add_argument("--name", default=REPLAY_PUBLISHER, help="process name (its endpoint)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument(
        "--flow-consumers", type=int, default=None, help="credit consumers (default: the same)"
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: ``python -m groundstation.acquisition.replay --session ID --uri replay://...``"""
    from groundstation.acquisition.session import session_from_args
    from groundstation.acquisition.sources import parse_replay_uri

    args = _parser().parse_args(argv)
    stop = StopSignals()
    opts = parse_replay_uri(args.uri)
    src = ReplaySource(
        opts.path,
        session_from_args(args),
        load_settings(args.config, args.set),
        opts.speed,
        opts.start_s,
        opts.end_s,
        name=args.name,
        wait_subscribers=args.wait_subscribers,
        flow_consumers=args.wait_subscribers
        if args.flow_consumers is None
        else args.flow_consumers,
    )
    return src.run(stop)


if __name__ == "__main__":
    sys.exit(main())
