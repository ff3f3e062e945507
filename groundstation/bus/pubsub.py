"""Thin ZeroMQ shells: :class:`Publisher` (XPUB) and :class:`Subscriber` (SUB).

Endpoints default to ``tcp://127.0.0.1:*`` (loopback, an ephemeral port read back from the
socket): portable, nothing to clean up on disk, and as fast as ``ipc://`` for our message sizes
(STACK.md). ``ipc://`` paths (<= 107 bytes) work too. Binding beyond loopback needs CURVE keys
(:mod:`groundstation.bus.security`).

Drop policy per topic (:mod:`groundstation.bus.topics`). A high-water mark is a socket option,
so a publisher owns one XPUB socket per policy among its topics, and a subscriber one SUB per
policy; each SUB connects to every endpoint given and subscribes only to its policy's topics, so
a subscriber needs only the list of endpoints, not which one carries what.

- lossless: SNDHWM = RCVHWM = 0 (no limit, never drop). Memory bound: what a stalled but
  connected subscriber has not read, e.g. 200 Hz x ~300 B ~= 60 kB/s, ~200 MB per hour; a
  subscriber that exits frees its queue. Replay at max speed bounds it with credits (:mod:`flow`).
- latest: SNDHWM = RCVHWM = :data:`LATEST_HWM`. At the HWM ZeroMQ drops the *newest* message
  (STACK.md) and the subscriber's gap counter shows it; memory per subscriber is about
  2 x LATEST_HWM x the largest message (~40 MB for 5 MB meshes). State publishers republish on
  change or periodically, so a reader that catches up sees a recent value. (CONFLATE would keep
  the newest but breaks multipart messages.)

Ready handshake (slow joiner): XPUB with XPUB_VERBOSER passes every subscribe/unsubscribe up,
so :meth:`Publisher.wait_for_subscribers` blocks until ``n`` subscriptions per topic arrived;
once the XPUB has read a subscription, the next send reaches that subscriber (its filter is in
place), so seq 0 is not lost. A subscriber that joins a running stream sees ``first_seq > 0``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import numpy as np
import zmq

from groundstation.bus import security
from groundstation.bus.envelope import Envelope, EnvelopeError, Header, decode, encode
from groundstation.bus.errors import BusError, BusTimeoutError, SchemaError
from groundstation.bus.flow import CreditClient, CreditServer
from groundstation.bus.sequence import SequenceTracker, TopicStats
from groundstation.bus.topics import TOPICS, Topic, get_topic

DEFAULT_ENDPOINT = "tcp://127.0.0.1:*"
LATEST_HWM = 4
_POLICIES = ("lossless", "latest")


def derive_latest_endpoint(endpoint: str) -> str:
    """Endpoint for the latest-value socket of a publisher that also binds ``endpoint``.

    ``tcp://h:*`` -> ``tcp://h:*``; ``tcp://h:P`` -> ``tcp://h:P+1``; ``ipc://p`` -> ``ipc://p.latest``.
    """
    scheme, _, rest = endpoint.partition("://")
    if scheme == "tcp":
        host, _, port = rest.rpartition(":")
        return endpoint if port == "*" else f"tcp://{host}:{int(port) + 1}"
    return f"{endpoint}.latest"


class Publisher:
    """Publishes envelopes on declared topics, assigning per-topic sequence numbers from 0.

    Parameters
    ----------
    endpoint : str
        Bind endpoint of the first policy socket (lossless if any lossless topic).
    topics : iterable of str
        Topics this publisher may send (must be in ``table``).
    latest_endpoint : str, optional
        Bind endpoint of the latest-value socket when both policies are present
        (default :func:`derive_latest_endpoint`).
    server_keys : CurveKeys, optional
        CURVE server keys; required to bind beyond loopback.
    flow_window : int, optional
        Enable credit flow control (:mod:`flow`) on lossless topics with this window.
    flow_endpoint : str
        Bind endpoint of the flow back channel.
    flow_timeout_s : float
        Longest wait for credit before :class:`BusTimeoutError`.
    origin : int, optional
        Publisher instance id in headers (default: random uint32).
    context : zmq.Context, optional
        Shared context (default: a private one, terminated by :meth:`close`).
    table : mapping, optional
        Topic table (default :data:`TOPICS`).
    clock : callable
        ns clock for default ``source_ns`` (default ``time.monotonic_ns``).
    linger_ms : int
        How long :meth:`close` waits to flush queued messages.
    """

    def __init__(
        self,
        endpoint: str = DEFAULT_ENDPOINT,
        topics: Iterable[str] = (),
        *,
        latest_endpoint: str | None = None,
        server_keys: security.CurveKeys | None = None,
        flow_window: int | None = None,
        flow_endpoint: str = DEFAULT_ENDPOINT,
        flow_timeout_s: float = 30.0,
        origin: int | None = None,
        context: zmq.Context | None = None,
        table: Mapping[str, Topic] = TOPICS,
        clock: Callable[[], int] = time.monotonic_ns,
        linger_ms: int = 1000,
    ):
        self._table = table
        self.topics: dict[str, Topic] = {n: get_topic(n, table) for n in topics}
        if not self.topics:
            raise BusError("a Publisher needs at least one topic")
        policies = [p for p in _POLICIES if any(t.policy == p for t in self.topics.values())]
        binds = {policies[0]: endpoint}
        if len(policies) == 2:
            binds["latest"] = latest_endpoint or derive_latest_endpoint(endpoint)
        for ep in binds.values():
            security.check_bind(ep, server_keys)
        self._own_context = context is None
        self._ctx = context or zmq.Context()
        self._clock = clock
        self._linger_ms = linger_ms
        self.origin = int.from_bytes(os.urandom(4), "little") if origin is None else origin
        self._seq = dict.fromkeys(self.topics, 0)
        self._subs: dict[str, dict[bytes, int]] = {p: {} for p in binds}
        self._socks: dict[str, zmq.Socket] = {}
        self.flow: CreditServer | None = None
        self.flow_timeout_s = flow_timeout_s
        try:
            for policy, ep in binds.items():
                sock = self._ctx.socket(zmq.XPUB)
                sock.setsockopt(zmq.XPUB_VERBOSER, 1)
                sock.sndhwm = 0 if policy == "lossless" else LATEST_HWM
                sock.linger = linger_ms
                if server_keys is not None:
                    security.apply_server_keys(sock, server_keys)
                self._socks[policy] = sock
                sock.bind(ep)
            if flow_window is not None:
                self.flow = CreditServer(self._ctx, flow_endpoint, flow_window, server_keys)
        except Exception:
            self.close(linger_ms=0)
            raise
        self.endpoints: tuple[str, ...] = tuple(
            s.getsockopt_string(zmq.LAST_ENDPOINT) for s in self._socks.values()
        )

    # -- sending -------------------------------------------------------------------------------
    def publish(
        self,
        topic: str,
        payload: Mapping[str, Any] | None = None,
        arrays: Mapping[str, np.ndarray] | None = None,
        *,
        source_ns: int | None = None,
        recv_ns: int = 0,
    ) -> Envelope:
        """Validate, stamp with the next sequence number and send one message.

        Arrays are sent zero-copy: do not modify them after publishing. With flow control,
        blocks until the slowest consumer of a lossless topic is within the window.

        Returns
        -------
        Envelope
            The message as sent (header with ``seq``, ``source_ns``, ``origin``).
        """
        t = self.topics.get(topic)
        if t is None:
            raise SchemaError(
                f"topic {topic!r} is not one of this publisher's {sorted(self.topics)}"
            )
        payload, arrays = dict(payload or {}), dict(arrays or {})
        t.validate(payload, arrays)
        seq = self._seq[topic]
        src = self._clock() if source_ns is None else int(source_ns)
        header = Header(t.type, t.schema_version, seq, src, int(recv_ns), self.origin)
        env = Envelope(topic, header, payload, arrays)
        self._send(t, seq, encode(env))
        self._seq[topic] = seq + 1
        return env

    def republish(self, frames: Sequence[bytes | memoryview]) -> Envelope:
        """Send recorded frames byte-for-byte (their own origin and seq); validates them first."""
        env = decode(frames, self._table)
        t = self.topics.get(env.topic)
        if t is None:
            raise SchemaError(f"topic {env.topic!r} is not one of this publisher's topics")
        self._send(t, env.header.seq, list(frames))
        return env

    def _send(self, t: Topic, seq: int, frames: list) -> None:
        if self.flow is not None and t.policy == "lossless":
            self.flow.wait_for_credit(t.name, seq, self.flow_timeout_s)
        self._socks[t.policy].send_multipart(frames, copy=False)

    # -- ready handshake ----------------------------------------------------------------------
    def _drain_subscriptions(self) -> None:
        for policy, sock in self._socks.items():
            while True:
                try:
                    msg = sock.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                if msg[:1] in (b"\x00", b"\x01"):
                    subs = self._subs[policy]
                    subs[msg[1:]] = subs.get(msg[1:], 0) + (1 if msg[0] == 1 else -1)

    def subscriber_counts(self) -> dict[str, int]:
        """Current number of subscriptions matching each of this publisher's topics."""
        self._drain_subscriptions()
        out = {}
        for name, t in self.topics.items():
            key = name.encode()
            out[name] = sum(n for p, n in self._subs[t.policy].items() if key.startswith(p))
        return out

    def wait_for_subscribers(
        self, n: int = 1, topics: Iterable[str] | None = None, timeout_s: float = 10.0
    ) -> dict[str, int]:
        """Block until every topic in ``topics`` has >= ``n`` subscriptions (and, with flow
        control, ``n`` consumers registered). Raises :class:`BusTimeoutError` naming the
        topics still short."""
        names = list(self.topics if topics is None else topics)
        deadline = time.monotonic() + timeout_s
        poller = zmq.Poller()
        for s in self._socks.values():
            poller.register(s, zmq.POLLIN)
        while True:
            counts = self.subscriber_counts()
            short = {k: counts.get(k, 0) for k in names if counts.get(k, 0) < n}
            remaining = deadline - time.monotonic()
            if not short:
                break
            if remaining <= 0:
                raise BusTimeoutError(
                    f"waited {timeout_s} s for {n} subscriber(s); still short: {short} "
                    f"on {list(self.endpoints)}"
                )
            poller.poll(max(1, int(remaining * 1000)))
        if self.flow is not None:
            self.flow.wait_for_consumers(n, max(0.0, deadline - time.monotonic()))
        return counts

    def close(self, linger_ms: int | None = None) -> None:
        """Close sockets (flushing for ``linger_ms``) and a private context."""
        linger = self._linger_ms if linger_ms is None else linger_ms
        for s in self._socks.values():
            s.close(linger=linger)
        self._socks = {}
        if self.flow is not None:
            self.flow.close()
            self.flow = None
        if self._own_context:
            self._ctx.term()

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Subscriber:
    """Receives envelopes on chosen topics, counting sequence gaps per topic.

    Parameters
    ----------
    endpoints : str or sequence of str
        Publisher endpoints to connect to (all of them; see the module docstring).
    topics : iterable of str, optional
        Topics to receive (default: every topic of the table).
    server_public_key : bytes, optional
        CURVE public key of the publishers (needed when they are keyed).
    flow_endpoint : str, optional
        Publisher's flow back channel: registers this subscriber's lossless topics there.
    auto_ack : bool
        With flow control, acknowledge a message when the next :meth:`recv` is called
        (i.e. once it has been processed). Otherwise call :meth:`ack`.
    context, table, clock
        As for :class:`Publisher`; ``clock`` stamps ``recv_ns`` when a message has none.
    """

    def __init__(
        self,
        endpoints: str | Sequence[str],
        topics: Iterable[str] | None = None,
        *,
        server_public_key: bytes | None = None,
        flow_endpoint: str | None = None,
        auto_ack: bool = True,
        context: zmq.Context | None = None,
        table: Mapping[str, Topic] = TOPICS,
        clock: Callable[[], int] = time.monotonic_ns,
    ):
        eps = [endpoints] if isinstance(endpoints, str) else list(endpoints)
        for ep in eps:
            security.check_endpoint(ep)
        self._table = table
        names = table if topics is None else list(topics)
        self.topics: dict[str, Topic] = {n: get_topic(n, table) for n in names}
        self._own_context = context is None
        self._ctx = context or zmq.Context()
        self._clock = clock
        self.tracker = SequenceTracker()
        self.bad_messages = 0
        self.last_error: str | None = None
        self._socks: list[zmq.Socket] = []
        self._poller = zmq.Poller()
        self._rr = 0
        self._unacked: Envelope | None = None
        self._auto_ack = auto_ack
        self.flow: CreditClient | None = None
        try:
            for policy in _POLICIES:
                names = [n for n, t in self.topics.items() if t.policy == policy]
                if not names:
                    continue
                sock = self._ctx.socket(zmq.SUB)
                sock.rcvhwm = 0 if policy == "lossless" else LATEST_HWM
                sock.linger = 0
                if server_public_key is not None:
                    security.apply_client_keys(sock, server_public_key)
                for name in names:
                    sock.setsockopt(zmq.SUBSCRIBE, name.encode())
                for ep in eps:
                    sock.connect(ep)
                self._socks.append(sock)
                self._poller.register(sock, zmq.POLLIN)
            if flow_endpoint is not None:
                lossless = [n for n, t in self.topics.items() if t.policy == "lossless"]
                self.flow = CreditClient(self._ctx, flow_endpoint, lossless, server_public_key)
        except Exception:
            self.close()
            raise

    def recv_with_frames(self, timeout_ms: int | None = None) -> tuple[Envelope, list] | None:
        """Next valid message and its frames exactly as received (for recording), or None on
        timeout. Undecodable messages are skipped and counted (``bad_messages``, ``stats``)."""
        if self._auto_ack and self._unacked is not None:
            self.ack(self._unacked)
            self._unacked = None
        deadline = None if timeout_ms is None else time.monotonic() + timeout_ms / 1000
        while True:
            wait = None if deadline is None else max(0, int((deadline - time.monotonic()) * 1000))
            ready = dict(self._poller.poll(wait))
            if not ready:
                return None
            self._rr += 1
            order = (
                self._socks[self._rr % len(self._socks) :]
                + self._socks[: self._rr % len(self._socks)]
            )
            for sock in order:
                if sock in ready:
                    got = self._read(sock)
                    if got is not None:
                        if self.flow is not None and self._auto_ack:
                            self._unacked = got[0]
                        return got
            if wait == 0:
                return None

    def _read(self, sock: zmq.Socket) -> tuple[Envelope, list] | None:
        frames = [f.buffer for f in sock.recv_multipart(copy=False)]
        try:
            env = decode(frames, self._table)
            if env.topic not in self.topics:
                raise SchemaError(f"topic {env.topic!r} was not subscribed")
        except Exception as exc:  # noqa: BLE001 - any undecodable message is skipped, counted
            # decode raises only EnvelopeError (fuzzed), but a receiver must never die of a
            # message: anything else is counted the same way and named in last_error.
            self.bad_messages += 1
            kind = "" if isinstance(exc, EnvelopeError) else f"{type(exc).__name__}: "
            self.last_error = (kind + str(exc))[:300]
            name = bytes(frames[0][:64]).decode("utf-8", "replace") if frames else "?"
            self.tracker.bad(name if name in self.topics else "?")
            return None
        self.tracker.observe(env.topic, env.header.origin, env.header.seq)
        if env.header.recv_ns == 0:
            env = env.with_recv_ns(self._clock())
        return env, frames

    def recv(self, timeout_ms: int | None = None) -> Envelope | None:
        """Next valid message (``recv_ns`` stamped if it had none), or None after ``timeout_ms``
        (None: wait forever)."""
        got = self.recv_with_frames(timeout_ms)
        return None if got is None else got[0]

    def ack(self, env: Envelope) -> None:
        """Tell the publisher's flow control that ``env`` (and all before it) was processed."""
        if self.flow is not None and self.topics[env.topic].policy == "lossless":
            self.flow.ack(env.topic, env.header.seq)

    @property
    def stats(self) -> dict[str, TopicStats]:
        """Per-topic counters (see :class:`TopicStats`)."""
        return self.tracker.stats

    @property
    def gaps(self) -> dict[str, int]:
        """Missing messages per topic."""
        return {k: s.gaps for k, s in self.stats.items()}

    @property
    def received(self) -> dict[str, int]:
        """Received messages per topic."""
        return {k: s.received for k, s in self.stats.items()}

    @property
    def last_seq(self) -> dict[str, int]:
        """Last sequence number per topic."""
        return {k: s.last_seq for k, s in self.stats.items()}

    def close(self) -> None:
        """Unregister from flow control, close sockets and a private context."""
        if self.flow is not None:
            self.flow.close()
            self.flow = None
        for s in self._socks:
            s.close(linger=0)
        self._socks = []
        if self._own_context:
            self._ctx.term()

    def __enter__(self) -> Subscriber:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
