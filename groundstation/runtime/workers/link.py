"""The link process: the one owner of the firmware link (serial:// or udp://).

``python -m groundstation.runtime.workers.link --session ID --link URI [--wait-subscribers N]``

- waits (XPUB ready handshake) until ``N`` subscribers hold its data topics, then opens the link;
- publishes every chunk read on ``raw.mavlink`` (source and receive time = the read time), the
  samples :class:`~groundstation.acquisition.decoders.MavlinkStreamDecoder` makes of it,
  ``link.health`` and ``status`` every ``health_period_s``;
- asks for HIGHRES_IMU and ATTITUDE_QUATERNION at the configured rates (SET_MESSAGE_INTERVAL) at
  start, when the vehicle is first heard and after every reconnect; pings TIMESYNC and sends a
  GCS HEARTBEAT every second; answers the vehicle's own TIMESYNC requests;
- forwards each ``pilot.command`` as one MANUAL_CONTROL while ``enabled`` (nothing is sent
  otherwise, so the vehicle's own failsafe acts). A dedicated command thread blocks on the bus
  and writes at once (links allow one reader and concurrent writers), so a command waits
  neither for the 20 ms link read nor for telemetry publishing. It never repeats a command on
  its own, and drops a command older than ``--max-command-age-ms`` (default 200 ms, measured
  from the pilot's tick time ``source_ns`` on the shared monotonic clock): a stalled link never
  sends a stale backlog. 200 ms = the pilot's input stale window: a command may spend in transit
  at most as long as its input was allowed to age (10-minute soak on a loaded 2-core machine:
  1 of 15006 commands took > 100 ms from tick to link);
- reports unplug/replug (link events) on ``log`` and ``status``; bad bytes are counted by the
  decoder, never raised. SIGINT/SIGTERM stop it cleanly (exit 0);
- UDP links lock to the vehicle first heard or to ``acquisition.link_allow_peers``
  (:class:`firmware_bridge.link.peer.PeerLock`); with ``acquisition.signing_key_file`` every
  frame sent is MAVLink 2 signed. Status ``topics["security"]``: ``peer``, ``system_id``,
  ``rejected_peers``, ``rejected_from``, ``last_rejected`` (UDP), ``signing`` and
  ``rejected_signature`` (received frames with a bad signature).

Two threads: the main loop reads the link (20 ms timeout) and publishes; the command thread
forwards ``pilot.command``. Encoding and writing share one lock (the codec's sequence counter).
"""

from __future__ import annotations

import argparse
import collections
import sys
import threading
import time
from collections.abc import Sequence

import numpy as np
import zmq

from firmware_bridge.errors import BridgeError
from firmware_bridge.link import Link, LinkOptions, open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    CommandAck,
    Heartbeat,
    ManualControl,
    Record,
    SetMessageInterval,
    Timesync,
)
from firmware_bridge.mavlink.signing import load_signing_key
from groundstation.acquisition.decoders import MavlinkStreamDecoder
from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.runtime.session import (
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    load_settings,
    publish_log,
    session_from_args,
)

DATA_TOPICS = ("raw.mavlink", "samples.imu", "samples.attitude", "samples.pose")
TOPICS = (*DATA_TOPICS, "link.health", "status", "log")
HIGHRES_IMU_ID, ATTITUDE_QUATERNION_ID = 105, 31
MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE = 6, 8, 4
_READ_TIMEOUT_NS = 20_000_000
#: Default largest age (ns) of a ``pilot.command`` the link still forwards (tick -> write).
MAX_COMMAND_AGE_NS = 200_000_000
_COMMAND_POLL_MS = 50
_REPORTED_EVENTS = {
    "disconnected": "warning",
    "reconnect_failed": "warning",
    "reconnected": "info",
    "read_error": "warning",
    "write_error": "warning",
    "peer_rejected": "warning",
}


class LinkProcess:
    """The loop of the link process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        link_uri: str,
        settings: AcquisitionSettings,
        *,
        name: str = "link",
        wait_subscribers: int = 1,
        context: zmq.Context | None = None,
        max_command_age_ns: int = MAX_COMMAND_AGE_NS,
    ) -> None:
        self.session, self.uri, self.settings, self.name = session, link_uri, settings, name
        self.max_command_age_ns = int(max_command_age_ns)
        self.wait_subscribers = wait_subscribers
        self.ctx = context or zmq.Context()
        self.pub = Publisher(topics=TOPICS, context=self.ctx, **session.publisher_kwargs(name))
        self.sub = Subscriber(
            session.subscribe_endpoints(exclude=[name]), ["pilot.command"], context=self.ctx
        )
        s = settings
        self.decoder = MavlinkStreamDecoder(
            s.timesync_window, int(s.timesync_max_rtt_ms * 1e6), int(s.mocap_latency_ms * 1e6)
        )
        self.tx: MavlinkCodec | None = None  # made in run(): loading the key may fail
        self.link: Link | None = None
        self.rates = RateCounter()
        self.state = "starting"
        self.manual_sent = 0
        self.commands_received = 0
        self.commands_stale = 0
        self.commands_rejected = 0
        self.acks: list[tuple[int, int]] = []
        self._tx_lock = threading.Lock()
        self._warnings: collections.deque[str] = collections.deque(maxlen=100)
        self._cmd_stop = threading.Event()
        self._cmd_thread: threading.Thread | None = None

    # -- sending -----------------------------------------------------------------------------
    def _send(self, record: Record) -> None:
        """Encode and write one record (any thread); a bad value is counted and reported by the
        main loop (the publisher belongs to it), never raised."""
        link, tx = self.link, self.tx
        if link is None or tx is None:
            return
        try:
            with self._tx_lock:
                link.write(tx.encode(record))
        except BridgeError as exc:  # a value out of range: report, keep going
            self.commands_rejected += 1
            self._warnings.append(f"not sent: {exc.message}")

    def request_streams(self) -> None:
        """SET_MESSAGE_INTERVAL for HIGHRES_IMU and ATTITUDE_QUATERNION."""
        s = self.settings
        for mid, hz in (
            (HIGHRES_IMU_ID, s.imu_rate_hz),
            (ATTITUDE_QUATERNION_ID, s.attitude_rate_hz),
        ):
            self._send(SetMessageInterval(mid, int(round(1e6 / hz)), s.target_system, 1))

    def on_pilot_command(
        self, payload: dict, source_ns: int | None = None, now_ns: int | None = None
    ) -> bool:
        """Forward one ``pilot.command`` as MANUAL_CONTROL when enabled and fresh (``now_ns -
        source_ns <= max_command_age_ns``); else send nothing. Returns True when sent."""
        self.commands_received += 1
        if not payload.get("enabled"):
            return False
        if source_ns is not None:
            now_ns = time.monotonic_ns() if now_ns is None else now_ns
            if now_ns - source_ns > self.max_command_age_ns:
                self.commands_stale += 1
                return False
        self._send(
            ManualControl(
                int(payload["x"]),
                int(payload["y"]),
                int(payload["z"]),
                int(payload["r"]),
                int(payload["buttons"]),
                self.settings.target_system,
            )  # fmt: skip
        )
        self.manual_sent += 1
        return True

    def _command_loop(self) -> None:
        """The command thread: each ``pilot.command`` becomes one MANUAL_CONTROL at once."""
        while not self._cmd_stop.is_set():
            try:
                env = self.sub.recv(_COMMAND_POLL_MS)
            except zmq.ZMQError:
                return  # context terminated at shutdown
            if env is not None:
                try:
                    self.on_pilot_command(env.payload, env.header.source_ns)
                except (KeyError, TypeError, ValueError) as exc:
                    self.commands_rejected += 1
                    self._warnings.append(f"bad pilot.command {env.payload!r}: {exc}")

    # -- receiving ---------------------------------------------------------------------------
    def on_chunk(self, data: bytes, recv_ns: int) -> None:
        """Publish one chunk read at ``recv_ns`` and everything decoded from it."""
        self.pub.publish(
            "raw.mavlink",
            {"link": self.uri},
            {"data": np.frombuffer(data, np.uint8)},
            source_ns=recv_ns,
            recv_ns=recv_ns,
        )
        self.rates.add("raw.mavlink")
        heard_before = self.decoder.vehicle is not None
        records, samples = self.decoder.feed_records(data, recv_ns)
        for d in samples:
            self.pub.publish(d.topic, d.payload, d.arrays, source_ns=d.source_ns, recv_ns=d.recv_ns)
            self.rates.add(d.topic)
        for rec in records:
            if (
                isinstance(rec, Timesync)
                and rec.tc1 == 0
                and rec.system_id != self.settings.system_id
            ):
                self._send(Timesync(time.monotonic_ns(), rec.ts1))  # the vehicle syncs to us
            elif isinstance(rec, CommandAck):
                self.acks.append((rec.command, rec.result))
        if not heard_before and self.decoder.vehicle is not None:
            self.request_streams()  # the vehicle may have booted after our first request

    def _report_events(self) -> None:
        assert self.link is not None
        for ev in self.link.poll_events():
            level = _REPORTED_EVENTS.get(ev.kind)
            if level is None:
                continue
            publish_log(self.pub, self.name, level, f"link {ev.kind}: {ev.detail}")
            if ev.kind == "disconnected":
                self.state = "disconnected"
                self._status()
            elif ev.kind == "reconnected":
                self.state = "running"
                self.request_streams()
                self._status()

    def _connected(self) -> bool:
        return bool(getattr(self.link, "connected", True)) and self.state != "disconnected"

    def _status(self, now_ns: int | None = None) -> None:
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self.pub.publish("link.health", self.decoder.health_payload(self._connected()))
        topics = self.rates.snapshot(now_ns)
        topics["security"] = self.security_counters()
        topics["pilot.command"] = {
            "received": self.commands_received,
            "manual_control_sent": self.manual_sent,
            "stale_dropped": self.commands_stale,
            "rejected": self.commands_rejected,
        }
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": self.state,
                "topics": topics,
                "text": f"{self.uri}: {self.decoder.health.summary()}",
            },
        )

    def security_counters(self) -> dict:
        """Peer lock (UDP links) and signing counters for the status payload."""
        lock = getattr(self.link, "peer_lock", None)
        out: dict = lock.counters() if lock is not None else {}
        out["signing"] = bool(self.settings.signing_key_file)
        out["rejected_signature"] = int(self.decoder.codec.stats.rejected_signature)
        return out

    def _open(self) -> None:
        """Make the uplink codec (signed when a key is configured) and open the link."""
        s = self.settings
        key = load_signing_key(s.signing_key_file) if s.signing_key_file else None
        self.tx = MavlinkCodec(
            s.system_id, s.component_id, signing_key=key, sign_outgoing=key is not None
        )
        self.link = open_link(self.uri, LinkOptions(s.link_allow_peers, s.vehicle_system_id))

    # -- loop --------------------------------------------------------------------------------
    def run(self, stop: StopSignals | None = None, max_s: float | None = None) -> int:
        """Run until SIGINT/SIGTERM (or ``max_s`` seconds); returns the exit code."""
        stop = stop if stop is not None else StopSignals()
        try:
            try:
                self.pub.wait_for_subscribers(
                    self.wait_subscribers, DATA_TOPICS, self.settings.subscriber_timeout_s
                )
            except BusTimeoutError as exc:
                publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
            try:
                self._open()
            except BridgeError as exc:
                self.state = "failed"
                publish_log(self.pub, self.name, "error", exc.message, exc.hint)
                self.pub.publish(
                    "status",
                    {"process": self.name, "state": "failed", "topics": {}, "text": exc.message},
                )
                return 3
            self.state = "running"
            self._cmd_thread = threading.Thread(
                target=self._command_loop, name="pilot-commands", daemon=True
            )
            self._cmd_thread.start()
            self._loop(stop, max_s)
            return 0
        finally:
            self.close()

    def _loop(self, stop: StopSignals, max_s: float | None) -> None:
        s = self.settings
        ping_ns, health_ns = int(s.timesync_period_s * 1e9), int(s.health_period_s * 1e9)
        t0 = now = time.monotonic_ns()
        end = None if max_s is None else t0 + int(max_s * 1e9)
        self.request_streams()
        next_ping, next_beat, next_health = now, now, now + health_ns
        link = self.link
        assert link is not None
        while not stop and (end is None or now < end):
            if now >= next_ping:
                self._send(Timesync(0, time.monotonic_ns()))
                next_ping = max(next_ping + ping_ns, now)
            if now >= next_beat:
                self._send(Heartbeat(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE))
                next_beat = max(next_beat + 1_000_000_000, now)
            if now >= next_health:
                self._status(now)
                next_health = max(next_health + health_ns, now)
            wait = min(_READ_TIMEOUT_NS, next_ping - now, next_beat - now, next_health - now)
            data = link.read(max(0, wait) / 1e9)
            recv_ns = time.monotonic_ns()
            if data:
                self.on_chunk(data, recv_ns)
            while self._warnings:
                publish_log(self.pub, self.name, "warning", self._warnings.popleft())
            self._report_events()
            now = time.monotonic_ns()

    def close(self) -> None:
        self._cmd_stop.set()
        if self._cmd_thread is not None:
            self._cmd_thread.join(2.0)
        if self.link is not None:
            with self._tx_lock:
                link, self.link = self.link, None
            link.close()
        self.state = "stopped"
        try:
            self._status()
        except Exception:  # noqa: BLE001 - best effort at shutdown
            pass
        self.sub.close()
        self.pub.close()
        self.ctx.term()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.link")
    add_session_arguments(p)
    p.add_argument("--link", required=True, help="serial:///dev/ttyUSB0?baud=921600 or udp://...")
    p.add_argument("--name", default="link", help="process name (its endpoint in the session)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument("--max-s", type=float, default=None, help="stop after this many seconds")
    p.add_argument(
        "--max-command-age-ms",
        type=float,
        default=MAX_COMMAND_AGE_NS / 1e6,
        help="drop pilot.command older than this (tick time -> now), ms",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    args = _parser().parse_args(argv)
    stop = StopSignals()
    proc = LinkProcess(
        session_from_args(args),
        args.link,
        load_settings(args.config, args.set),
        name=args.name,
        wait_subscribers=args.wait_subscribers,
        max_command_age_ns=int(args.max_command_age_ms * 1e6),
    )
    return proc.run(stop, args.max_s)


if __name__ == "__main__":
    sys.exit(main())
