"""``natnet://`` link: a thin UDP shell that receives NatNet datagrams.

* ``natnet://239.255.42.99:1511`` - a multicast group (224.0.0.0/4): bind the port, join the
  group on the interface given by ``?iface=`` (default 0.0.0.0, the kernel's choice; use
  ``?iface=127.0.0.1`` for loopback).
* ``natnet://host:1511`` - unicast: bind that port on loopback when ``host`` is a loopback
  address, else on all interfaces, and receive what the server sends there.

Query parameters: ``iface`` (multicast interface), ``server`` (server address for commands
when multicast), ``cmd_port`` (server command port, default 1510), ``rcvbuf`` (socket receive
buffer bytes, default 1 MiB). Port 0 binds an ephemeral port (see :attr:`local_address`).

Senders are checked by :class:`~firmware_bridge.natnet.peers.NatNetPeerPolicy`: datagrams only
from the server's host (configured, or the first frame's host for multicast without
``?server=``), server info only from its command port. Others are dropped before anyone decodes
or records them, counted (``policy``) and reported once per sender as a ``peer_rejected`` event.

Follows :class:`firmware_bridge.link.base.Link`: :meth:`read` blocks in ``select`` for at most
``timeout_s`` and returns one datagram, ``b""`` on timeout or once closed (no sleep-polling;
:meth:`close` wakes a blocked reader); :meth:`write` never raises for transport trouble, it
counts and records events. Decoding is :func:`firmware_bridge.natnet.parse_packet`'s job.
"""

from __future__ import annotations

import ipaddress
import os
import select
import socket
import struct
import threading

from firmware_bridge.errors import LinkError
from firmware_bridge.link.base import Link, LinkOptions, ParsedUri, parse_uri
from firmware_bridge.natnet.peers import NatNetPeerPolicy

DEFAULT_DATA_PORT = 1511
DEFAULT_COMMAND_PORT = 1510
EXAMPLE = "natnet://239.255.42.99:1511?iface=127.0.0.1 or natnet://127.0.0.1:1511"
_MAX_DATAGRAM = 65535


class NatNetLink(Link):
    """Receive NatNet datagrams over UDP; send commands to the server's command port.

    Parameters
    ----------
    parsed : ParsedUri or str
        From :func:`firmware_bridge.link.base.parse_uri`, or the URI text.

    Attributes
    ----------
    group : str or None
        Multicast group joined, None for unicast.
    datagrams_read, bytes_read, dropped_writes : int
        Counters.

    Raises
    ------
    UriError
        Wrong scheme, missing host, bad port or query value.
    LinkError
        The socket cannot be bound or the group cannot be joined.
    """

    def __init__(self, parsed: ParsedUri | str, options: LinkOptions | None = None):
        if isinstance(parsed, str):
            parsed = parse_uri(parsed)
        super().__init__(parsed)
        if parsed.scheme != "natnet":
            raise parsed.error(f"NatNetLink cannot open scheme {parsed.scheme!r}", EXAMPLE)
        if not parsed.host:
            raise parsed.error("missing host (multicast group or server)", EXAMPLE)
        port = DEFAULT_DATA_PORT if parsed.port is None else parsed.port
        self.command_port = parsed.int_param("cmd_port", DEFAULT_COMMAND_PORT, 1, EXAMPLE)
        rcvbuf = parsed.int_param("rcvbuf", 1 << 20, 4096, EXAMPLE)
        if self.command_port > 0xFFFF:
            raise parsed.error(f"cmd_port={self.command_port} is not a UDP port", EXAMPLE)
        try:
            addr = ipaddress.IPv4Address(socket.gethostbyname(parsed.host))
            iface = ipaddress.IPv4Address(parsed.query.get("iface", "0.0.0.0"))
            server = parsed.query.get("server")
            if server is not None:
                server = str(ipaddress.IPv4Address(socket.gethostbyname(server)))
        except (ValueError, OSError) as exc:
            raise parsed.error(str(exc), EXAMPLE) from None
        self.group: str | None = str(addr) if addr.is_multicast else None
        self.interface = str(iface)
        self.policy = NatNetPeerPolicy(
            server if self.group else (server or str(addr)), self.command_port
        )
        self.datagrams_read = self.bytes_read = self.dropped_writes = 0
        self.last_source: tuple[str, int] | None = None
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
            if self.group:
                try:  # Linux: binding the group address filters out other groups' traffic
                    self._sock.bind((self.group, port))
                except OSError:
                    self._sock.bind(("", port))
                mreq = struct.pack("4s4s", addr.packed, iface.packed)
                self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            else:
                self._sock.bind(("127.0.0.1" if addr.is_loopback else "", port))
        except OSError as exc:
            self._sock.close()
            raise LinkError(
                f"{self.uri}: cannot open the NatNet socket: {exc}",
                hint="is another client bound to this port, or is the interface address wrong?",
            ) from None
        self._wake_r, self._wake_w = os.pipe()  # close() wakes a reader blocked in select
        where = f"{self.group} via {self.interface}" if self.group else "unicast"
        self._emit("opened", f"{where} on {self.local_address[0]}:{self.local_address[1]}")

    @property
    def local_address(self) -> tuple[str, int]:
        """(address, port) the socket is bound to."""
        return self._sock.getsockname()

    @property
    def server(self) -> str | None:
        """Server address for commands: configured, unicast host, or the first sender seen."""
        return self.policy.server

    def read(self, timeout_s: float) -> bytes:
        """One datagram received within ``timeout_s`` seconds, else ``b""`` (also once closed).

        Receive errors are recorded as ``read_error`` events and return ``b""``.
        """
        if self._closed.is_set():
            return b""
        try:
            ready, _, _ = select.select([self._sock, self._wake_r], [], [], max(0.0, timeout_s))
            if self._sock not in ready:
                return b""
            data, src = self._sock.recvfrom(_MAX_DATAGRAM)
        except (OSError, ValueError) as exc:  # closed under us, ICMP errors
            if not self._closed.is_set():
                self._emit("read_error", f"{self.uri}: {exc}")
            return b""
        policy = self.policy
        had_server = policy.server is not None
        before = len(policy.rejected_from)
        if not policy.admit(src[:2], data):
            if len(policy.rejected_from) > before:  # first rejection of this sender
                self._emit("peer_rejected", policy.last_rejected or "")
            return b""
        self.datagrams_read += 1
        self.bytes_read += len(data)
        self.last_source = src[:2]
        if not had_server:
            self._emit("connected", f"server {src[0]} (commands to port {self.command_port})")
        return data

    def write(self, data: bytes) -> bool:
        """Send ``data`` (an encoded NatNet command) to the server's command port; True when
        it went out.

        Dropped and counted (event ``write_dropped``) while the server is unknown (multicast
        without ``?server=`` before any datagram) or once closed; send errors become
        ``write_error`` events.
        """
        server = self.policy.server
        if server is None or self._closed.is_set():
            self.dropped_writes += 1
            why = "closed" if self._closed.is_set() else "server address unknown (add ?server=)"
            self._emit("write_dropped", f"{self.uri}: {why}")
            return False
        try:
            with self._lock:
                self._sock.sendto(bytes(data), (server, self.command_port))
        except OSError as exc:
            self.dropped_writes += 1
            self._emit("write_error", f"{self.uri} -> {server}:{self.command_port}: {exc}")
            return False
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
