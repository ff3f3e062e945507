"""Per-topic sequence accounting (pure): received, gaps, first/last sequence, bad messages.

Sequence numbers count per (topic, origin) from 0 (see :class:`~groundstation.bus.envelope.Header`).
ZeroMQ never reorders messages within one connection, so for one origin:

- ``seq == last + 1``: in order;
- ``seq > last + 1``: ``seq - last - 1`` messages were lost (``gaps``);
- ``seq <= last``: the stream went backwards (a replay restarted or a publisher reused its
  origin); counted in ``resets`` and not as a gap.

A stream's first message defines its baseline: ``first_seq > 0`` means the subscriber joined
late (start-up loss is visible, not silent). A new origin on a topic is a new stream.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass
class TopicStats:
    """Counters of one topic, summed over its origins.

    Attributes
    ----------
    received : int
        Messages accepted.
    gaps : int
        Messages missing between consecutive received sequence numbers.
    last_seq, first_seq : int
        Sequence number of the latest / first message received (-1 before any).
    streams : int
        Distinct origins seen.
    resets : int
        Times a stream's sequence went backwards.
    bad : int
        Messages on this topic that failed to decode or validate (skipped).
    """

    received: int = 0
    gaps: int = 0
    last_seq: int = -1
    first_seq: int = -1
    streams: int = 0
    resets: int = 0
    bad: int = 0

    def as_dict(self) -> dict[str, int]:
        """JSON-ready counters (for the ``status`` topic)."""
        return asdict(self)


class SequenceTracker:
    """Counts gaps per topic from (topic, origin, seq) triples; no I/O, no clock."""

    def __init__(self) -> None:
        self._last: dict[tuple[str, int], int] = {}
        self.stats: dict[str, TopicStats] = {}

    def observe(self, topic: str, origin: int, seq: int) -> int:
        """Account one received message; returns the number of messages newly found missing."""
        st = self.stats.setdefault(topic, TopicStats())
        st.received += 1
        key = (topic, origin)
        last = self._last.get(key)
        self._last[key] = seq
        st.last_seq = seq
        if last is None:
            st.streams += 1
            if st.first_seq < 0:
                st.first_seq = seq
            return 0
        if seq <= last:
            st.resets += 1
            return 0
        missing = seq - last - 1
        st.gaps += missing
        return missing

    def bad(self, topic: str) -> None:
        """Count a message on ``topic`` that could not be decoded or validated."""
        self.stats.setdefault(topic, TopicStats()).bad += 1

    def total_gaps(self) -> int:
        """Gaps summed over all topics."""
        return sum(s.gaps for s in self.stats.values())
