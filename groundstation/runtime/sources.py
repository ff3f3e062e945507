"""Sources by URI: which worker process owns a ``serial://``, ``udp://``, ``natnet://`` or
``replay://`` source, and with which arguments.

Each factory class answers for its schemes and raises :class:`NotMySchemeError` otherwise; the
first that accepts wins (model: cflib ``crtp.get_link_driver``). A factory returns a
:class:`~groundstation.runtime.supervisor.WorkerSpec` that runs the source's process in the
session, so ``groundstation record`` (and later ``live``/``replay``) only list URIs.

=================================  ======  ========================================
URI                                role    process
=================================  ======  ========================================
``serial:///dev/ttyUSB0?...``      link    ``groundstation.runtime.workers.link``
``udp://0.0.0.0:14550``            link    ``groundstation.runtime.workers.link``
``natnet://239.255.42.99:1511``    mocap   ``groundstation.runtime.workers.mocap``
``replay://flight.mcap?...``       replay  ``groundstation.runtime.workers.replay``
=================================  ======  ========================================

``replay://`` takes the path after ``//`` (``replay://flight.mcap`` is relative to the working
directory, ``replay:///abs/flight.mcap`` absolute) and ``speed`` (``1`` default, a positive
number, or ``max``), ``start`` and ``end`` (seconds from the log start).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from urllib.parse import parse_qsl, unquote, urlsplit

from firmware_bridge.errors import UriError
from firmware_bridge.link.base import parse_uri
from groundstation.runtime.session import Session
from groundstation.runtime.supervisor import WorkerSpec, python_module

REPLAY_EXAMPLE = "replay://flight.mcap?speed=max&start=10&end=70"


class NotMySchemeError(UriError):
    """A factory does not handle this URI's scheme (the next factory is asked)."""


@dataclass(frozen=True)
class ReplayOptions:
    """A parsed ``replay://`` URI: path, speed (``math.inf`` = max), window in seconds."""

    path: str
    speed: float = 1.0
    start_s: float | None = None
    end_s: float | None = None


def parse_replay_uri(uri: str) -> ReplayOptions:
    """Parse ``replay://PATH?speed=1|X|max&start=S&end=S``; raises :class:`UriError`."""
    parts = urlsplit(uri)
    if parts.scheme != "replay":
        raise NotMySchemeError(f"{uri!r} is not a replay:// URI", hint=f"e.g. {REPLAY_EXAMPLE}")
    path = unquote(parts.netloc + parts.path)
    if not path:
        raise UriError(f"bad replay URI {uri!r}: no file", hint=f"e.g. {REPLAY_EXAMPLE}")
    query = dict(parse_qsl(parts.query, keep_blank_values=True))
    unknown = set(query) - {"speed", "start", "end"}
    if unknown:
        raise UriError(
            f"bad replay URI {uri!r}: unknown parameter(s) {sorted(unknown)}",
            hint=f"known: speed, start, end; e.g. {REPLAY_EXAMPLE}",
        )

    def number(name: str, allow_max: bool = False) -> float | None:
        raw = query.get(name)
        if raw is None:
            return None
        if allow_max and raw == "max":
            return math.inf
        try:
            value = float(raw)
        except ValueError:
            raise UriError(
                f"bad replay URI {uri!r}: {name}={raw!r} is not a number",
                hint=f"e.g. {REPLAY_EXAMPLE}",
            ) from None
        if not math.isfinite(value) or value < 0 or (name == "speed" and value == 0):
            raise UriError(f"bad replay URI {uri!r}: {name}={raw!r} out of range")
        return value

    speed = number("speed", allow_max=True)
    start, end = number("start"), number("end")
    if start is not None and end is not None and end <= start:
        raise UriError(f"bad replay URI {uri!r}: end={end} must come after start={start}")
    return ReplayOptions(path, 1.0 if speed is None else speed, start, end)


class LinkSource:
    """serial:// and udp:// firmware links -> the link process."""

    schemes = ("serial", "udp")
    module = "groundstation.runtime.workers.link"

    @classmethod
    def worker(cls, uri: str, session: Session, name: str, extra: tuple[str, ...]) -> WorkerSpec:
        p = parse_uri(uri)
        if p.scheme not in cls.schemes:
            raise NotMySchemeError(f"{uri!r}: not a firmware link scheme {cls.schemes}")
        argv = python_module(cls.module, *session.as_args(), "--link", uri, "--name", name, *extra)
        return WorkerSpec(name, argv)


class MocapSource:
    """natnet:// motion capture -> the mocap process."""

    schemes = ("natnet",)
    module = "groundstation.runtime.workers.mocap"

    @classmethod
    def worker(cls, uri: str, session: Session, name: str, extra: tuple[str, ...]) -> WorkerSpec:
        p = parse_uri(uri)
        if p.scheme not in cls.schemes:
            raise NotMySchemeError(f"{uri!r}: not a mocap scheme {cls.schemes}")
        argv = python_module(cls.module, *session.as_args(), "--mocap", uri, "--name", name, *extra)
        return WorkerSpec(name, argv)


class ReplaySourceFactory:
    """replay:// recordings -> the replay process (runs once: not restarted)."""

    schemes = ("replay",)
    module = "groundstation.runtime.workers.replay"

    @classmethod
    def worker(cls, uri: str, session: Session, name: str, extra: tuple[str, ...]) -> WorkerSpec:
        parse_replay_uri(uri)  # NotMySchemeError / UriError early, in the caller's process
        argv = python_module(cls.module, *session.as_args(), "--uri", uri, "--name", name, *extra)
        return WorkerSpec(name, argv, restart=False)


FACTORIES = (LinkSource, MocapSource, ReplaySourceFactory)


def source_worker(uri: str, session: Session, name: str, extra: tuple[str, ...] = ()) -> WorkerSpec:
    """The worker that owns ``uri`` in ``session``, named ``name`` (its bus endpoint).

    Raises
    ------
    UriError
        Malformed URI, or no factory handles its scheme (the message lists the known ones).
    """
    for factory in FACTORIES:
        try:
            return factory.worker(uri, session, name, extra)
        except NotMySchemeError:
            continue
    known = [s for f in FACTORIES for s in f.schemes]
    raise UriError(
        f"no source handles {uri!r} (known schemes: {', '.join(known)})",
        hint="e.g. serial:///dev/ttyUSB0?baud=921600, natnet://239.255.42.99:1511, "
        + REPLAY_EXAMPLE,
    )
