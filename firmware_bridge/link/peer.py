"""Which senders a UDP link accepts: lock to the vehicle first heard, or to an allow-list (pure).

A listening MAVLink link used to reply to whoever sent the latest datagram: one datagram from
another port redirected every MANUAL_CONTROL there, and forged HIGHRES_IMU from a foreign port
was recorded as vehicle data. :class:`PeerLock` decides per datagram, with no sockets or clocks:

- **allow-list** (``allow``: ``"host"`` or ``"host:port"`` entries): only those senders count;
- **lock**: the first datagram that holds a MAVLink frame with a valid checksum (and, when
  ``system_id`` is set, that system id) fixes the peer: its address and its system id. From then
  on a datagram is accepted only from that address, and not when its first frame names another
  system id. Everything else is rejected and counted per sender (``rejected``, ``rejected_from``).

The lock never moves: a vehicle that comes back on another port needs a new session (or an
allow-list entry), which is what the operator sees in the status (``rejected peers``) instead of a
silent redirect.
"""

from __future__ import annotations

import ipaddress
import socket
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

from firmware_bridge.errors import UriError

_STX_V2, _STX_V1 = 0xFD, 0xFE
_MAX_SENDERS_KEPT = 32


@dataclass(frozen=True)
class PeerRule:
    """One allow-list entry: an IP address and optionally a port (None = any port)."""

    host: str
    port: int | None = None

    def matches(self, sender: tuple[str, int]) -> bool:
        return sender[0] == self.host and (self.port is None or sender[1] == self.port)


def parse_peer(text: str) -> PeerRule:
    """``"127.0.0.1"``, ``"127.0.0.1:14551"``, ``"[::1]:14551"`` or a host name -> rule.

    Raises
    ------
    UriError
        Not an address, or a port outside 1..65535.
    """
    raw = text.strip()
    host, port = raw, None
    if raw.startswith("["):
        host, _, rest = raw[1:].partition("]")
        if rest:
            port = rest.lstrip(":")
    elif raw.count(":") == 1:
        host, port = raw.split(":")
    try:
        port_n = None if port is None else int(port)
        if port_n is not None and not 0 < port_n < 65536:
            raise ValueError(f"port {port_n} out of range")
        try:
            addr = str(ipaddress.ip_address(host))
        except ValueError:
            addr = socket.gethostbyname(host)
    except (ValueError, OSError) as exc:
        raise UriError(
            f"bad allowed peer {text!r}: {exc}", hint="use HOST or HOST:PORT, e.g. 127.0.0.1:14551"
        ) from None
    return PeerRule(addr, port_n)


def first_frame_system_id(data: bytes) -> int | None:
    """System id in the header of the MAVLink frame that starts ``data`` (no checksum check)."""
    if len(data) >= 6 and data[0] == _STX_V2:
        return data[5]
    if len(data) >= 4 and data[0] == _STX_V1:
        return data[3]
    return None


def valid_frame_system_id(data: bytes) -> int | None:
    """System id of the first MAVLink frame in ``data`` whose checksum is valid, else None."""
    from firmware_bridge.mavlink.codec import MavlinkCodec  # pure codec, imported on first use

    codec = MavlinkCodec()
    for rec in codec.decode(bytes(data), 0):
        return rec.system_id
    if codec.stats.frames:  # valid frames that map to no record (e.g. SYS_STATUS)
        return next(iter(codec.stats.seq_gaps))[0]
    return None


class PeerLock:
    """Accept or reject each datagram by its sender (see the module docstring).

    Parameters
    ----------
    allow : sequence of str or PeerRule
        Allowed senders; empty = lock to the first vehicle heard.
    system_id : int or None
        Vehicle system id to lock to; None (or 0) = the first one heard.
    lock_to : (str, int), optional
        Start locked to this address (a send-mode target): nothing else is ever accepted, and
        its datagrams are accepted before a valid frame names the vehicle's system id.

    Attributes
    ----------
    peer : (str, int) or None
        The locked address.
    locked_system_id : int or None
        The locked vehicle's system id.
    accepted, rejected : int
        Datagrams accepted / rejected.
    rejected_from : Counter
        Rejected datagrams per ``"host:port"`` (the first 32 senders, then ``"other"``).
    last_rejected : str or None
        Why the latest datagram was rejected.
    """

    def __init__(
        self,
        allow: Sequence[str | PeerRule] = (),
        system_id: int | None = None,
        lock_to: tuple[str, int] | None = None,
    ) -> None:
        self.rules = tuple(r if isinstance(r, PeerRule) else parse_peer(r) for r in allow)
        if system_id is not None and not 0 <= system_id <= 255:
            raise UriError(f"vehicle system id {system_id} is not in 0..255")
        self.system_id = system_id or None
        self.peer: tuple[str, int] | None = lock_to
        self.locked_system_id: int | None = None
        self.accepted = 0
        self.rejected = 0
        self.rejected_from: Counter[str] = Counter()
        self.last_rejected: str | None = None

    def _reject(self, sender: tuple[str, int], why: str) -> bool:
        self.rejected += 1
        key = f"{sender[0]}:{sender[1]}"
        if key not in self.rejected_from and len(self.rejected_from) >= _MAX_SENDERS_KEPT:
            key = "other"
        self.rejected_from[key] += 1
        self.last_rejected = f"{sender[0]}:{sender[1]}: {why}"
        return False

    def admit(self, sender: tuple[str, int], data: bytes) -> bool:
        """True if the datagram ``data`` from ``sender`` (host, port) is the vehicle's."""
        sender = (str(sender[0]), int(sender[1]))
        if self.rules and not any(r.matches(sender) for r in self.rules):
            return self._reject(sender, "not in the allow-list")
        if self.peer is not None and sender != self.peer:
            return self._reject(sender, f"not the locked peer {self.peer[0]}:{self.peer[1]}")
        if self.locked_system_id is None:
            sysid = valid_frame_system_id(data)
            if sysid is None:
                if self.peer is None:
                    return self._reject(sender, "no valid MAVLink frame before the lock")
                self.accepted += 1  # the configured target, vehicle not identified yet
                return True
            if self.system_id is not None and sysid != self.system_id:
                return self._reject(sender, f"system id {sysid}, expected {self.system_id}")
            self.peer, self.locked_system_id = sender, sysid
            self.accepted += 1
            return True
        sysid = first_frame_system_id(data)
        if sysid is not None and sysid != self.locked_system_id:
            return self._reject(
                sender,
                f"system id {sysid} differs from the locked vehicle's {self.locked_system_id}",
            )
        self.accepted += 1
        return True

    def counters(self) -> dict[str, object]:
        """Counters for a status payload (JSON-ready)."""
        peer = None if self.peer is None else f"{self.peer[0]}:{self.peer[1]}"
        return {
            "peer": peer,
            "system_id": self.locked_system_id,
            "rejected_peers": self.rejected,
            "rejected_from": dict(self.rejected_from),
            "last_rejected": self.last_rejected,
        }
