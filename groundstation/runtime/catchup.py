"""Catch up after a restart: what a worker missed while it was down, from the recorded stream.

A restarted detector or mapper subscribes again and from then on receives every message live;
what was published while it was down (and, for the detector, after its last checkpoint) is in
the session's recording, which the recorder keeps writing meanwhile. Messages are identified by
their stream, (topic, publisher origin), and the sequence number the publisher gave them:

- :class:`GapPlan` (pure) knows what the worker had consumed (per stream, the last sequence)
  and the first sequence it received live on each stream; a recorded message fills the gap
  when it lies strictly between the two. It also says whether the recording reaches the last
  message before each first live one (the recorder closes a chunk at least once a second, so
  the tail may take a moment to appear on disk).
- :func:`catch_up` (the shell) reads the recording, buffers what arrives live meanwhile, and
  re-reads until the gap is covered or ``deadline_s`` passes; what is still missing then is
  reported as lost (counted, never silent).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from groundstation.acquisition.segments import GrowingSession
from groundstation.bus.envelope import Envelope, from_bytes

StreamKey = tuple[str, int]  # (topic, origin)


def stream_key(env: Envelope) -> StreamKey:
    """The stream a message belongs to: (topic, publisher origin)."""
    return env.topic, int(env.header.origin)


class GapPlan:
    """Which recorded messages fill the gap between consumed and live (pure).

    Parameters
    ----------
    consumed : mapping of (topic, origin) to int
        Last sequence number processed per stream before the restart (empty: nothing).
    """

    def __init__(self, consumed: dict[StreamKey, int] | None = None) -> None:
        self.consumed = dict(consumed or {})
        self.first_live: dict[StreamKey, int] = {}
        self.collected: dict[StreamKey, int] = {}

    def live(self, env: Envelope) -> None:
        """Note a message received live (the first one of a stream marks where live begins)."""
        self.first_live.setdefault(stream_key(env), int(env.header.seq))

    def wanted(self, env: Envelope) -> bool:
        """Whether a recorded message fills the gap (and note it as collected)."""
        key, seq = stream_key(env), int(env.header.seq)
        if seq <= self.consumed.get(key, -1):
            return False
        first = self.first_live.get(key)
        if first is not None and seq >= first:
            return False
        if seq > self.collected.get(key, -1):
            self.collected[key] = seq
        return True

    def missing(self) -> dict[StreamKey, int]:
        """Messages per live stream the recording does not (yet) hold before its first live
        one."""
        out = {}
        for key, first in self.first_live.items():
            have = max(self.consumed.get(key, -1), self.collected.get(key, -1))
            if first - 1 > have:
                out[key] = first - 1 - have
        return out

    def reset_collected(self) -> None:
        self.collected = {}


@dataclasses.dataclass
class CatchUpResult:
    """What :func:`catch_up` found.

    Attributes
    ----------
    recorded : list of Envelope
        Messages that fill the gap, in log-time order.
    live : list of Envelope
        Messages received live meanwhile, in arrival order (process after ``recorded``).
    lost : dict
        Messages per stream neither recorded nor received live (``"topic@origin": n``).
    reads : int
        Times the recording was read.
    waited_s : float
        Wall time spent.
    error : str or None
        Why the recording could not be read (then everything before live is lost).
    """

    recorded: list[Envelope]
    live: list[Envelope]
    lost: dict[str, int]
    reads: int
    waited_s: float
    error: str | None = None


def read_recorded(
    source: GrowingSession | str | Path,
    topics: Sequence[str],
    since_ns: int | None,
    plan: GapPlan,
) -> list[Envelope]:
    """Envelopes of ``topics`` recorded at or after log time ``since_ns`` that fill ``plan``'s
    gap, in log-time order (a segment still being written is read up to its last chunk).
    ``source``: a :class:`~groundstation.acquisition.segments.GrowingSession` to read again
    cheaply, or the recording's path."""
    if not isinstance(source, GrowingSession):
        with GrowingSession(source) as grow:
            return read_recorded(grow, topics, since_ns, plan)
    plan.reset_collected()
    out = []
    start = None if since_ns is None else max(0, since_ns)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the open segment reads as truncated: expected
        for m in source.session().messages(list(topics), start):
            try:
                env = from_bytes(m.data)
            except Exception:  # noqa: BLE001 - a damaged message: skip, it counts as missing
                continue
            if plan.wanted(env):
                out.append(env)
    return out


def catch_up(
    path: str | Path,
    topics: Sequence[str],
    plan: GapPlan,
    receive: Callable[[int], Envelope | None],
    *,
    since_ns: int | None = None,
    stop: Callable[[], bool] = lambda: False,
    settle_s: float = 0.3,
    poll_s: float = 0.4,
    deadline_s: float = 8.0,
    clock: Callable[[], float] = time.monotonic,
    on_wait: Callable[[], None] | None = None,
) -> CatchUpResult:
    """Fill the gap of ``plan`` from the recording at ``path`` while buffering live messages.

    Parameters
    ----------
    path : path
        The session's recording (its first segment or folder).
    topics : sequence of str
        Topics to catch up on (live messages of other topics are buffered too).
    plan : GapPlan
        What was consumed before the restart.
    receive : callable
        ``receive(timeout_ms) -> Envelope | None``: the worker's live subscriber.
    since_ns : int, optional
        Read the recording from this log time (default: from its start).
    stop : callable
        Give up at once when it returns True (a stop signal).
    settle_s : float
        Live time to wait before the first read, so that each stream's first live message is
        known.
    poll_s, deadline_s : float
        Re-read interval while the recording does not yet reach live, and the longest wait.
    on_wait : callable, optional
        Called between reads (the worker publishes its status meanwhile).
    """
    t0 = clock()
    live: list[Envelope] = []

    def pump(until: float) -> None:
        while not stop():
            left = until - clock()
            env = receive(max(0, int(left * 1000)))
            if env is not None:
                plan.live(env)
                live.append(env)
            elif left <= 0:
                return

    pump(t0 + settle_s)
    recorded: list[Envelope] = []
    reads, error = 0, None
    grow = GrowingSession(path)  # finished segments are read once, the newest when it grew
    try:
        while not stop():
            try:
                recorded = read_recorded(grow, topics, since_ns, plan)
                error = None
            except Exception as exc:  # noqa: BLE001 - no file yet, unreadable: retry, report
                error = f"{type(exc).__name__}: {exc}"
            reads += 1
            if error is None and not {k: n for k, n in plan.missing().items() if k[0] in topics}:
                break
            if clock() - t0 >= deadline_s:
                break
            if on_wait is not None:
                on_wait()
            pump(clock() + poll_s)
    finally:
        grow.close()
    lost = {f"{k[0]}@{k[1]:08x}": n for k, n in plan.missing().items() if k[0] in topics}
    return CatchUpResult(recorded, live, lost, reads, clock() - t0, error)


def last_positions(envs: Iterable[Envelope]) -> dict[StreamKey, int]:
    """Newest sequence number per stream in ``envs``."""
    out: dict[StreamKey, int] = {}
    for env in envs:
        key = stream_key(env)
        if env.header.seq > out.get(key, -1):
            out[key] = int(env.header.seq)
    return out
