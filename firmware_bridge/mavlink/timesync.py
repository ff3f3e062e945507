"""Vehicle clock offset from TIMESYNC round trips (pure; times come in with the data).

MAVLink TIMESYNC: the station sends ``tc1 = 0, ts1 = t0`` (its clock, ns); the vehicle answers
``tc1 = t_v`` (its clock at reply), ``ts1 = t0`` echoed; the station receives it at ``t3``.
NTP-style estimate for one round trip (RFC 5905 section 8, with the vehicle's receive and send
times collapsed into one stamp t_v):

    rtt    = t3 - t0
    offset = t_v - (t0 + t3) / 2          (vehicle clock minus station clock)

The error of one sample is bounded by rtt / 2, so the filter keeps the offset of the smallest-RTT
sample in a sliding window of the last ``window`` accepted samples (Mills' clock filter). A vehicle
reboot (a persistent offset step larger than ``jump_threshold_ns``) restarts the window.
"""

from __future__ import annotations

from collections import deque

from firmware_bridge.errors import BridgeError
from firmware_bridge.mavlink.messages import Timesync


class NotSyncedError(BridgeError, RuntimeError):
    """No accepted TIMESYNC round trip yet, so vehicle time cannot be mapped to station time."""


class TimesyncEstimator:
    """Minimum-RTT clock-offset filter over a sliding window of TIMESYNC round trips.

    Parameters
    ----------
    window : int
        Number of most recent accepted samples the minimum-RTT choice looks at.
    max_rtt_ns : int
        Round trips longer than this (or negative) are rejected and counted.
    jump_threshold_ns : int
        An offset differing from the estimate by more than this on ``jump_confirm`` consecutive
        samples is taken as a vehicle clock step (reboot): the window restarts.
    jump_confirm : int
        Consecutive samples needed to accept a clock step.
    """

    def __init__(
        self,
        window: int = 16,
        max_rtt_ns: int = 500_000_000,
        jump_threshold_ns: int = 100_000_000,
        jump_confirm: int = 3,
    ) -> None:
        if window < 1 or jump_confirm < 1 or max_rtt_ns <= 0 or jump_threshold_ns <= 0:
            raise ValueError(
                f"TimesyncEstimator: window={window}, jump_confirm={jump_confirm} must be >= 1 and "
                f"max_rtt_ns={max_rtt_ns}, jump_threshold_ns={jump_threshold_ns} must be > 0"
            )
        self.window = window
        self.max_rtt_ns = max_rtt_ns
        self.jump_threshold_ns = jump_threshold_ns
        self.jump_confirm = jump_confirm
        self._samples: deque[tuple[int, int]] = deque(maxlen=window)  # (rtt_ns, offset_ns)
        self._pending_jump: list[tuple[int, int]] = []
        self.offset_ns: int | None = None
        self.rtt_ns: int | None = None
        self.accepted = 0
        self.rejected = 0
        self.clock_steps = 0

    @property
    def synced(self) -> bool:
        """True once at least one round trip was accepted."""
        return self.offset_ns is not None

    def add(self, sent_ns: int, vehicle_ns: int, recv_ns: int) -> bool:
        """Add one round trip; return True if it was accepted.

        Parameters
        ----------
        sent_ns : int
            Station time the request left (``ts1``), ns.
        vehicle_ns : int
            Vehicle time in the reply (``tc1``), ns.
        recv_ns : int
            Station time the reply arrived, ns.
        """
        rtt = recv_ns - sent_ns
        if rtt < 0 or rtt > self.max_rtt_ns:
            self.rejected += 1
            return False
        offset = vehicle_ns - (sent_ns + recv_ns) // 2
        self.accepted += 1
        if self.offset_ns is not None and abs(offset - self.offset_ns) > self.jump_threshold_ns:
            self._pending_jump.append((rtt, offset))
            if len(self._pending_jump) < self.jump_confirm:
                return True
            self._samples.clear()  # confirmed step: forget the old clock
            self._samples.extend(self._pending_jump)
            self.clock_steps += 1
        else:
            self._samples.append((rtt, offset))
        self._pending_jump.clear()
        self.rtt_ns, self.offset_ns = min(self._samples)
        return True

    def observe(self, reply: Timesync) -> bool:
        """Add a TIMESYNC reply record (``tc1 != 0``) using its ``time_recv_ns``."""
        if reply.tc1 == 0:
            return False
        return self.add(reply.ts1, reply.tc1, reply.time_recv_ns)

    def to_station_ns(self, vehicle_ns: int) -> int:
        """Map a vehicle timestamp (ns) to the station's monotonic clock (ns).

        Raises
        ------
        NotSyncedError
            Before the first accepted round trip.
        """
        if self.offset_ns is None:
            raise NotSyncedError(
                "no TIMESYNC round trip yet: vehicle time cannot be mapped to station time",
                hint="send TIMESYNC requests (MavlinkEndpoint does, once a second) and wait",
            )
        return vehicle_ns - self.offset_ns
