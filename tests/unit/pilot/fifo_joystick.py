"""Test helper: a FIFO that speaks the Linux joystick protocol like the kernel does.

The writer opens the FIFO (blocking until the device shell opens it for reading), sends the
JS_EVENT_INIT burst of its current state, then event bytes; a heartbeat thread can repeat the
current axis values (a FIFO has no presence signal, so a live stream must keep talking).
"""

from __future__ import annotations

import os
import threading
import time

from groundstation.pilot.jsdev import (
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JsEvent,
    encode_events,
    init_burst,
)

CENTRE = 0
FULL = 32767


class FifoJoystick:
    """Kernel-like js_event writer into a FIFO path."""

    def __init__(self, path: str, n_axes: int = 4, n_buttons: int = 8):
        self.path = path
        self.axes = [CENTRE] * n_axes
        self.buttons = [False] * n_buttons
        self.fd: int | None = None
        self.last_write_ns: int | None = None
        self._lock = threading.Lock()
        self._beat_stop = threading.Event()
        self._beat: threading.Thread | None = None

    def open(self, timeout: float = 5.0) -> FifoJoystick:
        """Open for writing (blocks until a reader opens) and send the INIT burst."""
        box: dict[str, int] = {}
        t = threading.Thread(target=lambda: box.setdefault("fd", os.open(self.path, os.O_WRONLY)))
        t.daemon = True
        t.start()
        t.join(timeout)
        if "fd" not in box:
            raise TimeoutError(f"no reader opened {self.path} within {timeout} s")
        self.fd = box["fd"]
        self._write(init_burst(self.axes, self.buttons, self._ms()))
        return self

    def _ms(self) -> int:
        return (time.monotonic_ns() // 1_000_000) & 0xFFFFFFFF

    def _write(self, data: bytes) -> None:
        with self._lock:
            if self.fd is None:
                raise RuntimeError("writer is closed")
            os.write(self.fd, data)
            self.last_write_ns = time.monotonic_ns()

    def set_axes(self, **values: int) -> None:
        """set_axes(a0=..., a3=...): move axes, one event each."""
        evs = []
        for key, v in values.items():
            n = int(key[1:])
            self.axes[n] = int(v)
            evs.append(JsEvent(self._ms(), int(v), JS_EVENT_AXIS, n))
        self._write(encode_events(evs))

    def buttons_to(self, pressed: dict[int, bool]) -> None:
        evs = []
        for n, down in pressed.items():
            self.buttons[n] = bool(down)
            evs.append(JsEvent(self._ms(), int(bool(down)), JS_EVENT_BUTTON, n))
        self._write(encode_events(evs))

    def repeat(self) -> None:
        """Re-send every axis value (a heartbeat for FIFO streams)."""
        self._write(
            encode_events(JsEvent(self._ms(), v, JS_EVENT_AXIS, n) for n, v in enumerate(self.axes))
        )

    def start_heartbeat(self, period_s: float = 0.01) -> None:
        self._beat_stop.clear()

        def beat() -> None:
            while not self._beat_stop.wait(period_s):
                try:
                    self.repeat()
                except (OSError, RuntimeError):
                    return

        self._beat = threading.Thread(target=beat, daemon=True)
        self._beat.start()

    def stop_heartbeat(self) -> int | None:
        """Stop repeating (the FIFO stays open); returns the time of the last write, ns."""
        self._beat_stop.set()
        if self._beat is not None:
            self._beat.join(2.0)
        return self.last_write_ns

    def close(self) -> int | None:
        """Close the writer end (the reader sees EOF); returns the last write time, ns."""
        self.stop_heartbeat()
        with self._lock:
            if self.fd is not None:
                os.close(self.fd)
                self.fd = None
        return self.last_write_ns
