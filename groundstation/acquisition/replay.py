"""Replay source: a recording's raw bytes through the live decoders, on the log clock.

``replay://flight.mcap?speed=1|X|max&start=S&end=S`` (times in seconds from the log start; see
:mod:`groundstation.runtime.sources`).

- :func:`replay_decoded` (pure apart from reading the file): the raw channels (``raw.mavlink``,
  ``raw.natnet``) in log-time order, each channel through its own
  :class:`~groundstation.acquisition.decoders.MavlinkStreamDecoder` /
  :class:`~groundstation.acquisition.decoders.NatNetStreamDecoder` fed with the recorded receive
  time (``log_time``), exactly as the live processes fed them. NatNet version and Motive up axis
  come from the channel metadata when recorded, else from the settings.
- :func:`iter_replay`: the same as bus envelopes, in process, no sockets (the offline pipeline).
- :class:`~groundstation.runtime.workers.replay.ReplaySource` / ``python -m
  groundstation.runtime.workers.replay``: publishes raw + samples on the bus. ``speed=X`` paces
  against absolute deadlines ``wall0 + (log_time - t0) / X`` (a late wake-up never shifts later
  deadlines); ``speed=max`` runs unpaced under credit flow control (``groundstation.bus.flow``),
  so it never outruns a subscriber that registered for credit. The last lossless message is a
  ``log`` line ``"replay finished ..."``: a subscriber that sees it has every sample before it
  (one socket, ordered).

Seeking with ``start`` starts the decoders cold: MAVLink resynchronises on the next frame and
``t_station_ns`` falls back to the receive time until the next TIMESYNC reply in the log.
Determinism: same file, same window, same settings -> identical samples, at any speed.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from firmware_bridge.frames import AxisConvention
from groundstation.acquisition import layout
from groundstation.acquisition.decoders import (
    Decoded,
    MavlinkStreamDecoder,
    NatNetStreamDecoder,
)
from groundstation.acquisition.reader import ChannelInfo, RecordedMessage, Recording
from groundstation.acquisition.segments import open_session as open_recording  # segments as one
from groundstation.acquisition.settings import AcquisitionSettings, natnet_version_tuple
from groundstation.bus.envelope import Envelope
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
