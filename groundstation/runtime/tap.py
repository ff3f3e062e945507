"""A light subscriber for the recorders: every message as received frames, header parsed only.

The recorder stores envelope topics as the frames it received and needs only their header
(topic, origin, sequence, times) to order, count gaps and find messages again after a takeover;
decoding and validating every payload (what :class:`~groundstation.bus.pubsub.Subscriber`
does for the stages) would double its CPU for nothing. :class:`Tap` owns one SUB socket per drop
policy, like the subscriber shell (same high-water marks), and returns :class:`Tapped` messages
whose full :class:`~groundstation.bus.envelope.Envelope` is decoded only when asked for (raw
topics, whose wire bytes and source are in the payload and arrays).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from functools import cached_property

import zmq

from groundstation.bus.envelope import Envelope, EnvelopeError, Header, decode, unpack_header
from groundstation.bus.pubsub import LATEST_HWM
from groundstation.bus.security import check_endpoint
from groundstation.bus.sequence import SequenceTracker, TopicStats
from groundstation.bus.topics import TOPICS


class Tapped:
    """One received message: ``topic``, ``header``, the ``frames`` as received and
    ``recv_ns`` (the header's receive time, or the tap's clock when the publisher left it 0)."""

    __slots__ = ("topic", "header", "frames", "recv_ns", "__dict__")

    def __init__(self, topic: str, header: Header, frames: list, recv_ns: int) -> None:
        self.topic, self.header, self.frames, self.recv_ns = topic, header, frames, recv_ns

    @cached_property
    def envelope(self) -> Envelope:
        """The decoded message (raises ``EnvelopeError`` for a malformed one)."""
        env = decode(self.frames)
        return env if env.header.recv_ns else env.with_recv_ns(self.recv_ns)


class Tap:
    """Every topic of ``endpoints`` as :class:`Tapped` messages, counting sequence gaps.

    Parameters
    ----------
    endpoints : sequence of str
        Publisher endpoints (a session's, both policies).
    context : zmq.Context
    clock : callable
        ns clock stamping messages that carry no receive time.
    """

    def __init__(
        self,
        endpoints: Sequence[str],
        context: zmq.Context,
        clock: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        for ep in endpoints:
            check_endpoint(ep)
        self._clock = clock
        self.tracker = SequenceTracker()
        self.bad_messages = 0
        self._socks: list[zmq.Socket] = []
        self._poller = zmq.Poller()
        self._rr = 0
        for policy in ("lossless", "latest"):
            sock = context.socket(zmq.SUB)
            sock.rcvhwm = 0 if policy == "lossless" else LATEST_HWM
            sock.linger = 0
            for name, t in TOPICS.items():
                if t.policy == policy:
                    sock.setsockopt(zmq.SUBSCRIBE, name.encode())
            for ep in endpoints:
                sock.connect(ep)
            self._socks.append(sock)
            self._poller.register(sock, zmq.POLLIN)

    @property
    def stats(self) -> dict[str, TopicStats]:
        """Per-topic counters (received, gaps, bad)."""
        return self.tracker.stats

    def recv(self, timeout_ms: int) -> Tapped | None:
        """The next message, or None after ``timeout_ms``; malformed headers are counted and
        skipped."""
        deadline = time.monotonic() + timeout_ms / 1000
        while True:
            wait = max(0, int((deadline - time.monotonic()) * 1000))
            ready = dict(self._poller.poll(wait))
            if not ready:
                return None
            self._rr += 1
            k = self._rr % len(self._socks)
            for sock in self._socks[k:] + self._socks[:k]:
                if sock in ready:
                    got = self._read(sock)
                    if got is not None:
                        return got
            if wait == 0:
                return None

    def _read(self, sock: zmq.Socket) -> Tapped | None:
        frames = [f.buffer for f in sock.recv_multipart(copy=False)]
        try:
            if len(frames) < 3:
                raise EnvelopeError(f"{len(frames)} frames, need at least 3")
            topic = bytes(frames[0]).decode("utf-8")
            header = unpack_header(frames[1])
        except (EnvelopeError, UnicodeDecodeError):
            self.bad_messages += 1
            self.tracker.bad("?")
            return None
        self.tracker.observe(topic, header.origin, header.seq)
        return Tapped(topic, header, frames, header.recv_ns or self._clock())

    def close(self) -> None:
        for s in self._socks:
            s.close(linger=0)
        self._socks = []
