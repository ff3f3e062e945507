"""Which NatNet datagrams come from the mocap server (pure; used by the ``natnet://`` link).

One spoofed server-info datagram from anyone used to switch the decoder to NatNet 2.0 and stop
all mocap silently. :class:`NatNetPeerPolicy` accepts:

- frames of data (and any other message) only from the server's host: the configured one
  (``natnet://HOST`` unicast, ``?server=`` for multicast) or, without one, the host of the first
  frame of data heard;
- server info (message 1) only from the server's host *and* its command port (server info is the
  reply to a connect request, sent from the command socket).

Rejections are counted by kind and per sender (the first 32 senders, then ``"other"``).
"""

from __future__ import annotations

from collections import Counter

from firmware_bridge.natnet.records import NAT_FRAMEOFDATA, NAT_SERVERINFO

_MAX_SENDERS_KEPT = 32


class NatNetPeerPolicy:
    """Accept or reject NatNet datagrams by sender (see the module docstring).

    Parameters
    ----------
    server : str or None
        Server IP address; None = lock to the host of the first frame of data.
    command_port : int
        The server's command port (server info is accepted only from it).

    Attributes
    ----------
    server : str or None
    rejected_peers : int
        Datagrams from a host that is not the server.
    rejected_server_info : int
        Server-info datagrams not sent from the server's command port.
    rejected_from : Counter
        Rejections per ``"host:port"``.
    last_rejected : str or None
        Why the latest datagram was rejected.
    """

    def __init__(self, server: str | None, command_port: int) -> None:
        self.server = server
        self.command_port = int(command_port)
        self.rejected_peers = 0
        self.rejected_server_info = 0
        self.rejected_from: Counter[str] = Counter()
        self.last_rejected: str | None = None

    def _reject(self, sender: tuple[str, int], why: str) -> bool:
        key = f"{sender[0]}:{sender[1]}"
        if key not in self.rejected_from and len(self.rejected_from) >= _MAX_SENDERS_KEPT:
            key = "other"
        self.rejected_from[key] += 1
        self.last_rejected = f"{sender[0]}:{sender[1]}: {why}"
        return False

    def admit(self, sender: tuple[str, int], data: bytes) -> bool:
        """True if ``data`` from ``sender`` (host, port) may be decoded and recorded."""
        message_id = int.from_bytes(data[:2], "little") if len(data) >= 2 else None
        host, port = str(sender[0]), int(sender[1])
        if self.server is None and message_id == NAT_FRAMEOFDATA:
            self.server = host  # multicast without ?server=: the first frame's host
        if host != self.server:
            self.rejected_peers += 1
            return self._reject((host, port), f"not the NatNet server {self.server}")
        if message_id == NAT_SERVERINFO and port != self.command_port:
            self.rejected_server_info += 1
            return self._reject(
                (host, port), f"server info not from the command port {self.command_port}"
            )
        return True

    def counters(self) -> dict[str, object]:
        """Counters for a status payload (JSON-ready)."""
        return {
            "server": self.server,
            "rejected_peers": self.rejected_peers,
            "rejected_server_info": self.rejected_server_info,
            "rejected_from": dict(self.rejected_from),
            "last_rejected": self.last_rejected,
        }
