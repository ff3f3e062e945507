"""Thin I/O shell: a reader thread between a :class:`Link` and the pure :class:`MavlinkCodec`.

The reader thread blocks in ``link.read`` (select with a timeout), stamps each chunk with
``time.monotonic_ns()``, decodes it, feeds :class:`LinkHealth` and :class:`TimesyncEstimator`,
answers the vehicle's TIMESYNC requests, sends our own TIMESYNC pings and GCS heartbeat on
schedule, and hands every record to the callback. Nothing that goes wrong in a read, a decode or
the callback stops the thread: it is recorded in ``events`` and counted.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable

from firmware_bridge.link.base import Link, LinkEvent
from firmware_bridge.mavlink.codec import MavlinkCodec
from firmware_bridge.mavlink.health import LinkHealth
from firmware_bridge.mavlink.messages import (
    Heartbeat,
    Record,
    SetMessageInterval,
    Timesync,
)
from firmware_bridge.mavlink.timesync import TimesyncEstimator

MAV_TYPE_GCS = 6
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
_MAX_PENDING_PINGS = 64


class MavlinkEndpoint:
    """Reader thread + thread-safe sender over one link.

    Parameters
    ----------
    link : Link
        An open link (``open_link(uri)``); the endpoint does not close it.
    codec : MavlinkCodec
        Codec with our system/component id and signing settings.
    health : LinkHealth, optional
        Fed with every chunk and record (a new one by default).
    timesync : TimesyncEstimator, optional
        Fed with replies to our pings (a new one by default).
    read_timeout_s : float
        Longest blocking read; bounds how late ``stop`` and scheduled sends can be.
    timesync_period_s, heartbeat_period_s : float or None
        Periods of our TIMESYNC pings and GCS HEARTBEAT (None: never send).
    target_system, target_component : int
        Vehicle address for commands; follows the first vehicle HEARTBEAT heard.
    """

    def __init__(
        self,
        link: Link,
        codec: MavlinkCodec,
        health: LinkHealth | None = None,
        timesync: TimesyncEstimator | None = None,
        *,
        read_timeout_s: float = 0.05,
        timesync_period_s: float | None = 1.0,
        heartbeat_period_s: float | None = 1.0,
        target_system: int = 1,
        target_component: int = 1,
    ) -> None:
        self.link = link
        self.codec = codec
        self.health = health if health is not None else LinkHealth()
        self.timesync = timesync if timesync is not None else TimesyncEstimator()
        self.read_timeout_s = read_timeout_s
        self.timesync_period_ns = (
            None if timesync_period_s is None else int(timesync_period_s * 1e9)
        )
        self.heartbeat_period_ns = (
            None if heartbeat_period_s is None else int(heartbeat_period_s * 1e9)
        )
        self.target_system = target_system
        self.target_component = target_component
        self.vehicle_heard = False
        self.callback_errors = 0
        self.read_errors = 0
        self.records_received = 0
        self.reader_cpu_ns = 0
        self.reader_wall_ns = 0
        self._events: deque[LinkEvent] = deque(maxlen=1000)
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._callback: Callable[[Record], None] | None = None
        self._pending_pings: OrderedDict[int, None] = OrderedDict()

    # --- sending (any thread) -----------------------------------------------------------

    def send(self, record: Record) -> None:
        """Encode and write one record (thread-safe). Raises ProtocolError for bad values."""
        with self._send_lock:
            frame = self.codec.encode(record)
            self.link.write(frame)

    def request_message_interval(self, msg_id: int, hz: float) -> None:
        """Ask the vehicle to stream message ``msg_id`` at ``hz`` (<= 0: stop streaming it).

        Sends COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (param2 = interval in us, -1 disables).
        """
        interval_us = int(round(1e6 / hz)) if hz > 0 else -1
        self.send(
            SetMessageInterval(msg_id, interval_us, self.target_system, self.target_component)
        )

    def ping_timesync(self) -> None:
        """Send a TIMESYNC request stamped with our monotonic clock (tc1 = 0, ts1 = now ns)."""
        ts1 = time.monotonic_ns()
        with self._send_lock:
            self._pending_pings[ts1] = None
            while len(self._pending_pings) > _MAX_PENDING_PINGS:
                self._pending_pings.popitem(last=False)
            self.link.write(self.codec.encode(Timesync(0, ts1)))

    # --- reader thread ------------------------------------------------------------------

    @property
    def events(self) -> list[LinkEvent]:
        """Endpoint events (callback_error, read_error); link events are in ``link.events``."""
        return list(self._events)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self, callback: Callable[[Record], None] | None = None) -> None:
        """Start the reader thread; ``callback(record)`` runs in it for every decoded record."""
        if self.running:
            raise RuntimeError("MavlinkEndpoint already started")
        self._callback = callback
        self._stop.clear()
        self._thread = threading.Thread(
            target=self._run, name=f"mavlink-reader {self.link.uri}", daemon=True
        )
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the reader thread (returns within about ``read_timeout_s``)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                self._event("stop_timeout", f"reader still running after {timeout_s} s")
            self._thread = None

    def _event(self, kind: str, detail: str) -> None:
        self._events.append(LinkEvent(kind, detail, time.monotonic_ns()))

    def _run(self) -> None:
        cpu0, wall0 = time.thread_time_ns(), time.monotonic_ns()
        next_ping = next_beat = wall0
        while not self._stop.is_set():
            now = time.monotonic_ns()
            timeout_ns = int(self.read_timeout_s * 1e9)
            try:
                if self.timesync_period_ns is not None:
                    if now >= next_ping:
                        self.ping_timesync()
                        next_ping = now + self.timesync_period_ns
                    timeout_ns = min(timeout_ns, next_ping - now)
                if self.heartbeat_period_ns is not None:
                    if now >= next_beat:
                        self.send(
                            Heartbeat(MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID, 0, 0, MAV_STATE_ACTIVE)
                        )
                        next_beat = now + self.heartbeat_period_ns
                    timeout_ns = min(timeout_ns, next_beat - now)
                data = self.link.read(max(0, timeout_ns) / 1e9)
            except Exception as exc:  # a broken link must not kill the reader
                self.read_errors += 1
                self._event("read_error", f"{type(exc).__name__}: {exc}")
                self._stop.wait(self.read_timeout_s)
                continue
            if data:
                self._handle(data, time.monotonic_ns())
            self.reader_cpu_ns = time.thread_time_ns() - cpu0
            self.reader_wall_ns = time.monotonic_ns() - wall0

    def _handle(self, data: bytes, recv_ns: int) -> None:
        records = self.codec.decode(data, recv_ns)
        self.health.on_bytes(len(data), recv_ns)
        for rec in records:
            self.records_received += 1
            if isinstance(rec, Timesync):
                self._on_timesync(rec)
            elif isinstance(rec, Heartbeat) and not self.vehicle_heard:
                if rec.type != MAV_TYPE_GCS:
                    self.vehicle_heard = True
                    self.target_system, self.target_component = rec.system_id, rec.component_id
            self.health.on_record(rec, self.timesync.offset_ns)
            if self._callback is not None:
                try:
                    self._callback(rec)
                except Exception as exc:
                    self.callback_errors += 1
                    self._event("callback_error", f"{type(exc).__name__}: {exc}")
        self.health.on_stats(self.codec.stats)

    def _on_timesync(self, rec: Timesync) -> None:
        if rec.tc1 == 0:
            # The vehicle syncs to us: answer with our clock, echoing its ts1 (TIMESYNC spec).
            if rec.system_id != self.codec.system_id:
                try:
                    self.send(Timesync(time.monotonic_ns(), rec.ts1))
                except Exception as exc:
                    self._event("timesync_error", f"{type(exc).__name__}: {exc}")
            return
        with self._send_lock:
            ours = rec.ts1 in self._pending_pings
            if ours:
                del self._pending_pings[rec.ts1]
        if ours:
            self.timesync.observe(rec)
