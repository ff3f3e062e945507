"""Vehicle-side transports of the SITL: a pseudo-terminal (like USB telemetry) and UDP.

Both are thin: ``send(bytes)`` never blocks the simulation (a full pty buffer drops whole frames
and counts them), ``recv()`` returns what the station sent (non-blocking), ``fileno()`` serves
select. The pty's device path is what the station opens (``serial:///dev/pts/N``).

``pty:/path`` (:class:`PtyTransport` with ``link_path``) also makes ``/path`` a symlink to the
pty and holds a lock on ``/path.lock`` while the SITL runs; the station opens
``serial:///path`` and refuses it once the lock is free (the SITL is gone and ``/dev/pts/N`` may
belong to another process by then), so a station never attaches to another process's vehicle
through a stale or reused pty number.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import ipaddress
import os
import select
import socket
import struct
import termios
import time
import tty
from dataclasses import dataclass

from firmware_bridge.errors import LinkError
from firmware_bridge.link.base import parse_uri


@dataclass
class TransportStats:
    frames_sent: int = 0
    bytes_sent: int = 0
    frames_dropped: int = 0
    bytes_dropped: int = 0
    bytes_received: int = 0
    send_errors: int = 0


class PtyTransport:
    """A pseudo-terminal pair in raw mode; we hold the master, the station opens ``path``.

    Parameters
    ----------
    max_pending : bytes buffered while the reader is slow; beyond it whole frames are dropped.
    link_path : a path to make a symlink to the pty (held with ``link_path + ".lock"``).
    """

    def __init__(self, max_pending: int = 65536, link_path: str | None = None):
        self.link_path: str | None = None
        self._lock_fd = -1
        self.master, self._slave = os.openpty()
        try:
            tty.setraw(self._slave)  # no echo, no line discipline: bytes pass unchanged
            attrs = termios.tcgetattr(self._slave)
            attrs[4] = attrs[5] = termios.B921600
            termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
            os.set_blocking(self.master, False)
            self.path = os.ttyname(self._slave)
        except OSError as exc:
            self.close()
            raise LinkError(f"cannot set up the SITL pseudo-terminal: {exc}") from exc
        self.max_pending = max_pending
        self._pending = bytearray()
        self.stats = TransportStats()
        if link_path is not None:
            try:
                self._make_link(os.path.abspath(link_path))
            except LinkError:
                self.close()
                raise
        self.uri = f"serial://{self.link_path or self.path}?baud=921600"

    def _make_link(self, path: str) -> None:
        """``path`` -> our pty, locked while we run; never replaces anything but a stale link."""
        lock = path + ".lock"
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise LinkError(f"cannot create the SITL link lock {lock}: {exc.strerror}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise LinkError(
                f"{path} is the link of another running SITL", hint="choose another path"
            ) from None
        try:
            if os.path.lexists(path):
                if not os.path.islink(path):
                    raise LinkError(
                        f"{path} exists and is not a SITL link; not replacing it",
                        hint="choose another path for --link pty:PATH",
                    )
                os.unlink(path)  # a stale link of a SITL that is gone (its lock was free)
            os.symlink(self.path, path)
        except OSError as exc:
            os.close(fd)
            raise LinkError(f"cannot create the SITL link {path}: {exc.strerror}") from None
        except LinkError:
            os.close(fd)
            raise
        self._lock_fd, self.link_path = fd, path

    def fileno(self) -> int:
        return self.master

    @property
    def pending_bytes(self) -> int:
        """Bytes accepted by :meth:`send` but not yet taken by the pty."""
        return len(self._pending)

    def flush(self) -> None:
        """Write as much of the pending buffer as the pty accepts."""
        while self._pending:
            try:
                n = os.write(self.master, self._pending)
            except BlockingIOError:
                return
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    return
                raise
            del self._pending[:n]

    def send(self, data: bytes) -> None:
        """Queue one frame; drop it whole (counted) if the reader is too far behind."""
        self.flush()
        if len(self._pending) + len(data) > self.max_pending:
            self.stats.frames_dropped += 1
            self.stats.bytes_dropped += len(data)
            return
        self._pending += data
        self.stats.frames_sent += 1
        self.stats.bytes_sent += len(data)
        self.flush()

    def drain(self, timeout_s: float = 0.5) -> None:
        """Give a slow reader up to ``timeout_s`` to take the pending bytes (before closing)."""
        end = time.monotonic() + timeout_s
        self.flush()
        while self._pending and time.monotonic() < end:
            select.select([], [self.master], [], max(0.0, end - time.monotonic()))
            self.flush()
        # Closing a pty master discards what the station has not read yet, so also wait for the
        # kernel queue to empty. Shutdown only: a short sleep loop is fine here.
        # The kernel moves written bytes to the reader's queue asynchronously (the pty flip
        # buffer), so an empty queue must be seen several times in a row.
        quiet = 0
        while quiet < 5 and time.monotonic() < end:
            quiet = quiet + 1 if self._unread() == 0 else 0
            time.sleep(0.02)

    def _unread(self) -> int:
        """Bytes written to the pty that the station side has not read yet."""
        try:
            raw = fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0")
        except OSError:
            return 0
        return struct.unpack("i", raw)[0]

    def recv(self) -> bytes:
        """Bytes the station wrote to the device (b"" if none)."""
        try:
            data = os.read(self.master, 65536)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:
                return b""
            raise
        self.stats.bytes_received += len(data)
        return data

    def close(self) -> None:
        path = getattr(self, "link_path", None)
        if path is not None:
            with contextlib.suppress(OSError):
                if os.path.islink(path) and os.readlink(path) == self.path:
                    os.unlink(path)
            with contextlib.suppress(OSError):
                os.unlink(path + ".lock")
            self.link_path = None
        for fd in (getattr(self, "master", -1), getattr(self, "_slave", -1),
                   getattr(self, "_lock_fd", -1)):  # fmt: skip
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self._slave = self._lock_fd = -1


class UdpTransport:
    """UDP socket that sends to ``udp://HOST:PORT`` and receives commands on the same socket.

    ``?local_port=PORT`` binds the local port (default: an ephemeral one).
    """

    def __init__(self, uri: str, receive: bool = True):
        p = parse_uri(uri)
        if p.scheme != "udp" or not p.host or not p.port:
            raise p.error("expected udp://HOST:PORT", "udp://127.0.0.1:14550")
        local = p.int_param("local_port", 0, lo=0, example="udp://127.0.0.1:14550?local_port=14555")
        try:
            info = socket.getaddrinfo(p.host, p.port, type=socket.SOCK_DGRAM)[0]
        except socket.gaierror as exc:
            raise LinkError(f"cannot resolve {p.host!r} in {uri!r}: {exc}") from None
        self.target = info[4]
        self.sock = socket.socket(info[0], socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 1 << 20)
            if info[0] == socket.AF_INET and ipaddress.ip_address(self.target[0]).is_multicast:
                self.sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 1)
            self.sock.bind(("", local))
        except OSError as exc:
            self.sock.close()
            raise LinkError(f"cannot open UDP socket for {uri!r}: {exc}") from exc
        self.sock.setblocking(False)
        self.receive = receive
        self.uri = uri
        self.local_port = self.sock.getsockname()[1]
        self.stats = TransportStats()

    def fileno(self) -> int:
        return self.sock.fileno()

    def flush(self) -> None:
        """Datagrams are never buffered here."""

    def send(self, data: bytes) -> None:
        """One datagram; errors (no listener yet, full buffer) drop it and are counted."""
        try:
            self.sock.sendto(data, self.target)
        except OSError:
            self.stats.frames_dropped += 1
            self.stats.bytes_dropped += len(data)
            self.stats.send_errors += 1
            return
        self.stats.frames_sent += 1
        self.stats.bytes_sent += len(data)

    def recv(self) -> bytes:
        """All datagrams waiting (concatenated), b"" if none."""
        chunks = []
        for _ in range(1000):
            try:
                data, _ = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. ECONNREFUSED reported for an earlier send
                self.stats.send_errors += 1
                continue
            chunks.append(data)
        out = b"".join(chunks)
        self.stats.bytes_received += len(out)
        return out

    def close(self) -> None:
        self.sock.close()


def open_transport(link: str) -> PtyTransport | UdpTransport:
    """``pty`` or ``pty:/path`` -> :class:`PtyTransport`; ``udp://HOST:PORT`` ->
    :class:`UdpTransport`."""
    if link == "pty":
        return PtyTransport()
    if link.startswith("pty:"):
        path = link[4:]
        if not path:
            raise LinkError("--link pty:PATH needs a path", hint="e.g. --link pty:/tmp/sitl-link")
        return PtyTransport(link_path=path)
    if link.startswith("udp://"):
        return UdpTransport(link)
    raise LinkError(
        f"--link {link!r}: expected 'pty', 'pty:/path' or udp://HOST:PORT",
        hint="e.g. --link udp://127.0.0.1:14550",
    )
