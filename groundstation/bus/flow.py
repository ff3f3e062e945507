"""Credit-based flow control for lossless replay at maximum speed.

PUB/SUB has no back-pressure: a replay source at ``speed=max`` would queue the whole recording
in memory (lossless topics have an unbounded high-water mark) or, with a bound, drop. Here each
consumer acknowledges, per topic, the highest sequence number it has *processed* on a back
channel, and the publisher does not send sequence ``s`` of a topic while a registered consumer of
that topic has acknowledged less than ``s - window``. So the source is never more than ``window``
messages ahead of its slowest consumer on any topic, memory stays bounded, and nothing is dropped.

Back channel: the publisher binds a ROUTER, each consumer connects a DEALER and sends::

    [b"hello", JSON list of topics]     register (before the first message is published)
    [b"ack", topic, uint64 seq (LE)]    cumulative: "processed every seq <= this one"
    [b"bye"]                            unregister (a consumer that leaves must not block)

Acks are cumulative, so an ack lost to a full queue is superseded by the next one.
:class:`CreditWindow` is the pure bookkeeping; :class:`CreditServer` / :class:`CreditClient` are
thin socket shells used by :class:`~groundstation.bus.pubsub.Publisher` /
:class:`~groundstation.bus.pubsub.Subscriber` when given a flow endpoint.
"""

from __future__ import annotations

import json
import struct
import time
from collections.abc import Callable, Iterable

import zmq

from groundstation.bus import security
from groundstation.bus.errors import BusError, BusTimeoutError

_SEQ = struct.Struct("<Q")


class CreditWindow:
    """Pure credit bookkeeping (no sockets, no clock).

    Parameters
    ----------
    window : int
        Maximum number of unacknowledged messages per (consumer, topic), >= 1.
    """

    def __init__(self, window: int):
        if window < 1:
            raise BusError(f"flow window must be >= 1, got {window}")
        self.window = int(window)
        self._topics: dict[bytes, frozenset[str]] = {}
        self._acked: dict[tuple[bytes, str], int] = {}

    @property
    def consumers(self) -> list[bytes]:
        """Registered consumer ids."""
        return list(self._topics)

    def register(self, consumer: bytes, topics: Iterable[str]) -> None:
        """Register ``consumer`` for ``topics`` (nothing acknowledged yet)."""
        self._topics[consumer] = frozenset(topics)

    def unregister(self, consumer: bytes) -> None:
        """Forget ``consumer`` (it no longer holds the publisher back)."""
        self._topics.pop(consumer, None)
        for key in [k for k in self._acked if k[0] == consumer]:
            del self._acked[key]

    def ack(self, consumer: bytes, topic: str, seq: int) -> None:
        """Record that ``consumer`` processed every message of ``topic`` up to ``seq``."""
        key = (consumer, topic)
        self._acked[key] = max(seq, self._acked.get(key, -1))

    def ahead(self, topic: str, seq: int) -> int:
        """Unacknowledged messages of ``topic`` if ``seq`` were sent now (max over consumers)."""
        lags = [
            seq - self._acked.get((c, topic), -1) for c, t in self._topics.items() if topic in t
        ]
        return max(lags, default=0)

    def blocking(self, topic: str, seq: int) -> list[bytes]:
        """Consumers that forbid sending ``seq`` of ``topic`` now (empty: send allowed)."""
        return [
            c
            for c, topics in self._topics.items()
            if topic in topics and seq - self._acked.get((c, topic), -1) > self.window
        ]


class CreditServer:
    """Publisher side of the back channel: a bound ROUTER feeding a :class:`CreditWindow`."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str = "tcp://127.0.0.1:*",
        window: int = 64,
        server_keys: security.CurveKeys | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        security.check_bind(endpoint, server_keys)
        self.credit = CreditWindow(window)
        self._clock = clock
        self._sock = context.socket(zmq.ROUTER)
        self._sock.linger = 0
        if server_keys is not None:
            security.apply_server_keys(self._sock, server_keys)
        self._sock.bind(endpoint)
        self.endpoint: str = self._sock.getsockopt_string(zmq.LAST_ENDPOINT)
        self.bad_messages = 0

    def drain(self) -> None:
        """Apply every pending hello/ack/bye without blocking."""
        while True:
            try:
                frames = self._sock.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self._handle(frames)

    def _handle(self, frames: list[bytes]) -> None:
        ident, *msg = frames
        try:
            if msg[0] == b"ack" and len(msg) == 3:
                self.credit.ack(ident, msg[1].decode(), _SEQ.unpack(msg[2])[0])
            elif msg[0] == b"hello" and len(msg) == 2:
                topics = json.loads(msg[1])
                if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
                    raise ValueError("hello topics must be a list of str")
                self.credit.register(ident, topics)
            elif msg[0] == b"bye":
                self.credit.unregister(ident)
            else:
                raise ValueError(f"unknown flow message {msg[:1]!r}")
        except (ValueError, IndexError, struct.error, UnicodeDecodeError):
            self.bad_messages += 1  # a malformed back-channel message never stops the publisher

    def wait_for_consumers(self, n: int, timeout_s: float) -> None:
        """Block until ``n`` consumers said hello; raises :class:`BusTimeoutError`."""
        deadline = self._clock() + timeout_s
        while True:
            self.drain()
            if len(self.credit.consumers) >= n:
                return
            remaining = deadline - self._clock()
            if remaining <= 0:
                raise BusTimeoutError(
                    f"{len(self.credit.consumers)} of {n} flow consumers registered "
                    f"on {self.endpoint} after {timeout_s} s"
                )
            self._sock.poll(max(1, int(remaining * 1000)))

    def wait_for_credit(self, topic: str, seq: int, timeout_s: float) -> None:
        """Block until ``seq`` of ``topic`` may be sent; raises :class:`BusTimeoutError`."""
        self.drain()
        if not self.credit.blocking(topic, seq):
            return
        deadline = self._clock() + timeout_s
        while blockers := self.credit.blocking(topic, seq):
            remaining = deadline - self._clock()
            if remaining <= 0:
                raise BusTimeoutError(
                    f"flow control: {len(blockers)} consumer(s) did not acknowledge {topic!r} "
                    f"seq {seq - self.credit.window} within {timeout_s} s (window "
                    f"{self.credit.window})",
                    hint="a consumer stopped processing; it must ack() or close() (sends bye)",
                )
            if self._sock.poll(max(1, int(remaining * 1000))):
                self.drain()

    def close(self) -> None:
        """Close the ROUTER socket."""
        self._sock.close(linger=0)


class CreditClient:
    """Consumer side: a DEALER that registers its topics and sends cumulative acks."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        topics: Iterable[str],
        server_public_key: bytes | None = None,
    ):
        security.check_endpoint(endpoint)
        self._sock = context.socket(zmq.DEALER)
        self._sock.linger = 1000  # let "bye" reach the publisher on close
        if server_public_key is not None:
            security.apply_client_keys(self._sock, server_public_key)
        self._sock.connect(endpoint)
        self._sock.send_multipart([b"hello", json.dumps(sorted(topics)).encode()])
        self.dropped_acks = 0

    def ack(self, topic: str, seq: int) -> None:
        """Acknowledge every message of ``topic`` up to ``seq`` (never blocks)."""
        try:
            self._sock.send_multipart([b"ack", topic.encode(), _SEQ.pack(seq)], zmq.NOBLOCK)
        except zmq.Again:
            self.dropped_acks += 1  # cumulative: the next ack supersedes it

    def close(self) -> None:
        """Unregister (so this consumer stops holding the publisher back) and close."""
        try:
            self._sock.send_multipart([b"bye"], zmq.NOBLOCK)
        except zmq.Again:
            pass
        self._sock.close()
