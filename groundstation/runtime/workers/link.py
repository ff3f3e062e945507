"""The link process: the one owner of the firmware link (serial:// or udp://).

``python -m groundstation.runtime.workers.link --session ID --link URI [--wait-subscribers N]``

- opens the link, then waits (XPUB ready handshake) until ``N`` subscribers hold its data topics
  before it reads: the vehicle's bytes wait in the device's buffers meanwhile (opening a serial
  port flushes its input, so a restarted link opens first and loses only what arrived while no
  process held the port); a device that is missing or cannot be opened is not a crash: the
  process stays up with state
  ``no_device`` (the error in its status text, shown in upper case on the status line) and tries
  again every second, so plugging the radio in is enough. A ``serial://`` path that is a SITL's
  pseudo-terminal link (``sitl --link pty:/path``) whose SITL is gone is refused the same way (a
  freed ``/dev/pts/N`` may belong to another process by now);
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
  1 of 15006 commands took > 100 ms from tick to link). A command the transport could not send
  (no vehicle heard yet on a listening UDP link, a serial device gone) is counted as
  ``unsent``, not as sent;
- after a restart, measures the vehicle data it missed: the firmware-time gap between the last
  IMU sample the previous incarnation published (kept current in ``link.state``, a memory-mapped
  file of the session directory) and the first one it publishes (``restart_gap_s`` in its
  status, and a ``log`` warning);
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
import fcntl
import os
import sys
import threading
import time
from collections.abc import Sequence

import numpy as np
import zmq

from firmware_bridge.errors import BridgeError, LinkError
from firmware_bridge.link import Link, LinkOptions, open_link
from firmware_bridge.link.base import parse_uri
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
from groundstation.bus.pubsub import Subscriber
from groundstation.config import Config
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.statefile import StateFile
from groundstation.runtime.worker import Worker, worker_main

SAMPLE_TOPICS = ("samples.imu", "samples.attitude", "samples.pose")
DATA_TOPICS = ("raw.mavlink", *SAMPLE_TOPICS)
TOPICS = (*DATA_TOPICS, "link.health", "status", "log")
HIGHRES_IMU_ID, ATTITUDE_QUATERNION_ID = 105, 31
MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, MAV_STATE_ACTIVE = 6, 8, 4
_READ_TIMEOUT_NS = 20_000_000
#: Default largest age (ns) of a ``pilot.command`` the link still forwards (tick -> write).
MAX_COMMAND_AGE_NS = 200_000_000
_COMMAND_POLL_MS = 50
_REOPEN_S = 1.0
#: Longest ready handshake of a restarted link (its subscribers only reconnect), seconds.
RESTART_WAIT_S = 1.5
_REPORTED_EVENTS = {
    "disconnected": "warning",
    "reconnect_failed": "warning",
    "reconnected": "info",
    "read_error": "warning",
    "write_error": "warning",
    "peer_rejected": "warning",
}


def check_sitl_link(uri: str) -> None:
    """Refuse a ``serial://`` path that is a SITL pseudo-terminal link whose SITL is gone.

    ``groundstation sitl --link pty:/path`` makes ``/path`` a symlink to its ``/dev/pts/N`` and
    holds a lock on ``/path.lock`` while it runs. When that lock is free the SITL has exited and
    the ``/dev/pts/N`` it pointed to may have been handed to another process.

    Raises
    ------
    LinkError
        The link's SITL is gone.
    """
    p = parse_uri(uri)
    if p.scheme != "serial" or not p.path or not os.path.islink(p.path):
        return
    lock = p.path + ".lock"
    if not os.path.realpath(p.path).startswith("/dev/pts/") or not os.path.exists(lock):
        return
    try:
        fd = os.open(lock, os.O_RDONLY)
    except OSError:
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return  # the SITL holds it: alive
    finally:
        os.close(fd)
    raise LinkError(
        f"{p.path} is the link of a SITL that is no longer running (its pseudo-terminal "
        f"{os.path.realpath(p.path)} may belong to another process now)",
        hint="start the SITL again: groundstation sitl --link pty:" + p.path,
    )


class LinkProcess(Worker):
    """The loop of the link process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        link_uri: str,
        config: Config,
        *,
        name: str = "link",
        wait_subscribers: int = 1,
        context: zmq.Context | None = None,
        max_command_age_ns: int = MAX_COMMAND_AGE_NS,
        wait_samples: int | None = None,
    ) -> None:
        parse_uri(link_uri)  # a malformed URI is a configuration error, not a missing device
        super().__init__(session, config, name=name, topics=TOPICS, context=context)
        self.uri = link_uri
        self.settings = s = config.acquisition
        self.max_command_age_ns = int(max_command_age_ns)
        self.wait_subscribers = wait_subscribers
        self.wait_samples = wait_subscribers if wait_samples is None else wait_samples
        self.sub = Subscriber(
            session.subscribe_endpoints(exclude=[name]), ["pilot.command"], context=self.ctx
        )
        self.decoder = MavlinkStreamDecoder(
            s.timesync_window, int(s.timesync_max_rtt_ms * 1e6), int(s.mocap_latency_ms * 1e6)
        )
        self.tx: MavlinkCodec | None = None  # made in run(): loading the key may fail
        self.link: Link | None = None
        self.device_error: str | None = None
        self.manual_sent = 0
        self.commands_received = 0
        self.commands_stale = 0
        self.commands_rejected = 0
        self.commands_unsent = 0  # the transport dropped it (no peer / device yet)
        self.acks: list[tuple[int, int]] = []
        self.last_rx_ns: int | None = None
        self.last_imu_source_ns: int | None = None
        self.restart_gap_s: float | None = None
        self._previous_imu_ns: int | None = None
        self._state: StateFile | None = None
        self._tx_lock = threading.Lock()
        self._warnings: collections.deque[str] = collections.deque(maxlen=100)
        self._cmd_stop = threading.Event()
        self._cmd_thread: threading.Thread | None = None
        self._reopen_at = 0.0
        self._next_ping = self._next_beat = 0
        self.status_period_ns = int(s.health_period_s * 1e9)  # link.health rides with status

    # -- sending -----------------------------------------------------------------------------
    def _send(self, record: Record) -> bool:
        """Encode and write one record (any thread); True when the transport sent it. A bad
        value is counted and reported by the main loop (the publisher belongs to it), never
        raised."""
        link, tx = self.link, self.tx
        if link is None or tx is None:
            return False
        try:
            with self._tx_lock:
                return link.write(tx.encode(record))
        except BridgeError as exc:  # a value out of range: report, keep going
            self.commands_rejected += 1
            self._warnings.append(f"not sent: {exc.message}")
            return False

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
        sent = self._send(
            ManualControl(
                int(payload["x"]),
                int(payload["y"]),
                int(payload["z"]),
                int(payload["r"]),
                int(payload["buttons"]),
                self.settings.target_system,
            )  # fmt: skip
        )
        if sent:
            self.manual_sent += 1
        else:
            self.commands_unsent += 1
        return sent

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
        self.last_rx_ns = recv_ns
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
            if d.topic == "samples.imu":
                self._imu(int(d.source_ns))
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

    def _imu(self, source_ns: int) -> None:
        if self.last_imu_source_ns is None and self._previous_imu_ns is not None:
            gap = (source_ns - self._previous_imu_ns) / 1e9
            if 0 <= gap < 3600:  # same vehicle clock (a rebooted vehicle restarts its clock)
                self.restart_gap_s = round(gap, 4)
                self.log("info" if gap < 0.05 else "warning",
                         f"link restart: first vehicle IMU sample {gap:.3f} s (firmware time) "
                         "after the last one published before the restart")  # fmt: skip
        self.last_imu_source_ns = source_ns
        if self._state is not None:
            self._state.set(source_ns)

    def _report_events(self) -> None:
        assert self.link is not None
        for ev in self.link.poll_events():
            level = _REPORTED_EVENTS.get(ev.kind)
            if level is None:
                continue
            self.log(level, f"link {ev.kind}: {ev.detail}")
            if ev.kind == "disconnected":
                self.state = "disconnected"
                self.publish_status()
            elif ev.kind == "reconnected":
                self.state = "running"
                self.request_streams()
                self.publish_status()

    def _connected(self) -> bool:
        return (
            self.link is not None
            and bool(getattr(self.link, "connected", True))
            and self.state != "disconnected"
        )

    # -- state across restarts -----------------------------------------------------------------
    def _load_state(self) -> None:
        try:
            self._state = StateFile(os.path.join(self.session.directory, f"{self.name}.state"), 1)
        except OSError:
            return
        last = self._state.get()[0]
        self._previous_imu_ns = last if last > 0 else None

    # -- worker hooks --------------------------------------------------------------------------
    def setup(self) -> int | None:
        try:
            self._make_codec()
        except BridgeError as exc:
            self.log("error", exc.message, exc.hint)
            self.device_error = exc.message
            return 3
        self._load_state()
        self._try_open(request=False)  # first: the port buffers what arrives meanwhile
        # a restart waits briefly (its subscribers reconnect within ~0.1 s): the port's
        # buffers hold the vehicle's bytes for a few seconds only
        limit = RESTART_WAIT_S if self.incarnation > 0 else None
        if self.wait_ready(self.wait_subscribers, DATA_TOPICS, limit):
            self.wait_ready(self.wait_samples, SAMPLE_TOPICS, limit)  # monitor, detector
        self._cmd_thread = threading.Thread(
            target=self._command_loop, name="pilot-commands", daemon=True
        )
        self._cmd_thread.start()
        if self.link is not None:
            self.request_streams()
        return None

    def _try_open(self, request: bool = True) -> None:
        self._reopen_at = time.monotonic() + _REOPEN_S
        try:
            check_sitl_link(self.uri)
            s = self.settings
            link = open_link(self.uri, LinkOptions(s.link_allow_peers, s.vehicle_system_id))
        except BridgeError as exc:
            if self.device_error != exc.message:
                self.log("error", f"cannot open {self.uri}: {exc.message}", exc.hint)
            self.device_error = exc.message
            self.state = "no_device"
            return
        if self.device_error is not None:
            self.log("info", f"opened {self.uri}")
        self.device_error = None
        with self._tx_lock:
            self.link = link
        self.state = "running"
        now = time.monotonic_ns()
        self._next_ping = self._next_beat = now
        if request:
            self.request_streams()

    def step(self) -> None:
        if self.link is None:
            if time.monotonic() >= self._reopen_at:
                self._try_open()
            if self.link is None:
                time.sleep(0.05)
                return
        s, link = self.settings, self.link
        now = time.monotonic_ns()
        if now >= self._next_ping:
            self._send(Timesync(0, time.monotonic_ns()))
            self._next_ping = max(self._next_ping + int(s.timesync_period_s * 1e9), now)
        if now >= self._next_beat:
            self._send(Heartbeat(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE))
            self._next_beat = max(self._next_beat + 1_000_000_000, now)
        wait = min(_READ_TIMEOUT_NS, self._next_ping - now, self._next_beat - now,
                   self._next_status - now)  # fmt: skip
        data = link.read(max(0, wait) / 1e9)
        recv_ns = time.monotonic_ns()
        if data:
            self.on_chunk(data, recv_ns)
        while self._warnings:
            self.log("warning", self._warnings.popleft())
        self._report_events()

    def publish_status(self, now_ns: int | None = None) -> None:
        """``link.health`` and ``status`` (the health first: the status line reads both)."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self.pub.publish("link.health", self.decoder.health_payload(self._connected()))
        super().publish_status(now_ns)

    def status_topics(self, now_ns: int) -> dict:
        topics = self.rates.snapshot(now_ns)
        topics["security"] = self.security_counters()
        topics["pilot.command"] = {
            "received": self.commands_received,
            "manual_control_sent": self.manual_sent,
            "stale_dropped": self.commands_stale,
            "rejected": self.commands_rejected,
            "unsent": self.commands_unsent,
        }
        st = self.decoder.codec.stats
        topics["link"] = {
            "uri": self.uri,
            "connected": self._connected(),
            "device_error": self.device_error,
            "lost_frames": int(st.lost),
            "rx_messages": int(self.decoder.rx_messages),
            "silent_s": None if self.last_rx_ns is None
            else round((now_ns - self.last_rx_ns) / 1e9, 3),
            "restart_gap_s": self.restart_gap_s,
        }  # fmt: skip
        return topics

    def status_text(self) -> str:
        if self.device_error is not None:
            return f"{self.uri}: NO DEVICE: {self.device_error}"
        return f"{self.uri}: {self.decoder.health.summary()}"

    def security_counters(self) -> dict:
        """Peer lock (UDP links) and signing counters for the status payload."""
        lock = getattr(self.link, "peer_lock", None)
        out: dict = lock.counters() if lock is not None else {}
        out["signing"] = bool(self.settings.signing_key_file)
        out["rejected_signature"] = int(self.decoder.codec.stats.rejected_signature)
        return out

    def _make_codec(self) -> None:
        """The uplink codec, signed when a key is configured (raises BridgeError for a bad key)."""
        s = self.settings
        key = load_signing_key(s.signing_key_file) if s.signing_key_file else None
        self.tx = MavlinkCodec(
            s.system_id, s.component_id, signing_key=key, sign_outgoing=key is not None
        )

    def teardown(self) -> None:
        self._cmd_stop.set()
        if self._cmd_thread is not None:
            self._cmd_thread.join(2.0)
        if self.link is not None:
            with self._tx_lock:
                link, self.link = self.link, None
            link.close()
        if self._state is not None:
            self._state.close()
        self.sub.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.link")
    add_session_arguments(p)
    p.add_argument("--link", required=True, help="serial:///dev/ttyUSB0?baud=921600 or udp://...")
    p.add_argument("--name", default="link", help="process name (its endpoint in the session)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument("--wait-samples", type=int, default=None,
                   help="sample-topic subscribers to wait for (default: the same)")  # fmt: skip
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

    def build(args: argparse.Namespace) -> LinkProcess:
        return LinkProcess(
            session_from_args(args),
            args.link,
            worker_config(args),
            name=args.name,
            wait_subscribers=args.wait_subscribers,
            max_command_age_ns=int(args.max_command_age_ms * 1e6),
            wait_samples=args.wait_samples,
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
