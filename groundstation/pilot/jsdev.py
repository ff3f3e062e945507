"""Linux joystick device shell: a reader thread (thin I/O) over the pure codec in
:mod:`groundstation.pilot.jsevent`.

:class:`JoystickDevice` owns one path (``/dev/input/jsN`` or, in tests and replays, a FIFO). Its
reader thread blocks in ``select()`` with a timeout (``alive_period_ms``; no sleep polling),
applies events to the latest state and reports "alive" by the rule in
:mod:`groundstation.pilot.watchdog`. Device loss (EOF, ENODEV, ...) is recorded as a fault and
the device is reopened with bounded exponential backoff. The ioctls (JSIOCGAXES, JSIOCGBUTTONS,
JSIOCGNAME) are used where they work; a FIFO has none, so its name comes from a setting.
"""

from __future__ import annotations

import collections
import dataclasses
import errno
import fcntl
import logging
import os
import select
import stat
import threading
import time
from collections.abc import Callable

from groundstation.errors import GroundstationError
from groundstation.pilot.commander import InputSnapshot
from groundstation.pilot.jsevent import (  # noqa: F401 - re-exported for the shells and tests
    EVENT_SIZE,
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JS_EVENT_INIT,
    JSIOCGAXES,
    JSIOCGBUTTONS,
    JSIOCGNAME,
    JSIOCGVERSION,
    JsEvent,
    decode_events,
    encode_events,
    init_burst,
)

log = logging.getLogger(__name__)


class JoystickError(GroundstationError, OSError):
    """The joystick device cannot be used (bad path, not a joystick, timeout)."""


@dataclasses.dataclass
class DeviceStats:
    """Counters of the reader thread (read by the status line)."""

    events: int = 0
    bad_events: int = 0
    open_attempts: int = 0
    opens: int = 0
    timeouts: int = 0
    losses: int = 0
    read_errors: int = 0
    raw_dropped: int = 0


@dataclasses.dataclass(frozen=True)
class DeviceNotice:
    """A device-level happening for the recorder: "opened", "lost", "read_error", "open_failed"."""

    t_ns: int
    kind: str
    path: str
    text: str

    def to_dict(self) -> dict[str, object]:
        return dataclasses.asdict(self)


def _ioctl_info(fd: int) -> tuple[int | None, int | None, str | None]:
    """(axes, buttons, name) from the joystick ioctls, None where unavailable."""

    def get(req: int, size: int) -> bytes | None:
        try:
            return fcntl.ioctl(fd, req, bytes(size))
        except OSError:
            return None

    a, b, n = get(JSIOCGAXES, 1), get(JSIOCGBUTTONS, 1), get(JSIOCGNAME(128), 128)
    name = n.split(b"\0", 1)[0].decode("utf-8", "replace").strip() if n else None
    return (a[0] if a else None), (b[0] if b else None), (name or None)


class JoystickDevice:
    """Reader thread over one joystick path; :meth:`snapshot` gives the latest state.

    Parameters
    ----------
    path : str
        ``/dev/input/jsN`` or a FIFO/pipe path.
    name : str
        Name to use when the ioctl gives none (FIFO); a real device's own name wins.
    alive_period_ms : float
        select() timeout, ms.
    idle_is_alive : bool or None
        Count a quiet select timeout as proof of life. None: True for character devices, False
        for FIFOs/pipes/files (see :mod:`groundstation.pilot.watchdog`).
    reconnect_min_ms, reconnect_max_ms : float
        Bounded exponential backoff between reopen attempts.
    clock : callable
        Monotonic ns clock used to stamp alive reports (the shell's only clock).
    raw_capacity : int
        Bound on the queue of raw chunks kept for the recorder (:meth:`drain_raw`).
    """

    def __init__(
        self,
        path: str,
        *,
        name: str = "",
        alive_period_ms: float = 50.0,
        idle_is_alive: bool | None = None,
        reconnect_min_ms: float = 100.0,
        reconnect_max_ms: float = 2000.0,
        clock: Callable[[], int] = time.monotonic_ns,
        raw_capacity: int = 4096,
    ):
        self.path = path
        self.name_override = name
        self.alive_period_s = alive_period_ms / 1000.0
        self.idle_is_alive = idle_is_alive
        self.backoff_s = (reconnect_min_ms / 1000.0, reconnect_max_ms / 1000.0)
        self.clock = clock
        self.stats = DeviceStats()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._thread: threading.Thread | None = None
        self._raw: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=raw_capacity)
        self._notices: collections.deque[DeviceNotice] = collections.deque(maxlen=1024)
        self._barrier: list[threading.Event] = []
        # state guarded by _lock
        self._name = name
        self._connected = False
        self._alive_ns: int | None = None
        self._fault: str | None = None
        self._axes: dict[int, int] = {}
        self._buttons = 0
        self._generation = 0
        self.n_axes: int | None = None
        self.n_buttons: int | None = None
        self._idle_alive = bool(idle_is_alive)

    # -- public API -------------------------------------------------------------------------
    def start(self) -> JoystickDevice:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="joystick-reader", daemon=True)
            self._thread.start()
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout)
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> JoystickDevice:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        """The reader thread is running."""
        return self._thread is not None and self._thread.is_alive()

    def snapshot(self) -> InputSnapshot:
        """The latest state, copied under the lock."""
        with self._lock:
            return InputSnapshot(
                name=self._name,
                connected=self._connected,
                alive_ns=self._alive_ns,
                fault=self._fault,
                axes=dict(self._axes),
                buttons=self._buttons,
                generation=self._generation,
            )

    def drain_raw(self) -> list[tuple[int, bytes]]:
        """Raw chunks read since the last call, as (read time ns, bytes) for ``raw.pilot``."""
        out = []
        while self._raw:
            out.append(self._raw.popleft())
        return out

    def drain_notices(self) -> list[DeviceNotice]:
        out = []
        while self._notices:
            out.append(self._notices.popleft())
        return out

    def wait_connected(self, timeout: float) -> bool:
        """Wait (event-driven, via :meth:`barrier`) until the device is open and has been read."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            snap = self.snapshot()
            if snap.connected and snap.alive_ns is not None and snap.fault is None:
                return True
            self.barrier(min(0.2, max(0.0, deadline - time.monotonic())))
        return False

    def barrier(self, timeout: float = 2.0) -> bool:
        """Block until every byte written to the device before this call has been applied.

        The reader acknowledges when a zero-timeout select finds its descriptor empty (or, with
        the device closed, after its next reopen attempt; a stopping reader releases every
        waiter). Returns False on timeout.
        """
        ev = threading.Event()
        with self._lock:
            self._barrier.append(ev)
        self._wake()
        return ev.wait(timeout)

    # -- reader thread ----------------------------------------------------------------------
    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except OSError:
            pass

    def _notice(self, kind: str, text: str) -> None:
        self._notices.append(DeviceNotice(self.clock(), kind, self.path, text))
        level = {"opened": logging.INFO, "open_failed": logging.DEBUG}.get(kind, logging.WARNING)
        log.log(level, "joystick %s: %s", kind, text)

    def _open(self) -> int | None:
        self.stats.open_attempts += 1
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            with self._lock:
                self._connected = False
                self._fault = "device_lost"
            self._notice("open_failed", f"cannot open {self.path}: {exc.strerror}")
            return None
        is_chr = stat.S_ISCHR(os.fstat(fd).st_mode)
        n_axes, n_buttons, name = _ioctl_info(fd) if is_chr else (None, None, None)
        self._idle_alive = self.idle_is_alive if self.idle_is_alive is not None else is_chr
        with self._lock:
            self._connected = True
            # A fault stays until the first read proves the device is back (a FIFO opens fine
            # with no writer); a fresh alive report is needed from this open either way.
            self._alive_ns = None
            self._axes, self._buttons = {}, 0
            self._generation += 1
            self._name = name or self.name_override
            self.n_axes, self.n_buttons = n_axes, n_buttons
        self.stats.opens += 1
        self._notice(
            "opened",
            f"{self.path}: {self._name!r} ({n_axes if n_axes is not None else '?'} axes, "
            f"{n_buttons if n_buttons is not None else '?'} buttons)",
        )
        return fd

    def _lose(self, fd: int, kind: str, text: str) -> None:
        try:
            os.close(fd)
        except OSError:
            pass
        with self._lock:
            self._connected = False
            self._fault = kind
        if kind == "device_lost":
            self.stats.losses += 1
        else:
            self.stats.read_errors += 1
        self._notice(kind, text)

    def _apply(self, events: list[JsEvent]) -> None:
        with self._lock:
            for ev in events:
                kind = ev.kind
                if kind == JS_EVENT_AXIS:
                    self._axes[ev.number] = ev.value
                elif kind == JS_EVENT_BUTTON:
                    if ev.number < 32:
                        bit = 1 << ev.number
                        self._buttons = self._buttons | bit if ev.value else self._buttons & ~bit
                else:
                    self.stats.bad_events += 1
                    continue
                self.stats.events += 1

    def _mark_alive(self) -> None:
        with self._lock:
            self._alive_ns = self.clock()
            self._fault = None

    def _release_barriers(self, fd: int | None) -> None:
        with self._lock:
            if not self._barrier:
                return
        if fd is not None and select.select([fd], [], [], 0)[0]:
            return  # more bytes pending: acknowledge after reading them
        with self._lock:
            waiting, self._barrier = self._barrier, []
        for ev in waiting:
            ev.set()

    def _run(self) -> None:
        fd: int | None = None
        backoff = self.backoff_s[0]
        pending = b""
        try:
            while not self._stop.is_set():
                if fd is None:
                    fd = self._open()
                    pending = b""
                    if fd is None:
                        self._release_barriers(None)
                        self._stop.wait(backoff)
                        backoff = min(backoff * 2, self.backoff_s[1])
                        continue
                try:
                    ready = select.select([fd, self._wake_r], [], [], self.alive_period_s)[0]
                except (OSError, ValueError) as exc:
                    self._lose(fd, "read_error", f"select failed: {exc}")
                    fd = None
                    continue
                if self._wake_r in ready:
                    try:
                        os.read(self._wake_r, 4096)
                    except OSError:
                        pass
                if fd in ready:
                    try:
                        data = os.read(fd, EVENT_SIZE * 64)
                    except BlockingIOError:
                        data = None
                    except OSError as exc:
                        lost = exc.errno in (errno.ENODEV, errno.ENXIO, errno.EBADF, errno.EIO)
                        kind = "device_lost" if lost else "read_error"
                        self._lose(fd, kind, f"read failed: {exc.strerror} (errno {exc.errno})")
                        fd = None
                        self._stop.wait(backoff)
                        backoff = min(backoff * 2, self.backoff_s[1])
                        continue
                    if data == b"":
                        self._lose(fd, "device_lost", "end of file: device or writer gone")
                        fd = None
                        self._stop.wait(backoff)
                        backoff = min(backoff * 2, self.backoff_s[1])
                        continue
                    if data:
                        if len(self._raw) == self._raw.maxlen:
                            self.stats.raw_dropped += 1
                        self._raw.append((self.clock(), data))
                        events, pending = decode_events(pending + data)
                        self._apply(events)
                        self._mark_alive()
                        backoff = self.backoff_s[0]
                elif not ready:
                    self.stats.timeouts += 1
                    if self._idle_alive:
                        self._mark_alive()  # quiet select timeout on a live character device
                        backoff = self.backoff_s[0]
                self._release_barriers(fd)
        finally:
            if fd is not None:
                os.close(fd)
            with self._lock:
                self._connected = False
                waiting, self._barrier = self._barrier, []
            for ev in waiting:
                ev.set()
