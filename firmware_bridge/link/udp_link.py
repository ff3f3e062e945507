"""UDP link: ``udp://0.0.0.0:14550`` listens, ``udp://host:port`` sends.

Listen mode binds ``host:port`` and replies to the vehicle it locked to (MAVLink's usual
ground-station arrangement). Send mode binds an ephemeral local port (or ``local_port``) and sends
to ``host:port``; replies come back to that local port. The mode follows the host (wildcard
``0.0.0.0`` / ``::`` listens) unless ``?mode=listen`` or ``?mode=send`` says otherwise, so
``udp://127.0.0.1:14550?mode=listen`` listens on loopback only.

In both modes a :class:`~firmware_bridge.link.peer.PeerLock` accepts datagrams only from the
vehicle first heard (its address and system id; in send mode the target's address) or from an
allow-list
(:class:`~firmware_bridge.link.base.LinkOptions`); others are dropped, counted
(``peer_lock.rejected``) and reported once per sender as a ``peer_rejected`` event. Until the
lock, nothing is sent in listen mode.

One ``read`` returns one datagram (MAVLink frames may still span datagrams; the codec copes).
Reads block in ``select`` on the socket and a wake pipe, so ``close`` interrupts them.
"""

from __future__ import annotations

import os
import select
import socket
import threading

from firmware_bridge.errors import LinkError
from firmware_bridge.link.base import Link, LinkOptions, ParsedUri
from firmware_bridge.link.peer import PeerLock

EXAMPLE = "udp://0.0.0.0:14550 (listen) or udp://192.168.1.10:14550 (send)"
_PARAMS = {"mode", "local_port", "rcvbuf"}
_WILDCARDS = {"0.0.0.0", "::", ""}
_MAX_DATAGRAM = 65535


class UdpLink(Link):
    """UDP link opened from a parsed ``udp://`` URI.

    Attributes
    ----------
    mode : {"listen", "send"}
    local_address : (str, int)
        Bound address (useful with port 0).
    peer : (str, int) or None
        Where ``write`` sends: the target (send mode) or the locked vehicle (listen mode).
    peer_lock : PeerLock
        Which senders are accepted; its counters go into the link process's status.
    dropped_writes, bytes_read, bytes_written, datagrams_read : int
        Counters.
    """

    def __init__(self, parsed: ParsedUri, options: LinkOptions | None = None) -> None:
        super().__init__(parsed)
        options = options or LinkOptions()
        if parsed.scheme != "udp":
            raise parsed.error("not a udp:// URI", EXAMPLE)
        unknown = set(parsed.query) - _PARAMS
        if unknown:
            raise parsed.error(
                f"unknown parameter(s) {sorted(unknown)} (known: {sorted(_PARAMS)})", EXAMPLE
            )
        if parsed.port is None:
            raise parsed.error("no port", EXAMPLE)
        if parsed.path not in ("", "/"):
            raise parsed.error(f"unexpected path {parsed.path!r}", EXAMPLE)
        mode = parsed.query.get("mode", "listen" if parsed.host in _WILDCARDS else "send")
        if mode not in ("listen", "send"):
            raise parsed.error(f"mode={mode!r} must be 'listen' or 'send'", EXAMPLE)
        if mode == "send" and (parsed.host in _WILDCARDS or parsed.port == 0):
            raise parsed.error("send mode needs a destination host and a non-zero port", EXAMPLE)
        self.mode = mode
        host = parsed.host or "0.0.0.0"
        try:
            infos = socket.getaddrinfo(host, parsed.port, type=socket.SOCK_DGRAM)
        except socket.gaierror as exc:
            raise parsed.error(f"cannot resolve host {host!r}: {exc}", EXAMPLE) from None
        family, _, _, _, address = infos[0]
        self._sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(
                socket.SOL_SOCKET, socket.SO_RCVBUF, parsed.int_param("rcvbuf", 1 << 20)
            )
            if mode == "listen":
                self._sock.bind(address)
                self.peer: tuple[str, int] | None = None
            else:
                local_port = parsed.int_param("local_port", 0, lo=0, example=EXAMPLE)
                wildcard = "::" if family == socket.AF_INET6 else "0.0.0.0"
                self._sock.bind((wildcard, local_port))
                self.peer = (address[0], address[1])
        except OSError as exc:
            self._sock.close()
            raise LinkError(
                f"cannot open UDP socket for {self.uri}: {exc}",
                hint="is another program bound to that port? (ss -ulpn)",
            ) from exc
        self.peer_lock = PeerLock(
            options.allow_peers, options.vehicle_system_id or None, lock_to=self.peer
        )
        self._sock.setblocking(False)
        self.local_address = self._sock.getsockname()[:2]
        self._wake_r, self._wake_w = os.pipe()
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self.dropped_writes = 0
        self.bytes_read = 0
        self.bytes_written = 0
        self.datagrams_read = 0
        self._emit("opened", f"{mode} on {self.local_address[0]}:{self.local_address[1]}")

    def read(self, timeout_s: float) -> bytes:
        """One datagram received within ``timeout_s`` s, or ``b""``; errors become events."""
        if self._closed.is_set():
            return b""
        try:
            ready, _, _ = select.select([self._sock, self._wake_r], [], [], max(0.0, timeout_s))
            if self._sock not in ready:
                return b""
            data, sender = self._sock.recvfrom(_MAX_DATAGRAM)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as exc:  # ICMP errors, closed socket
            if not self._closed.is_set():
                self._emit("read_error", f"{self.uri}: {exc}")
            return b""
        sender = (str(sender[0]), int(sender[1]))
        lock = self.peer_lock
        was_locked = lock.peer is not None
        before = len(lock.rejected_from)
        if not lock.admit(sender, data):
            if len(lock.rejected_from) > before:  # first rejection of this sender
                self._emit("peer_rejected", lock.last_rejected or "")
            return b""
        self.bytes_read += len(data)
        self.datagrams_read += 1
        if not was_locked:
            if self.mode == "listen":
                self.peer = sender
            self._emit("connected", f"{sender[0]}:{sender[1]} system {lock.locked_system_id}")
        return data

    def write(self, data: bytes) -> bool:
        """Send one datagram to the peer; dropped (counted, False) if no peer is known yet."""
        peer = self.peer
        if peer is None or self._closed.is_set():
            self.dropped_writes += 1
            return False
        try:
            with self._lock:
                self._sock.sendto(data, peer)
        except OSError as exc:
            self.dropped_writes += 1
            self._emit("write_error", f"{self.uri} -> {peer[0]}:{peer[1]}: {exc}")
            return False
        self.bytes_written += len(data)
        return True

    def close(self) -> None:
        """Close the socket and wake a blocked reader; idempotent."""
        if self._closed.is_set():
            return
        self._closed.set()
        try:
            os.write(self._wake_w, b"\0")
        except OSError:
            pass
        with self._lock:
            self._sock.close()
        for fd in (self._wake_r, self._wake_w):
            try:
                os.close(fd)
            except OSError:
                pass
        self._emit("closed", self.uri)
