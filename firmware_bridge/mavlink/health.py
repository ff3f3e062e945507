"""Link health from decoded records and byte counts (pure: all times come in with the data).

Rates and bytes/s are counted over a sliding window of receive time ending at the newest receive
time seen; latency is receive time minus the source time mapped to the station clock by the
TIMESYNC offset (``latency = t_recv - (t_source - offset)``, offset = vehicle - station).
"""

from __future__ import annotations

import math
from collections import deque

from firmware_bridge.mavlink.codec import DecodeStats
from firmware_bridge.mavlink.messages import Record, Timesync, message_name


def percentile(values: list[int] | deque[int], q: float) -> int:
    """Nearest-rank percentile (q in [0, 100]) of a non-empty collection of integers."""
    s = sorted(values)
    k = max(0, min(len(s) - 1, math.ceil(q / 100.0 * len(s)) - 1))
    return s[k]


class LinkHealth:
    """Per-link health: rates, bytes/s, gaps, CRC errors, latency and inter-arrival percentiles.

    Parameters
    ----------
    window_s : float
        Sliding window for rates and bytes/s, s (of receive time).
    history : int
        Number of latency / inter-arrival samples kept per statistic for percentiles.
    """

    def __init__(self, window_s: float = 2.0, history: int = 2000) -> None:
        if not window_s > 0 or history < 1:
            raise ValueError(f"LinkHealth: window_s={window_s} must be > 0, history={history} >= 1")
        self.window_ns = int(window_s * 1e9)
        self.history = history
        self._arrivals: dict[str, deque[int]] = {}
        self._intervals: dict[str, deque[int]] = {}
        self._bytes: deque[tuple[int, int]] = deque()
        self._bytes_in_window = 0
        self._latency: deque[int] = deque(maxlen=history)
        self._first_ns: int | None = None
        self.now_ns = 0
        self.total_bytes = 0
        self.total_records = 0
        self.stats = DecodeStats()

    def _tick(self, recv_ns: int) -> None:
        if self._first_ns is None:
            self._first_ns = recv_ns
        if recv_ns > self.now_ns:
            self.now_ns = recv_ns

    def on_bytes(self, n: int, recv_ns: int) -> None:
        """Count ``n`` bytes received at ``recv_ns`` (station monotonic ns)."""
        self._tick(recv_ns)
        self.total_bytes += n
        self._bytes.append((recv_ns, n))
        self._bytes_in_window += n

    def on_record(self, record: Record, offset_ns: int | None = None) -> None:
        """Count a decoded record; with a TIMESYNC ``offset_ns`` (vehicle - station) add latency."""
        t = record.time_recv_ns
        self._tick(t)
        self.total_records += 1
        name = message_name(record)
        arr = self._arrivals.get(name)
        if arr is None:
            arr = self._arrivals[name] = deque()
            self._intervals[name] = deque(maxlen=self.history)
        elif arr:
            self._intervals[name].append(t - arr[-1])
        arr.append(t)
        if offset_ns is not None and record.time_source_ns and not isinstance(record, Timesync):
            self._latency.append(t - (record.time_source_ns - offset_ns))

    def on_stats(self, stats: DecodeStats) -> None:
        """Take the decoder's counters (CRC errors, gaps, garbage) as of now."""
        self.stats = stats.copy()

    def _prune(self) -> None:
        cut = self.now_ns - self.window_ns
        for arr in self._arrivals.values():
            while arr and arr[0] <= cut:
                arr.popleft()
        while self._bytes and self._bytes[0][0] <= cut:
            self._bytes_in_window -= self._bytes.popleft()[1]

    def _span_s(self) -> float:
        if self._first_ns is None:
            return 0.0
        return min(self.window_ns, self.now_ns - self._first_ns) / 1e9

    def rates(self) -> dict[str, float]:
        """Messages per second per message name over the window (Hz)."""
        self._prune()
        span = self._span_s()
        if span <= 0:
            return {k: 0.0 for k in self._arrivals}
        return {k: len(v) / span for k, v in self._arrivals.items()}

    def bytes_per_s(self) -> float:
        """Received bytes per second over the window."""
        self._prune()
        span = self._span_s()
        return self._bytes_in_window / span if span > 0 else 0.0

    def latency_ns(self) -> tuple[int, int] | None:
        """(p50, p99) of receive latency in ns, or None without TIMESYNC-corrected samples."""
        if not self._latency:
            return None
        return percentile(self._latency, 50), percentile(self._latency, 99)

    def interarrival_ns(self, name: str) -> tuple[int, int] | None:
        """(p50, p99) of receive-time intervals between consecutive ``name`` messages, ns."""
        iv = self._intervals.get(name)
        if not iv:
            return None
        return percentile(iv, 50), percentile(iv, 99)

    def loss_fraction(self) -> float:
        """Frames lost (MAVLink sequence gaps) over frames sent, since the link opened."""
        lost = self.stats.lost
        return lost / (lost + self.total_records) if lost + self.total_records else 0.0

    def summary(self) -> str:
        """One status line: rates, bytes/s, lost frames, CRC errors, garbage, latency."""
        parts = [f"{k} {v:.1f}Hz" for k, v in sorted(self.rates().items())]
        parts.append(f"{self.bytes_per_s() / 1000:.1f}kB/s")
        st = self.stats
        loss = f" ({100 * self.loss_fraction():.2f}%)" if st.lost else ""
        parts.append(f"lost {st.lost}{loss} crc {st.crc_errors} garbage {st.garbage_bytes}B")
        if st.rejected_signature:
            parts.append(f"badsig {st.rejected_signature}")
        lat = self.latency_ns()
        if lat is not None:
            parts.append(f"latency p50 {lat[0] / 1e6:.2f}ms p99 {lat[1] / 1e6:.2f}ms")
        return " | ".join(parts)
