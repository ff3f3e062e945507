"""Pair samples from different streams on one time axis.

The aligner answers "where was the vehicle, and how was it oriented, at time t?" from a stream of
timestamped poses (mocap rigid bodies, or firmware attitude), by linear interpolation of position
and spherical linear interpolation (slerp) of orientation between the two poses that bracket t.

It never reads a clock: every time is an integer nanosecond on the *station* time axis, supplied by
the caller (a mocap pose's receive time, or a firmware sample's source time mapped through the
TIMESYNC offset). Two settings make the pairing explicit:

* ``max_gap_ns``: if the bracketing poses are further apart than this (dropped mocap frames,
  occlusion), or t lies outside the buffered span by more than ``max_extrapolation_ns``, the answer
  is :class:`NoPose` with the reason, never a silently stale pose.
* ``latency_ns``: mocap latency compensation. A pose stamped at receive time r describes the vehicle
  at r - latency, so poses are stored at ``t_insert - latency_ns``.

Quaternions are (w, x, y, z), unit norm; positions metres.
"""

from __future__ import annotations

import bisect
import dataclasses
import math

import numpy as np

from groundstation.errors import InputDataError


@dataclasses.dataclass(frozen=True, slots=True)
class Pose:
    """A pose at a time on the station axis.

    Attributes
    ----------
    t_ns : int
        Station time, ns.
    position : (3,) float64 ndarray
        Metres, world frame.
    quaternion : (4,) float64 ndarray
        (w, x, y, z), body to world.
    gap_ns : int
        Spacing of the two poses it was interpolated from (0 for an exact hit).
    """

    t_ns: int
    position: np.ndarray
    quaternion: np.ndarray
    gap_ns: int = 0


@dataclasses.dataclass(frozen=True, slots=True)
class NoPose:
    """No trustworthy pose at ``t_ns``; ``reason`` says why ("gap", "before", "after", "empty")."""

    t_ns: int
    reason: str
    gap_ns: int = 0

    def __bool__(self) -> bool:  # so that ``if pose:`` reads naturally
        return False


def slerp(q0: np.ndarray, q1: np.ndarray, f: float) -> np.ndarray:
    """Spherical linear interpolation between unit quaternions (w, x, y, z), shortest arc.

    Parameters
    ----------
    q0, q1 : (4,) array
        Unit quaternions.
    f : float
        Fraction in [0, 1]; 0 gives q0, 1 gives q1.
    """
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    dot = float(q0.dot(q1))  # = np.dot for 1-D arrays; this runs once per IMU sample
    if dot < 0.0:  # q and -q are the same rotation: take the short way round
        q1 = -q1
        dot = -dot
    if dot > 0.9995:  # nearly parallel: normalised lerp is exact to ~1e-7 and stable
        q = q0 + f * (q1 - q0)
        return q / math.sqrt(q.dot(q))  # np.linalg.norm of a 1-D vector, without its overhead
    theta = math.acos(min(1.0, dot))
    s = math.sin(theta)
    return (math.sin((1.0 - f) * theta) / s) * q0 + (math.sin(f * theta) / s) * q1


class PoseBuffer:
    """A bounded, time-ordered buffer of poses that interpolates at any query time.

    Parameters
    ----------
    max_gap_ns : int
        Largest spacing of two bracketing poses that may be interpolated across (default 50 ms:
        10 frames at 200 Hz).
    latency_ns : int
        Constant latency of the pose source; stored times are ``t - latency_ns``.
    max_extrapolation_ns : int
        How far past the newest (or before the oldest) pose a query may be answered by holding
        that pose (default 0: no extrapolation).
    capacity : int
        Number of poses kept (oldest dropped first).
    """

    def __init__(
        self,
        max_gap_ns: int = 50_000_000,
        latency_ns: int = 0,
        max_extrapolation_ns: int = 0,
        capacity: int = 4096,
    ):
        if max_gap_ns <= 0:
            raise InputDataError(f"max_gap_ns must be > 0, got {max_gap_ns!r}")
        if capacity < 2:
            raise InputDataError(f"capacity must be >= 2, got {capacity!r}")
        self.max_gap_ns = int(max_gap_ns)
        self.latency_ns = int(latency_ns)
        self.max_extrapolation_ns = int(max_extrapolation_ns)
        self.capacity = int(capacity)
        self._t: list[int] = []
        self._p: list[np.ndarray] = []
        self._q: list[np.ndarray] = []
        self.rejected = 0  # poses refused (non-finite, non-unit quaternion, out of order)

    def __len__(self) -> int:
        return len(self._t)

    def insert(self, t_ns: int, position, quaternion) -> bool:
        """Add a pose stamped ``t_ns`` (before latency compensation).

        Returns False (and counts it in ``rejected``) for a non-finite position, a quaternion
        whose norm is not within 1e-3 of 1, or a time not after the newest stored pose.
        """
        p = np.asarray(position, dtype=float).reshape(3)
        q = np.asarray(quaternion, dtype=float).reshape(4)
        t = int(t_ns) - self.latency_ns
        qq = float(q.dot(q))  # np.dot(q, q); NaN or inf when q is not finite
        if not (qq <= 3.0 and all(map(math.isfinite, p.tolist()))) or abs(qq - 1.0) > 2e-3:
            self.rejected += 1
            return False
        if self._t and t <= self._t[-1]:
            self.rejected += 1
            return False
        self._t.append(t)
        self._p.append(p)
        self._q.append(q / math.sqrt(qq))  # q / np.linalg.norm(q), the same bits
        if len(self._t) > self.capacity:
            drop = len(self._t) - self.capacity
            del self._t[:drop], self._p[:drop], self._q[:drop]
        return True

    def at(self, t_ns: int) -> Pose | NoPose:
        """The interpolated pose at station time ``t_ns``, or :class:`NoPose` with the reason."""
        t = int(t_ns)
        ts = self._t
        if not ts:
            return NoPose(t, "empty")
        i = bisect.bisect_left(ts, t)
        if i < len(ts) and ts[i] == t:
            return Pose(t, self._p[i].copy(), self._q[i].copy(), 0)
        if i == 0:
            if ts[0] - t <= self.max_extrapolation_ns:
                return Pose(t, self._p[0].copy(), self._q[0].copy(), ts[0] - t)
            return NoPose(t, "before", ts[0] - t)
        if i == len(ts):
            if t - ts[-1] <= self.max_extrapolation_ns:
                return Pose(t, self._p[-1].copy(), self._q[-1].copy(), t - ts[-1])
            return NoPose(t, "after", t - ts[-1])
        t0, t1 = ts[i - 1], ts[i]
        gap = t1 - t0
        if gap > self.max_gap_ns:
            return NoPose(t, "gap", gap)
        f = (t - t0) / gap
        p = self._p[i - 1] + f * (self._p[i] - self._p[i - 1])
        return Pose(t, p, slerp(self._q[i - 1], self._q[i], f), gap)

    def drop_before(self, t_ns: int) -> None:
        """Forget poses older than ``t_ns`` (station time, after latency compensation), keeping
        the last one before it so that ``t_ns`` itself can still be interpolated."""
        i = bisect.bisect_left(self._t, int(t_ns)) - 1
        if i > 0:
            del self._t[:i], self._p[:i], self._q[:i]
