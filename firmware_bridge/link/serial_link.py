"""Serial link (``serial:///dev/ttyUSB0?baud=921600``) that survives unplug/replug.

pyserial opens and configures the port (raw mode, baud, exclusive lock); reads block in
``select`` on the port and a wake pipe, then ``os.read`` whatever is there. On a read/write error
or a hang-up (readable but no data: the device vanished) the link records ``disconnected``,
closes the port and retries opening the same path with bounded exponential backoff (waits block
on an event with a timeout, so ``close`` interrupts them), then records ``reconnected``. The
``Link`` object stays the same throughout; callers just keep calling ``read``/``write``.

Query parameters: ``baud`` (921600), ``reconnect_min_s`` (0.05), ``reconnect_max_s`` (1.0),
``write_timeout_s`` (1.0).
"""

from __future__ import annotations

import os
import select
import threading
import time

import serial

from firmware_bridge.errors import LinkError
from firmware_bridge.link.base import Link, LinkOptions, ParsedUri

EXAMPLE = "serial:///dev/ttyUSB0?baud=921600"
_PARAMS = {"baud", "reconnect_min_s", "reconnect_max_s", "write_timeout_s"}
_READ_SIZE = 65536


class SerialLink(Link):
    """Serial port link opened from a parsed ``serial://`` URI.

    Attributes
    ----------
    path : str
        Device path (may be a symlink; re-resolved on every reconnect).
    baud : int
        Baud rate (pseudo-terminals ignore it).
    connected : bool
        Whether the port is open right now.
    reconnects, dropped_writes, bytes_read, bytes_written : int
        Counters.
    """

    def __init__(self, parsed: ParsedUri, options: LinkOptions | None = None) -> None:
        super().__init__(parsed)  # options (UDP peer lock) do not apply to a serial line
        if parsed.scheme != "serial":
            raise parsed.error("not a serial:// URI", EXAMPLE)
        if parsed.host:
            raise parsed.error(
                f"serial URIs need an absolute path (three slashes), got host {parsed.host!r}",
                EXAMPLE,
            )
        if not parsed.path or parsed.path == "/":
            raise parsed.error("no device path", EXAMPLE)
        unknown = set(parsed.query) - _PARAMS
        if unknown:
            raise parsed.error(
                f"unknown parameter(s) {sorted(unknown)} (known: {sorted(_PARAMS)})", EXAMPLE
            )
        self.path = parsed.path
        self.baud = parsed.int_param("baud", 921600, example=EXAMPLE)
        self.reconnect_min_s = parsed.float_param("reconnect_min_s", 0.05, EXAMPLE)
        self.reconnect_max_s = max(
            self.reconnect_min_s, parsed.float_param("reconnect_max_s", 1.0, EXAMPLE)
        )
        self.write_timeout_s = parsed.float_param("write_timeout_s", 1.0, EXAMPLE)
        self.reconnects = 0
        self.dropped_writes = 0
        self.bytes_read = 0
        self.bytes_written = 0
        self._closed = threading.Event()
        self._io_lock = threading.RLock()  # held by the reader inside select/read
        self._write_lock = threading.RLock()  # held by writers; taken first when swapping ports
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._backoff_s = self.reconnect_min_s
        self._retry_at = 0.0
        self._failed_attempts = 0
        self._broken: tuple[serial.Serial, str] | None = None
        try:
            self._ser: serial.Serial | None = self._open()
        except (serial.SerialException, OSError, ValueError) as exc:
            self._close_pipe()
            raise LinkError(
                f"cannot open serial port {self.path} ({self.uri}): {exc}",
                hint="check the device exists (ls -l /dev/serial/by-id) and that you are in the "
                "dialout group",
            ) from exc
        self._emit("opened", self.path)

    # --- open / lose / reconnect --------------------------------------------------------

    def _open(self) -> serial.Serial:
        return serial.Serial(
            self.path,
            self.baud,
            timeout=0,
            write_timeout=self.write_timeout_s,
            exclusive=True,
        )

    @property
    def connected(self) -> bool:
        return self._ser is not None

    def _wake_reader(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # pipe full (reader already has a wake pending) or closed

    def _lost(self, ser: serial.Serial, reason: str) -> None:
        """Mark ``ser`` as gone (if still current), close it and schedule reconnection.

        Must not be called while another thread is blocked in ``select`` on the port (the reader
        holds ``_io_lock`` there); writers that cannot take ``_io_lock`` hand the loss to the
        reader through ``_broken`` and the wake pipe instead.
        """
        with self._write_lock:
            with self._io_lock:
                self._broken = None
                if self._ser is not ser:
                    return
                self._ser = None
                try:
                    ser.close()
                except (serial.SerialException, OSError):
                    pass
                self._backoff_s = self.reconnect_min_s
                self._retry_at = time.monotonic()
                self._failed_attempts = 0
        if not self._closed.is_set():
            self._emit("disconnected", f"{self.path}: {reason}")

    def _maybe_reconnect(self) -> bool:
        """One reopen attempt if one is due; True if the port is open afterwards."""
        if self._closed.is_set():
            return False
        if time.monotonic() < self._retry_at:
            return self._ser is not None
        with self._write_lock, self._io_lock:
            if self._ser is not None:
                return True
            try:
                ser = self._open()
            except (serial.SerialException, OSError, ValueError) as exc:
                self._failed_attempts += 1
                self._retry_at = time.monotonic() + self._backoff_s
                self._backoff_s = min(2.0 * self._backoff_s, self.reconnect_max_s)
                if self._failed_attempts == 1:
                    self._emit("reconnect_failed", f"{self.path}: {exc} (retrying)")
                return False
            self._ser = ser
            self.reconnects += 1
            attempts = self._failed_attempts + 1
        self._emit("reconnected", f"{self.path} after {attempts} attempt(s)")
        return True

    # --- I/O ----------------------------------------------------------------------------

    def read(self, timeout_s: float) -> bytes:
        """Bytes available within ``timeout_s`` s (``b""`` on timeout, while disconnected or
        after close). Read errors and hang-ups are reported as events and trigger reconnection."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        while not self._closed.is_set():
            ser = self._ser
            if ser is None:
                if self._maybe_reconnect():
                    continue
                now = time.monotonic()
                if now >= deadline:
                    return b""
                self._closed.wait(max(0.0, min(self._retry_at, deadline) - now))
                continue
            error: str | None = None
            data = b""
            with self._io_lock:
                if ser is not self._ser:
                    continue
                try:
                    fd = ser.fileno()
                    ready, _, _ = select.select(
                        [fd, self._wake_r], [], [], max(0.0, deadline - time.monotonic())
                    )
                    if self._wake_r in ready:
                        self._drain_wake()
                        broken = self._broken
                        if broken is not None and broken[0] is ser:
                            error = broken[1]
                            ready = [self._wake_r]
                    if fd in ready:
                        data = os.read(fd, _READ_SIZE)
                        if not data:
                            error = "device reports readiness to read but returned no data"
                    elif not ready:
                        return b""
                except (OSError, ValueError, serial.SerialException) as exc:
                    error = f"read failed: {exc}"
            if error is not None:
                if self._closed.is_set():
                    return b""
                self._lost(ser, error)
                continue
            if data:
                self.bytes_read += len(data)
                return data
            if time.monotonic() >= deadline:
                return b""
        return b""

    def _drain_wake(self) -> None:
        try:
            while os.read(self._wake_r, 64):
                pass
        except (BlockingIOError, OSError):
            pass

    def write(self, data: bytes) -> bool:
        """Write all of ``data``; while disconnected the bytes are dropped and counted
        (False)."""
        with self._write_lock:
            ser = self._ser
            if ser is None and not self._maybe_reconnect():
                self.dropped_writes += 1
                return False
            ser = self._ser
            assert ser is not None
            try:
                ser.write(data)
            except serial.SerialTimeoutException as exc:
                self.dropped_writes += 1
                self._emit("write_error", f"{self.path}: {exc}")
                return False
            except (serial.SerialException, OSError, ValueError) as exc:
                self.dropped_writes += 1
                self._emit("write_error", f"{self.path}: {exc}")
                if self._io_lock.acquire(blocking=False):  # no reader inside select
                    try:
                        self._lost(ser, f"write failed: {exc}")
                    finally:
                        self._io_lock.release()
                else:  # the reader holds the port: let it do the swap
                    self._broken = (ser, f"write failed: {exc}")
                    self._wake_reader()
                return False
            self.bytes_written += len(data)
            return True

    def close(self) -> None:
        """Close the port and wake a blocked reader; idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._wake_reader()
        with self._write_lock, self._io_lock:
            ser, self._ser = self._ser, None
            if ser is not None:
                try:
                    ser.close()
                except (serial.SerialException, OSError):
                    pass
            self._close_pipe()
        self._emit("closed", self.path)

    def _close_pipe(self) -> None:
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1
