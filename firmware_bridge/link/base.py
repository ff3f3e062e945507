"""Links chosen by URI behind one small interface, and the lazy scheme -> class factory.

A link moves raw bytes; it knows nothing of MAVLink. ``read`` blocks in the kernel (select/poll)
for at most ``timeout_s`` and returns ``b""`` on timeout; it never sleep-polls. State changes
(disconnected, reconnected, errors) are recorded as :class:`LinkEvent` in ``link.events``.
"""

from __future__ import annotations

import abc
import importlib
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from types import TracebackType
from urllib.parse import parse_qsl, urlsplit

from firmware_bridge.errors import LinkError, UriError

#: scheme -> "module:Class"; modules are imported only when their scheme is opened.
LINK_CLASSES: dict[str, str] = {
    "serial": "firmware_bridge.link.serial_link:SerialLink",
    "udp": "firmware_bridge.link.udp_link:UdpLink",
    "natnet": "firmware_bridge.natnet.link:NatNetLink",
}

URI_EXAMPLES = (
    "serial:///dev/ttyUSB0?baud=921600, udp://0.0.0.0:14550 (listen), "
    "udp://192.168.1.10:14550 (send), natnet://239.255.42.99:1511"
)


@dataclass(frozen=True)
class ParsedUri:
    """A link URI split into parts; ``query`` maps each parameter to its (last) value."""

    scheme: str
    host: str
    port: int | None
    path: str
    query: dict[str, str] = field(default_factory=dict)
    uri: str = ""

    def error(self, problem: str, example: str | None = None) -> UriError:
        """A :class:`UriError` naming this URI, the problem and a good example."""
        return UriError(
            f"bad link URI {self.uri!r}: {problem}", hint=f"e.g. {example or URI_EXAMPLES}"
        )

    def int_param(self, name: str, default: int, lo: int = 1, example: str | None = None) -> int:
        """Integer query parameter ``name`` (>= lo), or ``default`` when absent."""
        raw = self.query.get(name)
        if raw is None:
            return default
        try:
            value = int(raw)
        except ValueError:
            raise self.error(f"{name}={raw!r} is not an integer", example) from None
        if value < lo:
            raise self.error(f"{name}={value} must be >= {lo}", example)
        return value

    def float_param(self, name: str, default: float, example: str | None = None) -> float:
        """Positive float query parameter ``name``, or ``default`` when absent."""
        raw = self.query.get(name)
        if raw is None:
            return default
        try:
            value = float(raw)
        except ValueError:
            raise self.error(f"{name}={raw!r} is not a number", example) from None
        if not value > 0:
            raise self.error(f"{name}={value} must be > 0", example)
        return value


def parse_uri(uri: str) -> ParsedUri:
    """Split ``scheme://host:port/path?key=value`` (no scheme-specific checks).

    Raises
    ------
    UriError
        Not a string, no ``scheme://``, or a port that is not an integer in 0..65535.
    """
    if not isinstance(uri, str) or "://" not in uri:
        raise UriError(f"bad link URI {uri!r}: expected scheme://...", hint=f"e.g. {URI_EXAMPLES}")
    parts = urlsplit(uri)
    try:
        port = parts.port
    except ValueError as exc:
        raise UriError(f"bad link URI {uri!r}: {exc}", hint=f"e.g. {URI_EXAMPLES}") from None
    return ParsedUri(
        scheme=parts.scheme.lower(),
        host=parts.hostname or "",
        port=port,
        path=parts.path,
        query=dict(parse_qsl(parts.query, keep_blank_values=True)),
        uri=uri,
    )


def link_class(scheme: str, uri: str = "") -> type:
    """Import and return the link class registered for ``scheme`` (lazily)."""
    target = LINK_CLASSES.get(scheme)
    if target is None:
        raise UriError(
            f"bad link URI {uri!r}: unknown scheme {scheme!r} (known: {', '.join(LINK_CLASSES)})",
            hint=f"e.g. {URI_EXAMPLES}",
        )
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise LinkError(f"link for {scheme}:// is not available ({module_name}): {exc}") from exc
    return getattr(module, class_name)


@dataclass(frozen=True)
class LinkOptions:
    """Settings a link takes besides its URI.

    Attributes
    ----------
    allow_peers : tuple of str
        UDP links: senders accepted (``"host"`` or ``"host:port"``); empty = lock to the first
        vehicle heard (:class:`firmware_bridge.link.peer.PeerLock`). Other links ignore it.
    vehicle_system_id : int
        UDP links: lock only to this MAVLink system id (0 = the first one heard).
    """

    allow_peers: tuple[str, ...] = ()
    vehicle_system_id: int = 0


def open_link(uri: str, options: LinkOptions | None = None) -> Link:
    """Open a link by URI: ``serial:///dev/ttyUSB0?baud=921600``, ``udp://0.0.0.0:14550``, ...

    Parameters
    ----------
    uri : str
        The link URI.
    options : LinkOptions, optional
        Peer lock / allow-list of UDP links (default: lock to the first vehicle heard).

    Raises
    ------
    UriError
        Malformed URI or unknown scheme (message names the URI and shows good ones).
    LinkError
        The device or socket cannot be opened.
    """
    parsed = parse_uri(uri)
    cls = link_class(parsed.scheme, uri)
    return cls(parsed) if options is None else cls(parsed, options=options)


@dataclass(frozen=True)
class LinkEvent:
    """A link state change: ``kind`` (opened, disconnected, reconnected, reconnect_failed,
    read_error, write_error, write_dropped, closed), detail text, station monotonic time (ns)."""

    kind: str
    detail: str
    time_ns: int


class Link(abc.ABC):
    """Byte link. Subclasses implement ``read``, ``write`` and ``close``.

    One thread may ``read`` while others ``write``; ``events`` is safe to read from any thread.
    """

    def __init__(self, parsed: ParsedUri, max_events: int = 1000) -> None:
        self.uri = parsed.uri
        self.parsed = parsed
        self._events: deque[LinkEvent] = deque(maxlen=max_events)
        self._event_cond = threading.Condition()
        self._event_count = 0
        self._events_polled = 0

    @abc.abstractmethod
    def read(self, timeout_s: float) -> bytes:
        """Bytes received within ``timeout_s`` seconds, ``b""`` on timeout."""

    @abc.abstractmethod
    def write(self, data: bytes) -> bool:
        """Send bytes; True when they went out. A drop (no peer or device yet, a send error)
        returns False and is counted in ``dropped_writes`` (errors also as events), never
        raised."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device/socket; idempotent."""

    @property
    def events(self) -> list[LinkEvent]:
        """All recorded events (oldest first, bounded history)."""
        with self._event_cond:
            return list(self._events)

    def poll_events(self) -> list[LinkEvent]:
        """Events recorded since the previous call to ``poll_events``."""
        with self._event_cond:
            new = min(self._event_count - self._events_polled, len(self._events))
            self._events_polled = self._event_count
            return list(self._events)[len(self._events) - new :] if new else []

    def wait_for_event(self, kind: str, timeout_s: float, after: int = 0) -> LinkEvent | None:
        """Block until the ``after``-th-or-later event of ``kind`` exists (counting from 0 in
        ``events``), up to ``timeout_s``; return it or None on timeout."""

        def find() -> LinkEvent | None:
            hits = [e for e in self._events if e.kind == kind]
            return hits[after] if len(hits) > after else None

        with self._event_cond:
            self._event_cond.wait_for(lambda: find() is not None, timeout=timeout_s)
            return find()

    def _emit(self, kind: str, detail: str = "") -> None:
        with self._event_cond:
            self._events.append(LinkEvent(kind, detail, time.monotonic_ns()))
            self._event_count += 1
            self._event_cond.notify_all()

    def __enter__(self) -> Link:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.uri!r})"
