"""Pure stream decoders: raw wire bytes + station receive time -> bus samples.

The live link/mocap processes and the replay source run *these* classes on the *same* bytes with
the *same* receive times, so a replay reproduces the live samples exactly (no sockets, threads,
files or clock reads here; time comes in with the data).

Time axis of the detector (``t_station_ns``, station monotonic clock, integer ns)
---------------------------------------------------------------------------------
Every sample keeps three times:

- header ``source_ns``: the source's own clock (firmware ``time_usec``/``time_boot_ms`` for
  IMU and attitude, Motive's frame timestamp for poses);
- header ``recv_ns``: station monotonic receive time of the bytes that completed the sample;
- payload ``t_station_ns``: the time the detector and the aligner use.

  * IMU / attitude: ``source_ns - offset`` where ``offset`` (vehicle - station) is the current
    estimate of a :class:`~firmware_bridge.mavlink.timesync.TimesyncEstimator` fed from the
    TIMESYNC *replies found in the received byte stream* (``tc1`` vehicle time, ``ts1`` our
    request time echoed, the chunk's receive time as ``t3``; NTP formula in that module). Before
    the first accepted round trip: ``recv_ns``. Since the estimator only sees recorded bytes, a
    replay recomputes the same mapping sample by sample.
  * pose: ``recv_ns - mocap_latency_ns`` (the mocap clock is not synchronised; a constant
    configured latency is compensated here, so the aligner runs with ``latency_ns = 0``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from firmware_bridge.frames import (
    AxisConvention,
    AxisError,
    motive_pose_to_world,
    ned_to_enu,
    quat_ned_frd_to_enu_flu,
)
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.health import LinkHealth
from firmware_bridge.mavlink.messages import (
    AttitudeSample,
    Heartbeat,
    ImuSample,
    MocapPose,
    Record,
    Timesync,
)
from firmware_bridge.mavlink.timesync import TimesyncEstimator
from firmware_bridge.natnet import (
    SUPPORTED_VERSIONS,
    FrameOfData,
    NatNetParseError,
    ServerInfo,
    parse_packet,
)
from groundstation.bus.envelope import Envelope, Header
from groundstation.bus.topics import TOPICS

MAV_TYPE_GCS = 6
_NAN3 = (math.nan,) * 3
_NAN4 = (math.nan,) * 4
#: Header times are int64 ns on the bus: a sample whose time does not fit (a corrupt or forged
#: HIGHRES_IMU time_usec up to 2**64-1 us, a NatNet timestamp of 1e291 s) is never published.
INT64_MAX = 2**63 - 1
_MAX_TIMESTAMP_S = INT64_MAX / 1e9


def in_int64(*values: int) -> bool:
    """True if every value fits a signed 64-bit integer (bus header and payload times)."""
    return not values or (-INT64_MAX - 1 <= min(values) and max(values) <= INT64_MAX)


@dataclass(frozen=True, eq=False)
class Decoded:
    """One message a decoder produced, before the publisher numbers it.

    Attributes
    ----------
    topic : str
        Bus topic (``samples.imu``, ``samples.attitude``, ``samples.pose``).
    payload : dict
        JSON payload (``t_station_ns``, ...).
    arrays : dict of str to ndarray
        float64 arrays, see ``groundstation.bus.topics``.
    source_ns, recv_ns : int
        Header times (source clock; station receive time), ns.
    """

    topic: str
    payload: dict[str, Any]
    arrays: dict[str, np.ndarray]
    source_ns: int
    recv_ns: int

    def envelope(self, seq: int = 0, origin: int = 0) -> Envelope:
        """The bus envelope with sequence number ``seq``."""
        t = TOPICS[self.topic]
        header = Header(t.type, t.schema_version, seq, self.source_ns, self.recv_ns, origin)
        return Envelope(self.topic, header, dict(self.payload), dict(self.arrays))


def content_key(msg: Decoded | Envelope) -> tuple:
    """What "the same decoded sample" means: topic, both header times, payload and array
    bytes (dtype and shape included); sequence numbers and publisher origin are left out."""
    if isinstance(msg, Envelope):
        topic, src, rcv = msg.topic, msg.header.source_ns, msg.header.recv_ns
    else:
        topic, src, rcv = msg.topic, msg.source_ns, msg.recv_ns
    arrays = tuple(
        (k, a.dtype.str, a.shape, np.ascontiguousarray(a).tobytes())
        for k, a in sorted(msg.arrays.items())
    )
    return topic, src, rcv, json.dumps(msg.payload, sort_keys=True), arrays


@dataclass
class StreamCounters:
    """Counters of one stream decoder (cumulative).

    Attributes
    ----------
    chunks, bytes : int
        Raw chunks / bytes fed.
    samples : dict of str to int
        Decoded messages per topic.
    bad : int
        Undecodable input units (NatNet datagrams that failed to parse; MAVLink damage is in
        the codec's ``DecodeStats``).
    nonfinite : int
        Samples dropped because a value was NaN/inf (counted, never published).
    ignored : int
        Valid messages that map to no sample (server info, unknown NatNet messages, ...).
    out_of_range : int
        Samples whose time does not fit int64 ns (MAVLink: dropped; NatNet: the pose is kept
        with source time 0, its station time comes from the receive time).
    refused_versions : int
        NatNet server info announcing a bitstream version this decoder cannot read (ignored:
        switching to it would stop all mocap).
    version_changes : int
        NatNet server info that changed the bitstream version after frames were decoded (each
        also appended to ``NatNetStreamDecoder.events``).
    """

    chunks: int = 0
    bytes: int = 0
    samples: dict[str, int] = field(default_factory=dict)
    bad: int = 0
    nonfinite: int = 0
    ignored: int = 0
    out_of_range: int = 0
    refused_versions: int = 0
    version_changes: int = 0

    def count(self, topic: str) -> None:
        self.samples[topic] = self.samples.get(topic, 0) + 1


def _finite(*values: tuple[float, ...]) -> bool:
    return all(all(map(math.isfinite, vs)) for vs in values)


class MavlinkStreamDecoder:
    """Firmware byte stream -> ``samples.imu`` / ``samples.attitude`` (and ``samples.pose`` from
    ATT_POS_MOCAP), with link health counters and the stream-fed TIMESYNC estimate.

    Parameters
    ----------
    timesync_window : int
        Minimum-RTT window of the TIMESYNC filter.
    max_rtt_ns : int
        Round trips longer than this are rejected.
    mocap_latency_ns : int
        Subtracted from the receive time of ATT_POS_MOCAP poses.
    health_window_s : float
        Window of the rates reported by :meth:`health_payload`.
    """

    def __init__(
        self,
        timesync_window: int = 16,
        max_rtt_ns: int = 500_000_000,
        mocap_latency_ns: int = 0,
        health_window_s: float = 2.0,
    ) -> None:
        self.codec = MavlinkCodec()
        self.timesync = TimesyncEstimator(window=timesync_window, max_rtt_ns=max_rtt_ns)
        self.health = LinkHealth(window_s=health_window_s)
        self.mocap_latency_ns = int(mocap_latency_ns)
        self.counters = StreamCounters()
        self.rx_messages = 0
        self.last_heartbeat_ns: int | None = None
        self.vehicle: tuple[int, int] | None = None  # (system, component) of the first HEARTBEAT

    def t_station_ns(self, source_ns: int, recv_ns: int) -> int:
        """Firmware time -> station time through the current TIMESYNC offset (receive time
        before the first accepted round trip)."""
        off = self.timesync.offset_ns
        return recv_ns if off is None else source_ns - off

    def feed_records(self, data: bytes, recv_ns: int) -> tuple[list[Record], list[Decoded]]:
        """Decode one raw chunk read at ``recv_ns``; return the records and the samples.

        Never raises for bad bytes (damage is skipped and counted in ``codec.stats``).
        """
        recv_ns = int(recv_ns)
        c = self.counters
        c.chunks += 1
        c.bytes += len(data)
        records = self.codec.decode(bytes(data), recv_ns)
        self.health.on_bytes(len(data), recv_ns)
        out: list[Decoded] = []
        for rec in records:
            self.rx_messages += 1
            d = self._record(rec, recv_ns)
            if d is not None:
                c.count(d.topic)
                out.append(d)
            self.health.on_record(rec, self.timesync.offset_ns)
        self.health.on_stats(self.codec.stats)
        return records, out

    def feed(self, data: bytes, recv_ns: int) -> list[Decoded]:
        """Decode one raw chunk read at ``recv_ns``; return the samples it completed."""
        return self.feed_records(data, recv_ns)[1]

    def _record(self, rec: Record, recv_ns: int) -> Decoded | None:
        d = self._sample(rec, recv_ns)
        if d is not None and not in_int64(d.source_ns, d.recv_ns, d.payload["t_station_ns"]):
            self.counters.out_of_range += 1
            return None
        return d

    def _sample(self, rec: Record, recv_ns: int) -> Decoded | None:
        if isinstance(rec, ImuSample):
            if not _finite(rec.accel, rec.gyro):
                self.counters.nonfinite += 1
                return None
            src = rec.time_source_ns
            return Decoded(
                "samples.imu",
                {"t_station_ns": self.t_station_ns(src, recv_ns)},
                {"accel_mps2": np.array(rec.accel), "gyro_radps": np.array(rec.gyro)},
                src,
                recv_ns,
            )
        if isinstance(rec, AttitudeSample):
            q = np.array(rec.quaternion)
            # np.linalg.norm of a 1-D float vector is sqrt(q.dot(q)): the same bits, less overhead
            norm = math.sqrt(q.dot(q)) if _finite(rec.quaternion, rec.rates) else math.nan
            if not norm > 1e-12 or not math.isfinite(norm):  # zero, denormal or overflowing
                self.counters.nonfinite += 1
                return None
            src = rec.time_source_ns
            return Decoded(
                "samples.attitude",
                {"t_station_ns": self.t_station_ns(src, recv_ns)},
                {"q_wxyz": q / norm, "rates_radps": np.array(rec.rates)},
                src,
                recv_ns,
            )
        if isinstance(rec, Timesync):
            if rec.tc1 != 0:  # a reply to one of our pings: tc1 vehicle time, ts1 our t0
                self.timesync.add(rec.ts1, rec.tc1, recv_ns)
            return None
        if isinstance(rec, Heartbeat):
            if rec.type != MAV_TYPE_GCS:
                self.last_heartbeat_ns = recv_ns
                if self.vehicle is None:
                    self.vehicle = (rec.system_id, rec.component_id)
            return None
        if isinstance(rec, MocapPose):
            try:
                if not _finite(rec.position, rec.quaternion):
                    raise AxisError("non-finite pose")
                p = ned_to_enu(rec.position)
                q = quat_ned_frd_to_enu_flu(rec.quaternion)  # AxisError: zero/denormal norm
            except AxisError:
                self.counters.nonfinite += 1
                return None
            return Decoded(
                "samples.pose",
                {
                    "body_id": int(rec.component_id),
                    "valid": True,
                    "t_station_ns": recv_ns - self.mocap_latency_ns,
                },
                {"position_m": np.asarray(p, float), "q_wxyz": np.asarray(q, float)},
                rec.time_source_ns,
                recv_ns,
            )
        return None

    def health_payload(self, connected: bool) -> dict[str, Any]:
        """The ``link.health`` payload as of the last chunk fed."""
        st = self.codec.stats
        return {
            "connected": bool(connected),
            "rx_bytes": int(st.bytes),
            "rx_messages": int(self.rx_messages),
            "bad_frames": int(st.crc_errors + st.rejected_signature),
            "last_heartbeat_ns": self.last_heartbeat_ns,
            "lost_frames": int(st.lost),
            "garbage_bytes": int(st.garbage_bytes),
            "timesync_offset_ns": self.timesync.offset_ns,
            "timesync_rtt_ns": self.timesync.rtt_ns,
            "rates_hz": {k: round(v, 2) for k, v in sorted(self.health.rates().items())},
        }


class NatNetStreamDecoder:
    """NatNet datagrams -> ``samples.pose`` in the station's world frame.

    Parameters
    ----------
    version : (int, int)
        Bitstream version of frames of data; a SERVERINFO in the stream updates it.
    convention : AxisConvention
        Motive up axis and quaternion order.
    mocap_latency_ns : int
        Subtracted from the receive time to give ``t_station_ns``.
    """

    def __init__(
        self,
        version: tuple[int, int] = (4, 1),
        convention: AxisConvention | None = None,
        mocap_latency_ns: int = 0,
    ) -> None:
        self.version = tuple(version)
        self.convention = convention or AxisConvention()
        self.mocap_latency_ns = int(mocap_latency_ns)
        self.counters = StreamCounters()
        self.frames = 0
        self.last_error: str | None = None
        self.events: list[str] = []  # version changes and refusals, oldest first

    def _server_info(self, info: ServerInfo) -> None:
        """Follow a server's bitstream version, but never silently and never to one we cannot
        read (a spoofed 2.0 used to stop all mocap for the rest of the session)."""
        c = self.counters
        c.ignored += 1
        new = info.bitstream_version
        if new == self.version:
            return
        old = f"{self.version[0]}.{self.version[1]}"
        if new not in SUPPORTED_VERSIONS:
            c.refused_versions += 1
            self.events.append(
                f"NatNet server info announces unsupported version {new[0]}.{new[1]}: "
                f"still decoding {old}"
            )
            return
        if self.frames:
            c.version_changes += 1
            self.events.append(
                f"NATNET VERSION CHANGED {old} -> {new[0]}.{new[1]} after {self.frames} frames "
                f"(server info from {info.app_name!r})"
            )
        self.version = new

    def feed(self, data: bytes, recv_ns: int) -> list[Decoded]:
        """Decode one datagram received at ``recv_ns``: one pose per rigid body.

        Bad datagrams are counted (``counters.bad``, ``last_error``), never raised. Server info
        may change the bitstream version (see :meth:`_server_info`); who may send it is the
        link's job (:class:`firmware_bridge.natnet.peers.NatNetPeerPolicy`).
        """
        recv_ns = int(recv_ns)
        c = self.counters
        c.chunks += 1
        c.bytes += len(data)
        try:
            msg = parse_packet(data, self.version)  # type: ignore[arg-type]
        except NatNetParseError as exc:
            c.bad += 1
            self.last_error = exc.message
            return []
        if isinstance(msg, ServerInfo):
            self._server_info(msg)
            return []
        if not isinstance(msg, FrameOfData):
            c.ignored += 1
            return []
        self.frames += 1
        ts = msg.timestamp_s
        if math.isfinite(ts) and 0 <= ts < _MAX_TIMESTAMP_S:
            source_ns = min(int(round(ts * 1e9)), INT64_MAX)
        else:  # NaN, negative or beyond int64 ns (1e291 s raised OverflowError here)
            source_ns = 0
            c.out_of_range += 1
            self.last_error = f"NatNet frame {msg.frame_id}: timestamp {ts!r} s out of range"
        t_station_ns = recv_ns - self.mocap_latency_ns
        if not in_int64(recv_ns, t_station_ns):
            c.out_of_range += 1
            return []
        out = []
        up, order = self.convention.motive_up, self.convention.quaternion_order
        for body in msg.rigid_bodies:
            valid = bool(body.tracking_valid)
            # AxisConvention.to_world on one pose, in floats (same bits, a tenth of the time)
            world = motive_pose_to_world(body.position, body.orientation, up, order)
            if world is None or not _finite(*world):  # lost track: zeros or NaN on the wire
                p, q, valid = _NAN3, _NAN4, False
                c.nonfinite += 1
            else:
                p, q = world
            out.append(
                Decoded(
                    "samples.pose",
                    {"body_id": int(body.id), "valid": valid, "t_station_ns": t_station_ns},
                    {"position_m": np.array(p), "q_wxyz": np.array(q)},
                    source_ns,
                    recv_ns,
                )
            )
            c.count("samples.pose")
        return out
